"""Robots by name from example-robot-data (issue 58 item 3): ``robot: NAME`` in a linkage or
inline in a scenario, ``robot:NAME`` where a linkage file is taken; the link meshes are the
contact geometry without any capsule override; errors in one line."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from haptic_topology.dynamics.contacts import ContactSettings
from haptic_topology.errors import LinkageError
from haptic_topology.model.linkage import linkage_from_dict, load_linkage
from haptic_topology.model.robots import ROBOTS, VERSION, robot_urdf
from haptic_topology.sim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[3]


def test_the_pinned_version_is_the_requirements_pin() -> None:
    pins = re.findall(r'^example-robot-data==(\S+)$', (REPO / 'requirements.in').read_text(),
                      re.M)
    assert pins == [VERSION]


def test_ur5_by_name_has_its_meshes_as_contact_geometry() -> None:
    lk = load_linkage('robot:ur5')
    assert (lk.name, lk.task.value, lk.dof, lk.grasp_link) == ('ur5', 'spatial', 6,
                                                               'wrist_3_link')
    assert lk.urdf_path is not None and lk.urdf_path.as_posix().endswith(
        'share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf')
    settings = ContactSettings.from_config(
        {'obstacles': [{'type': 'plane', 'point': [0, 0, 0], 'normal': [0, 0, 1]}]}, 'c', lk)
    kinds = [(s.link, s.kind) for s in settings.shapes(lk)]
    assert [k for k in kinds if k[1] == 'mesh'] == [(i, 'mesh') for i in range(6)]
    assert all(s.mesh is not None and s.mesh.path.suffix == '.stl'
               for s in settings.shapes(lk) if s.kind == 'mesh')


def test_panda_by_name_in_a_linkage_and_inline_in_a_scenario(tmp_path: Path) -> None:
    lk = linkage_from_dict({'linkage': {'robot': 'panda', 'grasp': {'link': 'panda_link4'}}},
                           str(tmp_path / 'p.yaml'))
    assert (lk.name, lk.dof, lk.grasp_link) == ('panda', 7, 'panda_link4')
    doc = yaml.safe_load((REPO / 'config' / 'scenarios' / 'panda_link4.yaml').read_text())
    doc['scenario']['linkage'] = {'robot': 'panda', 'grasp': {'link': 'panda_link4'}}
    doc['scenario']['contacts'] = {'obstacles': [
        {'type': 'mesh', 'file': '../box.stl', 'center': [0.5, 0.0, 0.2], 'scale': 0.2}]}
    (tmp_path / 'box.stl').write_bytes((REPO / 'test' / 'fixtures' / 'meshes' / 'box12.stl')
                                       .read_bytes())
    (tmp_path / 'sc').mkdir()
    path = tmp_path / 'sc' / 's.yaml'   # the mesh file is relative to it
    path.write_text(yaml.safe_dump(doc))
    sc = load_scenario(str(path))
    assert (sc.linkage.name, sc.linkage.grasp_link) == ('panda', 'panda_link4')
    assert sc.contacts is not None
    (box,) = sc.contacts.obstacles
    assert box.mesh is not None and box.mesh.path == tmp_path / 'sc' / '../box.stl'


def test_robot_errors_are_one_line() -> None:
    with pytest.raises(LinkageError) as err:
        load_linkage('robot:r2d2')
    assert str(err.value) == (f'robot:r2d2: linkage.robot: unknown robot {"r2d2"!r} '
                              f'(expected one of: {", ".join(sorted(ROBOTS))})')
    with pytest.raises(LinkageError) as err:
        robot_urdf('ur5', 'x.yaml: linkage.robot', 'example-robot-data-absent')
    assert str(err.value) == (
        "x.yaml: linkage.robot: robot 'ur5' comes from example-robot-data-absent, which is not "
        f"installed (131 MB): pip install 'example-robot-data-absent=={VERSION}'")
    with pytest.raises(LinkageError, match=r'p: linkage: give one of robot, urdf and links'):
        linkage_from_dict({'linkage': {'robot': 'ur5', 'urdf': 'a.urdf'}}, 'p')
