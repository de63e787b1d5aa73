"""Property-based checks of the dynamics core on random serial linkages (issue 12 item 5).

Random linkages: 1-8 joints, revolute and prismatic, planar and spatial (random axes and
joint placements), link lengths from 1 mm to 1 m, random grasp link and point, random
configuration. Checked against Pinocchio's own algorithms, finite differences and the
paper's identities (eq. 6, 7, 13). Deterministic: ``derandomize=True`` and no example
database, so a run can never fail by chance and pass on the next.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pinocchio as pin
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haptic_topology.dynamics import LinkageDynamics, pose_difference, task_scale
from haptic_topology.dynamics.constraints import joint_scale
from haptic_topology.model import Linkage, PenaltyDirection, linkage_from_dict

PROFILE = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow])
_unit = st.floats(0.0, 1.0, allow_nan=False, allow_infinity=False)


def _direction(draw: Any) -> list[float]:
    theta = draw(st.floats(0.0, math.pi))
    phi = draw(st.floats(0.0, 2.0 * math.pi))
    return [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]


@st.composite
def linkage_docs(draw: Any) -> tuple[dict[str, Any], np.ndarray]:
    """A linkage YAML document and a configuration q (rad / m)."""
    task = draw(st.sampled_from(['planar', 'spatial']))
    n = draw(st.integers(1, 8))
    links: list[dict[str, Any]] = []
    q = []
    for i in range(n):
        joint = draw(st.sampled_from(['revolute', 'prismatic']))
        length = 10.0 ** draw(st.floats(-3.0, 0.0))
        mass = draw(st.floats(0.05, 5.0))
        izz = mass * length ** 2 / 12.0 + mass * 1e-8
        link: dict[str, Any] = {'name': f'l{i}', 'joint': joint, 'length': length,
                                'mass': mass}
        if task == 'planar':
            link['inertia'] = izz * draw(st.floats(0.5, 2.0))
            link['com'] = [length * draw(_unit), length * (draw(_unit) - 0.5) * 0.4, 0.0]
            if joint == 'prismatic':
                a = draw(st.floats(0.0, 2.0 * math.pi))
                link['axis'] = [math.cos(a), math.sin(a), 0.0]
        else:
            link['inertia'] = [izz * draw(st.floats(0.5, 2.0)) for _ in range(3)]
            link['com'] = [length * (draw(_unit) - 0.2) for _ in range(3)]
            link['axis'] = _direction(draw)
            prev = links[-1]['length'] if links else 0.0
            link['origin'] = {'xyz': [prev * c for c in _direction(draw)],
                              'rpy': [draw(st.floats(-math.pi, math.pi)) for _ in range(3)]}
        links.append(link)
        span = math.pi if joint == 'revolute' else length
        q.append(draw(st.floats(-span, span)))
    grasp_index = draw(st.integers(0, n - 1))
    gl = links[grasp_index]['length']
    point = [gl * draw(_unit), gl * (draw(_unit) - 0.5),
             0.0 if task == 'planar' else gl * (draw(_unit) - 0.5)]
    doc = {'linkage': {'name': 'random', 'task': task, 'links': links,
                       'grasp': {'link': f'l{grasp_index}', 'point': point}}}
    return doc, np.array(q)


def _load(doc: dict[str, Any]) -> Linkage:
    return linkage_from_dict(doc, '<hypothesis>')


@PROFILE
@given(linkage_docs())
def test_mass_matrix_is_symmetric_positive_definite(case: tuple[dict[str, Any], Any]) -> None:
    doc, q = case
    dyn = LinkageDynamics(_load(doc))
    d = dyn.mass_matrix(q)
    np.testing.assert_array_equal(d, d.T)
    np.linalg.cholesky(d)   # raises unless positive definite


@PROFILE
@given(linkage_docs(), st.integers(0, 2 ** 31 - 1))
def test_mass_matrix_solve_equals_aba(case: tuple[dict[str, Any], Any], seed: int) -> None:
    """``D^-1 (tau - B - G)`` (eq. 2) equals Pinocchio's articulated-body algorithm."""
    doc, q = case
    dyn = LinkageDynamics(_load(doc))
    rng = np.random.default_rng(seed)
    dq = rng.normal(size=dyn.dof)
    tau = rng.normal(size=dyn.dof)
    expected = np.linalg.solve(dyn.mass_matrix(q), tau - dyn.bias(q, dq))
    got = dyn.forward_dynamics(q, dq, tau)
    np.testing.assert_allclose(got, expected, rtol=1e-7, atol=1e-9 * np.abs(expected).max())


