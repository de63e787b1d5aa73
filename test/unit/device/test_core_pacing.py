"""DeadlinePacer on a fake clock: absolute deadlines, the overrun policy, the busy-wait, figures.

Times are multiples of 2**-16 s with a period of 2**-10 s (0.977 ms), so every sum is exact in
floating point and the assertions are ``==``; one test runs the real 1 ms period.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from haptic_topology.device.pacing import DeadlinePacer, PacerFigures, PacerTick
from haptic_topology.errors import ConfigError

P = 2.0 ** -10          # the period (s)
S = 2.0 ** -16          # one step of the fake clock (s)


class FakeTime:
    """A monotonic clock that moves only when slept on or worked on; each read advances it by
    ``read_step`` (what a busy-wait sees); each sleep overshoots by ``oversleep``."""

    def __init__(self, t: float = 0.0, read_step: float = 0.0, oversleep: float = 0.0) -> None:
        self.t = t
        self.read_step = read_step
        self.oversleep = oversleep
        self.sleeps: list[float] = []
        self.reads = 0

    def clock(self) -> float:
        self.reads += 1
        now = self.t
        self.t += self.read_step
        return now

    def sleep(self, seconds: float) -> None:
        assert seconds > 0.0, seconds
        self.sleeps.append(seconds)
        self.t += seconds + self.oversleep

    def work(self, seconds: float) -> None:
        self.t += seconds


def pacer(ft: FakeTime, period: float = P, **kwargs: Any) -> DeadlinePacer:
    return DeadlinePacer(period, clock=ft.clock, sleep=ft.sleep, **kwargs)


def test_on_time_cycles_sleep_to_each_deadline() -> None:
    ft = FakeTime(t=5.0)
    p = pacer(ft)
    ticks = []
    for _ in range(5):
        ticks.append(p.wait())
        ft.work(P / 4)
    assert p.t0 == 5.0
    assert ticks == [PacerTick(0, 5.0, P, 0, 0.0)] + [
        PacerTick(k, 5.0 + k * P, P, 0, 0.0) for k in range(1, 5)]
    assert ft.sleeps == [3 * P / 4] * 4
    f = p.figures()
    assert f == PacerFigures(cycles=5, missed=0, max_missed_run=0, period_p50=P,
                             period_p99=P, period_max=P, period_mean=P, late_p50=0.0,
                             late_p99=0.0, late_max=0.0)


def test_module_doc_example_at_1ms() -> None:
    ft = FakeTime()
    p = pacer(ft, period=0.001)
    assert p.wait() == PacerTick(0, 0.0, 0.001, 0, 0.0)
    ft.work(0.0035)
    tick = p.wait()
    assert (tick.index, tick.missed, tick.now, tick.dt) == (3, 2, 0.0035, 0.0035)
    assert tick.late == pytest.approx(0.0005, abs=1e-15)
    assert ft.sleeps == []               # released at once: no sleep after an overrun
    tick = p.wait()
    assert (tick.index, tick.missed, tick.now) == (4, 0, 0.004)
    assert ft.sleeps == [pytest.approx(0.0005, abs=1e-15)]


def test_one_long_overrun_skips_the_passed_deadlines_and_counts_them() -> None:
    ft = FakeTime()
    p = pacer(ft)
    p.wait()
    p.wait()
    ft.work(3.5 * P)                    # cycle 1 runs until 4.5 P
    late = p.wait()
    assert late == PacerTick(4, 4.5 * P, 3.5 * P, 2, 0.5 * P)   # deadlines 2 and 3 skipped
    on_grid = p.wait()                  # no catch-up burst: the next deadline, 5 P
    assert on_grid == PacerTick(5, 5 * P, 0.5 * P, 0, 0.0)
    assert ft.sleeps == [P, 0.5 * P]
    f = p.figures()           # periods P, 3.5 P, 0.5 P
    assert (f.cycles, f.missed, f.max_missed_run, f.period_p50, f.period_max) == (
        4, 2, 2, P, 3.5 * P)
    assert f.period_p99 == pytest.approx(3.45 * P)


def test_a_late_start_within_the_period_misses_nothing() -> None:
    ft = FakeTime()
    p = pacer(ft)
    p.wait()
    ft.work(1.25 * P)
    assert p.wait() == PacerTick(1, 1.25 * P, 1.25 * P, 0, 0.25 * P)
    assert p.wait() == PacerTick(2, 2 * P, 0.75 * P, 0, 0.0)
    assert p.missed == 0


def test_drift_free_over_10000_cycles() -> None:
    # Every sleep overshoots by 2**-14 s (61 us); relative sleeps would end 10000 of them
    # (0.61 s) late. Absolute deadlines: each release is one overshoot after its deadline.
    ft = FakeTime(oversleep=4 * S)
    p = pacer(ft)
    for k in range(10_000):
        tick = p.wait()
        assert (tick.index, tick.missed) == (k, 0)
        assert tick.now == (k * P + 4 * S if k else 0.0)
        ft.work(8 * S)
    assert tick.now == 9999 * P + 4 * S
    assert p.figures().missed == 0 and p.figures().cycles == 10_000


def test_drift_free_at_1ms() -> None:
    ft = FakeTime(oversleep=3e-5)
    p = pacer(ft, period=0.001)
    lateness = []
    for k in range(10_000):
        tick = p.wait()
        assert (tick.index, tick.missed) == (k, 0)
        lateness.append(tick.late)
        ft.work(2e-4)
    # Each release one overshoot after its own deadline, the last one included.
    assert max(abs(v - 3e-5) for v in lateness[1:]) < 1e-12
    assert tick.now == pytest.approx(9.999 + 3e-5, abs=1e-12)
    f = p.figures()           # the releases after the first: each one overshoot late
    for late in (f.late_p50, f.late_p99, f.late_max):
        assert late == pytest.approx(3e-5, abs=1e-12)


def test_consecutive_miss_runs() -> None:
    ft = FakeTime()
    p = pacer(ft)
    works = [P / 4, 4.25 * P, P / 4, 2.5 * P, 0.0, 21 * P]
    ticks = []
    for w in works:
        ticks.append(p.wait())
        ft.work(w)
    ticks.append(p.wait())
    assert [(t.index, t.missed, t.late) for t in ticks] == [
        (0, 0, 0.0), (1, 0, 0.0), (5, 3, 0.25 * P), (6, 0, 0.0), (8, 1, 0.5 * P),
        (9, 0, 0.0), (30, 20, 0.0)]     # released exactly at a deadline: that one's cycle
    f = p.figures()
    assert (f.cycles, f.missed, f.max_missed_run) == (7, 24, 20)


def test_busy_wait_before_the_deadline() -> None:
    ft = FakeTime(read_step=S)          # P = 64 S; spin the last 16 S
    p = pacer(ft, spin_before=16 * S)
    p.start(0.0)
    assert p.wait() == PacerTick(0, 0.0, P, 0, 0.0)     # clock now at S
    reads = ft.reads
    tick = p.wait()
    # read at S, sleep to the spin start 48 S (t = 49 S), then read 49 S .. 64 S.
    assert ft.sleeps == [47 * S]
    assert ft.reads - reads == 1 + 16
    assert tick == PacerTick(1, P, P, 0, 0.0)
    # Without the busy-wait the sleep targets the deadline and the wake-up is late by a read.
    ft2 = FakeTime(read_step=S)
    p2 = pacer(ft2)
    p2.start(0.0)
    p2.wait()
    assert p2.wait() == PacerTick(1, P + S, P + S, 0, S)
    assert ft2.sleeps == [63 * S]


def test_start_sets_the_grid_and_no_period_spans_a_restart() -> None:
    ft = FakeTime()
    p = pacer(ft)
    p.start(2 * P)                      # a grid in the future: wait sleeps to its origin
    assert p.wait() == PacerTick(0, 2 * P, P, 0, 0.0)
    ft.work(100 * P)
    p.start()
    assert p.wait() == PacerTick(0, 102 * P, P, 0, 0.0)
    assert p.figures().cycles == 2 and math.isnan(p.figures().period_max)


def test_period_figures_use_a_bounded_window_and_the_run_max() -> None:
    ft = FakeTime()
    p = pacer(ft, window=4)
    p.wait()
    ft.work(2.5 * P)
    p.wait()                            # dt 2.5 P
    for _ in range(5):
        p.wait()                        # dt 0.5 P, then P x 4
    f = p.figures()
    assert (f.period_p50, f.period_p99, f.period_max) == (P, P, 2.5 * P)
    # The release 0.5 P after its deadline has left the window of lateness too; its max stays.
    assert (f.late_p50, f.late_p99, f.late_max) == (0.0, 0.0, 0.5 * P)
    assert f.values('pacer_') == {
        'pacer_cycles': '7', 'pacer_missed_deadlines': '1',
        'pacer_max_consecutive_missed_deadlines': '1',
        'pacer_period_p50_ms': f'{1e3 * P:.3f}', 'pacer_period_p99_ms': f'{1e3 * P:.3f}',
        'pacer_period_max_ms': f'{2.5e3 * P:.3f}', 'pacer_wake_late_p50_ms': '0.000',
        'pacer_wake_late_p99_ms': '0.000', 'pacer_wake_late_max_ms': f'{0.5e3 * P:.3f}'}


def test_lateness_figures_are_the_releases_after_their_deadlines() -> None:
    """Each release's lateness is kept slot for slot with its period, in the buffers a
    caller hands over (e.g. shared memory); the first release after start has neither."""
    ft = FakeTime()
    p = pacer(ft, window=8)
    periods, late = np.full(8, 9.0), np.full(8, 9.0)
    p.use_period_buffer(periods, late)
    assert not periods.any() and not late.any()
    p.wait()
    for k in range(1, 7):               # released 0, S, ..., 5 S after deadlines 1..6
        ft.work(P + (k - 1) * S - (ft.t - (k - 1) * P))
        tick = p.wait()
        assert (tick.index, tick.late) == (k, (k - 1) * S)
    assert late[:6].tolist() == [k * S for k in range(6)] and not late[6:].any()
    assert p.lateness is late and p.periods == (periods, 6)
    f = p.figures()
    assert (f.late_p50, f.late_max) == (2.5 * S, 5 * S)
    assert f.late_p99 == pytest.approx(4.95 * S, abs=1e-15)
    assert math.isnan(p.figures(percentiles=False).late_p50)
    with pytest.raises(ConfigError, match=r'lateness buffer must be 8 float64, got \(4,\)'):
        p.use_period_buffer(np.zeros(8), np.zeros(4))


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'period': 0.0}, r'period must be a finite number > 0 s, got 0\.0'),
    ({'period': math.nan}, r'period must be a finite number > 0 s, got nan'),
    ({'period': 0.001, 'spin_before': 0.002},
     r'spin_before must be in \[0, period = 0\.001\] s, got 0\.002'),
    ({'period': 0.001, 'spin_before': -1e-4}, r'spin_before must be in .* got -0\.0001'),
    ({'period': 0.001, 'window': 0}, r'window must be >= 1 period, got 0'),
])
def test_bad_settings_are_refused_with_the_value(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        DeadlinePacer(**kwargs)


def test_release_follows_a_device_clock_and_counts_its_missed_ticks() -> None:
    """A device's servo loop is the clock (``release``): no sleep; a release 3.5 periods
    after the previous one missed 3 ticks (3.5 rounds half up to 4), one 1.25 periods after
    is 0.25 ms late, one early (0.75) misses nothing; the periods are measured as
    ``wait``'s."""
    sleeps: list[float] = []
    pacer = DeadlinePacer(0.001, clock=lambda: math.nan, sleep=sleeps.append)
    ticks = [pacer.release(t) for t in (10.0, 10.001, 10.0045, 10.00575, 10.0065)]
    assert sleeps == []
    assert [t.index for t in ticks] == [0, 1, 5, 6, 7]
    assert [t.missed for t in ticks] == [0, 0, 3, 0, 0]
    assert [t.late for t in ticks] == pytest.approx([0.0, 0.0, 0.0, 0.00025, 0.0], abs=1e-12)
    assert [t.dt for t in ticks] == pytest.approx([0.001, 0.001, 0.0035, 0.00125, 0.00075],
                                                  abs=1e-12)
    f = pacer.figures()
    assert (f.cycles, f.missed, f.max_missed_run) == (5, 3, 3)
    assert f.period_max == pytest.approx(0.0035, abs=1e-12)
