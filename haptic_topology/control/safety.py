"""Force scale of the controller while its local model ages, re-syncs or (re)joins a loop.

The LMI keeps the haptic loop alive between updates of the full simulation. When updates stop
(``ve_sim`` slow, stopped or killed), the controller goes through three stages, by the age of
the newest update: the time since the device state it describes (its arrival time minus its
lag behind the loop, so a VE that catches up on a backlog of old inputs does not count as
fresh):

* ``FRESH`` (age <= ``stale_after``): normal operation.
* ``STALE`` (``stale_after`` < age <= ``degrade_after``): still the local model, with the last
  good constraint set (the LMI's directions are frozen at the last update, so no penalty is
  added beyond it); reported as a warning.
* ``DEGRADED`` (age > ``degrade_after``): the force fades to zero over ``ramp_time``.

A re-sync that may move the model's VT by a lot - the first update after the model degraded,
an update from a restarted ``ve_sim`` - is held (``PENDING``) until the force has faded to zero,
then applied, and the force fades back in. Joining a loop that already runs (a restarted
controller, a restarted device) also starts from zero force. So the model never jumps under
a non-zero force scale, and the output ``u = s * clip(u_law, -L, L)`` changes per answered
cycle by at most::

    L * cycle_time / ramp_time   (fade)   +   s * |delta clip(u_law)|   (the law's own change)

The fade term is the stated bound (20 N * 1 ms / 0.2 s = 0.1 N for the scenarios' x axis);
the second term is what an undisturbed loop does anyway. Keep ``degrade_after`` below the
LMI's input history (1024 cycles = 1.02 s at 1 kHz): then every update applied under a
non-zero force can be replayed completely. ``s`` moves by ``cycle_time /
ramp_time`` per answered cycle (counted, not timed, so the bound holds for any jitter).

Example: ``stale_after = 0.05``, ``degrade_after = 0.6``, ``ramp_time = 0.2``, 1 ms cycles,
updates stop at t = 0: stale from 50 ms, the force falls from 600 ms and is zero at 800 ms.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from haptic_topology.errors import ConfigError


class ModelHealth(enum.Enum):
    """Stage of the local model (see module doc)."""

    UNSYNCED = 'unsynced'
    FRESH = 'fresh'
    STALE = 'stale'
    DEGRADED = 'degraded'
    PENDING = 'pending'      # a re-sync waits for the force to fade out


@dataclass(frozen=True)
class SyncGuardConfig:
    """Times in seconds (see module doc)."""

    stale_after: float = 0.05
    degrade_after: float = 0.6
    ramp_time: float = 0.2

    def __post_init__(self) -> None:
        for name in ('stale_after', 'degrade_after', 'ramp_time'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f'{name} must be a positive number of seconds, got {v}')
        if self.degrade_after < self.stale_after:
            raise ConfigError(f'degrade_after ({self.degrade_after} s) must be >= stale_after '
                              f'({self.stale_after} s)')


class SyncGuard:
    """The stages and force scale of the module doc; pure (times passed in, in seconds)."""

    def __init__(self, config: SyncGuardConfig, cycle_time: float, scale: float = 1.0) -> None:
        if not (math.isfinite(cycle_time) and cycle_time > 0.0):
            raise ConfigError(f'cycle_time must be > 0 s, got {cycle_time}')
        self.config = config
        self.step_size = min(1.0, cycle_time / config.ramp_time)
        self.scale = float(np.clip(scale, 0.0, 1.0))
        self.last_arrival: float | None = None
        self.pending = False
        self._fading_out = False
        self.degradations = 0
        self.resyncs_held = 0

    # -- events ------------------------------------------------------------------------------
    def age(self, now: float) -> float:
        """Seconds since the newest update arrived (inf before the first)."""
        return math.inf if self.last_arrival is None else max(0.0, now - self.last_arrival)

    def update_arrived(self, now: float, restart: bool = False, lag: float = 0.0) -> bool:
        """An update arrived at ``now``, describing the loop ``lag`` seconds ago; ``restart``:
        it comes from a restarted simulation.

        Returns True if the caller should apply it now, False if it must hold it (the newest
        held one is applied when :meth:`cycle` says so).
        """
        first = self.last_arrival is None
        degraded = self.age(now) > self.config.degrade_after
        when = now - max(lag, 0.0)
        self.last_arrival = when if self.last_arrival is None else max(self.last_arrival, when)
        degraded = degraded or self.age(now) > self.config.degrade_after
        if first:
            return True
        if restart or degraded or self._fading_out or self.pending:
            if not self.pending:
                self.resyncs_held += 1
            self.pending = True
            return False
        return True

    def rejoin(self) -> None:
        """The loop was (re)joined mid-run (device restarted, controller restarted): the force
        starts from zero and fades in."""
        self.scale = 0.0

    # -- per cycle ---------------------------------------------------------------------------
    def health(self, now: float) -> ModelHealth:
        if self.last_arrival is None:
            return ModelHealth.UNSYNCED
        if self.pending:
            return ModelHealth.PENDING
        age = self.age(now)
        if age > self.config.degrade_after:
            return ModelHealth.DEGRADED
        if age > self.config.stale_after:
            return ModelHealth.STALE
        return ModelHealth.FRESH

    def cycle(self, now: float) -> tuple[float, bool]:
        """Advance the scale by one answered cycle; return ``(scale, apply_held_update)``.

        When ``apply_held_update`` is True the caller applies the newest held update now (the
        scale is 0) and the force fades back in from the next cycle on.
        """
        arrival = self.last_arrival
        if (self.scale >= 1.0 and not self.pending and arrival is not None
                and now - arrival <= self.config.degrade_after):
            # FRESH or STALE at full scale, nothing held (the steady state): what the
            # general path below returns then, without its lookups (it runs every cycle).
            self._fading_out = False
            return self.scale, False
        health = self.health(now)
        target_zero = health in (ModelHealth.DEGRADED, ModelHealth.PENDING)
        if target_zero and not self._fading_out and health is ModelHealth.DEGRADED:
            self.degradations += 1
        self._fading_out = target_zero
        if target_zero:
            self.scale = max(0.0, self.scale - self.step_size)
        else:
            self.scale = min(1.0, self.scale + self.step_size)
        apply = self.pending and self.scale <= 0.0
        if apply:
            self.pending = False
            self._fading_out = False
        return self.scale, apply


def scaled_wrench(wrench: np.ndarray, scale: float, limit: np.ndarray) -> np.ndarray:
    """``wrench`` unchanged at full scale, else ``scale * clip(wrench, -limit, limit)``.

    Clipping first makes the fade's step bounded by ``limit * step`` whatever the law asks for
    (the device clamps to the same limit anyway).
    """
    if scale >= 1.0:
        return wrench
    return scale * np.clip(wrench, -limit, limit)
