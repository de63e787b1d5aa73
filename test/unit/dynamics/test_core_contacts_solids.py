"""Boxes and cylinders on links (issue 13 item 1: "the URDF's collision geometry where it is a
primitive"): the geometry against hand-computed distances, the URDF's boxes and cylinders as
contact shapes (spatial and, projected, planar), the gap's rate equal to the normal velocity of
the contact point (what makes the penalty force passive), energy conserved without damping and
dissipated with it, and what is still refused.

Expected numbers are worked out by hand in each docstring, not with the code under test."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from two_links import two_link_urdf

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import (
    ContactModel,
    ContactParams,
    ContactSettings,
    LinkCapsule,
    LinkSolid,
)
from haptic_topology.errors import ConfigError
from haptic_topology.model import Linkage
from haptic_topology.model.obstacles import obstacles_from_config
from haptic_topology.model.solids import (
    convex_hull_xy,
    cylinder_rims,
    cylinder_sdf,
    polygon_segment,
    solid_gaps,
)
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

BOX12 = Path(__file__).resolve().parents[2] / 'fixtures' / 'meshes' / 'box12.stl'
RY90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])   # local z -> world x
SQUARE = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.1, 0.0]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _obstacle(raw: dict, task: TaskSpace = TaskSpace.SPATIAL):
    return obstacles_from_config([raw], 'test', task)[0]


# ----------------------------------------------------------------------------- geometry


def test_box_against_a_sphere_by_hand() -> None:
    """Box at (0.1, 0.2, 0.3), turned 90 deg about z, half extents (0.05, 0.02, 0.01): in the
    world it spans +-0.02 in x, +-0.05 in y, +-0.01 in z; a sphere of radius 1 mm off a face,
    an edge, inside and off the bottom (through coal): the gap is the box's signed distance
    at the sphere's centre less 1 mm, the point the centre moved onto the surface, the normal
    from the sphere towards the box."""
    c, rot, half = np.array([0.1, 0.2, 0.3]), _rz(math.pi / 2), (0.05, 0.02, 0.01)
    for offset, sdf, grad in (([0.05, 0.0, 0.0], 0.03, [1.0, 0.0, 0.0]),          # face
                              ([0.05, 0.09, 0.0], 0.05, [0.6, 0.8, 0.0]),         # edge
                              ([0.0, 0.045, 0.0], -0.005, [0.0, 1.0, 0.0]),       # inside
                              ([0.0, 0.0, -0.012], 0.002, [0.0, 0.0, -1.0])):
        centre = c + np.array(offset)
        sphere = _obstacle({'type': 'sphere', 'center': centre.tolist(), 'radius': 0.001})
        ((gap, point, normal),) = solid_gaps(sphere, 'box', c, rot, half)
        assert gap == pytest.approx(sdf - 0.001, abs=1e-15)
        np.testing.assert_allclose(normal, -np.array(grad), atol=1e-12)
        np.testing.assert_allclose(point, centre - sdf * np.array(grad), atol=1e-15)


def test_cylinder_sdf_and_rims_by_hand() -> None:
    """Cylinder r = 0.02, half length 0.05 along z: side, cap, rim, inside near the side and
    near a cap; the same turned onto x; the deepest rim points of a tilted cylinder."""
    o = np.zeros(3)
    for p, sdf, grad in (([0.05, 0.0, 0.0], 0.03, [1.0, 0.0, 0.0]),
                         ([0.0, 0.0, 0.08], 0.03, [0.0, 0.0, 1.0]),
                         ([0.05, 0.0, 0.09], 0.05, [0.6, 0.0, 0.8]),
                         ([0.0, -0.015, 0.0], -0.005, [0.0, -1.0, 0.0]),
                         ([0.0, 0.0, -0.045], -0.005, [0.0, 0.0, -1.0])):
        got, g = cylinder_sdf(np.array(p), o, np.eye(3), 0.02, 0.05)
        assert got == pytest.approx(sdf, abs=1e-15)
        np.testing.assert_allclose(g, grad, atol=1e-15)
    got, g = cylinder_sdf(np.array([0.08, 0.0, 0.0]), o, RY90, 0.02, 0.05)
    assert got == pytest.approx(0.03, abs=1e-15)
    np.testing.assert_allclose(g, [1.0, 0.0, 0.0], atol=1e-15)
    # axis a = (cos t, 0, sin t): the rim points lowest along z are c -+ h a + r (sin t, 0, -cos t)
    t = 0.3
    a = np.array([math.cos(t), 0.0, math.sin(t)])
    rot = np.array([[math.sin(t), 0.0, math.cos(t)], [0.0, 1.0, 0.0],
                    [-math.cos(t), 0.0, math.sin(t)]])
    assert np.allclose(rot[:, 2], a) and np.allclose(rot.T @ rot, np.eye(3))
    c = np.array([0.0, 0.0, 0.1])
    rims = cylinder_rims(c, rot, 0.02, 0.05, np.array([0.0, 0.0, 1.0]))
    down = 0.02 * np.array([math.sin(t), 0.0, -math.cos(t)])
    np.testing.assert_allclose(rims, [c - 0.05 * a + down, c + 0.05 * a + down], atol=1e-15)
    # standing on a cap (axis along the plane's normal): the cap centres
    np.testing.assert_allclose(cylinder_rims(c, np.eye(3), 0.02, 0.05, np.array([0.0, 0.0, 1.0])),
                               [[0.0, 0.0, 0.05], [0.0, 0.0, 0.15]], atol=1e-15)


def test_polygon_against_points_and_segments_by_hand() -> None:
    """The square [0, 0.1]^2 (counter-clockwise) against points (discs) and segments: apart,
    the nearest features; overlapping, the smallest separating translation (negative)."""
    cases = [
        # point beside an edge: 0.05 away, witness on the edge, pushed along -x
        ((0.15, 0.05), (0.15, 0.05), 0.05, (0.1, 0.05), (-1.0, 0.0)),
        # point beyond a corner: (0.03, 0.04) from it
        ((0.13, 0.14), (0.13, 0.14), 0.05, (0.1, 0.1), (-0.6, -0.8)),
        # point inside, 0.01 from the edge x = 0.1: the edge's axis, witness under the point
        ((0.09, 0.05), (0.09, 0.05), -0.01, (0.1, 0.05), (-1.0, 0.0)),
        # the line x + y = 0.19 cuts the corner (0.1, 0.1) 0.01/sqrt 2 deep: its normal's axis
        ((0.07, 0.12), (0.12, 0.07), -0.01 / math.sqrt(2), (0.1, 0.1),
         (-1 / math.sqrt(2), -1 / math.sqrt(2))),
        # a segment along y at x = 0.15: 0.05 from the edge x = 0.1
        ((0.15, -0.05), (0.15, 0.2), 0.05, None, (-1.0, 0.0)),
        # a segment along x at y = 0.095 through the square: 0.005 under the top edge; both ends
        # equally deep, so the witness is the middle of the segment projected on that edge
        ((-0.05, 0.095), (0.15, 0.095), -0.005, (0.05, 0.1), (0.0, -1.0)),
    ]
    for a, b, sd, witness, normal in cases:
        got, point, n = polygon_segment(SQUARE, np.array([*a, 0.0]), np.array([*b, 0.0]))
        assert got == pytest.approx(sd, abs=1e-15), (a, b)
        np.testing.assert_allclose(n, [*normal, 0.0], atol=1e-15)
        if witness is not None:
            np.testing.assert_allclose(point, [*witness, 0.0], atol=1e-15)


def test_convex_hull_of_a_turned_box() -> None:
    """A box turned 45 deg about z and 90 deg about x projects to a square turned 45 deg: the
    hull keeps its 4 corners once each, counter-clockwise."""
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    rot = _rz(math.pi / 4) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    half = np.array([0.02, 0.03, 0.02])         # x and (after the turn about x) y: 0.02
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    hull = convex_hull_xy(corners * half @ rot.T)
    assert hull.shape == (4, 3)
    expected = {(round(x, 12), round(y, 12)) for x, y in
                [(0.0, -0.04 * s), (0.04 * c, 0.0), (0.0, 0.04 * s), (-0.04 * c, 0.0)]}
    assert {(round(x, 12), round(y, 12)) for x, y, _ in hull} == expected
    area = 0.5 * sum(hull[i, 0] * hull[(i + 1) % 4, 1] - hull[(i + 1) % 4, 0] * hull[i, 1]
                     for i in range(4))
    assert area == pytest.approx(0.04 * 0.04 * 2 * s * c)      # positive: counter-clockwise


def test_solids_against_a_box_obstacle_by_hand() -> None:
    """coal's signed distance: a slab z in [-0.02, 0.02]; a box (half height 0.01) 5 mm above
    and 5 mm into it, a cube (half 0.01) standing on an edge 3 mm deep (its lowest edge
    0.01 sqrt 2 below its centre), a cylinder (r = 0.01) lying 4 mm above."""
    slab = _obstacle({'type': 'box', 'center': [0.0, 0.0, 0.0],
                      'half_extents': [0.1, 0.1, 0.02]})
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    ry45 = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    for kind, centre, rot, size, gap, point_z in (
            ('box', [0.0, 0.0, 0.035], np.eye(3), (0.05, 0.02, 0.01), 0.005, 0.025),
            ('box', [0.0, 0.0, 0.025], np.eye(3), (0.05, 0.02, 0.01), -0.005, 0.015),
            ('box', [0.01, 0.0, 0.02 + 0.01 * math.sqrt(2) - 0.003], ry45, (0.01,) * 3,
             -0.003, 0.017),
            ('cylinder', [0.0, 0.0, 0.034], RY90, (0.01, 0.05), 0.004, 0.024)):
        [(got, point, normal)] = solid_gaps(slab, kind, np.array(centre), rot, size)
        assert got == pytest.approx(gap, abs=1e-9)
        assert point[2] == pytest.approx(point_z, abs=1e-9)
        np.testing.assert_allclose(normal, [0.0, 0.0, 1.0], atol=1e-9)


# ----------------------------------------------------------------------------- URDF links

BOX_L1 = ('<collision><origin xyz="0.05 0 0"/><geometry><box size="0.1 0.02 0.03"/></geometry>'
          '</collision>')
CYL_L2 = ('<collision><origin xyz="0.04 0 0" rpy="0 1.5707963267948966 0"/>'
          '<geometry><cylinder radius="0.01" length="0.08"/></geometry></collision>')
CYL_UP = ('<collision><origin xyz="0.02 0 0"/><geometry><cylinder radius="0.006" '
          'length="0.03"/></geometry></collision>')


def _urdf(tmp_path: Path, l1: str = BOX_L1, l2: str = CYL_L2, planar: bool = False,
          axis2: str = '0 0 1', name: str = 'solids.urdf') -> Linkage:
    """Link 1 (yaw about z at the origin) carries a 0.1 x 0.02 x 0.03 box from x = 0 to 0.1;
    link 2 (about ``axis2`` at x = 0.1 of link 1) a cylinder r = 0.01 from x = 0 to 0.08."""
    return two_link_urdf(tmp_path, l1, l2, name, axis2, planar, 0.001, 'solids')


def _contacts(linkage: Linkage, obstacles: list[dict], **params: float
              ) -> tuple[LinkageDynamics, ContactModel]:
    dyn = LinkageDynamics(linkage)
    settings = ContactSettings(ContactParams(**params),
                               obstacles_from_config(obstacles, 'test', linkage.task), 0.003,
                               where='test')
    return dyn, ContactModel(dyn.model, linkage, settings)


def test_urdf_box_and_cylinder_are_the_link_shapes(tmp_path: Path) -> None:
    """At q = (0.3, -0.7), against the plane z = -0.02 (normal +z): the box's 4 lower corners
    are 5 mm above it and the 4 upper ones 35 mm; the lying cylinder's two lowest rim points
    10 mm. A sphere of r 0.01 at (0.05, 0.04, 0) in link 1's frame is 0.03 - 0.01 from the
    box's side y = 0.01 (normal -y of link 1) and hypot(0.03, 0.05) - 0.01 from the
    cylinder's rim (link 2 at q2 = 0: the cylinder spans x in [0.1, 0.18] of link 1)."""
    linkage = _urdf(tmp_path)
    shapes = ContactSettings(ContactParams(), (), where='t').shapes(linkage)
    assert [(type(s), s.kind) for s in shapes] == [(LinkSolid, 'box'), (LinkSolid, 'cylinder')]
    assert shapes[0].size == (0.05, 0.01, 0.015) and shapes[1].size == (0.01, 0.04)
    plane = {'type': 'plane', 'point': [0.0, 0.0, -0.02], 'normal': [0.0, 0.0, 1.0]}
    _, cm = _contacts(linkage, [plane])
    q = np.array([0.3, -0.7])
    cs = cm.detect(q, margin=1.0)
    assert cs.links.tolist() == [0] * 8 + [1] * 2
    np.testing.assert_allclose(sorted(cs.gaps[:8]), [0.005] * 4 + [0.035] * 4, atol=1e-15)
    np.testing.assert_allclose(cs.gaps[8:], [0.01, 0.01], atol=1e-15)
    r1, r2 = _rz(0.3), _rz(0.3) @ _rz(-0.7)
    corner = r1 @ [0.1, 0.01, -0.015]      # corner (+, +, -) of the box
    assert np.min(np.linalg.norm(cs.points[:8] - corner, axis=1)) < 1e-15
    tip = r1 @ [0.1, 0.0, 0.0]
    np.testing.assert_allclose(cs.points[8:], [tip + [0, 0, -0.01],
                                               tip + r2 @ [0.08, 0.0, 0.0] + [0, 0, -0.01]],
                               atol=1e-15)
    sphere = {'type': 'sphere', 'center': (r1 @ [0.05, 0.04, 0.0]).tolist(), 'radius': 0.01}
    _, cm = _contacts(linkage, [sphere])
    cs = cm.detect(np.array([0.3, 0.0]), margin=1.0)
    np.testing.assert_allclose(cs.gaps, [0.02, math.hypot(0.03, 0.05) - 0.01], atol=1e-15)
    np.testing.assert_allclose(cs.normals[0], r1 @ [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(cs.points[0], r1 @ [0.05, 0.01, 0.0], atol=1e-15)
    np.testing.assert_allclose(cs.points[1], r1 @ [0.1, 0.01, 0.0], atol=1e-15)


def test_urdf_solids_against_a_box_obstacle(tmp_path: Path) -> None:
    """A box obstacle spanning x in [0.03, 0.07], y in [-0.065, -0.015] (q = 0): 5 mm from
    link 1's box (side y = -0.01), and from link 2's cylinder (end disc at x = 0.1, radius
    0.01) the distance from the obstacle's edge (x 0.07, y -0.015) to the disc's point
    (0.1, -0.01, 0): hypot(0.03, 0.005). GJK's witness on a curved surface is only as good as
    the square root of its distance tolerance (the distance is flat to first order along the
    rim): 1e-5 m."""
    box = {'type': 'box', 'center': [0.05, -0.04, 0.0], 'half_extents': [0.02, 0.025, 0.02]}
    _, cm = _contacts(_urdf(tmp_path), [box])
    cs = cm.detect(np.zeros(2), margin=1.0)
    np.testing.assert_allclose(cs.gaps, [0.005, math.hypot(0.03, 0.005)], atol=1e-9)
    np.testing.assert_allclose(cs.normals[0], [0.0, 1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(cs.points[1], [0.1, -0.01, 0.0], atol=1e-5)


def test_planar_urdf_solids_are_polygons(tmp_path: Path) -> None:
    """Planar: link 1's box projects to the rectangle x in [0, 0.1], y in [-0.01, 0.01]; link
    2's cylinder (axis in the plane) to x in [0.1, 0.18], y in [-0.01, 0.01]; a cylinder along
    z to a disc (a sphere's capsule). A half-plane y >= -0.012: every lower corner 2 mm away;
    a disc r 0.01 at (0.05, 0.03): 0.01; a segment (radius 1 mm) from (0.14, -0.015) to
    (0.14, 0.03) across link 2's rectangle: the rectangle must move 0.025 down (-y) to clear
    it, witness (0.14, 0.01) on its top edge."""
    linkage = _urdf(tmp_path, planar=True)
    shapes = ContactSettings(ContactParams(), (), where='t').shapes(linkage)
    assert [s.kind for s in shapes] == ['polygon', 'polygon']
    np.testing.assert_allclose(shapes[0].vertices, [[0.0, -0.01, 0.0], [0.1, -0.01, 0.0],
                                                    [0.1, 0.01, 0.0], [0.0, 0.01, 0.0]],
                               atol=1e-15)
    upright = ContactSettings(ContactParams(), (), where='t').shapes(
        _urdf(tmp_path, l2=CYL_UP, planar=True, name='up.urdf'))
    assert isinstance(upright[1], LinkCapsule) and upright[1].radius == 0.006
    np.testing.assert_array_equal(upright[1].a, upright[1].b)
    obstacles = [{'type': 'half_plane', 'point': [0.0, -0.012], 'normal': [0.0, 1.0]},
                 {'type': 'disc', 'center': [0.05, 0.03], 'radius': 0.01},
                 {'type': 'segment', 'a': [0.14, -0.015], 'b': [0.14, 0.03], 'radius': 0.001}]
    _, cm = _contacts(linkage, obstacles)
    cs = cm.detect(np.zeros(2), margin=1.0)
    by = {(int(k), int(o)): [] for k, o in zip(cs.links, cs.obstacles, strict=True)}
    for i, key in enumerate(zip(cs.links.tolist(), cs.obstacles.tolist(), strict=True)):
        by[key].append(i)
    np.testing.assert_allclose(sorted(cs.gaps[by[0, 0]]), [0.002, 0.002, 0.022, 0.022],
                               atol=1e-15)
    np.testing.assert_allclose(cs.gaps[by[0, 1]], [0.01], atol=1e-15)
    [k] = by[1, 2]
    assert cs.gaps[k] == pytest.approx(-0.026, abs=1e-15)
    np.testing.assert_allclose(cs.normals[k], [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(cs.points[k], [0.14, 0.01, 0.0], atol=1e-15)


def test_planar_meshes_are_the_projection_of_their_hull(tmp_path: Path) -> None:
    """In a planar task a mesh is the projection of its convex hull, as a box is: the
    12-triangle unit cube scaled and turned as a box on each link gives the box's polygon and,
    at random configurations, the box's candidates against a half-plane, a disc and a segment
    (planar obstacles extend along z, so the whole link meets them where its projection
    does)."""
    turned = '<origin xyz="0.05 0.01 0.02" rpy="0.3 -0.4 0.5"/>'

    def box(mesh: bool) -> str:
        geometry = (f'<mesh filename="{BOX12}" scale="0.1 0.02 0.03"/>' if mesh
                    else '<box size="0.1 0.02 0.03"/>')
        return f'<collision>{turned}<geometry>{geometry}</geometry></collision>'

    prim = _urdf(tmp_path, box(False), box(False), planar=True, name='pb.urdf')
    mesh = _urdf(tmp_path, box(True), box(True), planar=True, name='pm.urdf')
    shapes = [ContactSettings(ContactParams(), (), where='t').shapes(k) for k in (prim, mesh)]
    assert [s.kind for s in shapes[1]] == ['polygon', 'polygon']
    for a, b in zip(*shapes, strict=True):
        assert a.vertices is not None and b.vertices is not None
        np.testing.assert_allclose(b.vertices, a.vertices, atol=1e-15)
    _, cm_p = _contacts(prim, PLANAR_OBSTACLES)
    _, cm_m = _contacts(mesh, PLANAR_OBSTACLES)
    for q in np.random.default_rng(58).uniform(-2.0, 2.0, (20, 2)):
        a, b = cm_p.detect(q, margin=1.0), cm_m.detect(q, margin=1.0)
        np.testing.assert_array_equal(b.obstacles, a.obstacles)
        np.testing.assert_allclose(b.gaps, a.gaps, atol=1e-15)
        np.testing.assert_allclose(b.points, a.points, atol=1e-15)


def test_tilted_planar_cylinders_are_refused(tmp_path: Path) -> None:
    """In a planar task a cylinder tilted out of the plane (its projection has elliptic ends)
    is not modelled: refused in one line naming the link and both choices."""
    tilted = ('<collision><origin rpy="0.4 0 0"/><geometry><cylinder radius="0.01" '
              'length="0.05"/></geometry></collision>')
    linkage = _urdf(tmp_path, l2=tilted, planar=True, name='bad.urdf')
    with pytest.raises(ConfigError) as err:
        ContactSettings.from_config({'obstacles': []}, 'c', linkage)
    assert '\n' not in str(err.value)
    assert re.search(r"^c.links.l2: the URDF gives link 'l2' a cylinder tilted out of the "
                     r'plane \(axis z = 0.921061 in the link frame, whose projection has '
                     r'elliptic ends\) collision shape .*set links.l2.radius \(m\) in this '
                     r'contacts block .*or links.l2.collide: false', str(err.value))
    ok = ContactSettings.from_config({'obstacles': [], 'links': {'l2': {'radius': 0.01}}},
                                     'c', linkage)
    assert [type(s) for s in ok.shapes(linkage)] == [LinkSolid, LinkCapsule]


# ----------------------------------------------------------------------------- dynamics

SPATIAL_OBSTACLES = [
    {'type': 'plane', 'point': [0.0, 0.0, -0.03], 'normal': [0.1, -0.2, 1.0]},
    {'type': 'sphere', 'center': [0.12, 0.06, 0.01], 'radius': 0.02},
    {'type': 'box', 'center': [0.03, 0.1, 0.0], 'half_extents': [0.02, 0.03, 0.04],
     'rpy': [0.1, 0.2, 0.3]}]
PLANAR_OBSTACLES = [
    {'type': 'half_plane', 'point': [0.0, -0.05], 'normal': [0.3, 1.0]},
    {'type': 'disc', 'center': [0.12, 0.06], 'radius': 0.02},
    {'type': 'segment', 'a': [0.02, 0.09], 'b': [0.09, 0.12], 'radius': 0.002}]


@pytest.mark.parametrize('planar', [False, True])
def test_gap_rate_is_the_normal_velocity_of_the_contact_point(tmp_path: Path,
                                                              planar: bool) -> None:
    """For every candidate of every shape and obstacle kind, at random configurations, the
    derivative of the gap (central differences) is ``n^T J_i``: the penalty force at the
    point does the work ``-dU``, so the contacts conserve energy without damping."""
    linkage = _urdf(tmp_path, planar=planar, axis2='0 0 1' if planar else '0 1 1')
    _, cm = _contacts(linkage, PLANAR_OBSTACLES if planar else SPATIAL_OBSTACLES)
    rng = np.random.default_rng(11)
    kinds = set()
    for _ in range(25):
        q = rng.uniform(-1.5, 1.5, 2)
        cs = cm.detect(q, margin=1.0)
        fd = np.zeros((len(cs), 2))
        for j in range(2):
            e = np.zeros(2)
            e[j] = 1e-6
            fd[:, j] = (cm.detect(q + e, margin=1.0).gaps
                        - cm.detect(q - e, margin=1.0).gaps) / 2e-6
        rate = np.einsum('ci,cij->cj', cs.normals, cs.jacobians)
        np.testing.assert_allclose(fd, rate, atol=2e-6)
        kinds.update(zip(cs.links.tolist(), cs.obstacles.tolist(), strict=True))
    assert kinds == {(link, k) for link in (0, 1) for k in range(3)}


def _bounce(tmp_path: Path, planar: bool, **params: float
            ) -> tuple[float, list[float], list[float], float]:
    """The free linkage thrown at the obstacles (no hand wrench, 0.4 s): ``T + U`` and the
    contact energy balance every ms, and the largest U (it did hit something)."""
    linkage = _urdf(tmp_path, planar=planar, axis2='0 0 1' if planar else '0 1 1')
    dyn, cm = _contacts(linkage, PLANAR_OBSTACLES if planar else SPATIAL_OBSTACLES,
                        stiffness=3000.0, **params)
    q0, dq0 = np.array([0.2, -0.3]), np.array([3.0, -4.0])
    ve = VirtualEnvironment(dyn, q0, dq0, internal_step=1e-4, contacts=cm)
    e0 = ve.kinetic_energy() + cm.potential(q0)
    energy, balance, peak = [], [], 0.0
    for _ in range(400):
        ve.integrate(np.zeros(linkage.task.dim), 1e-3)
        u = cm.potential(ve.q)
        peak = max(peak, u)
        energy.append(ve.kinetic_energy() + u)
        balance.append(ve.contact_energy_balance())
    return e0, energy, balance, peak


@pytest.mark.parametrize('planar', [False, True])
def test_solids_conserve_energy_without_damping_and_dissipate_with_it(tmp_path: Path,
                                                                      planar: bool) -> None:
    e0, energy, balance, peak = _bounce(tmp_path, planar, damping=0.0)
    assert peak > 0.05 * e0                          # the contacts were hit hard
    np.testing.assert_allclose(energy, e0, rtol=1e-5)
    assert max(abs(b) for b in balance) < 1e-5 * e0
    e0, energy, balance, _ = _bounce(tmp_path, planar, damping=20.0, friction=0.5)
    assert energy[-1] < 0.9 * e0
    assert max(balance) <= 1e-9 * e0 and balance[-1] < -0.05 * e0


@pytest.mark.parametrize('planar', [False, True])
def test_model_candidates_equal_the_geometry_pair_by_pair(tmp_path: Path, planar: bool) -> None:
    """``detect(q, margin)``'s solid candidates are those of ``solid_gaps`` for each solid
    and obstacle placed by forward kinematics, with ``gap < margin``: the bounding-sphere
    culling drops nothing it should keep."""
    linkage = _urdf(tmp_path, planar=planar, axis2='0 0 1' if planar else '0 1 1')
    _, cm = _contacts(linkage, PLANAR_OBSTACLES if planar else SPATIAL_OBSTACLES)
    shapes = cm.settings.shapes(linkage)
    rng = np.random.default_rng(3)
    counts = []
    for margin in (0.0, 0.01, 1.0):
        for _ in range(15):
            q = rng.uniform(-2.0, 2.0, 2)
            cs = cm.detect(q, margin=margin)
            expected = []
            for sol in shapes:
                placement = cm.data.oMi[sol.link + 1]
                rot, origin = placement.rotation, placement.translation
                verts = None
                if sol.vertices is not None:
                    verts = sol.vertices @ rot.T + origin
                    verts[:, 2] = 0.0
                for k, ob in enumerate(cm.settings.obstacles):
                    for gap, point, normal in solid_gaps(ob, sol.kind, rot @ sol.centre + origin,
                                                         rot @ sol.rotation, sol.size, verts):
                        if gap < margin:
                            expected.append((sol.link, k, gap, *point, *normal))
            got = list(zip(cs.links.tolist(), cs.obstacles.tolist(), cs.gaps.tolist(),
                           *cs.points.T.tolist(), *cs.normals.T.tolist(), strict=True))
            assert len(got) == len(expected)
            counts.append(len(got))
            np.testing.assert_allclose(np.array(got, dtype=float).reshape(-1, 9),
                                       np.array(expected, dtype=float).reshape(-1, 9),
                                       atol=1e-12)
    assert max(counts[:15]) > 0 and min(counts[30:]) > max(counts[:15])   # some hit, some not


def test_lmi_contacts_of_solids_equal_the_ve_at_the_update(tmp_path: Path) -> None:
    """The LMI's frozen contacts (eq. 17) give the VE's contact torques at the update's
    ``(q, dq)`` for boxes and cylinders too."""
    linkage = _urdf(tmp_path, axis2='0 1 1')
    dyn, cm = _contacts(linkage, SPATIAL_OBSTACLES, damping=30.0, friction=0.4)
    q, dq = np.array([1.5, 0.2]), np.array([0.4, -0.9])
    local = cm.local(q)
    assert len(local) >= 3 and np.any(local.gaps < 0.0)
    tau, _ = cm.torques(q, dq)
    forces = local.forces(q, dq)
    assert forces is not None
    np.testing.assert_allclose(local.stacked_jacobian.T @ forces.ravel(), tau, rtol=1e-12,
                               atol=1e-15)


def test_box_table_scenario_sets_the_cube_down_flat() -> None:
    """6-D, URDF boxes and cylinder: F_h = 0.3 N down on the tool cube's centre; at rest the
    cube stands on its 4 lower corners, each 0.3 / 4 / k = 37.5 um deep, the device pushes
    back with 0.3 N, and the contacts inject no energy."""
    sc = load_scenario('box_table')
    trace = simulate(sc)
    s = trace.summary()
    assert s['energy_injected_j'] == 0.0 and s['energy_dissipated_j'] > 0.0
    assert 0.0 < s['max_penetration_m'] < 0.001 and s['contact_time_s'] > 1.5
    depth = trace.columns['penetration']      # as the VE's last update reported it
    assert depth[np.isfinite(depth)][-1] == pytest.approx(0.3 / 4 / 2000.0, rel=1e-3)
    np.testing.assert_allclose(trace.columns['applied'][-1], [0.0, 0.0, 0.3, 0.0, 0.0, 0.0],
                               atol=1e-4)
    dyn = LinkageDynamics(sc.linkage)
    cm = ContactModel(dyn.model, sc.linkage, sc.contacts)
    cs = cm.detect(trace.columns['q'][-1], 0.0)
    assert len(cs) == 4
    np.testing.assert_allclose(cs.gaps, -0.3 / 4 / 2000.0, rtol=2e-3)
