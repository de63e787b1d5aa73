"""Issue 14 item 2 (core): the URDF of a linkage and the link frames of /tf.

The generated URDF is read back by Pinocchio's own URDF parser and compared with
``build_model`` (joint placements, axes, inertias, forward kinematics at random q), and read
back as a linkage by ``load_linkage`` (same mass matrix); the transforms of ``/tf`` composed
from the world down are compared with the dynamics' forward kinematics (``oMi`` of
``LinkageDynamics``) and its grasp frame, for the repository's linkages (planar Table I, the
spatial arm with a prismatic joint, the Panda's own URDF) and for linkages with tilted origins
and unaligned axes.
"""

from __future__ import annotations

import dataclasses
import doctest
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import LinkageError
from haptic_topology.model import Linkage, frames, linkage_from_dict, load_linkage
from haptic_topology.model import urdf as urdf_module
from haptic_topology.model.build import build_model
from haptic_topology.model.linkage import serial_chain
from haptic_topology.model.urdf import (
    LinkFrames,
    joint_placement,
    linkage_urdf,
    parse_urdf,
    robot_description,
)
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

LINKAGES = config_dir() / 'linkages'
TOL = 1e-12


def _planar_prismatic() -> Linkage:
    """Planar: a revolute, a prismatic joint sliding along a tilted in-plane axis, a yawed
    origin, a z offset."""
    return linkage_from_dict({'linkage': {
        'name': 'planar_slider', 'task': 'planar', 'links': [
            {'name': 'a', 'joint': 'revolute', 'length': 0.05, 'mass': 1.0, 'inertia': 0.01},
            {'name': 'b', 'joint': 'prismatic', 'axis': [0.6, 0.8, 0.0], 'length': 0.04,
             'mass': 0.5, 'inertia': 0.002,
             'origin': {'xyz': [0.05, 0.01, 0.002], 'rpy': [0.0, 0.0, 0.3]}},
            {'name': 'c', 'joint': 'revolute', 'length': 0.03, 'mass': 0.2, 'inertia': 0.001,
             'com': [0.01, 0.005, 0.0]}],
        'grasp': {'link': 'c', 'point': [0.02, 0.001, 0.0]}}}, '<planar_slider>')


def _spatial_tilted() -> Linkage:
    """Spatial: unaligned axes, tilted origins (all three rpy angles), full inertia tensors."""
    return linkage_from_dict({'linkage': {
        'name': 'tilted', 'task': 'spatial', 'gravity': [0.0, 0.0, -9.81], 'links': [
            {'name': 'l1', 'joint': 'revolute', 'axis': [0.0, 0.3, 1.0], 'length': 0.1,
             'mass': 1.0, 'inertia': [0.01, 0.02, 0.03, 0.001, 0.002, 0.003],
             'origin': {'xyz': [0.01, -0.02, 0.03], 'rpy': [0.1, -0.2, 0.3]}},
            {'name': 'l2', 'joint': 'prismatic', 'axis': [1.0, -1.0, 0.5], 'length': 0.08,
             'mass': 0.5, 'inertia': [0.004, 0.005, 0.006],
             'origin': {'xyz': [0.1, 0.0, 0.02], 'rpy': [0.7, 0.0, -0.4]}},
            {'name': 'l3', 'joint': 'revolute', 'axis': [1.0, 0.0, 0.0], 'length': 0.06,
             'mass': 0.3, 'com': [0.03, 0.01, -0.01], 'inertia': [0.001, 0.002, 0.002]}],
        'grasp': {'link': 'l2'}}}, '<tilted>')


CASES = {
    'table1_planar3': lambda: load_linkage(LINKAGES / 'table1_planar3.yaml'),
    'spatial_arm4': lambda: load_linkage(LINKAGES / 'spatial_arm4.yaml'),
    'panda_link4': lambda: load_linkage(LINKAGES / 'panda_link4.yaml'),
    'arm3_collision': lambda: load_linkage(LINKAGES / 'arm3_collision.yaml'),
    'planar_slider': _planar_prismatic,
    'tilted': _spatial_tilted,
    'chain7_spatial': lambda: serial_chain(7, TaskSpace.SPATIAL),
}


