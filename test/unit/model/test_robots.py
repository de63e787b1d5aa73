"""Robots by name from example-robot-data (issue 58 item 3), an optional extra: ``robot: NAME``
in a linkage or inline in a scenario, ``robot:NAME`` where a linkage file is taken; the link
meshes are the contact geometry without any capsule override; the SRDF's disabled collision
pairs; errors in one line. These tests do not need the extra: :func:`robots_from_the_repo`
serves the Panda and the UR5 shipped in config/robots/ as package ``example-robot-data``
through the ament index, and :mod:`test_without_robots` hides an installed extra."""

from __future__ import annotations

import base64
import hashlib
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from haptic_topology.dynamics.contacts import ContactSettings
from haptic_topology.dynamics.self_contacts import self_pairs
from haptic_topology.errors import LinkageError
from haptic_topology.model.linkage import linkage_from_dict, load_linkage
from haptic_topology.model.robots import ROBOTS, VERSION, read_srdf, robot_files
from haptic_topology.sim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[3]
SHIPPED = REPO / 'config' / 'robots' / 'example-robot-data'

#: sha256 (urlsafe base64, as in a wheel's RECORD) of each shipped file in the RECORD of the
#: example-robot-data 6.0.0 wheel: the copies in config/robots/ are its files, unchanged.
UPSTREAM = {
    'LICENSE':
        'KnA8ca5oHFD2ISur9XxCfCe2UWSY_K9WndPqFnE1nkI',
    'robots/panda_description/LICENSE':
        'psuoW8kuDP96RQsdhzwOqi6fyWv0ct8CR6Jr7He_P_k',
    'robots/panda_description/README.md':
        '8KoLdmDGw5w1sLt6iI4l1onBWQuYRE-BwRxvfRPXpIs',
    'robots/panda_description/meshes/collision/finger.stl':
        'LQenQDkvO5sIFvZdZP_5kn09V8iXhw_Etv-cVv_zoMg',
    'robots/panda_description/meshes/collision/hand.stl':
        'lEk-lPMP6UDyyMovFVw7vme7_0BtPt9eJhZw0vD24u0',
    'robots/panda_description/meshes/collision/link0.stl':
        '38bZQzDejdsAWzEb_bqfO44ap8JWtxWS7n_zLLmppao',
    'robots/panda_description/meshes/collision/link1.stl':
        '5Bo5qUEI_PVqrP9gP8keyAVB9MGvF7UaDeVhf1Vm5tI',
    'robots/panda_description/meshes/collision/link2.stl':
        'Nw92BaD641KdsWne1Q9S8XECSqeS1NdzvIQZcwH2oDk',
    'robots/panda_description/meshes/collision/link3.stl':
        'Co1ji5NJxsDu_E6IhjasSDjEsnFw8YpRaZMhEYr3CcE',
    'robots/panda_description/meshes/collision/link4.stl':
        'AYDrtXcuyYQMsEl1DP-ymp3ckDEXUqFuo0dXeC755I0',
    'robots/panda_description/meshes/collision/link5.stl':
        '3RfmiMeHDnIig1JYeWQ9U6dMACTTKLDhSwNLVMi2wxo',
    'robots/panda_description/meshes/collision/link6.stl':
        'ILdo6ZoOBEC1dU3MoQgBZDTleTfMNWrNnDUszTyyf3c',
    'robots/panda_description/meshes/collision/link7.stl':
        'kqxq_PdXTANNMXDYpo6VrJBIq50N1bvYMRuG5VG5qxw',
    'robots/panda_description/srdf/panda.srdf':
        'my3pcUYPGcE7yMxDe2dFgeg6wPLXF7R6v2nhWLVZH24',
    'robots/panda_description/urdf/panda.urdf':
        'Y3ktJnnyLE5BzaLE2dkDZE5iiXCtBla57shIUROUFVU',
    'robots/ur_description/README.md':
        'lXcNw_yYidNPpVac5MT6IxwWPAVcWqMiQCQTMy-DKlA',
    'robots/ur_description/meshes/ur5/collision/base.stl':
        'x69X0QneanP1eUNhO7AANGUY3wa7WuEZougM8AvL694',
    'robots/ur_description/meshes/ur5/collision/forearm.stl':
        'jnmqgKUySUulMgwwtANj_2PSKOPVnikEcD3KNB3Loqw',
    'robots/ur_description/meshes/ur5/collision/shoulder.stl':
        'HWLiOow_-eYzT7FXyAXmICA3vPymW8ajbFya6GZ1Gzs',
    'robots/ur_description/meshes/ur5/collision/upperarm.stl':
        'VcEawK0eFE8jCEmyAzUy6LFAsugY6klyltCN-4h1dEA',
    'robots/ur_description/meshes/ur5/collision/wrist1.stl':
        'Ch_RIVAUDv3ukWUNy0wtBEMGVVGpIHotLb3lj_H7Trc',
    'robots/ur_description/meshes/ur5/collision/wrist2.stl':
        'wdn3hDNmBoyzMfP1xD-nFtPs7rjIAhbsy7yHiQXasSM',
    'robots/ur_description/meshes/ur5/collision/wrist3.stl':
        'z3IgOXtW8dMEe-lGXuoRgdRxtA_IJygFLjHJdYhYW0s',
    'robots/ur_description/srdf/ur5.srdf':
        'eV-sKzPekLPpUMhLW0EFuA9RlZJPxnjpqMQuRDDo52w',
    'robots/ur_description/urdf/ur5_robot.urdf':
        'zt6ID8Kph--d0ju82j4K0eex34tY1jjRAM-_-OvIBss',
}


