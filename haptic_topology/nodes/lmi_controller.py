"""``lmi_controller``: answers every device state with a command (eq. 14, or eq. 10).

ROS I/O only; the loop policy is :class:`~haptic_topology.control.loop.ControllerLoop` (LMI,
law, sync guard, device/VE session tracking, re-sync force-jump check), run through a
:class:`~haptic_topology.control.port.ControllerPort` (hand batches, lock-step hold, figures):

* ``DeviceState`` -> ``on_state`` -> ``DeviceCommand``, and the hand input for the VE into a
  :class:`~haptic_topology.control.batch.HandBatcher`: one ``HandInputs`` message per VE
  update period (the scenario's ``lmi.update_period``), published when the input's seq
  completes the period, the schedule of the VE's updates; a steady-clock timer (every update
  period, at least 10 ms) flushes samples whose oldest is two update periods old (the end of
  a run, a stalled device), which changes no result: the VE takes the samples one by one;
* ``LmiUpdate`` -> ``on_update``; with the wall clock, while device states come, in the gap
  after the next command is sent rather than on arrival
  (:class:`~haptic_topology.control.port.UpdateGap`: taking an update holds the executor for
  0.5-1 ms), unless ``ack_updates`` is set (someone waits for each update to be taken);
  ``updates_deferred`` in ``/diagnostics`` counts them;
* lock-step (``clock: lockstep``): a state that comes before the LMI update the offline
  simulation applies at that step is held until the update has come (at most
  ``lockstep_wait`` wall seconds, then a warning and the answer from the local model).

Hosted (``device_driver`` with ``host_controller``, the default layout): the driver's loop
thread calls the same :class:`ControllerLoop` through a
:class:`~haptic_topology.device.hosted.HostedCycle`; this node then takes no ``DeviceState``
from DDS, offers each LMI update to the cycle (applied by the loop thread at its next step)
and the driver's outbox thread publishes, with :meth:`LmiController.send`, the commands and
hand inputs the loop computed (:class:`~haptic_topology.nodes.hosting.HostedLoop`). Live
parameter changes are handed to the loop thread. Lock-step waiting is then the loop
thread's (``lockstep_wait`` the same).

Live parameters: ``mode``, ``k_tc``, ``b_tc`` (checked in an on-set-parameters callback); the
others are read-only. ``DeviceCommand.update_age`` and ``/diagnostics`` report the age of the
newest update (wall seconds since it arrived); ``hand_batches_sent`` counts the
``HandInputs`` messages (``hand_batches_partial`` of them flushed by the timer).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import UInt64

from haptic_topology import vocabulary as vocab
from haptic_topology.config import node_params
from haptic_topology.config.resolve import resolve_lmi_controller, zwidth_warning
from haptic_topology.config.settings import LmiControllerSettings, scenario_defaults
from haptic_topology.control.admission import UpdateAdmission
from haptic_topology.control.batch import HandBatch
from haptic_topology.control.loop import StateSample
from haptic_topology.control.port import ControllerPort, Outgoing, UpdateGap, live_change
from haptic_topology.device.loop_process import LoopProcess
from haptic_topology.device.runner import LoopHandle
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model.frames import DEVICE_BASE
from haptic_topology.nodes import wire
from haptic_topology.nodes.convert import (
    CONTROLLER_ID,
    GraphFilter,
    MessageError,
    RejectCounter,
    lmi_from_msg,
    stamp_ns,
    state_from_msg,
)
from haptic_topology.nodes.diagnostics import (
    PublisherWatch,
    diagnostics,
    log_notices,
    matched,
    monotonic,
)
from haptic_topology.nodes.parameters import declare_settings, declare_spec
from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, QOS_LMI, hand_inputs_qos, loop_qos
from haptic_topology.nodes.runtime import run_main
from haptic_topology.sim.lockstep import build_controller_loop
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate


class LmiController(Node):
    """The haptic-rate controller node."""

    def __init__(self, scenario: Scenario | None = None, hosted: bool = False,
                 **kwargs: Any) -> None:
        super().__init__('lmi_controller', **kwargs)
        name = declare_spec(self, node_params.LMI_CONTROLLER['scenario'])
        sc = scenario or load_scenario(name)
        s = declare_settings(self, LmiControllerSettings,
                                    scenario_defaults(LmiControllerSettings, sc))
        self.cfg = c = resolve_lmi_controller(s, sc)
        for line in zwidth_warning(c):          # outside the map: warn, not refuse
            self.get_logger().warn(line)
        lockstep = c.clock is vocab.Clock.LOCKSTEP
        self.loop = build_controller_loop(sc, c.mode, c.guard, c.max_dt, c.resync_max_jump,
                                          sc.update_period if lockstep else None, c.gains,
                                          c.passivity)
        self.port = ControllerPort(self.loop, sc.update_period, sc.linkage.task.dim, sc.dt,
                                   lockstep, c.lockstep_wait)
        self.flush_period = self.port.flush_period
        self.task, self.dof = sc.linkage.task, sc.lmi_dof
        self.penalty_direction = sc.linkage.constraints.penalty_direction
        self.add_on_set_parameters_callback(self._on_set_parameters)
        qos = loop_qos(c.clock)
        self.cmd_pub = self.create_publisher(DeviceCommand, vocab.TOPIC_COMMAND, qos)
        self.hand_pub = self.create_publisher(HandInputs, vocab.TOPIC_HAND_INPUTS,
                                              hand_inputs_qos(c.clock))
        self.diag_pub = self.create_publisher(DiagnosticArray, vocab.TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        lmi_sub = self.create_subscription(LmiUpdate, vocab.TOPIC_LMI, self._on_update, QOS_LMI)
        self._endpoints = {vocab.TOPIC_LMI: lmi_sub, vocab.TOPIC_COMMAND: self.cmd_pub,
                           vocab.TOPIC_HAND_INPUTS: self.hand_pub}
        self.hosted = hosted
        self.host: LoopHandle | None = None   # the driver's loop, once attached
        self.ack_pub = (self.create_publisher(UInt64, vocab.TOPIC_LMI_ACK, QOS_LMI)
                        if s.ack_updates else None)
        self.graph = GraphFilter(s.graph_id)
        # device-side quantities, published as serialized bytes (nodes.wire)
        self._hand = wire.hand_inputs_writer(DEVICE_BASE, self.graph.wire)
        self.command_wire = wire.command_writer(DEVICE_BASE, self.graph.wire)
        self.rejected = RejectCounter()
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        # who publishes its inputs in the graph (the driver's states: separate layout only)
        inputs = {vocab.TOPIC_LMI: ('ve_sim',),
                  **({} if hosted else {vocab.TOPIC_STATE: ('device_driver',)})}
        self.input_publishers = PublisherWatch(self, inputs, self._publish_diagnostics)
        # A closed chain's updates are reduced (q local): no model to check them against.
        self.admission = UpdateAdmission(None if sc.linkage.loops else LinkageDynamics(
            sc.linkage), self.input_publishers.gates[vocab.TOPIC_LMI])
        # separate layout, wall clock, no one waiting for acks: updates in the gap after an
        # answer (control.port.UpdateGap)
        self.gap: UpdateGap | None = (None if hosted or lockstep or s.ack_updates
                                      else UpdateGap())
        if hosted:
            self.process_sched_priority = 0       # the driver's loop thread has its own
            return
        self._endpoints[vocab.TOPIC_STATE] = self.create_subscription(
            DeviceState, vocab.TOPIC_STATE, self._on_state, qos)
        self.create_timer(self.flush_period, self.flush_hand, clock=steady)
        if lockstep:
            self.create_timer(0.01, self._check_wait, clock=steady)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate and apply live changes of mode, k_tc, b_tc (all or none)."""
        ctrl = self.loop.ctrl
        change = live_change(ctrl.gains, ctrl.mode, ((p.name, p.value) for p in params))
        if isinstance(change, str):
            return SetParametersResult(successful=False, reason=change)

        if self.host is not None:
            self.host.change_law(*change)     # between two cycles of the loop
        if self.host is None or isinstance(self.host, LoopProcess):
            ctrl.gains, ctrl.mode = change    # (a loop process: this node's copy follows)
        return SetParametersResult(successful=True)

    # -- hosted --------------------------------------------------------------------------------
    def attach(self, runner: LoopHandle) -> None:
        """Hosted: the driver's loop thread now runs :attr:`loop` (see module doc)."""
        self.host = runner

    # -- separate ------------------------------------------------------------------------------
    def _on_state(self, msg: DeviceState) -> None:
        if not (self.graph.own(msg, vocab.TOPIC_STATE)
                and self.input_publishers.admits(vocab.TOPIC_STATE, self.rejected)):
            return None
        try:
            seq, stamp, pose, twist, f_h, status = state_from_msg(msg, self.task)
        except MessageError as exc:
            return self._reject('state', exc)
        self.send(self.port.on_state(StateSample(seq, stamp, pose, twist, f_h, status),
                                      stamp_ns(msg.header.stamp), monotonic()))
        return self._take_updates(self.gap.answered() if self.gap else [])

    def _check_wait(self) -> None:
        self.send(self.port.check_wait(monotonic()))

    def send(self, out: Outgoing | None, stamp_ns: int | None = None) -> None:
        """Publish the command (stamped ``stamp_ns``, default now) and a completed hand
        batch."""
        if out is not None:
            ns = self.get_clock().now().nanoseconds if stamp_ns is None else stamp_ns
            self.cmd_pub.publish(wire.command_cdr(self.command_wire, out.answer.state_seq, ns,
                                             out.answer.out, out.update_age,
                                             update_seq=out.answer.update_seq))
            if out.batch is not None:
                self.publish_hand(out.batch)
        log_notices(self, self.loop.notices)

    def publish_hand(self, batch: HandBatch) -> None:
        self.admission.sent(int(batch.seq[-1]))     # before the VE can answer it
        self.hand_pub.publish(wire.hand_inputs_cdr(self._hand, batch))

    def flush_hand(self) -> None:
        """Steady timer (hosted: the outbox thread): the pending hand samples once the
        oldest is two periods old."""
        batch = self.port.flush(monotonic())
        if batch is not None:
            self.publish_hand(batch)
        self._take_updates(self.gap.due(monotonic(), self.port.state_time) if self.gap else [])

    def _on_update(self, msg: LmiUpdate) -> None:
        self._take_updates(self.gap.arrived(msg, monotonic(), self.port.state_time)
                           if self.gap else [msg])

    def _take_updates(self, msgs: list[LmiUpdate]) -> None:
        for msg in msgs:
            self._take_update(msg)

    def _take_update(self, msg: LmiUpdate) -> None:
        if not self.graph.own(msg, vocab.TOPIC_LMI):
            return
        try:
            snap = lmi_from_msg(msg, self.task, self.dof, self.penalty_direction)
            self.admission.admit(snap)
        except MessageError as exc:
            self._reject('LMI update', exc)
            snap = None
        out = None
        if snap is not None and self.host is not None:
            self.host.offer_update(snap)      # the loop applies it
        if snap is not None:
            out = self.port.on_update(snap, monotonic(), self.host is None)
        if self.ack_pub is not None:
            self.ack_pub.publish(UInt64(data=int(msg.seq)))
        self.send(out)

    def _reject(self, what: str, exc: MessageError) -> None:
        self.rejected.add(exc)
        self.get_logger().warn(f'{what} rejected: {exc}', throttle_duration_sec=1.0)

    def _publish_diagnostics(self) -> None:
        now = monotonic()
        values = self.port.values(now)
        values.update({'clock': self.cfg.clock.value,
                       'layout': 'hosted' if self.hosted else 'separate',
                       'lockstep_timeouts': str(self.port.lockstep_timeouts + (
                           self.host.lockstep_timeouts if self.host else 0)),
                       f'sent {vocab.TOPIC_COMMAND}': str(self.port.commands),
                       f'sent {vocab.TOPIC_HAND_INPUTS}': str(self.port.batcher.batches),
                       'controller_id': str(CONTROLLER_ID),
                       'updates_deferred': str(self.gap.deferred if self.gap else 0),
                       'rejected_messages': str(self.rejected.total), **self.rejected.values(),
                       **self.graph.values(), **matched(self._endpoints)})
        level, message = self.port.health(now)
        if isinstance(self.host, LoopProcess):      # the loop's controller is the child's
            values.update(self.host.controller_values())
            level, message = self.host.controller_health() or (level, message)
        level, message = self.input_publishers.merge(values, level, message)
        self.diag_pub.publish(diagnostics(self, vocab.STATUS_CONTROLLER, values, level,
                                                 message))


def main(args: Sequence[str] | None = None) -> int:
    return run_main('lmi_controller', lambda: [LmiController()], args,
                           node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
