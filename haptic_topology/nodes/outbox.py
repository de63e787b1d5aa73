"""The thread of a hosted ``device_driver`` that publishes what its loop produced.

The hosted ``device_driver`` runs the 1 kHz cycle in a loop process
(:class:`~haptic_topology.device.loop_process.LoopProcess`) or a loop thread
(:class:`~haptic_topology.device.runner.LoopRunner`) that never touches DDS. Everything the
graph's observers get (``DeviceState``, ``DeviceCommand``, ``HandInputs`` batches, the
lock-step ``/clock``) is published by :class:`OutboxThread`: every ``period`` seconds, or
sooner when woken (lock-step: the loop thread wakes it after each cycle, a
:class:`threading.Event`, or the loop process's eventfd; no executor involved, as rclpy's
``EventsExecutor`` supports no guard conditions), it takes every cycle the loop produced, in
order, as records (:class:`~haptic_topology.device.records.CycleCodec`), hands them to the
node's publish function, then calls ``idle`` (the controller's flush of a partial hand-input
batch).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from haptic_topology.device.loop_process import LoopProcess
from haptic_topology.device.realtime import name_os_thread, raise_session_nice, renice_thread
from haptic_topology.device.runner import LoopRunner


class OutboxThread:
    """Publishes what ``runner`` puts in its outbox, taken by ``drain`` as cycle records
    (see module doc)."""

    def __init__(self, runner: LoopRunner | LoopProcess, drain: Callable[[], np.ndarray],
                 publish: Callable[[np.ndarray], None], idle: Callable[[], None],
                 period: float, wait: Callable[[float], None] | None = None,
                 nice: int = 0) -> None:
        self.runner = runner
        self._drain = drain
        self._nice = nice
        self.problem: str | None = None     # the nice increment was refused
        self._wait = wait
        self._publish = publish
        self._idle = idle
        self._period = period
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
                if self._wait is not None:     # a loop process: its eventfd, or a poll
                    self._wait(self._period)
                else:
                    self._event.wait(self._period)
                    self._event.clear()
                entries = self._drain()
                if len(entries):
                    self._publish(entries)
                    self.published += len(entries)
                self._idle()
                if self._stop.is_set() and not self.runner.outbox:
                    return
        except BaseException as exc:  # reported by the node's check timer
            self.error = exc


__all__ = ['OutboxThread']
