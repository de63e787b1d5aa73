"""Issue 12 item 1: one-joint linkages, URDF joints and origins, planar URDFs, the default
characteristic length, branched URDFs and the unit check of ``characteristic_length``."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
import yaml

from haptic_topology.dynamics import LinkageDynamics, pose_difference
from haptic_topology.errors import LinkageError
from haptic_topology.model import linkage_from_dict, load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

TABLE1 = config_dir() / 'linkages' / 'table1_planar3.yaml'


# -- hand-computed forward kinematics (URDF conventions) ------------------------------------
def _rpy(r: float, p: float, y: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                              math.cos(y), math.sin(y))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _axis_angle(axis: np.ndarray, a: float) -> np.ndarray:
    """Rodrigues' formula for a rotation of ``a`` rad about the unit vector ``axis``."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx


def _hom(rot: np.ndarray, xyz: Any) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = xyz
    return t


def _fk(joints: list[tuple[str, Any, Any, Any]], q: np.ndarray) -> np.ndarray:
    """World transform of the last frame of a chain of (type, xyz, rpy, axis) joints."""
    t = np.eye(4)
    k = 0
    for kind, xyz, rpy, axis in joints:
        t = t @ _hom(_rpy(*rpy), xyz)
        if kind in ('revolute', 'continuous'):
            t = t @ _hom(_axis_angle(np.array(axis), q[k]), np.zeros(3))
            k += 1
        elif kind == 'prismatic':
            a = np.asarray(axis, dtype=float)
            t = t @ _hom(np.eye(3), a / np.linalg.norm(a) * q[k])
            k += 1
    return t


def _urdf(name: str, joints: list[tuple[str, str, str, str, Any, Any, Any]],
          masses: dict[str, float], extra: str = '') -> str:
    """A URDF with links ``masses`` (inertial at x = 0.01) and (name, type, parent, child,
    xyz, rpy, axis) joints."""
    links = []
    for link, mass in masses.items():
        if mass == 0.0:
            links.append(f'<link name="{link}"/>')
        else:
            links.append(
                f'<link name="{link}"><inertial><origin xyz="0.01 0 0"/><mass value="{mass}"/>'
                '<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.002"/>'
                '</inertial></link>')
    js = []
    for jname, kind, parent, child, xyz, rpy, axis in joints:
        limit = ('<limit lower="-3" upper="3" effort="1" velocity="1"/>'
                 if kind in ('revolute', 'prismatic') else '')
        ax = f'<axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>' if axis is not None else ''
        js.append(f'<joint name="{jname}" type="{kind}"><parent link="{parent}"/>'
                  f'<child link="{child}"/><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" '
                  f'rpy="{rpy[0]} {rpy[1]} {rpy[2]}"/>{ax}{limit}</joint>')
    return (f'<?xml version="1.0"?>\n<robot name="{name}">{extra}\n' + '\n'.join(links) +
            '\n' + '\n'.join(js) + '\n</robot>\n')