@pytest.fixture(params=sorted(CASES))
def linkage(request: pytest.FixtureRequest) -> Linkage:
    return CASES[request.param]()


def _random_q(lk: Linkage, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(-math.pi, math.pi, lk.dof) * np.array(
        [0.05 if link.joint.value == 'prismatic' else 1.0 for link in lk.links])


def _urdf_q(model: pin.Model, lk: Linkage, q: np.ndarray) -> np.ndarray:
    """The q of a model read from the generated URDF (continuous joints: cos, sin)."""
    out = pin.neutral(model)
    for link, v in zip(lk.links, q, strict=True):
        jm = model.joints[model.getJointId(link.joint_label)]
        if jm.nq == 2:
            out[jm.idx_q:jm.idx_q + 2] = [math.cos(v), math.sin(v)]
        else:
            out[jm.idx_q] = v
    return out


def _assert_se3(a: pin.SE3, b: pin.SE3, what: str) -> None:
    np.testing.assert_allclose(a.translation, b.translation, rtol=0, atol=TOL, err_msg=what)
    np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=TOL, err_msg=what)


# -- the generated URDF against build_model -----------------------------------------------------
def test_generated_urdf_matches_build_model(linkage: Linkage) -> None:
    ours = build_model(linkage).model
    model = pin.buildModelFromXML(linkage_urdf(linkage))
    assert model.njoints == ours.njoints == linkage.dof + 1
    for j, link in enumerate(linkage.links, start=1):
        jid = model.getJointId(link.joint_label)
        assert jid == j and model.parents[j] == j - 1
        # where the joint sits in its parent and how it moves: the motion subspace at 0
        _assert_se3(model.jointPlacements[j], ours.jointPlacements[j], link.joint_label)
        s = []
        for m in (model, ours):
            jd = m.joints[j].createData()
            m.joints[j].calc(jd, pin.neutral(m))
            s.append(np.asarray(jd.S).reshape(6))
        np.testing.assert_allclose(s[0], s[1], rtol=0, atol=TOL, err_msg=link.joint_label)
        a, b = model.inertias[j], ours.inertias[j]
        assert a.mass == pytest.approx(b.mass, rel=0, abs=TOL)
        np.testing.assert_allclose(a.lever, b.lever, rtol=0, atol=TOL)
        np.testing.assert_allclose(a.inertia, b.inertia, rtol=0, atol=TOL)
    rng = np.random.default_rng(14)
    data, ours_data = model.createData(), ours.createData()
    for _ in range(20):
        q = _random_q(linkage, rng)
        pin.forwardKinematics(model, data, _urdf_q(model, linkage, q))
        pin.forwardKinematics(ours, ours_data, q)
        for j in range(1, ours.njoints):
            _assert_se3(data.oMi[j], ours_data.oMi[j], f'oMi[{j}] at q={q.tolist()}')


def test_generated_urdf_joint_placements_by_hand() -> None:
    """Joint placements against the YAML's numbers (not against build_model): Table I's
    joints sit at [l_{i-1}, 0, 0]; spatial_arm4's 'upper' at its origin [0, 0, 0.05]."""
    lk = load_linkage(LINKAGES / 'table1_planar3.yaml')
    _, joints, links = parse_urdf(linkage_urdf(lk), 't1')
    assert links == ('base_link', 'link1', 'link2', 'link3')
    assert [(j.name, j.kind, j.parent, j.child) for j in joints] == [
        ('joint_link1', 'continuous', 'base_link', 'link1'),
        ('joint_link2', 'continuous', 'link1', 'link2'),
        ('joint_link3', 'continuous', 'link2', 'link3')]
    model = pin.buildModelFromXML(linkage_urdf(lk))
    assert [model.jointPlacements[j].translation.tolist() for j in (1, 2, 3)] == [
        [0.0, 0.0, 0.0], [0.042, 0.0, 0.0], [0.042, 0.0, 0.0]]
    arm = load_linkage(LINKAGES / 'spatial_arm4.yaml')
    model = pin.buildModelFromXML(linkage_urdf(arm))
    assert model.jointPlacements[2].translation.tolist() == [0.0, 0.0, 0.05]
    assert model.jointPlacements[4].translation.tolist() == [0.08, 0.0, 0.0]
    assert model.joints[4].shortname().startswith('JointModelP')     # the prismatic slider
    assert joint_placement(arm, 3).translation.tolist() == [0.08, 0.0, 0.0]


