"""Single-producer / single-consumer rings of fixed-layout records in shared memory.

What two processes exchange without a lock, a GIL or a message that the other side controls:
a segment (:class:`multiprocessing.shared_memory.SharedMemory`) holds a small header, one
sequence word per slot and ``capacity`` records of one numpy structured ``dtype``. The
producer writes record ``k`` (``k`` = 0, 1, 2, ... counted over the ring's life) into slot
``k % capacity``; the consumer takes records in order. Neither ever waits for the other
inside :meth:`ShmRing.put` or :meth:`ShmRing.take`.

**Torn reads** are detected with a per-slot sequence word (a seqlock): the producer stores
``2k + 1`` (writing), then the record, then ``2k + 2`` (written). The consumer copies record
``k`` only if the word reads ``2k + 2`` before and after the copy; a word that changed during
the copy (the producer lapped the consumer and rewrote the slot) discards the copy, and a
word that is already past ``2k + 2`` means the record was overwritten before it was taken.
The numpy stores of the producer reach the other core in program order on x86-64 (total
store order), and the consumer's copy is complete before it marks the record taken: rings
are refused on any other architecture (:func:`check_machine`: there, run the loop in a
thread of the node, ``loop_process: false``).

**A full ring** (the consumer ``capacity`` records behind): :meth:`ShmRing.put` with
``overwrite=True`` (the wall-clock loop: the deadline never waits for an observer) writes
anyway, the oldest unread record is lost and counted in :attr:`ShmRing.overwritten`, and the
consumer skips to the oldest record still there and counts what it missed in
:attr:`ShmRing.lost`; with ``overwrite=False`` (lock-step: nothing recorded may be lost)
:meth:`ShmRing.put` returns False and writes nothing, and the producer tries again later.
The consumer marks each record taken only after its copy is checked intact, so a producer that
does not overwrite never rewrites a slot still being copied: nothing is lost.

**Memory** is allocated when a segment is created (``posix_fallocate``): a ``/dev/shm`` too
small for it is a :class:`~haptic_topology.errors.DeviceError` then, never a SIGBUS in the
middle of the loop.

**Lifetime.** The process that :meth:`ShmRing.create` s a segment owns it and unlinks it in
:meth:`ShmRing.close`; :meth:`ShmRing.attach` opens it in the other process. Python 3.11's
resource tracker registers every segment a process opens and unlinks it when that process
exits, even a segment the owner still uses (``track=False`` arrives in 3.13): the attaching
side unregisters it at once, so only the owner's :meth:`~ShmRing.close` (or the owner's
tracker, if the owner dies) removes it.

Example (checked by ``test/unit/device/test_shm_ring.py``)::

    >>> import numpy as np
    >>> ring = ShmRing.create(np.dtype([('k', '<i8'), ('x', '<f8', 3)]), capacity=4)
    >>> peer = ShmRing.attach(ring.name, ring.dtype, 4)
    >>> ring.put((1, [0.1, 0.2, 0.3]))
    True
    >>> got = peer.take()
    >>> int(got[0]['k']), got['x'].tolist()
    (1, [[0.1, 0.2, 0.3]])
    >>> peer.close(); ring.close()
"""

from __future__ import annotations

import os
import platform
import shutil
from collections.abc import Callable
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from haptic_topology.errors import ConfigError, DeviceError

#: Header words (int64): records written (producer), records taken (consumer), capacity,
#: record size in bytes (both sides check they agree on the layout).
_WRITTEN, _TAKEN, _CAPACITY, _ITEMSIZE = range(4)
_HEADER_WORDS = 8
#: Segments created (and not yet unlinked) by this process.
_OWNED: set[str] = set()


#: Machines whose memory ordering the rings rely on (total store order).
TSO_MACHINES = ('x86_64', 'amd64')


def _segment_size(dtype: np.dtype[Any], capacity: int) -> int:
    return 8 * (_HEADER_WORDS + capacity) + dtype.itemsize * capacity


def check_machine(machine: str | None = None) -> None:
    """Refuse a machine (default: this one, ``platform.machine()``) whose memory ordering
    the rings do not hold on (see module doc)."""
    machine = platform.machine() if machine is None else machine
    if machine.lower() not in TSO_MACHINES:
        raise ConfigError(f'shm ring: this machine is {machine!r}, expected one of '
                          f'{", ".join(TSO_MACHINES)} (the rings rely on total store order); '
                          'set loop_process: false to run the loop in a thread of the node')


def new_segment(size: int, what: str) -> SharedMemory:
    """A new shared-memory segment of ``size`` bytes, its memory allocated now (see module
    doc); ``what`` names it in the error when ``/dev/shm`` has no room."""
    check_machine()
    shm = SharedMemory(create=True, size=size)
    try:
        os.posix_fallocate(shm._fd, 0, size)        # type: ignore[attr-defined]
    except OSError as exc:
        shm.close()
        shm.unlink()
        free = shutil.disk_usage('/dev/shm').free
        raise DeviceError(f'shared memory: no room for {what} ({size} bytes) in /dev/shm '
                          f'({exc.strerror}; {free} bytes free): free or enlarge /dev/shm '
                          '(a container: --shm-size)') from None
    _OWNED.add(shm.name)
    return shm