@PROFILE
@given(linkage_docs())
def test_hand_jacobian_equals_finite_differences(case: tuple[dict[str, Any], Any]) -> None:
    """J_h of eq. 7 against central differences of the hand pose (rotations by log map)."""
    doc, q = case
    dyn = LinkageDynamics(_load(doc))
    j = dyn.hand_jacobian(q)
    h = 1e-6 * np.array([1.0 if link.joint.value == 'revolute' else link.length
                         for link in dyn.linkage.links])
    fd = np.empty_like(j)
    for i in range(dyn.dof):
        step = np.zeros(dyn.dof)
        step[i] = h[i]
        if dyn.task.dim == 3:
            diff = pose_difference(dyn.hand_pose(q + step), dyn.hand_pose(q - step), dyn.task)
        else:  # from the placements: no round trip through a rotation vector near pi
            plus, minus = dyn.hand_placement(q + step), dyn.hand_placement(q - step)
            diff = np.concatenate([plus.translation - minus.translation,
                                   pin.log3(plus.rotation @ minus.rotation.T)])
        fd[:, i] = diff / (2.0 * h[i])
    np.testing.assert_allclose(j, fd, atol=1e-6 * (1.0 + np.abs(j).max()))


def _weighted(dyn: LinkageDynamics, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``J_w = W J_h S``, ``W`` and ``S`` diagonals (L_c in m): every entry a length."""
    w = task_scale(dyn.task, dyn.linkage.constraints.characteristic_length)
    s = joint_scale(dyn.linkage)
    return w[:, None] * dyn.hand_jacobian(q) * s[None, :], w, s


@PROFILE
@given(linkage_docs())
def test_null_space_of_inverse_operational_inertia_is_that_of_jt(
        case: tuple[dict[str, Any], Any]) -> None:
    """``N(Lambda_h^-1) = N(J_h^T)`` (Section V; eq. 6 ``Lambda_h^-1 = J_h D^-1 J_h^T``).

    Checked in the L_c-weighted coordinates (``W Lambda_h^-1 W = J_w (S D S)^-1 J_w^T``), where
    both sides are maps between lengths and well conditioned; W is invertible, so the null
    spaces correspond one to one.
    """
    doc, q = case
    dyn = LinkageDynamics(_load(doc))
    jw, w, _ = _weighted(dyn, q)
    lam_w = w[:, None] * dyn.inverse_operational_inertia(q) * w[None, :]
    u, sv, _ = np.linalg.svd(jw, full_matrices=True)
    rank = int(np.count_nonzero(sv > 1e-9 * max(sv.max(), 1e-300)))
    null, rng_ = u[:, rank:], u[:, :rank]
    scale = np.abs(lam_w).max()
    # N(J^T) is in N(Lambda^-1) ...
    np.testing.assert_allclose(lam_w @ null, 0.0, atol=1e-9 * scale)
    # ... and Lambda^-1 is positive definite on range(J) = N(J^T)^perp: nothing else is null.
    if rank:
        reduced = rng_.T @ lam_w @ rng_
        assert np.linalg.eigvalsh(0.5 * (reduced + reduced.T)).min() > 1e-12 * scale


@PROFILE
@given(linkage_docs(), st.integers(0, 2 ** 31 - 1))
def test_nullspace_penalty_force_is_orthogonal_to_allowed_motion(
        case: tuple[dict[str, Any], Any], seed: int) -> None:
    """Eq. 13 with ``penalty_direction: nullspace``: ``u_add . (J_h qd) = 0`` for all qd.

    Exactly against ``J_h`` of the rank the weighted SVD decided (``J_h`` itself when it is
    exactly singular; its rank-r truncation inside the tolerance band).
    """
    doc, q = case
    lk = _load(doc)
    lk = replace(lk, constraints=replace(lk.constraints,
                                         penalty_direction=PenaltyDirection.NULLSPACE))
    dyn = LinkageDynamics(lk)
    cons = dyn.constraints(q)
    p = cons.projector()
    jw, w, s = _weighted(dyn, q)
    u, sv, vt = np.linalg.svd(jw, full_matrices=False)
    keep = dyn.task.dim - cons.count
    j_kept = ((u[:, :keep] * sv[:keep]) @ vt[:keep]) / w[:, None] / s[None, :]
    rng = np.random.default_rng(seed)
    force = p @ rng.normal(size=dyn.task.dim)          # any penalty force of eq. 13
    for _ in range(3):
        xd = j_kept @ rng.normal(size=dyn.dof)          # an allowed hand motion
        assert abs(force @ xd) <= 1e-9 * np.linalg.norm(force) * (np.linalg.norm(xd) + 1e-300)
    np.testing.assert_allclose(p, p.T, atol=1e-12)


@PROFILE
@given(linkage_docs(), st.sampled_from([1e-3, 0.1, 10.0, 1e3]))
def test_rank_decision_is_unchanged_by_the_unit_of_length(case: tuple[dict[str, Any], Any],
                                                           factor: float) -> None:
    """Scaling every length (and the default L_c, the reach) by ``factor`` keeps t of eq. 13."""
    doc, q = case
    base = _load(doc)
    scaled_doc = _scaled(doc, factor)
    scaled = _load(scaled_doc)
    assert math.isclose(scaled.constraints.characteristic_length,
                        factor * base.constraints.characteristic_length, rel_tol=1e-12)
    qs = np.array([v if link.joint.value == 'revolute' else v * factor
                   for v, link in zip(q, base.links, strict=True)])
    a = LinkageDynamics(base).constraints(q)
    b = LinkageDynamics(scaled).constraints(qs)
    tol = base.constraints.rank_tolerance
    ratio = a.singular_values / base.constraints.characteristic_length
    if np.any(np.abs(ratio - tol) < 1e-9 * tol):
        return  # on the threshold itself the decision is a coin toss of round-off
    assert a.count == b.count
    np.testing.assert_allclose(b.singular_values, factor * a.singular_values,
                               rtol=1e-9, atol=1e-12 * factor * a.singular_values.max())


def _scaled(doc: dict[str, Any], c: float) -> dict[str, Any]:
    """The same linkage with every length times ``c`` (inertias times c^2)."""
    raw = doc['linkage']
    links = []
    for link in raw['links']:
        new = dict(link, length=link['length'] * c, com=[v * c for v in link['com']])
        new['inertia'] = (link['inertia'] * c * c if isinstance(link['inertia'], float)
                          else [v * c * c for v in link['inertia']])
        if 'origin' in link:
            new['origin'] = dict(link['origin'], xyz=[v * c for v in link['origin']['xyz']])
        links.append(new)
    grasp = dict(raw['grasp'], point=[v * c for v in raw['grasp']['point']])
    return {'linkage': dict(raw, links=links, grasp=grasp)}


def test_properties_use_pinocchio_aba() -> None:
    """Guard: forward_dynamics is Pinocchio's ABA (the property above compares against D)."""
    dyn = LinkageDynamics(_load({'linkage': {'task': 'planar', 'links': [
        {'joint': 'revolute', 'length': 0.1, 'mass': 1.0, 'inertia': 0.001}]}}))
    q, dq, tau = np.array([0.2]), np.array([0.3]), np.array([0.5])
    np.testing.assert_array_equal(dyn.forward_dynamics(q, dq, tau),
                                  pin.aba(dyn.model, pin.Data(dyn.model), q, dq, tau))
