"""Statistics of a periodic callback's periods, shared by the controller's port, the device
loops and the VE (no ROS; read by the nodes' diagnostics)."""

from __future__ import annotations

from collections import deque

import numpy as np


class LoopStats:
    """Periods of a periodic callback over a sliding window (default: the last second)."""

    def __init__(self, nominal_period: float, window: int = 1000) -> None:
        self.nominal = nominal_period
        self.periods: deque[float] = deque(maxlen=window)
        self.last: float | None = None
        self.count = 0
        self.overruns = 0

    def tick(self, now: float) -> float | None:
        """Record a tick at monotonic time ``now`` (s); return the measured period or None."""
        self.count += 1
        period = None if self.last is None else now - self.last
        self.last = now
        if period is not None:
            self.periods.append(period)
            if period > 1.5 * self.nominal:
                self.overruns += 1
        return period

    def values(self, prefix: str = '') -> dict[str, str]:
        """As diagnostics key/values. Any thread: the window is copied by one C call
        (``tuple`` of the deque, atomic under the GIL) while another thread may
        :meth:`tick` (the hosted controller's statistics are ticked by the publishing
        thread and read by the diagnostics timer)."""
        periods = tuple(self.periods)
        if not periods:
            return {f'{prefix}rate_hz': '0', f'{prefix}overruns': str(self.overruns)}
        p = np.array(periods, dtype=float)
        return {
            f'{prefix}rate_hz': f'{1.0 / float(p.mean()):.1f}',
            f'{prefix}period_p50_ms': f'{1e3 * float(np.percentile(p, 50)):.3f}',
            f'{prefix}period_p99_ms': f'{1e3 * float(np.percentile(p, 99)):.3f}',
            f'{prefix}period_max_ms': f'{1e3 * float(p.max()):.3f}',
            f'{prefix}overruns': str(self.overruns),
            f'{prefix}cycles': str(self.count),
        }


