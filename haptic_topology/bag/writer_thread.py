"""The recorder's writer thread: takes batches of messages from a source every
``drain_period`` and writes them with one :class:`~haptic_topology.bag.writer.BagWriter`,
which it alone touches from start to finish (the writer is not thread-safe): it also closes
the bag when told to stop, so a caller that stops waiting for it never closes the writer
beside it.

A failure of the writer (disk full, the bag's directory gone, a split file that cannot be
created, ...) or of the source ends the writing, never silently: :attr:`WriterThread.error`
holds the exception at once, and the thread goes on taking what arrives and discarding it,
so that :meth:`WriterThread.unwritten` counts every message received but not written (the
recorder reports both on ``/diagnostics``; docs/nodes.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from haptic_topology.bag.writer import BagWriter

#: ``write([(topic_index, receive_time_ns, serialized), ...])``, oldest first
Write = Callable[[Sequence[tuple[int, int, bytes]]], None]
#: Hands what arrived since the last call to ``write``; returns how many messages it took.
Drain = Callable[[Write], int]


def _discard(items: Sequence[tuple[int, int, bytes]]) -> None:
    """The sink after a failure: the messages are counted as taken, never written."""


class WriterThread:
    """Writes what ``drain`` takes into ``writer`` every ``drain_period`` s, flushes every
    ``flush_period`` s, and after :meth:`stop` takes the rest once more and closes the bag
    (see module doc)."""

    def __init__(self, writer: BagWriter, drain: Drain, flush_period: float,
                 drain_period: float = 0.01) -> None:
        self.writer = writer
        self._drain = drain
        self.flush_period, self.drain_period = flush_period, drain_period
        #: The exception that ended the writing (None: none).
        self.error: BaseException | None = None
        #: Messages the writer had accepted when it failed (its counts then).
        self.written_at_error = 0
        #: The bag was finished (summary, footer, final metadata.yaml) by this thread.
        self.closed = False
        #: What ended the counting after :attr:`error` (the source failed too; None: none).
        self.counting_error: Exception | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='bag-writer', daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        """Writing loop; on a failure, the counting loop until :meth:`stop`."""
        write = self.writer.write_many
        next_flush = time.monotonic() + self.flush_period
        try:
            while not self._stop.wait(self.drain_period):
                self._drain(write)
                now = time.monotonic()
                if now >= next_flush:
                    self.writer.flush()
                    next_flush = now + self.flush_period
            self._drain(write)
            self.writer.close()
            self.closed = True
            return
        except Exception as exc:  # reported: the recorder's status and close name it
            self.written_at_error = sum(self.writer.counts.values())
            self.error = exc
        # Keep taking what arrives, so that it is counted (unwritten) and the source's
        # queues do not fill; a source that fails too stops the counting.
        try:
            while not self._stop.wait(self.drain_period):
                self._drain(_discard)
            self._drain(_discard)
        except Exception as exc:  # reported beside the first error
            self.counting_error = exc

    def unwritten(self, taken: int) -> int:
        """Messages of the ``taken`` so far that the writer did not get (after a failure: every
        one since; while writing: those not yet handed over)."""
        written = (self.written_at_error if self.error is not None
                   else sum(self.writer.counts.values()))
        return max(taken - written, 0)

    def stop(self, timeout: float) -> bool:
        """Ask the thread to take the rest and close the bag; wait up to ``timeout`` s.
        Returns whether it has ended (else it goes on, alone, and closes the bag itself
        when done)."""
        self._stop.set()
        self._thread.join(timeout=timeout)
        return not self._thread.is_alive()
