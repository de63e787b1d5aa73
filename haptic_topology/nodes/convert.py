"""Conversions between ``haptic_topology_msgs`` messages and the core's numpy objects.

Incoming messages are checked where they enter: a wrong ``task_dim`` or ``dof``, a wrong array
size, a non-finite value or a value out of its range (a mass matrix that is not symmetric
positive definite, constraint weights outside [0, 1], an unknown mode, ...) raises
:class:`MessageError` naming the field, with a ``reason`` (one of :data:`REASONS`) that the
nodes count per reason in their diagnostics (``rejected_<reason>``); the node drops the
message, so nothing of it reaches the device.

Integers are range-checked too (sequence numbers at most
:data:`~haptic_topology.messages.check.MAX_SEQ` ``= 2**53``, see
:mod:`haptic_topology.messages.check`,
where the checks live without rclpy so that the bag tools use the same ones).

Sequence numbers: device states count from 1, so ``LmiUpdate.hand_input_seq == 0`` means
"no hand input consumed yet" (the core's ``-1``).

Controller identity: :data:`CONTROLLER_ID` is drawn once per process when this module is
imported; :func:`command_msg` writes it into every ``DeviceCommand``, so a restarted
``lmi_controller`` has a new id, and the device driver follows the one it engaged with
(:mod:`haptic_topology.device.loop`).
"""

from __future__ import annotations

import math
from array import array as pyarray

import numpy as np
from builtin_interfaces.msg import Time

from haptic_topology.control.batch import HandBatch
from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.update_message import lmi_from_msg
from haptic_topology.device.backend import DeviceReading
from haptic_topology.errors import MessageError
from haptic_topology.messages.check import (
    MAX_CONTROLLER_ID,
    MAX_SEQ,
    MODES,
    REASONS,
    GraphFilter,
    RejectCounter,
    check_command,
    check_hand_inputs,
    check_state,
    new_controller_id,
)
from haptic_topology.vocabulary import TaskSpace
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate


