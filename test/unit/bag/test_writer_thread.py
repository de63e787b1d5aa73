"""The recorder's writer thread (:class:`~haptic_topology.bag.writer_thread.WriterThread`)
with a real :class:`~haptic_topology.bag.writer.BagWriter` and a source of messages that the
test controls: every failure ends in :attr:`WriterThread.error` with the count of messages
not written, and the bag is closed by the thread alone, never beside it."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from haptic_topology.bag.reader import iter_messages, open_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.bag.writer_thread import Write, WriterThread
from haptic_topology.errors import BagError
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

STATE = type_name('DeviceState')
#: What the OS says of a bag directory that became a regular file (or is gone for an instant)
GONE = ('Not a directory', 'No such file or directory')


def _state_bytes(seq: int) -> bytes:
    ts = typestore_with_haptic_msgs()
    header = ts.types['std_msgs/msg/Header'](ts.types['builtin_interfaces/msg/Time'](1, 2),
                                             'base')
    v = np.array([0.1, 0.2, 0.3])
    return bytes(ts.serialize_cdr(ts.types[STATE](header, seq, 3, v, v, v, v, 0, np.zeros(0), 0),
                                  STATE))


class Source:
    """Hands ``batch`` new states per drain (``taken`` counts them, as the recorder's taker
    does before writing); ``hold`` set: the drain waits until it is cleared; ``fail``: the
    drain raises it."""

    def __init__(self, batch: int = 10) -> None:
        self.batch, self.taken = batch, 0
        self.hold = threading.Event()
        self.release = threading.Event()
        self.holding = threading.Event()
        self.fail: Exception | None = None

    def drain(self, write: Write) -> int:
        if self.fail is not None:
            raise self.fail
        if self.hold.is_set():
            self.holding.set()
            self.release.wait(30.0)
        items = [(0, 1_000_000_000 + (self.taken + k) * 1_000_000, _state_bytes(self.taken + k))
                 for k in range(1, self.batch + 1)]
        self.taken += len(items)
        write(items)
        return len(items)


def _writer(path: Path, **split: int) -> BagWriter:
    return BagWriter(path, [TopicSpec('/haptic/device/state', STATE, (make_qos(False, 1),))],
                     typestore_with_haptic_msgs(), sources=message_definitions(),
                     compression='none', **split)


def _wait(cond: object, what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():  # type: ignore[operator]
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


def _count(paths: Sequence[Path]) -> int:
    """Messages in the files ``paths`` (one just created when the writer failed is empty)."""
    return sum(1 for p in paths if p.stat().st_size for _ in iter_messages(open_bag(p)))


def test_the_thread_finishes_the_bag_with_every_message(tmp_path: Path) -> None:
    source = Source()
    thread = WriterThread(_writer(tmp_path / 'b'), source.drain, flush_period=0.02,
                          drain_period=0.001)
    thread.start()
    _wait(lambda: source.taken >= 200, 'taken')
    assert thread.stop(20.0)
    assert thread.closed and thread.error is None
    bag = open_bag(tmp_path / 'b')
    assert sum(1 for _ in iter_messages(bag)) == source.taken and not bag.truncated
    assert thread.unwritten(source.taken) == 0


def test_a_stop_that_times_out_leaves_the_bag_to_the_thread(tmp_path: Path) -> None:
    """The thread is in its last take when the wait ends: the caller gets False and the bag
    stays open (no close beside the thread); the thread finishes it when the take returns."""
    source = Source()
    thread = WriterThread(_writer(tmp_path / 'b'), source.drain, flush_period=0.02,
                          drain_period=0.001)
    thread.start()
    _wait(lambda: source.taken >= 50, 'taken')
    source.hold.set()
    _wait(source.holding.is_set, 'the thread in a take')
    assert not thread.stop(0.01)
    assert not thread.closed and thread.running
    assert (tmp_path / 'b' / 'b_0.mcap').exists()
    source.release.set()
    assert thread.stop(20.0)
    assert thread.closed and thread.error is None
    bag = open_bag(tmp_path / 'b')
    assert sum(1 for _ in iter_messages(bag)) == source.taken and not bag.truncated


def test_a_split_that_cannot_create_its_file_is_an_error_with_the_count(
        tmp_path: Path) -> None:
    """The bag's directory replaced by a regular file (fails for root too): the next flush
    cannot rewrite metadata.yaml, or its split cannot create the next file; the error is
    kept, and what keeps arriving is counted."""
    source = Source()
    path = tmp_path / 'b'
    thread = WriterThread(_writer(path, max_bag_size=1), source.drain, flush_period=0.0,
                          drain_period=0.001)
    thread.start()
    _wait(lambda: (path / 'b_1.mcap').exists(), 'a split')
    moved = tmp_path / 'moved'
    path.rename(moved)
    path.write_text('not a directory\n')
    _wait(lambda: thread.error is not None, 'the error')
    # BagError from the split's new file, or OSError from the flush's metadata.yaml before;
    # the path is gone for an instant before the file takes its place
    assert isinstance(thread.error, (BagError, OSError))
    assert any(why in str(thread.error) for why in GONE), thread.error
    taken = source.taken
    _wait(lambda: source.taken > taken + 100, 'taking after the error')
    assert thread.stop(20.0) and not thread.closed
    in_files = _count(sorted(moved.glob('*.mcap')))
    assert in_files == thread.written_at_error
    assert in_files + thread.unwritten(source.taken) == source.taken


def test_a_failing_source_is_an_error_too(tmp_path: Path) -> None:
    source = Source()
    thread = WriterThread(_writer(tmp_path / 'b'), source.drain, flush_period=0.02,
                          drain_period=0.001)
    thread.start()
    _wait(lambda: source.taken >= 30, 'taken')
    source.fail = RuntimeError('take failed')
    _wait(lambda: thread.error is not None, 'the error')
    assert str(thread.error) == 'take failed'
    # The counting loop, which comes next in the thread, stops at the source's next failure.
    _wait(lambda: thread.counting_error is not None, 'the counting stopped')
    assert thread.counting_error is source.fail
    assert thread.stop(20.0)
    assert thread.unwritten(source.taken) == source.taken - thread.written_at_error == 0


def test_a_file_size_limit_is_an_error(tmp_path: Path) -> None:
    """A write the OS refuses (the file-size limit: EFBIG, as a full disk gives ENOSPC)."""
    import resource
    import signal

    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    source = Source()
    thread = WriterThread(_writer(tmp_path / 'b'), source.drain, flush_period=0.0,
                          drain_period=0.001)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, old[1]))    # bytes
    try:
        thread.start()
        _wait(lambda: thread.error is not None, 'the error')
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old)
        signal.signal(signal.SIGXFSZ, handler)
    assert isinstance(thread.error, OSError), thread.error
    assert thread.stop(20.0) and not thread.closed
    assert thread.unwritten(source.taken) == source.taken - thread.written_at_error > 0
