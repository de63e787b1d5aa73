"""The fixed-layout records the loop process and its node exchange through their rings
(:mod:`~haptic_topology.device.loop_process`): one cycle as a record of ints and floats
(:class:`CycleCodec`), and records of bytes (:func:`put_bytes`, :func:`payloads`) for the LMI
updates (:mod:`~haptic_topology.control.update_record`), the control requests and the status.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.loop import Answer, HandSample
from haptic_topology.device.backend import DeviceReading
from haptic_topology.device.hosted import HostedStep
from haptic_topology.device.loop import DeviceTick
from haptic_topology.device.runner import Published
from haptic_topology.device.shm_ring import ShmRing
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import ControlMode, device_status

# Integer fields of a cycle record, then flags of its optional parts.
_INTS = ('stamp_ns', 'seq', 'run_index', 'status', 'reading_status', 'flags',
         'state_seq', 'update_seq', 'mode', 'constraint_count', 'hand_seq', 'hand_state_seq')
HAS_ENV, HAS_ANSWER, HAS_HAND, HAS_OUT_ENV = 1, 2, 4, 8
# m-vectors of a cycle record: the state, the answer, the hand input.
_VECS = ('pose', 'twist', 'hand_wrench', 'applied', 'env', 'wrench', 'coupling', 'vt_wrench',
         'vt_pose', 'vt_twist', 'out_env', 'h_pose', 'h_twist', 'h_wrench', 'h_coupling',
         'h_vt_wrench')


def bytes_dtype(size: int) -> np.dtype[Any]:
    return np.dtype([('n', '<i8'), ('b', 'u1', (size,))])


def update_bytes(dof: int) -> int:
    """Bytes of one LMI update record for a linkage of ``dof`` joints (the prepared update,
    :mod:`~haptic_topology.control.update_record`: mass matrix, Jacobians, contacts and the
    re-sync's matrices; an update that does not fit is refused, never cut)."""
    return (1 << 17) + 32 * dof * (dof + 64)


class CycleCodec:
    """One :class:`~haptic_topology.device.runner.Published` cycle as a fixed-layout record
    of task dimension ``m`` and back (ints: ``_INTS``; floats: the state's stamp, the
    hand input's stamp, then the m-vectors ``_VECS``)."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.dtype = np.dtype([('i', '<i8', (len(_INTS),)),
                               ('f', '<f8', (2 + len(_VECS) * m,))])
        self._zero = np.zeros(m)
        self._no_hand = (self._zero,) * 5            # the record's hand part, absent
        self._no_answer = (self._zero,) * 11         # its answer and hand parts, absent
        #: Entries of ``rec['i'].tolist() + rec['f'].tolist()`` (see :meth:`position`).
        self.width = len(_INTS) + 2 + len(_VECS) * m

    def position(self, name: str) -> int:
        """Where ``name`` is in the list ``rec['i'].tolist() + rec['f'].tolist()`` of a record
        ``rec``: an int (``stamp_ns``, ``seq``, ``status``, ``flags``, ``state_seq``, ...), a
        float (``stamp``, ``hand_stamp``: s) or the first of the m entries of a vector
        (``pose``, ``applied``, ``wrench``, ``h_pose``, ...; the hand input's vectors are
        ``h_pose``, ``h_twist``, ``h_wrench``, ``h_coupling``, ``h_vt_wrench``, in this order)."""
        if name in _INTS:
            return _INTS.index(name)
        floats = len(_INTS)
        if name in ('stamp', 'hand_stamp'):
            return floats + ('stamp', 'hand_stamp').index(name)
        if name not in _VECS:
            raise KeyError(f'cycle record: no field {name!r} (ints {_INTS}, vectors {_VECS})')
        return floats + 2 + _VECS.index(name) * self.m

    def encode(self, e: Published) -> tuple[list[int], np.ndarray]:
        """The record of ``e`` (what
        :meth:`~haptic_topology.device.shm_ring.ShmRing.put` writes): its ints and its floats."""
        step = e.step
        tick, ans = step.tick, step.answer
        r, env = tick.reading, tick.env_wrench
        flags = 0 if env is None else HAS_ENV
        if env is None:
            env = self._zero
        if ans is None:
            return ([e.stamp_ns, tick.seq, tick.run_index, int(tick.status), int(r.status), flags,
                     0, -1, 0, 0, 0, 0],
                    np.concatenate(((step.stamp, 0.0), r.pose, r.twist, r.hand_wrench,
                                    tick.applied, env, *self._no_answer)))
        o, h = ans.out, ans.hand
        out_env = o.env_wrench
        flags |= HAS_ANSWER if out_env is None else HAS_ANSWER | HAS_OUT_ENV
        if out_env is None:
            out_env = self._zero
        if h is None:
            hand_seq = hand_state_seq = 0
            hand_stamp = 0.0
            hand = self._no_hand
        else:
            flags |= HAS_HAND
            hand_seq, hand_state_seq, hand_stamp = h.seq, h.state_seq, h.stamp
            hand = (h.pose, h.twist, h.hand_wrench, h.coupling, h.vt_wrench)
        return ([e.stamp_ns, tick.seq, tick.run_index, int(tick.status), int(r.status), flags,
                 ans.state_seq, ans.update_seq, int(o.mode), o.constraint_count, hand_seq,
                 hand_state_seq],
                np.concatenate(((step.stamp, hand_stamp), r.pose, r.twist, r.hand_wrench,
                                tick.applied, env, o.wrench, o.coupling, o.vt_wrench, o.vt_pose,
                                o.vt_twist, out_env, *hand)))

    def decode(self, rec: np.void) -> Published:
        i = rec['i'].tolist()
        f = rec['f']
        # One copy of the record's vectors; each vector is a row view of it (the ring slot
        # is written again later, the copy is not).
        (pose, twist, hand_wrench, applied, env, wrench, coupling, vt_wrench, vt_pose,
         vt_twist, out_env, h_pose, h_twist, h_wrench, h_coupling, h_vt_wrench) = \
            f[2:].reshape(len(_VECS), self.m).copy()
        flags = i[5]
        # device_status: the members looked up (an IntFlag built from an int costs ~1 us)
        reading = DeviceReading(pose, twist, hand_wrench, device_status(i[4]))
        tick = DeviceTick(i[1], i[2], reading, applied, device_status(i[3]),
                          env if flags & HAS_ENV else None)
        ans = None
        if flags & HAS_ANSWER:
            out = CycleOutput(wrench, coupling, vt_wrench, vt_pose, vt_twist, i[9],
                              ControlMode(i[8]), out_env if flags & HAS_OUT_ENV else None)
            hand = (HandSample(i[10], i[11], float(f[1]), h_pose, h_twist, h_wrench,
                               h_coupling, h_vt_wrench)
                    if flags & HAS_HAND else None)
            ans = Answer(i[6], out, hand, i[7])
        return Published(HostedStep(tick, float(f[0]), ans, None, ()), i[0])

    def records(self, entries: list[Published]) -> np.ndarray:
        """The records of ``entries`` as one array of ``dtype``, as
        :meth:`~haptic_topology.device.shm_ring.ShmRing.take` returns them."""
        out = np.empty(len(entries), self.dtype)
        for n, e in enumerate(entries):
            out[n] = self.encode(e)
        return out


def put_bytes(ring: ShmRing, data: bytes, what: str, overwrite: bool = True) -> bool:
    """Put ``data`` into a ring of ``_bytes_dtype`` records; too long is an error."""
    size = ring.dtype['b'].shape[0]
    if len(data) > size:
        raise DeviceError(f'loop process: {what} of {len(data)} bytes exceeds its record '
                          f'({size} bytes)')
    def fill(slot: Any) -> None:     # the payload only: a record is sized for the largest
        slot['n'] = len(data)
        slot['b'][:len(data)] = np.frombuffer(data, np.uint8)
    return ring.put_with(fill, overwrite)


def payloads(ring: ShmRing, limit: int | None = None) -> list[bytes]:
    """The byte records waiting in ``ring``, oldest first (taken; at most ``limit``)."""
    if not ring.pending:
        return []
    # Only the payload is copied: a record is sized for the largest (an LMI update of a
    # 100-link chain: 650 kB), and a backlog copied whole took tens of milliseconds.
    return ring.take_each(lambda r: bytes(r['b'][:int(r['n'])]), limit)
