"""``lmi_controller``: answers every device state with a command (eq. 14, or eq. 10).

A thin adapter over :class:`~haptic_topology.control.HapticController`:

* ``DeviceState`` k -> ``cycle(k, dt, x_h, xd_h, F_h)`` with ``dt`` the difference of the
  header stamps of this state and the previous answered one (the device's measured period);
  publishes the ``DeviceCommand`` for k and the ``HandInput`` for k (stamped with the state's
  stamp, which the VE integrates against);
* ``LmiUpdate`` -> ``update(snapshot)``: re-sync, replaying the inputs the VE has not seen.

Before the first LMI update there is no model of the VT: the answer is zero (MODE_ZERO) and
no hand input is sent. States flagged STATUS_IDLE (device not engaged yet) are answered with a
zero wrench in the controller's mode (which engages the device) and are not integrated; states
flagged only STATUS_WATCHDOG (the device fades a stale command) are part of the loop.

Faults (:class:`~haptic_topology.control.safety.SyncGuard`):

* stale LMI updates: the loop runs on the local model with the last constraint set; after
  ``degrade_after`` the force fades to zero over ``resync_ramp``; the first update after that
  is applied once the force is zero, and the force fades back in. ``DeviceCommand.update_age``
  and ``/diagnostics`` report the age;
* an update that disagrees with our model at the same state by more than would step the
  force by ``resync_max_jump`` (the VE lost inputs, or caught up on a backlog) is held the
  same way;
* a restarted ``ve_sim`` (its update seq goes backwards) places its VT at the hand on our
  first input; its updates are ignored until it has consumed one, then the same held
  re-sync applies;
* a restarted ``device_driver`` (its seq goes backwards): the loop seq carried to the LMI and
  the VE (``HandInput.state_seq``) continues (device seq + offset), and the force fades in;
* this controller restarted into a running loop (its first states are running but faded by
  the device's watchdog, no idle state seen): the force fades in.

Live parameters: ``mode``, ``k_tc``, ``b_tc`` (checked in an on-set-parameters callback); the
others are read-only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from haptic_topology.control.controller import CycleOutput, HapticController
from haptic_topology.control.laws import ControlMode
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.safety import ModelHealth, SyncGuard, SyncGuardConfig, scaled_wrench
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.errors import ConfigError
from haptic_topology.nodes import common, node_params
from haptic_topology.nodes.convert import (
    MessageError,
    RejectCounter,
    command_msg,
    hand_msg,
    lmi_from_msg,
    state_from_msg,
)
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInput, LmiUpdate

MODES = node_params.MODES
#: Loop states whose VT hand is kept for comparing updates (> the LMI's input history).
_VT_KEEP = 512
GAIN_MAX = node_params.GAIN_MAX


def check_gain(name: str, value: Any) -> str | None:
    """Why ``value`` is not an acceptable ``k_tc``/``b_tc``, or None if it is."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f'{name} must be a number, got {value!r}'
    if not math.isfinite(value):
        return f'{name} must be finite, got {value}'
    if value < 0.0:
        return f'{name} must be >= 0 (a negative penalty pushes off the manifold), got {value}'
    if value > GAIN_MAX:
        return f'{name} must be <= {GAIN_MAX:g}, got {value}'
    return None


