"""``ve_sim``: the full virtual-environment simulation (eq. 2) driven by the haptic loop.

A thin adapter over :class:`~haptic_topology.sim.ve.VirtualEnvironment` and its input policy
:class:`~haptic_topology.sim.ve.HandFeed`:

* each ``HandInputs`` batch (~100 Hz, one per update period of the controller) is checked
  as a whole where it enters (sizes n and n x task_dim, integer ranges, ascending seqs,
  finite, ``|wrench| <= max_hand_wrench``); a malformed batch is rejected entirely, counted
  per reason and logged with the field and the expected value;
* then each of its samples (state_seq k, stamped with device state k's time) goes through
  ``HandFeed.take`` on its own, as single inputs did: ``push_input`` with
  ``F_vt = F_h - F_pc`` (``vt_coupling``) or ``F_h``, the held input integrated up to this
  stamp; after every ``update_period``-th input an ``LmiUpdate`` is published (10 inputs of
  a 1 kHz loop: 100 Hz), also in the middle of a batch, carrying ``hand_input_seq`` so the
  controller replays what is newer; a seq going backwards is a restarted controller (the VE
  forgets the held input, the numbering starts afresh); a jump counts lost inputs;
* while no hand input comes (before the first one, or while the controller is stopped or
  restarting) the current state is published as an ``LmiUpdate`` at ``idle_update_rate_hz``
  so that a (new) controller can sync and close the loop. "No input" means none for the
  idle period and for three update periods (batches come once per update period);
* a restarted ``ve_sim`` (its first hand input is not the controller's first) places the
  VT's grasp point at the device pose (damped least squares from ``q0``, zero velocity
  relative to the device): nothing in the graph holds the old VE's joint state, and starting
  at ``q0`` would let the coordination spring yank the VT across the workspace. The
  controller re-syncs to it at zero force (see ``lmi_controller``);
* after each update driven by inputs, ``VtPath``: the VT hand after every input consumed
  since the previous one, so a recorded run has the VT at every device cycle;
* lock-step (``clock: lockstep``): no keep-alive updates once inputs flow (an update at
  another step than the offline simulation's would change the run); timers run on the steady
  clock, stamps are simulated time;
* the linkage as a robot (:mod:`haptic_topology.nodes.viz`): ``/robot_description`` once
  (transient local), and at ``viz_rate_hz`` ``/tf`` (every link, ``vt_hand``, ``device``),
  ``sensor_msgs/JointState`` named after the URDF's joints, markers (linkage, grasp point,
  device ghost, ``n_tc``, ``F_h``, ``u``, ``F_pc``, ``F_env``) and the standard mirrors
  (``PoseStamped``/``TwistStamped`` of the device and the VT hand, ``WrenchStamped`` of the
  applied, hand and coupling wrenches), by :class:`~haptic_topology.nodes.ve_viz.VeViz`.

Diagnostics: ``hand_inputs`` (samples taken), ``hand_batches`` (messages),
``lost_hand_inputs``, ``batch_*`` (arrival periods of the batches), ``update_*``,
``viz_device_states`` (device states taken for the viz, from
``haptic/device/state_sampled``), ``viz_rejected_states`` (malformed
ones skipped), ``rejected_messages`` (hand input batches rejected), of them
``rejected_hand_batches`` (those whose contents failed the checks, not the well-formed ones
the admission refuses as another sender's) and ``hand_rejection`` (the first of those's
reason, empty while none was: ``run`` ends on it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node

from haptic_topology.config import node_params
from haptic_topology.config.resolve import resolve_ve_sim
from haptic_topology.config.settings import VeSimSettings
from haptic_topology.control.admission import HandAdmission
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.stats import LoopStats
from haptic_topology.nodes.convert import (
    GraphFilter,
    MessageError,
    RejectCounter,
    stamp_seconds,
    vt_wrenches_from_hand_inputs,
)
from haptic_topology.nodes.diagnostics import PublisherWatch, diagnostics, matched, monotonic
from haptic_topology.nodes.parameters import declare_settings
from haptic_topology.nodes.qos import (
    QOS_DIAGNOSTICS,
    QOS_LMI,
    hand_inputs_qos,
)
from haptic_topology.nodes.runtime import run_main
from haptic_topology.nodes.ve_viz import VeViz
from haptic_topology.nodes.wire import lmi_cdr, lmi_writer, path_cdr, path_writer
from haptic_topology.sim.lockstep import initial_device_pose, virtual_environment
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.sim.ve import HandFeed
from haptic_topology.vocabulary import (
    STATUS_VE,
    TOPIC_DIAGNOSTICS,
    TOPIC_HAND_INPUTS,
    TOPIC_LMI,
    TOPIC_VT_PATH,
    Clock,
)
from haptic_topology_msgs.msg import HandInputs, LmiUpdate, VtPath

#: s, the shortest period of the silence check (path flush, idle keep-alive): at 1 kHz it
#: cost an idle VE a tenth of a core for nothing, as silence is at least an idle period or
#: three update periods long.
IDLE_CHECK_MIN_PERIOD = 0.01


class VeSim(Node):
    """The VE node (full dynamics at ``internal_step``, LMI updates at ~100 Hz)."""

    def __init__(self, scenario: Scenario | None = None, **kwargs: Any) -> None:
        super().__init__('ve_sim', **kwargs)
        s = declare_settings(self, VeSimSettings)
        self.cfg = c = resolve_ve_sim(s, scenario or load_scenario(s.scenario))
        self.scenario = sc = c.scenario
        self.lockstep = c.clock is Clock.LOCKSTEP
        self.update_period = c.update_period
        self.max_hand_wrench = c.max_hand_wrench
        self.task = sc.linkage.task
        self.ve = virtual_environment(sc)     # as `simulate` builds it (contacts included)
        self.dyn = self.ve.dyn
        self.graph = GraphFilter(s.graph_id)
        self.viz = VeViz(self, sc, c.frame_id, self.ve.q, self.graph)

        self.lmi_pub = self.create_publisher(LmiUpdate, TOPIC_LMI, QOS_LMI)
        self.path_pub = self.create_publisher(VtPath, TOPIC_VT_PATH, QOS_LMI)
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        hand_sub = self.create_subscription(HandInputs, TOPIC_HAND_INPUTS,
                                            self._on_hand, hand_inputs_qos(c.clock))
        self._endpoints = {TOPIC_HAND_INPUTS: hand_sub, TOPIC_LMI: self.lmi_pub,
                           TOPIC_VT_PATH: self.path_pub}
        # Both published as serialized bytes (nodes.wire): rclpy then converts no message
        # object (~40 us of the update's publish, live).
        self._lmi = lmi_writer(c.frame_id, self.graph.wire)
        self._path = path_writer(c.frame_id, self.graph.wire)
        self._update_seq = 0
        self.feed = HandFeed(self.ve, self.update_period)
        self.batches = 0
        self.rejected = RejectCounter()
        #: Batches of the graph whose contents failed the checks (sizes, ranges, finite,
        #: ``max_hand_wrench``), and the first one's reason (and when), for ``run`` to end on
        #: (``rejected_hand_batches``, ``hand_rejection`` in ``/diagnostics``). Not the
        #: well-formed batches the admission refuses (another sender's, proven so).
        self.bad_batches = 0
        self.first_rejection = ''
        self._last_publish = -math.inf
        self._last_input = -math.inf
        self._idle_period = c.idle_period
        # Inputs come in batches, one per update period: silence shorter than a few of
        # those is not "no input".
        self._silent_after = max(c.idle_period, 3.0 * sc.dt * self.update_period)
        self._last_snap: LmiSnapshot = self.ve.snapshot(seq=0)
        self.paths_sent = 0
        self.stats = LoopStats(sc.dt * self.update_period)
        self.update_stats = LoopStats(sc.dt * self.update_period)
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(max(min(self._idle_period, sc.dt * self.update_period),
                              IDLE_CHECK_MIN_PERIOD), self._publish_idle, clock=steady)
        self.create_timer(c.viz_period, self._publish_viz, clock=steady)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.input_publishers = PublisherWatch(self, {TOPIC_HAND_INPUTS: ('lmi_controller',)},
                                         self._publish_diagnostics)
        # lock-step: every input comes, the first where the device starts (as in simulate)
        self.admission = HandAdmission(self.task, self.input_publishers.gates[TOPIC_HAND_INPUTS],
                                       complete=self.lockstep,
                                       origin=initial_device_pose(sc) if self.lockstep else None)

    def _publish_update(self) -> None:
        self._last_snap = self.ve.snapshot(seq=self._update_seq)
        self._update_seq += 1
        now = monotonic()
        self._last_publish = now
        self.update_stats.tick(now)
        self.lmi_pub.publish(lmi_cdr(self._lmi, self._last_snap,
                                     self.get_clock().now().nanoseconds))

    def _publish_idle(self) -> None:
        """Keep-alive: the current state when no hand input (and no update) came for an idle
        period. While inputs flow, updates go out every ``update_period`` inputs only, as in
        the offline simulation."""
        now = monotonic()
        silent = now - self._last_input >= self._silent_after
        if silent:
            self._publish_path()    # the inputs since the last update, once they stop
        if self.lockstep and self.feed.t0 is not None:
            return
        if silent and now - self._last_publish >= self._idle_period:
            self._publish_update()

    def _on_hand(self, msg: HandInputs) -> None:
        if not self.graph.own(msg, TOPIC_HAND_INPUTS):
            return
        checked = False
        try:
            seqs, state_seqs, stamps, pose, twist, f_vt = vt_wrenches_from_hand_inputs(
                msg, self.task, self.scenario.vt_coupling, self.max_hand_wrench)
            checked = True
            self.admission.admit(seqs, state_seqs, stamps, pose, twist)
        except MessageError as exc:
            self.rejected.add(exc)
            if not checked:
                self.bad_batches += 1
                self.first_rejection = self.first_rejection or self._rejection(msg, exc)
            self.get_logger().warn(f'hand input batch rejected: {exc}',
                                   throttle_duration_sec=1.0)
            return
        self.batches += 1
        self._last_input = monotonic()
        self.stats.tick(self._last_input)
        feed = self.feed
        for i, seq in enumerate(seqs):
            update_due = feed.take(seq, state_seqs[i], stamps[i], pose[i], twist[i], f_vt[i])
            for text in feed.notices:
                self.get_logger().warn(text)
            feed.notices.clear()
            if update_due:
                self._publish_update()
                self._publish_path()
        self.viz.keep_samples(msg, pose[-1], twist[-1], self.ve.q)

    def _rejection(self, msg: HandInputs, exc: MessageError) -> str:
        """``exc``'s text, with the batch's time in the run (s from the first input taken)
        when its stamp can tell it."""
        t0 = self.feed.t0
        t = stamp_seconds(msg.header.stamp) - t0 if t0 is not None else math.nan
        return f'{exc} (at {t:.3f} s of the run)' if math.isfinite(t) and t >= 0.0 else str(exc)

    def _publish_path(self) -> None:
        path = self.ve.take_path()
        if not path:
            return
        self.path_pub.publish(path_cdr(self._path, self._update_seq - 1, self.task.dim, path,
                                       self.get_clock().now().nanoseconds))
        self.paths_sent += 1

    def _publish_diagnostics(self) -> None:
        feed = self.feed
        values = self.stats.values('batch_')
        values.update(self.update_stats.values('update_'))
        values.update({
            # The run's task: task_dim 3 alone is planar or spatial_point (the live view's
            # drift takes x, y or x, y, z by it).
            'task': self.task.value,
            'hand_inputs': str(feed.inputs),
            'hand_batches': str(self.batches),
            # What the bringup checks the bag against at the end of a run (exact, no
            # timing): batches taken, path samples not yet sent, paths sent.
            f'received {TOPIC_HAND_INPUTS}': str(self.batches),
            'path_pending': str(len(self.ve.path)),
            f'sent {TOPIC_VT_PATH}': str(self.paths_sent),
            'lost_hand_inputs': str(feed.lost),
            'hand_last_seq': str(feed.last_seq),
            'hand_input_seq': str(self.ve.hand_input_seq),
            'lmi_updates': str(self._update_seq),
            'controller_restarts': str(feed.controller_restarts),
            'rejected_messages': str(self.rejected.total),
            'rejected_hand_batches': str(self.bad_batches),
            'hand_rejection': self.first_rejection,
            **self.rejected.values(),
            **self.graph.values(),
            **self.input_publishers.values(),
            'kinetic_energy_j': f'{self.ve.kinetic_energy():.6g}',
            'held_capped': str(self.ve.held_capped),
            'viz_device_states': str(self.viz.device_states),
            'viz_rejected_states': str(self.viz.rejected_states),
            **matched(self._endpoints),
        })
        problem = None if self.ve.state_finite else 'VE state not finite'
        problem = problem or self.input_publishers.problem()
        self.diag_pub.publish(diagnostics(self, STATUS_VE, values, 2 if problem else 0,
                                          problem or 'ok'))

    def _publish_viz(self) -> None:
        self.viz.publish(self.ve.q, self.ve.dq, self._last_snap)

    def close(self) -> None:
        """Destroy the viz's device-state reader (called on shutdown)."""
        self.viz.close()


def main(args: Sequence[str] | None = None) -> int:
    return run_main('ve_sim', lambda: [VeSim()], args, node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