class ShmRing:
    """One ring (module doc). Use ``create`` (owner) or ``attach`` (peer); one
    process puts, the other takes."""

    def __init__(self, shm: SharedMemory, dtype: np.dtype[Any], capacity: int,
                 owner: bool) -> None:
        if capacity < 1:
            raise ConfigError(f'shm ring: capacity must be >= 1, got {capacity}')
        self._shm = shm
        self.dtype = np.dtype(dtype)
        self.capacity = capacity
        self.owner = owner
        buf = shm.buf
        self._header = np.ndarray((_HEADER_WORDS,), np.int64, buf, 0)
        self._seq = np.ndarray((capacity,), np.int64, buf, 8 * _HEADER_WORDS)
        self._slots = np.ndarray((capacity,), self.dtype, buf, 8 * (_HEADER_WORDS + capacity))
        #: Producer: records put while the ring was full (overwrite) or refused (no room).
        self.overwritten = 0
        self.refused = 0
        #: Consumer: records overwritten before they could be taken; copies discarded
        #: because the producer rewrote the slot during the copy.
        self.lost = 0
        self.torn = 0
        self._next = 0          # consumer: index of the next record to take
        self._none = np.empty(0, dtype)     # what take() returns when nothing is new

    @property
    def name(self) -> str:
        """The segment's name (``/dev/shm/<name>``), for ``attach``."""
        return str(self._shm.name)

    @classmethod
    def create(cls, dtype: np.dtype[Any], capacity: int, what: str = 'a ring') -> ShmRing:
        """A new, empty ring owned by this process (unlinked by :meth:`close`); ``what`` names
        it in errors."""
        dtype = np.dtype(dtype)
        if capacity < 1:
            raise ConfigError(f'shm ring: capacity must be >= 1, got {capacity}')
        shm = new_segment(_segment_size(dtype, capacity), what)
        ring = cls(shm, dtype, capacity, owner=True)
        ring._header[:] = 0
        ring._seq[:] = 0
        ring._header[_CAPACITY] = capacity
        ring._header[_ITEMSIZE] = dtype.itemsize
        return ring

    @classmethod
    def attach(cls, name: str, dtype: np.dtype[Any], capacity: int) -> ShmRing:
        """The ring ``name`` created by another process, with the layout both agree on."""
        dtype = np.dtype(dtype)
        check_machine()
        shm = SharedMemory(name=name, create=False)
        if name not in _OWNED:
            # Python 3.11 registers the attached segment with this process's resource
            # tracker, which would unlink it at this process's exit while the owner still
            # uses it (a process started by spawn or as a new interpreter has a tracker of
            # its own; the owner's process keeps its registration).
            resource_tracker.unregister(shm._name, 'shared_memory')  # type: ignore[attr-defined]
        header = np.ndarray((_HEADER_WORDS,), np.int64, shm.buf, 0)
        have = (int(header[_CAPACITY]), int(header[_ITEMSIZE]))
        del header
        if have != (capacity, dtype.itemsize):
            shm.close()
            raise ConfigError(f'shm ring {name}: capacity and record size are {have}, '
                              f'expected {(capacity, dtype.itemsize)}')
        ring = cls(shm, dtype, capacity, owner=False)
        ring._next = int(ring._header[_TAKEN])
        return ring

    # -- producer ------------------------------------------------------------------------------
    def put(self, record: Any, overwrite: bool = True) -> bool:
        """Write ``record`` (anything numpy assigns to one element of ``dtype``: a
        tuple, a ``np.void``) as the next record. A full ring: overwrite the oldest unread
        record (counted in :attr:`overwritten`) or, with ``overwrite=False``, write nothing
        and return False (counted in ``refused``)."""
        return self._write(record, None, overwrite)

    def put_with(self, fill: Callable[[Any], None], overwrite: bool = True) -> bool:
        """:meth:`put` of the record that ``fill`` writes into the slot in place (it gets a
        view of the slot; what it does not write keeps the slot's earlier contents): for
        records of which only a part is used, e.g. the bytes a record sized for the largest
        payload holds, so that the rest is neither built nor copied."""
        return self._write(None, fill, overwrite)

    def _write(self, record: Any, fill: Callable[[Any], None] | None, overwrite: bool) -> bool:
        header = self._header
        k = int(header[_WRITTEN])
        if k - int(header[_TAKEN]) >= self.capacity:
            if not overwrite:
                self.refused += 1
                return False
            self.overwritten += 1
        slot = k % self.capacity
        self._seq[slot] = 2 * k + 1
        if fill is None:
            self._slots[slot] = record
        else:
            fill(self._slots[slot])
        self._seq[slot] = 2 * k + 2
        header[_WRITTEN] = k + 1
        return True

    @property
    def written(self) -> int:
        """Records put over the ring's life."""
        return int(self._header[_WRITTEN])

    @property
    def full(self) -> bool:
        """The producer's view: the consumer has not taken (and marked) ``capacity``
        records: a put now overwrites one or is refused."""
        return int(self._header[_WRITTEN]) - int(self._header[_TAKEN]) >= self.capacity

    # -- consumer ------------------------------------------------------------------------------
    def _claim(self, limit: int | None) -> range:
        """The record numbers to take now (at most ``limit``); records the producer overwrote
        before they could be taken are counted in :attr:`lost`. Nothing is marked taken here:
        :meth:`_taken` does it record by record, after each copy is checked intact, so the
        producer's room check never lets it rewrite a slot still being copied."""
        written = int(self._header[_WRITTEN])
        if written == self._next:       # nothing new (most calls: the loop polls each cycle)
            return range(0)
        oldest = written - self.capacity
        if self._next < oldest:
            self.lost += oldest - self._next
            self._next = oldest
        n = written - self._next if limit is None else min(written - self._next, limit)
        return range(self._next, self._next + n)

    def _taken(self, k: int) -> None:
        """Record ``k`` is copied (or lost): its slot is the producer's again."""
        self._next = k + 1
        self._header[_TAKEN] = k + 1

    def _intact(self, k: int, before: bool) -> bool:
        """Whether slot ``k % capacity`` still holds record ``k`` (``before`` the copy: not
        yet rewritten; after it: not rewritten during it, else a torn read); counts the
        losses."""
        if int(self._seq[k % self.capacity]) == 2 * k + 2:
            return True
        self.lost += 1
        self.torn += 0 if before else 1
        return False

    def take(self, limit: int | None = None) -> np.ndarray:
        """Copies of the records written since the last take, oldest first (at most
        ``limit``), as an array of ``dtype``; records overwritten meanwhile are skipped
        and counted in :attr:`lost`."""
        ks = self._claim(limit)
        if not ks:
            return self._none
        out = np.empty(len(ks), self.dtype)
        got = 0
        for k in ks:
            if self._intact(k, before=True):
                out[got] = self._slots[k % self.capacity]
                got += self._intact(k, before=False)
            self._taken(k)
        return out[:got]

    def take_each(self, copy: Callable[[Any], Any], limit: int | None = None) -> list[Any]:
        """What ``copy`` makes of each record written since the last take (it gets a view of
        the slot and must copy what it keeps), oldest first, at most ``limit``; a record
        overwritten before or during its copy is skipped as in :meth:`take`. For records of
        which only a part is used, e.g. the bytes a record of a size fixed for the largest
        payload holds: nothing else of the record is copied."""
        out: list[Any] = []
        for k in self._claim(limit):
            if self._intact(k, before=True):
                item = copy(self._slots[k % self.capacity])
                if self._intact(k, before=False):
                    out.append(item)
            self._taken(k)
        return out

    @property
    def pending(self) -> int:
        """Records written and not taken yet (at most ``capacity`` can still be taken)."""
        return int(self._header[_WRITTEN]) - self._next

    # -- end -----------------------------------------------------------------------------------
    def _release(self) -> None:
        # numpy views hold exports of the buffer: drop them before the mapping is closed.
        self._header = self._seq = self._slots = None  # type: ignore[assignment]
        self._shm.close()

    def close(self) -> None:
        """Unmap the segment; the owner also unlinks it (nothing is left in /dev/shm)."""
        if self._header is None:
            return
        self._release()
        if self.owner:
            _OWNED.discard(self._shm.name)
            self._shm.unlink()


