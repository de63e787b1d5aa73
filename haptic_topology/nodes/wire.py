"""The graph's own messages as serialized bytes, for ``Publisher.publish(bytes)``: the same
messages :func:`~haptic_topology.nodes.convert.state_msg`,
:func:`~haptic_topology.nodes.convert.command_msg`,
:func:`~haptic_topology.nodes.convert.lmi_msg` and
:func:`~haptic_topology.nodes.convert.hand_inputs_msg` fill (``DeviceState`` and
``DeviceCommand`` at 1 kHz, ``LmiUpdate``, ``VtPath`` and ``HandInputs`` at 100 Hz), packed in
one step by a :class:`~haptic_topology.messages.cdr.CdrWriter`: rclpy publishes the bytes as
they are, without converting a message object (for a ``DeviceState`` about half the cost of
filling and publishing one)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from haptic_topology.control.batch import HandBatch
from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.device.backend import DeviceReading
from haptic_topology.device.loop import DeviceTick
from haptic_topology.device.records import HAS_ANSWER, HAS_ENV, HAS_HAND, HAS_OUT_ENV, CycleCodec
from haptic_topology.messages.cdr import CdrWriter
from haptic_topology.nodes.convert import CONTROLLER_ID
from haptic_topology.vocabulary import TOPIC_STATE, TOPIC_STATE_SAMPLED, DeviceStatus
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate, VtPath

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


#: The fields :func:`lmi_cdr` writes, in its order; the rest are the writer's constants.
LMI_FIELDS = ('header.stamp.sec', 'header.stamp.nanosec', 'seq', 'hand_input_seq', 'dof',
              'task_dim', 'q', 'dq', 'mass_matrix', 'gravity', 'hand_jacobian',
              'singular_values', 'left_singular_vectors', 'constraint_count',
              'constraint_weights', 'characteristic_length', 'hand_pose', 'hand_twist',
              'contact_count', 'contact_points', 'contact_normals', 'contact_gaps',
              'contact_jacobians', 'contact_stiffness', 'contact_damping', 'contact_friction',
              'contact_slip_velocity', 'contact_local', 'contact_energy')


def lmi_writer(frame_id: str, graph_id: int) -> CdrWriter:
    """The writer of :func:`lmi_cdr` in ``frame_id`` for the graph ``graph_id`` (its wire
    value)."""
    return CdrWriter(LmiUpdate, LMI_FIELDS, {'header.frame_id': frame_id, 'graph_id': graph_id})


def lmi_cdr(writer: CdrWriter, snap: LmiSnapshot, ns: int) -> bytes:
    """The serialized ``LmiUpdate`` that :func:`~haptic_topology.nodes.convert.lmi_msg` fills
    with ``snap`` (stamped ``ns``; matrices row-major), for ``Publisher.publish(bytes)``."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    c = snap.contacts
    if c is None:
        contacts: tuple[Any, ...] = (0, (), (), (), (), 0.0, 0.0, 0.0, 0.0, False, 0.0)
    else:
        p = c.params
        contacts = (len(c), c.points, c.normals, c.gaps, c.jacobians, float(p.stiffness),
                    float(p.damping), float(p.friction), float(p.slip_velocity), bool(c.local),
                    float(snap.contact_energy))
    return writer.pack(sec, nanosec, int(snap.seq), max(int(snap.hand_input_seq), 0),
                       snap.q.size, snap.task.dim, snap.q, snap.dq, snap.mass_matrix,
                       snap.gravity, snap.hand_jacobian, snap.singular_values, snap.left_vectors,
                       int(snap.constraint_count), snap.weights,
                       float(snap.characteristic_length), snap.hand_pose, snap.hand_twist,
                       *contacts)


#: The fields :func:`path_cdr` writes, in its order; the rest are the writer's constants.
PATH_FIELDS = ('header.stamp.sec', 'header.stamp.nanosec', 'update_seq', 'task_dim',
               'hand_input_seqs', 'hand_pose')


def path_writer(frame_id: str, graph_id: int) -> CdrWriter:
    """The writer of :func:`path_cdr` in ``frame_id`` for the graph ``graph_id``."""
    return CdrWriter(VtPath, PATH_FIELDS, {'header.frame_id': frame_id, 'graph_id': graph_id})


