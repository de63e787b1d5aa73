"""``device_driver``: the device side of the haptic loop, a lifecycle node (ROS I/O only).

The loop policy is :class:`~haptic_topology.device.loop.DeviceLoop` (engagement, clamp ->
watchdog -> clamp, statistics); this node converts messages, keeps the clock and publishes
diagnostics. Lifecycle, as a ros2_control hardware component: configure ->
``backend.configure``; activate -> ``backend.activate`` and the loop starts (idle until a
controller engages); deactivate -> zero output, ``backend.deactivate``. With ``autostart``
(default) the node configures and activates itself; a failing transition ends the process
with one line naming the cause. After ``run_duration`` seconds of engaged loop (simulated
seconds in lock-step) the node deactivates itself (measured on the states' stamps: wall
time since the first engaged state, or simulated time in lock-step): tools see the run end as
the lifecycle state ``inactive``.

Clocks (parameter ``clock``):

* ``wall``: a timer at ``rate_hz`` ticks the loop with the measured period; states are stamped
  with the node's clock;
* ``lockstep``: the node publishes ``/clock``; simulated time stays 0 while idle (idle states
  come from a steady timer) and advances one device period each time the command answering
  the current state has arrived, so every node computes with the offline simulation's times.
  A state left unanswered for ``lockstep_warn_after`` (wall s) gets a warning, not a timeout.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock as ClockMsg

from haptic_topology.device.backend import DeviceBackend, create_backend
from haptic_topology.device.loop import CommandVerdict, DeviceLoop, DeviceTick
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.errors import DeviceError, HapticTopologyError
from haptic_topology.nodes import common, node_params
from haptic_topology.nodes.convert import (
    MessageError,
    RejectCounter,
    command_from_msg,
    ns_to_stamp,
    state_msg,
)
from haptic_topology.resolve import resolve_device_driver
from haptic_topology.settings import Clock, DeviceDriverSettings
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


class DeviceDriver(LifecycleNode):
    """Steps the device backend through :class:`DeviceLoop` (see module doc)."""

    def __init__(self, scenario: Scenario | None = None, **kwargs: Any) -> None:
        super().__init__('device_driver', **kwargs)
        s = common.declare_settings(self, DeviceDriverSettings)
        self.cfg = resolve_device_driver(s, scenario or load_scenario(s.scenario))
        self.lockstep = self.cfg.clock is Clock.LOCKSTEP
        self.steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.backend: DeviceBackend | None = None
        self.loop: DeviceLoop | None = None
        self.fault = ''
        self.rejected = RejectCounter()
        self._loop_timers: list[Any] = []
        self._msg, self._clock_msg = DeviceState(), ClockMsg()
        self._state_wall = 0.0
        self._run_start_ns = 0       # stamp of the run's first state (ns)
        self.stats = common.LoopStats(self.cfg.period)
        qos = common.loop_qos(self.cfg.clock)
        self.state_pub = self.create_publisher(DeviceState, common.TOPIC_STATE, qos)
        self.clock_pub = self.create_publisher(ClockMsg, common.TOPIC_CLOCK, common.QOS_CLOCK)
        self.diag_pub = self.create_publisher(common.DiagnosticArray, common.TOPIC_DIAGNOSTICS,
                                              common.QOS_DIAGNOSTICS)
        cmd_sub = self.create_subscription(DeviceCommand, common.TOPIC_COMMAND, self._on_command,
                                           qos)
        self._endpoints = {common.TOPIC_STATE: self.state_pub, common.TOPIC_COMMAND: cmd_sub}
        self.create_timer(1.0, self._publish_diagnostics, clock=self.steady)
        if s.autostart:
            for step in (self.trigger_configure, self.trigger_activate):
                if step() != SUCCESS:
                    raise DeviceError(self.fault or f'device_driver: {step.__name__} failed')

    # -- lifecycle ---------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.backend = create_backend(self.cfg.backend)
            self.backend.configure(self.cfg.backend_config())
        except HapticTopologyError as exc:
            return self._fail(str(exc))
        self.loop = DeviceLoop(self.backend, self.cfg.wrench_limit,
                               CommandWatchdog(self.cfg.watchdog, self.cfg.task_dim),
                               self.cfg.period, self.cfg.takeover_after)
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        assert self.backend is not None
        try:
            self.backend.activate()
        except DeviceError as exc:
            self.backend.deactivate()
            return self._fail(str(exc))
        c = self.cfg
        timers = [(c.period, self._tick_idle if self.lockstep else self._tick_wall)]
        if self.lockstep:
            timers.append((c.lockstep_warn_after, self._warn_stalled))
            self._publish_clock(0)
        self._loop_timers = [self.create_timer(p, cb) for p, cb in timers]
        self.get_logger().info(f'active: backend {c.backend}, {c.rate_hz:g} Hz {c.clock.value}')
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_output()
        return SUCCESS

    on_shutdown = on_deactivate

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.loop = self.backend = None
        return SUCCESS

    def _fail(self, text: str) -> TransitionCallbackReturn:
        self.fault = text
        self.get_logger().error(text)
        return FAILURE

    def _stop_output(self) -> None:
        for t in self._loop_timers:
            self.destroy_timer(t)
        self._loop_timers = []
        if self.backend is not None:
            try:
                self.backend.write(np.zeros(self.cfg.task_dim))
            except DeviceError:
                pass
            self.backend.deactivate()
        if self.loop is not None and self.loop.engaged:
            self.get_logger().info(f'output zeroed at state {self.loop.seq}; loop: '
                                   f'{self.loop.figures()}')

    # -- loop --------------------------------------------------------------------------------
    def _on_command(self, msg: DeviceCommand) -> None:
        loop = self.loop
        if loop is None or not self._loop_timers:
            return
        try:
            state_seq, mode, wrench, cid = command_from_msg(msg, self.cfg.scenario.linkage.task)
        except MessageError as exc:
            self.rejected.add(exc)
            self.get_logger().warn(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        was_engaged, followed = loop.engaged, loop.controller_id
        may_engage = self.state_pub.get_subscription_count() >= self.cfg.min_subscribers
        verdict = loop.on_command(state_seq, mode, wrench, common.monotonic(), may_engage, cid)
        if loop.engaged and not was_engaged:
            self.get_logger().info(f'controller {cid} engaged at state {state_seq}')
        elif loop.controller_id != followed:
            self.get_logger().warn(f'controller {cid} took over from the silent {followed}')
        if (self.lockstep and verdict == CommandVerdict.APPLIED and loop.engaged
                and loop.answered_current):
            self._step(self.cfg.period)

    def _tick_wall(self) -> None:
        now = common.monotonic()
        period = self.stats.tick(now)
        nominal = self.cfg.period
        dt = nominal if period is None else min(max(period, 0.0), 20.0 * nominal)
        self._publish(self.loop.tick(now, dt) if self.loop else None,
                      self.get_clock().now().nanoseconds)

    def _tick_idle(self) -> None:
        """Lock-step, before engagement: idle states at simulated time 0."""
        if self.loop is not None and not self.loop.engaged:
            self._publish(self.loop.tick(common.monotonic(), self.cfg.period), 0)

    def _step(self, dt: float) -> None:
        """Lock-step: the current state is answered; advance one period."""
        assert self.loop is not None
        now = common.monotonic()
        self.stats.tick(now)
        tick = self.loop.tick(now, dt)
        ns = tick.run_index * self.cfg.period_ns
        self._publish_clock(ns)
        self._publish(tick, ns)

    def _publish(self, tick: DeviceTick | None, ns: int) -> None:
        if tick is None:
            return
        self._state_wall = common.monotonic()
        self.state_pub.publish(state_msg(self._msg, tick.seq, ns_to_stamp(ns), tick.reading,
                                         tick.applied, int(tick.status)))
        if tick.run_index == 0:
            self._run_start_ns = ns
        duration = self.cfg.run_duration
        if (duration > 0.0 and tick.run_index >= 0
                and ns - self._run_start_ns >= round(duration * 1e9)):
            self.get_logger().info(f'run_duration {duration:g} s reached: deactivating')
            self.trigger_deactivate()

    def _publish_clock(self, ns: int) -> None:
        self._clock_msg.clock = ns_to_stamp(ns)
        self.clock_pub.publish(self._clock_msg)

    def _warn_stalled(self) -> None:
        loop = self.loop
        if loop is None or not loop.engaged or loop.answered_current:
            return
        waited = common.monotonic() - self._state_wall
        if waited >= self.cfg.lockstep_warn_after:
            self.get_logger().warn(f'lock-step: no answer to state {loop.seq} for {waited:.1f}'
                                   ' s (is lmi_controller running, and ve_sim?)')

    def _publish_diagnostics(self) -> None:
        loop = self.loop
        values = self.stats.values()
        values.update({'backend': self.cfg.backend, 'clock': self.cfg.clock.value,
                       'rejected_commands': str(self.rejected.total), **self.rejected.values(),
                       **common.matched(self._endpoints)})
        level, message = (2, f'fault: {self.fault}') if self.fault else (1, 'not configured')
        if loop is not None:
            values.update(loop.values(common.monotonic()))
            values['rejected_commands'] = str(self.rejected.total + loop.rejected_commands)
            if not self.fault:
                level, message = loop.health()
        self.diag_pub.publish(common.diagnostics(self, 'device_driver: loop', values, level,
                                                 message))

    def close(self) -> None:
        """Zero and release the device (called on shutdown)."""
        if self._loop_timers:
            self._stop_output()


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('device_driver', lambda: [DeviceDriver()], args,
                           node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
