"""Loop closures (issue 29): the ``loops:`` block, ``phi``/``J_c``/``Jdot_c qd`` against
finite differences, a four-bar's coupler curve against Freudenstein's closed form, and the
constrained dynamics (closure held, energy of a passive chain conserved)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from fourbar_closed_form import branch_of, freudenstein

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.loops import LoopClosures, _cross
from haptic_topology.errors import LinkageError
from haptic_topology.model import linkage_from_dict, load_linkage, to_dict
from haptic_topology.model.loops import LoopKind
from haptic_topology.paths import config_dir

FOURBAR = load_linkage(config_dir() / 'linkages' / 'fourbar.yaml')


def _fourbar_doc(**loop: Any) -> dict[str, Any]:
    doc = yaml.safe_load((config_dir() / 'linkages' / 'fourbar.yaml').read_text())
    doc['linkage']['loops'][0].update(loop)
    return doc


def _spatial_doc(kind: str = 'revolute', **extra: Any) -> dict[str, Any]:
    """The four-bar as a spatial chain (joint axes along z) closed by a revolute joint
    about z (5 equations, 2 of them redundant for this planar mechanism) or a spherical one."""
    doc = _fourbar_doc()
    lk = doc['linkage']
    lk['task'] = 'spatial'
    for link in lk['links']:
        link['inertia'] = [link['inertia']] * 3
        link['axis'] = [0.0, 0.0, 1.0]
    for i, link in enumerate(lk['links'][1:]):
        link['origin'] = {'xyz': [lk['links'][i]['length'], 0.0, 0.0]}
    lk['loops'] = [{'link': 'rocker', 'point': [0.07, 0.0, 0.0], 'to_point': [0.1, 0.0, 0.0],
                    'kind': kind, **extra}]
    return doc


def test_the_loops_block_is_read_and_written_back() -> None:
    (loop,) = FOURBAR.loops
    assert (loop.name, loop.link, loop.to, loop.kind) == ('ground', 'rocker', 'world',
                                                          LoopKind.PIN)
    np.testing.assert_array_equal(loop.to_point, [0.1, 0.0, 0.0])
    again = linkage_from_dict(to_dict(FOURBAR), 'again')
    assert again.loops[0].to_dict() == loop.to_dict()
    assert FOURBAR.with_grasp('crank').loops == FOURBAR.loops


@pytest.mark.parametrize(('doc', 'message'), [
    (_fourbar_doc(link='bar'), r"loops\[0\]\.link: unknown link 'bar' \(expected one of: "
                               r'crank, coupler, rocker\)'),
    (_fourbar_doc(to='ground'), r"loops\[0\]\.to: unknown link 'ground' \(expected world or "
                                r'one of: crank, coupler, rocker\)'),
    (_fourbar_doc(to='rocker'), r"loops\[0\]\.to: 'rocker' is the closure's own link"),
    (_fourbar_doc(kind='revolute'), r'loops\[0\]\.kind: revolute closes a spatial loop; a '
                                    r'planar linkage takes pin'),
    (_fourbar_doc(kind='hinge'), r"loops\[0\]\.kind: expected one of pin, spherical, "
                                 r"revolute, got 'hinge'"),
    (_fourbar_doc(point=[0.07, 0.0, 0.01]), r'loops\[0\]: point and to_point must have z = 0'),
    (_fourbar_doc(axis=[0, 0, 1]), r'loops\[0\]\.axis: only a revolute closure has an axis'),
    (_spatial_doc('pin'), r'loops\[0\]\.kind: pin closes a planar loop'),
    (_spatial_doc('revolute'), r'loops\[0\]\.axis: missing required key'),
    (_spatial_doc('revolute', axis=[0, 0, 0]), r'loops\[0\]\.axis: expected a nonzero axis'),
])
def test_a_bad_closure_is_refused_naming_the_field(doc: dict[str, Any], message: str) -> None:
    with pytest.raises(LinkageError, match=r'^f\.yaml: linkage\.' + message):
        linkage_from_dict(doc, 'f.yaml')


def _finite_differences(cl: LoopClosures, q: np.ndarray, dq: np.ndarray,
                        eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """(d phi / dq, d/dt (J_c(q(t)) dq) at qdd = 0) by central differences."""
    jac = np.array([(cl.residual(q + eps * e) - cl.residual(q - eps * e)) / (2 * eps)
                    for e in np.eye(q.size)]).T
    drift = (cl.jacobian(q + eps * dq) - cl.jacobian(q - eps * dq)) @ dq / (2 * eps)
    return jac, drift


@pytest.mark.parametrize('kind', ['pin', 'spherical_planar', 'revolute', 'spherical'])
def test_jacobian_and_drift_match_finite_differences(kind: str) -> None:
    lk = {'pin': FOURBAR,
          'spherical_planar': linkage_from_dict(_fourbar_doc(kind='spherical'), 'f.yaml'),
          'revolute': linkage_from_dict(_spatial_doc(axis=[0, 0, 1]), 'f.yaml'),
          'spherical': linkage_from_dict(_spatial_doc('spherical'), 'f.yaml')}[kind]
    cl = LoopClosures(lk)
    rng = np.random.default_rng(7)
    q, err = cl.assemble(np.array([math.pi / 3, -0.6, 4.3]), fixed=(0,))
    assert err < 1e-13
    for _ in range(3):
        dq = cl.basis(q).null @ rng.normal(size=cl.mobility(q))
        jac, drift = _finite_differences(cl, q, dq)
        np.testing.assert_allclose(cl.jacobian(q), jac, atol=1e-8)
        np.testing.assert_allclose(cl.drift(q, dq), drift, atol=1e-7)
        q, _ = cl.assemble(q + 0.3 * dq)
    # Equations and their rank: pin 2, a planar spherical 3 (z row redundant), revolute 5
    # and spherical 3 on this planar mechanism (3 redundant rows of 5, 1 of 3).
    equations = {'pin': 2, 'spherical_planar': 3, 'revolute': 5, 'spherical': 3}[kind]
    assert cl.equations == equations and cl.mobility(q) == 1


def test_the_coupler_curve_is_freudensteins() -> None:
    """Assembled at 72 crank angles (held, the others solved from the previous
    configuration), the grasp point lies on Freudenstein's coupler curve to 1e-12 m."""
    cl, dyn = LoopClosures(FOURBAR), LinkageDynamics(FOURBAR)
    q, _ = cl.assemble(np.array([0.0, 0.5, 2.0]), fixed=(0,))
    branch = branch_of(q)
    worst = 0.0
    for theta in np.linspace(0.0, 2 * math.pi, 72, endpoint=False):
        q[0] = theta
        q, err = cl.assemble(q, fixed=(0,))
        assert err < 1e-13
        point, _ = freudenstein(theta, branch)
        worst = max(worst, float(np.abs(dyn.hand_pose(q)[:2] - point).max()))
    assert worst < 1e-12