def stamp_seconds(stamp: Time) -> float:
    """Seconds of a stamp, as :func:`haptic_topology.device.loop.ns_to_seconds` computes them
    (the offline simulation and the lock-step graph use the same numbers)."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """A stamp of ``ns`` nanoseconds (>= 0)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_stamp(t: float) -> Time:
    sec = int(t // 1.0)
    return Time(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


#: This process's controller id (module doc), in [1, MAX_CONTROLLER_ID].
CONTROLLER_ID: int = new_controller_id()

assert set(MODES) == {DeviceCommand.MODE_PENALTY, DeviceCommand.MODE_ACCELERATION_ONLY,
                      DeviceCommand.MODE_ZERO}


# -- DeviceState ------------------------------------------------------------------------------
def state_msg(msg: DeviceState, seq: int, stamp: Time, reading: DeviceReading,
              applied: np.ndarray, status: int,
              env_wrench: np.ndarray | None = None) -> DeviceState:
    """``msg`` filled with state ``seq``; ``env_wrench``: F_env of the command applied (None:
    empty)."""
    msg.header.stamp = stamp
    msg.seq = seq
    msg.task_dim = int(reading.pose.size)
    msg.pose = reading.pose.tolist()
    msg.twist = reading.twist.tolist()
    msg.hand_wrench = reading.hand_wrench.tolist()
    msg.applied_wrench = np.asarray(applied, dtype=float).tolist()
    msg.status = int(status)
    msg.env_wrench = [] if env_wrench is None else env_wrench.tolist()
    return msg


def state_from_msg(msg: DeviceState, task: TaskSpace
                   ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray, int]:
    """``(seq, stamp_s, pose, twist, hand_wrench, status)``; every field checked
    (:func:`haptic_topology.messages.check.check_state`: seq in [1, MAX_SEQ], known status
    bits)."""
    seq, stamp, pose, twist, f_h, _, status = check_state(msg, task.dim)
    return seq, stamp, pose, twist, f_h, status


# -- DeviceCommand ----------------------------------------------------------------------------
def command_msg(msg: DeviceCommand, state_seq: int, stamp: Time, out: CycleOutput,
                update_age: float, controller_id: int = CONTROLLER_ID,
                update_seq: int = -1) -> DeviceCommand:
    """``msg`` filled with the answer ``out`` to state ``state_seq``, from the controller
    ``controller_id`` (default this process's, :data:`CONTROLLER_ID`); ``update_age`` (s);
    ``update_seq``: the newest LMI update taken before it (-1: none)."""
    msg.header.stamp = stamp
    msg.state_seq = state_seq
    msg.controller_id = controller_id
    msg.mode = int(out.mode)
    msg.task_dim = int(out.wrench.size)
    msg.wrench = out.wrench.tolist()
    msg.vt_pose = out.vt_pose.tolist()
    msg.vt_twist = out.vt_twist.tolist()
    msg.constraint_count = int(out.constraint_count)
    msg.update_age = float(update_age)
    msg.update_seq = int(update_seq)
    msg.env_wrench = [] if out.env_wrench is None else out.env_wrench.tolist()
    return msg


def command_from_msg(msg: DeviceCommand, task: TaskSpace
                     ) -> tuple[int, int, np.ndarray, int]:
    """``(state_seq, mode, wrench, controller_id)``; the wrench must be finite and task_dim
    long, the mode one of the message's MODE_* constants, state_seq in [1, MAX_SEQ],
    controller_id in [1, MAX_CONTROLLER_ID]; the other fields are checked too
    (:func:`haptic_topology.messages.check.check_command`).

    A finite wrench beyond the device's limit is not an error: the device clamps it (status
    SATURATED), as it does for the controller's own large outputs.
    """
    return check_command(msg, task.dim)


# -- HandInputs -------------------------------------------------------------------------------
def stamp_ns(stamp: Time) -> int:
    """Integer nanoseconds of a stamp (exact; :func:`ns_to_stamp` turns them back)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def hand_inputs_msg(msg: HandInputs, batch: HandBatch) -> HandInputs:
    """``msg`` filled with ``batch`` (header stamp: the newest sample's state stamp)."""
    stamps = [ns_to_stamp(ns) for ns in batch.stamp_ns.tolist()]
    msg.header.stamp = stamps[-1]
    msg.task_dim = int(batch.pose.shape[1])
    msg.seq = batch.seq.tolist()
    msg.state_seq = batch.state_seq.tolist()
    msg.stamp = stamps
    msg.pose = _doubles(batch.pose)
    msg.twist = _doubles(batch.twist)
    msg.hand_wrench = _doubles(batch.hand_wrench)
    msg.coupling_wrench = _doubles(batch.coupling)
    return msg


def vt_wrenches_from_hand_inputs(msg: HandInputs, task: TaskSpace, vt_coupling: bool,
                                 max_wrench: float = math.inf
                                 ) -> tuple[list[int], list[int], list[float], np.ndarray,
                                            np.ndarray, np.ndarray]:
    """``(seqs, state_seqs, stamps_s, pose, twist, F_vt)`` of a batch, per sample (rows):
    ``F_vt = F_h - F_pc`` with VT coupling, else ``F_h``.

    The whole batch is checked first (:func:`haptic_topology.messages.check.check_hand_inputs`:
    sizes n and n x task_dim, integer ranges, ascending seqs, finite values, every wrench
    entry of a wrench applied to the VT within ``max_wrench`` (N, N m; ``coupling_wrench``
    only with VT coupling): a hand input far beyond any device's force would only blow the VT
    up); one bad field rejects it all.
    """
    seqs, state_seqs, stamps, pose, twist, f_h, f_pc = check_hand_inputs(
        msg, task.dim, max_wrench, vt_coupling)
    f_vt = f_h - f_pc if vt_coupling else f_h
    return seqs, state_seqs, stamps, pose, twist, f_vt


# -- LmiUpdate --------------------------------------------------------------------------------
def _doubles(a: np.ndarray) -> pyarray:
    """``a``'s entries (row-major) for a ``float64[]`` field, handed over as one block: the
    generated setter checks a list entry by entry (0.4-0.8 ms for a 100-link chain's mass
    matrix), an ``array.array('d')`` not at all."""
    return pyarray('d', np.ascontiguousarray(a, dtype=float).tobytes())


def lmi_msg(msg: LmiUpdate, snap: LmiSnapshot, stamp: Time) -> LmiUpdate:
    """``msg`` filled with the snapshot ``snap``, stamped ``stamp``; matrices row-major."""
    msg.header.stamp = stamp
    msg.seq = int(snap.seq)
    msg.hand_input_seq = max(int(snap.hand_input_seq), 0)
    msg.dof = int(snap.q.size)
    msg.task_dim = snap.task.dim
    msg.q = _doubles(snap.q)
    msg.dq = _doubles(snap.dq)
    msg.mass_matrix = _doubles(snap.mass_matrix)
    msg.gravity = _doubles(snap.gravity)
    msg.hand_jacobian = _doubles(snap.hand_jacobian)
    msg.singular_values = _doubles(snap.singular_values)
    msg.left_singular_vectors = _doubles(snap.left_vectors)
    msg.constraint_count = int(snap.constraint_count)
    msg.constraint_weights = _doubles(snap.weights)
    msg.characteristic_length = float(snap.characteristic_length)
    msg.hand_pose = _doubles(snap.hand_pose)
    msg.hand_twist = _doubles(snap.hand_twist)
    c = snap.contacts
    if c is None:
        msg.contact_count = 0
        msg.contact_points = msg.contact_normals = msg.contact_gaps = []
        msg.contact_jacobians = []
        msg.contact_stiffness = msg.contact_damping = msg.contact_friction = 0.0
        msg.contact_slip_velocity = 0.0
        msg.contact_local = False
        msg.contact_energy = 0.0
        return msg
    msg.contact_count = len(c)
    msg.contact_points = _doubles(c.points)
    msg.contact_normals = _doubles(c.normals)
    msg.contact_gaps = _doubles(c.gaps)
    msg.contact_jacobians = _doubles(c.jacobians)
    msg.contact_stiffness = float(c.params.stiffness)
    msg.contact_damping = float(c.params.damping)
    msg.contact_friction = float(c.params.friction)
    msg.contact_slip_velocity = float(c.params.slip_velocity)
    msg.contact_local = bool(c.local)
    msg.contact_energy = float(snap.contact_energy)
    return msg


__all__ = ['CONTROLLER_ID', 'MAX_CONTROLLER_ID', 'MAX_SEQ', 'REASONS', 'GraphFilter',
           'MessageError', 'RejectCounter', 'command_from_msg', 'command_msg', 'hand_inputs_msg',
           'lmi_from_msg', 'lmi_msg', 'ns_to_stamp', 'seconds_to_stamp', 'stamp_ns',
           'stamp_seconds', 'state_from_msg', 'state_msg', 'vt_wrenches_from_hand_inputs']
