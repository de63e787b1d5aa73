"""``lmi_controller``: answers every device state with a command (eq. 14, or eq. 10).

A thin adapter over :class:`~haptic_topology.control.HapticController`:

* ``DeviceState`` k -> ``cycle(k, dt, x_h, xd_h, F_h)`` with ``dt`` the difference of the
  header stamps of this state and the previous answered one (the device's measured period);
  publishes the ``DeviceCommand`` for k and the ``HandInput`` for k (stamped with the state's
  stamp, which the VE integrates against);
* ``LmiUpdate`` -> ``update(snapshot)``: re-sync, replaying the inputs the VE has not seen.

Before the first LMI update there is no model of the VT: the answer is zero (MODE_ZERO) and
no hand input is sent. States flagged STATUS_WATCHDOG (device idle before engagement, or
commands stale) are answered with a zero wrench in the controller's mode (which engages an
idle device) and are not integrated. Live parameters: ``mode``, ``k_tc``, ``b_tc`` (checked in an
on-set-parameters callback); the others are read-only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from haptic_topology.control.controller import CycleOutput, HapticController
from haptic_topology.control.laws import ControlMode
from haptic_topology.errors import ConfigError
from haptic_topology.nodes import common
from haptic_topology.nodes.convert import (
    MessageError,
    command_msg,
    hand_msg,
    lmi_from_msg,
    state_from_msg,
)
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInput, LmiUpdate

MODES = ('penalty', 'acceleration_only')
#: Upper end of the live penalty gains' range (N/(m kg), N s/(m kg)).
GAIN_MAX = 1.0e5


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
        d = common.declare
        scenario_name = d(self, 'scenario', 'fig8', 'scenario name (config/scenarios) or YAML '
                          'path: linkage, gains, device inertia, LMI model')
        d(self, 'executor', 'events', 'executor of the process', choices=common.EXECUTORS)
        self.scenario = sc = load_scenario(scenario_name)
        mode = d(self, 'mode', sc.mode.label, 'control law: penalty (eq. 14) or '
                 'acceleration_only (eq. 10); live', read_only=False, choices=MODES)
        k_tc = d(self, 'k_tc', float(sc.gains.k_tc), 'penalty stiffness k_tc of eq. 13 '
                 '(N/(m kg)); live', read_only=False, lo=0.0, hi=GAIN_MAX)
        b_tc = d(self, 'b_tc', float(sc.gains.b_tc), 'penalty damping b_tc of eq. 13 '
                 '(N s/(m kg)); live', read_only=False, lo=0.0, hi=GAIN_MAX)
        self.max_dt = d(self, 'max_dt', 0.05, 'longest measured period used for one LMI step '
                        '(s); longer gaps (a paused device) are clipped', lo=1e-4, hi=1.0)
        for name, value in (('k_tc', k_tc), ('b_tc', b_tc)):
            reason = check_gain(name, value)
            if reason:
                raise ConfigError(f'lmi_controller: parameter {reason}')
        self.task = sc.linkage.task
        self.dof = sc.linkage.dof
        self.ctrl = HapticController(self.task, ControlMode.parse(mode),
                                     sc.gains.with_penalty(k_tc, b_tc), sc.device.mass,
                                     sc.device.christoffel, sc.lmi_model, sc.vt_coupling)
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
        self._last_seq = 0
        self._last_stamp = 0.0
        self._hand_seq = 0
        self._update_time: float | None = None
        self.updates = 0
        self.rejected = 0
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
        now = common.monotonic()
        try:
            seq, stamp, pose, twist, f_h = state_from_msg(msg, self.task)
        except MessageError as exc:
            self.rejected += 1
            self.get_logger().warn(f'state rejected: {exc}', throttle_duration_sec=1.0)
            return
        if msg.status & DeviceState.STATUS_WATCHDOG:
            # The device is not running the loop (idle before engagement, or stale commands):
            # answer "alive" (zero wrench; our mode once synced) and integrate nothing.
            mode = self.ctrl.mode if self.ctrl.lmi.synced else ControlMode.ZERO
            zero = np.zeros(self.task.dim)
            ready = CycleOutput(zero, zero, zero, pose, twist, 0, mode)
            self.cmd_pub.publish(command_msg(self._cmd, seq, self.get_clock().now().to_msg(),
                                             ready, math.inf))
            return
        if seq <= self._last_seq:
            return
        if self._last_seq:
            self.skipped += seq - self._last_seq - 1
        dt = stamp - self._last_stamp if self._last_seq else self.scenario.dt
        dt = min(max(dt, 0.0), self.max_dt)
        self._last_seq, self._last_stamp = seq, stamp
        self.stats.tick(now)
        out = self.ctrl.cycle(seq, dt, pose, twist, f_h)
        age = now - self._update_time if self._update_time is not None else math.inf
        self.cmd_pub.publish(command_msg(self._cmd, seq, self.get_clock().now().to_msg(),
                                         out, age))
        if out.mode is not ControlMode.ZERO:
            self._hand_seq += 1
            self.hand_pub.publish(hand_msg(self._hand, self._hand_seq, seq, msg.header.stamp,
                                           pose, twist, f_h, out.coupling))

    def _on_update(self, msg: LmiUpdate) -> None:
        try:
            snap = lmi_from_msg(msg, self.task, self.dof)
        except MessageError as exc:
            self.rejected += 1
            self.get_logger().warn(f'LMI update rejected: {exc}', throttle_duration_sec=1.0)
            return
        self.ctrl.update(snap)
        self._update_time = common.monotonic()
        self.updates += 1

    def _publish_diagnostics(self) -> None:
        values = self.stats.values()
        age = (common.monotonic() - self._update_time if self._update_time is not None
               else math.inf)
        values.update({
            'mode': self.ctrl.mode.label,
            'k_tc': repr(self.ctrl.gains.k_tc),
            'b_tc': repr(self.ctrl.gains.b_tc),
            'last_state_seq': str(self._last_seq),
            'skipped_states': str(self.skipped),
            'lmi_updates': str(self.updates),
            'update_age_ms': f'{1e3 * age:.2f}',
            'rejected_messages': str(self.rejected),
        })
        level, message = (0, 'ok') if age < 0.5 else (1, 'no recent LMI update')
        self.diag_pub.publish(common.diagnostics(self, 'lmi_controller: loop', values, level,
                                                 message))


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('lmi_controller', lambda: [LmiController()], args)


if __name__ == '__main__':
    raise SystemExit(main())
