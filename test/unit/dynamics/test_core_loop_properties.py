"""Property-based checks of closed chains on random linkages (issue 29 point 6).

Random serial linkages (those of ``test_core_properties``: planar and spatial, revolute and
prismatic, 1 mm to 1 m) closed by one loop, assembled by construction at the drawn ``q``: a
point of a link pinned to the world (planar ``pin``, spatial ``spherical``) or to a point of
an earlier link, or (spatial) a ``revolute`` closure whose axes agree at ``q``. Checked:
``J_c`` and ``Jdot_c qd`` against finite differences, ``J_c N = 0``, the reduced
``Lambda_h^-1`` against the constrained-mobility formula, ``N(Lambda_h^-1) = N((J_h N)^T)``,
and the constrained acceleration (closures' acceleration zero, no work of the closure forces
on ``N``).
Deterministic: ``derandomize=True`` and no example database.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pinocchio as pin
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_core_properties import linkage_docs

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model import linkage_from_dict

PROFILE = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow])


@st.composite
def closed_chains(draw: Any) -> tuple[LinkageDynamics, np.ndarray]:
    """A random closed chain and a configuration at which it is assembled."""
    doc, q = draw(linkage_docs())
    links = doc['linkage']['links']
    assume(len(links) >= 2)
    planar = doc['linkage']['task'] == 'planar'
    open_chain = LinkageDynamics(linkage_from_dict(doc, '<hypothesis>'))
    pin.framesForwardKinematics(open_chain.model, open_chain.data, q)
    k = draw(st.integers(1, len(links) - 1))
    length = links[k]['length']
    point = np.array([length, length * (draw(st.floats(0.0, 1.0)) - 0.5), 0.0])
    if not planar:
        point[2] = length * (draw(st.floats(0.0, 1.0)) - 0.5)
    placement = open_chain.data.oMi[k + 1]
    world = placement.act(point)
    j = draw(st.integers(-1, k - 1))          # -1: the world
    kind = 'pin' if planar else draw(st.sampled_from(['spherical', 'revolute']))
    loop: dict[str, Any] = {'link': f'l{k}', 'point': point.tolist(), 'kind': kind}
    if j < 0:
        loop['to_point'] = world.tolist()
        to_rotation = np.eye(3)
    else:
        to_placement = open_chain.data.oMi[j + 1]
        loop.update(to=f'l{j}', to_point=to_placement.actInv(world).tolist())
        to_rotation = to_placement.rotation
    if kind == 'revolute':
        theta, phi = draw(st.floats(0.0, np.pi)), draw(st.floats(0.0, 2 * np.pi))
        axis = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                         np.cos(theta)])
        loop['axis'] = axis.tolist()
        loop['to_axis'] = (to_rotation.T @ placement.rotation @ axis).tolist()
    doc['linkage']['loops'] = [loop]
    dyn = LinkageDynamics(linkage_from_dict(doc, '<hypothesis>'))
    assert dyn.loops is not None
    return dyn, q


@PROFILE
@given(closed_chains())
def test_closure_jacobian_equals_finite_differences(case: tuple[LinkageDynamics, Any]
                                                    ) -> None:
    dyn, q = case
    cl = dyn.loops
    assert cl is not None
    phi = cl.residual(q)
    assert np.abs(phi).max() <= 1e-9 * max(1.0, cl.length)       # assembled by construction
    h = 1e-6 * cl.column_scale
    fd = np.array([(cl.residual(q + hi * e) - cl.residual(q - hi * e)) / (2 * hi)
                   for hi, e in zip(h, np.eye(q.size), strict=True)]).T
    j = cl.jacobian(q)
    np.testing.assert_allclose(j, fd, atol=1e-6 * max(1.0, float(np.abs(j).max())))
    # Jdot_c qd along a motion the closures allow, against J_c differenced along it.
    basis = cl.basis(q)
    assume(basis.mobility > 0)
    dq = basis.null @ np.linspace(1.0, 2.0, basis.mobility)
    eps = 1e-6
    fd_drift = (cl.jacobian(q + eps * dq) - cl.jacobian(q - eps * dq)) @ dq / (2 * eps)
    drift = cl.drift(q, dq)
    np.testing.assert_allclose(drift, fd_drift,
                               atol=1e-5 * max(1.0, float(np.abs(fd_drift).max())))


@PROFILE
@given(closed_chains(), st.integers(0, 2 ** 31 - 1))
def test_reduction_identities_hold_on_random_closed_chains(
        case: tuple[LinkageDynamics, Any], seed: int) -> None:
    """``J_c N = 0``; ``J_h N (N^T D N)^-1 N^T J_h^T`` equals
    ``J_h (D^-1 - D^-1 J_c^T (J_c D^-1 J_c^T)^+ J_c D^-1) J_h^T``; its null space is
    ``N((J_h N)^T)``; the constrained acceleration meets ``J_c qdd = -Jdot_c qd`` and
    ``N^T (D qdd - tau + B + G) = 0``."""
    dyn, q = case
    cl = dyn.loops
    assert cl is not None
    basis = cl.basis(q)
    assume(basis.mobility > 0)
    # Away from the closures' own singular configurations, where the rank decision would
    # be a matter of its tolerance (a singular value of J_w within 1e-4 of the threshold).
    ratio = basis.singular_values / (cl.tolerance * cl.length)
    assume(not np.any((ratio > 1e-4) & (ratio < 1e4)))
    n = dyn.mechanism_basis(q)
    d, j, jc = dyn.mass_matrix(q), dyn.hand_jacobian(q), cl.jacobian(q)
    scale = max(1.0, float(np.abs(jc).max()))
    np.testing.assert_allclose(jc @ n, 0.0, atol=1e-9 * scale * max(1.0, np.abs(n).max()))
    dinv = np.linalg.inv(d)
    # The pseudo-inverse with the rank the weighted decision chose (redundant rows dropped).
    u, s, vt = np.linalg.svd(jc @ dinv @ jc.T)
    r = basis.rows.shape[0]
    inner = (vt[:r].T / s[:r]) @ u[:, :r].T
    mobility = j @ (dinv - dinv @ jc.T @ inner @ jc @ dinv) @ j.T
    jr = j @ n
    reduced = jr @ np.linalg.solve(n.T @ d @ n, jr.T)
    open_mobility = float(np.abs(j @ dinv @ j.T).max())        # the scale: no closures
    np.testing.assert_allclose(reduced, mobility, atol=1e-7 * max(1e-300, open_mobility))
    # N(Lambda_h^-1) = N((J_h N)^T): Lambda_h^-1 = L L^T with L = J_r R^-T (D_r = R R^T), so
    # its kernel is L's left null space; compared where J_r's rank is unambiguous (no
    # singular value between 1e-9 and 1e-5 of the largest: a squared threshold would differ).
    sv = np.linalg.svd(jr, compute_uv=False)
    top = max(float(sv.max()) if sv.size else 0.0, 1e-300)
    assume(not np.any((sv > 1e-9 * top) & (sv < 1e-5 * top)))
    rank = int(np.count_nonzero(sv >= 1e-7 * top))
    lower = np.linalg.cholesky(n.T @ d @ n)
    factor = np.linalg.solve(lower, jr.T).T          # J_r R^-T
    u_l = np.linalg.svd(factor)[0]
    u_j = np.linalg.svd(jr)[0]
    kernel, left = u_l[:, rank:], u_j[:, rank:]
    assert np.linalg.matrix_rank(factor, tol=1e-7 * max(
        float(np.linalg.norm(factor, 2)), 1e-300)) == rank
    if kernel.size:          # the same subspace: each basis projects fully onto the other
        np.testing.assert_allclose(np.linalg.svd(kernel.T @ left)[1], 1.0, atol=1e-6)
    rng = np.random.default_rng(seed)
    dq = n @ rng.normal(size=n.shape[1])
    free = rng.normal(size=q.size) - dyn.bias(q, dq)
    qdd = cl.acceleration(q, dq, d, free)
    drift = cl.drift(q, dq)
    tol = 1e-7 * max(1.0, float(np.abs(jc @ qdd).max()), float(np.abs(drift).max()))
    np.testing.assert_allclose(jc @ qdd + drift, 0.0, atol=tol)
    work = n.T @ (d @ qdd - free)
    np.testing.assert_allclose(work, 0.0, atol=1e-7 * max(1.0, float(np.abs(free).max()),
                                                          float(np.abs(d @ qdd).max())))
