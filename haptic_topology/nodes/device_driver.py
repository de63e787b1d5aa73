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

Layouts (parameter ``host_controller``):

* hosted (default, the ros2_control pattern): the process also runs the ``lmi_controller``
  node (its own name, parameters, topics and diagnostics); each cycle (read device ->
  controller -> write) runs in one loop thread (:class:`~haptic_topology.device.runner.
  LoopRunner`: absolute deadlines, or lock-step), the state -> command hop is a function
  call, and a second thread (:class:`~haptic_topology.nodes.hosting.OutboxThread`)
  publishes the states, commands, hand inputs and ``/clock`` for observers. Commands from
  DDS never reach the device: the node does not subscribe to them. ``sched_priority``,
  ``cpu_affinity`` and ``lock_memory`` apply to the loop thread;
* separate: commands come over DDS from an ``lmi_controller`` process; the loop runs on
  executor timers and the command callback, as described above.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock as ClockMsg

from haptic_topology.device.backend import DeviceBackend, create_backend
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop import CommandVerdict, DeviceLoop, DeviceTick
from haptic_topology.device.runner import LoopRunner, Published, RunnerConfig
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.errors import DeviceError, HapticTopologyError
from haptic_topology.nodes import common, node_params
from haptic_topology.nodes.convert import (
    CONTROLLER_ID,
    MessageError,
    RejectCounter,
    command_from_msg,
    ns_to_stamp,
    state_msg,
)
from haptic_topology.nodes.hosting import OutboxThread
from haptic_topology.resolve import resolve_device_driver
from haptic_topology.settings import Clock, DeviceDriverSettings
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
#: GIL switch interval (s) of a process that hosts the loop thread (CPython's default: 5 ms).
SWITCH_INTERVAL = 2e-4
#: Hosted, wall clock: the outbox thread publishes what the loop produced every this many s.
PUBLISH_PERIOD = 0.002


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
        self._realtime_problems: list[str] = []
        self.states_sent = 0
        self._msg, self._clock_msg = DeviceState(), ClockMsg()
        self._state_wall = 0.0
        self._run_start_ns = 0       # stamp of the run's first state (ns)
        self.stats = common.LoopStats(self.cfg.period)
        self.hosted: Any = None       # the hosted LmiController node (host_controller)
        self.runner: LoopRunner | None = None
        self._outbox: OutboxThread | None = None
        # Real-time settings go to the loop thread when hosting (run_main leaves the rest).
        self.process_sched_priority = 0 if s.host_controller else s.sched_priority
        qos = common.loop_qos(self.cfg.clock)
        self.state_pub = self.create_publisher(DeviceState, common.TOPIC_STATE, qos)
        self.clock_pub = self.create_publisher(ClockMsg, common.TOPIC_CLOCK, common.QOS_CLOCK)
        self.diag_pub = self.create_publisher(common.DiagnosticArray, common.TOPIC_DIAGNOSTICS,
                                              common.QOS_DIAGNOSTICS)
        self._endpoints: dict[str, Any] = {common.TOPIC_STATE: self.state_pub}
        if not s.host_controller:
            self._endpoints[common.TOPIC_COMMAND] = self.create_subscription(
                DeviceCommand, common.TOPIC_COMMAND, self._on_command, qos)
        self.create_timer(1.0, self._publish_diagnostics, clock=self.steady)

    def host(self, controller: Any) -> None:
        """Host the ``lmi_controller`` node ``controller`` (before :meth:`start`)."""
        if controller.cfg.scenario.name != self.cfg.scenario.name:
            raise DeviceError(f'device_driver: hosted lmi_controller runs scenario '
                              f'{controller.cfg.scenario.name}, the device '
                              f'{self.cfg.scenario.name}: give both the same scenario')
        self.hosted = controller

    def start(self) -> None:
        """Configure and activate when ``autostart`` (after :meth:`host`)."""
        if self.cfg.settings.autostart:
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
        if self.cfg.settings.host_controller:
            if self.hosted is None:
                return self._fail('host_controller is true but no lmi_controller is hosted '
                                  '(start the node with its main, or set host_controller '
                                  'false and run lmi_controller)')
            c = self.cfg
            self.runner = LoopRunner(
                HostedCycle(self.loop, self.hosted.loop),
                RunnerConfig(c.period, self.lockstep, c.run_duration,
                             self.hosted.cfg.lockstep_wait),
                wall_ns=lambda: self.get_clock().now().nanoseconds)
            # Lock-step: woken by every cycle (the VE waits on the hand inputs); wall clock:
            # the outbox is drained every PUBLISH_PERIOD, so the loop thread pays no wake-up.
            self._outbox = OutboxThread(
                self.runner, self._observe, self.hosted.flush_hand,
                min(self.hosted.flush_period, 1.0 if self.lockstep else PUBLISH_PERIOD))
            if self.lockstep:
                self.runner.wake = self._outbox.wake
            self.hosted.attach(self.runner)
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        assert self.backend is not None
        try:
            self.backend.activate()
        except DeviceError as exc:
            self.backend.deactivate()
            return self._fail(str(exc))
        c = self.cfg
        if self.runner is not None and self._outbox is not None:
            s = c.settings
            # The loop thread must get the GIL back within a fraction of its period when it
            # wakes; CPython lets a thread keep it for up to the switch interval (5 ms).
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
            self.runner.may_engage = self._may_engage()
            self._outbox.start()
            def on_start() -> None:     # in the loop thread
                common.name_os_thread('device_loop')
                self._realtime_problems.extend(common.set_thread_realtime(
                    s.sched_priority, s.cpu_affinity, s.lock_memory))

            self.runner.start(on_start=on_start)
            self._loop_timers = [self.create_timer(0.02, self._check_hosted)]
            self.get_logger().info(f'active: backend {c.backend}, {c.rate_hz:g} Hz '
                                   f'{c.clock.value}, lmi_controller hosted (loop thread)')
            return SUCCESS
        if c.settings.lock_memory or list(c.settings.cpu_affinity) != [-1]:
            problems = common.set_thread_realtime(0, c.settings.cpu_affinity, False)
            if c.settings.lock_memory:
                problems.extend(filter(None, [common.lock_all_memory()]))
            for text in problems:
                self.get_logger().warn(text)
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
        self._stop_outbox()
        self.loop = self.backend = self.runner = None
        return SUCCESS

    def _stop_outbox(self) -> None:
        if self._outbox is not None:
            self._outbox.stop()
            self._outbox = None

    def _fail(self, text: str) -> TransitionCallbackReturn:
        self.fault = text
        self.get_logger().error(text)
        return FAILURE

    def _stop_output(self) -> None:
        for t in self._loop_timers:
            self.destroy_timer(t)
        self._loop_timers = []
        if self.runner is not None:
            # The outbox thread goes on (until cleanup): it publishes what the loop left and
            # flushes the controller's last, partial hand-input batch.
            self.runner.stop()
        if self.backend is not None:
            try:
                self.backend.write(np.zeros(self.cfg.task_dim))
            except DeviceError:
                pass
            self.backend.deactivate()
        if self.loop is not None and self.loop.engaged:
            self.get_logger().info(f'output zeroed at state {self.loop.seq}; loop: '
                                   f'{self.loop.figures()}')

    # -- hosted loop (the cycle runs in the runner's thread) ----------------------------------
    def _may_engage(self) -> bool:
        """Enough subscribers see the state (the hosted controller counts as one)."""
        hosted = 1 if self.hosted is not None else 0
        return self.state_pub.get_subscription_count() + hosted >= self.cfg.min_subscribers

    def _check_hosted(self) -> None:
        """Executor timer: engagement permission, the loop's end, its failures."""
        runner = self.runner
        if runner is None:
            return
        runner.may_engage = self._may_engage()
        while self._realtime_problems:
            self.get_logger().warn(self._realtime_problems.pop(0))
        error = runner.error or (self._outbox.error if self._outbox else None)
        if error is not None:
            self.fault = f'loop thread failed: {type(error).__name__}: {error}'
            self.get_logger().error(self.fault)
            self.trigger_deactivate()
        elif runner.finished and self._outbox is not None and self._outbox.caught_up():
            # Only once every state of the run is published: tools take "inactive" as the
            # end of the run.
            self.get_logger().info(f'run_duration {self.cfg.run_duration:g} s reached: '
                                   'deactivating')
            self.trigger_deactivate()

    def _observe(self, entries: list[Published]) -> None:
        """Outbox thread: publish the cycles' states (and ``/clock``), then the controller's
        commands and hand inputs."""
        for e in entries:
            if self.lockstep:
                self._publish_clock(e.stamp_ns)
            t = e.step.tick
            self.state_pub.publish(state_msg(self._msg, t.seq, ns_to_stamp(e.stamp_ns),
                                             t.reading, t.applied, int(t.status)))
            self.states_sent += 1
        self.hosted.observe(entries)
        assert self.runner is not None
        while self.runner.notices:
            self.get_logger().warn(self.runner.notices.popleft())

    # -- separate layout: the loop on executor callbacks --------------------------------------
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
        self.states_sent += 1
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
        runner = self.runner
        values = self.stats.values() if runner is None else _hosted_values(runner)
        values.update({'backend': self.cfg.backend, 'clock': self.cfg.clock.value,
                       'loop_running': str(self._loop_running()).lower(),
                       f'sent {common.TOPIC_STATE}': str(self.states_sent),
                       'rejected_commands': str(self.rejected.total), **self.rejected.values(),
                       **common.matched(self._endpoints)})
        level, message = (2, f'fault: {self.fault}') if self.fault else (1, 'not configured')
        if loop is not None:
            values.update(loop.values(common.monotonic()))
            values['rejected_commands'] = str(self.rejected.total + loop.rejected_commands)
            if runner is not None:
                values.update(_hosted_answered(runner))
            if not self.fault:
                level, message = loop.health()
        self.diag_pub.publish(common.diagnostics(self, 'device_driver: loop', values, level,
                                                 message))

    def _loop_running(self) -> bool:
        """Whether states may still be published (the bringup's end-of-run check)."""
        if self.runner is not None:
            return (self.runner.running
                    or not (self._outbox is None or self._outbox.caught_up()))
        return bool(self._loop_timers)

    def close(self) -> None:
        """Zero and release the device (called on shutdown)."""
        if self._loop_timers:
            self._stop_output()
        self._stop_outbox()


