"""The energy account and the passivity controller (haptic_topology.control.passivity, .energy)
against what holds independently of them: the Colgate-Schenkel passivity bound of a sampled
virtual wall, the work integral of a simulated run's trace, the passivity controller holding
an unstable penalty passive.
"""

from __future__ import annotations

import numpy as np
import pytest

from haptic_topology.control.compiled import PENALTY, ZERO
from haptic_topology.control.passivity import EnergyAccount, PassivityConfig

T = 1e-3          # s, the device period of every scenario


def wall_observer_min(k: float, b_wall: float, b_device: float, v: float = 0.05,
                      n: int = 2000) -> float:
    """The lowest observer value (J) of a one-axis device of damping ``b_device`` (N s/m)
    against the sampled virtual wall ``u_j = -K x_j - B (x_j - x_(j-1)) / T`` (zero-order hold,
    backward difference: Colgate & Schenkel's), the device moved with a velocity constant over
    each period and alternating in sign, ``+v, -v, ...`` (m/s), from ``x = 0``.

    The excitation is the worst case of the bound: a velocity constant over each period is
    the input whose energy the sampled wall misjudges most (the held force lags the motion by
    up to a period), and the alternation makes every product ``v_(j-1) v_j`` of the
    backward-difference damping negative and brings ``x`` back to 0 every second period, so
    neither term of ``b > K T / 2 + |B|`` is hidden behind stored energy."""
    account = EnergyAccount(1, PassivityConfig(window=0.0), T, np.eye(1))
    c_d = np.array([[b_device]])
    zero1 = np.zeros(1)
    ml = np.zeros((1, 1))
    x_prev = x = 0.0
    v_prev = 0.0
    lowest = 0.0
    for j in range(n):
        # the state at the start of period j: its pose, and the twist the device reports,
        # the velocity of the period that ended (a velocity sensor of the held velocity)
        u = np.array([-k * x - b_wall * (x - x_prev) / T])
        account_step(account, c_d, ml, np.array([x]), np.array([v_prev]), zero1, u)
        lowest = min(lowest, account.observer)
        vj = v if j % 2 == 0 else -v
        x_prev, x, v_prev = x, x + vj * T, vj
    return lowest


def account_step(account: EnergyAccount, c_d: np.ndarray, ml: np.ndarray, x: np.ndarray,
                 xd: np.ndarray, zero: np.ndarray, u: np.ndarray, mode: int = PENALTY) -> None:
    from haptic_topology.control.energy import account as step
    step(0, mode, ml, c_d, x, xd, zero, zero, zero, zero, u, T, account.state)


def boundary(k: float, b_wall: float) -> float:
    """The smallest device damping (N s/m) that keeps the observer >= 0, by bisection."""
    lo, hi = 0.0, 10.0 * (k * T / 2.0 + b_wall) + 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if wall_observer_min(k, b_wall, mid) >= 0.0:
            hi = mid
        else:
            lo = mid
    return hi


@pytest.mark.parametrize('b_wall', [0.0, 2.0])
def test_swept_boundary_is_colgate_schenkel(b_wall: float) -> None:
    """Over a decade of K the boundary in device damping lies within 10 % of
    ``K T / 2 + |B|`` (Colgate & Schenkel 1997)."""
    for k in (2e3, 5e3, 1e4, 2e4):
        expected = k * T / 2.0 + abs(b_wall)
        found = boundary(k, b_wall)
        assert found == pytest.approx(expected, rel=0.10), (k, b_wall, found, expected)


def test_observer_sign_convention() -> None:
    """A pure damper held over the period (u = -c v) takes energy: the observer grows by
    c v^2 T a period; a negative damper gives it: the work is positive, the observer falls."""
    for c, sign in ((5.0, 1.0), (-5.0, -1.0)):
        account = EnergyAccount(1, PassivityConfig(), T, np.eye(1))
        zero, ml, c_d = np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1))
        x, v = 0.0, 0.1
        for _ in range(11):
            account_step(account, c_d, ml, np.array([x]), np.array([v]), zero,
                         np.array([-c * v]))
            x += v * T
        assert account.work == pytest.approx(-sign * 10 * abs(c) * v * v * T, rel=1e-12)
        assert account.observer == pytest.approx(-account.work, rel=1e-12)
        assert account.work_parts['penalty'] == pytest.approx(account.work, rel=1e-12)


def test_passivity_controller_dissipates_the_deficit() -> None:
    """With the controller on, a deficit of the observer is answered by the damping that
    dissipates it over the next period: alpha = -E / (T v^2), capped by the wrench limit."""
    account = EnergyAccount(1, PassivityConfig(enabled=True, window=0.0), T, np.eye(1))
    account.set_limit(np.array([10.0]))
    zero, ml, c_d = np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1))
    v = 0.1
    account_step(account, c_d, ml, np.array([0.0]), np.array([v]), zero, np.array([2.0]))
    # the held 2 N over a period moving at v: work 2 v T, observer -2 v T
    u = np.array([0.0])
    account_step(account, c_d, ml, np.array([v * T]), np.array([v]), zero, u)
    assert account.observer == pytest.approx(-2.0 * v * T, rel=1e-12)
    alpha = 2.0 * v * T / (T * v * v)
    assert account.damping == pytest.approx(alpha, rel=1e-12)
    assert u[0] == pytest.approx(-alpha * v, rel=1e-12)
    account_step(account, c_d, ml, np.array([2 * v * T]), np.array([v]), zero, np.zeros(1))
    assert account.observer == pytest.approx(0.0, abs=1e-15)
    assert account.summary()['passivity_cycles'] >= 1
    # the cap: the added damping never exceeds the wrench limit
    account_step(account, c_d, ml, np.array([2 * v * T]), np.array([v]), zero, np.zeros(1))
    big = np.array([0.0])
    account.state[4] = -1.0                 # a deficit of 1 J in the window
    account_step(account, c_d, ml, np.array([2 * v * T]), np.array([v]), zero, big)
    assert big[0] == pytest.approx(-10.0, rel=1e-12)


