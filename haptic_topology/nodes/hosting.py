"""The publishing side of the hosted layout: a thread that drains the loop's outbox.

The hosted ``device_driver`` runs the 1 kHz cycle in a loop thread
(:class:`~haptic_topology.device.runner.LoopRunner`) that never touches DDS. Everything the
graph's observers get (``DeviceState``, ``DeviceCommand``, ``HandInputs`` batches, the
lock-step ``/clock``) is published by :class:`OutboxThread`: every ``period`` seconds, or
sooner when woken (lock-step: the loop thread wakes it after each cycle, a
:class:`threading.Event`; no executor involved, as rclpy's ``EventsExecutor`` supports no
guard conditions), it takes every entry of the outbox in order, hands them to the node's
publish function, then calls ``idle`` (the controller's flush of a partial hand-input
batch).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from haptic_topology.device.runner import LoopRunner, Published


class OutboxThread:
    """Publishes what a :class:`LoopRunner` puts in its outbox (see module doc)."""

    def __init__(self, runner: LoopRunner, publish: Callable[[list[Published]], None],
                 idle: Callable[[], None], period: float) -> None:
        self.runner = runner
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
        from haptic_topology.nodes.common import name_os_thread

        name_os_thread('device_publish')
        try:
            while True:
                self._event.wait(self._period)
                self._event.clear()
                entries = self.runner.drain()
                if entries:
                    self._publish(entries)
                    self.published += len(entries)
                self._idle()
                if self._stop.is_set() and not self.runner.outbox:
                    return
        except BaseException as exc:  # reported by the node's check timer
            self.error = exc
