"""The shared-memory ring (``haptic_topology/device/shm_ring.py``): order, a full ring both
ways, torn reads detected (forced, and under a producer in another process) by ``take`` and
``take_each``, and a segment's
lifetime across processes (Python 3.11's resource tracker must not unlink the owner's
segment when the attaching process exits; nothing is left in /dev/shm)."""

from __future__ import annotations

import doctest
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.device import shm_ring
from haptic_topology.device.records import bytes_dtype, payloads, put_bytes
from haptic_topology.device.shm_ring import ShmRing
from haptic_topology.errors import ConfigError, DeviceError

RECORD = np.dtype([('k', '<i8'), ('x', '<f8', 3)])


def _shm(name: str) -> Path:
    return Path('/dev/shm') / name


def test_docstring_example() -> None:
    assert doctest.testmod(shm_ring).failed == 0


def test_records_come_out_in_order_with_a_limit() -> None:
    ring = ShmRing.create(RECORD, 8)
    peer = ShmRing.attach(ring.name, RECORD, 8)
    try:
        for k in range(5):
            assert ring.put((k, [k, 2 * k, 3 * k]))
        first = peer.take(limit=2)
        rest = peer.take()
        assert first['k'].tolist() == [0, 1] and rest['k'].tolist() == [2, 3, 4]
        assert rest['x'][-1].tolist() == [4.0, 8.0, 12.0]
        assert peer.take().size == 0 and peer.pending == 0
        assert (peer.lost, peer.torn, ring.overwritten, ring.refused) == (0, 0, 0, 0)
    finally:
        peer.close()
        ring.close()


def test_a_full_ring_overwrites_the_oldest_and_both_sides_count_it() -> None:
    ring = ShmRing.create(RECORD, 4)
    peer = ShmRing.attach(ring.name, RECORD, 4)
    try:
        for k in range(7):
            assert ring.put((k, [k] * 3))
        assert ring.overwritten == 3
        got = peer.take()
        assert got['k'].tolist() == [3, 4, 5, 6] and peer.lost == 3
    finally:
        peer.close()
        ring.close()


def test_a_full_ring_refuses_without_overwrite_and_loses_nothing() -> None:
    ring = ShmRing.create(RECORD, 3)
    peer = ShmRing.attach(ring.name, RECORD, 3)
    try:
        assert [ring.put((k, [k] * 3), overwrite=False) for k in range(4)] == [
            True, True, True, False]
        assert ring.refused == 1
        assert peer.take(limit=1)['k'].tolist() == [0]
        assert ring.put((3, [3] * 3), overwrite=False)
        assert peer.take()['k'].tolist() == [1, 2, 3] and peer.lost == 0
    finally:
        peer.close()
        ring.close()


def test_put_with_writes_in_place_what_it_is_given_and_the_rest_stays() -> None:
    """``put_with``: the fill writes part of the slot in place (as ``put_bytes`` writes a
    payload into a record sized for the largest); the seqlock and a full ring as ``put``."""
    ring = ShmRing.create(RECORD, 2)
    peer = ShmRing.attach(ring.name, RECORD, 2)
    try:
        assert ring.put((1, [1.0, 2.0, 3.0]))
        assert ring.put((2, [4.0, 5.0, 6.0]))
        assert peer.take()['k'].tolist() == [1, 2]

        def fill(slot: Any) -> None:
            slot['k'] = 7
            slot['x'][0] = -1.0

        assert ring.put_with(fill) and ring.put_with(fill)
        got = peer.take()
        assert got['k'].tolist() == [7, 7]
        assert got['x'].tolist() == [[-1.0, 2.0, 3.0], [-1.0, 5.0, 6.0]]
        assert ring.put_with(fill, overwrite=False) and ring.put_with(fill, overwrite=False)
        assert not ring.put_with(fill, overwrite=False) and ring.refused == 1
        assert ring.put_with(fill) and ring.overwritten == 1
        assert peer.take()['k'].size == 2 and peer.lost == 1
    finally:
        peer.close()
        ring.close()


def test_put_bytes_keeps_each_payload_whole_and_refuses_one_too_long() -> None:
    ring = ShmRing.create(bytes_dtype(16), 4)
    peer = ShmRing.attach(ring.name, bytes_dtype(16), 4)
    try:
        for data in (b'0123456789abcdef', b'xy', b''):
            assert put_bytes(ring, data, 'test payload')
        assert payloads(peer) == [b'0123456789abcdef', b'xy', b'']
        with pytest.raises(DeviceError, match='test payload of 17 bytes exceeds its record '
                                              r'\(16 bytes\)'):
            put_bytes(ring, b'x' * 17, 'test payload')
    finally:
        peer.close()
        ring.close()


