"""Contacts (eqs. 1, 2, 10, 14, 17): Jacobians, forces, energy, the LMI against the VE, and the
contact scenarios offline.

Detection against hand-computed distances is in ``test_core_contacts_geometry``; here the
contact model is checked as dynamics: ``J_i`` against finite differences of the contact point,
the frictionless, undamped force as minus the gradient of the elastic energy, the energy
properties (resting, sliding, hitting a wall at speed conserve or dissipate energy), the LMI's
frozen contacts equal to the VE's at the update, and ``simulate wall`` / ``middle_link``.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from haptic_topology.cli import main as cli_main
from haptic_topology.control.lmi import LocalModel
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import (
    ContactModel,
    ContactParams,
    ContactSettings,
    contact_forces,
)
from haptic_topology.errors import ConfigError
from haptic_topology.model import load_linkage, serial_chain
from haptic_topology.model.obstacles import obstacles_from_config
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace_io import read_trace
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import ControlMode, TaskSpace

TABLE1 = config_dir() / 'linkages' / 'table1_planar3.yaml'
Q0 = np.array([0.0, np.pi / 6, -np.pi / 3])     # link 3's tip at (104.4, 6.0) mm


def _model(obstacles: list[dict], task: TaskSpace = TaskSpace.PLANAR, linkage=None,
           **params: float) -> tuple[LinkageDynamics, ContactModel]:
    lk = linkage or load_linkage(TABLE1)
    dyn = LinkageDynamics(lk)
    settings = ContactSettings(ContactParams(**params),
                               obstacles_from_config(obstacles, 'test', task), 0.003)
    return dyn, ContactModel(dyn.model, lk, settings)


WALL = [{'type': 'half_plane', 'point': [0.104, 0.0], 'normal': [-1.0, 0.0]}]


def test_tip_against_a_wall_by_hand() -> None:
    """Link 3's tip at x = 0.042 + 0.042 cos 30 deg + 0.030 cos 30 deg = 0.104354 m; the wall at
    x = 0.104 with a 3 mm capsule: gap 0.104 - 0.104354 - 0.003 = -3.354 mm, normal -x; link
    3's base (link 2's tip, x = 0.078373) is 25.6 mm - 3 mm away."""
    _, cm = _model(WALL)
    cs = cm.detect(Q0, margin=0.05)
    tip = 0.042 + 0.072 * np.cos(np.pi / 6)
    k = int(np.argmin(cs.gaps))
    assert cs.links[k] == 2
    assert cs.gaps[k] == pytest.approx(0.104 - tip - 0.003, abs=1e-12)
    np.testing.assert_allclose(cs.normals[k], [-1.0, 0.0, 0.0])
    np.testing.assert_allclose(cs.points[k][:2], [tip, 0.042 * np.sin(np.pi / 6)
                                                  - 0.030 * np.sin(np.pi / 6)], atol=1e-12)
    # Within 5 cm: link 2's tip (= link 3's base, once) and link 3's tip; within 1 m every
    # joint point once: link 1's base and the three tips.
    assert sorted(cs.links.tolist()) == [1, 2]
    assert sorted(cm.detect(Q0, margin=1.0).links.tolist()) == [0, 0, 1, 2]


def test_contact_jacobian_matches_finite_differences() -> None:
    """``J_i`` is the Jacobian of the link point (fixed in the link) that is the contact."""
    for linkage, task, obstacles in (
            (load_linkage(TABLE1), TaskSpace.PLANAR,
             [{'type': 'disc', 'center': [0.06, 0.025], 'radius': 0.008}]),
            (serial_chain(4, TaskSpace.SPATIAL), TaskSpace.SPATIAL,
             [{'type': 'sphere', 'center': [0.08, 0.03, 0.02], 'radius': 0.01}])):
        dyn, cm = _model(obstacles, task, linkage)
        rng = np.random.default_rng(3)
        q = rng.uniform(-0.5, 0.5, dyn.dof)
        cs = cm.detect(q, margin=1.0)
        assert len(cs)
        for i in range(len(cs)):
            link = int(cs.links[i]) + 1
            cm.detect(q, margin=1.0)
            local = cm.data.oMi[link].actInv(cs.points[i])
            fd = np.zeros((3, dyn.dof))
            for j in range(dyn.dof):
                e = np.zeros(dyn.dof)
                e[j] = 1e-7
                cm.detect(q + e, margin=1.0)
                plus = cm.data.oMi[link].act(local)
                cm.detect(q - e, margin=1.0)
                fd[:, j] = (plus - cm.data.oMi[link].act(local)) / 2e-7
            np.testing.assert_allclose(cs.jacobians[i], fd, atol=1e-8)


def test_elastic_force_is_minus_the_energy_gradient() -> None:
    """Frictionless, undamped, at rest: ``sum J_i^T F_i = -dU/dq`` (finite differences)."""
    for obstacles in (WALL, [{'type': 'disc', 'center': [0.098, 0.0], 'radius': 0.008}],
                      [{'type': 'segment', 'a': [0.106, -0.02], 'b': [0.106, 0.03]}]):
        dyn, cm = _model(obstacles, stiffness=3000.0, damping=0.0)
        tau, power = cm.torques(Q0, np.zeros(3))
        assert np.any(tau != 0.0) and power == 0.0
        grad = np.zeros(3)
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-7
            grad[j] = (cm.potential(Q0 + e) - cm.potential(Q0 - e)) / 2e-7
        np.testing.assert_allclose(tau, -grad, rtol=1e-5, atol=1e-9)


def test_forces_push_out_never_pull_and_friction_opposes_slip() -> None:
    p = ContactParams(stiffness=1000.0, damping=50.0, friction=0.5, slip_velocity=1e-3)
    n = np.array([[-1.0, 0.0, 0.0]] * 4)
    gaps = np.array([-0.001, -0.001, 0.001, -0.001])
    vel = np.array([[0.0, 0.0, 0.0],       # resting: k delta = 1 N along n
                    [-0.5, 0.0, 0.0],      # leaving fast: k delta - b gdot < 0 -> clipped to 0
                    [1.0, 0.0, 0.0],       # not in contact
                    [0.0, 0.2, 0.0]])      # sliding along y
    f = contact_forces(p, gaps, n, vel)
    np.testing.assert_allclose(f[0], [-1.0, 0.0, 0.0])
    np.testing.assert_array_equal(f[1:3], 0.0)
    assert f[3, 0] == pytest.approx(-1.0)
    assert f[3, 1] == pytest.approx(-0.5 * 0.2 / np.hypot(0.2, 1e-3))
    assert np.all(np.einsum('ij,ij->i', f, vel) <= 0.0)


def _energy_run(dq0: np.ndarray, duration: float, **params: float
                ) -> tuple[VirtualEnvironment, list[float], list[float], float]:
    """The free linkage (no hand wrench) from ``Q0`` with ``dq0`` near the wall: the
    mechanical energy ``T + U`` and the contact energy balance at every ms, the largest U."""
    dyn, cm = _model([{'type': 'half_plane', 'point': [0.108, 0.0], 'normal': [-1.0, 0.0]}],
                     **params)
    ve = VirtualEnvironment(dyn, Q0, dq0, internal_step=1e-4, contacts=cm)
    energy, balance = [], []
    peak = 0.0
    for _ in range(int(round(duration / 1e-3))):
        ve.integrate(np.zeros(3), 1e-3)
        potential = cm.potential(ve.q)
        peak = max(peak, potential)
        energy.append(ve.kinetic_energy() + potential)
        balance.append(ve.contact_energy_balance())
    return ve, energy, balance, peak


HIT = np.array([0.0, 0.0, 3.0])    # link 3 swings its tip into the wall at ~0.1 m/s


def test_hitting_a_wall_without_damping_conserves_energy() -> None:
    ve, energy, balance, peak = _energy_run(HIT, 0.3, stiffness=5000.0, damping=0.0)
    e0 = 0.5 * float(HIT @ ve.dyn.mass_matrix(Q0) @ HIT)
    assert peak > 0.1 * e0                             # it did hit the wall
    np.testing.assert_allclose(energy, e0, rtol=1e-6)
    assert max(abs(b) for b in balance) < 1e-6 * e0


def test_hitting_a_wall_with_damping_and_friction_dissipates() -> None:
    ve, energy, balance, _ = _energy_run(HIT, 0.3, stiffness=5000.0, damping=30.0,
                                         friction=0.5)
    e0 = 0.5 * float(HIT @ ve.dyn.mass_matrix(Q0) @ HIT)
    assert energy[-1] < 0.9 * e0
    assert np.all(np.diff(energy) <= 1e-9 * e0)                     # never gains energy
    assert max(balance) <= 1e-9 * e0 and balance[-1] < -0.1 * e0


def test_sliding_without_friction_conserves_and_with_friction_dissipates() -> None:
    """Link 3 pressed flat against a wall parallel to it (both ends in contact), sliding along
    it: frictionless and undamped the energy stays, with friction it goes."""
    q = np.array([0.0, np.pi / 6, np.pi / 3])      # link 3 upright at x = 78.373 mm
    wall = [{'type': 'half_plane', 'point': [0.0812, 0.0], 'normal': [-1.0, 0.0]}]
    dq0 = np.array([2.0, -2.0, 0.0])               # link 3 translates along +y, no rotation
    for friction, damping in ((0.0, 0.0), (0.8, 20.0)):
        dyn, cm = _model(wall, stiffness=5000.0, damping=damping, friction=friction)
        ve = VirtualEnvironment(dyn, q, dq0, internal_step=1e-4, contacts=cm)
        e0 = ve.kinetic_energy() + cm.potential(q)
        assert len(cm.detect(q, 0.0)) == 2                          # both ends touch
        for _ in range(100):
            ve.integrate(np.zeros(3), 1e-3)
        e1 = ve.kinetic_energy() + cm.potential(ve.q)
        if friction == 0.0:
            assert e1 == pytest.approx(e0, rel=1e-6)
        else:
            assert e1 < 0.98 * e0 and ve.contact_energy_balance() < -0.01 * e0


def test_resting_against_a_wall_dissipates_and_settles() -> None:
    """A constant push into the wall: the contact energy balance never goes above zero
    while the linkage is pressed against the wall and slides off it."""
    dyn, cm = _model([{'type': 'half_plane', 'point': [0.105, 0.0], 'normal': [-1.0, 0.0]}],
                     stiffness=2000.0, damping=40.0, friction=0.5)
    ve = VirtualEnvironment(dyn, Q0, np.zeros(3), internal_step=5e-4, contacts=cm)
    worst, deepest = 0.0, 0.0
    for _ in range(1500):
        ve.integrate(np.array([0.4, 0.0, 0.0]), 1e-3)
        worst = max(worst, ve.contact_energy_balance())
        gaps = cm.detect(ve.q, 0.0).gaps
        deepest = max(deepest, -float(gaps.min()) if gaps.size else 0.0)
    assert worst <= 1e-12
    assert 0.0 < deepest < 0.003       # bounded: the link's axis stays out of the wall


def test_lmi_contacts_equal_the_ve_at_the_update() -> None:
    """At the update's (q, dq) the LMI's contact torques are the VE's, and ``F_env`` gives the
    hand the contacts' acceleration (eq. 11: ``Lambda^-1 F_env = J_h D^-1 tau_c``)."""
    dyn, cm = _model(WALL + [{'type': 'disc', 'center': [0.06, 0.022], 'radius': 0.008}],
                     damping=30.0, friction=0.4)
    dq = np.array([0.3, -0.5, 1.1])
    ve = VirtualEnvironment(dyn, Q0, dq, contacts=cm)
    snap = ve.snapshot(seq=1)
    assert snap.contacts is not None and len(snap.contacts) >= 2
    lmi = LocalModel(TaskSpace.PLANAR)
    lmi.sync(snap)
    tau, _ = cm.torques(Q0, dq)
    np.testing.assert_allclose(lmi.contact_torques, tau, rtol=1e-12, atol=1e-15)
    d = dyn.mass_matrix(Q0)
    j = dyn.hand_jacobian(Q0)
    np.testing.assert_allclose(lmi.lambda_inv @ lmi.env_wrench, j @ np.linalg.solve(d, tau),
                               rtol=1e-9, atol=1e-12)
    # Held (contacts at the VE's rate): the same torques, also after the LMI moved.
    held = dataclasses.replace(snap, contacts=dataclasses.replace(snap.contacts, local=False))
    lmi.sync(held)
    at_update = lmi.contact_torques.copy()
    np.testing.assert_allclose(at_update, tau, rtol=1e-12, atol=1e-15)
    lmi.record_input(1, np.array([5.0, 0.0, 0.0]))
    lmi.advance(2, 1e-3)
    assert np.any(lmi.q != snap.q)
    np.testing.assert_array_equal(lmi.contact_torques, at_update)


