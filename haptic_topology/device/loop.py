"""Device side of the haptic loop: engagement, clamp -> watchdog -> clamp, loop statistics.

One :class:`DeviceLoop` per device. The offline simulation, the lock-step graph and the
real-time graph drive the same object (``device_driver`` only converts messages and keeps the
clock); nothing here knows about ROS or reads a clock itself: every time is passed in (s).

Per device cycle (:meth:`DeviceLoop.tick`):

1. before engagement (no command with a mode other than ZERO yet): the backend idles (zero
   output; a simulation parks) and the state is flagged ``WATCHDOG | IDLE``;
2. the first tick after engagement publishes the resting state (status OK): the run's first
   state, ``t = 0`` of the offline simulation;
3. from then on: clamp the newest command to ``limit``, fade it towards the fallback when it is
   stale (:class:`~haptic_topology.device.watchdog.CommandWatchdog`, by the *command age*: the
   time since the oldest unanswered state was published), clamp again (a damping fallback could
   exceed the limit), ``write`` it to the backend and ``read`` the device ``dt`` later.

So the applied wrench is finite and within ``limit`` by construction, whatever the commands
were. Commands enter through :meth:`DeviceLoop.on_command`, already checked for size and
finiteness by the caller (``nodes.convert``); a command that answers a state this loop never
published, or an older one than the command held, is not applied.

**Device faults.** While the newest reading of the backend carries ``DeviceStatus.FAULT``
(the device reports a fault, :mod:`haptic_topology.device.backend`), every cycle writes a zero
wrench whatever the command, and the state is flagged ``FAULT`` (from the reading) and
``WATCHDOG`` (the output is not the command); once a reading comes without the bit, the
output fades back to the command over the watchdog's ``ramp_time`` (``CommandWatchdog.cut``).
:meth:`DeviceLoop.health` is ERROR while the fault lasts, with the backend's
``fault_reason()``; ``device_faults`` counts its onsets and ``fault_cycles`` the cycles written
as zero because of it.

**Which controller.** Every command carries the id of the controller that sent it
(``DeviceCommand.controller_id``, drawn at random once per controller process; ``0`` in the
offline simulation and for a controller hosted in the driver's process, whose commands never
cross DDS). The loop follows one controller: the one whose command engaged the device. A
command with another id is rejected and counted (``foreign_commands``), whatever state it
answers, and never reaches the device, while that controller is *alive*: while a command
carrying its id that answers one of this loop's states arrived less than ``takeover_after``
seconds ago (default :data:`TAKEOVER_AFTER` = 0.5 s). Once it has been silent that long, the
first command of another id that would be applied (it answers a state newer than the command
held) is applied, and that id becomes the one followed (``controller_takeovers``): so a
restarted controller, which draws a new id, takes the device over from its killed
predecessor. By then the watchdog has long faded the output to its fallback
(``timeout + ramp_time`` = 55 ms with the shipped parameters), so the take-over fades the new
controller's output in like any recovery. The price of the rule: a foreign publisher can take
the device over when the engaged controller stalls for ``takeover_after`` (a stall that long
is a failure of its own: the output has been at the fallback for most of it). This is
identity, not authentication: any process on the domain can read the id from the command
topic and copy it (DDS security is the answer to that, see docs/safety.md).

Example (ids 7 and 9, ``takeover_after`` 0.5 s, states 1 to 4 published; the verdicts are
checked by a test)::

    loop.on_command(1, PENALTY, u, now=0.000, controller_id=7)  # 'applied', engages on 7
    loop.on_command(2, PENALTY, v, now=0.001, controller_id=9)  # 'foreign', 7 is alive
    loop.on_command(2, PENALTY, u, now=0.001, controller_id=7)  # 'applied'
    # 7 silent from 0.001 s on; at 0.501 s it has been silent 0.5 s:
    loop.on_command(3, PENALTY, v, now=0.501, controller_id=9)  # 'applied', 9 took over
    loop.on_command(4, PENALTY, u, now=0.502, controller_id=7)  # 'foreign' now
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from haptic_topology.device.backend import DeviceBackend, DeviceReading, activate_backend
from haptic_topology.device.maglev import saturate
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.vocabulary import ControlMode, DeviceStatus, device_status

#: Publish times kept for the command age and the round trip (states).
_KEEP = 4096
#: ``DeviceStatus.FAULT`` as a plain int: tested on every reading (an ``IntFlag`` operation
#: costs ~0.7 us, ``int(status) & _FAULT_BIT`` ~0.07 us).
_FAULT_BIT = int(DeviceStatus.FAULT)
_WATCHDOG_BIT = int(DeviceStatus.WATCHDOG)
_IDLE_BIT = int(DeviceStatus.IDLE)
_SATURATED_BIT = int(DeviceStatus.SATURATED)
#: Round-trip samples kept for the run's percentiles (10 min at 1 kHz).
RTT_KEEP = 600_000
#: ``device.compiled.max_abs_into``, imported by the first DeviceLoop (see its __init__).
_max_abs_into: Any = None
#: Default silence (s) of the followed controller after which another controller's command
#: may take the device over (see module doc): 100 watchdog timeouts, 10 fade ramps of the
#: shipped parameters, and shorter than a controller process needs to restart (2-4 s).
TAKEOVER_AFTER = 0.5


def period_ns(period: float) -> int:
    """A device period (s) in integer nanoseconds (the clock's unit)."""
    return int(round(period * 1e9))


def ns_to_seconds(ns: int) -> float:
    """Integer nanoseconds as seconds, computed exactly as from a ROS stamp
    (``sec + 1e-9 * nanosec``), so the offline simulation and the lock-step graph, whose
    messages carry such stamps, integrate over the same floating-point intervals."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return float(sec) + 1e-9 * float(nanosec)


class CommandVerdict:
    """What :meth:`DeviceLoop.on_command` did with a command (diagnostics count them)."""

    APPLIED = 'applied'
    OLD = 'old'                  # older than (or the same as) the command held
    UNKNOWN_STATE = 'unknown'    # answers a state this loop never published
    FOREIGN = 'foreign'          # from another controller than the one followed


class DeviceTick(NamedTuple):
    """One published device state: ``seq`` (from 1), ``run_index`` (0 at the first engaged
    state, -1 while idle), the backend's reading, the wrench written (N, N m) and status."""

    seq: int
    run_index: int
    reading: DeviceReading
    applied: np.ndarray
    status: DeviceStatus
    #: F_env (eqs. 10, 14) of the command applied this cycle, as its controller computed it
    #: (None: no command applied, or the command carried none).
    env_wrench: np.ndarray | None = None


class DeviceLoop:
    """Engagement, the clamp/watchdog/clamp pipeline and loop statistics of one device."""

    def activate(self) -> None:
        """Activate the configured backend; on failure the device is zeroed and released and
        :class:`~haptic_topology.errors.DeviceError` says why
        (:func:`~haptic_topology.device.backend.activate_backend`)."""
        activate_backend(self.backend, self.limit.size)

    def __init__(self, backend: DeviceBackend, limit: np.ndarray, watchdog: CommandWatchdog,
                 period: float, takeover_after: float = TAKEOVER_AFTER) -> None:
        """``limit`` (N, N m) per axis; ``period`` (s) nominal device period;
        ``takeover_after`` (s, > 0; ``inf``: never): silence of the followed controller after
        which another one may take over (module doc)."""
        limit = np.asarray(limit, dtype=float)
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f'period must be > 0 s, got {period}')
        if not takeover_after > 0.0:
            raise ValueError(f'takeover_after must be > 0 s, got {takeover_after}')
        self.backend = backend
        self.limit = limit
        self.watchdog = watchdog
        self.period = period
        m = limit.size
        self.seq = 0
        self.engaged_seq = 0          # the idle state whose answer engaged the device
        self.run_index = -1
        self._cmd = np.zeros(m)
        self._cmd_env: np.ndarray | None = None
        self._cmd_seq = 0
        self._twist = np.zeros(m)
        self._publish_times = np.zeros(_KEEP)
        self._rtt = np.zeros(RTT_KEEP)
        self._rtt_n = 0
        self._rtt_max = math.nan
        self.answered = 0             # the command for state k arrived before tick k+1
        self.answered_previous = 0    # ... or the one for state k-1
        self.expected = 0
        self.missed_run = 0           # consecutive cycles without their answer in time, now
        self.max_missed_run = 0       # ... the longest such run (Franka's FCI stops at 20)
        self.rejected_seq = 0
        self.takeover_after = float(takeover_after)
        self.controller_id = 0        # id of the controller followed (valid once engaged)
        self._heard = -math.inf       # when it last answered one of our states (s)
        self.foreign_commands = 0     # commands of other controllers, rejected
        self.takeovers = 0            # times another controller took over after silence
        self.saturated_cycles = 0
        self.max_applied = np.zeros(m)
        # Compiled (loaded with maglev.saturate's clamp at the first cycle anyway): numpy's
        # maximum of the absolute values costs three times as much per cycle.
        global _max_abs_into
        if _max_abs_into is None:
            from haptic_topology.device.compiled import max_abs_into as _max_abs_into
        self.fault_active = False     # the newest reading carries DeviceStatus.FAULT
        self.device_faults = 0        # onsets of such readings
        self.fault_cycles = 0         # engaged cycles written as zero because of a fault

    @property
    def engaged(self) -> bool:
        return self.engaged_seq > 0

    # -- commands ----------------------------------------------------------------------------
    def on_command(self, state_seq: int, mode: int, wrench: np.ndarray, now: float,
                   may_engage: bool = True, controller_id: int = 0,
                   env_wrench: np.ndarray | None = None) -> str:
        """Take a command of controller ``controller_id`` answering state ``state_seq`` that
        arrived at ``now`` (s, the clock of :meth:`tick`); ``may_engage``: whether a non-ZERO
        mode may engage the device now (e.g. enough subscribers see the state). Once engaged,
        only the followed controller's commands are taken (module doc). ``env_wrench``: the
        command's F_env, reported with the states it is applied in (never applied itself: it
        is part of ``wrench``). Returns a :class:`CommandVerdict` value."""
        other = self.engaged and controller_id != self.controller_id
        if other and now - self._heard < self.takeover_after:
            self.foreign_commands += 1
            return CommandVerdict.FOREIGN
        if state_seq > self.seq or state_seq < 1:
            self.rejected_seq += 1
            return CommandVerdict.UNKNOWN_STATE
        if not other:
            self._heard = now
        if state_seq > self.seq - _KEEP:
            rtt = now - self._publish_times[state_seq % _KEEP]
            self._rtt[self._rtt_n % RTT_KEEP] = rtt
            self._rtt_n += 1
            if not rtt <= self._rtt_max:
                self._rtt_max = rtt
        if state_seq <= self._cmd_seq:
            return CommandVerdict.OLD
        if other:                     # silent long enough: this controller takes over
            self.controller_id = controller_id
            self._heard = now
            self.takeovers += 1
        if not self.engaged and mode != ControlMode.ZERO and may_engage:
            self.engaged_seq = state_seq
            self.controller_id = controller_id
            self._heard = now
        self._cmd = wrench
        self._cmd_env = env_wrench
        self._cmd_seq = state_seq
        return CommandVerdict.APPLIED

    @property
    def rejected_commands(self) -> int:
        """Commands refused by the loop: answering no state of this loop, or foreign."""
        return self.rejected_seq + self.foreign_commands

    @property
    def answered_current(self) -> bool:
        """Whether the newest published state has its answer (lock-step steps on this)."""
        return self.seq > 0 and self._cmd_seq >= self.seq

    def command_age(self, now: float) -> float:
        """Seconds since the oldest state without an answer was published (0 when the newest
        state is answered): how long the controller has been silent, not counting the
        device's own late ticks."""
        if self._cmd_seq >= self.seq:
            return 0.0
        oldest = self._cmd_seq + 1
        if self.seq - oldest >= _KEEP:
            return math.inf
        return max(0.0, now - float(self._publish_times[oldest % _KEEP]))

    # -- cycle -------------------------------------------------------------------------------
    def tick(self, now: float, dt: float) -> DeviceTick:
        """One device cycle at ``now`` (s), ``dt`` (s) after the previous one; returns the
        state to publish (see module doc)."""
        status = 0                    # DeviceStatus bits as a plain int until the end
        env = None
        if not self.engaged:
            u = np.zeros(self.limit.size)
            reading = self.backend.idle(dt)
            status = _WATCHDOG_BIT | _IDLE_BIT
        elif self.run_index < 0:
            u = np.zeros(self.limit.size)
            self.run_index = 0
            reading = self.backend.idle(dt)
        else:
            self.run_index += 1
            self.expected += 1
            if self._cmd_seq == self.seq:
                self.answered += 1
                self.missed_run = 0
            else:
                self.missed_run += 1
                self.max_missed_run = max(self.max_missed_run, self.missed_run)
            if self._cmd_seq >= self.seq - 1:
                self.answered_previous += 1
            if self.fault_active:
                # The device reported a fault: u stays zero (no command is applied) and the
                # output fades back in once a reading comes without it (module doc).
                self.watchdog.cut()
                self.fault_cycles += 1
                u = np.zeros(self.limit.size)
                saturated = saturated_out = False
            else:
                cmd, saturated = saturate(self._cmd, self.limit)
                # The fade advances by at most two nominal periods per tick, so one late tick
                # cannot step the output by more than 2 * limit * period / ramp_time.
                u = self.watchdog.step(cmd, self.command_age(now), self._twist,
                                       min(dt, 2.0 * self.period))
                saturated_out = False
                if u is not cmd:      # faded: clamp again (cmd itself is clamped already)
                    u, saturated_out = saturate(u, self.limit)
                env = self._cmd_env
            if self.watchdog.active:
                status |= _WATCHDOG_BIT
            if saturated or saturated_out:
                status |= _SATURATED_BIT
                self.saturated_cycles += 1
            self.backend.write(u)
            u = self.backend.written(u)     # what the device got (a vendor's grasp gates it)
            _max_abs_into(u, self.max_applied)
            reading = self.backend.read(dt)
        fault = int(reading.status) & _FAULT_BIT != 0
        if fault and not self.fault_active:
            self.device_faults += 1
        self.fault_active = fault
        self._twist = reading.twist
        self.seq += 1
        self._publish_times[self.seq % _KEEP] = now
        return DeviceTick(self.seq, self.run_index if self.engaged else -1, reading, u,
                          device_status(status | int(reading.status)), env)

    # -- statistics --------------------------------------------------------------------------
    @property
    def round_trips(self) -> tuple[np.ndarray, int]:
        """The round-trip buffer (s, a ring of the newest answers) and how many it has held."""
        return self._rtt, self._rtt_n

    def use_round_trip_buffer(self, buf: np.ndarray) -> None:
        """Keep the round trips in ``buf`` (zeroed, :data:`RTT_KEEP` float64; e.g. shared
        memory that another process reads, so the loop never sorts them itself)."""
        if buf.shape != (RTT_KEEP,) or buf.dtype != np.float64:
            raise ValueError(f'round-trip buffer must be {RTT_KEEP} float64, got '
                             f'{buf.shape} {buf.dtype}')
        buf[:] = 0.0
        self._rtt, self._rtt_n = buf, 0

    def figures(self, percentiles: bool = True) -> dict[str, float]:
        """Answered fractions and round-trip percentiles (ms) over the run so far
        (``percentiles=False``: NaN for them; sorting the buffer takes milliseconds)."""
        n = min(self._rtt_n, RTT_KEEP)
        rtt = self._rtt[:n]
        exp = self.expected
        p50, p99 = ((1e3 * float(v) for v in np.percentile(rtt, [50, 99])) if n and percentiles
                    else (math.nan, math.nan))
        return {
            'answered_fraction': self.answered / exp if exp else math.nan,
            'answered_or_previous_fraction': self.answered_previous / exp if exp else math.nan,
            'round_trip_p50_ms': p50,
            'round_trip_p99_ms': p99,
            'round_trip_max_ms': 1e3 * self._rtt_max,
            'max_consecutive_missed': float(self.max_missed_run),
        }

    def values(self, now: float, percentiles: bool = True) -> dict[str, str]:
        """Loop figures as diagnostics key/values (``percentiles``: see :meth:`figures`)."""
        f = self.figures(percentiles)
        return {
            'seq': str(self.seq),
            'engaged_seq': str(self.engaged_seq),
            'answered_in_time': str(self.answered),
            'answer_expected': str(self.expected),
            'answered_fraction': f'{f["answered_fraction"]:.5f}',
            'answered_or_previous_fraction': f'{f["answered_or_previous_fraction"]:.5f}',
            'max_consecutive_missed': str(self.max_missed_run),
            'round_trip_max_ms': f'{f["round_trip_max_ms"]:.3f}',
            'round_trip_p50_ms': f'{f["round_trip_p50_ms"]:.3f}',
            'round_trip_p99_ms': f'{f["round_trip_p99_ms"]:.3f}',
            'command_age_cycles': str(self.seq - self._cmd_seq if self._cmd_seq else -1),
            'command_age_ms': f'{1e3 * self.command_age(now):.2f}',
            'rejected_seq': str(self.rejected_seq),
            'controller_id': str(self.controller_id),
            'foreign_commands': str(self.foreign_commands),
            'controller_takeovers': str(self.takeovers),
            'watchdog_trips': str(self.watchdog.trips),
            'watchdog_cycles': str(self.watchdog.stale_cycles),
            'watchdog_scale': f'{self.watchdog.scale:.3f}',
            'saturated_cycles': str(self.saturated_cycles),
            'device_fault': self.backend.fault_reason() if self.fault_active else '',
            'device_faults': str(self.device_faults),
            'fault_cycles': str(self.fault_cycles),
            'max_abs_applied': ' '.join(f'{v:.4g}' for v in self.max_applied),
            'wrench_limit': ' '.join(f'{v:.4g}' for v in self.limit),
        }

    def health(self) -> tuple[int, str]:
        """``(level, message)`` for diagnostics (0 OK, 1 WARN, 2 ERROR): ERROR while the device
        reports a fault (engaged or not), else WARN while idle or while the watchdog acts."""
        if self.fault_active:
            return 2, f'device fault: {self.backend.fault_reason()}'
        if not self.engaged:
            return 1, 'idle: no controller engaged yet'
        if self.watchdog.stale:
            return 1, 'watchdog: commands stale, output faded to the fallback'
        if self.watchdog.active:
            return 1, 'watchdog: fading back in'
        return 0, 'ok'


