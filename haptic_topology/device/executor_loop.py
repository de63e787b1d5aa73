"""The device side of the *separate* layout: a :class:`~haptic_topology.device.loop.DeviceLoop`
stepped by executor
callbacks, without ROS.

In the separate layout (``device_driver`` with ``host_controller: false``) commands come from
an ``lmi_controller`` process over DDS and the device is ticked by the node's executor, not
by a loop thread (:mod:`haptic_topology.device.runner` is the hosted layout's). The node
converts messages and publishes; this object decides when the device ticks and with which
stamp:

* **wall** clock: :meth:`ExecutorLoop.wall_tick` on every timer tick (``period`` s); the
  device integrates over the measured period, clipped to ``[0, 20 * period]`` (a stalled
  executor does not make one huge step); the state is stamped with the node's clock;
* **lockstep**: simulated time. Before engagement :meth:`ExecutorLoop.idle_tick` (a steady
  timer) publishes idle states at stamp 0; once engaged, the device steps one period each
  time the command answering the newest state has arrived (:meth:`ExecutorLoop.on_command`
  returns the step's state, stamped ``run_index * period``, integer ns), so every node
  computes with the offline simulation's times. :meth:`ExecutorLoop.stalled` names a state
  left unanswered for ``warn_after`` wall seconds.

``run_duration`` (s, 0 = none): ``Emitted.ends_run`` marks the first state whose stamp is
that far from the run's first state (the node then deactivates).

Times ``now`` are monotonic seconds (the :class:`~haptic_topology.device.loop.DeviceLoop`'s clock);
stamps are integer ns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from haptic_topology.control.stats import LoopStats
from haptic_topology.device.loop import CommandVerdict, DeviceLoop, DeviceTick, period_ns


@dataclass(frozen=True, slots=True)
class Emitted:
    """A state to publish: the cycle ``tick``, its stamp ``stamp_ns`` (ns, loop time);
    ``clock``: publish ``/clock`` at the stamp first (lock-step steps); ``ends_run``: the
    run has lasted ``run_duration``."""

    tick: DeviceTick
    stamp_ns: int
    clock: bool = False
    ends_run: bool = False


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """What a command did: its :class:`~haptic_topology.device.loop.CommandVerdict` value, a log
    line (``info``: the
    controller engaged; ``warning``: another controller took over), and the lock-step step
    it released (or None)."""

    verdict: str
    info: str = ''
    warning: str = ''
    emitted: Emitted | None = None


class ExecutorLoop:
    """Steps ``loop`` on executor callbacks (see module doc); ``period`` (s), ``lockstep``,
    ``run_duration`` (s, 0 = none), ``warn_after`` (wall s)."""

    def __init__(self, loop: DeviceLoop, period: float, lockstep: bool,
                 run_duration: float = 0.0, warn_after: float = 5.0) -> None:
        self.loop = loop
        self.period = period
        self.lockstep = lockstep
        self._period_ns = period_ns(period)
        self._duration_ns = round(run_duration * 1e9)
        self.warn_after = warn_after
        self.stats = LoopStats(period)      # periods between ticks (monotonic s)
        self._run_start_ns = 0              # stamp of the run's first state (ns)
        self._state_time = 0.0              # when the newest state was emitted (s)

    def wall_tick(self, now: float, stamp_ns: int) -> Emitted:
        """Wall clock: the timer's tick at ``now``; the state is stamped ``stamp_ns``."""
        period = self.stats.tick(now)
        dt = self.period if period is None else min(max(period, 0.0), 20.0 * self.period)
        return self._emit(self.loop.tick(now, dt), stamp_ns, now)

    def idle_tick(self, now: float) -> Emitted | None:
        """Lock-step, before engagement: an idle state at simulated time 0 (None once
        engaged: the commands step the loop then)."""
        if self.loop.engaged:
            return None
        return self._emit(self.loop.tick(now, self.period), 0, now)

    def on_command(self, state_seq: int, mode: int, wrench: np.ndarray, now: float,
                   may_engage: bool, controller_id: int,
                   env_wrench: np.ndarray | None = None) -> CommandOutcome:
        """A command of ``controller_id`` answering ``state_seq`` arrived at ``now``
        (:meth:`~haptic_topology.device.loop.DeviceLoop.on_command`); in lock-step, an applied
        answer to the newest
        state steps the loop one period."""
        loop = self.loop
        was_engaged, followed = loop.engaged, loop.controller_id
        verdict = loop.on_command(state_seq, mode, wrench, now, may_engage, controller_id,
                                  env_wrench)
        info = warning = ''
        if loop.engaged and not was_engaged:
            info = f'controller {controller_id} engaged at state {state_seq}'
        elif loop.controller_id != followed:
            warning = f'controller {controller_id} took over from the silent {followed}'
        emitted = None
        if (self.lockstep and verdict == CommandVerdict.APPLIED and loop.engaged
                and loop.answered_current):
            self.stats.tick(now)
            tick = loop.tick(now, self.period)
            emitted = self._emit(tick, tick.run_index * self._period_ns, now, clock=True)
        return CommandOutcome(verdict, info, warning, emitted)

    def stalled(self, now: float) -> str:
        """Lock-step: a warning when the newest state has waited ``warn_after`` s for its
        answer ('' otherwise)."""
        loop = self.loop
        if not loop.engaged or loop.answered_current:
            return ''
        waited = now - self._state_time
        if waited < self.warn_after:
            return ''
        return (f'lock-step: no answer to state {loop.seq} for {waited:.1f} s (is '
                'lmi_controller running, and ve_sim?)')

    def _emit(self, tick: DeviceTick, stamp_ns: int, now: float,
              clock: bool = False) -> Emitted:
        self._state_time = now
        if tick.run_index == 0:
            self._run_start_ns = stamp_ns
        ends = (self._duration_ns > 0 and tick.run_index >= 0
                and stamp_ns - self._run_start_ns >= self._duration_ns)
        return Emitted(tick, stamp_ns, clock, ends)
