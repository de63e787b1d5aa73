"""Point grasps (``planar_point``, ``spatial_point``): J_h, its rank and the directions of
topological constraint against closed forms, and the penalty of eq. 13-14 workless on every
motion the linkage allows. The expected values are written from the geometry, not from the
code under test."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.dynamics import compiled
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.model.linkage import linkage_from_dict, load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import Axis, TaskSpace


def planar_chain(lengths: list[float], task: str = 'planar_point') -> LinkageDynamics:
    links = [{'name': f'l{i}', 'joint': 'revolute', 'length': a, 'mass': 1.0,
              'inertia': 0.01} for i, a in enumerate(lengths)]
    return LinkageDynamics(linkage_from_dict({'linkage': {
        'name': 'chain', 'task': task, 'links': links}}, '<test>'))


def constrained(dyn: LinkageDynamics, q: np.ndarray) -> np.ndarray:
    """The penalty projector of eq. 13 with M_d = I: ``sum_i n_i n_i^T``."""
    return dyn.constraints(q).projector()


def test_task_space_vocabulary() -> None:
    assert [t.dim for t in TaskSpace] == [3, 6, 2, 3]
    assert TaskSpace.PLANAR_POINT.frame_rows == (0, 1)
    assert TaskSpace.SPATIAL_POINT.frame_rows == (0, 1, 2)
    assert TaskSpace.PLANAR.axes == (Axis.X, Axis.Y, Axis.RZ)
    assert TaskSpace.SPATIAL_POINT.axes == (Axis.X, Axis.Y, Axis.Z)
    assert [t.rotation_dim for t in TaskSpace] == [1, 3, 0, 0]
    assert TaskSpace.PLANAR.point_grasp is TaskSpace.PLANAR_POINT
    assert TaskSpace.SPATIAL_POINT.rigid is TaskSpace.SPATIAL


@pytest.mark.parametrize('q1', [-2.5, -0.7, 0.0, 0.3, 1.9])
def test_one_link_is_constrained_radially_everywhere(q1: float) -> None:
    """One link of length 0.1 held at its COM (0.05 m from the joint) through a pin: the point
    moves on a circle, ``J_h = 0.05 (-sin q, cos q)^T``, the radial direction (cos q, sin q)
    is constrained at every q."""
    dyn = planar_chain([0.1])
    q = np.array([q1])
    c, s = np.cos(q1), np.sin(q1)
    np.testing.assert_allclose(dyn.hand_jacobian(q), [[-0.05 * s], [0.05 * c]], atol=1e-15)
    np.testing.assert_allclose(dyn.hand_pose(q), [0.05 * c, 0.05 * s], atol=1e-15)
    assert dyn.constraints(q).count == 1
    np.testing.assert_allclose(constrained(dyn, q), np.outer([c, s], [c, s]), atol=1e-12)


@pytest.mark.parametrize('q1', [-1.0, 0.0, 0.8])
def test_two_links_are_constrained_radially_at_full_stretch_only(q1: float) -> None:
    """Two links (0.1 m, held at the second's COM): at q2 = 0 both columns of J_h are
    perpendicular to the arm, so the radial direction (cos q1, sin q1) is constrained; bent,
    the point moves in the plane freely (t = 0)."""
    dyn = planar_chain([0.1, 0.1])
    c, s = np.cos(q1), np.sin(q1)
    stretched = np.array([q1, 0.0])
    np.testing.assert_allclose(dyn.hand_jacobian(stretched),
                               [[-0.15 * s, -0.05 * s], [0.15 * c, 0.05 * c]], atol=1e-15)
    assert dyn.constraints(stretched).count == 1
    np.testing.assert_allclose(constrained(dyn, stretched), np.outer([c, s], [c, s]),
                               atol=1e-12)
    bent = np.array([q1, 1.0])
    assert dyn.constraints(bent).count == 0
    np.testing.assert_array_equal(constrained(dyn, bent), np.zeros((2, 2)))


def test_point_jacobian_is_the_rigid_grasp_translation_rows() -> None:
    rng = np.random.default_rng(3)
    for rigid, point in ((TaskSpace.PLANAR, TaskSpace.PLANAR_POINT),
                         (TaskSpace.SPATIAL, TaskSpace.SPATIAL_POINT)):
        path = 'table1_planar3' if rigid is TaskSpace.PLANAR else 'spatial_arm4'
        lk = load_linkage(config_dir() / 'linkages' / f'{path}.yaml')
        full, held = LinkageDynamics(lk), LinkageDynamics(replace(lk, task=point))
        for _ in range(5):
            q = rng.uniform(-1.0, 1.0, lk.dof)
            rows = rigid.translation_rows
            np.testing.assert_array_equal(held.hand_jacobian(q), full.hand_jacobian(q)[rows])
            np.testing.assert_array_equal(held.hand_pose(q), full.hand_pose(q)[rows])
            f = rng.normal(size=point.dim)
            wrench = np.zeros(rigid.dim)
            wrench[rows] = f
            np.testing.assert_allclose(held.hand_wrench_torques(q, f),
                                       full.hand_wrench_torques(q, wrench), atol=1e-15)


def spatial_arm_at_fore_tip() -> LinkageDynamics:
    lk = load_linkage(config_dir() / 'linkages' / 'spatial_arm4.yaml')
    return LinkageDynamics(replace(lk.with_grasp('fore', np.array([0.08, 0.0, 0.0])),
                                   task=TaskSpace.SPATIAL_POINT))


@pytest.mark.parametrize('yaw,pitch', [(0.0, 0.0), (0.3, 0.4), (-1.2, -0.9)])
def test_spatial_arm_stretched_is_constrained_along_the_arm(yaw: float, pitch: float) -> None:
    """spatial_arm4 held through a ball joint at the forearm's tip (0.08 m beyond the elbow):
    yaw about z, then two pitches about y at the shoulder (0.05 m up) and at the elbow (0.1 m
    along the upper arm). Stretched (q3 = 0) the tip is 0.18 m from the shoulder along
    u = Rz(yaw) Ry(pitch) x; both pitches move it across u and the yaw sideways, so u is the
    one constrained direction. The slider beyond the grasp does not move it (a zero column)."""
    dyn = spatial_arm_at_fore_tip()
    q = np.array([yaw, pitch, 0.0, 0.02])
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    u = np.array([cy * cp, sy * cp, -sp])
    np.testing.assert_allclose(dyn.hand_pose(q), np.array([0.0, 0.0, 0.05]) + 0.18 * u,
                               atol=1e-15)
    j = dyn.hand_jacobian(q)
    assert j.shape == (3, 4)
    np.testing.assert_allclose(j[:, 3], 0.0, atol=1e-15)
    np.testing.assert_allclose(u @ j, 0.0, atol=1e-15)
    assert dyn.constraints(q).count == 1
    np.testing.assert_allclose(constrained(dyn, q), np.outer(u, u), atol=1e-12)
    assert dyn.constraints(np.array([yaw, pitch, -0.8, 0.02])).count == 0


@pytest.mark.parametrize('case', ['one_link', 'two_link_stretched', 'fourbar', 'spatial_arm'])
def test_penalty_does_no_work_on_any_allowed_motion(case: str) -> None:
    """Eq. 14's penalty wrench ``M_d P a`` (any error a, a device inertia M_d that is not I)
    is orthogonal to every hand velocity ``J_h qd`` the linkage allows: ``|F . J_h qd|``
    below 1e-12 of ``|F| |J_h qd|``."""
    rng = np.random.default_rng(11)
    if case == 'one_link':
        dyn, q = planar_chain([0.1]), np.array([0.7])
    elif case == 'two_link_stretched':
        dyn, q = planar_chain([0.1, 0.07]), np.array([-0.4, 0.0])
    elif case == 'fourbar':
        lk = load_linkage(config_dir() / 'linkages' / 'fourbar.yaml')
        dyn = LinkageDynamics(replace(lk, task=TaskSpace.PLANAR_POINT))
        q = np.array([1.5707963267948966, -2.6535164683936445, 1.68213734113586])
    else:
        dyn, q = spatial_arm_at_fore_tip(), np.array([0.3, 0.4, 0.0, 0.01])
    snap = dyn.snapshot(q, np.zeros(dyn.dof))
    assert snap.constraints.count >= 1
    m = dyn.task.dim
    m_d = np.diag(rng.uniform(0.5, 3.0, m))
    p = snap.constraints.projector(m_d)
    j = snap.hand_jacobian
    for _ in range(20):
        force = m_d @ p @ rng.normal(size=m)
        motion = j @ rng.normal(size=j.shape[1])
        assert abs(force @ motion) <= 1e-12 * np.linalg.norm(force) * np.linalg.norm(motion)
        assert np.linalg.norm(force) > 0.0


def test_compiled_pose_difference_of_a_point_is_a_plain_difference() -> None:
    """A spatial_point pose is 3 numbers like a planar one: its third entry (z, m) must not
    be wrapped as an angle."""
    a, b, out = np.array([0.1, 0.2, 4.0]), np.array([0.0, 0.0, 0.0]), np.empty(3)
    compiled.task_pose_difference(a, b, TaskSpace.SPATIAL_POINT.rotation_dim, out)
    np.testing.assert_array_equal(out, [0.1, 0.2, 4.0])
    out2 = np.empty(2)
    compiled.task_pose_difference(np.array([1.0, 2.0]), np.array([0.5, -1.0]), 0, out2)
    np.testing.assert_array_equal(out2, [0.5, 3.0])
    moved = np.array([0.1, 0.2])
    compiled.integrate_pose(moved, np.array([1.0, -1.0]), 0.5)
    np.testing.assert_array_equal(moved, [0.6, -0.3])


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_panda_elbow_is_constrained_radially_about_the_shoulder(seed: int) -> None:
    """panda_link4_point holds the Panda at panda_link4's origin, on the joint-4 axis. From the
    URDF: joint 1 about z at the base, joint 2 333 mm above it, joint 3 along the upper arm
    through the shoulder, joint 4 316 mm along it and 82.5 mm aside. Joints 1-3 turn about
    axes through the shoulder (0, 0, 0.333) and joints 4-7 do not move the point, so it lies
    at sqrt(0.316^2 + 0.0825^2) from the shoulder and the radial direction is constrained at
    every configuration (t = 1, rank J_h = 2)."""
    from haptic_topology.sim.scenario import load_scenario

    lk = load_scenario('panda_link4_point').linkage
    assert lk.task is TaskSpace.SPATIAL_POINT
    dyn = LinkageDynamics(lk)
    q = np.random.default_rng(seed).uniform(-2.5, 2.5, dyn.dof)
    shoulder = np.array([0.0, 0.0, 0.333])
    r = dyn.hand_pose(q) - shoulder
    assert np.linalg.norm(r) == pytest.approx(np.hypot(0.316, 0.0825), abs=1e-12)
    u = r / np.linalg.norm(r)
    j = dyn.hand_jacobian(q)
    assert j.shape == (3, 7)
    np.testing.assert_allclose(j[:, 3:], 0.0, atol=1e-15)
    np.testing.assert_allclose(u @ j, 0.0, atol=1e-15)
    assert dyn.constraints(q).count == 1
    np.testing.assert_allclose(constrained(dyn, q), np.outer(u, u), atol=1e-12)