def test_snapshot_without_obstacles_carries_no_contacts() -> None:
    dyn = LinkageDynamics(load_linkage(TABLE1))
    snap = VirtualEnvironment(dyn, Q0, np.zeros(3)).snapshot(seq=1)
    assert snap.contacts is None
    lmi = LocalModel(TaskSpace.PLANAR)
    lmi.sync(snap)
    assert not np.any(lmi.env_wrench)


@pytest.mark.parametrize('mode', [ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY])
def test_wall_scenario_stops_the_hand_at_the_wall(mode: ControlMode) -> None:
    sc = load_scenario('wall')
    tr = simulate(dataclasses.replace(sc, duration=1.0), mode)
    s = tr.summary()
    assert 0.0 < s['max_penetration_m'] < 1e-3
    assert s['contact_time_s'] > 0.3
    assert s['energy_injected_j'] == 0.0 and s['energy_dissipated_j'] > 0.0
    # The device never gets through: its x stays behind the wall's x minus the capsule's
    # radius plus the hand's distance to link 3's tip along x (15 mm cos 30 deg).
    assert tr.columns['device_pose'][:, 0].max() < 0.108 - 0.003
    env = tr.columns['env_wrench']
    assert np.all(np.isfinite(env)) and env[:, 0].min() < -0.3      # the wall pushes back


