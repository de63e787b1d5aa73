"""``device_driver``: the device side of the haptic loop, a lifecycle node (ROS I/O only).

The loop policy is :class:`~haptic_topology.device.loop.DeviceLoop` (engagement, clamp ->
watchdog -> clamp, statistics, device faults); this node converts messages, keeps the clock
and publishes diagnostics (``hardware_id``: the backend and its device, e.g. ``sim_maglev
planar``; ERROR while the device reports a fault or after a failed transition). Lifecycle,
as a ros2_control hardware component: configure -> ``backend.configure``; activate ->
``backend.activate`` and the loop starts (idle until a controller engages); deactivate ->
zero output, ``backend.deactivate``. With ``autostart`` (default) the node configures and
activates itself; a failing transition ends the process with one line naming the cause.
After ``run_duration`` seconds of engaged loop (simulated seconds in lock-step) the node
deactivates itself (measured on the states' stamps: wall time since the first engaged state,
or simulated time in lock-step): tools see the run end as the lifecycle state ``inactive``.
Every state goes to ``haptic/device/state``; at most ``sampled_state_rate_hz`` of them a
second (of the node's monotonic clock, under either clock) also go to
``haptic/device/state_sampled``, for readers that want the newest state now and then
(``ve_sim``'s picture) without being sent every one.

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
  controller -> write) runs in the core :class:`~haptic_topology.device.runner.LoopRunner`
  (absolute deadlines, or lock-step; :class:`~haptic_topology.nodes.hosting.HostedLoop`),
  the state -> command hop is a function call, and a thread of this node publishes the
  states, commands, hand inputs and ``/clock`` for observers. With ``loop_process``
  (default) the cycle runs in a child process without rclpy, which opens the device
  (:mod:`haptic_topology.device.loop_process`); else, and with a backend that uses rclpy
  itself (``ros_topics``: the node says so when it configures), in a loop thread of this
  process. Commands from DDS never reach the device: the node does not subscribe to them.
  ``sched_priority``, ``cpu_affinity`` and ``lock_memory`` apply to the loop process or
  thread;
* separate: commands come over DDS from an ``lmi_controller`` process; executor timers and
  the command callback step the loop through the core
  :class:`~haptic_topology.device.executor_loop.ExecutorLoop`, as described above.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock as ClockMsg

from haptic_topology import vocabulary as vocab
from haptic_topology.config import node_params
from haptic_topology.config.resolve import configure_hosted, resolve_device_driver
from haptic_topology.config.settings import DeviceDriverSettings
from haptic_topology.device.backend import DeviceBackend, create_backend, zero_and_release
from haptic_topology.device.loop import DeviceLoop, DeviceTick, device_report, hardware_id
from haptic_topology.device.runner import LOCKSTEP_RUNS_ONCE
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.errors import DeviceError, error_line
from haptic_topology.model.frames import DEVICE_BASE
from haptic_topology.nodes.convert import GraphFilter, RejectCounter, ns_to_stamp
from haptic_topology.nodes.diagnostics import PublisherWatch, diagnostics, matched, monotonic
from haptic_topology.nodes.hosting import HostedLoop, driver_layout, in_child
from haptic_topology.nodes.parameters import declare_settings
from haptic_topology.nodes.qos import QOS_CLOCK, QOS_DIAGNOSTICS, QOS_SAMPLED, loop_qos
from haptic_topology.nodes.runtime import run_main
from haptic_topology.nodes.separate import SeparateLoop
from haptic_topology.nodes.wire import StateOut
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology_msgs.msg import DeviceCommand

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


class DeviceDriver(LifecycleNode):
    """Steps the device backend through :class:`DeviceLoop` (see module doc)."""

    def __init__(self, scenario: Scenario | None = None, **kwargs: Any) -> None:
        super().__init__('device_driver', **kwargs)
        s = declare_settings(self, DeviceDriverSettings)
        self.cfg = resolve_device_driver(s, scenario or load_scenario(s.scenario))
        self.lockstep = self.cfg.clock is vocab.Clock.LOCKSTEP
        self.backend: DeviceBackend | None = None
        self.loop: DeviceLoop | None = None
        self.layout: HostedLoop | SeparateLoop | None = None    # once configured
        self.in_child = False         # the loop runs in a loop process (loop_process)
        self.hosted: Any = None       # the hosted LmiController node (host_controller)
        self.fault = ''
        self.rejected = RejectCounter()
        self._active = self._ran = False  # between activate and deactivate; activated once
        self._clock_msg = ClockMsg()
        self.graph = GraphFilter(s.graph_id)
        # Real-time settings go to the loop thread when hosting (run_main leaves the rest).
        self.process_sched_priority = 0 if s.host_controller else s.sched_priority
        qos = loop_qos(self.cfg.clock)
        self.states = StateOut(self.create_publisher, qos, QOS_SAMPLED, DEVICE_BASE,
                               self.graph.wire, s.sampled_state_rate_hz)
        self.clock_pub = self.create_publisher(ClockMsg, vocab.TOPIC_CLOCK, QOS_CLOCK)
        self.diag_pub = self.create_publisher(DiagnosticArray, vocab.TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        self._endpoints: dict[str, Any] = {vocab.TOPIC_STATE: self.states.pub}
        if not s.host_controller:
            self._endpoints[vocab.TOPIC_COMMAND] = self.create_subscription(
                DeviceCommand, vocab.TOPIC_COMMAND, self._on_command, qos)
        self.input_publishers = PublisherWatch(
            self, {} if s.host_controller else {vocab.TOPIC_COMMAND: ('lmi_controller',)},
            self._publish_diagnostics)
        self.create_timer(1.0, self._publish_diagnostics,
                          clock=RosClock(clock_type=ClockType.STEADY_TIME))

    def start(self, hosted: Any = None) -> None:
        """Host the ``lmi_controller`` node ``hosted`` (with ``host_controller``); configure
        and activate when ``autostart``."""
        self.hosted = hosted
        if self.cfg.settings.autostart:
            for step in (self.trigger_configure, self.trigger_activate):
                if step() != SUCCESS:
                    raise DeviceError(self.fault or f'device_driver: {step.__name__} failed')

    # -- lifecycle ---------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        c = self.cfg
        try:
            self.backend = create_backend(c.backend, self.lockstep)
            self.in_child = self.hosted is not None and in_child(self)
            if self.hosted is not None and c.settings.loop_process and not self.in_child:
                self.get_logger().warn(f'loop_process: backend {c.backend} uses rclpy itself, '
                                       'so the loop runs in a thread of this process')
            if not self.in_child:         # else the loop process opens the device
                self.backend.configure(c.backend_config())
                self.loop = DeviceLoop(self.backend, c.wrench_limit,
                                       CommandWatchdog(c.watchdog, c.task_dim), c.period,
                                       c.takeover_after)
            if self.hosted is not None:   # passivity: auto; the device's own Z-width map
                configure_hosted(self.hosted.cfg, self.hosted.loop.ctrl.energy, self.backend,
                                 self.get_logger().warn, self.get_logger().info)
            self.layout = driver_layout(self, self.hosted)
        except Exception as exc:    # a backend's own code too: the fault
            why = error_line(exc, f'{getattr(self.backend, "name", c.backend)}: configure()')
            # Not configured: diagnostics report the backend parameter, not a half-made backend.
            self.loop = self.backend = None
            return self.fail(why)
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        assert self.backend is not None and self.layout is not None
        if self.lockstep and self._ran:
            return self.fail(LOCKSTEP_RUNS_ONCE)
        try:
            if self.loop is not None:       # else the loop process opens the device
                self.loop.activate()
            self.layout.start()     # a loop process opens the device: it raises here
        except DeviceError as exc:      # the device is zeroed and released
            return self.fail(str(exc))
        self._active = self._ran = True
        c = self.cfg
        where = self.layout.where() if isinstance(self.layout, HostedLoop) else ''

        self.get_logger().info(f'active: backend {c.backend}, {c.rate_hz:g} Hz {c.clock.value}'
                               + (f', lmi_controller hosted ({where})'
                                  if self.hosted is not None else ''))
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_output()
        return SUCCESS

    on_shutdown = on_deactivate

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.layout is not None:
            self.layout.close()
        if self.backend is not None and not self.in_child:
            self.backend.cleanup()
        self.loop = self.backend = self.layout = None
        return SUCCESS

    def fail(self, text: str) -> TransitionCallbackReturn:
        """Record and log the fault ``text`` and publish it in diagnostics now (ERROR; the
        bringup reports a failed transition with it)."""
        self.fault = text
        self.get_logger().error(text)
        self._publish_diagnostics()
        return FAILURE

    def end_run(self) -> None:
        self.get_logger().info(f'run_duration {self.cfg.run_duration:g} s reached: '
                               'deactivating')
        self.trigger_deactivate()

    def _stop_output(self) -> None:
        self._active = False
        if self.layout is not None:
            self.layout.stop()
        if self.backend is not None and not self.in_child:   # the child zeroed its own
            for problem in zero_and_release(self.backend, self.cfg.task_dim):
                self.get_logger().error(problem)
        if self.loop is not None and self.loop.engaged:
            self.get_logger().info(f'output zeroed at state {self.loop.seq}; loop: '
                                   f'{self.loop.figures()}')

    def may_engage(self) -> bool:
        """Enough subscribers see the state (a hosted controller counts as one)."""
        hosted = 1 if self.hosted is not None else 0
        return self.states.pub.get_subscription_count() + hosted >= self.cfg.min_subscribers

    def _on_command(self, msg: DeviceCommand) -> None:
        if (isinstance(self.layout, SeparateLoop) and self.graph.own(msg, vocab.TOPIC_COMMAND)
                and self.input_publishers.admits(vocab.TOPIC_COMMAND, self.rejected)):
            self.layout.on_command(msg)

    def publish_state(self, tick: DeviceTick | bytes, ns: int, clock: bool = False) -> None:
        """Publish ``/clock`` at ``ns`` (when ``clock``), then the state stamped ``ns``
        (``tick``, or its bytes packed by ``states.writer``), sampled
        (:class:`~haptic_topology.nodes.wire.StateOut`)."""
        if clock:
            self.publish_clock(ns)
        self.states.publish(tick, ns)

    def publish_clock(self, ns: int) -> None:
        self._clock_msg.clock = ns_to_stamp(ns)
        self.clock_pub.publish(self._clock_msg)

    def _publish_diagnostics(self) -> None:
        layout = self.layout
        child = layout.process if isinstance(layout, HostedLoop) else None
        if isinstance(layout, HostedLoop) and child is not None:
            # the loop process's report, with this node's refusals
            level, message, loop_values = child.device_report(self.fault, self.rejected.total)
            loop_values.update(layout.values())
        else:
            level, message, loop_values = device_report(   # a hosted loop thread's round
                self.loop, monotonic(), self.fault, self.rejected.total,   # trips: its values
                layout.values() if layout else {}, not isinstance(layout, HostedLoop))
        values = {'backend': self.cfg.backend, 'clock': self.cfg.clock.value,
                  'loop_running': str(layout is not None and layout.running).lower(),
                  **self.states.values(),
                  **self.rejected.values(), **self.graph.values(), **matched(self._endpoints),
                  **loop_values}
        level, message = self.input_publishers.merge(values, level, message)
        self.diag_pub.publish(diagnostics(
            self, vocab.STATUS_DEVICE, values, level, message,
            child.status.get('hardware_id', self.cfg.backend) if child is not None
            else hardware_id(self.backend, self.cfg.backend)))

    def close(self) -> None:
        """Zero and release the device (called on shutdown)."""
        if self._active:
            self._stop_output()
        if self.layout is not None:
            self.layout.close()
        if self.backend is not None and not self.in_child:
            self.backend.cleanup()


def build() -> list[Any]:
    """The process's nodes: the driver, and the hosted ``lmi_controller`` unless
    ``host_controller`` is false."""
    driver = DeviceDriver()
    nodes: list[Any] = [driver]
    try:
        if driver.cfg.settings.host_controller:
            from haptic_topology.nodes.lmi_controller import LmiController
            nodes.append(LmiController(driver.cfg.scenario, hosted=True))
        driver.start(nodes[1] if len(nodes) > 1 else None)
    except BaseException:
        for n in reversed(nodes):
            n.destroy_node()
        raise
    return nodes


def main(args: Sequence[str] | None = None) -> int:
    return run_main('device_driver', build, args, node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