def test_generated_urdf_reads_back_as_the_same_linkage(linkage: Linkage,
                                                       tmp_path: Path) -> None:
    """load_linkage of the written URDF: same task, joints and mass matrix at random q."""
    path = tmp_path / f'{linkage.name}.urdf'
    path.write_text(linkage_urdf(linkage))
    back = load_linkage(path).with_grasp(linkage.grasp_link, linkage.grasp_point)
    assert back.task is linkage.task
    assert [link.joint_label for link in back.links] == [k.joint_label for k in linkage.links]
    a, b = LinkageDynamics(linkage), LinkageDynamics(back)
    rng = np.random.default_rng(3)
    for _ in range(10):
        q = _random_q(linkage, rng)
        np.testing.assert_allclose(b.mass_matrix(q), a.mass_matrix(q), rtol=0, atol=TOL)
        _assert_se3(b.hand_placement(q), a.hand_placement(q), 'hand')


# -- /tf against the dynamics' forward kinematics -----------------------------------------------
def test_tf_link_frames_equal_the_dynamics_forward_kinematics(linkage: Linkage) -> None:
    dyn = LinkageDynamics(linkage)
    desc = robot_description(linkage)
    assert desc.generated is (linkage.urdf_path is None)
    tf = LinkFrames(desc, world='map')
    assert tf.edges[0] == ('map', desc.root_link)
    assert tf.edges[-1] == (linkage.grasp_link, frames.VT_HAND)
    children = [c for _, c in tf.edges]
    assert len(children) == len(set(children)), 'a frame with two parents'
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = _random_q(linkage, rng)
        pin.forwardKinematics(dyn.model, dyn.data, q)
        oMi = [dyn.data.oMi[j].copy() for j in range(1, dyn.model.njoints)]
        for link, placement in zip(linkage.links, oMi, strict=True):
            _assert_se3(tf.link_placement(q, link.name), placement, f'{link.name} q={q}')
        _assert_se3(tf.link_placement(q, frames.VT_HAND), dyn.hand_placement(q), 'vt_hand')
        rows = tf.transforms(q)
        np.testing.assert_allclose(np.linalg.norm(rows[:, 3:7], axis=1), 1.0, atol=1e-12)


def test_tf_rows_are_parent_to_child_joint_transforms() -> None:
    """Each URDF joint's row is origin * joint motion (robot_state_publisher's transform):
    Table I's joint 2 at q2 is [0.042, 0, 0] turned by q2 about z."""
    lk = load_linkage(LINKAGES / 'table1_planar3.yaml')
    tf = LinkFrames(robot_description(lk))
    q = np.array([0.3, -0.7, 1.1])
    rows = tf.transforms(q)
    row = rows[tf.edges.index(('link1', 'link2'))]
    np.testing.assert_allclose(row[0:3], [0.042, 0.0, 0.0], atol=TOL)
    np.testing.assert_allclose(row[3:7], [0.0, 0.0, math.sin(-0.35), math.cos(-0.35)],
                               atol=TOL)
    assert rows[tf.edges.index(('world', 'base_link'))].tolist() == [0, 0, 0, 0, 0, 0, 1]
    np.testing.assert_allclose(rows[-1], [*lk.grasp_point, 0, 0, 0, 1], atol=0)


# -- the user's own URDF ------------------------------------------------------------------------
def test_urdf_linkage_publishes_the_users_file_with_side_branches() -> None:
    lk = load_linkage(LINKAGES / 'panda_link4.yaml')
    desc = robot_description(lk)
    assert lk.urdf_path is not None
    assert desc.urdf == lk.urdf_path.read_text() and not desc.generated
    assert desc.root_link == 'panda_link0'
    assert desc.joint_names == tuple(f'panda_joint{i}' for i in range(1, 8)) + (
        'panda_finger_joint1', 'panda_finger_joint2')
    assert desc.locked == (0.0, 0.0)
    tf = LinkFrames(desc)
    # every URDF link has a frame (fixed ones too: the hand, its TCP, the fingers)
    children = {c for _, c in tf.edges}
    _, _, links = parse_urdf(desc.urdf, 'panda')
    assert set(links) - {'panda_link0'} <= children