def test_without_local_contacts_the_lmi_renders_the_ve_rate() -> None:
    sc = load_scenario('wall')
    sc = dataclasses.replace(sc, duration=0.8)
    local = simulate(sc).columns['env_wrench']
    held = simulate(dataclasses.replace(sc, contacts=dataclasses.replace(
        sc.contacts, lmi_local=False))).columns['env_wrench']
    assert not np.array_equal(local, held)
    # Held: F_env changes only when an update arrives (every 10 cycles) ...
    steps = np.nonzero(np.any(np.diff(held, axis=0) != 0.0, axis=1))[0]
    assert steps.size and np.all((steps + 1) % 10 <= 1)
    # ... local: between updates too.
    steps = np.nonzero(np.any(np.diff(local, axis=0) != 0.0, axis=1))[0]
    assert np.any((steps + 1) % 10 > 1)


def test_middle_link_contact_acts_through_the_linkage() -> None:
    tr = simulate(dataclasses.replace(load_scenario('middle_link'), duration=0.6))
    s = tr.summary()
    assert s['contact_time_s'] > 0.1 and s['energy_injected_j'] == 0.0
    dyn, cm = _model([{'type': 'disc', 'center': [0.060, 0.025], 'radius': 0.008}])
    touching = [cm.detect(q, 0.0).links.tolist() for q in tr.columns['q'][::50]]
    assert {1} <= {link for links in touching for link in links} <= {0, 1}   # link 2 only
    assert np.abs(tr.columns['env_wrench']).max() > 0.1


