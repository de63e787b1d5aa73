"""Dynamics on Pinocchio cross-checked against closed forms, identities and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_topology.dynamics import (
    LinkageDynamics,
    constraint_directions,
    integrate_pose,
    pose_difference,
    task_scale,
)
from haptic_topology.model import ConstraintSettings, load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

TABLE1 = load_linkage(config_dir() / 'linkages' / 'table1_planar3.yaml')
SPATIAL = load_linkage(config_dir() / 'linkages' / 'spatial_arm4.yaml')
L1, L2 = 0.042, 0.042
RNG = np.random.default_rng(7)
CONFIGS = [np.array([-math.pi / 4, math.pi / 6, -math.pi / 6]),
           np.array([0.0, math.pi / 6, -math.pi / 3]),
           np.array([0.7, -1.1, 2.0]),
           np.array([2.5, 0.3, -0.4])]


def _fd_jacobian(dyn: LinkageDynamics, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of the hand pose, rotations through the world-frame log map."""
    cols = []
    for i in range(q.size):
        dq = np.zeros(q.size)
        dq[i] = h
        plus, minus = dyn.hand_pose(q + dq), dyn.hand_pose(q - dq)
        cols.append(pose_difference(plus, minus, dyn.task) / (2 * h))
    return np.array(cols).T


@pytest.mark.parametrize('linkage', [TABLE1, TABLE1.with_grasp('link2'), SPATIAL],
                         ids=['planar-distal', 'planar-middle', 'spatial'])
def test_hand_jacobian_matches_finite_differences(linkage) -> None:
    dyn = LinkageDynamics(linkage)
    for _ in range(5):
        q = RNG.uniform(-2.0, 2.0, dyn.dof)
        np.testing.assert_allclose(dyn.hand_jacobian(q), _fd_jacobian(dyn, q), atol=1e-7)


@pytest.mark.parametrize('q', CONFIGS)
def test_middle_link_grasp_is_eq8_and_rank_2(q: np.ndarray) -> None:
    """The paper's Fig. 2 example: grasp at the COM of link 2, eq. 8, rank 2, t = 1."""
    dyn = LinkageDynamics(TABLE1.with_grasp('link2'))
    lc2 = 0.021
    s1, c1 = math.sin(q[0]), math.cos(q[0])
    s12, c12 = math.sin(q[0] + q[1]), math.cos(q[0] + q[1])
    eq8 = np.array([[-L1 * s1 - lc2 * s12, -lc2 * s12, 0.0],
                    [L1 * c1 + lc2 * c12, lc2 * c12, 0.0],
                    [1.0, 1.0, 0.0]])
    np.testing.assert_allclose(dyn.hand_jacobian(q), eq8, atol=1e-14)
    assert np.linalg.matrix_rank(dyn.hand_jacobian(q)) == 2
    cons = dyn.constraints(q)
    assert cons.count == 1
    # J_w^T n_w = J_h^T (W n_w) = 0: W n_w is the constrained direction of J_h
    w = task_scale(TaskSpace.PLANAR, TABLE1.constraints.characteristic_length)
    np.testing.assert_allclose(dyn.hand_jacobian(q).T @ (w * cons.left_vectors[:, -1]), 0.0,
                               atol=1e-14)


@pytest.mark.parametrize('q', CONFIGS)
def test_distal_grasp_determinant(q: np.ndarray) -> None:
    dyn = LinkageDynamics(TABLE1)
    assert np.linalg.det(dyn.hand_jacobian(q)) == pytest.approx(L1 * L2 * math.sin(q[1]),
                                                               abs=1e-15)


@pytest.mark.parametrize('linkage', [TABLE1, SPATIAL], ids=['planar', 'spatial'])
def test_mass_matrix_identities(linkage) -> None:
    dyn = LinkageDynamics(linkage)
    for _ in range(5):
        q = RNG.uniform(-2.0, 2.0, dyn.dof)
        dq = RNG.uniform(-3.0, 3.0, dyn.dof)
        tau = RNG.uniform(-1.0, 1.0, dyn.dof)
        d = dyn.mass_matrix(q)
        np.testing.assert_allclose(d, d.T, atol=1e-15)
        assert np.linalg.eigvalsh(d).min() > 0.0
        # D^-1 (tau - B - G) equals the articulated-body algorithm (eq. 2)
        np.testing.assert_allclose(np.linalg.solve(d, tau - dyn.bias(q, dq)),
                                   dyn.forward_dynamics(q, dq, tau), rtol=1e-9, atol=1e-9)
        # C dq = B, and Ddot - 2C is skew-symmetric (Ddot by central differences along dq)
        c = dyn.coriolis_matrix(q, dq)
        np.testing.assert_allclose(c @ dq, dyn.coriolis(q, dq), atol=1e-12)
        h = 1e-6
        d_dot = (dyn.mass_matrix(q + h * dq) - dyn.mass_matrix(q - h * dq)) / (2 * h)
        n = d_dot - 2 * c
        np.testing.assert_allclose(n, -n.T, atol=1e-7 * max(1.0, np.abs(d_dot).max()))


