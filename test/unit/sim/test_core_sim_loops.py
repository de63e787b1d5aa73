"""``simulate fourbar``: the Section VIII experiment on a closed chain (issue 29's four-bar).

The VE integrates the closed chain (closures held by projection), the LMI runs on its one
independent velocity, and eq. 14 keeps the device on the coupler curve where eq. 10 lets it
leave along a straight line into its x stop."""

from __future__ import annotations

import numpy as np
import pytest
from fourbar_closed_form import branch_of, freudenstein

from haptic_topology.dynamics.loops import LoopClosures
from haptic_topology.sim import Trace, load_scenario, simulate
from haptic_topology.vocabulary import ControlMode


@pytest.fixture(scope='module')
def runs() -> dict[ControlMode, Trace]:
    sc = load_scenario('fourbar')
    return {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}


def test_eq14_follows_the_coupler_curve_where_eq10_leaves_it(
        runs: dict[ControlMode, Trace]) -> None:
    s14 = runs[ControlMode.PENALTY].summary()
    s10 = runs[ControlMode.ACCELERATION_ONLY].summary()
    assert s14['max_distance_m'] < 2e-3 and s14['workspace_limit_time_s'] == 0.0
    assert s10['max_distance_m'] > 10e-3 and s10['first_limit_s'] is not None
    for tr in runs.values():     # f = 1 of m = 3: two directions constrained throughout
        assert np.all(tr.columns['constraint_count'] == 2)


def test_the_vt_stays_assembled_on_freudensteins_coupler_curve(
        runs: dict[ControlMode, Trace]) -> None:
    """Every recorded VE configuration closes the loop to 1e-9 m and puts the VT's grasp
    point on the closed-form coupler curve at its crank angle; the VT moves along it."""
    sc = load_scenario('fourbar')
    cl = LoopClosures(sc.linkage)
    branch = branch_of(sc.q0)
    for tr in runs.values():
        q, vt = tr.columns['q'], tr.columns['vt_pose']
        closure = max(float(np.abs(cl.residual(row)).max()) for row in q[::20])
        curve = max(float(np.abs(vt[k, :2] - freudenstein(q[k, 0], branch)[0]).max())
                    for k in range(0, len(q), 20))
        assert closure < 1e-9 and curve < 1e-9
        assert np.linalg.norm(vt[-1, :2] - vt[0, :2]) > 0.03