class _LappingSlots:
    """The consumer's slot array, whose read lets the producer lap the ring in the middle of
    the consumer's copy (what a producer on another core can do at any instant)."""

    def __init__(self, slots: np.ndarray, producer: ShmRing) -> None:
        self.slots, self.producer = slots, producer
        self.lapped = False

    def __getitem__(self, i: int) -> Any:
        if not self.lapped:
            self.lapped = True
            for k in range(100, 100 + self.producer.capacity):
                self.producer.put((k, [k] * 3))
        return self.slots[i]


def _k(r: Any) -> int:
    return int(r['k'])


@pytest.mark.parametrize('take', [lambda peer: peer.take()['k'].tolist(),
                                  lambda peer: peer.take_each(_k)], ids=['take', 'take_each'])
def test_a_record_rewritten_during_the_copy_is_discarded_as_torn(take: Any) -> None:
    ring = ShmRing.create(RECORD, 4)
    peer = ShmRing.attach(ring.name, RECORD, 4)
    try:
        ring.put((1, [1] * 3))
        peer._slots = _LappingSlots(peer._slots, ring)  # type: ignore[assignment]
        assert take(peer) == []
        assert peer.torn == 1 and peer.lost == 1
    finally:
        peer._slots = peer._slots.slots  # type: ignore[attr-defined]
        peer.close()
        ring.close()


def test_take_each_copies_what_it_is_given_in_order_with_a_limit_and_skips_lost_records(
        ) -> None:
    """``take_each`` hands each record's slot to the copy function: the same records in the
    same order as ``take``, a limit, and records overwritten before their turn skipped and
    counted."""
    ring = ShmRing.create(RECORD, 4)
    peer = ShmRing.attach(ring.name, RECORD, 4)
    try:
        for k in range(3):
            ring.put((k, [k] * 3))
        assert peer.take_each(_k, limit=2) == [0, 1]
        assert peer.take_each(lambda r: r['x'].tolist()) == [[2.0, 2.0, 2.0]]
        assert peer.take_each(_k) == [] and peer.pending == 0
        for k in range(3, 10):
            ring.put((k, [k] * 3))
        assert peer.take_each(_k) == [6, 7, 8, 9] and peer.lost == 3 and peer.torn == 0
    finally:
        peer.close()
        ring.close()


_PRODUCER = r'''
import sys
import numpy as np
from haptic_topology.device.shm_ring import ShmRing
dtype = np.dtype([('k', '<i8'), ('x', '<f8', 3)])
ring = ShmRing.attach(sys.argv[1], dtype, int(sys.argv[2]))
for k in range(int(sys.argv[3])):
    ring.put((k, [k, k, k]))
print(ring.written, ring.overwritten)
ring.close()
'''


def test_every_record_taken_from_a_producer_in_another_process_is_whole() -> None:
    """The producer (another process) laps a small ring many times while this process takes:
    whatever the interleaving, a record taken is never a mix of two writes, records come in
    increasing order, and taken + lost = written."""
    n, capacity = 200_000, 16
    ring = ShmRing.create(RECORD, capacity)
    try:
        proc = subprocess.Popen([sys.executable, '-c', _PRODUCER, ring.name, str(capacity),
                                 str(n)], stdout=subprocess.PIPE, text=True)
        taken: list[np.ndarray] = []
        while proc.poll() is None:
            taken.append(ring.take())
        out, _ = proc.communicate(timeout=60)
        taken.append(ring.take())
        assert proc.returncode == 0
        got = np.concatenate(taken)
        assert out.split()[0] == str(n)
        assert np.all(got['x'] == got['k'][:, None]), 'a torn record was taken'
        assert np.all(np.diff(got['k']) > 0)
        assert got.size + ring.lost == n
    finally:
        ring.close()


def test_the_attaching_process_leaves_the_segment_to_its_owner() -> None:
    ring = ShmRing.create(RECORD, 4)
    name = ring.name
    code = ('import sys, numpy as np\n'
            'from haptic_topology.device.shm_ring import ShmRing\n'
            "r = ShmRing.attach(sys.argv[1], np.dtype([('k', '<i8'), ('x', '<f8', 3)]), 4)\n"
            'r.put((7, [7.0, 7.0, 7.0]))\n')
    try:
        subprocess.run([sys.executable, '-c', code, name], check=True, timeout=60)
        assert _shm(name).exists()
        assert ring.take()['k'].tolist() == [7]
    finally:
        ring.close()
    assert not _shm(name).exists()