def test_gravity_is_the_gradient_of_potential_energy() -> None:
    dyn = LinkageDynamics(SPATIAL)
    import pinocchio as pin

    q = np.array([0.3, -0.4, 0.8, 0.02])

    def potential(qq: np.ndarray) -> float:
        return float(pin.computePotentialEnergy(dyn.model, dyn.data, qq))

    h = 1e-6
    grad = [(potential(q + h * e) - potential(q - h * e)) / (2 * h) for e in np.eye(4)]
    np.testing.assert_allclose(dyn.gravity(q), grad, atol=1e-6)


def test_free_motion_conserves_kinetic_energy() -> None:
    """No input, no gravity: the VE's RK4 keeps 0.5 dq^T D dq to integrator accuracy."""
    dyn = LinkageDynamics(TABLE1)
    ve = VirtualEnvironment(dyn, np.array([0.2, 0.9, -0.5]), np.array([2.0, -3.0, 4.0]))
    e0 = ve.kinetic_energy()
    for k in range(1, 1001):
        ve.push_input(k, k * 1e-3, np.zeros(3))
    assert ve.time == pytest.approx(0.999)
    assert abs(ve.kinetic_energy() - e0) / e0 < 1e-8
    # and half the step size is ~16x more accurate (4th order), i.e. not a lucky constant
    errs = []
    for step in (1e-3, 5e-4):
        v = VirtualEnvironment(dyn, np.array([0.2, 0.9, -0.5]), np.array([20.0, -30.0, 40.0]),
                               internal_step=step)
        e = v.kinetic_energy()
        v.integrate(np.zeros(3), 0.5)
        errs.append(abs(v.kinetic_energy() - e) / e)
    assert errs[0] / errs[1] > 8.0


@pytest.mark.parametrize('q2', [0.0, math.pi])
def test_rank_drops_where_eq8_says(q2: float) -> None:
    dyn = LinkageDynamics(TABLE1)
    q = np.array([0.4, q2, -0.9])
    cons = dyn.constraints(q)
    assert cons.count == 1
    assert cons.singular_values[-1] < 1e-12
    # away from the singularity the distal grasp is unconstrained
    assert dyn.constraints(np.array([0.4, 1.2, -0.9])).count == 0


def test_null_space_of_lambda_inv_equals_null_space_of_jt() -> None:
    """Section V: N(Lambda_h^-1) = N(J_h^T) at a singular configuration."""
    for linkage, q in ((TABLE1, np.array([0.4, 0.0, -0.9])),
                       (TABLE1.with_grasp('link2'), np.array([0.3, 0.8, 0.1])),
                       (SPATIAL, np.array([0.3, -0.4, 0.8, 0.02]))):
        dyn = LinkageDynamics(linkage)
        j = dyn.hand_jacobian(q)
        lam_inv = dyn.inverse_operational_inertia(q)
        u, s, _ = np.linalg.svd(j)
        rank = int(np.sum(s > 1e-10))
        null_jt = u[:, rank:]
        assert null_jt.shape[1] >= 1
        np.testing.assert_allclose(lam_inv @ null_jt, 0.0, atol=1e-12)
        ul, sl, _ = np.linalg.svd(lam_inv)
        assert int(np.sum(sl > 1e-10)) == rank
        null_lam = ul[:, rank:]
        # same subspace: the projectors agree
        np.testing.assert_allclose(null_lam @ null_lam.T, null_jt @ null_jt.T, atol=1e-8)


def test_rank_decision_is_independent_of_the_unit_of_length() -> None:
    """Scaling every length (and L_c) by 1000 (m -> mm) scales sigma by 1000: same count."""
    dyn = LinkageDynamics(TABLE1)
    settings = TABLE1.constraints
    mm = ConstraintSettings(settings.characteristic_length * 1000.0, settings.rank_tolerance)
    for q2 in np.linspace(-0.6, 0.6, 25):
        j = dyn.hand_jacobian(np.array([0.3, q2, -0.2]))
        j_mm = j.copy()
        j_mm[0:2] *= 1000.0
        a = constraint_directions(j, TaskSpace.PLANAR, settings)
        b = constraint_directions(j_mm, TaskSpace.PLANAR, mm)
        assert a.count == b.count
        np.testing.assert_allclose(b.singular_values, 1000.0 * a.singular_values, rtol=1e-9,
                                   atol=1e-9)


def test_blend_makes_the_weight_continuous() -> None:
    from haptic_topology.dynamics import penalty_weight

    ratios = np.linspace(0.0, 0.2, 2001)
    hard = penalty_weight(ratios, 0.05, 0.0)
    soft = penalty_weight(ratios, 0.05, 1.0)
    assert np.max(np.abs(np.diff(hard))) == 1.0          # a jump at the threshold
    assert np.max(np.abs(np.diff(soft))) < 0.02          # continuous ramp
    assert soft[ratios < 0.05].min() == 1.0 and soft[ratios > 0.1].max() == 0.0


def test_spatial_pose_arithmetic_round_trips() -> None:
    pose = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    twist = np.array([0.01, 0.02, -0.03, 0.3, -0.1, 0.2])
    moved = integrate_pose(pose, twist, 0.01, TaskSpace.SPATIAL)
    np.testing.assert_allclose(pose_difference(moved, pose, TaskSpace.SPATIAL), twist * 0.01,
                               atol=1e-12)