def test_locked_side_branch_joints_stand_at_the_yaml_positions(tmp_path: Path) -> None:
    src = yaml.safe_load((LINKAGES / 'panda_link4.yaml').read_text())
    src['linkage']['locked_joints'] = {'panda_finger_joint1': 0.03}
    for key in ('urdf', 'srdf'):    # relative to the shipped file, not to tmp_path
        src['linkage'][key] = str((LINKAGES / src['linkage'][key]).resolve())
    path = tmp_path / 'panda_open.yaml'
    path.write_text(yaml.safe_dump(src))
    lk = load_linkage(path)
    desc = robot_description(lk)
    assert desc.locked == (0.03, 0.0)
    assert urdf_module.locked_positions(lk) == {'panda_finger_joint1': 0.03}
    tf = LinkFrames(desc)
    q = np.zeros(lk.dof)
    hand = tf.link_placement(q, 'panda_hand')
    left = tf.link_placement(q, 'panda_leftfinger')
    right = tf.link_placement(q, 'panda_rightfinger')
    # the Panda's fingers slide along +-y of the hand: 0.03 m open against 0 m
    np.testing.assert_allclose(hand.actInv(left).translation[1], 0.03, atol=TOL)
    np.testing.assert_allclose(hand.actInv(right).translation[1], 0.0, atol=TOL)
    # an explicit mapping wins over the YAML
    assert robot_description(lk, locked={}).locked == (0.0, 0.0)


def test_urdf_without_the_linkage_joint_is_refused() -> None:
    lk = load_linkage(LINKAGES / 'panda_link4.yaml')
    renamed = dataclasses.replace(lk.links[2], joint_name='elbow')
    other = dataclasses.replace(lk, links=(*lk.links[:2], renamed, *lk.links[3:]))
    with pytest.raises(LinkageError, match=r"has joint 'elbow' \(revolute\) moving link "
                                           r"'panda_link3'; the URDF has none"):
        robot_description(other)
    moved = dataclasses.replace(lk.links[2], name='panda_link5')
    other = dataclasses.replace(lk, links=(*lk.links[:2], moved, *lk.links[3:]))
    with pytest.raises(LinkageError, match="the URDF has a revolute joint moving "
                                           "'panda_link3'"):
        robot_description(other)


def test_link_named_as_a_graph_frame_is_refused() -> None:
    lk = linkage_from_dict({'linkage': {'links': [
        {'name': 'device', 'joint': 'revolute', 'length': 0.1, 'mass': 1.0,
         'inertia': 0.01}]}}, '<clash>')
    with pytest.raises(LinkageError, match='link name.s. device are frames of the graph'):
        robot_description(lk)


def test_root_link_avoids_a_link_named_base_link() -> None:
    lk = linkage_from_dict({'linkage': {'name': 'arm', 'links': [
        {'name': 'base_link', 'joint': 'revolute', 'length': 0.1, 'mass': 1.0,
         'inertia': 0.01}]}}, '<root>')
    desc = robot_description(lk)
    assert desc.root_link == 'arm_base_link'
    assert parse_urdf(desc.urdf, 'arm')[0] == 'arm_base_link'


def test_parse_urdf_errors() -> None:
    with pytest.raises(LinkageError, match='x: not a valid URDF'):
        parse_urdf('<robot', 'x')
    with pytest.raises(LinkageError, match='x: expected a <robot> element, got <model>'):
        parse_urdf('<model/>', 'x')
    with pytest.raises(LinkageError, match=r"x: expected one root link, got \['a', 'b'\]"):
        parse_urdf('<robot name="r"><link name="a"/><link name="b"/></robot>', 'x')


