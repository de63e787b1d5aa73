"""The shared memory of the loop process and its node, laid out once for both sides.

:class:`LoopRings` holds the four rings (:class:`~haptic_topology.device.shm_ring.ShmRing`)
and the three statistics arrays (:class:`~haptic_topology.device.shm_ring.SharedArray`) that
:mod:`~haptic_topology.device.loop_process` describes. The node :meth:`~LoopRings.create` s
them (when the driver is configured: a ``/dev/shm`` without room fails there, with the
segment named) and the child :meth:`~LoopRings.attach` es them by name; both take the
record types and capacities from :data:`RINGS` and :data:`ARRAYS`, never from literals of
their own.

===========  ==========  ==========================================  =======================
ring         written by  record                                      when full
===========  ==========  ==========================================  =======================
``cycles``   child       one cycle (:class:`~.records.CycleCodec`)   wall clock: the oldest
                                                                     is overwritten and
                                                                     counted; lock-step: the
                                                                     loop waits
``updates``  node        one LMI update (``update_record``)          the node keeps it and
                                                                     offers it again
``control``  node        one request (engage, law, stop)             the node says so; a
                                                                     stop escalates to
                                                                     SIGTERM
``status``   child       the child's figures and notices (JSON)      the oldest is
                                                                     overwritten
===========  ==========  ==========================================  =======================

Each side counts what its rings lost (:meth:`LoopRings.counts`): the producer the records it
overwrote or was refused room for, the consumer the records lost before it could take them
and the copies it discarded as torn. The child reports its counts in its status; the node adds
its own, and ``/diagnostics`` shows both as ``ring_<ring>_<count>``.
"""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from haptic_topology.device.loop import RTT_KEEP
from haptic_topology.device.pacing import PERIOD_WINDOW
from haptic_topology.device.records import CycleCodec, bytes_dtype, update_bytes
from haptic_topology.device.shm_ring import SharedArray, ShmRing

#: Cycle records the ring keeps (4 s at 1 kHz), as the in-process outbox.
CYCLE_RECORDS = 4096
#: LMI update records the ring keeps (0.3 s at 100 Hz).
UPDATE_RECORDS = 32
#: Control requests the ring keeps, and the bytes of one (pickle).
CONTROL_RECORDS = 64
CONTROL_BYTES = 1 << 12
#: Status records the ring keeps, and the bytes of one (JSON).
STATUS_RECORDS = 4
STATUS_BYTES = 1 << 16

#: Each ring: its record type for a task of dimension ``m`` and a linkage of ``dof`` joints,
#: and its capacity (records).
RINGS: dict[str, tuple[Callable[[int, int], np.dtype[Any]], int]] = {
    'cycles': (lambda m, dof: CycleCodec(m).dtype, CYCLE_RECORDS),
    'updates': (lambda m, dof: bytes_dtype(update_bytes(dof)), UPDATE_RECORDS),
    'control': (lambda m, dof: bytes_dtype(CONTROL_BYTES), CONTROL_RECORDS),
    'status': (lambda m, dof: bytes_dtype(STATUS_BYTES), STATUS_RECORDS),
}
#: Each statistics array (float64, written by the child, sorted by the node): its size.
ARRAYS = {'periods': PERIOD_WINDOW, 'round_trips': RTT_KEEP, 'lateness': PERIOD_WINDOW}
#: What each side counts of a ring's losses.
COUNTS = ('overwritten', 'refused', 'lost', 'torn')


def wait_eventfd(fd: int, timeout: float) -> bool:
    """Block until the eventfd ``fd`` (non-blocking) is signalled or ``timeout`` s have
    passed; reset it. Returns whether it was signalled."""
    ready, _, _ = select.select([fd], [], [], max(timeout, 0.0))
    if not ready:
        return False
    try:
        os.eventfd_read(fd)
    except BlockingIOError:         # reset meanwhile: signalled all the same
        pass
    return True


