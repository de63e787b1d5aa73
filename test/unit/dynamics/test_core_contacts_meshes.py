"""Mesh collision geometry (issue 58): URDF link meshes and mesh obstacles through coal.

The expectations do not come from the code under test: a mesh box (12 triangles, written by
hand in ``test/fixtures/meshes/box12.stl``) must give the primitive box's gaps, points and
normals (the primitive's gaps are checked by hand in ``test_core_contacts_solids``); a sphere
mesh (an icosphere written here) must approach the sphere from outside as it is refined; the
penalty force of mesh contacts must conserve ``T + U`` without damping and dissipate with it;
a missing and an unreadable mesh are refused in one line."""

from __future__ import annotations

import math
import multiprocessing
import os
import re
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from two_links import two_link_urdf

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import ContactModel, ContactParams, ContactSettings
from haptic_topology.errors import ConfigError
from haptic_topology.model import Linkage
from haptic_topology.model.meshes import resolve_mesh
from haptic_topology.model.obstacles import obstacles_from_config
from haptic_topology.model.solids import CoalPair
from haptic_topology.sim.lockstep import simulate, virtual_environment
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

BOX12 = Path(__file__).resolve().parents[2] / 'fixtures' / 'meshes' / 'box12.stl'
SPATIAL = TaskSpace.SPATIAL
#: The box of link 1 (m): 0.1 x 0.02 x 0.03, from x = 0 to 0.1, turned a little.
BOX_ORIGIN = '<origin xyz="0.05 0 0" rpy="0.1 -0.2 0.3"/>'
BOX_SIZE = (0.1, 0.02, 0.03)

OBSTACLES: list[dict[str, Any]] = [
    {'type': 'plane', 'point': [0.0, 0.0, -0.03], 'normal': [0.1, -0.2, 1.0]},
    {'type': 'sphere', 'center': [0.12, 0.06, 0.01], 'radius': 0.02},
    {'type': 'box', 'center': [0.03, 0.1, 0.0], 'half_extents': [0.02, 0.03, 0.04],
     'rpy': [0.1, 0.2, 0.3]},
    {'type': 'mesh', 'file': str(BOX12), 'center': [0.08, -0.09, 0.02],
     'scale': [0.03, 0.05, 0.04], 'rpy': [0.3, -0.1, 0.2]}]


def _box_collision(mesh: bool) -> str:
    size = ' '.join(str(v) for v in BOX_SIZE)
    geometry = (f'<mesh filename="{BOX12}" scale="{size}"/>' if mesh
                else f'<box size="{size}"/>')
    return f'<collision>{BOX_ORIGIN}<geometry>{geometry}</geometry></collision>'


def _urdf(tmp_path: Path, l1: str, l2: str = '', name: str = 'm.urdf') -> Linkage:
    """Link 1 (yaw about z at the origin) carries ``l1``; link 2 (about (0, 1, 1) at x = 0.1
    of link 1) carries ``l2``."""
    return two_link_urdf(tmp_path, l1, l2, name)


def _contacts(linkage: Linkage, obstacles: list[dict[str, Any]], **params: float
              ) -> tuple[LinkageDynamics, ContactModel]:
    dyn = LinkageDynamics(linkage)
    settings = ContactSettings(ContactParams(**params),
                               obstacles_from_config(obstacles, 'test', SPATIAL), 0.003,
                               where='test')
    return dyn, ContactModel(dyn.model, linkage, settings)


def _deepest(cm: ContactModel, q: np.ndarray) -> dict[int, tuple[float, np.ndarray, np.ndarray]]:
    """Per obstacle: the smallest gap of link 1's candidates, its normal and point."""
    cs = cm.detect(q, margin=10.0)
    out: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
    for i in np.flatnonzero(cs.links == 0).tolist():
        k = int(cs.obstacles[i])
        if k not in out or cs.gaps[i] < out[k][0]:
            out[k] = (float(cs.gaps[i]), cs.normals[i], cs.points[i])
    return out