def path_cdr(writer: CdrWriter, update_seq: int, task_dim: int,
             path: list[tuple[int, np.ndarray]], ns: int) -> bytes:
    """The serialized ``VtPath`` of the VT hand poses ``path`` (``(hand input seq, pose)``
    each, oldest first) after update ``update_seq``, stamped ``ns``."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return writer.pack(sec, nanosec, update_seq, task_dim, [int(s) for s, _ in path],
                       np.concatenate([x for _, x in path]))


#: The fields :func:`hand_inputs_cdr` writes, in its order; the rest are the writer's constants.
HAND_FIELDS = ('header.stamp.sec', 'header.stamp.nanosec', 'task_dim', 'seq', 'state_seq',
               'stamp', 'pose', 'twist', 'hand_wrench', 'coupling_wrench')


def hand_inputs_writer(frame_id: str, graph_id: int) -> CdrWriter:
    """The writer of :func:`hand_inputs_cdr` in ``frame_id`` for the graph ``graph_id``."""
    return CdrWriter(HandInputs, HAND_FIELDS, {'header.frame_id': frame_id,
                                               'graph_id': graph_id})


def hand_inputs_cdr(writer: CdrWriter, batch: HandBatch) -> bytes:
    """The serialized ``HandInputs`` that
    :func:`~haptic_topology.nodes.convert.hand_inputs_msg` fills with ``batch`` (header
    stamp: the newest sample's state stamp)."""
    sec, nanosec = np.divmod(batch.stamp_ns, 1_000_000_000)
    return writer.pack(int(sec[-1]), int(nanosec[-1]), batch.pose.shape[1], batch.seq,
                       batch.state_seq, np.stack((sec, nanosec), axis=1), batch.pose,
                       batch.twist, batch.hand_wrench, batch.coupling)


class CycleWire:
    """The ``DeviceState`` and ``DeviceCommand`` of cycle records (the layout of ``codec``,
    :class:`~haptic_topology.device.records.CycleCodec`) as the bytes :func:`state_cdr` and
    :func:`command_cdr` give for the decoded cycle, packed from the record's values without
    decoding it (:meth:`~haptic_topology.messages.cdr.CdrWriter.gather`): the publishing
    thread's work per cycle at 1 kHz.

    ``src`` of :meth:`state` and :meth:`command` is ``rec['i'].tolist() +
    rec['f'].tolist()`` of a record ``rec`` followed by :meth:`extras`."""

    def __init__(self, codec: CycleCodec, state: CdrWriter, command: CdrWriter,
                 controller_id: int = CONTROLLER_ID) -> None:
        m, at = codec.m, codec.position
        self._flags, self._status, self._hand_seq = at('flags'), at('status'), at('hand_seq')
        # The hand input's pose, twist, F_h and F_pc: 4 x m in the record's floats.
        self._block = slice(at('h_pose') - at('stamp'), at('h_vt_wrench') - at('stamp'))
        self._cid = controller_id
        # extras: the stamp's sec and nanosec, the task dimension, update_age, controller_id
        sec = codec.width
        self._age = sec + 3
        width = sec + 5
        stamp = {'header.stamp.sec': sec, 'header.stamp.nanosec': sec + 1}
        where = {**stamp, 'seq': at('seq'), 'task_dim': sec + 2, 'pose': at('pose'),
                 'twist': at('twist'), 'hand_wrench': at('hand_wrench'),
                 'applied_wrench': at('applied'), 'status': at('status'),
                 'env_wrench': at('env')}
        self._state = [state.gather(width, where, {**{p: m for p in STATE_FIELDS[4:8]},
                                                   'env_wrench': n}) for n in (0, m)]
        where = {**stamp, 'state_seq': at('state_seq'), 'controller_id': sec + 4,
                 'mode': at('mode'), 'task_dim': sec + 2, 'wrench': at('wrench'),
                 'vt_pose': at('vt_pose'), 'vt_twist': at('vt_twist'),
                 'constraint_count': at('constraint_count'), 'update_age': sec + 3,
                 'env_wrench': at('out_env'), 'update_seq': at('update_seq')}
        self._command = [command.gather(width, where, {'wrench': m, 'vt_pose': m,
                                                       'vt_twist': m, 'env_wrench': n})
                         for n in (0, m)]
        self._m = m

    def extras(self, stamp_ns: int) -> list[Any]:
        """What follows a record's values in ``src``: its state's stamp (``stamp_ns``) as sec
        and nanosec, the task dimension, a slot for ``update_age`` (written by
        :meth:`command`) and the controller id."""
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return [sec, nanosec, self._m, 0.0, self._cid]

    def state(self, src: list[Any]) -> bytes:
        """The record's ``DeviceState``, as :func:`state_cdr` packs it."""
        return self._state[src[self._flags] & HAS_ENV](src)

    def answered(self, src: list[Any]) -> bool:
        """The record holds an answer (a command)."""
        return bool(src[self._flags] & HAS_ANSWER)

    def idle(self, src: list[Any]) -> bool:
        """The record's state is flagged IDLE (the device not engaged)."""
        return bool(int(src[self._status]) & _IDLE)

    def hand(self, src: list[Any], floats: np.ndarray
             ) -> tuple[int, int, np.ndarray] | None:
        """The answer's hand input (None: none): its ``seq``, ``state_seq`` and the 4 x m
        rows pose, twist, F_h, F_pc, a view of ``floats`` (the record's ``'f'``), as
        :meth:`~haptic_topology.control.port.ControllerPort.answered_block` takes it."""
        if not src[self._flags] & HAS_HAND:
            return None
        at = self._hand_seq
        return int(src[at]), int(src[at + 1]), floats[self._block].reshape(4, self._m)

    def command(self, src: list[Any], update_age: float) -> bytes:
        """The record's ``DeviceCommand`` (the record holds an answer) computed ``update_age``
        s after the newest LMI update, as :func:`command_cdr` packs it."""
        src[self._age] = update_age
        return self._command[(src[self._flags] & HAS_OUT_ENV) // HAS_OUT_ENV](src)


_IDLE = int(DeviceStatus.IDLE)


class StateSampler:
    """Which states ``device_driver`` also publishes on ``haptic/device/state_sampled``: at
    most ``rate_hz`` of them a second, by the times (ns) the caller gives (``device_driver``:
    its monotonic clock when it publishes, so that a viewer gets them at that rate in its own
    time, also while a lock-step run is slower or faster than real time).

    A state is taken when its time lies at or after the end of the period the last one taken
    began (periods of ``1/rate_hz`` s laid end to end from the first state taken, so that
    1 kHz states sampled at 30 Hz come 30 a second, not one every 34 ms) or before that
    period's start (the clock went back); after a gap longer than a period the grid starts
    again at the state after it. ``rate_hz`` 0: none is taken.

    Example (30 Hz: periods of 33,333,333 ns)::

        >>> s = StateSampler(30.0)
        >>> [ns for ns in range(0, 100_000_000, 1_000_000) if s.due(ns)]
        [0, 34000000, 67000000]
    """

    def __init__(self, rate_hz: float) -> None:
        if not (rate_hz >= 0.0 and np.isfinite(rate_hz)):
            raise ValueError(f'rate_hz must be a finite number >= 0, got {rate_hz}')
        self.period_ns = round(1e9 / rate_hz) if rate_hz > 0.0 else 0
        self._start: int | None = None      # the period of the last state taken
        self.taken = 0

    def due(self, ns: int) -> bool:
        """Whether the state at time ``ns`` is taken (see class doc)."""
        period, start = self.period_ns, self._start
        if not period or (start is not None and start <= ns < start + period):
            return False
        if start is not None and start + period <= ns < start + 2 * period:
            self._start = start + period        # the next period of the grid
        else:
            self._start = ns                    # the first state, a gap, or a restart
        self.taken += 1
        return True


class StateOut:
    """``device_driver``'s state publishers, made with ``create_publisher`` (the node's): every
    state on ``haptic/device/state`` (QoS ``qos``), and those its :class:`StateSampler` takes
    (``rate_hz``, by the monotonic clock when published) on ``haptic/device/state_sampled`` as
    well (``sampled_qos``), the same bytes; a state given as a tick is packed by
    :attr:`writer` (``frame_id``, the graph's wire id ``graph_id``)."""

    def __init__(self, create_publisher: Any, qos: Any, sampled_qos: Any, frame_id: str,
                 graph_id: int, rate_hz: float) -> None:
        self.writer = state_writer(frame_id, graph_id)
        self.pub = create_publisher(DeviceState, TOPIC_STATE, qos)
        self.sampled_pub = create_publisher(DeviceState, TOPIC_STATE_SAMPLED, sampled_qos)
        self.sampler = StateSampler(rate_hz)
        self.sent = 0

    def publish(self, tick: DeviceTick | bytes, ns: int) -> None:
        """Publish the state ``tick`` (or its bytes packed by :attr:`writer`) stamped ``ns``."""
        data = tick if isinstance(tick, bytes) else state_cdr(
            self.writer, tick.seq, ns, tick.reading, tick.applied, int(tick.status),
            tick.env_wrench)
        self.pub.publish(data)
        if self.sampler.due(time.monotonic_ns()):
            self.sampled_pub.publish(data)
        self.sent += 1

    def values(self) -> dict[str, str]:
        """States sent on either topic, as diagnostics key/values."""
        return {f'sent {TOPIC_STATE}': str(self.sent),
                f'sent {TOPIC_STATE_SAMPLED}': str(self.sampler.taken)}


__all__ = ['COMMAND_FIELDS', 'LMI_FIELDS', 'PATH_FIELDS', 'STATE_FIELDS', 'CycleWire',
           'StateOut', 'StateSampler',
           'command_cdr', 'command_writer', 'lmi_cdr', 'lmi_writer', 'path_cdr',
           'path_writer', 'state_cdr', 'state_writer']