def test_a_layout_the_sides_disagree_on_is_refused() -> None:
    ring = ShmRing.create(RECORD, 4)
    try:
        with pytest.raises(ConfigError, match=r'capacity and record size are \(4, 32\), '
                           r'expected \(8, 32\)'):
            ShmRing.attach(ring.name, RECORD, 8)
        with pytest.raises(ConfigError, match='capacity must be >= 1, got 0'):
            ShmRing.create(RECORD, 0)
    finally:
        ring.close()


class _OfferingSlots:
    """The consumer's slot array, whose every read first lets the producer offer (what a
    producer in another process can do during any copy)."""

    def __init__(self, slots: np.ndarray, offer: Any) -> None:
        self.slots, self.offer = slots, offer

    def __getitem__(self, i: int) -> Any:
        self.offer()
        return self.slots[i]


@pytest.mark.parametrize('take', [lambda peer: peer.take()['k'].tolist(),
                                  lambda peer: peer.take_each(_k)], ids=['take', 'take_each'])
def test_no_loss_a_slot_being_copied_is_not_the_producers_until_its_copy_is_checked(
        take: Any) -> None:
    """A full ring, the producer offering without overwrite while the consumer copies (what
    the node does while the child copies a backlog of LMI updates): the producer must be
    refused until the copy is checked intact, and every record arrives once, in order."""
    ring = ShmRing.create(RECORD, 4)
    peer = ShmRing.attach(ring.name, RECORD, 4)
    offered = [4, 5, 6, 7]                      # the producer's queue, oldest first

    def offer() -> None:
        if offered and ring.put((offered[0], [offered[0]] * 3), overwrite=False):
            del offered[0]                      # refused: offered again next time

    try:
        for k in range(4):
            assert ring.put((k, [k] * 3), overwrite=False)
        peer._slots = _OfferingSlots(peer._slots, offer)  # type: ignore[assignment]
        got: list[int] = take(peer)
        peer._slots = peer._slots.slots  # type: ignore[attr-defined]
        while offered:
            offer()
        got += peer.take_each(_k)
        assert got == list(range(8)), got
        assert (peer.lost, peer.torn) == (0, 0)
    finally:
        if isinstance(peer._slots, _OfferingSlots):
            peer._slots = peer._slots.slots  # type: ignore[assignment]
        peer.close()
        ring.close()


_OFFERER = r'''
import sys, time
import numpy as np
from haptic_topology.device.shm_ring import ShmRing
dtype = np.dtype([('k', '<i8'), ('x', '<f8', 3)])
ring = ShmRing.attach(sys.argv[1], dtype, int(sys.argv[2]))
k, n = int(sys.argv[2]), int(sys.argv[3])
while k < n:                       # offer every ~0.5 ms, never overwrite; refused: offer again
    if ring.put((k, [k, k, k]), overwrite=False):
        k += 1
    time.sleep(0.0005)
print(ring.refused)
ring.close()
'''


def test_no_loss_two_processes_a_full_ring_and_a_slow_copy_lose_nothing() -> None:
    """The issue's experiment: a full ring of 32 (the child's start), copies that take a
    while, the other process offering all the time without overwrite: nothing lost."""
    n, capacity = 96, 32
    ring = ShmRing.create(RECORD, capacity)
    try:
        for k in range(capacity):
            ring.put((k, [k] * 3))
        proc = subprocess.Popen([sys.executable, '-c', _OFFERER, ring.name, str(capacity),
                                 str(n)], stdout=subprocess.PIPE, text=True)

        def slow(r: Any) -> tuple[int, list[float]]:
            time.sleep(0.002)            # slower than the offers: they catch up
            return int(r['k']), r['x'].tolist()

        got: list[tuple[int, list[float]]] = []
        while proc.poll() is None or ring.pending:
            got += ring.take_each(slow)
        proc.communicate(timeout=60)
        assert proc.returncode == 0
        assert [k for k, _ in got] == list(range(n)), [k for k, _ in got]
        assert all(x == [k] * 3 for k, x in got)
        assert (ring.lost, ring.torn) == (0, 0)
    finally:
        ring.close()