def test_a_fast_axis_against_a_small_limit_leaves_the_others_damped() -> None:
    """Two axes, one moving fast against a small limit (a rotation spinning at 1 rad/s,
    0.1 N m): the added wrench is clipped to that limit on that axis alone; the other axis
    gets the whole damping ``alpha = -E / (T |v|^2)`` (not ``0.1 / 1``, which a common cap
    by the fastest axis would leave it)."""
    account = EnergyAccount(2, PassivityConfig(enabled=True, window=0.0), T, np.eye(2))
    account.set_limit(np.array([10.0, 0.1]))
    zero, ml, c_d = np.zeros(2), np.zeros((2, 2)), np.zeros((2, 2))
    v = np.array([0.1, 1.0])
    account_step(account, c_d, ml, np.zeros(2), v, zero, np.array([2.0, 0.0]))
    u = np.zeros(2)
    account_step(account, c_d, ml, v * T, v, zero, u)
    deficit = 2.0 * v[0] * T                        # the held 2 N along axis 0
    alpha = deficit / (T * float(v @ v))
    assert account.damping == pytest.approx(alpha, rel=1e-12)
    assert u[0] == pytest.approx(-alpha * v[0], rel=1e-12)
    assert u[1] == -0.1


def test_zero_mode_accounts_nothing() -> None:
    """Mode ZERO: no part of the command, no work, whatever the device does."""
    account = EnergyAccount(2, PassivityConfig(enabled=True), T, np.eye(2))
    zero, ml, c_d = np.zeros(2), np.eye(2), np.zeros((2, 2))
    for j in range(5):
        account_step(account, c_d, ml, np.array([0.01 * j, 0.0]), np.array([10.0, 0.0]),
                     zero, np.zeros(2), mode=ZERO)
    assert account.work == 0.0 and account.observer == 0.0
    assert set(account.work_parts.values()) == {0.0}


def test_passivity_setting_and_backends() -> None:
    """``lmi_controller``'s ``passivity``: enabled/disabled as set; auto leaves it to the
    backend when the scenario has no ``passivity`` block (the hosting driver switches it on
    for a device that is not simulated); the simulated maglev says it is one, a backend by
    default not."""
    from haptic_topology.config.resolve import resolve_passivity
    from haptic_topology.device.backend import DeviceBackend, backend_class
    from haptic_topology.sim.scenario import load_scenario

    sc = load_scenario('fig6')
    assert resolve_passivity('enabled', sc) == (PassivityConfig(enabled=True), False)
    assert resolve_passivity('disabled', sc) == (PassivityConfig(enabled=False), False)
    assert resolve_passivity('auto', sc) == (PassivityConfig(enabled=False), True)
    assert backend_class('sim_maglev').simulated and not DeviceBackend.simulated
    assert not backend_class('network').simulated


def test_auto_turns_the_controller_on_for_every_real_device() -> None:
    """``auto`` with no scenario block: on for every backend that is not a simulation, point
    and rigid grasps alike (the two-port observer leaves a rigid grasp's coordination alone:
    test_energy_sim's spatial_arm4), off for the simulated maglev."""
    from haptic_topology.config.resolve import passivity_by_default
    from haptic_topology.device.backend import backend_class

    backends = ('sim_maglev', 'network', 'forcedimension', 'openhaptics', 'haply')
    on = {b for b in backends if passivity_by_default(backend_class(b).simulated,
                                                       backend_class(b).velocity_filtered)}
    # OpenHaptics' velocity is the driver's filtered difference: the controller stays off
    # there (test_the_controller_on_a_filtered_velocity_adds_energy)
    assert on == {'network', 'forcedimension', 'haply'}


def test_the_controller_on_a_filtered_velocity_adds_energy() -> None:
    """Why ``auto`` leaves it off on a device whose velocity is a filtered difference of its
    encoder positions: fig8_point on the OpenHaptics emulator's parameters (0.1 kg, 1 N s/m,
    55 um encoders, velocity filtered at 35.5 Hz) loses passivity and drifts with the
    controller, not without it; on the Force Dimension emulator's (the exact velocity) the
    controller changes nothing that matters."""
    from dataclasses import replace

    import numpy as np

    from haptic_topology.sim.lockstep import simulate
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.zwidth import DEVICES

    sc = load_scenario('fig8_point')
    sc = replace(sc, duration=min(sc.duration, 2.0))

    def run(device: str, on: bool) -> tuple[float, float]:
        tr = simulate(sc, device=DEVICES[device].params(sc),
                      passivity=PassivityConfig(enabled=on))
        return (float(np.nanmin(tr.columns['passivity_observer'])),
                float(tr.summary()['max_distance_m']))

    (e_on, d_on), (e_off, d_off) = run('openhaptics', True), run('openhaptics', False)
    assert e_on < 10.0 * e_off < 0.0 and d_on > 5.0 * d_off, (e_on, e_off, d_on, d_off)
    (e_on, d_on), (e_off, d_off) = run('forcedimension', True), run('forcedimension', False)
    assert e_on >= -1e-6 and d_on <= 1.01 * d_off, (e_on, d_on, d_off)