class LmiController(Node):
    """The haptic-rate controller node."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('lmi_controller', **kwargs)
        spec = node_params.LMI_CONTROLLER

        def d(name: str, default: Any = None) -> Any:
            return common.declare_spec(self, spec[name], default)

        scenario_name = d('scenario')
        common.declare_process_params(self, spec)
        self.scenario = sc = load_scenario(scenario_name)
        mode = d('mode', sc.mode.label)
        k_tc = d('k_tc', float(sc.gains.k_tc))
        b_tc = d('b_tc', float(sc.gains.b_tc))
        self.max_dt = d('max_dt')
        try:
            guard_config = SyncGuardConfig(d('stale_after'), d('degrade_after'),
                                           d('resync_ramp'))
        except ConfigError as exc:
            raise ConfigError(f'lmi_controller: parameters: {exc}') from None
        for name, value in (('k_tc', k_tc), ('b_tc', b_tc)):
            reason = check_gain(name, value)
            if reason:
                raise ConfigError(f'lmi_controller: parameter {reason}')
        self.task = sc.linkage.task
        self.dof = sc.linkage.dof
        self.limit = sc.device.wrench_limit.copy()
        self.ctrl = HapticController(self.task, ControlMode.parse(mode),
                                     sc.gains.with_penalty(k_tc, b_tc), sc.device.mass,
                                     sc.device.christoffel, sc.lmi_model, sc.vt_coupling)
        self.guard = SyncGuard(guard_config, sc.dt)
        self.max_jump = d('resync_max_jump')
        m = self.task.dim
        # The LMI's VT hand (pose, twist) by loop seq, to compare an update with.
        self._vt_seq = np.zeros(_VT_KEEP, dtype=np.int64)
        self._vt = np.zeros((_VT_KEEP, 2, m))
        self.resync_jump_max = 0.0
        self.jumps_held = 0
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.cmd_pub = self.create_publisher(DeviceCommand, common.TOPIC_COMMAND,
                                             common.QOS_LOOP)
        self.hand_pub = self.create_publisher(HandInput, common.TOPIC_HAND, common.QOS_HAND)
        self.diag_pub = self.create_publisher(common.DiagnosticArray, common.TOPIC_DIAGNOSTICS,
                                              common.QOS_DIAGNOSTICS)
        self.create_subscription(DeviceState, common.TOPIC_STATE, self._on_state,
                                 common.QOS_LOOP)
        self.create_subscription(LmiUpdate, common.TOPIC_LMI, self._on_update, common.QOS_LMI)
        self._cmd = DeviceCommand()
        self._hand = HandInput()
        # Loop seq = device seq + offset; the offset grows when the device restarts, so the
        # LMI's and the VE's input numbering never goes backwards.
        self._last_seq = 0
        self._last_stamp = 0.0
        self._device_seq = 0
        self._seq_offset = 0
        self._running = False           # a non-idle state of this device session was seen
        self._saw_idle = False
        self.device_sessions = 1
        self._hand_seq = 0
        self._ve_seq: int | None = None
        self._ve_new_session = False
        self._pending: LmiSnapshot | None = None
        self._loop_time = 0.0          # newest state stamp (s): the guard's clock
        self._update_wall: float | None = None
        self._loop_wall = 0.0
        self.ve_restarts = 0
        self.updates = 0
        self.rejected = RejectCounter()
        self.skipped = 0
        self.stats = common.LoopStats(sc.dt)
        self.create_timer(1.0, self._publish_diagnostics)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate and apply live changes of mode, k_tc, b_tc (all or none)."""
        gains = self.ctrl.gains
        mode = self.ctrl.mode
        for p in params:
            if p.name in ('k_tc', 'b_tc'):
                reason = check_gain(p.name, p.value)
                if reason:
                    return SetParametersResult(successful=False, reason=reason)
                gains = (gains.with_penalty(float(p.value), gains.b_tc) if p.name == 'k_tc'
                         else gains.with_penalty(gains.k_tc, float(p.value)))
            elif p.name == 'mode':
                if p.value not in MODES:
                    return SetParametersResult(successful=False, reason=(
                        f'mode must be one of {", ".join(MODES)}, got {p.value!r}'))
                mode = ControlMode.parse(str(p.value))
        self.ctrl.gains = gains
        self.ctrl.mode = mode
        return SetParametersResult(successful=True)

    def _on_state(self, msg: DeviceState) -> None:
        wall = common.monotonic()
        try:
            seq, stamp, pose, twist, f_h = state_from_msg(msg, self.task)
        except MessageError as exc:
            self.rejected.add(exc)
            self.get_logger().warn(f'state rejected: {exc}', throttle_duration_sec=1.0)
            return
        # The guard runs on loop time (the device's stamps), so the controller is a function
        # of its inputs: a lock-step replay of a bag reproduces its commands.
        now = self._loop_time = max(self._loop_time, stamp)
        self._loop_wall = wall
        if seq < self._device_seq:
            self._new_device_session(seq)
        self._device_seq = seq
        if msg.status & DeviceState.STATUS_IDLE:
            # The device is not engaged (start-up, or a restarted driver): answer "alive"
            # (zero wrench; our mode once synced, which engages it) and integrate nothing.
            self._saw_idle = True
            mode = self.ctrl.mode if self.ctrl.lmi.synced else ControlMode.ZERO
            zero = np.zeros(self.task.dim)
            ready = CycleOutput(zero, zero, zero, pose, twist, 0, mode)
            self.cmd_pub.publish(command_msg(self._cmd, seq, self.get_clock().now().to_msg(),
                                             ready, math.inf))
            return
        loop_seq = seq + self._seq_offset
        if loop_seq <= self._last_seq:
            return
        if not self._running:
            self._running = True
            stale = bool(msg.status & DeviceState.STATUS_WATCHDOG)
            if self.device_sessions > 1 or (stale and not self._saw_idle):
                # Joined a loop that already runs (the device restarted, or this controller
                # did: the device's output is faded, nobody engaged it in front of us):
                # start from zero force and fade in. A state stream that begins with a
                # plain running state (a bag replayed from engagement on) is not a rejoin.
                self.guard.rejoin()
                self.get_logger().info(f'joined a running loop at device state {seq}: the '
                                       'force fades in')
        if self._last_seq and self._last_stamp:
            self.skipped += loop_seq - self._last_seq - 1
            dt = stamp - self._last_stamp
        else:
            dt = self.scenario.dt
        dt = min(max(dt, 0.0), self.max_dt)
        self._last_seq, self._last_stamp = loop_seq, stamp
        self.stats.tick(wall)
        scale = 1.0
        if self.ctrl.lmi.synced:
            scale, apply = self.guard.cycle(now)
            if apply and self._pending is not None:
                self._apply_update(self._pending)
                self._pending = None
        out = self.ctrl.cycle(loop_seq, dt, pose, twist, f_h)
        slot = loop_seq % _VT_KEEP
        self._vt_seq[slot] = loop_seq
        self._vt[slot, 0] = out.vt_pose
        self._vt[slot, 1] = out.vt_twist
        if scale < 1.0:
            out = replace(out, wrench=scaled_wrench(out.wrench, scale, self.limit))
        self.cmd_pub.publish(command_msg(self._cmd, seq, self.get_clock().now().to_msg(),
                                         out, self._update_age(wall)))
        if out.mode is not ControlMode.ZERO:
            self._hand_seq += 1
            self.hand_pub.publish(hand_msg(self._hand, self._hand_seq, loop_seq,
                                           msg.header.stamp, pose, twist, f_h, out.coupling))

    def _new_device_session(self, seq: int) -> None:
        """The device's seq went backwards: a restarted device_driver."""
        self.device_sessions += 1
        self._seq_offset = self._last_seq
        self._last_stamp = 0.0
        self._running = False
        self._saw_idle = False
        self.get_logger().warn(f'device restarted (state {seq} after {self._device_seq}); '
                               f'the loop seq continues after {self._last_seq}')

    def _on_update(self, msg: LmiUpdate) -> None:
        now = self._loop_time      # arrival, in loop time (the newest state's stamp)
        try:
            snap = lmi_from_msg(msg, self.task, self.dof)
        except MessageError as exc:
            self.rejected.add(exc)
            self.get_logger().warn(f'LMI update rejected: {exc}', throttle_duration_sec=1.0)
            return
        if self._ve_seq is not None and snap.seq < self._ve_seq:
            self.ve_restarts += 1
            self._ve_new_session = True
            self.get_logger().warn(f've_sim restarted (update {snap.seq}); re-sync at zero '
                                   'force once it has taken our hand input')
        self._ve_seq = snap.seq
        self.updates += 1
        if not self._loop_time:
            # No device state yet, so no loop time: sync (start-up); the guard starts
            # counting with the first update after the loop's first state.
            self._update_wall = common.monotonic()
            self._apply_update(snap)
            return
        restart = False
        if self._ve_new_session:
            if snap.hand_input_seq < 0:
                # The restarted VE has not placed its VT at the hand yet: nothing to sync to
                # (the model keeps ageing, the force fades out).
                return
            restart = True
            self._ve_new_session = False
        # How far the VE lags behind the loop: its update describes the VT after consuming
        # input hand_input_seq, i.e. at loop state hand_input_seq + 1.
        lag = (max(self._last_seq - snap.hand_input_seq - 1, 0) * self.scenario.dt
               if snap.hand_input_seq >= 0 and not restart else 0.0)
        if not restart and self.ctrl.lmi.synced and snap.hand_input_seq >= 0:
            jump = self._jump(snap)
            self.resync_jump_max = max(self.resync_jump_max, min(jump, 1e9))
            if jump > self.max_jump:
                # The VE and our model disagree (it lost inputs, or caught up on a backlog):
                # syncing now would step the force. Hold it until the force has faded.
                restart = True
                self.jumps_held += 1
        self._update_wall = common.monotonic()
        if self.guard.update_arrived(now, restart, lag):
            self._apply_update(snap)
            self._pending = None
        else:
            self._pending = snap

    def _update_age(self, wall: float) -> float:
        """``DeviceCommand.update_age``: seconds since the newest usable update arrived (inf
        before the first). The guard's model age also counts the update's lag."""
        return wall - self._update_wall if self._update_wall is not None else math.inf

    def _jump(self, snap: LmiSnapshot) -> float:
        """Estimated force step (N or N m, largest axis) of syncing to ``snap`` now: the
        update's VT hand against ours at the same time (our first cycle after its
        ``hand_input_seq``); inf when ours is no longer known."""
        # The VE consumed input s: its VT is at the time of our next cycle after s (states
        # we skipped were never inputs).
        for seq in range(snap.hand_input_seq + 1, min(snap.hand_input_seq + 64,
                                                      self._last_seq + 1)):
            slot = seq % _VT_KEEP
            if self._vt_seq[slot] == seq:
                break
        else:
            return math.inf
        g = self.ctrl.gains
        dx = np.abs(pose_difference(snap.hand_pose, self._vt[slot, 0], self.task))
        dv = np.abs(snap.hand_twist - self._vt[slot, 1])
        penalty = np.abs(self.ctrl.m_d @ self.ctrl.lmi.projector @ (g.k_tc * dx + g.b_tc * dv))
        step = g.k_pc * dx + g.b_pc * dv + penalty
        return float(step.max())

    def _apply_update(self, snap: LmiSnapshot) -> None:
        self.ctrl.update(snap)

    def _publish_diagnostics(self) -> None:
        # Loop time now: the newest state's stamp plus the wall time since it came.
        now = self._loop_time + (common.monotonic() - self._loop_wall if self._loop_wall
                                 else 0.0)
        values = self.stats.values()
        age = self.guard.age(now)
        health = self.guard.health(now)
        values.update({
            'mode': self.ctrl.mode.label,
            'k_tc': repr(self.ctrl.gains.k_tc),
            'b_tc': repr(self.ctrl.gains.b_tc),
            'last_state_seq': str(self._device_seq),
            'loop_seq': str(self._last_seq),
            'skipped_states': str(self.skipped),
            'lmi_updates': str(self.updates),
            'update_age_ms': f'{1e3 * self._update_age(common.monotonic()):.2f}',
            'model_age_ms': f'{1e3 * age:.2f}',
            'model': health.value,
            'force_scale': f'{self.guard.scale:.3f}',
            'degradations': str(self.guard.degradations),
            'resyncs_held': str(self.guard.resyncs_held),
            'resync_jumps_held': str(self.jumps_held),
            'resync_jump_max': f'{self.resync_jump_max:.4g}',
            've_restarts': str(self.ve_restarts),
            'device_sessions': str(self.device_sessions),
            'rejected_messages': str(self.rejected.total),
            **self.rejected.values(),
        })
        level, message = _HEALTH_MESSAGES[health]
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
