"""``simulate fourbar``: the Section VIII experiment on a closed chain (issue 29's four-bar).

The VE integrates the closed chain (closures held by projection), the LMI runs on its one
independent velocity, and eq. 14 keeps the device on the coupler curve where eq. 10 lets it
leave along a straight line into its x stop."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from fourbar_closed_form import branch_of, freudenstein

from haptic_topology.dynamics.loops import LoopClosures
from haptic_topology.errors import ConfigError
from haptic_topology.paths import config_dir
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


@pytest.mark.parametrize(('name', 'first_t'), [('fivebar_distal', 1), ('fivebar_proximal', 2)])
def test_the_five_bars_constraints_depend_on_the_grasp(name: str, first_t: int) -> None:
    """The five-bar (f = 2) held at its distal joint has t = 1 until its distal links
    straighten near the end of the run (t = 2 there); held at a proximal link (which moves
    with one joint) t = 2 throughout. The closure holds; eq. 14 drifts less than eq. 10."""
    sc = load_scenario(name)
    cl = LoopClosures(sc.linkage)
    runs = {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}
    for tr in runs.values():
        counts = tr.columns['constraint_count']
        assert counts[0] == first_t and set(np.unique(counts)) <= {first_t, 2}
        assert max(float(np.abs(cl.residual(row)).max()) for row in tr.columns['q'][::50]) \
            < 1e-9
    s14 = runs[ControlMode.PENALTY].summary()
    s10 = runs[ControlMode.ACCELERATION_ONLY].summary()
    assert s14['max_distance_m'] < 0.5 * s10['max_distance_m']


def test_a_scenario_may_hold_the_linkage_elsewhere(tmp_path: Path) -> None:
    assert load_scenario('fivebar_proximal').linkage.grasp_link == 'left_proximal'
    assert load_scenario('fivebar_distal').linkage.grasp_link == 'right_distal'
    doc = yaml.safe_load((config_dir() / 'scenarios' / 'fivebar_proximal.yaml').read_text())
    doc['scenario']['linkage'] = str(config_dir() / 'linkages' / 'fivebar.yaml')
    doc['scenario']['grasp'] = {'link': 'elbow'}
    (tmp_path / 's.yaml').write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r'scenario\.grasp\.link: expected one of '
                       r'left_proximal, left_distal, right_distal, right_proximal, got '
                       r"'elbow'$"):
        load_scenario(str(tmp_path / 's.yaml'))


def test_the_bennett_linkage_moves_by_bennetts_relation_under_both_laws() -> None:
    """The spatial loop (6-DOF device): a revolute closure of 5 equations of rank 2 leaves
    the 3-joint chain one degree of freedom (t = 5 throughout); the VE's joint angles obey
    Bennett's closed-form relation ``tan(q1/2) tan(q2/2) = sin((a2+a1)/2) / sin((a2-a1)/2)``
    (twists a1 = 60, a2 = 30 deg) to 1e-9 while the coupler moves, the closure holds to
    1e-9 m, and eq. 14 keeps the device within a tenth of eq. 10's drift (which reaches a
    stop)."""
    import math

    sc = load_scenario('bennett')
    cl = LoopClosures(sc.linkage)
    alpha1, alpha2 = math.pi / 3, math.pi / 6
    relation = math.sin((alpha2 + alpha1) / 2) / math.sin((alpha2 - alpha1) / 2)
    runs = {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}
    for tr in runs.values():
        q = tr.columns['q']
        assert np.all(tr.columns['constraint_count'] == 5)
        assert np.ptp(q[:, 0]) > 0.5                          # it moved
        products = np.tan(q[:, 0] / 2) * np.tan(q[:, 1] / 2)
        assert np.abs(products - relation).max() < 1e-9
        np.testing.assert_allclose(q[:, 2], -q[:, 0], atol=1e-9)   # opposite joints
        assert max(float(np.abs(cl.residual(row)).max()) for row in q[::50]) < 1e-9
    s14 = runs[ControlMode.PENALTY].summary()
    s10 = runs[ControlMode.ACCELERATION_ONLY].summary()
    assert s14['max_distance_m'] < 0.1 * s10['max_distance_m']
    assert s14['workspace_limit_time_s'] == 0.0 and s10['first_limit_s'] is not None


def test_contacts_on_a_closed_loop_are_passive_and_reach_the_lmi() -> None:
    """fourbar_floor: the coupler-rocker joint lands on the floor and rests there. The
    contacts inject no energy (the VE's work-and-potential balance never goes positive), the
    closure holds, the LMI renders F_env from its reduced contacts, and eq. 14 still keeps
    the device far closer than eq. 10."""
    sc = load_scenario('fourbar_floor')
    cl = LoopClosures(sc.linkage)
    runs = {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}
    for tr in runs.values():
        s = tr.summary()
        assert s['contact_time_s'] > 0.5 and 0.0 < s['max_penetration_m'] < 1e-3
        assert s['energy_injected_j'] == 0.0 and s['energy_dissipated_j'] > 0.0
        assert np.abs(tr.columns['env_wrench']).max() > 1e-3
        assert max(float(np.abs(cl.residual(row)).max()) for row in tr.columns['q'][::50]) \
            < 1e-9
    s14 = runs[ControlMode.PENALTY].summary()
    s10 = runs[ControlMode.ACCELERATION_ONLY].summary()
    assert s14['max_distance_m'] < 0.2 * s10['max_distance_m']


def test_the_loop_passes_a_change_point_without_a_jolt() -> None:
    """fourbar_change_point: the four-bar at the Grashof limit pushed through its change
    point (crank angle 0, all links on one line): the closures' smallest weighted singular
    value comes within 1e-4 L_c of zero, the mobility (and the LMI's update size) stays 1,
    the closure holds, and the largest per-cycle change of the commanded wrench within 50 ms
    of the change point is no larger than anywhere else in the run (lock-step: exact)."""
    sc = load_scenario('fourbar_change_point')
    cl = LoopClosures(sc.linkage)
    for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY):
        tr = simulate(sc, mode)
        q = tr.columns['q']
        sigma = np.array([cl.basis(row).singular_values[-1] for row in q]) / cl.length
        k = int(np.argmin(sigma))
        assert sigma[k] < 1e-4 and q[:, 0].min() < 0.0 < q[:, 0].max()
        assert {cl.mobility(row) for row in q[::10]} == {1}
        assert max(float(np.abs(cl.residual(row)).max()) for row in q[::50]) < 1e-9
        step = np.linalg.norm(np.diff(tr.columns['command'], axis=0), axis=1)
        near = np.abs(tr.t[1:] - tr.t[k]) < 0.05
        assert step[near].max() <= step[~near].max()
        if mode is ControlMode.PENALTY:
            assert tr.summary()['max_distance_m'] < 1e-4
