"""Absolute-deadline pacing of the device cycle (the 1 kHz loop thread), without ROS.

A :class:`DeadlinePacer` releases cycle ``k`` at its deadline

    d_k = t0 + k * period        (s, on the injected monotonic clock)

computed from the origin ``t0`` every time, never by adding periods up: a sleep that
overshoots, or the rounding of a sum, does not accumulate. After 10,000 cycles of 1 ms the
loop is at ``t0 + 10000 * 0.001`` (plus one wake-up latency), not 10,000 oversleeps later.

:meth:`DeadlinePacer.wait` is called at the start of every cycle (read -> update -> write
follows). It sleeps until ``d_k - spin_before`` with the injected ``sleep`` and busy-waits on
the clock for the last ``spin_before`` seconds (default 0: no busy-wait). A busy-wait holds
the GIL (other Python threads run only at the interpreter's switch interval), so keep it to a
fraction of the period.

**Overrun policy** (as Linux ``timerfd``, whose read returns at once with the number of
expirations): when ``wait`` is called at or after the next deadline ``d_k`` (the previous
cycle overran), it does not sleep. It releases, at once, the newest deadline that has passed,
``j = max{i : d_i <= now}``, and *skips* the deadlines ``d_k .. d_{j-1}``: no cycle runs for
them, there is no burst of catch-up cycles. ``missed = j - k`` of them are counted. A cycle
that starts late but before the following deadline misses nothing, and the next cycle is on
the grid again. ``max_missed_run`` is the longest run of consecutive skipped deadlines
(Franka's FCI stops a robot after 20 lost cycles in a row). It is not
``DeviceLoop.max_missed_run`` (:mod:`haptic_topology.device.loop`), which counts cycles that
ran without the controller's answer in time.

Example (checked by
``test/unit/device/test_core_pacing.py``): ``period = 1 ms``, ``t0 = 0``; cycle 0 is
released at 0 and its work takes 3.5 ms; ``wait()`` at 3.5 ms returns at once with index 3,
``missed = 2`` (the deadlines at 1 and 2 ms), ``dt = 3.5 ms``, ``late = 0.5 ms``; the next
``wait()`` sleeps until 4 ms.

Statistics (:meth:`DeadlinePacer.figures`): cycles, missed deadlines, the longest miss run,
the measured period (time between releases) and the wake-up lateness (how long after its
deadline a cycle was released, as cyclictest measures a timer's latency): p50/p99 over the
last ``window`` releases (ring buffers allocated once; the first release after
:meth:`~DeadlinePacer.start` has no period and is not counted), max over the pacer's life.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from haptic_topology.errors import ConfigError

#: Measured periods kept for the percentiles (1 min at 1 kHz).
PERIOD_WINDOW = 60_000


@dataclass(frozen=True, slots=True)
class PacerTick:
    """One released cycle: ``index`` k of its deadline ``t0 + k * period``; ``now`` (s, the
    pacer's clock) when it was released; ``dt`` (s) since the previous release (the nominal
    period for the first cycle after :meth:`DeadlinePacer.start`); ``missed``: deadlines
    skipped just before this one (see module doc); ``late`` (s): ``now - d_k``, >= 0."""

    index: int
    now: float
    dt: float
    missed: int
    late: float


@dataclass(frozen=True, slots=True)
class PacerFigures:
    """Pacing figures: ``cycles`` released, ``missed`` deadlines skipped in all,
    ``max_missed_run`` (consecutive skipped deadlines), measured period (s): ``period_p50``
    and ``period_p99`` over the last ``window`` periods, ``period_max`` over the run,
    ``period_mean`` over the window (NaN before two cycles); the wake-up lateness (s, a
    :class:`PacerTick`'s ``late``) ``late_p50`` and ``late_p99`` over the same releases,
    ``late_max`` over the run."""

    cycles: int
    missed: int
    max_missed_run: int
    period_p50: float
    period_p99: float
    period_max: float
    period_mean: float = math.nan
    late_p50: float = math.nan
    late_p99: float = math.nan
    late_max: float = math.nan

    def values(self, prefix: str = '') -> dict[str, str]:
        """As diagnostics key/values (periods and lateness in ms)."""
        return {
            f'{prefix}cycles': str(self.cycles),
            f'{prefix}missed_deadlines': str(self.missed),
            f'{prefix}max_consecutive_missed_deadlines': str(self.max_missed_run),
            f'{prefix}period_p50_ms': f'{1e3 * self.period_p50:.3f}',
            f'{prefix}period_p99_ms': f'{1e3 * self.period_p99:.3f}',
            f'{prefix}period_max_ms': f'{1e3 * self.period_max:.3f}',
            f'{prefix}wake_late_p50_ms': f'{1e3 * self.late_p50:.3f}',
            f'{prefix}wake_late_p99_ms': f'{1e3 * self.late_p99:.3f}',
            f'{prefix}wake_late_max_ms': f'{1e3 * self.late_max:.3f}',
        }


class DeadlinePacer:
    """Releases a periodic loop at absolute deadlines (see module doc).

    ``period`` (s, > 0); ``clock``: monotonic time in s (default :func:`time.monotonic`);
    ``sleep``: sleeps for s seconds (default :func:`time.sleep`); ``spin_before`` (s, in
    ``[0, period]``): busy-wait this long before each deadline instead of sleeping;
    ``window``: measured periods kept for the percentiles.

    Use from one thread (the loop thread); :meth:`figures` may be read from another (the
    counters are plain ints, the percentiles see the ring buffer as it is).
    """

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, spin_before: float = 0.0,
                 window: int = PERIOD_WINDOW) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ConfigError(f'period must be a finite number > 0 s, got {period}')
        if not (math.isfinite(spin_before) and 0.0 <= spin_before <= period):
            raise ConfigError(f'spin_before must be in [0, period = {period}] s, got '
                              f'{spin_before}')
        if window < 1:
            raise ConfigError(f'window must be >= 1 period, got {window}')
        self.period = period
        self.spin_before = spin_before
        self._clock = clock
        self._sleep = sleep
        self._t0: float | None = None
        self._index = -1
        self._last_now: float | None = None
        self._periods = np.zeros(window)
        self._late = np.zeros(window)       # the wake-up lateness, slot for slot
        self._n_periods = 0
        self.period_max = math.nan
        self.late_max = math.nan
        self.cycles = 0
        self.missed = 0
        self.max_missed_run = 0

    @property
    def t0(self) -> float | None:
        """The origin of the deadline grid (s), None before :meth:`start`."""
        return self._t0

    @property
    def index(self) -> int:
        """Index of the newest released cycle (-1 before the first of this grid)."""
        return self._index

    def deadline(self, k: int) -> float:
        """Deadline of cycle ``k`` (s): ``t0 + k * period``."""
        if self._t0 is None:
            raise RuntimeError('deadline() before start()')
        return self._t0 + k * self.period

    def next_deadline(self) -> float:
        """The deadline (s) of the cycle :meth:`wait` releases next, unless the loop overruns
        it (the end of the gap between two cycles)."""
        return self.deadline(self._index + 1)

    def start(self, t0: float | None = None) -> None:
        """Begin a deadline grid at ``t0`` (s; default now): the next :meth:`wait` releases
        cycle 0 at ``t0``. Counters and statistics carry on; no period is measured across
        the restart. The first :meth:`wait` calls this when it has not been called."""
        self._t0 = self._clock() if t0 is None else float(t0)
        self._index = -1
        self._last_now = None

    def wait(self) -> PacerTick:
        """Sleep (then busy-wait) until the next deadline and release the cycle; after an
        overrun, release the newest passed deadline at once (see module doc)."""
        if self._t0 is None:
            self.start()
        k = self._index + 1
        d = self.deadline(k)
        now = self._clock()
        if now < d:
            wake = d - self.spin_before
            while now < wake:
                self._sleep(wake - now)
                now = self._clock()
            while now < d:          # the busy-wait (or a sleep that returned early)
                now = self._clock()
        j = k
        if now >= self.deadline(k + 1):
            j = k + max(1, int((now - d) // self.period))
            # Settle the rounding of the division against the deadline formula itself.
            while self.deadline(j + 1) <= now:
                j += 1
            while j > k and self.deadline(j) > now:
                j -= 1
        missed = j - k
        late = now - self.deadline(j)
        if self._last_now is None:
            dt = self.period
        else:
            dt = now - self._last_now
            slot = self._n_periods % self._periods.size
            self._periods[slot] = dt
            self._late[slot] = late
            self._n_periods += 1
            self.period_max = dt if math.isnan(self.period_max) else max(self.period_max, dt)
            self.late_max = late if math.isnan(self.late_max) else max(self.late_max, late)
        self._index = j
        self._last_now = now
        self.cycles += 1
        self.missed += missed
        self.max_missed_run = max(self.max_missed_run, missed)
        return PacerTick(j, now, dt, missed, late)

    def release(self, now: float) -> PacerTick:
        """Release a cycle at ``now`` (s, the pacer's clock) without waiting: the device's
        own servo loop is the clock (:attr:`DeviceBackend.drives_loop
        <haptic_topology.device.backend.DeviceBackend.drives_loop>`), so the grid follows
        it: the cycle is due one period after the previous release. A release ``dt`` after
        the previous one counts ``dt / period``, rounded half up, less one, as missed periods
        (servo ticks the loop did not get) and is ``late`` by what ``dt`` exceeds the periods
        it spans; periods and lateness go into the same statistics as :meth:`wait`'s."""
        if self._last_now is None:
            self._t0, self._index = now, -1
            dt, missed, late = self.period, 0, 0.0
        else:
            dt = now - self._last_now
            missed = max(0, int(dt / self.period + 0.5) - 1)
            late = max(0.0, dt - (missed + 1) * self.period)
            slot = self._n_periods % self._periods.size
            self._periods[slot] = dt
            self._late[slot] = late
            self._n_periods += 1
            self.period_max = dt if math.isnan(self.period_max) else max(self.period_max, dt)
            self.late_max = late if math.isnan(self.late_max) else max(self.late_max, late)
        self._index += 1 + missed
        self._last_now = now
        self.cycles += 1
        self.missed += missed
        self.max_missed_run = max(self.max_missed_run, missed)
        return PacerTick(self._index, now, dt, missed, late)

    @property
    def periods(self) -> tuple[np.ndarray, int]:
        """The measured-period buffer (s, a ring of the newest) and how many it has held."""
        return self._periods, self._n_periods

    @property
    def lateness(self) -> np.ndarray:
        """The wake-up lateness buffer (s), slot for slot with the period buffer of
        :attr:`periods` (and counted by it)."""
        return self._late

    def use_period_buffer(self, buf: np.ndarray, late: np.ndarray | None = None) -> None:
        """Keep the measured periods in ``buf`` and the wake-up lateness in ``late`` (None:
        a buffer of this pacer's own), both float64 of the window's size; e.g. shared memory
        that another process reads, so the loop never sorts them itself."""
        late = np.zeros_like(self._late) if late is None else late
        for name, b in (('period', buf), ('lateness', late)):
            if b.shape != self._periods.shape or b.dtype != np.float64:
                raise ConfigError(f'{name} buffer must be {self._periods.size} float64, got '
                                  f'{b.shape} {b.dtype}')
        buf[:] = 0.0
        late[:] = 0.0
        self._periods, self._late, self._n_periods = buf, late, 0

    def figures(self, percentiles: bool = True) -> PacerFigures:
        """The pacing figures so far (see :class:`PacerFigures`; ``percentiles=False``: NaN
        for p50 and p99, which sort the window: milliseconds for a minute of periods)."""
        n = min(self._n_periods, self._periods.size)
        p = self._periods[:n]
        p50 = p99 = l50 = l99 = math.nan
        if n and percentiles:
            p50, p99 = (float(v) for v in np.percentile(p, [50, 99]))
            l50, l99 = (float(v) for v in np.percentile(self._late[:n], [50, 99]))
        return PacerFigures(self.cycles, self.missed, self.max_missed_run, p50, p99,
                            self.period_max, float(p.mean()) if n else math.nan, l50, l99,
                            self.late_max)