@pytest.fixture
def robots_from_the_repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An ament prefix, first on AMENT_PREFIX_PATH, whose package ``example-robot-data`` is
    config/robots/example-robot-data (the Panda and the UR5 only), as a ROS install of the
    extra would be found; whether the wheel is installed or not does not matter."""
    prefix = tmp_path / 'prefix'
    (prefix / 'share').mkdir(parents=True)
    (prefix / 'share' / 'example-robot-data').symlink_to(SHIPPED)
    index = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'example-robot-data').touch()
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(
        filter(None, (str(prefix), os.environ.get('AMENT_PREFIX_PATH', '')))))
    yield prefix


def test_the_pinned_version_is_the_extras_pin() -> None:
    pins = [line.split('==')[1] for line in (REPO / 'requirements-robots.in').read_text()
            .splitlines() if line.startswith('example-robot-data==')]
    assert pins == [VERSION]


def as_upstream(rel: str, text: str) -> str:
    """A shipped URDF as example-robot-data has it: without the note of line 2 and with its
    collision meshes as ``package://`` references again (the only change made)."""
    lines = text.split('\n')
    assert lines[1].startswith('<!-- Changed by haptic_topology: in the collision <mesh ')
    package = 'package://example-robot-data/' + rel.split('/urdf/')[0] + '/'
    return '\n'.join(lines[:1] + lines[2:]).replace('filename="../', f'filename="{package}')


def test_the_shipped_robots_are_example_robot_datas_files() -> None:
    """Every file is the wheel's, byte for byte, but the two URDFs, whose collision mesh
    references are relative (so that the copy uses its own meshes, wherever another
    example-robot-data is installed) with a note saying so."""
    files = sorted(p.relative_to(SHIPPED).as_posix() for p in SHIPPED.rglob('*') if p.is_file())
    assert files == sorted(UPSTREAM)
    for rel, digest in UPSTREAM.items():
        data = (SHIPPED / rel).read_bytes()
        if rel.endswith('.urdf'):
            text = data.decode()
            assert text.count('filename="../') == (9 if 'panda' in rel else 7)
            assert all(ref.startswith(('../meshes/', 'package://example-robot-data/'))
                       for ref in re.findall(r'filename="([^"]+)"', text)
                       if ref.endswith(('.stl', '.dae')))
            data = as_upstream(rel, text).encode()
        got = base64.urlsafe_b64encode(hashlib.sha256(data).digest())
        assert got.decode().rstrip('=') == digest, rel
    # each robot carries its licence beside it; the collection its own
    assert 'Apache License' in (SHIPPED / 'robots/panda_description/LICENSE').read_text()
    assert 'license: BSD' in (SHIPPED / 'robots/ur_description/README.md').read_text()
    assert 'BSD 2-Clause' in (SHIPPED / 'LICENSE').read_text()


def test_ur5_by_name_has_its_meshes_as_contact_geometry(robots_from_the_repo: Path) -> None:
    lk = load_linkage('robot:ur5')
    assert (lk.name, lk.task.value, lk.dof, lk.grasp_link) == ('ur5', 'spatial', 6,
                                                               'wrist_3_link')
    assert lk.urdf_path == (robots_from_the_repo / 'share/example-robot-data/robots/'
                            'ur_description/urdf/ur5_robot.urdf')
    settings = ContactSettings.from_config(
        {'obstacles': [{'type': 'plane', 'point': [0, 0, 0], 'normal': [0, 0, 1]}]}, 'c', lk)
    kinds = [(s.link, s.kind) for s in settings.shapes(lk)]
    assert [k for k in kinds if k[1] == 'mesh'] == [(i, 'mesh') for i in range(6)]
    assert all(s.mesh is not None and s.mesh.path.suffix == '.stl'
               and s.mesh.path.is_relative_to(robots_from_the_repo)
               for s in settings.shapes(lk) if s.kind == 'mesh')


