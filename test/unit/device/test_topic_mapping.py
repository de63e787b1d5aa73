"""Device frame <-> task vectors of the ``ros_topics`` backend
(``haptic_topology/device/topic_mapping.py``; no ROS): the module doc's example, round trips
both ways, the plain-float products against numpy/Pinocchio, the planar angle kept continuous
across +-pi, invalid samples refused."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from haptic_topology.device.topic_mapping import (
    TopicMapping,
    matrix_to_quat,
    parse_topic_options,
    quat_to_matrix,
    rotz,
)
from haptic_topology.vocabulary import TaskSpace

TOPICS = {'pose_topic': '/p', 'twist_topic': '/t', 'command_topic': '/c'}


def _mapping(task: TaskSpace, **opts: object) -> TopicMapping:
    return parse_topic_options({**TOPICS, **opts}, task).mapping


def test_module_doc_example() -> None:
    m = _mapping(TaskSpace.PLANAR, axes=['y', '-x', 'z'], scale=0.001, origin=[0.1, 0.0, 0.0])
    pose = m.pose((10.0, 20.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    assert pose is not None
    np.testing.assert_allclose(pose, [0.12, -0.01, -math.pi / 2], rtol=0.0, atol=1e-15)
    f, t = m.command(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(f, [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(t, [0.0, 0.0, 0.0], atol=1e-15)


def test_axis_names_are_rows_of_the_rotation() -> None:
    m = _mapping(TaskSpace.SPATIAL, axes=['x', '-z', 'y'])
    np.testing.assert_array_equal(m.rotation, [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    # task y is device -z: a device velocity along +z is a task velocity along -y
    tw = m.twist((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    assert tw is not None
    np.testing.assert_allclose(tw, [0.0, -2.0, 0.0, 0.0, 0.0, 0.0], atol=1e-15)


#: Mappings by name: options, plus the origin for each task space (planar x, y, theta;
#: spatial x, y, z and a rotation vector). A tilted axis matrix is fine for a planar task too:
#: the plane is whatever the mapping makes the task's x-y plane.
MAPPINGS: dict[str, tuple[dict[str, object], list[float], list[float]]] = {
    'identity': ({}, [0.0, 0.0, 0.0], [0.0] * 6),
    'planar_turned_mm': ({'axes': ['y', '-x', 'z'], 'scale': 0.001, 'force_scale': 0.5,
                          'torque_scale': 0.001},
                         [0.01, -0.02, 2.9], [0.01, -0.02, 0.05, 0.0, 0.0, 2.9]),
    'tilted_matrix': ({'axes': [[1.0, 0.0, 0.0], [0.0, math.cos(0.5), -math.sin(0.5)],
                                [0.0, math.sin(0.5), math.cos(0.5)]],
                       'scale': 0.001, 'force_scale': 2.0, 'torque_scale': 0.01},
                      [0.1, 0.2, 0.3], [0.1, 0.2, 0.3, 0.3, -0.2, 1.0]),
}


@pytest.mark.parametrize('name', sorted(MAPPINGS))
@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
def test_round_trips_and_products_match_numpy(name: str, task: TaskSpace) -> None:
    opts, planar_origin, spatial_origin = MAPPINGS[name]
    opts = {**opts, 'origin': planar_origin if task is TaskSpace.PLANAR else spatial_origin}
    m = _mapping(task, **opts)
    rng = np.random.default_rng(7)
    mt = m.rotation.T
    for _ in range(50):
        if task is TaskSpace.PLANAR:
            pose = np.array([*rng.uniform(-0.1, 0.1, 2), rng.uniform(-3.0, 3.0)])
        else:
            pose = np.concatenate([rng.uniform(-0.1, 0.1, 3), rng.uniform(-1.0, 1.0, 3)])
        twist, wrench = rng.normal(size=task.dim), rng.normal(size=task.dim)
        p, q = m.device_pose(pose)
        back = m.pose(tuple(p), q, previous_theta=pose[2] if task is TaskSpace.PLANAR else None)
        assert back is not None
        if task is TaskSpace.PLANAR:
            np.testing.assert_allclose(back, pose, rtol=0.0, atol=1e-12)
        else:
            np.testing.assert_allclose(back[:3], pose[:3], rtol=0.0, atol=1e-12)
            np.testing.assert_allclose(pin.exp3(back[3:]), pin.exp3(pose[3:]), atol=1e-12)
        # the forward map against numpy: p_T = p_o + M s p_D, R_T = M R_D
        r_d = quat_to_matrix(*q)
        assert r_d is not None
        np.testing.assert_allclose(m.origin + m.rotation @ (m.scale * p),
                                   [*pose[:2], 0.0] if task is TaskSpace.PLANAR else pose[:3],
                                   atol=1e-12)
        v, w = m.device_twist(twist)
        got = m.twist(tuple(v), tuple(w))
        assert got is not None
        np.testing.assert_allclose(got, twist, rtol=0.0, atol=1e-12)
        f, t = m.device_wrench(wrench)
        got = m.hand_wrench(tuple(f), tuple(t))
        assert got is not None
        np.testing.assert_allclose(got, wrench, rtol=0.0, atol=1e-12)
        cf, ct = m.command(wrench)
        full = ([wrench[0], wrench[1], 0.0, 0.0, 0.0, wrench[2]] if task is TaskSpace.PLANAR
                else wrench)
        np.testing.assert_allclose(cf, mt @ np.asarray(full[:3]) / m.force_scale, atol=1e-12)
        np.testing.assert_allclose(ct, mt @ np.asarray(full[3:]) / m.torque_scale, atol=1e-12)
        back_cmd = m.task_command(cf, ct)
        assert back_cmd is not None
        np.testing.assert_allclose(back_cmd, wrench, rtol=0.0, atol=1e-12)


def test_planar_angle_stays_continuous_across_pi() -> None:
    """A handle turning steadily through +-pi: theta goes on past pi (no jump of 2 pi)."""
    m = _mapping(TaskSpace.PLANAR)
    prev = None
    thetas = []
    for yaw in np.linspace(2.5, 4.5, 41):
        q = matrix_to_quat(rotz(float(yaw)))
        pose = m.pose((0.0, 0.0, 0.0), q, prev)
        assert pose is not None
        prev = float(pose[2])
        thetas.append(prev)
    np.testing.assert_allclose(thetas, np.linspace(2.5, 4.5, 41), atol=1e-12)


@pytest.mark.parametrize(('p', 'q'), [
    ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ((0.0, math.inf, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),        # unset quaternion
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.5)),        # not a unit quaternion
    ((0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0)),
])
@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
def test_invalid_samples_are_refused(p: tuple[float, float, float],
                                     q: tuple[float, float, float, float],
                                     task: TaskSpace) -> None:
    m = _mapping(task)
    assert m.pose(p, q) is None
    assert m.twist((0.0, math.nan, 0.0), (0.0, 0.0, 0.0)) is None
    assert m.hand_wrench((0.0, 0.0, 0.0), (math.inf, 0.0, 0.0)) is None
    assert m.task_command((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0)) is None


def test_nearly_unit_quaternion_is_normalised() -> None:
    m = _mapping(TaskSpace.SPATIAL)
    s = 1.005
    pose = m.pose((0.0, 0.0, 0.0), (0.0, 0.0, s * math.sin(0.2), s * math.cos(0.2)))
    assert pose is not None
    np.testing.assert_allclose(pose[3:], [0.0, 0.0, 0.4], atol=1e-12)
