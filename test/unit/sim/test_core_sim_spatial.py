"""Spatial end to end: the 6-DOF device on spatial_arm4 and on a public robot arm's URDF
(example-robot-data's Panda as shipped in config/robots/, held at a middle link), offline;
package:// references."""

from __future__ import annotations

import dataclasses
import importlib.metadata as md
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.model.linkage import linkage_from_dict
from haptic_topology.paths import resolve_package_uri
from haptic_topology.sim import Trace, load_scenario, simulate
from haptic_topology.sim.lockstep import SimStep
from haptic_topology.sim.plots import plot_trace
from haptic_topology.sim.trace_io import read_trace
from haptic_topology.vocabulary import ControlMode

#: A file of an installed cmeel wheel (coal, a dependency of pin) by package:// URI.
COAL_HOOK = 'package://coal/hook/python_path.dsv'
REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope='module', params=['spatial_arm4', 'panda_link4'])
def runs(request: pytest.FixtureRequest) -> dict[ControlMode, Trace]:
    sc = load_scenario(request.param)
    return {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}


def test_eq14_holds_the_device_where_eq10_drifts(runs: dict[ControlMode, Trace]) -> None:
    """Section VIII in 6-D: with the penalty (eq. 14) the device stays within a third of eq.
    10's largest distance from the grasp point (1.0 of 2.9 mm for the Panda, 0.53 of 2.4 mm for
    the arm; the penalty's metric is the device inertia, 0.01 kg m^2 in rotation) and never
    touches its stops; under eq. 10 it drifts more than 1.5 mm and reaches a stop (placed just
    beyond the VT's path) before the end of the run."""
    s14 = runs[ControlMode.PENALTY].summary()
    s10 = runs[ControlMode.ACCELERATION_ONLY].summary()
    assert runs[ControlMode.PENALTY].task_dim == 6
    assert s14['max_distance_m'] < s10['max_distance_m'] / 2.5
    assert s10['max_distance_m'] > 1.5e-3
    assert s10['rms_distance_m'] > 2.5 * s14['rms_distance_m']
    assert s14['workspace_limit_time_s'] == 0.0 and s14['first_limit_s'] is None
    assert s10['first_limit_s'] is not None and 1.0 < s10['first_limit_s'] < 2.0
    counts = runs[ControlMode.PENALTY].columns['constraint_count']
    assert counts.min() >= 2     # J_h is 6 x k with rank <= 4: t >= 2 throughout


def test_a_device_at_its_stop_holds_the_vt_only_through_vt_coupling() -> None:
    """spatial_arm4 run for 6 s (its scenario: 2 s): its device reaches the y stop (0.3 m)
    at 2.025 s. Without VT coupling (Section VIII, eq. 20: the VT moves freely under
    ``F_vt = F_h``) nothing holds the VT: it runs on, 2.2 m beyond the device at 6 s, its
    kinetic energy exactly the work of the hand's 0.05 N along y over its path (no other
    force acts on it), in both laws alike; the coordination wrench of eq. 15 grows with the
    distance on the device side only (its actuators saturate at 20 N). With the coordination
    acting on the VT (``vt_coupling``) the VT stays at the stop with the device, within 2 mm
    (``F_h / K_pc`` = 0.5 mm at rest)."""
    sc = dataclasses.replace(load_scenario('spatial_arm4'), duration=6.0)
    energy: list[float] = []

    def at_end(step: SimStep) -> None:
        if step.k == 6000:
            energy.append(step.ve.kinetic_energy())
            assert step.answer.hand is not None
            assert step.answer.hand.vt_wrench.tolist() == [0.0, 0.05, 0.0, 0.0, 0.0, 0.0]

    free = simulate(sc, observer=at_end)
    c = free.columns
    drift = np.linalg.norm(c['device_pose'][:, :3] - c['vt_pose'][:, :3], axis=1)
    assert free.summary()['first_limit_s'] == pytest.approx(2.025, abs=1e-3)
    assert c['device_pose'][6000, 1] == 0.3 and drift[6000] > 2.0
    assert energy[0] == pytest.approx(0.05 * (c['vt_pose'][6000, 1] - c['vt_pose'][0, 1]),
                                      rel=1e-9)
    assert np.abs(c['applied'][6000, :2]).tolist() == [20.0, 20.0]
    eq10 = simulate(sc, ControlMode.ACCELERATION_ONLY).columns['vt_pose']
    np.testing.assert_array_equal(eq10, c['vt_pose'])     # the VT ignores the device
    held = simulate(dataclasses.replace(sc, vt_coupling=True)).columns
    assert held['device_pose'][6000, 1] == 0.3
    assert np.linalg.norm(held['device_pose'][:, :3] - held['vt_pose'][:, :3],
                          axis=1).max() < 2e-3