def test_panda_by_name_in_a_linkage_and_inline_in_a_scenario(
        tmp_path: Path, robots_from_the_repo: Path) -> None:
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


def test_a_robot_by_name_and_the_shipped_scenario_are_the_same_robot(
        robots_from_the_repo: Path) -> None:
    """panda_table's inline linkage (the shipped URDF and SRDF) is what ``robot: panda``
    expands to: same links, joints, inertias, grasp and disabled pairs."""
    sc = load_scenario('panda_table')
    by_name = linkage_from_dict({'linkage': {'robot': 'panda',
                                             'grasp': {'link': 'panda_link5'}}}, 'p.yaml')
    shipped = sc.linkage
    assert (shipped.name, shipped.task, shipped.grasp_link, shipped.disabled_collisions) == (
        by_name.name, by_name.task, by_name.grasp_link, by_name.disabled_collisions)
    assert shipped.urdf is not None and by_name.urdf is not None
    assert shipped.urdf.text == by_name.urdf.text   # the fixture serves the same files
    assert len(shipped.links) == len(by_name.links) == 7
    for a, b in zip(shipped.links, by_name.links, strict=True):
        assert (a.name, a.joint, a.mass) == (b.name, b.joint, b.mass)
        assert (a.com == b.com).all() and (a.inertia == b.inertia).all()


def test_the_srdfs_disabled_pairs_are_read_into_the_linkage(robots_from_the_repo: Path
                                                             ) -> None:
    ur5 = load_linkage('robot:ur5')
    assert ur5.disabled_collisions == (
        ('base_link', 'shoulder_link'), ('base_link', 'upper_arm_link'),
        ('shoulder_link', 'upper_arm_link'), ('forearm_link', 'upper_arm_link'),
        ('forearm_link', 'wrist_1_link'), ('forearm_link', 'wrist_2_link'),
        ('forearm_link', 'wrist_3_link'), ('wrist_1_link', 'wrist_2_link'),
        ('wrist_1_link', 'wrist_3_link'), ('wrist_2_link', 'wrist_3_link'))
    panda = load_linkage('robot:panda')
    assert len(panda.disabled_collisions) == 35
    assert ('panda_link0', 'panda_link1') in panda.disabled_collisions
    # every shipped scenario with a robot knows its pairs
    assert load_scenario('ur5_table').linkage.disabled_collisions == ur5.disabled_collisions
    assert load_scenario('panda_link4_point').linkage.disabled_collisions == \
        panda.disabled_collisions


def test_srdf_errors_are_one_line(tmp_path: Path) -> None:
    urdf = SHIPPED / 'robots/ur_description/urdf/ur5_robot.urdf'
    bad = tmp_path / 'bad.srdf'
    bad.write_text('<robot name="ur5"><disable_collisions link1="base_link" link2="hand"/>'
                   '</robot>')
    with pytest.raises(LinkageError) as err:
        linkage_from_dict({'linkage': {'task': 'spatial', 'urdf': str(urdf),
                                       'srdf': str(bad)}}, 'u.yaml')
    assert str(err.value) == ("u.yaml: linkage.srdf: bad.srdf disables collisions of link "
                              "'hand', which the URDF does not have")
    bad.write_text('<robot')
    with pytest.raises(LinkageError, match=r'^u\.yaml: linkage\.srdf: cannot read the SRDF '):
        read_srdf(bad, ('a',), 'u.yaml: linkage.srdf')
    bad.write_text('<package/>')
    with pytest.raises(LinkageError, match=r'is no SRDF \(root element <package>, expected '):
        read_srdf(bad, ('a',), 'w')
    with pytest.raises(LinkageError, match=r'^p: linkage.srdf: only allowed with urdf'):
        linkage_from_dict({'linkage': {'srdf': str(bad), 'links': []}}, 'p')


