"""``device_driver``: the 1 kHz clock master of the haptic loop.

Each tick (a wall timer at ``rate_hz``; ``dt`` is the measured time since the previous tick,
because rclpy timers catch up after a late tick):

1. take the newest valid ``DeviceCommand`` (finite, ``task_dim`` entries); if it answers a
   state older than ``watchdog_cycles`` ticks, apply zero instead (status WATCHDOG);
2. clamp it to ``wrench_limit`` (status SATURATED), ``write`` it to the backend and ``read``
   the device ``dt`` later (before the first engaged command: ``idle``);
3. publish ``DeviceState`` with the next sequence number, stamped with the tick time.

Engagement: until a command with a mode other than MODE_ZERO arrives (and ``min_subscribers``
see the state topic) the device idles with zero output and publishes STATUS_WATCHDOG; the
first tick after engagement publishes the resting state with status OK (the run's first
state, t = 0 of the offline simulation), and from then on every tick steps the backend.

Loop health on ``/diagnostics`` (1 Hz): tick rate and period percentiles, overruns, the
fraction of cycles answered in time (the command for state k arrived before tick k+1),
round trip (command arrival - publication of the state it answers) p50/p99 over the run,
command age, rejected commands.
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
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.nodes import common
from haptic_topology.nodes.convert import MessageError, command_from_msg, state_msg
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState

#: Round-trip samples kept for the run's percentiles (10 min at 1 kHz).
_RTT_KEEP = 600_000


class DeviceDriver(Node):
    """Steps the device backend at ``rate_hz`` and applies the newest controller command."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('device_driver', **kwargs)
        d = common.declare
        scenario_name = d(self, 'scenario', 'fig8', 'scenario name (config/scenarios) or YAML '
                          'path: device model, limits, initial pose and simulated user')
        d(self, 'executor', 'events', 'executor of the process', choices=common.EXECUTORS)
        backend_name = d(self, 'backend', 'sim_maglev', 'device backend: sim_maglev, hardware,'
                         ' module:Class, or an entry point of haptic_topology.device_backends')
        options_text = d(self, 'backend_options', '', 'backend settings as a YAML/JSON mapping'
                         " (e.g. '{port: /dev/ttyUSB0}'); empty for none")
        self.rate_hz = d(self, 'rate_hz', 1000.0, 'device cycle rate (Hz)', lo=10.0, hi=10000.0)
        self.watchdog_cycles = d(self, 'watchdog_cycles', 50, 'zero the wrench when the '
                                 'newest command answers a state older than this many cycles',
                                 lo=1, hi=100000)
        self.min_subscribers = d(self, 'min_subscribers', 1, 'ignore commands (device idle) '
                                 'until this many subscribers see the state topic (e.g. 2 '
                                 'with a recorder)', lo=0, hi=100)
        limit = d(self, 'wrench_limit', [0.0], 'per-axis |u| limit (N, N m); [0.0] = the '
                  "scenario's device.wrench_limit")
        self.scenario = load_scenario(scenario_name)
        sc = self.scenario
        self.task = sc.linkage.task
        m = self.task.dim
        if list(limit) == [0.0]:
            self.limit = sc.device.wrench_limit.copy()
        else:
            arr = np.asarray(limit, dtype=float)
            if arr.shape != (m,) or not np.all(arr > 0.0):
                raise ConfigError(f'device_driver: parameter wrench_limit: expected {m} '
                                  f'positive numbers, got {list(limit)}')
            self.limit = arr
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
        self._publish_times = np.zeros(4096)        # monotonic publish time by seq % 4096
        self._rtt = np.zeros(_RTT_KEEP)
        self._rtt_n = 0
        self.answered = 0
        self.expected = 0
        self.rejected = 0
        self.watchdog_trips = 0
        self._last_tick: float | None = None
        self.stats = common.LoopStats(1.0 / self.rate_hz)
        self.create_timer(1.0 / self.rate_hz, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f'backend {backend_name}, scenario {sc.name}, '
                               f'{self.rate_hz:.0f} Hz')

    # -- callbacks (thin: checks, bookkeeping, one backend call) -----------------------------
    def _on_command(self, msg: DeviceCommand) -> None:
        now = common.monotonic()
        try:
            state_seq, mode, wrench = command_from_msg(msg, self.task)
        except MessageError as exc:
            self.rejected += 1
            self.get_logger().warn(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        if state_seq > self.seq or state_seq == 0:
            self.rejected += 1
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
            # No controller yet: output held at zero by the watchdog; a simulation parks.
            reading = self.backend.idle(dt)
            status |= DeviceStatus.WATCHDOG
        elif not self._started:
            # First state of the run: where the device rests when the controller engages.
            self._started = True
            reading = self.backend.idle(dt)
        else:
            self.expected += 1
            if self._cmd_seq == self.seq:
                self.answered += 1
            u = self._cmd
            if self.seq - self._cmd_seq > self.watchdog_cycles:
                u = np.zeros_like(u)
                status |= DeviceStatus.WATCHDOG
                self.watchdog_trips += 1
            u, saturated = saturate(u, self.limit)
            if saturated:
                status |= DeviceStatus.SATURATED
            self.backend.write(u)
            reading = self.backend.read(dt)
        self.seq += 1
        self._publish_times[self.seq % 4096] = now
        self.state_pub.publish(state_msg(self._msg, self.seq, now_ros.to_msg(), reading, u,
                                         int(status | reading.status)))

    def loop_figures(self) -> dict[str, float]:
        """Answered fraction and round-trip percentiles (ms) over the run so far."""
        n = min(self._rtt_n, _RTT_KEEP)
        rtt = self._rtt[:n]
        return {
            'answered_fraction': self.answered / self.expected if self.expected else math.nan,
            'round_trip_p50_ms': 1e3 * float(np.percentile(rtt, 50)) if n else math.nan,
            'round_trip_p99_ms': 1e3 * float(np.percentile(rtt, 99)) if n else math.nan,
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
            'round_trip_p50_ms': f'{figures["round_trip_p50_ms"]:.3f}',
            'round_trip_p99_ms': f'{figures["round_trip_p99_ms"]:.3f}',
            'command_age_cycles': str(self.seq - self._cmd_seq if self._cmd_seq else -1),
            'rejected_commands': str(self.rejected),
            'watchdog_cycles': str(self.watchdog_trips),
        })
        late = self.engaged_seq and self.seq - self._cmd_seq > self.watchdog_cycles
        level, message = (1, 'watchdog: commands stale') if late else (0, 'ok')
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
    return common.run_main('device_driver', lambda: [DeviceDriver()], args)


if __name__ == '__main__':
    raise SystemExit(main())
