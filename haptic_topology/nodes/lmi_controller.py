"""``lmi_controller``: answers every device state with a command (eq. 14, or eq. 10).

ROS I/O only; the loop policy is :class:`~haptic_topology.control.loop.ControllerLoop` (LMI,
law, sync guard, device/VE session tracking, re-sync force-jump check):

* ``DeviceState`` -> ``on_state`` -> ``DeviceCommand``, and the hand input for the VE into a
  :class:`~haptic_topology.control.batch.HandBatcher`: one ``HandInputs`` message per VE
  update period (the scenario's ``lmi.update_period``), published when the input's seq
  completes the period, the schedule of the VE's updates; a steady-clock timer (every update
  period, at least 10 ms) flushes samples whose oldest is two update periods old (the end of
  a run, a stalled device), which changes no result: the VE takes the samples one by one;
* ``LmiUpdate`` -> ``on_update``;
* lock-step (``clock: lockstep``): a state that comes before the LMI update the offline
  simulation applies at that step is held until the update has come (at most
  ``lockstep_wait`` wall seconds, then a warning and the answer from the local model).

Hosted (``device_driver`` with ``host_controller``, the default layout): the driver's loop
thread calls the same :class:`ControllerLoop` through a
:class:`~haptic_topology.device.hosted.HostedCycle`; this node then takes no ``DeviceState``
from DDS, offers each LMI update to the cycle (applied by the loop thread at its next step)
and publishes, from the driver's outbox thread, the commands and hand inputs the loop
computed (:meth:`LmiController.observe`). Live parameter changes are handed to the loop
thread. Lock-step waiting is then the loop thread's (``lockstep_wait`` the same).

Live parameters: ``mode``, ``k_tc``, ``b_tc`` (checked in an on-set-parameters callback); the
others are read-only. ``DeviceCommand.update_age`` and ``/diagnostics`` report the age of the
newest update (wall seconds since it arrived); ``hand_batches_sent`` counts the
``HandInputs`` messages (``hand_batches_partial`` of them flushed by the timer).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import UInt64

from haptic_topology.control.batch import HandBatch, HandBatcher
from haptic_topology.control.laws import ControlMode
from haptic_topology.control.loop import Answer, ControllerLoop, StateSample
from haptic_topology.control.safety import ModelHealth
from haptic_topology.device.runner import LoopRunner, Published
from haptic_topology.nodes import common, node_params
from haptic_topology.nodes.convert import (
    CONTROLLER_ID,
    MessageError,
    RejectCounter,
    command_msg,
    hand_inputs_msg,
    lmi_from_msg,
    ns_to_stamp,
    stamp_ns,
    state_from_msg,
)
from haptic_topology.resolve import resolve_lmi_controller
from haptic_topology.settings import Clock, LmiControllerSettings, check_live, scenario_defaults
from haptic_topology.sim.lockstep import build_controller_loop
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate


class LmiController(Node):
    """The haptic-rate controller node."""

    def __init__(self, scenario: Scenario | None = None, hosted: bool = False,
                 **kwargs: Any) -> None:
        super().__init__('lmi_controller', **kwargs)
        name = common.declare_spec(self, node_params.LMI_CONTROLLER['scenario'])
        sc = scenario or load_scenario(name)
        s = common.declare_settings(self, LmiControllerSettings,
                                    scenario_defaults(LmiControllerSettings, sc))
        self.cfg = c = resolve_lmi_controller(s, sc)
        self.lockstep = c.clock is Clock.LOCKSTEP
        self.loop: ControllerLoop = build_controller_loop(
            sc, c.mode, c.guard, c.max_dt, c.resync_max_jump,
            sc.update_period if self.lockstep else None, c.gains)
        self.task, self.dof = sc.linkage.task, sc.linkage.dof
        self.penalty_direction = sc.linkage.constraints.penalty_direction
        self.add_on_set_parameters_callback(self._on_set_parameters)
        qos = common.loop_qos(c.clock)
        self.cmd_pub = self.create_publisher(DeviceCommand, common.TOPIC_COMMAND, qos)
        self.hand_pub = self.create_publisher(HandInputs, common.TOPIC_HAND_INPUTS,
                                              common.hand_inputs_qos(c.clock))
        self.diag_pub = self.create_publisher(common.DiagnosticArray, common.TOPIC_DIAGNOSTICS,
                                              common.QOS_DIAGNOSTICS)
        lmi_sub = self.create_subscription(LmiUpdate, common.TOPIC_LMI, self._on_update,
                                           common.QOS_LMI)
        self._endpoints = {common.TOPIC_LMI: lmi_sub, common.TOPIC_COMMAND: self.cmd_pub,
                           common.TOPIC_HAND_INPUTS: self.hand_pub}
        self.hosted = hosted
        self.host: LoopRunner | None = None     # the driver's loop, once attached
        if hosted:
            self.process_sched_priority = 0       # the driver's loop thread has its own
        else:
            self._endpoints[common.TOPIC_STATE] = self.create_subscription(
                DeviceState, common.TOPIC_STATE, self._on_state, qos)
        self.ack_pub = (self.create_publisher(UInt64, common.TOPIC_LMI_ACK, common.QOS_LMI)
                        if s.ack_updates else None)
        self._cmd, self._hand = DeviceCommand(), HandInputs()
        batch_period = sc.dt * sc.update_period     # s: one VE update period
        self.batcher = HandBatcher(sc.update_period, self.task.dim, 2.0 * batch_period)
        self._held: tuple[StateSample, Any, float] | None = None   # lock-step wait
        self._update_wall: float | None = None
        self._loop_wall = 0.0
        self.rejected = RejectCounter()
        self.lockstep_timeouts = 0
        self.commands_sent = 0
        self.stats = common.LoopStats(sc.dt)
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.flush_period = max(batch_period, 0.01)
        if not hosted:
            self.create_timer(self.flush_period, self.flush_hand, clock=steady)
            if self.lockstep:
                self.create_timer(0.01, self._check_wait, clock=steady)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate and apply live changes of mode, k_tc, b_tc (all or none)."""
        gains, mode = self.loop.ctrl.gains, self.loop.ctrl.mode
        for p in params:
            reason = check_live(p.name, p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
            if p.name == 'k_tc':
                gains = gains.with_penalty(float(p.value), gains.b_tc)
            elif p.name == 'b_tc':
                gains = gains.with_penalty(gains.k_tc, float(p.value))
            elif p.name == 'mode':
                mode = ControlMode.parse(str(p.value))

        def apply() -> None:
            self.loop.ctrl.gains, self.loop.ctrl.mode = gains, mode

        if self.host is not None:
            self.host.submit(apply)       # between two cycles of the loop thread
        else:
            apply()
        return SetParametersResult(successful=True)

    # -- hosted --------------------------------------------------------------------------------
    def attach(self, runner: LoopRunner) -> None:
        """Hosted: the driver's loop thread now runs :attr:`loop` (see module doc)."""
        self.host = runner

    def observe(self, entries: list[Published]) -> None:
        """Hosted, outbox thread: publish the commands and hand inputs of these cycles."""
        for e in entries:
            ans = e.step.answer
            if ans is None:
                continue
            if not e.step.tick.status & DeviceState.STATUS_IDLE:
                self.stats.tick(1e-9 * e.stamp_ns)
            self._publish_answer(ans, e.stamp_ns, ns_to_stamp(e.stamp_ns))
        self._loop_wall = common.monotonic()
        self._log_notices()

    def _on_state(self, msg: DeviceState) -> None:
        self._loop_wall = wall = common.monotonic()
        try:
            seq, stamp, pose, twist, f_h, status = state_from_msg(msg, self.task)
        except MessageError as exc:
            return self._reject('state', exc)
        sample = StateSample(seq, stamp, pose, twist, f_h, status)
        if self.lockstep and self.loop.waiting_for_update():
            self._held = (sample, msg.header.stamp, wall)
            return None
        self._answer(sample, msg.header.stamp)
        return None

    def _answer(self, sample: StateSample, stamp: Any) -> None:
        if not sample.status & DeviceState.STATUS_IDLE:
            self.stats.tick(common.monotonic())
        ans: Answer | None = self.loop.on_state(sample)
        self._log_notices()
        if ans is not None:
            self._publish_answer(ans, stamp_ns(stamp), self.get_clock().now().to_msg())

    def _publish_answer(self, ans: Answer, state_ns: int, cmd_stamp: Any) -> None:
        """The command (stamped ``cmd_stamp``) and the hand input of the state stamped
        ``state_ns`` (ns)."""
        age = (common.monotonic() - self._update_wall if self._update_wall is not None
               else math.inf)
        self.cmd_pub.publish(command_msg(self._cmd, ans.state_seq, cmd_stamp, ans.out, age))
        self.commands_sent += 1
        if ans.hand is not None:
            batch = self.batcher.add(ans.hand, state_ns, common.monotonic())
            if batch is not None:
                self._publish_hand(batch)

    def _publish_hand(self, batch: HandBatch) -> None:
        self.hand_pub.publish(hand_inputs_msg(self._hand, batch))

    def flush_hand(self) -> None:
        """Steady timer (hosted: the outbox thread): the pending hand samples once the
        oldest is two periods old."""
        batch = self.batcher.due(common.monotonic())
        if batch is not None:
            self._publish_hand(batch)

    def _on_update(self, msg: LmiUpdate) -> None:
        try:
            snap = lmi_from_msg(msg, self.task, self.dof, self.penalty_direction)
        except MessageError as exc:
            self._reject('LMI update', exc)
            snap = None
        if snap is not None:
            if self.host is None:
                self.loop.on_update(snap)
            else:       # the loop thread applies it at its next step
                self.host.cycle.offer_update(snap)
                if not self.host.running:
                    self.host.cycle.apply_updates()
            self._update_wall = common.monotonic()
            self._log_notices()
        if self.ack_pub is not None:
            self.ack_pub.publish(UInt64(data=int(msg.seq)))
        if snap is None:
            return None
        if self._held is not None and not self.loop.waiting_for_update():
            sample, stamp, _ = self._held
            self._held = None
            self._answer(sample, stamp)
        return None

    def _check_wait(self) -> None:
        """Lock-step: a held state waits at most ``lockstep_wait`` for its update."""
        if self._held is None:
            return
        sample, stamp, since = self._held
        if common.monotonic() - since < self.cfg.lockstep_wait:
            return
        self.lockstep_timeouts += 1
        self.get_logger().warn(f'lock-step: no LMI update for state {sample.seq} within '
                               f'{self.cfg.lockstep_wait:g} s (is ve_sim running?): answering '
                               'from the local model; the run no longer matches simulate')
        self._held = None
        self._answer(sample, stamp)

    def _reject(self, what: str, exc: MessageError) -> None:
        self.rejected.add(exc)
        self.get_logger().warn(f'{what} rejected: {exc}', throttle_duration_sec=1.0)

    def _log_notices(self) -> None:
        notices = self.loop.notices     # hosted: appended by the loop thread
        while notices:
            try:
                text = notices.pop(0)
            except IndexError:          # taken by the other thread meanwhile
                break
            self.get_logger().warn(text)

    def _publish_diagnostics(self) -> None:
        loop = self.loop
        # Loop time now: the newest state's stamp plus the wall time since it came.
        now = loop.loop_time + (common.monotonic() - self._loop_wall if self._loop_wall
                                else 0.0)
        values = self.stats.values()
        values.update(loop.values(now))
        age = (common.monotonic() - self._update_wall if self._update_wall is not None
               else math.inf)
        values.update({'update_age_ms': f'{1e3 * age:.2f}', 'clock': self.cfg.clock.value,
                       'layout': 'hosted' if self.hosted else 'separate',
                       'lockstep_timeouts': str(self.lockstep_timeouts + (
                           self.host.lockstep_timeouts if self.host else 0)),
                       'hand_batches_sent': str(self.batcher.batches),
                       'hand_batches_partial': str(self.batcher.partial),
                       f'sent {common.TOPIC_COMMAND}': str(self.commands_sent),
                       f'sent {common.TOPIC_HAND_INPUTS}': str(self.batcher.batches),
                       'hand_pending': str(self.batcher.pending),
                       'controller_id': str(CONTROLLER_ID),
                       'rejected_messages': str(self.rejected.total), **self.rejected.values(),
                       **common.matched(self._endpoints)})
        level, message = _HEALTH_MESSAGES[loop.guard.health(now)]
        self.diag_pub.publish(common.diagnostics(self, 'lmi_controller: loop', values, level,
                                                 message))


_HEALTH_MESSAGES = {
    ModelHealth.FRESH: (0, 'ok'),
    ModelHealth.UNSYNCED: (1, 'no LMI update yet'),
    ModelHealth.STALE: (1, 'LMI update stale: local model, last constraint set'),
    ModelHealth.DEGRADED: (1, 'LMI update too old: force faded to zero'),
    ModelHealth.PENDING: (1, 're-sync held until the force has faded out'),
}


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('lmi_controller', lambda: [LmiController()], args,
                           node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