class SharedArray:
    """A float64 array in a shared-memory segment, written by one process and read by
    another (each 8-byte element is stored whole on x86-64: a reader sees an old or a new
    value, never a mix). Lifetime as :class:`ShmRing`'s: ``create`` owns and unlinks it,
    ``attach`` unregisters it from its process's resource tracker."""

    def __init__(self, shm: SharedMemory, size: int, owner: bool) -> None:
        self._shm = shm
        self.owner = owner
        self.array: np.ndarray = np.ndarray((size,), np.float64, shm.buf, 0)

    @property
    def name(self) -> str:
        return str(self._shm.name)

    @classmethod
    def create(cls, size: int, what: str = 'an array') -> SharedArray:
        if size < 1:
            raise ConfigError(f'shared array: size must be >= 1, got {size}')
        shm = new_segment(8 * size, what)
        arr = cls(shm, size, owner=True)
        arr.array[:] = 0.0
        return arr

    @classmethod
    def attach(cls, name: str, size: int) -> SharedArray:
        check_machine()
        shm = SharedMemory(name=name, create=False)
        if name not in _OWNED:      # see ShmRing.attach
            resource_tracker.unregister(shm._name, 'shared_memory')  # type: ignore[attr-defined]
        if shm.size < 8 * size:
            shm.close()
            raise ConfigError(f'shared array {name}: {shm.size} bytes, expected {8 * size}')
        return cls(shm, size, owner=False)

    def close(self) -> None:
        if self.array is None:
            return
        self.array = None  # type: ignore[assignment]
        self._shm.close()
        if self.owner:
            _OWNED.discard(self._shm.name)
            self._shm.unlink()
