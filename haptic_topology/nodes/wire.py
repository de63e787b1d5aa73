"""``DeviceState`` and ``DeviceCommand`` as serialized bytes, for ``Publisher.publish(bytes)``
at 1 kHz: the same messages :func:`~haptic_topology.nodes.convert.state_msg` and
:func:`~haptic_topology.nodes.convert.command_msg` fill, packed in one step by a
:class:`~haptic_topology.messages.cdr.CdrWriter` (about half the cost of filling and
publishing the message object)."""

from __future__ import annotations

import numpy as np

from haptic_topology.control.controller import CycleOutput
from haptic_topology.device.backend import DeviceReading
from haptic_topology.messages.cdr import CdrWriter
from haptic_topology.nodes.convert import CONTROLLER_ID
from haptic_topology_msgs.msg import DeviceCommand, DeviceState

#: The fields :func:`state_cdr` writes, in its order; the rest are the writer's constants.
STATE_FIELDS = ('header.stamp.sec', 'header.stamp.nanosec', 'seq', 'task_dim', 'pose', 'twist',
                'hand_wrench', 'applied_wrench', 'status', 'env_wrench')


def state_writer(frame_id: str, graph_id: int) -> CdrWriter:
    """The writer of :func:`state_cdr` in ``frame_id`` for the graph ``graph_id`` (its wire
    value)."""
    return CdrWriter(DeviceState, STATE_FIELDS,
                     {'header.frame_id': frame_id, 'graph_id': graph_id})


def state_cdr(writer: CdrWriter, seq: int, ns: int, reading: DeviceReading,
              applied: np.ndarray, status: int, env_wrench: np.ndarray | None = None) -> bytes:
    """The serialized ``DeviceState`` that :func:`state_msg` fills (stamped ``ns``), for
    ``Publisher.publish(bytes)``: at 1 kHz this costs about half of filling and publishing
    the message object (:mod:`haptic_topology.messages.cdr`)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return writer.pack(sec, nanosec, seq, reading.pose.size, reading.pose, reading.twist,
                       reading.hand_wrench, applied, int(status),
                       () if env_wrench is None else env_wrench)


#: The fields :func:`command_cdr` writes, in its order; the rest are the writer's constants.
COMMAND_FIELDS = ('header.stamp.sec', 'header.stamp.nanosec', 'state_seq', 'controller_id',
                  'mode', 'task_dim', 'wrench', 'vt_pose', 'vt_twist', 'constraint_count',
                  'update_age', 'env_wrench', 'update_seq')


def command_writer(frame_id: str, graph_id: int) -> CdrWriter:
    """The writer of :func:`command_cdr` in ``frame_id`` for the graph ``graph_id`` (its wire
    value)."""
    return CdrWriter(DeviceCommand, COMMAND_FIELDS,
                     {'header.frame_id': frame_id, 'graph_id': graph_id})


def command_cdr(writer: CdrWriter, state_seq: int, ns: int, out: CycleOutput,
                update_age: float, controller_id: int = CONTROLLER_ID,
                update_seq: int = -1) -> bytes:
    """The serialized ``DeviceCommand`` that :func:`command_msg` fills (stamped ``ns``), for
    ``Publisher.publish(bytes)`` (see :func:`state_cdr`)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return writer.pack(sec, nanosec, state_seq, controller_id, int(out.mode), out.wrench.size,
                       out.wrench, out.vt_pose, out.vt_twist, int(out.constraint_count),
                       float(update_age), () if out.env_wrench is None else out.env_wrench,
                       int(update_seq))


__all__ = ['COMMAND_FIELDS', 'STATE_FIELDS', 'command_cdr', 'command_writer', 'state_cdr',
           'state_writer']