def test_self_collisions_honour_the_srdfs_pairs(tmp_path: Path) -> None:
    """ur5_table with ``self_collisions: true``: the pairs checked are the chain's non-adjacent
    links less the SRDF's disabled pairs, by URDF link: ``ee_link`` (merged into wrist_3_link by
    a fixed joint) keeps its own name, so wrist_1-wrist_3 is off and wrist_1-ee_link on."""
    doc = yaml.safe_load((REPO / 'config' / 'scenarios' / 'ur5_table.yaml').read_text())
    doc['scenario']['linkage']['urdf'] = str(
        SHIPPED / 'robots/ur_description/urdf/ur5_robot.urdf')
    doc['scenario']['linkage']['srdf'] = str(SHIPPED / 'robots/ur_description/srdf/ur5.srdf')
    doc['scenario']['contacts']['self_collisions'] = True
    for o in doc['scenario']['contacts']['obstacles']:
        if 'file' in o:
            o['file'] = str(REPO / 'config' / 'meshes' / 'box.stl')
    path = tmp_path / 's.yaml'
    path.write_text(yaml.safe_dump(doc))
    sc = load_scenario(str(path))
    assert sc.contacts is not None and sc.contacts.self_collisions
    shapes = sc.contacts.shapes(sc.linkage)
    pairs = {(shapes[i].urdf_link, shapes[j].urdf_link)
             for i, j in self_pairs(sc.linkage, shapes)}
    assert pairs == {
        ('shoulder_link', 'forearm_link'), ('shoulder_link', 'wrist_1_link'),
        ('shoulder_link', 'wrist_2_link'), ('shoulder_link', 'wrist_3_link'),
        ('shoulder_link', 'ee_link'), ('upper_arm_link', 'wrist_1_link'),
        ('upper_arm_link', 'wrist_2_link'), ('upper_arm_link', 'wrist_3_link'),
        ('upper_arm_link', 'ee_link'), ('forearm_link', 'ee_link'),
        ('wrist_1_link', 'ee_link')}


def test_robot_errors_are_one_line() -> None:
    with pytest.raises(LinkageError) as err:
        load_linkage('robot:r2d2')
    assert str(err.value) == (f'robot:r2d2: linkage.robot: unknown robot {"r2d2"!r} '
                              f'(expected one of: {", ".join(sorted(ROBOTS))})')
    with pytest.raises(LinkageError) as err:
        robot_files('ur5', 'x.yaml: linkage.robot', 'example-robot-data-absent')
    assert str(err.value) == (
        "x.yaml: linkage.robot: robot 'ur5' comes from example-robot-data-absent, an optional "
        "extra that is not installed (131 MB): make robots (outside a checkout: pip install "
        f"'example-robot-data=={VERSION}'); the Panda and the UR5 of config/robots/ need no "
        "extra (scenarios panda_table, ur5_table)")
    with pytest.raises(LinkageError, match=r'p: linkage: give one of robot, urdf and links'):
        linkage_from_dict({'linkage': {'robot': 'ur5', 'urdf': 'a.urdf'}}, 'p')


def test_setup_installs_the_shipped_robots(monkeypatch: pytest.MonkeyPatch) -> None:
    """setup.py installs every file of config/robots/ (URDF, SRDF, meshes, licences) to the same
    place under share/haptic_topology/, so the scenarios' relative paths hold when installed."""
    import runpy

    import setuptools
    captured: dict[str, Any] = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.chdir(REPO)
    runpy.run_path(str(REPO / 'setup.py'))
    installed = {src: dest for dest, files in captured['data_files'] for src in files}
    shipped = sorted(p.relative_to(REPO).as_posix() for p in (REPO / 'config' / 'robots')
                     .rglob('*') if p.is_file())
    assert len(shipped) == len(UPSTREAM) + 1    # + config/robots/README.md
    for f in shipped:
        assert installed.get(f) == f'share/haptic_topology/{Path(f).parent.as_posix()}', f


def test_the_shipped_scenarios_use_their_own_meshes_whatever_is_installed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Another example-robot-data first on AMENT_PREFIX_PATH (its Panda and UR5 meshes all
    a 12-triangle box) changes nothing in panda_table and ur5_table: every link mesh is the
    one shipped beside their URDF."""
    other = tmp_path / 'prefix' / 'share' / 'example-robot-data'
    box = (REPO / 'test' / 'fixtures' / 'meshes' / 'box12.stl').read_bytes()
    for stl in SHIPPED.rglob('*.stl'):
        target = other / stl.relative_to(SHIPPED)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(box)
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(
        filter(None, (str(tmp_path / 'prefix'), os.environ.get('AMENT_PREFIX_PATH', '')))))
    for name, count in (('panda_table', 8), ('ur5_table', 6)):
        sc = load_scenario(name)
        assert sc.contacts is not None
        meshes = [s.mesh.path for s in sc.contacts.shapes(sc.linkage) if s.mesh is not None]
        assert len(meshes) == count
        assert all(m.resolve().is_relative_to(SHIPPED) for m in meshes), meshes
