"""Contacts with the URDF's collision geometry (issue 13 item 1): spheres and capsules read from
``<collision>`` (merged fixed links included) are the links' contact shapes, exactly;
a missing mesh file is refused unless the scenario says what to do (boxes and cylinders:
``test_core_contacts_solids``); the ``table`` scenario (6-D, URDF shapes) stops the tool on the
table.

Expected capsule ends are computed by hand from the URDF's numbers (rotations about y), not
with the code under test."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import (
    ContactModel,
    ContactParams,
    ContactSettings,
    contact_forces,
)
from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.model import Linkage, load_linkage
from haptic_topology.model.obstacles import obstacles_from_config
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import TaskSpace

ARM3 = config_dir() / 'linkages' / 'arm3_collision.yaml'
PLANE = [{'type': 'plane', 'point': [0.0, 0.0, 0.014], 'normal': [0.0, 0.0, 1.0]}]

_INERTIAL = ('<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" '
             'ixz="0" iyz="0"/></inertial>')


def _urdf(tmp_path: Path, l1_collision: str, l2_collision: str = '', planar: bool = False,
          name: str = 'chain.urdf') -> Path:
    """Two links on revolute z joints, link 2 at x = 0.1 of link 1, a tool fixed at x = 0.06
    of link 2 with a sphere of 0.01 at (0, 0.02, 0.005) of the tool."""
    path = tmp_path / name
    limit = '<limit lower="-3" upper="3" effort="1" velocity="1"/>'
    path.write_text(f'''<robot name="chain">
  {'<haptic_topology task="planar"/>' if planar else ''}
  <link name="base"/>
  <link name="l1">{_INERTIAL}{l1_collision}</link>
  <link name="l2">{_INERTIAL}{l2_collision}</link>
  <link name="tool">{_INERTIAL}<collision><origin xyz="0 0.02 0.005"/>
    <geometry><sphere radius="0.01"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>{limit}</joint>
  <joint name="fix" type="fixed"><parent link="l2"/><child link="tool"/>
    <origin xyz="0.06 0 0"/></joint>
</robot>''')
    return path


CAPSULE_ALONG_X = ('<collision><origin xyz="0.05 0 0" rpy="0 1.5707963267948966 0"/>'
                   '<geometry><capsule radius="0.01" length="0.1"/></geometry></collision>')


def _contacts(linkage: Linkage, obstacles: list[dict[str, Any]],
              task: TaskSpace = TaskSpace.SPATIAL,
              links: Sequence[tuple[str, float | None]] = (),
              **params: float) -> tuple[LinkageDynamics, ContactModel]:
    dyn = LinkageDynamics(linkage)
    settings = ContactSettings(ContactParams(**params),
                               obstacles_from_config(obstacles, 'test', task), 0.003,
                               tuple(links), where='test')
    return dyn, ContactModel(dyn.model, linkage, settings)


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_urdf_spheres_and_capsules_are_the_link_shapes(tmp_path: Path) -> None:
    """Link 1: a capsule of 0.1 along its x (rpy pitch 90 deg turns the capsule's z onto x),
    radius 0.01; link 2: no collision of its own, the merged tool's sphere at
    (0.06, 0.02, 0.005) of link 2. Ends by hand at q = (0.3, -0.7)."""
    linkage = load_linkage(_urdf(tmp_path, CAPSULE_ALONG_X))
    l1, l2 = (link.collision or () for link in linkage.links)
    assert [c.kind for c in l1] == ['capsule']
    assert [(c.kind, c.urdf_link) for c in l2] == [('sphere', 'tool')]
    _, cm = _contacts(linkage, PLANE)
    caps = cm.settings.capsules(linkage)
    assert [(c.link, c.radius) for c in caps] == [(0, 0.01), (1, 0.01)]
    q = np.array([0.3, -0.7])
    p0, p1 = cm._axes(q)
    r1, r2 = _rz(0.3), _rz(0.3) @ _rz(-0.7)
    np.testing.assert_allclose(p0[0], [0.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(p1[0], r1 @ [0.1, 0.0, 0.0], atol=1e-15)
    sphere = r1 @ [0.1, 0.0, 0.0] + r2 @ [0.06, 0.02, 0.005]
    np.testing.assert_allclose(p0[1], sphere, atol=1e-15)
    np.testing.assert_allclose(p1[1], sphere, atol=1e-15)
    # Against the plane z = 0.014: the capsule's two ends (z 0, 0.01 radius) and the sphere once.
    cs = cm.detect(q, margin=1.0)
    got = sorted(zip(cs.links.tolist(), cs.gaps.tolist(), strict=True))
    expected = sorted([(0, 0.0 - 0.014 - 0.01), (0, 0.0 - 0.014 - 0.01),
                       (1, 0.005 - 0.014 - 0.01)])
    assert [g[0] for g in got] == [e[0] for e in expected]
    np.testing.assert_allclose([g[1] for g in got], [e[1] for e in expected], atol=1e-15)


def test_off_axis_shapes_jacobians_torques_and_energy(tmp_path: Path) -> None:
    """For shapes away from the joint axis (the tool's sphere), ``J_i`` is the Jacobian of the
    link point (finite differences), the torques equal ``sum J_i^T F_i`` of the detected
    contacts, and the undamped force is minus the energy gradient."""
    linkage = load_linkage(_urdf(tmp_path, CAPSULE_ALONG_X))
    sphere = [{'type': 'sphere', 'center': [0.12, 0.09, 0.0], 'radius': 0.02}]
    dyn, cm = _contacts(linkage, PLANE + sphere, stiffness=3000.0, damping=0.0)
    q = np.array([0.3, 0.4])
    cs = cm.detect(q, margin=1.0)
    assert np.any(cs.gaps < 0.0) and np.any(cs.links == 1)
    for i in range(len(cs)):
        joint = int(cs.links[i]) + 1
        cm.detect(q, margin=1.0)
        local = cm.data.oMi[joint].actInv(cs.points[i])
        fd = np.zeros((3, 2))
        for j in range(2):
            e = np.zeros(2)
            e[j] = 1e-7
            cm.detect(q + e, margin=1.0)
            plus = cm.data.oMi[joint].act(local)
            cm.detect(q - e, margin=1.0)
            fd[:, j] = (plus - cm.data.oMi[joint].act(local)) / 2e-7
        np.testing.assert_allclose(cs.jacobians[i], fd, atol=1e-8)
    dq = np.array([0.2, -0.5])
    tau, _ = cm.torques(q, dq)
    vel = np.einsum('cij,j->ci', cs.jacobians, dq)
    f = contact_forces(cm.params, cs.gaps, cs.normals, vel)
    np.testing.assert_allclose(tau, np.einsum('cij,ci->j', cs.jacobians, f), atol=1e-12)
    tau0, power = cm.torques(q, np.zeros(2))
    assert power == 0.0 and np.any(tau0 != 0.0)
    grad = np.zeros(2)
    for j in range(2):
        e = np.zeros(2)
        e[j] = 1e-7
        grad[j] = (cm.potential(q + e) - cm.potential(q - e)) / 2e-7
    np.testing.assert_allclose(tau0, -grad, rtol=1e-5, atol=1e-9)


def test_a_missing_mesh_is_refused_unless_the_scenario_chooses(tmp_path: Path) -> None:
    """A link mesh that is nowhere is refused in one line naming the file and where it was
    looked for; the scenario can still put a capsule in its place or leave the link out.
    (Meshes found: ``test_core_contacts_meshes``.)"""
    linkage = load_linkage(_urdf(tmp_path, '<collision><geometry><mesh filename="package://'
                                           'nowhere/l1.stl"/></geometry></collision>'))
    with pytest.raises(ConfigError) as err:
        _contacts(linkage, PLANE)[1].settings.capsules(linkage)
    assert '\n' not in str(err.value)
    assert re.fullmatch(rf"{re.escape(str(tmp_path))}/chain.urdf: link 'l1' <mesh>: mesh file "
                        r"'package://nowhere/l1.stl' not found \(looked in: .*"
                        r"no Python distribution 'nowhere'\)", str(err.value)), str(err.value)
    # radius: the default capsule along the link (joint 1 -> joint 2), of that radius
    _, cm = _contacts(linkage, PLANE, links=[('l1', 0.004)])
    caps = cm.settings.capsules(linkage)
    assert [(c.link, c.radius) for c in caps] == [(0, 0.004), (1, 0.01)]
    np.testing.assert_array_equal(caps[0].b, [0.1, 0.0, 0.0])
    # collide: false: only the tool's sphere remains
    _, cm = _contacts(linkage, PLANE, links=[('l1', None)])
    assert [c.link for c in cm.settings.capsules(linkage)] == [1]
    assert set(cm.detect(np.zeros(2), margin=1.0).links.tolist()) == {1}


def test_contacts_links_block_errors_name_the_field(tmp_path: Path) -> None:
    linkage = load_linkage(_urdf(tmp_path, ''))
    base: dict[str, Any] = {'obstacles': PLANE}
    cases: list[tuple[dict[str, Any], str]] = [
        ({'links': {'l1': {'radius': 0.01, 'collide': False}}}, 'c.links.l1: give either radius'),
             ({'links': {'l1': {}}}, 'c.links.l1: give either radius'),
             ({'links': {'l1': {'collide': 'no'}}}, 'c.links.l1.collide'),
             ({'links': {'l1': {'radius': -0.01}}}, 'c.links.l1.radius'),
             ({'links': {'l7': {'radius': 0.01}}}, 'c.links.l7: unknown key')]
    for extra, expected in cases:
        with pytest.raises(ConfigError, match=expected):
            ContactSettings.from_config({**base, **extra}, 'c', linkage)
    # a URDF link without <collision> does not collide; link 2 has the tool's sphere
    settings = ContactSettings.from_config(base, 'c', linkage)
    assert [c.link for c in settings.capsules(linkage)] == [1]


def test_urdf_collision_errors_name_the_file_and_link(tmp_path: Path) -> None:
    cases = [('<collision><geometry><sphere radius="-1"/></geometry></collision>',
              r"link 'l1' <collision> 1: <sphere radius=\"-1\">: expected 1 finite number"),
             ('<collision><geometry><cone radius="1"/></geometry></collision>',
              r"link 'l1' <collision> 1: unknown geometry <cone>"),
             ('<collision></collision>', r"link 'l1' <collision> 1: missing <geometry>"),
             ('<collision><geometry><capsule radius="0.01"/></geometry></collision>',
              r"link 'l1' <collision> 1: <capsule> needs the attribute length"),
             ('<collision><origin xyz="0 0"/><geometry><sphere radius="0.01"/></geometry>'
              '</collision>',
              r"link 'l1' <collision> 1: <origin>: xyz and rpy take 3 numbers each")]
    for k, (collision, expected) in enumerate(cases):
        path = _urdf(tmp_path, collision, name=f'bad{k}.urdf')
        with pytest.raises(LinkageError, match=f'{path}: ' + expected):
            load_linkage(path)


def test_planar_urdf_shapes_are_projected_onto_the_plane(tmp_path: Path) -> None:
    """A planar linkage's obstacles extend along z: the tool sphere 5 mm above the plane
    touches a disc as if it were in it (2-D distance)."""
    linkage = load_linkage(_urdf(tmp_path, CAPSULE_ALONG_X, planar=True))
    assert linkage.task is TaskSpace.PLANAR
    disc = [{'type': 'disc', 'center': [0.16, 0.05], 'radius': 0.02}]
    _, cm = _contacts(linkage, disc, TaskSpace.PLANAR)
    cs = cm.detect(np.zeros(2), margin=1.0)
    k = int(np.flatnonzero(cs.links == 1)[0])
    # the sphere's centre (0.16, 0.02) to the disc's (0.16, 0.05): 0.03
    assert cs.gaps[k] == pytest.approx(0.03 - 0.02 - 0.01, abs=1e-15)
    np.testing.assert_allclose(cs.normals[k], [0.0, -1.0, 0.0], atol=1e-15)


def test_table_scenario_stops_the_tool_on_the_table() -> None:
    """6-D, URDF shapes: F_h = 0.3 N down; at rest the sphere sits delta = F/k = 0.15 mm deep
    and the device pushes back with 0.3 N; the contacts inject no energy. (F_env is the
    contact force's part along the motions the linkage allows, Lambda^+ J_h D^-1 J^T F; the
    penalty of eq. 14 renders the rest.)"""
    sc = load_scenario('table')
    assert sc.linkage.urdf_path is not None and sc.linkage.task is TaskSpace.SPATIAL
    trace = simulate(sc)
    s = trace.summary()
    assert 0.0 < s['max_penetration_m'] < 0.001
    assert s['energy_injected_j'] == 0.0
    assert s['contact_time_s'] > 1.5
    depth = trace.columns['penetration']      # as the VE's last update reported it
    assert depth[np.isfinite(depth)][-1] == pytest.approx(0.3 / 2000.0, rel=1e-3)
    # at rest the device holds the hand against the user's push: 0.3 N up, no torque
    np.testing.assert_allclose(trace.columns['applied'][-1], [0.0, 0.0, 0.3, 0.0, 0.0, 0.0],
                               atol=1e-4)
    np.testing.assert_allclose(trace.columns['device_twist'][-1], 0.0, atol=1e-4)
    assert trace.columns['env_wrench'][-1, 2] > 0.25    # the table's part of it (eq. 14)