def test_simulate_is_deterministic_and_writes_the_contact_summary(tmp_path) -> None:
    out = tmp_path / 'wall'
    assert cli_main(['simulate', 'wall', '--duration', '0.5', '--out', str(out)]) == 0
    summary = json.loads((out / 'summary.json').read_text())
    for key in ('max_penetration_m', 'rms_penetration_m', 'contact_time_s',
                'energy_injected_j'):
        assert isinstance(summary[key], float)
    back = read_trace(out / 'trace.parquet')
    again = simulate(dataclasses.replace(load_scenario('wall'), duration=0.5))
    np.testing.assert_array_equal(back.columns['env_wrench'], again.columns['env_wrench'])
    np.testing.assert_array_equal(back.columns['penetration'], again.columns['penetration'])
    assert back.summary() == again.summary()


def test_contacts_block_errors_name_the_field(tmp_path) -> None:
    base = (config_dir() / 'scenarios' / 'wall.yaml').read_text()
    cases = {
        'link_radius: 0.003': ('link_radius: -1', 'contacts.link_radius'),
        'margin: 0.005': ('margin: 0.005\n    links: {link9: {radius: 0.01}}',
                          'contacts.links.link9: unknown key'),
        'stiffness: 2000.0': ('stiffness: 0', 'contacts.stiffness'),
        "{type: half_plane, name: wall, point: [0.108, 0.0], normal: [-1.0, 0.0]}":
            ("{type: sphere, center: [0.1, 0, 0], radius: 0.01}", 'obstacles[0].type'),
    }
    for old, (new, expected) in cases.items():
        assert old in base
        path = tmp_path / 'bad.yaml'
        path.write_text(base.replace(old, new).replace('linkage: table1_planar3',
                                                       f'linkage: {TABLE1}'))
        with pytest.raises(ConfigError, match=expected.replace('[', r'\[').replace(']', r'\]')):
            load_scenario(str(path))


