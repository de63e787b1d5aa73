"""Issue 12 item 2: eq. 13's penalty acts along an orthonormal basis of N(J_h^T).

The characteristic length only decides the rank (how many directions are constrained); the
``weighted`` setting keeps the L_c-weighted projector of before (``W^-1 U diag(w) U^T W``).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.control.laws import penalty_acceleration
from haptic_topology.control.lmi import LmiSnapshot, LocalModel
from haptic_topology.dynamics import LinkageDynamics, constraint_directions, task_scale
from haptic_topology.model import (
    ConstraintSettings,
    Linkage,
    PenaltyDirection,
    load_linkage,
    serial_chain,
)
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

TABLE1 = load_linkage(config_dir() / 'linkages' / 'table1_planar3.yaml')
SPATIAL = load_linkage(config_dir() / 'linkages' / 'spatial_arm4.yaml')


def _with(linkage: Linkage, direction: PenaltyDirection, blend: float = 0.0) -> Linkage:
    return replace(linkage, constraints=replace(linkage.constraints,
                                                penalty_direction=direction, blend=blend))


def _old_projector(j: np.ndarray, task: TaskSpace, settings: ConstraintSettings,
                   column_scale: np.ndarray) -> np.ndarray:
    """The projector of before issue 12, written out: W^-1 U_w diag(w) U_w^T W."""
    w = task_scale(task, settings.characteristic_length)
    u, s, _ = np.linalg.svd(w[:, None] * j * column_scale[None, :], full_matrices=True)
    ratio = np.zeros(task.dim)
    ratio[:s.size] = s / settings.characteristic_length
    weights = (ratio < settings.rank_tolerance).astype(float)
    weights[s.size:] = 1.0
    pw = (u * weights) @ u.T
    return (pw * w[None, :]) / w[:, None]


def _truncated(j: np.ndarray, dyn: LinkageDynamics, count: int) -> np.ndarray:
    """J_h with its ``count`` smallest weighted singular values set to zero."""
    from haptic_topology.dynamics.constraints import joint_scale

    w = task_scale(dyn.task, dyn.linkage.constraints.characteristic_length)
    sc = joint_scale(dyn.linkage)
    u, s, vt = np.linalg.svd(w[:, None] * j * sc[None, :], full_matrices=False)
    keep = dyn.task.dim - count
    jw = (u[:, :keep] * s[:keep]) @ vt[:keep]
    return jw / w[:, None] / sc[None, :]


# Linkages whose J_h is rank-deficient at every configuration, so that N(J_h^T) is exact:
# Table I held at the middle link (eq. 8: t = 1), the spatial arm (4 joints, t >= 2), and a
# 2-link spatial chain (t = 4).
EXACT = [TABLE1.with_grasp('link2'), SPATIAL, serial_chain(2, TaskSpace.SPATIAL)]


@pytest.mark.parametrize('linkage', EXACT, ids=lambda lk: f'{lk.name}@{lk.grasp_link}')
def test_nullspace_penalty_is_orthogonal_to_the_allowed_motions(linkage: Linkage) -> None:
    dyn = LinkageDynamics(_with(linkage, PenaltyDirection.NULLSPACE))
    rng = np.random.default_rng(12)
    m = dyn.task.dim
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, dyn.dof)
        j = dyn.hand_jacobian(q)
        cons = dyn.constraints(q)
        exact = m - np.linalg.matrix_rank(j, tol=1e-9)
        assert cons.count >= exact
        p = cons.projector()
        np.testing.assert_allclose(p, p.T, atol=1e-12)
        np.testing.assert_allclose(p @ p, p, atol=1e-12)
        assert np.trace(p) == pytest.approx(cons.count)
        if cons.count == exact:
            np.testing.assert_allclose(j.T @ p, 0.0, atol=1e-12)   # force _|_ range(J_h)
        else:  # within the tolerance band: _|_ the rank-r J_h the rank decision kept
            j = _truncated(j, dyn, cons.count)
            np.testing.assert_allclose(j.T @ p, 0.0, atol=1e-12)
        # Power of the penalty force on any allowed motion xd = J_h qd is zero.
        force = penalty_acceleration(p, rng.normal(size=m) * 1e-2, rng.normal(size=m), 200.0,
                                     50.0)
        xd = j @ rng.normal(size=dyn.dof)
        assert abs(force @ xd) <= 1e-12 * np.linalg.norm(force) * np.linalg.norm(xd)


@pytest.mark.parametrize('linkage', EXACT + [TABLE1],
                         ids=lambda lk: f'{lk.name}@{lk.grasp_link}')
def test_weighted_reproduces_the_former_projector(linkage: Linkage) -> None:
    dyn = LinkageDynamics(_with(linkage, PenaltyDirection.WEIGHTED))
    from haptic_topology.dynamics.constraints import joint_scale

    rng = np.random.default_rng(5)
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, dyn.dof)
        j = dyn.hand_jacobian(q)
        expected = _old_projector(j, dyn.task, dyn.linkage.constraints,
                                  joint_scale(dyn.linkage))
        np.testing.assert_array_equal(dyn.constraints(q).projector(), expected)


def test_weighted_projector_tilts_the_force_off_the_null_space() -> None:
    """Why the default changed: with L_c != 1 the weighted force does work on allowed motion."""
    dyn = LinkageDynamics(_with(TABLE1.with_grasp('link2'), PenaltyDirection.WEIGHTED))
    q = np.array([0.3, 0.8, -0.2])
    p = dyn.constraints(q).projector()
    j = dyn.hand_jacobian(q)
    np.testing.assert_allclose(p @ j, 0.0, atol=1e-12)   # it ignores allowed errors ...
    assert np.abs(j.T @ p).max() > 1e-3                   # ... but its force does work


def test_blend_weights_keep_the_nullspace_directions() -> None:
    """With blend > 0 each basis vector gets its weight in [0, 1]; P stays symmetric PSD and
    its fully weighted part is still orthogonal to range(J_h) where J_h is singular."""
    lk = _with(TABLE1.with_grasp('link2'), PenaltyDirection.NULLSPACE, blend=1.0)
    dyn = LinkageDynamics(lk)
    for q in (np.array([0.3, 0.8, -0.2]), np.array([0.1, 0.05, 0.4])):
        p = dyn.constraints(q).projector()
        np.testing.assert_allclose(p, p.T, atol=1e-12)
        assert np.linalg.eigvalsh(p).min() >= -1e-12
        assert np.linalg.eigvalsh(p).max() <= 1.0 + 1e-12


@pytest.mark.parametrize('direction', list(PenaltyDirection))
def test_lmi_builds_the_projector_of_the_setting(direction: PenaltyDirection) -> None:
    lk = _with(TABLE1.with_grasp('link2'), direction)
    dyn = LinkageDynamics(lk)
    q, dq = np.array([0.3, 0.8, -0.2]), np.array([0.1, -0.2, 0.3])
    snap = LmiSnapshot.from_dynamics(dyn.snapshot(q, dq), dyn.task,
                                     lk.constraints.characteristic_length, 1, 0)
    assert snap.penalty_direction is direction
    lmi = LocalModel(dyn.task)
    lmi.sync(snap)
    np.testing.assert_array_equal(lmi.projector, dyn.constraints(q).projector())
    settings = lk.constraints
    direct = constraint_directions(dyn.hand_jacobian(q), dyn.task, settings)
    np.testing.assert_allclose(lmi.projector, direct.projector(), atol=1e-15)


def _qr_projector(u: np.ndarray, weights: np.ndarray, scale: np.ndarray,
                  inertia: np.ndarray | None) -> np.ndarray:
    """The projector by numpy's QR, written out: ``R^-T Q diag(w) Q^T R^T`` with
    ``Q = qr(R^-1 C)``, ``C`` the weighted columns ``W u_i``, the most constrained first."""
    m = u.shape[0]
    order = [i for i in range(m - 1, -1, -1) if weights[i] > 0.0]
    if not order:
        return np.zeros((m, m))
    r = np.ones(m) if inertia is None else np.sqrt(np.diag(inertia))
    basis, _ = np.linalg.qr(scale[:, None] * u[:, order] / r[:, None])
    return ((basis * weights[order]) @ basis.T) * r[None, :] / r[:, None]


@pytest.mark.parametrize('m', [3, 6])
def test_the_compiled_projector_is_the_qr_formulas(m: int) -> None:
    """The diagonal-inertia projector (one compiled call, Gram-Schmidt) against the QR
    formula, for every pattern of weights (0, 1 and blended), weighted rows, inertias of
    kg and kg m^2, and read-only arrays (e.g. a message's buffer)."""
    rng = np.random.default_rng(m)
    for trial in range(200):
        u = np.linalg.qr(rng.normal(size=(m, m)))[0]
        weights = rng.choice([0.0, 1.0, 0.25, 0.7], size=m)
        scale = np.where(np.arange(m) < m // 2, 1.0, rng.uniform(0.01, 2.0))
        inertia = None if trial % 3 == 0 else np.diag(rng.uniform(0.05, 3.0, size=m))
        for a in (u, weights, scale):
            a.flags.writeable = trial % 2 == 0
        cons = replace(constraint_directions(np.eye(m), TaskSpace.PLANAR if m == 3
                                             else TaskSpace.SPATIAL,
                                             ConstraintSettings(characteristic_length=1.0)),
                       left_vectors=u, weights=weights, task_scale=scale)
        np.testing.assert_allclose(cons.projector(inertia),
                                   _qr_projector(u, weights, scale, inertia), atol=1e-14,
                                   rtol=0, err_msg=f'trial {trial}')
    # M_d = I is the paper's sum of w_i n_i n_i^T, the same bits as no inertia.
    np.testing.assert_array_equal(cons.projector(np.eye(m)), cons.projector())