def test_spatial_plot_has_both_projections(runs: dict[ControlMode, Trace],
                                           tmp_path: Path) -> None:
    tr = runs[ControlMode.ACCELERATION_ONLY]
    sc = load_scenario(str(tr.meta['scenario']))
    out = plot_trace(tr, tmp_path / 'p.png', sc.linkage)
    assert out.stat().st_size > 50_000


def test_panda_is_loaded_unchanged_from_the_shipped_copy() -> None:
    """panda_link4 needs no optional extra: its URDF is config/robots/'s copy of
    example-robot-data's (test_robots checks the bytes), its meshes beside it."""
    sc = load_scenario('panda_link4')
    lk = sc.linkage
    assert lk.urdf_path is not None and lk.urdf_path.resolve() == (
        REPO / 'config/robots/example-robot-data/robots/panda_description/urdf/panda.urdf')
    assert lk.dof == 7 and lk.grasp_link == 'panda_link4'
    assert any('panda_finger_joint1' in note for note in lk.notes)
    from haptic_topology.dynamics import LinkageDynamics

    jac = LinkageDynamics(lk).hand_jacobian(sc.q0)
    assert jac.shape == (6, 7)
    np.testing.assert_array_equal(jac[:, 4:], 0.0)   # the wrist does not move link 4


def test_package_uri_errors_name_the_field() -> None:
    with pytest.raises(ConfigError, match=r"f\.urdf: package 'no-such-pkg-xyz' is not "
                                          r'installed .*pip install no-such-pkg-xyz'):
        resolve_package_uri('package://no-such-pkg-xyz/a.urdf', 'f.urdf')
    coal = md.distribution('coal').version
    with pytest.raises(ConfigError) as err:
        resolve_package_uri('package://coal/robots/x.urdf', 'f.urdf')
    assert str(err.value) == f"f.urdf: package 'coal' {coal} has no file share/coal/robots/x.urdf"
    with pytest.raises(ConfigError, match=r"f\.urdf: expected package://NAME/PATH, got "
                                          r"'package://coal'"):
        resolve_package_uri('package://coal', 'f.urdf')
    with pytest.raises(LinkageError, match=r'<memory>: linkage\.urdf: package '):
        linkage_from_dict({'linkage': {'task': 'spatial', 'urdf': 'package://nope-x/a.urdf'}})
    assert resolve_package_uri(COAL_HOOK, 'f').name == 'python_path.dsv'


def test_simulate_command_runs_a_spatial_scenario(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'simulate',
                          'spatial_arm4', '--mode', 'acceleration_only', '--duration', '0.3',
                          '--out', str(tmp_path)], capture_output=True, text=True, check=True)
    assert 'first at limit [s]' in res.stdout
    summary = json.loads((tmp_path / 'summary.json').read_text())
    assert summary['linkage'] == 'spatial_arm4' and summary['first_limit_s'] is None
    tr = read_trace(tmp_path / 'trace.parquet')
    assert tr.task_dim == 6 and len(tr) == 301
