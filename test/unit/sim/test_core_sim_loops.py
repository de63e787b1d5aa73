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
    with pytest.raises(ConfigError, match=r"scenario\.grasp\.link: unknown link 'elbow' "
                       r'\(expected one of: left_proximal, left_distal, right_distal, '
                       r'right_proximal\)'):
        load_scenario(str(tmp_path / 's.yaml'))