def hardware_id(backend: DeviceBackend | None, backend_name: str) -> str:
    """``DiagnosticStatus.hardware_id`` of the device side: the backend's
    :attr:`~haptic_topology.device.backend.DeviceBackend.hardware_id` (backend and device,
    e.g. ``'sim_maglev planar'``), or ``backend_name`` (the ``backend`` parameter) while no
    backend is created."""
    return backend.hardware_id if backend is not None else backend_name


def device_report(loop: DeviceLoop | None, now: float, fault: str, rejected: int,
                  layout_values: dict[str, str], percentiles: bool = True
                  ) -> tuple[int, str, dict[str, str]]:
    """The device side's diagnostics ``(level, message, values)``: ERROR with ``fault`` (a
    failed transition or loop), WARN while not configured (``loop`` None), else
    :meth:`DeviceLoop.health` (ERROR while the device reports a fault). ``rejected``: commands
    refused before the loop (malformed messages), added to the loop's own refusals;
    ``layout_values``: the layout's figures (measured period)."""
    level, message = (2, f'fault: {fault}') if fault else (1, 'not configured')
    values = {'rejected_commands': str(rejected)}
    if loop is not None:
        values.update(loop.values(now, percentiles))
        values.update(loop.backend.values())
        values['rejected_commands'] = str(rejected + loop.rejected_commands)
        values.update(layout_values)
        if not fault:
            level, message = loop.health()
    return level, message, values