def test_vectorised_candidates_equal_the_geometry_pair_by_pair() -> None:
    """:meth:`ContactModel.candidates` (planes, discs, spheres for all links at once) gives the
    candidates :func:`capsule_gaps` gives link by link, joint points once."""
    from haptic_topology.model.obstacles import capsule_gaps
    cases = (
        (load_linkage(TABLE1), TaskSpace.PLANAR, WALL + [
            {'type': 'disc', 'center': [0.06, 0.025], 'radius': 0.008},
            {'type': 'half_plane', 'point': [0.0, -0.01], 'normal': [0.0, 1.0]},
            {'type': 'segment', 'a': [0.02, 0.04], 'b': [0.09, 0.05], 'radius': 0.001}]),
        (serial_chain(5, TaskSpace.SPATIAL), TaskSpace.SPATIAL, [
            {'type': 'plane', 'point': [0.0, 0.0, -0.02], 'normal': [0.1, 0.2, 1.0]},
            {'type': 'sphere', 'center': [0.1, 0.05, 0.0], 'radius': 0.02},
            {'type': 'box', 'center': [0.15, -0.05, 0.0], 'half_extents': [0.02, 0.03, 0.04],
             'rpy': [0.1, 0.2, 0.3]}]),
        # more links than the scalar path takes: the array form of discs
        (serial_chain(12, TaskSpace.PLANAR), TaskSpace.PLANAR, [
            {'type': 'disc', 'center': [0.2, 0.1], 'radius': 0.05},
            {'type': 'half_plane', 'point': [0.3, 0.0], 'normal': [-1.0, 0.2]}]))
    rng = np.random.default_rng(5)
    for linkage, task, obstacles in cases:
        _, cm = _model(obstacles, task, linkage)
        for _ in range(20):
            q = rng.uniform(-1.0, 1.0, linkage.dof)
            p0, p1 = cm._axes(q)
            links, obs, s, gaps, normals = cm.candidates(p0, p1)
            expected = []
            for k, ob in enumerate(cm.settings.obstacles):
                for i in range(linkage.dof):
                    for gap, s_i, n_i in capsule_gaps(ob, p0[i], p1[i], 0.003):
                        if i > 0 and s_i == 0.0 and ob.kind.value in ('half_plane', 'plane'):
                            continue
                        expected.append((k, i, s_i, gap, tuple(n_i)))
            got = sorted(zip(obs.tolist(), links.tolist(), s.tolist(), gaps.tolist(),
                             map(tuple, normals.tolist()), strict=True))
            expected.sort()
            assert len(got) == len(expected)
            for a, b in zip(got, expected, strict=True):
                assert a[:2] == b[:2]
                np.testing.assert_allclose(a[2:4], b[2:4], rtol=1e-12, atol=1e-15)
                np.testing.assert_allclose(a[4], b[4], atol=1e-12)
