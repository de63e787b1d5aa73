"""Pure safety cores: the device's command watchdog and the controller's sync guard.

No timing here: times are passed in, so every check is exact and machine-independent.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_topology.control.safety import ModelHealth, SyncGuard, SyncGuardConfig, scaled_wrench
from haptic_topology.device.maglev import saturate
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig, WatchdogFallback
from haptic_topology.errors import ConfigError

DT = 0.001
LIMIT = np.array([20.0, 20.0, 2.0])


def _run_watchdog(wd: CommandWatchdog, cmd: np.ndarray, ages: list[float],
                  twist: np.ndarray | None = None) -> np.ndarray:
    tw = np.zeros(3) if twist is None else twist
    return np.array([wd.step(cmd, a, tw, DT) for a in ages])


# -- watchdog --------------------------------------------------------------------------------
def test_watchdog_docstring_example_fades_10n_to_zero_in_50ms() -> None:
    """timeout 5 ms, ramp 50 ms, 10 N: held 5 ms, then -0.2 N per cycle, zero 50 ms later."""
    wd = CommandWatchdog(WatchdogConfig(timeout=0.005, ramp_time=0.05), 3)
    cmd = np.array([10.0, 0.0, 0.0])
    ages = [k * DT for k in range(1, 61)]            # controller silent from cycle 1 on
    out = _run_watchdog(wd, cmd, ages)[:, 0]
    np.testing.assert_allclose(out[:5], 10.0)        # ages 1..5 ms: fresh
    np.testing.assert_allclose(out[5], 9.8)          # 6 ms: stale, first step
    np.testing.assert_allclose(np.diff(out[5:55]), -0.2, atol=1e-12)
    assert out[54] == pytest.approx(0.0, abs=1e-12) and np.all(out[54:] == 0.0)
    assert wd.trips == 1 and wd.stale and wd.active


def test_watchdog_recovers_by_itself_without_a_jump() -> None:
    wd = CommandWatchdog(WatchdogConfig(timeout=0.005, ramp_time=0.02), 3)
    cmd = np.array([8.0, -4.0, 0.5])
    _run_watchdog(wd, cmd, [1.0] * 30)               # stale long enough: faded out
    assert wd.scale == 0.0
    out = _run_watchdog(wd, cmd, [0.0] * 30)         # commands are back
    steps = np.abs(np.diff(np.vstack([np.zeros(3), out]), axis=0))
    # Bound of the module doc: |u_c - u_f| dt / ramp per cycle.
    assert np.all(steps <= np.abs(cmd) * DT / 0.02 + 1e-12)
    np.testing.assert_allclose(out[19:], np.tile(cmd, (11, 1)))
    assert not wd.active and not wd.stale


def test_watchdog_damping_fallback_damps_the_device_motion() -> None:
    cfg = WatchdogConfig(timeout=0.005, ramp_time=0.01, fallback=WatchdogFallback.DAMPING,
                         damping=np.array([5.0, 5.0, 0.1]))
    wd = CommandWatchdog(cfg, 3)
    twist = np.array([0.2, -0.1, 1.0])
    out = _run_watchdog(wd, np.array([3.0, 3.0, 0.3]), [1.0] * 20, twist)
    np.testing.assert_allclose(out[-1], [-1.0, 0.5, -0.1])


def test_watchdog_nan_age_counts_as_stale_and_config_is_checked() -> None:
    wd = CommandWatchdog(WatchdogConfig(), 3)
    wd.step(np.ones(3), math.nan, np.zeros(3), DT)
    assert wd.stale
    with pytest.raises(ConfigError, match='timeout'):
        WatchdogConfig(timeout=0.0)
    with pytest.raises(ConfigError, match='ramp_time'):
        WatchdogConfig(ramp_time=math.inf)
    with pytest.raises(ConfigError, match='damping must have 3 entries'):
        CommandWatchdog(WatchdogConfig(fallback=WatchdogFallback.DAMPING), 3)
    with pytest.raises(ConfigError, match='zero, damping'):
        WatchdogFallback.parse('brake')


def test_driver_pipeline_never_outputs_beyond_limits_or_non_finite() -> None:
    """saturate -> watchdog -> saturate, as device_driver runs it, for hostile commands."""
    rng = np.random.default_rng(3)
    cfg = WatchdogConfig(timeout=0.005, ramp_time=0.02, fallback=WatchdogFallback.DAMPING,
                         damping=np.array([1e3, 1e3, 1e3]))
    wd = CommandWatchdog(cfg, 3)
    specials = [np.nan, np.inf, -np.inf, 1e308, -1e308]
    for k in range(5000):
        cmd = rng.normal(scale=50.0, size=3)
        cmd[rng.integers(3)] = specials[k % len(specials)] if k % 3 == 0 else cmd[0]
        twist = rng.normal(scale=10.0, size=3)
        if k % 7 == 0:
            twist[0] = np.nan
        age = float(rng.choice([0.0, 0.003, 0.01, np.inf, np.nan]))
        c, _ = saturate(cmd, LIMIT)
        u, _ = saturate(wd.step(c, age, twist, DT), LIMIT)
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= LIMIT)


def test_saturate_clamps_replaces_non_finite_and_refuses_another_size() -> None:
    u, sat = saturate(np.array([0.5, -9.0, np.nan]), LIMIT)
    assert sat and np.array_equal(u, np.clip([0.5, -9.0, 0.0], -LIMIT, LIMIT))
    u, sat = saturate([0.1, 0.2, -0.3], LIMIT)
    assert not sat and np.array_equal(u, [0.1, 0.2, -0.3])
    with pytest.raises(ValueError, match='wrench must have 3 entries'):
        saturate(np.zeros(6), LIMIT)


# -- sync guard ------------------------------------------------------------------------------
CFG = SyncGuardConfig(stale_after=0.05, degrade_after=0.25, ramp_time=0.2)


def _cycles(guard: SyncGuard, t0: float, n: int, update_every: int = 0
            ) -> tuple[list[float], list[bool], float]:
    """``n`` cycles from ``t0``; an update every ``update_every`` cycles (0: none)."""
    scales, applies = [], []
    t = t0
    for k in range(1, n + 1):
        t = t0 + k * DT
        if update_every and k % update_every == 0:
            guard.update_arrived(t)
        s, a = guard.cycle(t)
        scales.append(s)
        applies.append(a)
    return scales, applies, t


def test_guard_docstring_example_stages_and_fade() -> None:
    """Updates stop at t = 0: stale from 50 ms, fading from 250 ms, zero at 450 ms."""
    g = SyncGuard(CFG, DT)
    assert g.update_arrived(0.0)
    assert g.health(0.04) is ModelHealth.FRESH
    assert g.health(0.06) is ModelHealth.STALE
    assert g.health(0.26) is ModelHealth.DEGRADED
    scales, applies, _ = _cycles(g, 0.0, 500)
    s = np.array(scales)
    assert np.all(s[:250] == 1.0)
    assert s[250] == pytest.approx(1.0 - 0.005)
    assert np.all(np.abs(np.diff(s)) <= 0.005 + 1e-12)
    assert np.all(s[449:] == 0.0) and s[448] > 0.0
    assert not any(applies) and g.degradations == 1


def test_guard_holds_a_resync_until_the_force_is_zero_then_fades_in() -> None:
    g = SyncGuard(CFG, DT)
    g.update_arrived(0.0)
    _, _, t = _cycles(g, 0.0, 300)                 # degrading: scale 0.75 at 300 ms
    assert 0.7 < g.scale < 0.8
    assert not g.update_arrived(t)                 # the VE is back: held
    assert g.health(t) is ModelHealth.PENDING
    scales, applies, t = _cycles(g, t, 400, update_every=10)   # 100 Hz updates again
    k = applies.index(True)
    assert scales[k] == 0.0 and scales[k - 1] > 0.0   # applied at zero force
    assert sum(applies) == 1
    after = np.array(scales[k:])
    assert np.all(np.diff(after[:201]) > 0.0) and after[200] == pytest.approx(1.0)
    assert np.all(after[200:] == 1.0) and g.health(t) is ModelHealth.FRESH


def test_guard_restart_is_held_even_when_fresh_and_rejoin_fades_in() -> None:
    g = SyncGuard(CFG, DT)
    g.update_arrived(0.0)
    assert g.update_arrived(0.01)                  # normal update: applied at once
    assert not g.update_arrived(0.02, restart=True)
    _, applies, _ = _cycles(g, 0.02, 250)
    assert applies.count(True) == 1
    h = SyncGuard(CFG, DT)
    h.update_arrived(0.0)
    h.rejoin()
    scales, _, _ = _cycles(h, 0.0, 3)
    assert scales == pytest.approx([0.005, 0.010, 0.015])


def test_scaled_wrench_bound_per_cycle() -> None:
    """|delta out| <= L * step for a law output far beyond the limit (the stated bound)."""
    u = np.array([500.0, -300.0, 40.0])
    step = DT / CFG.ramp_time
    outs = [scaled_wrench(u, k * step, LIMIT) for k in range(int(1 / step))]
    diffs = np.abs(np.diff(np.array(outs), axis=0))
    assert np.all(diffs <= LIMIT * step + 1e-12)
    assert scaled_wrench(u, 1.0, LIMIT) is u      # full scale: untouched (device clamps)


def test_guard_config_checked() -> None:
    with pytest.raises(ConfigError, match='degrade_after'):
        SyncGuardConfig(stale_after=0.3, degrade_after=0.1)
    with pytest.raises(ConfigError, match='ramp_time'):
        SyncGuardConfig(ramp_time=-1.0)


def test_guard_counts_an_update_by_the_time_it_describes() -> None:
    """A VE catching up on a backlog sends updates that arrive now but describe the loop
    long ago: they do not make the model fresh, and are held."""
    g = SyncGuard(CFG, DT)
    g.update_arrived(0.0)
    _cycles(g, 0.0, 500)                            # degraded, force zero
    assert not g.update_arrived(0.5, lag=0.45)      # describes t = 0.05: still degraded
    assert g.health(0.5) is ModelHealth.PENDING
    _, applies, _ = _cycles(g, 0.5, 1)
    assert applies == [True]                        # scale already 0: applied at once
    assert g.health(0.502) is ModelHealth.DEGRADED  # ... but the force stays off
    assert not g.update_arrived(0.51, lag=0.01)     # caught up: fresh, held once more
    scales, applies, _ = _cycles(g, 0.51, 10, update_every=5)
    assert applies[0] and scales[-1] > 0.0