def _write_urdf(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / f'{name}.urdf'
    p.write_text(text)
    return p


def _wrap(tmp_path: Path, urdf: Path, **linkage: Any) -> Path:
    p = tmp_path / f'{urdf.stem}_wrap.yaml'
    p.write_text(yaml.safe_dump({'linkage': dict(urdf=str(urdf), **linkage)}))
    return p


def _fd_jacobian(dyn: LinkageDynamics, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(q.size):
        dq = np.zeros(q.size)
        dq[i] = h
        cols.append(pose_difference(dyn.hand_pose(q + dq), dyn.hand_pose(q - dq), dyn.task)
                    / (2 * h))
    return np.array(cols).T


# -- a. one-joint linkages ---------------------------------------------------------------------
@pytest.mark.parametrize('task', ['planar', 'spatial'])
@pytest.mark.parametrize('joint', ['revolute', 'prismatic'])
def test_one_joint_linkage(task: str, joint: str) -> None:
    link: dict[str, Any] = {'name': 'only', 'joint': joint, 'length': 0.1, 'mass': 0.5,
                            'inertia': 0.002 if task == 'planar' else [0.001, 0.002, 0.002]}
    if task == 'spatial':
        link['axis'] = [0, 0, 1] if joint == 'revolute' else [1, 0, 0]
    lk = linkage_from_dict({'linkage': {'task': task, 'links': [link]}})
    dyn = LinkageDynamics(lk)
    q = np.array([0.3])
    pose = dyn.hand_pose(q)
    j = dyn.hand_jacobian(q)
    m = lk.task.dim
    assert j.shape == (m, 1)
    if joint == 'revolute':
        np.testing.assert_allclose(pose[:2], [0.05 * math.cos(0.3), 0.05 * math.sin(0.3)])
        np.testing.assert_allclose(j[:2, 0], [-0.05 * math.sin(0.3), 0.05 * math.cos(0.3)])
        mass = 0.5 * 0.05 ** 2 + 0.002
    else:
        np.testing.assert_allclose(pose[:2], [0.35, 0.0])
        np.testing.assert_allclose(j[:, 0], np.eye(m)[0])
        mass = 0.5
    np.testing.assert_allclose(j, _fd_jacobian(dyn, q), atol=1e-8)
    d = dyn.mass_matrix(q)
    assert d.shape == (1, 1)
    np.testing.assert_allclose(d, [[mass]], rtol=1e-12)
    np.testing.assert_allclose(dyn.forward_dynamics(q, np.zeros(1), np.array([1.0])),
                               [1.0 / mass], rtol=1e-12)
    cons = dyn.constraints(q)
    assert cons.count == m - 1
    snap = dyn.snapshot(q, np.array([0.1]))
    assert snap.hand_jacobian.shape == (m, 1) and snap.constraints.count == m - 1
    assert dyn.inverse_operational_inertia(q).shape == (m, m)


# -- b. URDF continuous / revolute / prismatic / fixed joints with origins and axes ---------------
SPATIAL_JOINTS = [
    ('mount', 'fixed', 'base', 'plate', (0.01, 0.0, 0.02), (0.0, 0.0, 0.2), None),
    ('j1', 'continuous', 'plate', 'l1', (0.0, 0.0, 0.05), (0.0, 0.0, 0.3), (0, 0, 1)),
    ('j2', 'revolute', 'l1', 'l2', (0.1, 0.0, 0.0), (0.2, -0.1, 0.4), (0, 1, 0)),
    ('j3', 'prismatic', 'l2', 'l3', (0.08, 0.01, 0.0), (0.0, 0.5, 0.0), (0.6, 0.8, 0)),
    ('tip_joint', 'fixed', 'l3', 'tip', (0.03, 0.0, 0.0), (0.0, 0.0, 0.7), None),
]
SPATIAL_MASSES = {'base': 0.0, 'plate': 0.0, 'l1': 1.0, 'l2': 0.7, 'l3': 0.3, 'tip': 0.0}


def _chain(joints: list[tuple[str, str, str, str, Any, Any, Any]]
           ) -> list[tuple[str, Any, Any, Any]]:
    return [(kind, xyz, rpy, axis) for _, kind, _, _, xyz, rpy, axis in joints]


def test_urdf_joint_types_origins_and_axes(tmp_path: Path) -> None:
    urdf = _write_urdf(tmp_path, 'arm', _urdf('arm', SPATIAL_JOINTS, SPATIAL_MASSES))
    point = [0.02, 0.01, -0.005]
    lk = load_linkage(_wrap(tmp_path, urdf, task='spatial',
                            grasp={'link': 'l3', 'point': point}))
    assert lk.dof == 3 and lk.link_names == ('l1', 'l2', 'l3')
    dyn = LinkageDynamics(lk)
    chain = _chain(SPATIAL_JOINTS[:4])
    for q in (np.zeros(3), np.array([0.4, -0.7, 0.02]), np.array([2.9, 1.1, -0.03])):
        t = _fk(chain, q) @ _hom(np.eye(3), point)
        placement = dyn.hand_placement(q)
        np.testing.assert_allclose(placement.translation, t[:3, 3], atol=1e-12)
        np.testing.assert_allclose(placement.rotation, t[:3, :3], atol=1e-12)
        np.testing.assert_allclose(dyn.hand_jacobian(q), _fd_jacobian(dyn, q), atol=1e-7)


def test_bare_urdf_with_a_continuous_joint_loads(tmp_path: Path) -> None:
    urdf = _write_urdf(tmp_path, 'arm', _urdf('arm', SPATIAL_JOINTS, SPATIAL_MASSES))
    lk = load_linkage(urdf)
    assert lk.task is TaskSpace.SPATIAL and lk.grasp_link == 'l3'
    # Reach: |j1->j2| + |j2->j3| + the tip frame fixed 3 cm beyond j3.
    reach = 0.1 + math.hypot(0.08, 0.01) + 0.03
    assert lk.constraints.characteristic_length == pytest.approx(reach)


# -- c. planar linkages from URDF ---------------------------------------------------------------
PLANAR_JOINTS = [
    ('j1', 'revolute', 'base', 'l1', (0.0, 0.0, 0.01), (0.0, 0.0, 0.5), (0, 0, 1)),
    ('j2', 'continuous', 'l1', 'l2', (0.05, 0.01, 0.0), (0.0, 0.0, -0.2), (0, 0, -1)),
    ('j3', 'prismatic', 'l2', 'l3', (0.04, 0.0, 0.0), (0.0, 0.0, 0.3), (0.6, 0.8, 0)),
]
PLANAR_MASSES = {'base': 0.0, 'l1': 1.0, 'l2': 0.7, 'l3': 0.3}


def test_planar_urdf_builds_the_planar_model(tmp_path: Path) -> None:
    urdf = _write_urdf(tmp_path, 'flat', _urdf('flat', PLANAR_JOINTS, PLANAR_MASSES))
    point = [0.02, 0.01, 0.0]
    lk = load_linkage(_wrap(tmp_path, urdf, task='planar',
                            grasp={'link': 'l3', 'point': point}))
    assert lk.task is TaskSpace.PLANAR
    dyn = LinkageDynamics(lk)
    for q in (np.zeros(3), np.array([0.4, -0.7, 0.02]), np.array([2.9, 1.1, -0.03])):
        t = _fk(_chain(PLANAR_JOINTS), q) @ _hom(np.eye(3), point)
        expected = [t[0, 3], t[1, 3], math.atan2(t[1, 0], t[0, 0])]
        np.testing.assert_allclose(dyn.hand_pose(q), expected, atol=1e-12)
        np.testing.assert_allclose(dyn.hand_jacobian(q), _fd_jacobian(dyn, q), atol=1e-7)


@pytest.mark.parametrize(('index', 'change', 'field'), [
    (1, {'axis': (0, 1, 0)}, 'axis'),
    (2, {'axis': (0.6, 0.0, 0.8)}, 'axis'),
    (1, {'rpy': (0.3, 0.0, 0.0)}, 'rpy'),
])
def test_non_planar_urdf_is_refused_naming_the_joint(tmp_path: Path, index: int,
                                                     change: dict[str, Any], field: str) -> None:
    joints = list(PLANAR_JOINTS)
    name, kind, parent, child, xyz, rpy, axis = joints[index]
    joints[index] = (name, kind, parent, child, xyz, change.get('rpy', rpy),
                     change.get('axis', axis))
    urdf = _write_urdf(tmp_path, 'bent', _urdf('bent', joints, PLANAR_MASSES))
    with pytest.raises(LinkageError, match=rf"joint '{name}'.*{field}.*planar") as info:
        load_linkage(_wrap(tmp_path, urdf, task='planar'))
    assert 'bent.urdf' in str(info.value)


# -- d. default characteristic length = the reach, YAML and URDF alike ---------------------------
TABLE1_JOINTS = [
    ('j1', 'revolute', 'base', 'link1', (0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 1)),
    ('j2', 'revolute', 'link1', 'link2', (0.042, 0.0, 0.0), (0, 0, 0), (0, 0, 1)),
    ('j3', 'revolute', 'link2', 'link3', (0.042, 0.0, 0.0), (0, 0, 0), (0, 0, 1)),
    ('tip_joint', 'fixed', 'link3', 'tip', (0.030, 0.0, 0.0), (0, 0, 0), None),
]


def _table1_urdf() -> str:
    """Table I as URDF: COM mid-link, Izz as in the paper (Ixx, Iyy only need to be valid)."""
    links = ['<link name="base"/>', '<link name="tip"/>']
    for name, length, mass, izz in (('link1', 0.042, 3.0, 0.015), ('link2', 0.042, 3.0, 0.015),
                                    ('link3', 0.030, 1.0, 0.005)):
        links.append(
            f'<link name="{name}"><inertial><origin xyz="{length / 2} 0 0"/>'
            f'<mass value="{mass}"/><inertia ixx="{izz}" ixy="0" ixz="0" iyy="{izz}" iyz="0" '
            f'izz="{izz}"/></inertial></link>')
    text = _urdf('table1', TABLE1_JOINTS, {})
    return text.replace('<robot name="table1">', '<robot name="table1">' + ''.join(links))


def test_default_characteristic_length_is_the_reach(tmp_path: Path) -> None:
    doc = yaml.safe_load(TABLE1.read_text())
    del doc['linkage']['constraints']['characteristic_length']
    assert linkage_from_dict(doc).constraints.characteristic_length == pytest.approx(0.114)
    urdf = _write_urdf(tmp_path, 'table1', _table1_urdf())
    bare = load_linkage(urdf)
    assert bare.constraints.characteristic_length == pytest.approx(0.114)
    planar = load_linkage(_wrap(tmp_path, urdf, task='planar'))
    assert planar.constraints.characteristic_length == pytest.approx(0.114)
    # ... and it is the same linkage as the YAML.
    a, b = LinkageDynamics(planar), LinkageDynamics(load_linkage(TABLE1))
    for q in (np.array([-math.pi / 4, math.pi / 6, -math.pi / 6]), np.array([0.7, -1.1, 2.0])):
        np.testing.assert_allclose(a.mass_matrix(q), b.mass_matrix(q), atol=1e-12)
        np.testing.assert_allclose(a.hand_jacobian(q), b.hand_jacobian(q), atol=1e-12)
        np.testing.assert_allclose(a.hand_pose(q), b.hand_pose(q), atol=1e-12)


def test_bare_urdf_may_say_it_is_planar(tmp_path: Path) -> None:
    text = _table1_urdf().replace('<robot name="table1">',
                                  '<robot name="table1"><haptic_topology task="planar"/>')
    lk = load_linkage(_write_urdf(tmp_path, 'table1', text))
    assert lk.task is TaskSpace.PLANAR and lk.dof == 3


# -- e. branched URDFs: the serial chain to the first branch, side branches locked ---------------
GRIPPER_JOINTS = [
    ('j1', 'revolute', 'base', 'l1', (0.0, 0.0, 0.05), (0, 0, 0), (0, 0, 1)),
    ('cam_pan', 'revolute', 'l1', 'camera', (0.0, 0.02, 0.03), (0, 0, 0), (0, 0, 1)),
    ('j2', 'revolute', 'l1', 'l2', (0.1, 0.0, 0.0), (0, 0, 0), (0, 1, 0)),
    ('wrist', 'continuous', 'l2', 'hand', (0.08, 0.0, 0.0), (0, 0, 0), (1, 0, 0)),
    ('finger_left', 'prismatic', 'hand', 'fl', (0.03, 0.01, 0.0), (0, 0, 0), (0, 1, 0)),
    ('finger_right', 'prismatic', 'hand', 'fr', (0.03, -0.01, 0.0), (0, 0, 0), (0, -1, 0)),
]
GRIPPER_MASSES = {'base': 0.0, 'l1': 1.0, 'camera': 0.2, 'l2': 0.7, 'hand': 0.4, 'fl': 0.05,
                  'fr': 0.05}


def _reduced_reference(urdf: Path, locked: dict[str, float]) -> pin.Model:
    full = pin.buildModelFromUrdf(str(urdf))
    q = pin.neutral(full)
    ids = []
    for name, value in locked.items():
        jid = full.getJointId(name)
        q[full.joints[jid].idx_q] = value
        ids.append(jid)
    return pin.buildReducedModel(full, ids, q)


@pytest.mark.parametrize(('grasp', 'locks', 'dof'), [
    (None, {}, 3),
    ({'link': 'l2'}, {'finger_left': 0.012}, 3),
    ({'link': 'fl'}, {}, 4),
])
def test_branched_urdf_loads_its_serial_chain(tmp_path: Path, grasp: dict[str, Any] | None,
                                              locks: dict[str, float], dof: int) -> None:
    urdf = _write_urdf(tmp_path, 'gripper', _urdf('gripper', GRIPPER_JOINTS, GRIPPER_MASSES))
    extra: dict[str, Any] = {'task': 'spatial'}
    if grasp is not None:
        extra['grasp'] = grasp
    if locks:
        extra['locked_joints'] = locks
    lk = load_linkage(_wrap(tmp_path, urdf, **extra) if grasp or locks else urdf)
    assert lk.dof == dof
    free = ['j1', 'j2', 'wrist'] + (['finger_left'] if dof == 4 else [])
    locked = {n: locks.get(n, 0.0) for n in ('cam_pan', 'finger_left', 'finger_right')
              if n not in free}
    assert len(lk.notes) == 1 and '\n' not in lk.notes[0]
    for name, value in locked.items():
        assert f'{name}={value:g}' in lk.notes[0]
    assert lk.grasp_link == (grasp['link'] if grasp else 'hand')
    dyn = LinkageDynamics(lk)
    # Every mass is kept, and the dynamics are Pinocchio's own reduced model's.
    assert sum(link.mass for link in lk.links) == pytest.approx(sum(GRIPPER_MASSES.values()))
    ref = _reduced_reference(urdf, locked)
    assert ref.nv == dof
    ref_data = ref.createData()
    rng = np.random.default_rng(3)
    for _ in range(3):
        q = rng.uniform(-1.0, 1.0, dof) * 0.5
        q_ref = pin.neutral(ref)
        for k in range(dof):
            jm = ref.joints[k + 1]
            if jm.nq == 2:
                q_ref[jm.idx_q:jm.idx_q + 2] = [math.cos(q[k]), math.sin(q[k])]
            else:
                q_ref[jm.idx_q] = q[k]
        d_ref = pin.crba(ref, ref_data, q_ref)
        d_ref = np.triu(d_ref) + np.triu(d_ref, 1).T
        np.testing.assert_allclose(dyn.mass_matrix(q), d_ref, atol=1e-12)


def test_locked_joints_are_checked(tmp_path: Path) -> None:
    urdf = _write_urdf(tmp_path, 'gripper', _urdf('gripper', GRIPPER_JOINTS, GRIPPER_MASSES))
    with pytest.raises(LinkageError, match=r"locked_joints\.nope: unknown side-branch joint"):
        load_linkage(_wrap(tmp_path, urdf, task='spatial', locked_joints={'nope': 0.0}))
    with pytest.raises(LinkageError, match=r"locked_joints\.j2: joint 'j2' is on the chain"):
        load_linkage(_wrap(tmp_path, urdf, task='spatial', locked_joints={'j2': 0.0}))


# -- f. unit check of characteristic_length ------------------------------------------------------
@pytest.mark.parametrize(('scale', 'lc'), [(1000.0, 0.114), (1.0, 114.0)])
def test_characteristic_length_far_from_the_reach_warns(scale: float, lc: float) -> None:
    doc = yaml.safe_load(TABLE1.read_text())
    for link in doc['linkage']['links']:
        link['length'] *= scale
    doc['linkage']['constraints']['characteristic_length'] = lc
    with pytest.warns(UserWarning, match=r'constraints\.characteristic_length.*reach'):
        linkage_from_dict(doc, 'units.yaml')


def test_characteristic_length_near_the_reach_does_not_warn() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        load_linkage(TABLE1)