# -- frames -------------------------------------------------------------------------------------
def test_task_poses_and_wrenches_in_3d() -> None:
    t, quat = frames.pose_transform(np.array([0.1, -0.2, 2.5]), TaskSpace.PLANAR, z=0.3)
    assert t.tolist() == [0.1, -0.2, 0.3]
    rot = pin.Quaternion(quat[3], *quat[0:3]).matrix()
    np.testing.assert_allclose(rot, pin.rpy.rpyToMatrix(0.0, 0.0, 2.5), atol=TOL)
    pose = np.array([0.1, 0.2, 0.3, 0.4, -0.5, 0.6])
    t, quat = frames.pose_transform(pose, TaskSpace.SPATIAL)
    assert t.tolist() == [0.1, 0.2, 0.3]
    np.testing.assert_allclose(pin.Quaternion(quat[3], *quat[0:3]).matrix(),
                               pin.exp3(pose[3:6]), atol=TOL)
    assert frames.spatial(np.array([1.0, 2.0, 3.0]), TaskSpace.PLANAR).tolist() == [
        1.0, 2.0, 0.0, 0.0, 0.0, 3.0]
    # a wrench in a frame turned by 90 degrees about z: x force becomes -y
    rz = frames.pose_rotation(np.array([0.0, 0.0, math.pi / 2]), TaskSpace.PLANAR)
    w = frames.wrench_in_frame(np.array([1.0, 0.0, 0.5]), rz, TaskSpace.PLANAR)
    np.testing.assert_allclose(w, [0.0, -1.0, 0.0, 0.0, 0.0, 0.5], atol=TOL)


def test_docstring_examples() -> None:
    assert doctest.testmod(urdf_module).failed == 0
    assert doctest.testmod(frames).failed == 0


def test_a_urdf_file_is_parsed_once_for_the_linkage_and_its_robot_description(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Loading a URDF linkage (YAML naming a URDF, with side branches locked) and making its
    robot description and /tf frames read and parse the file once (issue 25: it was parsed
    three times by the loader and a fourth time for the robot description)."""
    from haptic_topology.model import urdf_import
    from haptic_topology.model.urdf import LinkFrames, robot_description

    urdf_import._read.cache_clear()
    parsed: list[int] = []
    fromstring = urdf_import.ET.fromstring

    def counting(text: str, *args: object) -> object:
        parsed.append(len(text))
        return fromstring(text, *args)

    monkeypatch.setattr(urdf_import.ET, 'fromstring', counting)
    reads: list[Path] = []
    read_text = Path.read_text

    def counting_read(self: Path, *args: object, **kwargs: object) -> str:
        if self.suffix == '.urdf':
            reads.append(self)
        return read_text(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, 'read_text', counting_read)
    lk = load_linkage(config_dir() / 'linkages' / 'panda_link4.yaml')
    assert lk.urdf is not None and lk.notes      # side branches (the fingers) locked
    desc = robot_description(lk)
    LinkFrames(desc)
    assert len(reads) == 1 and len(parsed) == 1
    assert desc.urdf == lk.urdf.text and desc.source is lk.urdf


@pytest.mark.parametrize('name', ['fourbar', 'bennett'])
def test_a_closed_chains_urdf_carries_its_closures_as_extras(name: str) -> None:
    """URDF has no loops: the tree is the serial chain, and each closure follows as a
    ``<haptic_topology_loop>`` element whose attributes give the closure back exactly (the
    world as the root link); Pinocchio reads the URDF as the tree it is."""
    import xml.etree.ElementTree as ET

    lk = load_linkage(config_dir() / 'linkages' / f'{name}.yaml')
    rd = robot_description(lk)
    elements = ET.fromstring(rd.urdf.split('\n', 1)[1]).findall('haptic_topology_loop')
    assert len(elements) == len(lk.loops) == 1
    (el,), (loop,) = elements, lk.loops
    assert (el.get('name'), el.get('kind'), el.get('link'), el.get('to')) == (
        loop.name, loop.kind.value, loop.link, rd.root_link)
    for attr, value in (('point', loop.point), ('to_point', loop.to_point),
                        ('axis', loop.axis), ('to_axis', loop.to_axis)):
        if value is None:
            assert el.get(attr) is None
        else:
            np.testing.assert_array_equal([float(v) for v in el.get(attr, '').split()], value)
    assert pin.buildModelFromXML(rd.urdf).nv == lk.dof