def _hosted_values(runner: LoopRunner) -> dict[str, str]:
    """Hosted layout: the loop thread's pacing as the device's period figures."""
    f = runner.pacer.figures()
    values = runner.values(f)
    values.update({'rate_hz': f'{1.0 / f.period_mean:.1f}' if f.period_mean > 0 else '0',
                   'period_p50_ms': f'{1e3 * f.period_p50:.3f}',
                   'period_p99_ms': f'{1e3 * f.period_p99:.3f}',
                   'period_max_ms': f'{1e3 * f.period_max:.3f}',
                   'overruns': str(runner.missed_deadlines), 'cycles': str(f.cycles)})
    return values


def _hosted_answered(runner: LoopRunner) -> dict[str, str]:
    """Hosted layout: a skipped deadline is a cycle not answered in time."""
    answered, expected = runner.answered_in_time()
    d = runner.cycle.device
    return {'answered_fraction': f'{answered / expected:.5f}' if expected else 'nan',
            'answer_expected': str(expected),
            # The hosted controller's commands are published with this process's id.
            'controller_id': str(CONTROLLER_ID),
            'max_consecutive_missed': str(max(d.max_missed_run, runner.max_missed_deadlines))}


def build() -> list[Any]:
    """The process's nodes: the driver, and the hosted ``lmi_controller`` unless
    ``host_controller`` is false."""
    driver = DeviceDriver()
    nodes: list[Any] = [driver]
    try:
        if driver.cfg.settings.host_controller:
            from haptic_topology.nodes.lmi_controller import LmiController
            nodes.append(LmiController(driver.cfg.scenario, hosted=True))
            driver.host(nodes[1])
        driver.start()
    except BaseException:
        for n in reversed(nodes):
            n.destroy_node()
        raise
    return nodes


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('device_driver', build, args, node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
