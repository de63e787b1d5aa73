"""``device_driver``: the 1 kHz clock master of the haptic loop.

Each tick (a wall timer at ``rate_hz``; ``dt`` is the measured time since the previous tick,
because rclpy timers catch up after a late tick):

1. take the newest valid ``DeviceCommand`` (finite, ``task_dim`` entries, known mode;
   anything else is dropped and counted per reason) and clamp it to ``wrench_limit``;
2. watchdog (:class:`~haptic_topology.device.watchdog.CommandWatchdog`): when the oldest
   unanswered state is older than ``watchdog_timeout`` the output fades to the fallback
   (zero, or damping) over ``watchdog_ramp`` and back when commands return (status WATCHDOG
   while not the plain command);
3. clamp again (status SATURATED), ``write`` it to the backend and ``read`` the device ``dt``
   later (before the first engaged command: ``idle``);
4. publish ``DeviceState`` with the next sequence number, stamped with the tick time; its
   ``applied_wrench`` is what was written, finite and within ``wrench_limit`` by
   construction.

Engagement: until a command with a mode other than MODE_ZERO arrives (and ``min_subscribers``
see the state topic) the device idles with zero output and publishes STATUS_WATCHDOG |
STATUS_IDLE; the
first tick after engagement publishes the resting state with status OK (the run's first
state, t = 0 of the offline simulation), and from then on every tick steps the backend.

Loop health on ``/diagnostics`` (1 Hz): tick rate and period percentiles, overruns, the
fraction of cycles answered in time (the command for state k arrived before tick k+1),
round trip (command arrival - publication of the state it answers) p50/p99 over the run,
command age, watchdog trips and fade scale, rejected commands per reason, saturated cycles,
largest applied wrench per axis against the limit.

A restarted driver starts again at seq 1 (idle until the controller re-engages it); the
controller notices the seq going backwards (see ``lmi_controller``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import yaml
from rclpy.node import Node

from haptic_topology.control.laws import ControlMode
from haptic_topology.device.backend import BackendConfig, DeviceBackend, create_backend
from haptic_topology.device.maglev import DeviceStatus, saturate
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig, WatchdogFallback
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.nodes import common, node_params
from haptic_topology.nodes.convert import (
    MessageError,
    RejectCounter,
    command_from_msg,
    state_msg,
)
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState

#: Round-trip samples kept for the run's percentiles (10 min at 1 kHz).
_RTT_KEEP = 600_000


class DeviceDriver(Node):
    """Steps the device backend at ``rate_hz`` and applies the newest controller command."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('device_driver', **kwargs)
        spec = node_params.DEVICE_DRIVER

        def d(name: str) -> Any:
            return common.declare_spec(self, spec[name])

        scenario_name = d('scenario')
        common.declare_process_params(self, spec)
        backend_name = d('backend')
        options_text = d('backend_options')
        self.rate_hz = d('rate_hz')
        wd_timeout = d('watchdog_timeout')
        wd_ramp = d('watchdog_ramp')
        wd_fallback = WatchdogFallback.parse(d('watchdog_fallback'))
        wd_damping = d('watchdog_damping')
        self.min_subscribers = d('min_subscribers')
        limit = d('wrench_limit')
        self.scenario = load_scenario(scenario_name)
        sc = self.scenario
        self.task = sc.linkage.task
        m = self.task.dim
        if list(limit) == [0.0]:
            self.limit = sc.device.wrench_limit.copy()
        else:
            arr = np.asarray(limit, dtype=float)
            if arr.shape != (m,) or not np.all(arr > 0.0) or not np.all(np.isfinite(arr)):
                raise ConfigError(f'device_driver: parameter wrench_limit: expected {m} '
                                  f'positive numbers, got {list(limit)}')
            self.limit = arr
        damping = np.asarray(wd_damping, dtype=float)
        if damping.size == 1:
            damping = np.full(m, float(damping[0]))
        if (damping.shape != (m,) or not np.all(np.isfinite(damping))
                or np.any(damping < 0.0)):
            raise ConfigError(f'device_driver: parameter watchdog_damping: expected one or {m}'
                              f' numbers >= 0, got {list(wd_damping)}')
        self.watchdog = CommandWatchdog(WatchdogConfig(wd_timeout, wd_ramp, wd_fallback,
                                                       damping), m)
        try:
            options = yaml.safe_load(options_text) if options_text.strip() else {}
        except yaml.YAMLError as exc:
            raise ConfigError(f'device_driver: parameter backend_options: not YAML ({exc})'
                              ) from None
        if not isinstance(options, dict):
            raise ConfigError('device_driver: parameter backend_options: expected a mapping, '
                              f'got {options_text!r}')
        x0 = LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset
        self.backend: DeviceBackend = create_backend(backend_name)
        self.backend_name = backend_name
        self.backend.configure(BackendConfig(sc.device, x0, dict(sc.user), options, sc.source))
        try:
            self.backend.activate()
        except DeviceError:
            self.backend.deactivate()
            raise
        self._active = True

        self.state_pub = self.create_publisher(DeviceState, common.TOPIC_STATE, common.QOS_LOOP)
        self.diag_pub = self.create_publisher(common.DiagnosticArray, common.TOPIC_DIAGNOSTICS,
                                              common.QOS_DIAGNOSTICS)
        self.create_subscription(DeviceCommand, common.TOPIC_COMMAND, self._on_command,
                                 common.QOS_LOOP)
        self._msg = DeviceState()
        self.seq = 0
        self.engaged_seq = 0
        self._started = False
        self._cmd: np.ndarray = np.zeros(m)
        self._cmd_seq = 0
        self._twist = np.zeros(m)
        self._publish_times = np.zeros(4096)        # monotonic publish time by seq % 4096
        self._rtt = np.zeros(_RTT_KEEP)
        self._rtt_n = 0
        self.answered = 0
        self.answered_previous = 0   # by a command from this cycle's or the previous state
        self.expected = 0
        self.rejected = RejectCounter()
        self.rejected_seq = 0
        self.saturated_cycles = 0
        self.max_applied = np.zeros(m)
        self._last_tick: float | None = None
        self.stats = common.LoopStats(1.0 / self.rate_hz)
        self.create_timer(1.0 / self.rate_hz, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f'backend {backend_name}, scenario {sc.name}, '
                               f'{self.rate_hz:.0f} Hz, limit {self.limit.tolist()}, '
                               f'watchdog {wd_timeout * 1e3:g} ms -> {wd_fallback.value} over '
                               f'{wd_ramp * 1e3:g} ms')

    # -- callbacks (thin: checks, bookkeeping, one backend call) -----------------------------
    def _on_command(self, msg: DeviceCommand) -> None:
        now = common.monotonic()
        try:
            state_seq, mode, wrench = command_from_msg(msg, self.task)
        except MessageError as exc:
            self.rejected.add(exc)
            self.get_logger().warn(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        if state_seq > self.seq or state_seq == 0:
            # Answers a state this driver never published (a controller of an earlier run of
            # this driver, or a bogus publisher): not an answer to anything.
            self.rejected_seq += 1
            return
        if state_seq >= self.seq - 4095:
            rtt = now - self._publish_times[state_seq % 4096]
            self._rtt[self._rtt_n % _RTT_KEEP] = rtt
            self._rtt_n += 1
        if state_seq <= self._cmd_seq:
            return  # older than what we hold
        if (self.engaged_seq == 0 and mode != ControlMode.ZERO
                and self.state_pub.get_subscription_count() >= self.min_subscribers):
            self.engaged_seq = state_seq
            self.get_logger().info(f'controller engaged at state {state_seq}')
        self._cmd = wrench
        self._cmd_seq = state_seq

    def _tick(self) -> None:
        now_ros = self.get_clock().now()
        now = common.monotonic()
        period = self.stats.tick(now)
        nominal = 1.0 / self.rate_hz
        dt = nominal if period is None else min(max(period, 0.0), 20.0 * nominal)
        status = DeviceStatus.OK
        u = np.zeros(self.task.dim)
        if not self.engaged_seq:
            # No controller yet: output held at zero; a simulation parks.
            reading = self.backend.idle(dt)
            status |= DeviceStatus.WATCHDOG | DeviceStatus.IDLE
        elif not self._started:
            # First state of the run: where the device rests when the controller engages.
            self._started = True
            reading = self.backend.idle(dt)
        else:
            self.expected += 1
            if self._cmd_seq == self.seq:
                self.answered += 1
            if self._cmd_seq >= self.seq - 1:
                self.answered_previous += 1
            # Clamp, fade towards the fallback if stale, clamp again (a damping fallback
            # could exceed the limit): nothing else reaches the backend.
            cmd, saturated = saturate(self._cmd, self.limit)
            # The fade advances by at most two nominal periods per tick, so one late tick
            # cannot step the output by more than 2 * limit * period / watchdog_ramp.
            u = self.watchdog.step(cmd, self.command_age(now), self._twist,
                                   min(dt, 2.0 * nominal))
            u, saturated_out = saturate(u, self.limit)
            if self.watchdog.active:
                status |= DeviceStatus.WATCHDOG
            if saturated or saturated_out:
                status |= DeviceStatus.SATURATED
                self.saturated_cycles += 1
            np.maximum(self.max_applied, np.abs(u), out=self.max_applied)
            self.backend.write(u)
            reading = self.backend.read(dt)
        self._twist = reading.twist
        self.seq += 1
        self._publish_times[self.seq % 4096] = now
        self.state_pub.publish(state_msg(self._msg, self.seq, now_ros.to_msg(), reading, u,
                                         int(status | reading.status)))

    def command_age(self, now: float) -> float:
        """Seconds since the oldest state without an answer was published (0 when the newest
        state is answered): how long the controller has been silent, not counting the
        driver's own late ticks."""
        if self._cmd_seq >= self.seq:
            return 0.0
        oldest = self._cmd_seq + 1
        if self.seq - oldest >= 4096:
            return math.inf
        return max(0.0, now - float(self._publish_times[oldest % 4096]))

    def loop_figures(self) -> dict[str, float]:
        """Answered fraction and round-trip percentiles (ms) over the run so far."""
        n = min(self._rtt_n, _RTT_KEEP)
        rtt = self._rtt[:n]
        return {
            'answered_fraction': self.answered / self.expected if self.expected else math.nan,
            'answered_or_previous_fraction': (self.answered_previous / self.expected
                                              if self.expected else math.nan),
            'round_trip_p50_ms': 1e3 * float(np.percentile(rtt, 50)) if n else math.nan,
            'round_trip_p99_ms': 1e3 * float(np.percentile(rtt, 99)) if n else math.nan,
            'round_trip_max_ms': 1e3 * float(rtt.max()) if n else math.nan,
        }

    def _publish_diagnostics(self) -> None:
        values = self.stats.values()
        figures = self.loop_figures()
        values.update({
            'backend': self.backend_name,
            'seq': str(self.seq),
            'engaged_seq': str(self.engaged_seq),
            'answered_in_time': str(self.answered),
            'answer_expected': str(self.expected),
            'answered_fraction': f'{figures["answered_fraction"]:.5f}',
            'answered_or_previous_fraction':
                f'{figures["answered_or_previous_fraction"]:.5f}',
            'round_trip_max_ms': f'{figures["round_trip_max_ms"]:.3f}',
            'round_trip_p50_ms': f'{figures["round_trip_p50_ms"]:.3f}',
            'round_trip_p99_ms': f'{figures["round_trip_p99_ms"]:.3f}',
            'command_age_cycles': str(self.seq - self._cmd_seq if self._cmd_seq else -1),
            'command_age_ms': f'{1e3 * self.command_age(common.monotonic()):.2f}',
            'rejected_commands': str(self.rejected.total + self.rejected_seq),
            **self.rejected.values(),
            'rejected_seq': str(self.rejected_seq),
            'watchdog_trips': str(self.watchdog.trips),
            'watchdog_cycles': str(self.watchdog.stale_cycles),
            'watchdog_scale': f'{self.watchdog.scale:.3f}',
            'saturated_cycles': str(self.saturated_cycles),
            'max_abs_applied': ' '.join(f'{v:.4g}' for v in self.max_applied),
            'wrench_limit': ' '.join(f'{v:.4g}' for v in self.limit),
        })
        if not self.engaged_seq:
            level, message = 1, 'idle: no controller engaged yet'
        elif self.watchdog.stale:
            level, message = 1, 'watchdog: commands stale, output faded to the fallback'
        elif self.watchdog.active:
            level, message = 1, 'watchdog: fading back in'
        else:
            level, message = 0, 'ok'

        self.diag_pub.publish(common.diagnostics(self, 'device_driver: loop', values, level,
                                                 message))

    def close(self) -> None:
        """Zero and release the device (called on shutdown)."""
        if self._active:
            self._active = False
            try:
                self.backend.write(np.zeros(self.task.dim))
            except DeviceError:
                pass
            self.backend.deactivate()
            figures = self.loop_figures()
            self.get_logger().info('loop: ' + json.dumps(
                {k: round(v, 5) for k, v in figures.items()}))


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('device_driver', lambda: [DeviceDriver()], args,
                           node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
