"""The energy account of a simulated run against its trace, and the passivity controller in
the closed loop (haptic_topology.control.passivity through simulate)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace
from haptic_topology.vocabulary import ControlMode


def work_integral(trace: Trace) -> np.ndarray:
    """The work (J) of the wrench the device applied, row by row and accumulated, from the
    trace's columns alone: row k's ``applied`` is held over the period that ends at row k, in
    which the simulated device moves with row k's twist (it steps semi-implicitly)."""
    dt = np.diff(trace.t, prepend=np.nan)
    power = (trace.columns['applied'] * trace.columns['device_twist']).sum(axis=1)
    step = np.where(np.isfinite(dt), power * dt, 0.0)
    return np.cumsum(step)


def test_observer_is_the_traces_work_integral() -> None:
    """fig8 (eq. 14, no saturation, no device damping): the account's work after every row
    equals the trace's work integral to 1e-9 J, the parts add up to it, and the summary's
    work integral is the account's."""
    sc = replace(load_scenario('fig8'), duration=1.0)
    trace = simulate(sc)
    assert not np.any(trace.columns['status'] & 4)          # never saturated
    expected = work_integral(trace)
    assert np.abs(expected).max() > 1e-3
    np.testing.assert_allclose(trace.columns['port_work'], expected, rtol=0.0, atol=1e-9)
    s = trace.summary()
    acct = s['energy_account']
    assert sum(acct['port_work_parts_j'].values()) == pytest.approx(acct['port_work_j'],
                                                                    rel=0.0, abs=1e-12)
    assert s['port_work_j'] == pytest.approx(acct['port_work_j'], rel=0.0, abs=1e-9)
    # no device damping: the observer is the feedback parts' work, negated, plus the
    # coupling parts' work at the VT's end
    parts = acct['port_work_parts_j']
    assert acct['passivity_observer_j'] == pytest.approx(
        -(acct['port_work_j'] - parts['hand']) + acct['vt_work_j'], rel=0.0, abs=1e-12)


def test_zero_force_is_zero_sum() -> None:
    """Mode ZERO (a controller known passive: it does nothing): no work, no observer, in
    every row, exactly."""
    sc = replace(load_scenario('fig6'), duration=0.3)
    trace = simulate(sc, ControlMode.ZERO)
    assert np.all(trace.columns['port_work'] == 0.0)
    assert np.all(trace.columns['passivity_observer'] == 0.0)
    assert trace.summary()['port_work_j'] == 0.0


def test_passivity_controller_holds_an_unstable_penalty() -> None:
    """fig6 with the penalty 50 times stiffer and no damping (k_tc = 1e4 N/(m kg) on a 1 kg
    device at 1 kHz, K T / 2 = 5 N s/m against no device damping: beyond the Colgate-Schenkel
    bound): without the passivity controller the observer goes below -1 mJ and keeps falling;
    with it the observer ends positive, its lowest value is above the uncontrolled run's, and
    the drift stays within the stable (default gains) run's."""
    sc = replace(load_scenario('fig6'), duration=1.0)
    stiff = sc.gains.with_penalty(1e4, 0.0)
    stable = simulate(sc).summary()
    off = simulate(sc, gains=stiff)
    on = simulate(sc, gains=stiff, passivity=PassivityConfig(enabled=True))
    e_off = off.columns['passivity_observer']
    n = len(e_off)
    assert e_off.min() < -1e-3
    assert e_off[-1] < e_off[n // 2] < 0.0
    e_on = on.columns['passivity_observer']
    s_on = on.summary()
    assert s_on['energy_account']['passivity_cycles'] > 0
    assert e_on[-1] > 0.0
    assert e_on.min() > e_off.min()
    assert s_on['max_distance_m'] <= stable['max_distance_m'] * (1.0 + 1e-9)


def test_passivity_controller_keeps_a_rigid_grasps_drift() -> None:
    """spatial_arm4 (a rigid 6-D grasp; the hand moves the VT through the VE and the
    coordination pulls the device after it): the energy the coupling hands the device is the
    VE's, counted at the VT's end, so the law is passive (observer never below -1 uJ without
    the controller) and the controller, on, leaves the drift of the run without it (max and
    RMS within 1e-6 relative)."""
    sc = load_scenario('spatial_arm4')
    off = simulate(sc, passivity=PassivityConfig(enabled=False)).summary()
    on = simulate(sc, passivity=PassivityConfig(enabled=True)).summary()
    assert off['energy_account']['passivity_observer_min_j'] > -1e-6
    assert on['energy_account']['passivity_observer_min_j'] > -1e-6
    for key in ('max_distance_m', 'rms_distance_m'):
        assert on[key] <= off[key] * (1.0 + 1e-6), (key, on[key], off[key])


def test_energy_figure_draws_the_work_integral_and_the_observer() -> None:
    """energy.png of simulate: the total port work drawn is the trace's work integral (mJ);
    a run with its controller's account has the observer panel and the damping's twin."""
    import matplotlib.pyplot as plt

    from haptic_topology.sim.energy_plots import energy_figure

    trace = simulate(replace(load_scenario('fig6'), duration=0.3))
    fig = energy_figure(trace)
    try:
        assert len(fig.axes) == 3
        total = next(ln for ln in fig.axes[0].get_lines() if ln.get_label() == 'port, total')
        np.testing.assert_allclose(total.get_ydata(), 1e3 * work_integral(trace), rtol=0.0,
                                   atol=1e-9)
        observer = fig.axes[1].get_lines()[0].get_ydata()
        np.testing.assert_array_equal(observer, 1e3 * trace.columns['passivity_observer'])
    finally:
        plt.close(fig)
