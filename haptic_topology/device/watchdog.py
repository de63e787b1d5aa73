"""Command watchdog of the device: fade to a safe output when commands stop, back when they return.

The device driver applies the controller's newest command ``u_c``. When no fresh command has
come for ``timeout`` seconds the output fades linearly to the fallback ``u_f`` (zero, or pure
damping ``-B xd`` of the device's own motion) over ``ramp_time`` seconds; when commands return
it fades back to the command over the same time, so neither direction is a step::

    u = u_f + s (u_c - u_f),   s in [0, 1],   s -> 1 while fresh, s -> 0 while stale,
    |s_k - s_{k-1}| <= dt_k / ramp_time

Bound (what the tests check): per cycle the output changes by at most
``|u_c - u_f| dt / ramp_time`` from the fade, plus ``s |delta u_c| + (1 - s) |delta u_f|`` from
the signals themselves. With the command clamped to the limit ``L`` first and the zero
fallback: ``L dt / ramp_time`` (20 N * 1 ms / 50 ms = 0.4 N for the scenarios' x axis).

Example: ``timeout = 0.005``, ``ramp_time = 0.05``, 1 ms cycles, a command of 10 N that stops:
the output stays 10 N for 5 ms, then falls by 0.2 N per cycle and is zero 50 ms later.

"Fresh" is measured by the caller as the *command age*: the time since the oldest device state
that has no answer yet was published (0 while the newest state is answered). A late tick of
the device itself therefore does not trip the watchdog; a controller that stops answering does.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from haptic_topology.errors import ConfigError


class WatchdogFallback(enum.Enum):
    """What the output fades to when commands go stale."""

    ZERO = 'zero'          # u_f = 0
    DAMPING = 'damping'    # u_f = -B xd (per axis), the device's own motion damped

    @classmethod
    def parse(cls, text: str) -> WatchdogFallback:
        try:
            return cls(text)
        except ValueError:
            raise ConfigError(f'watchdog fallback: expected one of '
                              f'{", ".join(f.value for f in cls)}, got {text!r}') from None


@dataclass(frozen=True)
class WatchdogConfig:
    """``timeout`` (s) without a fresh command before fading; ``ramp_time`` (s) of a full fade;
    ``fallback``; ``damping`` B per task axis (N s/m, N m s/rad) for the damping fallback."""

    timeout: float = 0.005
    ramp_time: float = 0.05
    fallback: WatchdogFallback = WatchdogFallback.ZERO
    damping: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        if not (np.isfinite(self.timeout) and self.timeout > 0.0):
            raise ConfigError(f'watchdog timeout must be > 0 s, got {self.timeout}')
        if not (np.isfinite(self.ramp_time) and self.ramp_time > 0.0):
            raise ConfigError(f'watchdog ramp_time must be > 0 s, got {self.ramp_time}')
        d = np.asarray(self.damping, dtype=float)
        if not np.all(np.isfinite(d)) or np.any(d < 0.0):
            raise ConfigError(f'watchdog damping must be finite and >= 0, got {d.tolist()}')


class CommandWatchdog:
    """The fade of the module doc; one :meth:`step` per device cycle (no allocation-free
    guarantees needed at m <= 6: a few small numpy operations)."""

    def __init__(self, config: WatchdogConfig, dim: int, scale: float = 1.0) -> None:
        damping = np.asarray(config.damping, dtype=float)
        if config.fallback is WatchdogFallback.DAMPING and damping.shape != (dim,):
            raise ConfigError(f'watchdog damping must have {dim} entries for the damping '
                              f'fallback, got {damping.tolist()}')
        self.config = config
        self.dim = dim
        self._damping = damping if damping.shape == (dim,) else np.zeros(dim)
        self.scale = float(np.clip(scale, 0.0, 1.0))
        self.stale = False
        self.trips = 0            # fresh -> stale transitions
        self.stale_cycles = 0

    @property
    def active(self) -> bool:
        """True while the output is not the plain command (stale, or fading either way)."""
        return self.stale or self.scale < 1.0

    def cut(self) -> None:
        """The caller wrote zero instead of this cycle's output (the device reported a fault):
        the fade starts again from the fallback, so once :meth:`step` runs again the output
        fades back to the command over ``ramp_time`` instead of stepping to it."""
        self.scale = 0.0

    def fallback(self, twist: np.ndarray) -> np.ndarray:
        if self.config.fallback is WatchdogFallback.DAMPING:
            tw = np.where(np.isfinite(twist), twist, 0.0)
            return -self._damping * tw
        return np.zeros(self.dim)

    def step(self, command: np.ndarray, command_age: float, twist: np.ndarray,
             dt: float) -> np.ndarray:
        """The output for this cycle: ``command`` (finite, already clamped) of age
        ``command_age`` (s), device ``twist``, ``dt`` (s) since the previous cycle. While the
        output is the plain command (fresh, fully faded in) it is ``command`` itself."""
        stale = not command_age <= self.config.timeout     # NaN age counts as stale
        if stale and not self.stale:
            self.trips += 1
        self.stale = stale
        if stale:
            self.stale_cycles += 1
        rate = max(dt, 0.0) / self.config.ramp_time
        self.scale = max(0.0, self.scale - rate) if stale else min(1.0, self.scale + rate)
        if self.scale >= 1.0:
            return command
        fb = self.fallback(twist)
        return fb + self.scale * (np.asarray(command, dtype=float) - fb)