def test_a_mesh_box_is_the_primitive_box(tmp_path: Path) -> None:
    """The 12-triangle box scaled to link 1's box gives, against a plane, a sphere, a box and
    a mesh obstacle, at configurations apart and penetrating, the primitive box's smallest
    gap (the plane: the deepest of its corners), the same normal and the same point."""
    # the plane and the sphere moved into link 1's reach
    obstacles = [{**OBSTACLES[0], 'point': [0.0, 0.0, -0.026]},
                 {**OBSTACLES[1], 'center': [0.07, 0.05, 0.0]}, *OBSTACLES[2:]]
    _, prim = _contacts(_urdf(tmp_path, _box_collision(False), name='p.urdf'), obstacles)
    _, mesh = _contacts(_urdf(tmp_path, _box_collision(True), name='m.urdf'), obstacles)
    rng = np.random.default_rng(58)
    signs = set()
    for _ in range(60):
        q = rng.uniform(-2.0, 2.0, 2)
        a, b = _deepest(prim, q), _deepest(mesh, q)
        assert sorted(a) == sorted(b) == [0, 1, 2, 3]
        for k in a:
            assert b[k][0] == pytest.approx(a[k][0], abs=1e-9), (q, k)
            signs.add((k, a[k][0] < 0.0))
            if abs(a[k][0]) > 1e-6:     # a face or an edge: the normal; a unique point
                np.testing.assert_allclose(b[k][1], a[k][1], atol=1e-6)
            if k == 0:                  # the plane: the deepest corner
                np.testing.assert_allclose(b[k][2], a[k][2], atol=1e-9)
    # every obstacle was met both apart and penetrating
    assert signs == {(k, s) for k in range(4) for s in (False, True)}