class LoopRings:
    """The segments of one loop process (see module doc): ``rings`` and ``arrays`` by name."""

    def __init__(self, rings: dict[str, ShmRing], arrays: dict[str, SharedArray]) -> None:
        self.rings = rings
        self.arrays = arrays

    @classmethod
    def create(cls, m: int, dof: int) -> LoopRings:
        """New segments for a task of dimension ``m`` and ``dof`` joints, owned by this
        process; if one cannot be created, those made before it are removed."""
        made = cls({}, {})
        try:
            for name, (dtype, capacity) in RINGS.items():
                made.rings[name] = ShmRing.create(dtype(m, dof), capacity,
                                                  f'the loop process\'s {name} ring')
            for name, size in ARRAYS.items():
                made.arrays[name] = SharedArray.create(size, f'the loop process\'s {name}')
        except BaseException:
            made.close()
            raise
        return made

    @classmethod
    def attach(cls, names: dict[str, str], m: int, dof: int) -> LoopRings:
        """The segments ``names`` (by ring or array name) created by the other side."""
        made = cls({}, {})
        try:
            for name, (dtype, capacity) in RINGS.items():
                made.rings[name] = ShmRing.attach(names[name], dtype(m, dof), capacity)
            for name, size in ARRAYS.items():
                made.arrays[name] = SharedArray.attach(names[name], size)
        except BaseException:
            made.close()
            raise
        return made

    def names(self) -> dict[str, str]:
        """Each segment's name (``/dev/shm/<name>``), by ring or array name."""
        return {**{k: r.name for k, r in self.rings.items()},
                **{k: a.name for k, a in self.arrays.items()}}

    def counts(self) -> dict[str, int]:
        """This side's losses per ring (see module doc), as ``ring_<ring>_<count>``."""
        return {f'ring_{name}_{what}': int(getattr(ring, what))
                for name, ring in self.rings.items() for what in COUNTS}

    def close(self) -> None:
        """Unmap every segment (the owner also unlinks it), whatever one of them raises;
        the first error is raised after all were tried."""
        first: BaseException | None = None
        segments: list[ShmRing | SharedArray] = [*self.rings.values(), *self.arrays.values()]
        for seg in segments:
            try:
                seg.close()
            except BaseException as exc:
                first = first or exc
        self.rings, self.arrays = {}, {}
        if first is not None:
            raise first


def add_counts(*sides: dict[str, Any]) -> dict[str, str]:
    """The ring counts of both sides (:meth:`LoopRings.counts`, or the child's as its
    status carries them), added per key, as diagnostics values."""
    out: dict[str, int] = {}
    for side in sides:
        for key, n in side.items():
            out[key] = out.get(key, 0) + int(n)
    return {k: str(v) for k, v in out.items()}


class SortedFigures:
    """Percentiles computed in a thread of their own (the node sorts the statistics arrays so:
    see :mod:`~haptic_topology.device.loop_process`): ``read()`` returns
    the newest ``compute()`` result (empty before the first) and asks for a new one, which
    the thread computes at most once per ``period`` s. ``stop()`` before the data that
    ``compute`` reads goes away."""

    def __init__(self, compute: Callable[[], dict[str, str]], period: float) -> None:
        self._compute = compute
        self._period = period
        self.latest: dict[str, str] = {}
        self.problem: str | None = None
        self._asked = threading.Event()
        self._done = False
        self._thread: threading.Thread | None = None

    def read(self) -> dict[str, str]:
        if self._thread is None and not self._done:
            self._thread = threading.Thread(target=self._body, name='loop_figures',
                                            daemon=True)
            self._thread.start()
        self._asked.set()
        return self.latest

    def _body(self) -> None:
        while True:
            self._asked.wait()
            if self._done:
                return
            self._asked.clear()
            try:
                self.latest = self._compute()
            except Exception as exc:    # reported with the figures, the loop goes on
                self.problem = f'loop figures: {type(exc).__name__}: {exc}'
            time.sleep(self._period)

    def stop(self) -> None:
        self._done = True
        self._asked.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self._done = False
