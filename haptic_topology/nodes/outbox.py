"""The thread of a hosted ``device_driver`` that publishes what its loop produced.

The hosted ``device_driver`` runs the 1 kHz cycle in a loop process
(:class:`~haptic_topology.device.loop_process.LoopProcess`) or a loop thread
(:class:`~haptic_topology.device.runner.LoopRunner`) that never touches DDS. Everything the
graph's observers get (``DeviceState``, ``DeviceCommand``, ``HandInputs`` batches, the
lock-step ``/clock``) is published by :class:`OutboxThread`: after a wait of ``period``
seconds (or of what ``timeout()`` says, :func:`until_batch`), or sooner when woken
(lock-step: the loop thread wakes it after each cycle, a :class:`threading.Event`, or the
loop process's eventfd; no executor involved, as rclpy's ``EventsExecutor`` supports no
guard conditions), it takes every cycle the loop produced, in order, as records
(:class:`~haptic_topology.device.records.CycleCodec`), hands them to the node's publish
function, then calls ``idle`` (the controller's flush of a partial hand-input batch).

With the wall clock nothing wakes it (the loop makes no system call for it): it sleeps
until just after the cycle that completes the next batch of hand inputs
(:func:`until_batch`, from the newest record's stamp and hand-input number), so the VE gets
each batch as soon as it is complete, and the states and commands of the cycles between go
out with it, ten cycles a wake-up at a VE update period of 10 instead of two (each wake-up
of this thread cost about as much as publishing two messages).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from haptic_topology.device.realtime import name_os_thread, raise_session_nice, renice_thread
from haptic_topology.device.runner import LoopHandle


def until_batch(now_ns: int, stamp_ns: int, hand_seq: int, batch: int, period_ns: int,
                margin_ns: int, longest: float, shortest: float = 1e-3) -> float:
    """Seconds to wait, at ``now_ns``, after taking records whose newest is the cycle stamped
    ``stamp_ns`` (ns, the same clock) carrying hand input ``hand_seq`` (the controller's
    number, from 1; 0: none): until ``margin_ns`` after the cycle expected to complete the
    next batch of ``batch`` inputs (a batch ends at a multiple of ``batch``; one input per
    cycle of ``period_ns``), within ``[shortest, longest]`` s. ``longest`` without a hand
    input (not engaged), and when that cycle should have come more than ``longest`` ago (the
    loop stalls, or its stamps are of another clock). Cycles that bring no input
    (unanswered) make the batch later than expected: the caller then takes what came and
    waits again.

    Example (batches of 10 inputs, 1 ms cycles, margin 0.5 ms)::

        >>> until_batch(now_ns=0, stamp_ns=0, hand_seq=37, batch=10, period_ns=1_000_000,
        ...             margin_ns=500_000, longest=0.01)      # input 40 ends the batch
        0.0035
        >>> until_batch(0, -200_000, 40, 10, 1_000_000, 500_000, 0.02)   # 50 ends the next
        0.0103
        >>> until_batch(0, -200_000, 40, 10, 1_000_000, 500_000, 0.01)   # at most longest
        0.01
        >>> until_batch(0, -9_800_000, 39, 10, 1_000_000, 500_000, 0.01)  # 40 is late
        0.001
    """
    if hand_seq <= 0:
        return longest
    wait = 1e-9 * (stamp_ns + (batch - hand_seq % batch) * period_ns + margin_ns - now_ns)
    if wait < -longest:
        return longest
    return min(max(wait, shortest), longest)


class OutboxThread:
    """Publishes what ``runner`` puts in its outbox, taken by ``drain`` as cycle records
    (see module doc)."""

    def __init__(self, runner: LoopHandle, drain: Callable[[], np.ndarray],
                 publish: Callable[[np.ndarray], None], idle: Callable[[], None],
                 period: float, wait: Callable[[float], None] | None = None,
                 nice: int = 0, timeout: Callable[[], float] | None = None) -> None:
        self.runner = runner
        self._drain = drain
        self._nice = nice
        self.problem: str | None = None     # the nice increment was refused
        self._wait = wait
        self._publish = publish
        self._idle = idle
        self._period = period
        self._timeout = timeout
        self._event = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.published = 0       # outbox entries published

    def caught_up(self) -> bool:
        """Everything the loop put in the outbox is published (or was dropped)."""
        r = self.runner
        return self.published + r.outbox_dropped >= r.appended

    def wake(self) -> None:
        """Called by the loop thread after each outbox append."""
        self._event.set()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Start the thread (no-op while it runs: it outlives a deactivation, see
        ``device_driver``)."""
        if self.running:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._body, name='device_publish',
                                        daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop after publishing what is in the outbox (call once the loop has stopped)."""
        self._stop.set()
        self._event.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def _body(self) -> None:
        name_os_thread('device_publish')
        if self._nice:      # and this node's autogroup, when the node leads its session
            self.problem = renice_thread(self._nice) or raise_session_nice(self._nice)
        try:
            while True:
                wait = self._period if self._timeout is None else self._timeout()
                if self._wait is not None:     # a loop process: its eventfd, or a poll
                    self._wait(wait)
                else:
                    self._event.wait(wait)
                    self._event.clear()
                entries = self._drain()
                if len(entries):
                    self._publish(entries)
                    self.published += len(entries)
                self._idle()
                if self._stop.is_set() and not self.runner.outbox_pending:
                    return
        except BaseException as exc:  # reported by the node's check timer
            self.error = exc


__all__ = ['OutboxThread', 'until_batch']