def _icosphere(level: int) -> np.ndarray:
    """Triangles (t x 3 x 3) of the unit icosphere refined ``level`` times (vertices on the
    sphere, outward winding)."""
    g = (1.0 + math.sqrt(5.0)) / 2.0
    v = [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g), (0, -1, -g),
         (0, 1, -g), (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    tris = [np.array([v[i] for i in face], dtype=float) for face in f]
    tris = [t / np.linalg.norm(t, axis=1)[:, None] for t in tris]
    for _ in range(level):
        finer = []
        for a, b, c in tris:
            ab, bc, ca = (a + b), (b + c), (c + a)
            ab, bc, ca = (x / np.linalg.norm(x) for x in (ab, bc, ca))
            finer += [np.array(t) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
        tris = finer
    return np.array(tris)


def _write_stl(path: Path, tris: np.ndarray) -> Path:
    lines = ['solid s']
    for t in tris:
        n = np.cross(t[1] - t[0], t[2] - t[0])
        n /= np.linalg.norm(n)
        lines += [f'facet normal {n[0]:.17g} {n[1]:.17g} {n[2]:.17g}', 'outer loop']
        lines += [f'vertex {p[0]:.17g} {p[1]:.17g} {p[2]:.17g}' for p in t]
        lines += ['endloop', 'endfacet']
    path.write_text('\n'.join(lines + ['endsolid s']) + '\n')
    return path


def test_a_sphere_mesh_approaches_the_sphere_as_it_is_refined(tmp_path: Path) -> None:
    """A sphere of radius 0.02 on link 2, as URDF sphere and as icospheres of 20, 80, 320
    and 1280 triangles (scaled by 0.02): against every obstacle the mesh's gap is never below
    the sphere's (the mesh is inside it), at most the sphere's sagitta ``r (1 - cos a)``
    above it (``a``: the largest angle of a vertex from its face's centre), and the largest
    difference falls with every refinement."""
    r = 0.02
    place = '<origin xyz="0.06 0.01 0.0"/>'
    sphere = f'<collision>{place}<geometry><sphere radius="{r}"/></geometry></collision>'
    _, ref = _contacts(_urdf(tmp_path, '', sphere, name='s.urdf'), OBSTACLES)
    qs = np.random.default_rng(3).uniform(-2.0, 2.0, (25, 2))

    def gaps(cm: ContactModel) -> np.ndarray:
        out = []
        for q in qs:
            cs = cm.detect(q, margin=10.0)
            out.append([cs.gaps[(cs.links == 1) & (cs.obstacles == k)].min()
                        for k in range(len(OBSTACLES))])
        return np.array(out)

    exact = gaps(ref)
    worst = []
    for level in range(4):
        tris = _icosphere(level)
        centres = tris.mean(axis=1)
        centres /= np.linalg.norm(centres, axis=1)[:, None]
        angle = max(math.acos(min(1.0, float(c @ p))) for t, c in zip(tris, centres, strict=True)
                    for p in t)
        stl = _write_stl(tmp_path / f'ico{level}.stl', tris)
        mesh = f'<collision>{place}<geometry><mesh filename="{stl}" scale="{r} {r} {r}"/>' \
               '</geometry></collision>'
        _, cm = _contacts(_urdf(tmp_path, '', mesh, name=f'ico{level}.urdf'), OBSTACLES)
        diff = gaps(cm) - exact
        assert diff.min() >= -1e-9, level
        assert diff.max() <= r * (1.0 - math.cos(angle)) + 1e-9, level
        worst.append(float(diff.max()))
    assert all(b < a for a, b in zip(worst, worst[1:], strict=False)), worst
    assert worst[-1] < 2e-4     # 1280 triangles: within 0.2 mm of the 20 mm sphere


def _bounce(tmp_path: Path, **params: float) -> tuple[float, list[float], list[float], float]:
    """The free linkage, a mesh box on link 1 and a mesh icosphere on link 2, thrown at the
    four obstacles (no hand wrench, 0.4 s): ``T + U`` and the contact energy balance every ms,
    and the largest U (it did hit something)."""
    stl = _write_stl(tmp_path / 'ico2.stl', _icosphere(2))
    ball = (f'<collision><origin xyz="0.06 0.01 0.0"/><geometry><mesh filename="{stl}" '
            f'scale="0.02 0.02 0.02"/></geometry></collision>')
    linkage = _urdf(tmp_path, _box_collision(True), ball, name='bounce.urdf')
    dyn, cm = _contacts(linkage, OBSTACLES, stiffness=3000.0, **params)
    q0, dq0 = np.array([0.2, -0.3]), np.array([3.0, -4.0])
    ve = VirtualEnvironment(dyn, q0, dq0, internal_step=1e-4, contacts=cm)
    e0 = ve.kinetic_energy() + cm.potential(q0)
    energy, balance, peak = [], [], 0.0
    for _ in range(400):
        ve.integrate(np.zeros(6), 1e-3)
        u = cm.potential(ve.q)
        peak = max(peak, u)
        energy.append(ve.kinetic_energy() + u)
        balance.append(ve.contact_energy_balance())
    return e0, energy, balance, peak


def test_mesh_contacts_are_passive(tmp_path: Path) -> None:
    """Without damping the mesh contacts conserve ``T + U`` (to the integration error) and
    inject nothing; with damping and friction they dissipate."""
    e0, energy, balance, peak = _bounce(tmp_path, damping=0.0)
    assert peak > 0.05 * e0                          # the contacts were hit hard
    np.testing.assert_allclose(energy, e0, rtol=1e-5)
    assert max(abs(b) for b in balance) < 1e-5 * e0
    e0, energy, balance, _ = _bounce(tmp_path, damping=20.0, friction=0.5)
    assert energy[-1] < 0.9 * e0
    assert max(balance) <= 1e-9 * e0 and balance[-1] < -0.05 * e0


def test_gap_rate_of_mesh_contacts_is_the_normal_velocity(tmp_path: Path) -> None:
    """The derivative of every mesh candidate's gap (central differences) is ``n^T J_i``: the
    force at the witness point does the work ``-dU`` (the envelope theorem)."""
    linkage = _urdf(tmp_path, _box_collision(True), _box_collision(True), name='rate.urdf')
    _, cm = _contacts(linkage, OBSTACLES)
    rng = np.random.default_rng(5)
    for _ in range(20):
        q = rng.uniform(-1.5, 1.5, 2)
        cs = cm.detect(q, margin=1.0)
        fd = np.zeros((len(cs), 2))
        for j in range(2):
            e = np.zeros(2)
            e[j] = 1e-6
            fd[:, j] = (cm.detect(q + e, margin=1.0).gaps
                        - cm.detect(q - e, margin=1.0).gaps) / 2e-6
        np.testing.assert_allclose(fd, np.einsum('ci,cij->cj', cs.normals, cs.jacobians),
                                   atol=2e-6)


#: The 12 triangles (outward) of the 8 corners ``(sx, sy, sz)``, x slowest, of a box.
_BOX_FACES = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7),
              (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
#: An off-centre box, 0.1 x 0.2 x 0.3 m (three different sizes: a turn would show).
_CORNERS = np.array([[sx * 0.05, sy * 0.1, sz * 0.15] for sx in (-1, 1) for sy in (-1, 1)
                     for sz in (-1, 1)]) + np.array([0.01, 0.02, 0.03])


def _dae(vertices: np.ndarray, up: str = 'Z_UP', meter: str = '1') -> str:
    """A COLLADA file of the box ``vertices`` (in the file's unit) as 12 triangles."""
    pos = ' '.join(f'{v:.17g}' for v in vertices.ravel())
    idx = ' '.join(str(i) for face in _BOX_FACES for i in face)
    xyz = ''.join(f'<param name="{a}" type="float"/>' for a in 'XYZ')
    return f'''<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit name="u" meter="{meter}"/><up_axis>{up}</up_axis></asset>
  <library_geometries><geometry id="g"><mesh>
    <source id="p"><float_array id="pa" count="24">{pos}</float_array><technique_common>
      <accessor source="#pa" count="8" stride="3">{xyz}</accessor></technique_common></source>
    <vertices id="v"><input semantic="POSITION" source="#p"/></vertices>
    <triangles count="12"><input semantic="VERTEX" source="#v" offset="0"/><p>{idx}</p>
    </triangles></mesh></geometry></library_geometries>
  <library_visual_scenes><visual_scene id="s"><node id="n"><instance_geometry url="#g"/>
  </node></visual_scene></library_visual_scenes>
  <scene><instance_visual_scene url="#s"/></scene>
</COLLADA>
'''


def _obj(vertices: np.ndarray) -> str:
    return (''.join(f'v {x:.17g} {y:.17g} {z:.17g}\n' for x, y, z in vertices)
            + ''.join(f'f {a + 1} {b + 1} {c + 1}\n' for a, b, c in _BOX_FACES))


def test_dae_and_obj_meshes_load_as_the_urdf_describes(tmp_path: Path) -> None:
    """The same off-centre box as COLLADA (z up; y up; in millimetres, ``<unit
    meter="0.001">``) and as OBJ, on a URDF link with and without ``scale``: the link's hull is
    the box's 8 corners (m, mesh frame) times the scale, as ROS's mesh loaders read these
    files (the unit applied, the up axis ignored: a URDF's meshes are z up), and its gap to a
    plane is the lowest corner's height."""
    files = {'z.dae': _dae(_CORNERS), 'y.dae': _dae(_CORNERS, 'Y_UP'),
             'mm.dae': _dae(1000.0 * _CORNERS, meter='0.001'), 'box.obj': _obj(_CORNERS)}
    plane = [{'type': 'plane', 'point': [0.0, 0.0, -1.0], 'normal': [0.0, 0.0, 1.0]}]
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        for scale in ((1.0, 1.0, 1.0), (2.0, 3.0, 4.0)):
            attr = ' '.join(str(v) for v in scale)
            collision = (f'<collision><geometry><mesh filename="{name}" scale="{attr}"/>'
                         '</geometry></collision>')
            linkage = _urdf(tmp_path, collision, name=f'{name}.urdf')
            dyn, cm = _contacts(linkage, plane)
            (solid,) = [s for s in cm._solids if s.link == 0]
            assert solid.mesh is not None
            want = _CORNERS * np.array(scale)
            got = solid.mesh.vertices
            assert got.shape == (8, 3), name
            # assimp reads single precision: a relative 1e-7
            np.testing.assert_allclose(got[np.lexsort(got.T)], want[np.lexsort(want.T)],
                                       rtol=1e-7, atol=1e-12, err_msg=f'{name} scale {scale}')
            cs = cm.detect(np.zeros(2), margin=10.0)
            assert cs.gaps[cs.links == 0].min() == pytest.approx(1.0 + want[:, 2].min(),
                                                                  abs=1e-7)
    (tmp_path / 'bad.dae').write_text(_dae(_CORNERS, meter='0'))
    raw = [{'type': 'mesh', 'file': 'bad.dae', 'center': [0, 0, 0]}]
    with pytest.raises(ConfigError) as err:
        obstacles_from_config(raw, 'w', SPATIAL, tmp_path)
    assert str(err.value) == (f'w[0].file: the mesh {tmp_path}/bad.dae: <unit meter="0">: '
                              f'expected a number > 0 (metres per unit of the file)')


def test_missing_and_unreadable_meshes_are_refused_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.stl'
    bad.write_text('this is not a mesh\n')
    cases = [
        ('<mesh filename="meshes/none.stl"/>',
         rf"m0.urdf: link 'l1' <mesh>: mesh file 'meshes/none.stl' not found \(looked in: "
         rf"{re.escape(str(tmp_path))}/meshes/none.stl\)"),
        (f'<mesh filename="{bad}"/>',
         rf"m1.urdf: link 'l1' <mesh>: coal cannot read the mesh {re.escape(str(bad))} \("
         r'.+\)'),
        (f'<mesh filename="{BOX12}" scale="1 0 1"/>',
         r"m2.urdf: link 'l1' <collision> 1: <mesh scale=\"1 0 1\">: expected 1 or 3 finite "
         r'numbers > 0')]
    for i, (geometry, expected) in enumerate(cases):
        with pytest.raises(ConfigError) as err:
            linkage = _urdf(tmp_path, f'<collision><geometry>{geometry}</geometry></collision>',
                            name=f'm{i}.urdf')
            ContactSettings.from_config({'obstacles': []}, 'c', linkage)
        assert '\n' not in str(err.value)
        assert re.search(expected, str(err.value)), str(err.value)
    raw = [{'type': 'mesh', 'file': 'bad.stl', 'center': [0, 0, 0]}]
    with pytest.raises(ConfigError, match=r'^w\[0\]\.file: coal cannot read the mesh .*bad\.stl'):
        obstacles_from_config(raw, 'w', SPATIAL, tmp_path)
    raw = [{'type': 'mesh', 'file': 'table.stl', 'center': [0, 0, 0]}]
    with pytest.raises(ConfigError) as err:
        obstacles_from_config(raw, 'w', SPATIAL, tmp_path)
    assert str(err.value) == (f"w[0].file: mesh file 'table.stl' not found (looked in: "
                              f'{tmp_path}/table.stl)')
    raw = [{'type': 'mesh', 'file': str(BOX12), 'center': [0, 0, 0]}]
    with pytest.raises(ConfigError, match=r"'mesh' is a spatial obstacle"):
        obstacles_from_config(raw, 'w', TaskSpace.PLANAR)


def test_package_uris_resolve_through_ament_ros_package_path_and_the_urdf(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``package://pkg/meshes/a.stl`` is found under ``share/pkg`` of an
    ``AMENT_PREFIX_PATH`` prefix, under ``pkg`` in a ``ROS_PACKAGE_PATH`` entry, or in the
    package directory above the URDF; nowhere: one line naming every place looked at."""
    uri = 'package://pkg/meshes/a.stl'
    ament = tmp_path / 'install' / 'share' / 'pkg' / 'meshes' / 'a.stl'
    ros = tmp_path / 'src' / 'pkg' / 'meshes' / 'a.stl'
    beside = tmp_path / 'ws' / 'pkg' / 'meshes' / 'a.stl'
    for f in (ament, ros, beside):
        f.parent.mkdir(parents=True)
        f.write_bytes(BOX12.read_bytes())
    urdf_dir = tmp_path / 'ws' / 'pkg' / 'urdf'
    urdf_dir.mkdir()
    monkeypatch.setenv('AMENT_PREFIX_PATH', f'{tmp_path / "nothing"}:{tmp_path / "install"}')
    monkeypatch.setenv('ROS_PACKAGE_PATH', str(tmp_path / 'src'))
    assert resolve_mesh(uri, urdf_dir, 'w') == ament
    monkeypatch.setenv('AMENT_PREFIX_PATH', '')
    assert resolve_mesh(uri, urdf_dir, 'w') == ros
    monkeypatch.setenv('ROS_PACKAGE_PATH', '')
    assert resolve_mesh(uri, urdf_dir, 'w') == beside
    assert resolve_mesh('../meshes/a.stl', urdf_dir, 'w') == urdf_dir / '../meshes/a.stl'
    assert resolve_mesh(f'file://{ros}', None, 'w') == ros
    monkeypatch.setenv('ROS_PACKAGE_PATH', str(tmp_path / 'src'))
    with pytest.raises(ConfigError) as err:
        resolve_mesh('package://pkg/meshes/b.stl', urdf_dir, 'w')
    assert str(err.value) == (
        f"w: mesh file 'package://pkg/meshes/b.stl' not found (looked in: "
        f"{tmp_path}/src/pkg/meshes/b.stl; AMENT_PREFIX_PATH unset; no Python distribution "
        f"'pkg'; {tmp_path}/ws/pkg/meshes/b.stl)")


@pytest.mark.parametrize('name', ['panda_table', 'ur5_table'])
def test_robots_touch_the_table_with_their_own_meshes(name: str) -> None:
    """The shipped scenarios: the robot by name, every link's contact shape its URDF mesh (no
    capsule), the mesh table installed with the scenarios; in 0.45 s the links reach the
    table, within 1 mm, and the contacts inject no energy."""
    sc = load_scenario(name)
    assert sc.contacts is not None and sc.contacts.links == ()
    kinds = {s.kind for s in sc.contacts.shapes(sc.linkage)}
    assert 'mesh' in kinds and kinds <= {'mesh', 'box'}      # the Panda's fingers are boxes
    table = sc.contacts.obstacles[0]
    assert table.mesh is not None and table.mesh.path.name == 'box.stl'
    s = simulate(replace(sc, duration=0.45)).summary()
    assert s['contact_time_s'] > 0.0 and s['energy_injected_j'] == 0.0
    assert 0.0 < s['max_penetration_m'] < 1e-3


def _ur5_table_columns() -> dict[str, np.ndarray]:
    """``ur5_table``'s trace over 0.6 s (the links reach the table at about 0.25 s; the
    differences of a box's last bits show from 0.55 s)."""
    return simulate(replace(load_scenario('ur5_table'), duration=0.6)).columns


def test_a_run_does_not_depend_on_what_ran_before_it_in_the_process() -> None:
    """Determinism: ``ur5_table`` run in this process after ``panda_table``'s VE was made
    (its initial contact potential: coal queries of the Panda's meshes and finger boxes
    against the table and the box) equals, bit for bit, the same run in a fresh interpreter.
    (coal 3.0 fixes its box's shape on the process's first box query; the meshes module
    fixes it on import, the same in every process.)"""
    virtual_environment(load_scenario('panda_table'))
    got = _ur5_table_columns()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) as pool:
        fresh = pool.submit(_ur5_table_columns).result(timeout=300)
    assert np.nanmax(got['penetration']) > 0.0      # the links touched the table
    assert sorted(got) == sorted(fresh)
    differ = {k: float(np.nanmax(np.abs(got[k] - fresh[k].astype(float))))
              for k in sorted(got) if not np.array_equal(got[k], fresh[k], equal_nan=True)}
    assert differ == {}


#: A fresh interpreter: coal queries a capsule against a turned box (a first box direction
#: without zero components), then two 2 m cubes 1 m apart along x (the second box at x = -3).
_BOX_PROBE = """
import sys, warnings
import coal, numpy as np
if sys.argv[1] == 'first':
    import haptic_topology.model.meshes
turned = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])
coal.distance(coal.Capsule(0.1, 0.3), coal.Transform3s(np.eye(3), np.array([5.0, 1.0, 2.0])),
              coal.Box(1.0, 1.0, 1.0), coal.Transform3s(turned, np.zeros(3)),
              coal.DistanceRequest(), coal.DistanceResult())
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter('always')
    import haptic_topology.model.meshes
print(' | '.join(f'{w.category.__name__}: {w.message}' for w in caught))
print(repr(coal.distance(coal.Box(2.0, 2.0, 2.0), coal.Transform3s(), coal.Box(2.0, 2.0, 2.0),
                         coal.Transform3s(np.eye(3), np.array([-3.0, 0.0, 0.0])),
                         coal.DistanceRequest(), coal.DistanceResult())))
"""


def test_coals_box_is_the_same_in_every_process() -> None:
    """coal 3.0 fixes its box's shape on the process's first box query (``1 + 1e-10`` times
    the half extents on the side away from the direction if that direction has a zero
    component, else exact); the meshes module makes that query on import: after it, a turned
    box queried first changes nothing (the cubes are 1 - 1e-10 m apart, as in a process that
    queried no other box). A box queried before the import is warned about in one line."""
    root = Path(__file__).resolve().parents[3]
    out = [subprocess.run([sys.executable, '-c', _BOX_PROBE, when], capture_output=True,
                          text=True, cwd=root, env={**os.environ, 'PYTHONPATH': str(root)},
                          check=True, timeout=120).stdout.splitlines()
           for when in ('first', 'after')]
    assert out[0] == ['', '0.9999999999']
    assert out[1] == [
        'RuntimeWarning: coal made a box query before haptic_topology.model.meshes was '
        'imported and so fixed its box shape otherwise (coal 3.0: a static in the box '
        'support function): contacts with boxes differ in their last bits from a fresh '
        'process; import haptic_topology.model.meshes before using coal', '1.0']


def test_setup_installs_the_meshes_the_scenarios_use(monkeypatch: pytest.MonkeyPatch) -> None:
    """``setup.py`` installs ``config/meshes/box.stl`` beside the scenarios that name it
    (``../meshes/box.stl``), as ``test_launch_file`` reads setup.py's arguments."""
    import runpy

    import setuptools
    root = Path(__file__).resolve().parents[3]
    captured: dict[str, Any] = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.chdir(root)
    runpy.run_path(str(root / 'setup.py'))
    installed = {src: dest for dest, files in captured['data_files'] for src in files}
    assert installed['config/meshes/box.stl'] == 'share/haptic_topology/config/meshes'
    assert installed['config/scenarios/panda_table.yaml'] == \
        'share/haptic_topology/config/scenarios'


def test_culling_keeps_every_pair_within_the_limit() -> None:
    """The UR5's shapes (meshes and a box) against the mesh table and the box of
    ``ur5_table``: the candidates the model keeps below a limit are those of every pair
    computed one by one (coal, no culling) that are below it, at configurations around the
    start."""
    sc = load_scenario('ur5_table')
    assert sc.contacts is not None
    dyn = LinkageDynamics(sc.linkage)
    cm = ContactModel(dyn.model, sc.linkage, sc.contacts)
    shapes = [s for s in sc.contacts.shapes(sc.linkage) if s.kind in ('mesh', 'box')]
    data = dyn.model.createData()
    rng = np.random.default_rng(7)
    kept = 0
    for _ in range(12):
        q = sc.q0 + rng.uniform(-0.3, 0.3, sc.linkage.dof)
        pin.forwardKinematics(dyn.model, data, q)
        every = []
        for sol in shapes:
            placement = data.oMi[sol.link + 1]
            centre = placement.rotation @ sol.centre + placement.translation
            rotation = placement.rotation @ sol.rotation
            for k, ob in enumerate(sc.contacts.obstacles):
                pair = CoalPair(sol.kind, sol.size, ob, sol.mesh)
                every.append((sol.link, k, pair.gap(centre, rotation)[0]))
        for limit in (0.0, 0.01, 0.05):
            cs = cm.detect(q, margin=limit, jacobians=False)
            want = sorted((link, k, g) for link, k, g in every if g < limit)
            got = sorted(zip(cs.links.tolist(), cs.obstacles.tolist(), cs.gaps.tolist(),
                             strict=True))
            assert [w[:2] for w in want] == [g[:2] for g in got], (q, limit)
            np.testing.assert_allclose([g[2] for g in got], [w[2] for w in want], atol=1e-12)
            kept += len(got)
    assert kept > 0
