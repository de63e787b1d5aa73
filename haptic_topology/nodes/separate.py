"""The node side of the separate layout: executor timers and the command callback step the
device (``device_driver`` with ``host_controller: false``).

:class:`SeparateLoop` is what a separate-layout ``device_driver`` runs instead of a loop
thread: the core :class:`~haptic_topology.device.executor_loop.ExecutorLoop` decides when the
device ticks and with which stamp; this class owns the timers (wall clock: one per device
period; lock-step: the idle timer before engagement and the stall warning), takes the
``DeviceCommand`` messages the driver subscribes to, and hands each state to
``driver.publish_state``. Same interface as :class:`~haptic_topology.nodes.hosting.
HostedLoop`: :meth:`start`, :meth:`stop`, :meth:`close`, :attr:`running`, :meth:`values`.
"""

from __future__ import annotations

from typing import Any

from haptic_topology.device.executor_loop import Emitted, ExecutorLoop
from haptic_topology.device.realtime import set_thread_realtime
from haptic_topology.messages.check import env_wrench
from haptic_topology.nodes.convert import MessageError, command_from_msg
from haptic_topology.nodes.diagnostics import monotonic
from haptic_topology_msgs.msg import DeviceCommand


class SeparateLoop:
    """The separate layout's loop, owned by the configured ``device_driver`` ``driver``."""

    def __init__(self, driver: Any) -> None:
        c = driver.cfg
        self.driver = driver
        self.stepper = ExecutorLoop(driver.loop, c.period, driver.lockstep, c.run_duration,
                                    c.lockstep_warn_after)
        self._timers: list[Any] = []

    def start(self) -> None:
        """The executor thread's real-time settings (``cpu_affinity``, ``lock_memory``,
        ``sched_slice_us``, ``timer_slack_ns``; ``sched_priority`` is the process's) and the
        loop's timers."""
        d, s = self.driver, self.driver.cfg.settings
        c = d.cfg
        for text in set_thread_realtime(0, s.cpu_affinity, s.lock_memory, s.sched_slice_us,
                                        s.timer_slack_ns):
            d.get_logger().warn(text)
        timers = [(c.period, self._tick_idle if d.lockstep else self._tick_wall)]
        if d.lockstep:
            timers.append((c.lockstep_warn_after, self._warn_stalled))
            d.publish_clock(0)
        self._timers = [d.create_timer(p, cb) for p, cb in timers]

    def stop(self) -> None:
        for t in self._timers:
            self.driver.destroy_timer(t)
        self._timers = []

    def close(self) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return bool(self._timers)

    def values(self) -> dict[str, str]:
        """The measured period between device ticks."""
        return self.stepper.stats.values()

    def on_command(self, msg: DeviceCommand) -> None:
        """A ``DeviceCommand`` from DDS (ignored while stopped)."""
        d = self.driver
        if not self._timers:
            return
        try:
            state_seq, mode, wrench, cid = command_from_msg(msg, d.cfg.scenario.linkage.task)
            env = env_wrench(msg, d.cfg.scenario.linkage.task.dim)
        except MessageError as exc:
            d.rejected.add(exc)
            d.get_logger().warn(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        out = self.stepper.on_command(state_seq, mode, wrench, monotonic(),
                                      d.may_engage(), cid, env)
        if out.info:
            d.get_logger().info(out.info)
        if out.warning:
            d.get_logger().warn(out.warning)
        self._emit(out.emitted)

    def _tick_wall(self) -> None:
        if not self._timers:      # a tick the executor had queued before stop(): the device
            return                # is zeroed and released, it must not be written again
        self._emit(self.stepper.wall_tick(monotonic(),
                                          self.driver.get_clock().now().nanoseconds))

    def _tick_idle(self) -> None:
        if not self._timers:
            return
        self._emit(self.stepper.idle_tick(monotonic()))

    def _warn_stalled(self) -> None:
        text = self.stepper.stalled(monotonic())
        if text:
            self.driver.get_logger().warn(text)

    def _emit(self, e: Emitted | None) -> None:
        if e is not None:
            self.driver.publish_state(e.tick, e.stamp_ns, e.clock)
            if e.ends_run:
                self.driver.end_run()
