"""Linkage descriptions: Table I, URDF, and errors that name the field (issue 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from haptic_topology.errors import LinkageError
from haptic_topology.model import JointType, build_model, load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

TABLE1 = config_dir() / 'linkages' / 'table1_planar3.yaml'
SPATIAL = config_dir() / 'linkages' / 'spatial_arm4.yaml'


def test_table1_matches_the_paper() -> None:
    lk = load_linkage(TABLE1)
    assert lk.task is TaskSpace.PLANAR and lk.dof == 3
    assert [link.length for link in lk.links] == [0.042, 0.042, 0.030]
    assert [link.mass for link in lk.links] == [3.0, 3.0, 1.0]
    assert [link.inertia[2, 2] for link in lk.links] == [0.015, 0.015, 0.005]
    assert lk.grasp_link == 'link3'
    np.testing.assert_allclose(lk.grasp_point, [0.015, 0.0, 0.0])  # the distal COM
    model = build_model(lk)
    assert model.model.nq == 3 and model.model.frames[model.hand_frame].name == 'hand'


def test_spatial_yaml_with_prismatic_joint() -> None:
    lk = load_linkage(SPATIAL)
    assert lk.task is TaskSpace.SPATIAL and lk.dof == 4
    assert lk.links[3].joint is JointType.PRISMATIC
    assert lk.links[2].inertia[0, 1] == pytest.approx(1e-5)


URDF = """<?xml version="1.0"?>
<robot name="two_link">
  <link name="base"/>
  <link name="l1">
    <inertial><origin xyz="0.05 0 0"/><mass value="1.0"/>
      <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.002"/></inertial>
  </link>
  <link name="l2">
    <inertial><origin xyz="0.04 0 0"/><mass value="0.5"/>
      <inertia ixx="0.0005" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial>
  </link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def test_urdf_equals_the_same_linkage_in_yaml(tmp_path: Path) -> None:
    from haptic_topology.dynamics import LinkageDynamics

    (tmp_path / 'two.urdf').write_text(URDF)
    from_urdf = load_linkage(tmp_path / 'two.urdf')
    assert from_urdf.task is TaskSpace.SPATIAL
    assert from_urdf.link_names == ('l1', 'l2') and from_urdf.grasp_link == 'l2'
    doc = {'linkage': {'task': 'spatial', 'links': [
        {'name': 'l1', 'joint': 'revolute', 'axis': [0, 0, 1], 'length': 0.1, 'mass': 1.0,
         'com': [0.05, 0, 0], 'inertia': [0.001, 0.002, 0.002]},
        {'name': 'l2', 'joint': 'revolute', 'axis': [0, 0, 1], 'length': 0.08, 'mass': 0.5,
         'com': [0.04, 0, 0], 'inertia': [0.0005, 0.001, 0.001]}]}}
    (tmp_path / 'two.yaml').write_text(yaml.safe_dump(doc))
    from_yaml = load_linkage(tmp_path / 'two.yaml')
    a, b = LinkageDynamics(from_urdf), LinkageDynamics(from_yaml)
    for q in ([0.3, -0.7], [1.2, 0.4]):
        qa = np.array(q)
        np.testing.assert_allclose(a.mass_matrix(qa), b.mass_matrix(qa), atol=1e-12)
        np.testing.assert_allclose(a.hand_jacobian(qa), b.hand_jacobian(qa), atol=1e-12)


def _write(tmp_path: Path, doc: object) -> Path:
    p = tmp_path / 'bad.yaml'
    p.write_text(yaml.safe_dump(doc) if not isinstance(doc, str) else doc)
    return p


def _table1() -> dict:
    return yaml.safe_load(TABLE1.read_text())


@pytest.mark.parametrize(('mutate', 'expected'), [
    (lambda d: d['linkage']['links'][1].update(mass=-3.0),
     r'linkage\.links\[1\]\.mass: expected a value > 0\.0, got -3\.0'),
    (lambda d: d['linkage']['links'][0].update(inertia=-0.01),
     r'linkage\.links\[0\]\.inertia: expected a value > 0\.0'),
    (lambda d: d['linkage']['links'][2].update(inertia=[[1, 2, 0], [2, 1, 0], [0, 0, 1]]),
     r'linkage\.links\[2\]\.inertia: inertia must be positive definite'),
    (lambda d: d['linkage']['grasp'].update(link='link9'),
     r"linkage\.grasp\.link: unknown link 'link9' \(expected one of: link1, link2, link3\)"),
    (lambda d: d['linkage']['grasp'].update(point=[0.1, 0.0]),
     r'linkage\.grasp\.point: expected 3 numbers, got 2'),
    (lambda d: d['linkage']['links'][0].update(joint='spherical'),
     r"linkage\.links\[0\]\.joint: expected one of revolute, prismatic, got 'spherical'"),
    (lambda d: d['linkage']['links'][0].update(colour='red'),
     r'linkage\.links\[0\]\.colour: unknown key'),
    (lambda d: d['linkage']['links'][0].pop('length'),
     r'linkage\.links\[0\]\.length: missing required key'),
    (lambda d: d['linkage']['constraints'].update(rank_tolerance=0.0),
     r'linkage\.constraints\.rank_tolerance: expected a value > 0\.0'),
])
def test_bad_linkage_names_the_field(tmp_path: Path, mutate, expected: str) -> None:
    doc = _table1()
    mutate(doc)
    path = _write(tmp_path, doc)
    with pytest.raises(LinkageError, match=expected) as info:
        load_linkage(path)
    assert str(path) in str(info.value)


def test_yaml_syntax_error_and_missing_file(tmp_path: Path) -> None:
    path = _write(tmp_path, 'linkage: {links: [\n')
    with pytest.raises(LinkageError, match=r'bad\.yaml: YAML syntax error at line'):
        load_linkage(path)
    with pytest.raises(LinkageError, match=r'nope\.yaml: file not found'):
        load_linkage(tmp_path / 'nope.yaml')
    (tmp_path / 'broken.urdf').write_text('<robot name="x"><link name=')
    with pytest.raises(LinkageError, match=r'broken\.urdf: not a valid URDF'):
        load_linkage(tmp_path / 'broken.urdf')


def test_with_grasp_validates_the_link() -> None:
    lk = load_linkage(TABLE1)
    np.testing.assert_allclose(lk.with_grasp('link2').grasp_point, [0.021, 0, 0])
    with pytest.raises(LinkageError, match='grasp.link: unknown link'):
        lk.with_grasp('hand')
