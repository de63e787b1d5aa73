"""Control laws (eq. 10, 13, 14) and the LMI (eq. 17-20) as pure functions."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from haptic_topology.control import (
    ControlGains,
    HapticController,
    LmiModel,
    LmiSnapshot,
    LocalModel,
    acceleration_control,
    control_wrench,
    penalty_control,
)
from haptic_topology.dynamics import LinkageDynamics, inverse_operational_inertia
from haptic_topology.model import load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import ControlMode, TaskSpace

TABLE1 = load_linkage(config_dir() / 'linkages' / 'table1_planar3.yaml')
P = TaskSpace.PLANAR


def _snapshot(dyn: LinkageDynamics, q: np.ndarray, dq: np.ndarray, seq: int = 1,
              hand_input_seq: int = -1) -> LmiSnapshot:
    return LmiSnapshot.from_dynamics(dyn.snapshot(q, dq), dyn.task,
                                     dyn.linkage.constraints.characteristic_length, seq,
                                     hand_input_seq)


def test_eq10_gives_the_desired_device_acceleration() -> None:
    """Eq. 10 in eq. 9: M_d xdd + C_d xd = F_h + u  =>  xdd = L (F_h + F_env + F_pc - b_d xd)."""
    rng = np.random.default_rng(3)
    lam = rng.normal(size=(3, 3))
    lam = lam @ lam.T
    m_d = np.diag([1.5, 2.0, 0.3])
    c_d = rng.normal(size=(3, 3))
    b_d = np.diag([0.1, 0.2, 0.3])
    f_h, f_env, f_pc, x, xd = (rng.normal(size=3) for _ in range(5))
    u = acceleration_control(lam, m_d, c_d, f_h, f_env, f_pc, x, xd, b_d, None)
    xdd = np.linalg.solve(m_d, f_h + u - c_d @ xd)
    np.testing.assert_allclose(xdd, lam @ (f_h + f_env + f_pc - b_d @ xd), atol=1e-12)


def test_eq14_adds_penalties_only_along_the_constraint_directions() -> None:
    dyn = LinkageDynamics(TABLE1.with_grasp('link2'))   # t = 1 everywhere
    q = np.array([0.3, 0.8, 0.1])
    lam = dyn.inverse_operational_inertia(q)
    cons = dyn.constraints(q)
    proj = cons.projector()
    m_d = np.eye(3)
    z = np.zeros(3)
    x_h = dyn.hand_pose(q)
    err = np.array([0.002, -0.001, 0.05])
    u10 = acceleration_control(lam, m_d, np.zeros((3, 3)), z, z, z, x_h, z)
    u14 = penalty_control(lam, m_d, np.zeros((3, 3)), z, z, z, x_h, z, x_h + err, z, proj,
                          200.0, 50.0, P)
    extra = u14 - u10
    assert np.linalg.norm(extra) > 0.0
    # the extra wrench, seen through J_h^T (what the linkage can feel), is zero:
    # it lies along N(J_h^T) only (plain Euclidean: it does no work on allowed motion; before
    # issue 12 this held only with the rotation row weighted by L_c^2)
    np.testing.assert_allclose(dyn.hand_jacobian(q).T @ extra, 0.0, atol=1e-12)
    # and it is k_tc times the error's constrained component
    np.testing.assert_allclose(extra, 200.0 * proj @ err, atol=1e-12)


def test_penalty_is_the_papers_formula_when_unweighted() -> None:
    """With L_c = 1, P = sum n n^T, and eq. 13 is M_d sum (k n^T e + b n^T edot) n."""
    n = np.array([0.6, 0.8, 0.0])
    from haptic_topology.dynamics import ConstraintDirections

    u = np.linalg.qr(np.column_stack([[0.8, -0.6, 0.0], [0, 0, 1.0], n]))[0]
    cons = ConstraintDirections(np.array([1.0, 1.0, 0.0]), u, np.array([0.0, 0.0, 1.0]), 1,
                                np.ones(3))
    e, ed = np.array([0.01, 0.02, 0.3]), np.array([0.1, -0.2, 0.0])
    m_d = np.diag([2.0, 2.0, 1.0])
    z = np.zeros(3)
    u14 = penalty_control(np.zeros((3, 3)), m_d, np.zeros((3, 3)), z, z, z, z, z, e, ed,
                          cons.projector(), 10.0, 7.0, P)
    nn = u[:, 2]
    expected = m_d @ ((10.0 * nn @ e + 7.0 * nn @ ed) * nn)
    np.testing.assert_allclose(u14, expected, atol=1e-12)


def test_modes_select_the_law() -> None:
    gains = ControlGains(np.ones(3), np.ones(3), 10.0, 7.0)
    args = dict(lambda_inv=np.eye(3), m_d=np.eye(3), c_d=np.zeros((3, 3)),
                f_h=np.array([0.4, 0, 0]), f_pc=np.zeros(3), x_h=np.zeros(3),
                xd_h=np.zeros(3), x_vt=np.array([0.01, 0, 0]), xd_vt=np.zeros(3),
                projector=np.eye(3), gains=gains, task=P)
    assert not control_wrench(ControlMode.ZERO, **args).any()
    u10 = control_wrench(ControlMode.ACCELERATION_ONLY, **args)
    u14 = control_wrench(ControlMode.PENALTY, **args)
    np.testing.assert_allclose(u14 - u10, [0.1, 0, 0])
    assert ControlMode.parse('acceleration_only') is ControlMode.ACCELERATION_ONLY
    with pytest.raises(ValueError, match='mode: expected one of'):
        ControlMode.parse('fast')


def test_eq19_uses_the_transpose() -> None:
    dyn = LinkageDynamics(TABLE1)
    q = np.array([0.1, 0.5, -0.3])
    j, d = dyn.hand_jacobian(q), dyn.mass_matrix(q)
    np.testing.assert_allclose(inverse_operational_inertia(j, d), j @ np.linalg.inv(d) @ j.T,
                               atol=1e-12)
    lmi = LocalModel(P)
    lmi.sync(_snapshot(dyn, q, np.zeros(3)))
    np.testing.assert_allclose(lmi.lambda_inv, j @ np.linalg.inv(d) @ j.T, atol=1e-12)


@pytest.mark.parametrize('model', [LmiModel.EQ17, LmiModel.EQ20])
def test_lmi_step_integrates_the_frozen_dynamics(model: LmiModel) -> None:
    dyn = LinkageDynamics(load_linkage(config_dir() / 'linkages' / 'spatial_arm4.yaml'))
    q, dq = np.array([0.3, -0.4, 0.8, 0.02]), np.array([0.1, 0.0, -0.2, 0.01])
    snap = _snapshot(dyn, q, dq)
    lmi = LocalModel(TaskSpace.SPATIAL, model)
    lmi.sync(snap)
    f = np.array([0.5, -0.2, 0.1, 0.0, 0.01, 0.0])
    lmi.record_input(0, f)
    lmi.advance(1, 1e-3)
    tau = snap.hand_jacobian.T @ f - (snap.gravity if model is LmiModel.EQ17 else 0.0)
    qdd = np.linalg.solve(snap.mass_matrix, tau)
    np.testing.assert_allclose(lmi.dq, dq + 1e-3 * qdd, atol=1e-12)
    np.testing.assert_allclose(lmi.q, q + 1e-3 * (dq + 1e-3 * qdd), atol=1e-12)
    np.testing.assert_allclose(lmi.xd_vt, snap.hand_jacobian @ lmi.dq, atol=1e-12)


def test_lmi_resync_replays_inputs_newer_than_the_update() -> None:
    """An update that lags k inputs behind costs no time: the newer inputs are replayed."""
    dyn = LinkageDynamics(TABLE1)
    q0, dq0 = np.array([0.2, 0.6, -0.4]), np.zeros(3)
    snap0 = _snapshot(dyn, q0, dq0, seq=0, hand_input_seq=-1)
    a, b = LocalModel(P), LocalModel(P)
    a.sync(snap0)
    forces = [np.array([0.4, 0.1 * i, 0.0]) for i in range(10)]
    for k, f in enumerate(forces):
        a.advance(k, 1e-3)
        a.record_input(k, f)
    a.advance(10, 1e-3)
    # b receives the same inputs, then a late re-sync to the *same* model at input 4:
    for k, f in enumerate(forces):
        b.advance(k, 1e-3) if k else b.sync(snap0)
        b.record_input(k, f)
    state_after_4 = LocalModel(P)
    state_after_4.sync(snap0)
    for k in range(5):
        state_after_4.record_input(k, forces[k])
        state_after_4.advance(k + 1, 1e-3)
    late = LmiSnapshot(1, 4, P, state_after_4.q, state_after_4.dq, snap0.mass_matrix,
                       snap0.gravity, snap0.hand_jacobian, snap0.singular_values,
                       snap0.left_vectors, snap0.weights, snap0.constraint_count,
                       snap0.characteristic_length, state_after_4.x_vt, state_after_4.xd_vt)
    b.sync(late)
    b.advance(10, 1e-3)
    assert b.consumed == a.consumed == 9
    np.testing.assert_allclose(b.q, a.q, atol=1e-14)
    np.testing.assert_allclose(b.x_vt, a.x_vt, atol=1e-14)


def test_the_input_history_is_a_ring_of_the_newest_inputs() -> None:
    """A re-sync replays the inputs after the update's from a ring of the newest ones: the
    same with a ring of 8 (wrapped around 4 times) as with the default 1024; an update older
    than the ring holds replays what the ring still has."""
    dyn = LinkageDynamics(TABLE1)
    snap0 = _snapshot(dyn, np.array([0.2, 0.6, -0.4]), np.zeros(3), seq=0)
    models = [LocalModel(P), LocalModel(P, history=8)]
    for lmi in models:
        lmi.sync(snap0)
        for k in range(1, 36):
            lmi.advance(k, 1e-3)
            lmi.record_input(k, np.array([0.4, 0.01 * k, -0.2]))
        late = dataclasses.replace(snap0, seq=1, hand_input_seq=30)
        lmi.sync(late)                  # replays inputs 31..34 (35 has no duration yet)
        assert lmi.consumed == 34
    np.testing.assert_array_equal(models[0].q, models[1].q)
    np.testing.assert_array_equal(models[0].x_vt, models[1].x_vt)
    for lmi in models:
        lmi.sync(dataclasses.replace(snap0, seq=2, hand_input_seq=20))
    assert models[0].consumed == models[1].consumed == 34
    assert not np.array_equal(models[0].q, models[1].q)    # 21..34 against 28..34


def test_controller_answers_zero_before_the_first_update() -> None:
    gains = ControlGains(np.full(3, 100.0), np.full(3, 70.0), 10.0, 7.0)
    ctrl = HapticController(P, ControlMode.PENALTY, gains, np.eye(3), np.zeros((3, 3)))
    out = ctrl.cycle(0, 1e-3, np.zeros(3), np.zeros(3), np.array([0.4, 0, 0]))
    assert out.mode is ControlMode.ZERO and not out.wrench.any()
    with pytest.raises(ValueError, match=r'device_mass must have shape \(3, 3\)'):
        HapticController(P, ControlMode.PENALTY, gains, np.eye(2), np.zeros((3, 3)))
    dyn = LinkageDynamics(TABLE1)
    ctrl.update(_snapshot(dyn, np.array([0.0, math.pi / 6, -math.pi / 3]), np.zeros(3)))
    out = ctrl.cycle(1, 1e-3, np.zeros(3), np.zeros(3), np.array([0.4, 0, 0]))
    assert out.mode is ControlMode.PENALTY and np.all(np.isfinite(out.wrench))


@pytest.mark.parametrize('scenario', ['fig8', 'wall', 'spatial_arm4'])
def test_a_prepared_update_syncs_exactly_as_the_update_itself(scenario: str) -> None:
    """``prepare`` (run by the thread or process that receives the update, on another copy of
    the controller) and ``update`` with its result give the controller the state the update
    itself gives, bit for bit: contacts (wall), spatial and planar."""
    from haptic_topology.sim import load_scenario
    from haptic_topology.sim.lockstep import build_controller_loop, virtual_environment
    sc = load_scenario(scenario)
    snap = virtual_environment(sc).snapshot(seq=0)
    direct, adopted, preparer = (build_controller_loop(sc, sc.mode).ctrl for _ in range(3))
    direct.update(snap)
    adopted.update(preparer.prepare(snap))
    assert adopted.stable_dt == direct.stable_dt
    rng = np.random.default_rng(3)
    x, xd = snap.hand_pose.copy(), snap.hand_twist.copy()
    for k in range(20):
        f_h = rng.normal(size=x.size)
        a = direct.cycle(k + 1, sc.dt, x, xd, f_h)
        b = adopted.cycle(k + 1, sc.dt, x, xd, f_h)
        for name in ('wrench', 'coupling', 'vt_wrench', 'vt_pose', 'vt_twist', 'env_wrench'):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (k, name)
        x, xd = x + 1e-3 * rng.normal(size=x.size), xd + 1e-2 * rng.normal(size=x.size)
    assert np.array_equal(direct.lmi.q, adopted.lmi.q)
    assert np.array_equal(direct.lmi.projector, adopted.lmi.projector)
