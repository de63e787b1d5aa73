"""Conversions between ``haptic_topology_msgs`` messages and the core's numpy objects.

Incoming messages are checked where they enter: a wrong array size or a non-finite value
raises :class:`MessageError` naming the field, and the node drops the message.

Sequence numbers: device states count from 1, so ``LmiUpdate.hand_input_seq == 0`` means
"no hand input consumed yet" (the core's ``-1``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from builtin_interfaces.msg import Time

from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.device.backend import DeviceReading
from haptic_topology.errors import HapticTopologyError
from haptic_topology.model.linkage import TaskSpace
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInput, LmiUpdate


class MessageError(HapticTopologyError):
    """An incoming message does not fit the graph (sizes, task_dim, non-finite values)."""


def stamp_seconds(stamp: Time) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def seconds_to_stamp(t: float) -> Time:
    sec = int(t // 1.0)
    return Time(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def _array(msg: Any, field: str, size: int, finite: bool = True) -> np.ndarray:
    a = np.asarray(getattr(msg, field), dtype=float)
    if a.shape != (size,):
        raise MessageError(f'{type(msg).__name__}.{field} must have {size} entries, got '
                           f'{a.size}')
    if finite and not np.all(np.isfinite(a)):
        raise MessageError(f'{type(msg).__name__}.{field} has non-finite entries: {a.tolist()}')
    return a


def _task_dim(msg: Any, task: TaskSpace) -> None:
    if int(msg.task_dim) != task.dim:
        raise MessageError(f'{type(msg).__name__}.task_dim must be {task.dim}, got '
                           f'{msg.task_dim}')


# -- DeviceState ------------------------------------------------------------------------------
def state_msg(msg: DeviceState, seq: int, stamp: Time, reading: DeviceReading,
              applied: np.ndarray, status: int) -> DeviceState:
    msg.header.stamp = stamp
    msg.seq = seq
    msg.task_dim = int(reading.pose.size)
    msg.pose = reading.pose.tolist()
    msg.twist = reading.twist.tolist()
    msg.hand_wrench = reading.hand_wrench.tolist()
    msg.applied_wrench = np.asarray(applied, dtype=float).tolist()
    msg.status = int(status)
    return msg


def state_from_msg(msg: DeviceState, task: TaskSpace
                   ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray]:
    """``(seq, stamp_s, pose, twist, hand_wrench)``."""
    _task_dim(msg, task)
    m = task.dim
    return (int(msg.seq), stamp_seconds(msg.header.stamp), _array(msg, 'pose', m),
            _array(msg, 'twist', m), _array(msg, 'hand_wrench', m))


# -- DeviceCommand ----------------------------------------------------------------------------
def command_msg(msg: DeviceCommand, state_seq: int, stamp: Time, out: CycleOutput,
                update_age: float) -> DeviceCommand:
    msg.header.stamp = stamp
    msg.state_seq = state_seq
    msg.mode = int(out.mode)
    msg.task_dim = int(out.wrench.size)
    msg.wrench = out.wrench.tolist()
    msg.vt_pose = out.vt_pose.tolist()
    msg.vt_twist = out.vt_twist.tolist()
    msg.constraint_count = int(out.constraint_count)
    msg.update_age = float(update_age)
    return msg


def command_from_msg(msg: DeviceCommand, task: TaskSpace) -> tuple[int, int, np.ndarray]:
    """``(state_seq, mode, wrench)``; the wrench must be finite and task_dim long."""
    _task_dim(msg, task)
    return int(msg.state_seq), int(msg.mode), _array(msg, 'wrench', task.dim)


# -- HandInput --------------------------------------------------------------------------------
def hand_msg(msg: HandInput, seq: int, state_seq: int, stamp: Time, pose: np.ndarray,
             twist: np.ndarray, hand_wrench: np.ndarray, coupling: np.ndarray) -> HandInput:
    msg.header.stamp = stamp
    msg.seq = seq
    msg.state_seq = state_seq
    msg.task_dim = int(pose.size)
    msg.pose = pose.tolist()
    msg.twist = twist.tolist()
    msg.hand_wrench = hand_wrench.tolist()
    msg.coupling_wrench = coupling.tolist()
    return msg


def vt_wrench_from_hand(msg: HandInput, task: TaskSpace, vt_coupling: bool
                        ) -> tuple[int, float, np.ndarray]:
    """``(state_seq, stamp_s, F_vt)``: ``F_h - F_pc`` with VT coupling, else ``F_h``."""
    _task_dim(msg, task)
    f_h = _array(msg, 'hand_wrench', task.dim)
    f_vt = f_h - _array(msg, 'coupling_wrench', task.dim) if vt_coupling else f_h
    return int(msg.state_seq), stamp_seconds(msg.header.stamp), f_vt


# -- LmiUpdate --------------------------------------------------------------------------------
def lmi_msg(msg: LmiUpdate, snap: LmiSnapshot, stamp: Time) -> LmiUpdate:
    msg.header.stamp = stamp
    msg.seq = int(snap.seq)
    msg.hand_input_seq = max(int(snap.hand_input_seq), 0)
    msg.dof = int(snap.q.size)
    msg.task_dim = snap.task.dim
    msg.q = snap.q.tolist()
    msg.dq = snap.dq.tolist()
    msg.mass_matrix = snap.mass_matrix.ravel().tolist()
    msg.gravity = snap.gravity.tolist()
    msg.hand_jacobian = snap.hand_jacobian.ravel().tolist()
    msg.singular_values = snap.singular_values.tolist()
    msg.left_singular_vectors = snap.left_vectors.ravel().tolist()
    msg.constraint_count = int(snap.constraint_count)
    msg.constraint_weights = snap.weights.tolist()
    msg.characteristic_length = float(snap.characteristic_length)
    msg.hand_pose = snap.hand_pose.tolist()
    msg.hand_twist = snap.hand_twist.tolist()
    return msg


def lmi_from_msg(msg: LmiUpdate, task: TaskSpace, dof: int) -> LmiSnapshot:
    """The snapshot carried by ``msg``; sizes checked against the linkage's ``dof``."""
    _task_dim(msg, task)
    if int(msg.dof) != dof:
        raise MessageError(f'LmiUpdate.dof must be {dof}, got {msg.dof}')
    m = task.dim
    return LmiSnapshot(
        seq=int(msg.seq),
        hand_input_seq=int(msg.hand_input_seq) if msg.hand_input_seq > 0 else -1,
        task=task,
        q=_array(msg, 'q', dof), dq=_array(msg, 'dq', dof),
        mass_matrix=_array(msg, 'mass_matrix', dof * dof).reshape(dof, dof),
        gravity=_array(msg, 'gravity', dof),
        hand_jacobian=_array(msg, 'hand_jacobian', m * dof).reshape(m, dof),
        singular_values=_array(msg, 'singular_values', min(m, dof)),
        left_vectors=_array(msg, 'left_singular_vectors', m * m).reshape(m, m),
        weights=_array(msg, 'constraint_weights', m),
        constraint_count=int(msg.constraint_count),
        characteristic_length=float(msg.characteristic_length),
        hand_pose=_array(msg, 'hand_pose', m), hand_twist=_array(msg, 'hand_twist', m))