def test_a_passive_closed_chain_keeps_its_closure_and_its_energy() -> None:
    """No gravity, no damping, no load: over 10 s (RK4, 2 ms, projection after each step)
    the closure error stays below 1e-9 m, the kinetic energy within 1e-6 (relative), and
    the hand stays on Freudenstein's coupler curve."""
    cl, dyn = LoopClosures(FOURBAR), LinkageDynamics(FOURBAR)
    q, _ = cl.assemble(np.array([math.pi / 3, -0.6, 4.3]), fixed=(0,))
    q, dq = cl.project(q, cl.basis(q).null[:, 0] * 3.0, dyn.mass_matrix)

    def stage(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return dyn.mass_matrix(qs), -dyn.bias(qs, vs), 0.0

    energy0 = 0.5 * dq @ dyn.mass_matrix(q) @ dq
    branch = branch_of(q)
    closure = energy = curve = 0.0
    turned = q[0]
    for _ in range(5000):
        q, dq, _ = cl.step(q, dq, 2e-3, stage)
        closure = max(closure, float(np.abs(cl.residual(q)).max()))
        energy = max(energy, abs(0.5 * dq @ dyn.mass_matrix(q) @ dq - energy0) / energy0)
        curve = max(curve, float(np.abs(dyn.hand_pose(q)[:2]
                                        - freudenstein(q[0], branch)[0]).max()))
    assert closure < 1e-9 and energy < 1e-6 and curve < 1e-9
    assert abs(q[0] - turned) > 2 * math.pi           # the crank went round at least once


def test_a_chain_pinned_at_both_ends_has_no_mobility(tmp_path: Path) -> None:
    doc = _fourbar_doc()
    doc['linkage']['links'] = doc['linkage']['links'][:2]
    doc['linkage']['loops'][0].update(link='coupler', point=[0.09, 0.0, 0.0])
    doc['linkage']['grasp'] = {'link': 'coupler'}
    cl = LoopClosures(linkage_from_dict(doc, 'f.yaml'))
    q, err = cl.assemble(np.array([0.3, 1.0]))
    assert err < 1e-13 and cl.mobility(q) == 0


def test_a_start_that_is_open_immobile_or_moving_off_the_closures_is_refused() -> None:
    from haptic_topology.dynamics.loops import check_assembled
    from haptic_topology.errors import ConfigError

    cl = LoopClosures(FOURBAR)
    with pytest.raises(ConfigError, match=r'^s\.yaml: scenario\.q0: the loop closures of '
                       r'linkage fourbar are open by 0\.0792 m at q0 \(expected <= 1e-09 m\); '
                       r'the nearest assembled q0 is \[(\S+), (\S+), (\S+)\]$') as info:
        check_assembled(FOURBAR, np.array([0.0, math.pi / 6, -math.pi / 3]), np.zeros(3),
                        's.yaml: scenario')
    offered = np.array([float(v) for v in
                        str(info.value).split('[')[1].rstrip(']').split(', ')])
    assert np.abs(cl.residual(offered)).max() < 1e-10            # it is assembled
    check_assembled(FOURBAR, offered, cl.basis(offered).null[:, 0], 's.yaml: scenario')
    with pytest.raises(ConfigError, match=r'^s\.yaml: scenario\.dq0: violates the loop '
                       r'closures of linkage fourbar \(J_c dq0 = '):
        check_assembled(FOURBAR, offered, np.array([1.0, 0.0, 0.0]), 's.yaml: scenario')
    doc = _fourbar_doc()
    doc['linkage']['links'] = doc['linkage']['links'][:2]
    doc['linkage']['loops'][0].update(link='coupler', point=[0.09, 0.0, 0.0])
    doc['linkage']['grasp'] = {'link': 'coupler'}
    pinned = linkage_from_dict(doc, 'f.yaml')
    q, _ = LoopClosures(pinned).assemble(np.array([0.3, 1.0]))
    with pytest.raises(ConfigError, match=r'scenario\.q0: linkage fourbar cannot move at q0: '
                       r'mobility 0 \(2 joints, 2 independent closure equations\)'):
        check_assembled(pinned, q, np.zeros(2), 's.yaml: scenario')


@pytest.mark.parametrize('kind', ['pin', 'revolute'])
def test_the_reduced_model_is_the_constrained_mobility(kind: str) -> None:
    """``Lambda_h^-1`` of the reduction, ``J_h N (N^T D N)^-1 N^T J_h^T``, equals the mobility
    of the constrained chain ``J_h (D^-1 - D^-1 J_c^T (J_c D^-1 J_c^T)^+ J_c D^-1) J_h^T``,
    and its null space is ``N((J_h N)^T)`` (the directions of topological constraint); the
    snapshot carries ``D_r = N^T D N``, ``G_r = N^T G``, ``J_r = J_h N`` and ``v``."""
    lk = FOURBAR if kind == 'pin' else linkage_from_dict(_spatial_doc(axis=[0, 0, 1]), 'f')
    dyn = LinkageDynamics(lk)
    cl = dyn.loops
    assert cl is not None
    rng = np.random.default_rng(11)
    q, _ = cl.assemble(np.array([0.4, -0.6, 4.3]), fixed=(0,))
    for _ in range(5):
        q, _ = cl.assemble(q + 0.4 * cl.basis(q).null[:, 0] * rng.normal())
        n = dyn.mechanism_basis(q)
        d, j, jc = dyn.mass_matrix(q), dyn.hand_jacobian(q), cl.jacobian(q)
        np.testing.assert_allclose(jc @ n, 0.0, atol=1e-12)
        dinv = np.linalg.inv(d)
        mobility = j @ (dinv - dinv @ jc.T @ np.linalg.pinv(jc @ dinv @ jc.T, rcond=1e-10)
                        @ jc @ dinv) @ j.T
        jr = j @ n
        reduced = jr @ np.linalg.solve(n.T @ d @ n, jr.T)
        np.testing.assert_allclose(reduced, mobility, atol=1e-9 * np.abs(mobility).max())
        w, v = np.linalg.eigh(reduced)
        kernel = v[:, w < 1e-9 * w.max()]
        t = dyn.constraints(q).count
        assert kernel.shape[1] == t == j.shape[0] - np.linalg.matrix_rank(jr)
        np.testing.assert_allclose(jr.T @ kernel, 0.0, atol=1e-9)
        dq = n @ rng.normal(size=n.shape[1])
        snap = dyn.snapshot(q, dq)
        np.testing.assert_allclose(snap.mass_matrix, n.T @ d @ n, atol=1e-15)
        np.testing.assert_allclose(snap.gravity, n.T @ dyn.gravity(q), atol=1e-15)
        np.testing.assert_allclose(snap.hand_jacobian, jr, atol=1e-15)
        np.testing.assert_allclose(n @ snap.dq, dq, atol=1e-12)
        np.testing.assert_allclose(snap.hand_twist, j @ dq, atol=1e-12)
        assert snap.q.shape == (n.shape[1],) and not np.any(snap.q)


def test_a_passive_bennett_linkage_keeps_its_closure_and_its_energy() -> None:
    """The spatial loop (revolute closure, 3 of its 5 equations redundant): 10 s passive,
    with gravity (so ``T + U`` is what is conserved), closure below 1e-9 m and ``T + U``
    within 1e-6 of the motion's kinetic energy scale."""
    doc = yaml.safe_load((config_dir() / 'linkages' / 'bennett.yaml').read_text())
    doc['linkage']['gravity'] = [0.0, 0.0, -9.81]
    dyn = LinkageDynamics(linkage_from_dict(doc, 'bennett.yaml'))
    cl = dyn.loops
    assert cl is not None
    q, _ = cl.assemble(np.array([1.27, -2.61, -1.27]))
    q, dq = cl.project(q, cl.basis(q).null[:, 0] * 4.0, dyn.mass_matrix)

    def stage(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return dyn.mass_matrix(qs), -dyn.bias(qs, vs), 0.0

    def energy(qs: np.ndarray, vs: np.ndarray) -> float:
        import pinocchio as pin
        kinetic = 0.5 * vs @ dyn.mass_matrix(qs) @ vs
        return kinetic + float(pin.computePotentialEnergy(dyn.model, dyn.data, qs))

    e0 = energy(q, dq)
    scale = 0.5 * dq @ dyn.mass_matrix(q) @ dq
    worst = closure = 0.0
    start = q[0]
    for _ in range(5000):
        q, dq, _ = cl.step(q, dq, 2e-3, stage)
        worst = max(worst, abs(energy(q, dq) - e0) / scale)
        closure = max(closure, float(np.abs(cl.residual(q)).max()))
    assert worst < 1e-6 and closure < 1e-9
    assert abs(q[0] - start) > 1.0


def test_drift_of_a_revolute_closure_between_two_moving_links() -> None:
    """The Bennett linkage on a turntable: its closure joins link3 to the turning base, so
    both ends rotate and the axis rows' ``(w_a x p_i) . w_rel`` term of ``Jdot_c qd`` is
    exercised (it vanishes for a closure to the world); mobility 2."""
    doc = yaml.safe_load((config_dir() / 'linkages' / 'bennett.yaml').read_text())
    lk = doc['linkage']
    lk['links'].insert(0, {'name': 'base', 'joint': 'revolute', 'axis': [1.0, 0.2, 0.1],
                           'length': 0.05, 'mass': 0.5, 'inertia': [0.001, 0.001, 0.001]})
    lk['links'][1]['origin'] = {'xyz': [0.0, 0.0, 0.0]}
    lk['loops'][0]['to'] = 'base'
    cl = LoopClosures(linkage_from_dict(doc, 'turntable.yaml'))
    q, err = cl.assemble(np.array([0.4, 1.27, -2.61, -1.27]))
    assert err < 1e-13 and cl.mobility(q) == 2
    for v in (np.array([1.0, 0.0]), np.array([0.3, 1.0]), np.array([-1.0, 2.0])):
        dq = cl.basis(q).null @ v
        jac, drift = _finite_differences(cl, q, dq)
        np.testing.assert_allclose(cl.jacobian(q), jac, atol=1e-8)
        np.testing.assert_allclose(cl.drift(q, dq), drift, atol=1e-7)


def _change_point_fourbar() -> LinkageDynamics:
    """The four-bar at the Grashof limit (config/linkages/fourbar_change_point.yaml): its
    links can all lie on one line (q = (0, 0, pi)), where rank(J_c) drops to 1."""
    return LinkageDynamics(load_linkage(config_dir() / 'linkages'
                                        / 'fourbar_change_point.yaml'))


def test_a_start_at_a_change_point_is_refused() -> None:
    from haptic_topology.dynamics.loops import check_assembled
    from haptic_topology.errors import ConfigError

    dyn = _change_point_fourbar()
    flat = np.array([0.0, 0.0, math.pi])
    assert dyn.loops is not None and dyn.loops.mobility(flat) == 2
    with pytest.raises(ConfigError, match=r'^s\.yaml: scenario\.q0: a singular configuration '
                       r'of the loop closures of linkage fourbar_change_point \(mobility 2 '
                       r"there, 1 around it, e\.g\. a four-bar's change point\): start away "
                       r'from it$'):
        check_assembled(dyn.linkage, flat, np.zeros(3), 's.yaml: scenario')
    q, _ = dyn.loops.assemble(np.array([0.6, -0.5, 2.0]), fixed=(0,))
    check_assembled(dyn.linkage, q, np.zeros(3), 's.yaml: scenario')    # away from it: fine


def _branch_tangents(cl: LoopClosures, q: np.ndarray) -> list[np.ndarray]:
    """The unit joint-rate directions at the singular configuration ``q`` (rank of ``J_c``
    one less than around it) along which the closures can be kept to second order: ``t`` in
    ``N(J_c)`` with ``Jdot_c(t) t`` in the range of ``J_c`` (a quadratic in the null space's
    coordinates, one root per assembly branch through ``q``)."""
    basis = cl.basis(q)
    assert basis.mobility == 2
    n1, n2 = basis.null.T
    u, _, _ = np.linalg.svd(cl.row_scale[:, None] * cl.jacobian(q))
    left = u[:, -1]                     # the weighted J_c's left null vector

    def f(t: np.ndarray) -> float:
        return float(left @ (cl.row_scale * cl.drift(q, t)))

    a, c = f(n1), f(n2)
    b = f(n1 + n2) - a - c
    roots = np.roots([a, b, c])
    assert np.all(np.isreal(roots)) and abs(roots[0] - roots[1]) > 0.1
    return [(t := x.real * n1 + n2) / np.linalg.norm(t) for x in roots]


@pytest.mark.parametrize('branch', [0, 1])
@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_a_run_through_the_change_point_itself_keeps_its_mobility_and_its_branch(
        branch: int, sign: float) -> None:
    """At the change point itself (q = (0, 0, pi): rank(J_c) 1, mobility 2) a run keeps the
    mobility of its start (``keep_rank``): the LMI's basis has one velocity, along the branch
    the chain moves on, and the passive chain leaves along that branch (its first step turns
    the velocity by less than 1e-5 rad; deciding the rank at the point instead gives two
    velocities and turns it by 2e-5) with the closure held to 1e-9 m and the energy to 1e-6,
    for either branch and direction."""
    dyn = _change_point_fourbar()
    cl = dyn.loops
    assert cl is not None
    flat = np.array([0.0, 0.0, math.pi])
    tangent = sign * _branch_tangents(cl, flat)[branch]
    start, _ = cl.assemble(np.array([0.6, -0.5, 2.0]), fixed=(0,))
    assert cl.keep_rank(start) == 2 and cl.mobility(flat) == 1
    dq = 5.0 * tangent
    n = dyn.mechanism_basis(flat, dq)
    assert n.shape == (3, 1) and abs(float(n[:, 0] @ tangent)) > 1 - 1e-12
    snap = dyn.snapshot(flat, dq)
    assert snap.mechanism is not None and snap.dq.shape == (1,)
    np.testing.assert_allclose(snap.mechanism @ snap.dq, dq, rtol=0, atol=1e-12)

    def stage(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return dyn.mass_matrix(qs), -dyn.bias(qs, vs), 0.0

    energy0 = 0.5 * dq @ dyn.mass_matrix(flat) @ dq
    q1, dq1, _ = cl.step(flat, dq, 1e-3, stage)
    turn = math.acos(min(1.0, float(dq1 @ tangent) / float(np.linalg.norm(dq1))))
    assert turn < 1e-5 and float((q1 - flat) @ tangent) > 0.0
    q, v = q1, dq1
    for _ in range(300):
        q, v, _ = cl.step(q, v, 1e-3, stage)
        assert float(np.abs(cl.residual(q)).max()) < 1e-9
        assert abs(0.5 * v @ dyn.mass_matrix(q) @ v - energy0) / energy0 < 1e-6


def test_a_passive_four_bar_passes_near_its_change_point_without_blowing_up() -> None:
    """The change-point four-bar whirling passively (8 rad/s, 3 s, RK4 at 1 ms) comes within
    3e-4 L_c of its change point (the smallest weighted singular value of J_c) several times;
    the mobility stays 1, the closure holds to 1e-9 m and the energy to 1e-6."""
    dyn = _change_point_fourbar()
    cl = dyn.loops
    assert cl is not None
    q, _ = cl.assemble(np.array([0.6, -0.5, 2.0]), fixed=(0,))
    q, dq = cl.project(q, cl.basis(q).null[:, 0] * 8.0, dyn.mass_matrix)

    def stage(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return dyn.mass_matrix(qs), -dyn.bias(qs, vs), 0.0

    energy0 = 0.5 * dq @ dyn.mass_matrix(q) @ dq
    energy = closure = 0.0
    nearest = np.inf
    for _ in range(3000):
        q, dq, _ = cl.step(q, dq, 1e-3, stage)
        basis = cl.basis(q)
        assert basis.mobility == 1
        nearest = min(nearest, float(basis.singular_values[-1]) / cl.length)
        energy = max(energy, abs(0.5 * dq @ dyn.mass_matrix(q) @ dq - energy0) / energy0)
        closure = max(closure, float(np.abs(cl.residual(q)).max()))
    assert nearest < 3e-4 and energy < 1e-6 and closure < 1e-9


def test_the_closures_cross_product_is_numpys_bit_for_bit() -> None:
    """The revolute closures' residual and drift take cross products at every RK4 stage;
    ``_cross`` gives ``np.cross``'s bits, of two 3-vectors and of a 3-vector with each row of
    a k x 3 matrix, without its per-call cost."""
    rng = np.random.default_rng(7)
    for _ in range(2000):
        a, b = rng.normal(size=3) * 10.0 ** rng.integers(-8, 8), rng.normal(size=3)
        rows = rng.normal(size=(int(rng.integers(1, 4)), 3))
        assert np.array_equal(_cross(a, b), np.cross(a, b))
        assert np.array_equal(_cross(a, rows), np.cross(a, rows))
    assert _cross(np.ones(3), np.zeros((0, 3))).shape == (0, 3)
