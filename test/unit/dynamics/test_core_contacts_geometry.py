"""VE collision geometry: capsule-obstacle gaps against hand-computed distances, a sampled
cross-check, and config errors that name the field (haptic_topology.model.obstacles)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose

from haptic_topology.errors import ConfigError
from haptic_topology.model.obstacles import (
    Obstacle,
    ObstacleKind,
    capsule_gaps,
    obstacles_from_config,
)
from haptic_topology.vocabulary import TaskSpace

W = 'fig.yaml: scenario.contacts.obstacles'
PLANAR, SPATIAL = TaskSpace.PLANAR, TaskSpace.SPATIAL
X0, X1 = np.zeros(3), np.array([0.1, 0.0, 0.0])  # a 0.1 m link along world x
S2 = math.sqrt(2.0)
#: The unit cube [-0.5, 0.5]^3 as 12 triangles (ASCII STL, written for these tests).
BOX12 = Path(__file__).resolve().parents[2] / 'fixtures' / 'meshes' / 'box12.stl'


def one(raw: dict[str, Any], task: TaskSpace = PLANAR) -> Obstacle:
    (obs,) = obstacles_from_config([raw], W, task)
    return obs


def single(obs: Obstacle, p0: Any, p1: Any, r: float) -> tuple[float, float, np.ndarray]:
    cands = capsule_gaps(obs, np.asarray(p0, float), np.asarray(p1, float), r)
    assert len(cands) == 1
    return cands[0]


def check(cand: tuple[float, float, np.ndarray], gap: float, s: float | None,
          normal: Any, s_tol: float = 1e-12, tol: float = 1e-12) -> None:
    assert cand[0] == pytest.approx(gap, abs=tol)
    if s is not None:
        assert cand[1] == pytest.approx(s, abs=s_tol)
    assert_allclose(cand[2], normal, atol=1e-9)


# --- half-plane / plane -------------------------------------------------------------------

def test_half_plane_gives_one_candidate_per_axis_end() -> None:
    wall = one({'type': 'half_plane', 'point': [0.105, 0.0], 'normal': [-1, 0]})
    c0, c1 = capsule_gaps(wall, X0, X1, 0.01)
    check(c0, 0.105 - 0.01, 0.0, [-1, 0, 0])   # n.(p0 - point) = -(0 - 0.105) = 0.105
    check(c1, 0.005 - 0.01, 1.0, [-1, 0, 0])   # -(0.1 - 0.105) = 0.005 -> -0.005 (penetration)


def test_half_plane_degenerate_capsule_gives_one_candidate() -> None:
    wall = one({'type': 'half_plane', 'point': [0.0, 0.2], 'normal': [0, -2]})
    p = np.array([0.05, 0.17, 0.0])
    check(single(wall, p, p, 0.01), 0.03 - 0.01, 0.0, [0, -1, 0])  # -(0.17 - 0.2) = 0.03


def test_tilted_plane_normal_is_normalised() -> None:
    plane = one({'type': 'plane', 'point': [0, 0, 0.1], 'normal': [0, 1, 1]}, SPATIAL)
    n = np.array([0.0, 1.0, 1.0]) / S2
    c0, c1 = capsule_gaps(plane, X0, np.array([0.0, 0.1, 0.1]), 0.01)
    check(c0, -0.1 / S2 - 0.01, 0.0, n)  # n.((0,0,0) - (0,0,0.1)) = -0.1/sqrt2
    check(c1, 0.1 / S2 - 0.01, 1.0, n)   # n.((0,0.1,0.1) - (0,0,0.1)) = 0.1/sqrt2


# --- disc / sphere --------------------------------------------------------------------------

def test_disc_beside_the_middle() -> None:
    disc = one({'type': 'disc', 'center': [0.05, 0.03], 'radius': 0.01})
    # closest axis point (0.05, 0): distance 0.03 -> 0.03 - 0.01 (R) - 0.01 (r) = 0.01
    check(single(disc, X0, X1, 0.01), 0.01, 0.5, [0, -1, 0])


def test_disc_behind_the_end_is_clamped() -> None:
    disc = one({'type': 'disc', 'center': [0.13, 0.04], 'radius': 0.01})
    # projection s = 0.13 / 0.1 = 1.3 -> s = 1, point (0.1, 0); v = (-0.03, -0.04), |v| = 0.05
    check(single(disc, X0, X1, 0.01), 0.05 - 0.02, 1.0, [-0.6, -0.8, 0])


def test_disc_centre_on_the_axis_picks_the_xy_perpendicular() -> None:
    disc = one({'type': 'disc', 'center': [0.05, 0.0], 'radius': 0.01})
    # distance 0 -> gap -R - r = -0.02; normal z x axis = (0, 1, 0)
    check(single(disc, X0, X1, 0.01), -0.02, 0.5, [0, 1, 0])
    check(single(disc, [0.05, 0, 0], [0.05, 0, 0], 0.01), -0.02, 0.0, [1, 0, 0])  # degenerate


def test_sphere() -> None:
    sph = one({'type': 'sphere', 'center': [0.02, 0.03, 0.04], 'radius': 0.01}, SPATIAL)
    # projection s = 0.02/0.1 = 0.2, point (0.02, 0, 0); v = (0, -0.03, -0.04), |v| = 0.05
    check(single(sph, X0, X1, 0.01), 0.05 - 0.02, 0.2, [0, -0.6, -0.8])
    # degenerate capsule at (0.02, 0.03, 0.16): v = (0, 0, 0.12) -> 0.12 - 0.01 - 0.005
    p = [0.02, 0.03, 0.16]
    check(single(sph, p, p, 0.005), 0.105, 0.0, [0, 0, 1])


def test_sphere_centre_on_the_axis_is_deterministic() -> None:
    sph = one({'type': 'sphere', 'center': [0.05, 0, 0], 'radius': 0.01}, SPATIAL)
    gap, s, n = single(sph, X0, X1, 0.01)
    assert (gap, s) == pytest.approx((-0.02, 0.5))
    assert_allclose(n, [0, 0, 1])  # axis x cross e_y (the least aligned axis) = +z
    check(single(sph, [0.05, 0, 0], [0.05, 0, 0], 0.0), -0.01, 0.0, [1, 0, 0])


# --- segment --------------------------------------------------------------------------------

def seg(a: list[float], b: list[float], radius: float = 0.0) -> Obstacle:
    return one({'type': 'segment', 'a': a, 'b': b, 'radius': radius})


def test_segment_skew() -> None:
    # end a = (0.05, 0.02) of the rising obstacle is 0.02 above axis point s = 0.5; the link end
    # (0.1, 0) is |0.05*1 - (-0.02)*2| / sqrt(5) = 0.0402 from the obstacle's line: farther
    check(single(seg([0.05, 0.02], [0.15, 0.07], 0.002), X0, X1, 0.01),
          0.02 - 0.01 - 0.002, 0.5, [0, -1, 0])
    # vertical obstacle x = 0.13 across y = 0: link end (0.1, 0) to (0.13, 0) is 0.03
    check(single(seg([0.13, -0.05], [0.13, 0.05]), X0, X1, 0.01), 0.02, 1.0, [-1, 0, 0])


def test_segment_parallel() -> None:
    # overlap of the obstacle's projection [0.6, 2] with [0, 1] is [0.6, 1]: its middle s = 0.8
    for a, b in (([0.06, 0.02], [0.2, 0.02]), ([0.2, 0.02], [0.06, 0.02])):
        check(single(seg(a, b, 0.001), X0, X1, 0.01), 0.02 - 0.011, 0.8, [0, -1, 0])
    # obstacle on the axis' line beyond the end: (0.1, 0) to (0.13, 0.04) = 0.05 (3-4-5)
    check(single(seg([0.13, 0.04], [0.3, 0.04]), X0, X1, 0.0), 0.05, 1.0, [-0.6, -0.8, 0])
    check(single(seg([-0.3, -0.04], [-0.03, -0.04]), X0, X1, 0.0), 0.05, 0.0, [0.6, 0.8, 0])


def test_segment_crossing() -> None:
    # crossing at x = 0.03 (s = 0.3): gap -r - R; perpendicular of (0, 0.1) is (-1, 0), but
    # the axis midpoint (0.05, 0) lies on the +x side of the obstacle -> (1, 0, 0)
    check(single(seg([0.03, -0.05], [0.03, 0.05], 0.002), X0, X1, 0.01), -0.012, 0.3, [1, 0, 0])
    # crossing through the midpoint: ambiguous side -> +perpendicular (-1, 0, 0)
    check(single(seg([0.05, -0.05], [0.05, 0.05]), X0, X1, 0.01), -0.01, 0.5, [-1, 0, 0])


def test_segment_degenerate_capsule_and_degenerate_obstacle() -> None:
    p = [0.05, 0.03, 0.0]  # a disc-like link 0.03 above the obstacle's middle
    check(single(seg([0.0, 0.0], [0.1, 0.0], 0.001), p, p, 0.01), 0.03 - 0.011, 0.0, [0, 1, 0])
    dot = Obstacle(ObstacleKind.SEGMENT, 'dot', point=np.array([0.2, 0, 0]),
                   end=np.array([0.2, 0, 0]))
    check(single(dot, X0, X1, 0.01), 0.1 - 0.01, 1.0, [-1, 0, 0])  # (0.1, 0) to (0.2, 0)


# --- box ------------------------------------------------------------------------------------

#: coal's GJK/EPA tolerance (m): a box obstacle's gaps are coal's signed distances.
COAL = 1e-10
BOX = {'type': 'box', 'center': [0, 0, 0], 'half_extents': [0.1, 0.05, 0.02]}


def test_box_outside_face_edge_and_corner() -> None:
    box = one(BOX, SPATIAL)
    # above the top face z = 0.02, axis going up: 0.05 - 0.02 - 0.01
    check(single(box, [0, 0, 0.05], [0, 0, 0.15], 0.01), 0.02, 0.0, [0, 0, 1], tol=COAL)
    # off the edge (x = 0.1, z = 0.02): q = (0.03, -0.05, 0.04) -> sqrt(0.03^2 + 0.04^2) = 0.05
    check(single(box, [0.13, 0, 0.06], [0.23, 0, 0.16], 0.01), 0.04, 0.0, [0.6, 0, 0.8], tol=COAL)
    # corner: q = (0.02, 0.02, 0.02) -> 0.02 sqrt(3)
    check(single(box, [0.12, 0.07, 0.04], [0.22, 0.17, 0.14], 0.0), 0.02 * math.sqrt(3), 0.0,
          np.ones(3) / math.sqrt(3), tol=COAL)
    # axis on x + y = 0.25 (z = 0) passes the xy corner (0.1, 0.05) at |0.15 - 0.25|/sqrt2;
    # its foot (0.15, 0.1) is the axis' middle
    check(single(box, [0.2, 0.05, 0], [0.1, 0.15, 0], 0.01), 0.1 / S2 - 0.01, 0.5,
          [1 / S2, 1 / S2, 0], tol=COAL)


def test_box_inside_is_minus_the_nearest_face_distance() -> None:
    box = one(BOX, SPATIAL)
    # q = (|x| - 0.1, 0.01 - 0.05, 0.005 - 0.02): the top face is nearest along the whole axis
    check(single(box, [-0.02, 0.01, 0.005], [0.03, 0.01, 0.005], 0.01), -0.015 - 0.01, None,
          [0, 0, 1], tol=COAL)
    check(single(box, [-0.02, 0.01, -0.005], [0.03, 0.01, -0.005], 0.0), -0.015, None,
          [0, 0, -1], tol=COAL)
    p = [0.09, 0.01, 0.0]  # q = (-0.01, -0.04, -0.02): the +x face at 0.01
    check(single(box, p, p, 0.005), -0.015, 0.0, [1, 0, 0], tol=COAL)


def test_box_rotated_45_degrees_about_z() -> None:
    box = one({'type': 'box', 'center': [0, 0, 0], 'half_extents': [0.05, 0.05, 0.05],
               'rpy': [0, 0, math.pi / 4]}, SPATIAL)
    # the corner local (0.05, -0.05) sits at world (0.05 sqrt2, 0); the axis x = 0.15 passes it
    # at 0.15 - 0.0707107 = 0.0792893 (at y = 0, s = 0.5), normal = world +x
    check(single(box, [0.15, -0.1, 0], [0.15, 0.1, 0], 0.01), 0.15 - 0.05 * S2 - 0.01, 0.5,
          [1, 0, 0], s_tol=1e-9, tol=COAL)
    # (0.1, 0.1, 0) is local (0.1 sqrt2, 0, 0): 0.1 sqrt2 - 0.05 off the local +x face
    p = [0.1, 0.1, 0.0]
    check(single(box, p, p, 0.0), 0.1 * S2 - 0.05, 0.0, [1 / S2, 1 / S2, 0], tol=COAL)


# --- sampled cross-check --------------------------------------------------------------------

def pointwise(obs: Obstacle, x: np.ndarray) -> np.ndarray:
    """Signed distance (m) of points x (N, 3) to the obstacle, written independently."""
    if obs.kind in (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE):
        return (x - obs.point) @ obs.normal
    if obs.kind in (ObstacleKind.DISC, ObstacleKind.SPHERE):
        return np.linalg.norm(x - obs.point, axis=1) - obs.radius
    if obs.kind is ObstacleKind.SEGMENT:
        d = obs.end - obs.point
        t = np.clip((x - obs.point) @ d / (d @ d), 0.0, 1.0)
        return np.linalg.norm(x - obs.point - t[:, None] * d, axis=1) - obs.radius
    # a box; a mesh obstacle here is the 12-triangle unit cube scaled to the box
    half = obs.half_extents if obs.mesh is None else 0.5 * np.array(obs.mesh.scale)
    q = np.abs((x - obs.point) @ obs.rotation) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def sampled_min(obs: Obstacle, p0: np.ndarray, p1: np.ndarray, r: float) -> float:
    """Min over 20001 uniform s, refined by 20001 more around the best (f is convex in s, so
    its minimiser lies within one step of the best sample): exact to ~|p1 - p0| 1e-8 / 2."""
    f = lambda s: pointwise(obs, p0 + s[:, None] * (p1 - p0)) - r  # noqa: E731
    grid = np.linspace(0.0, 1.0, 20001)
    k = int(np.argmin(f(grid)))
    fine = np.linspace(grid[max(k - 1, 0)], grid[min(k + 1, 20000)], 20001)
    return float(f(fine).min())


def random_obstacle(rng: np.random.Generator, kind: ObstacleKind) -> Obstacle:
    def pt() -> list[float]:
        v = rng.uniform(-0.1, 0.1, 3 if kind.task is SPATIAL else 2)
        return [float(c) for c in v]
    raw: dict[str, Any] = {'type': kind.value}
    if kind in (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE):
        raw.update(point=pt(), normal=pt())
    elif kind is ObstacleKind.SEGMENT:
        raw.update(a=pt(), b=pt(), radius=float(rng.choice([0.0, rng.uniform(0, 0.02)])))
    elif kind is ObstacleKind.BOX:
        raw.update(center=pt(), half_extents=rng.uniform(0.005, 0.1, 3).tolist(),
                   rpy=rng.uniform(-math.pi, math.pi, 3).tolist())
    elif kind is ObstacleKind.MESH:     # the box above as a mesh of 12 triangles
        raw.update(file=str(BOX12), center=pt(), scale=rng.uniform(0.01, 0.2, 3).tolist(),
                   rpy=rng.uniform(-math.pi, math.pi, 3).tolist())
    else:
        raw.update(center=pt(), radius=float(rng.uniform(0.002, 0.05)))
    return one(raw, kind.task)


@pytest.mark.parametrize('kind', list(ObstacleKind), ids=lambda k: k.value)
def test_gap_matches_sampled_minimum(kind: ObstacleKind) -> None:
    rng = np.random.default_rng(20240 + list(ObstacleKind).index(kind))
    mask = np.array([1.0, 1.0, 1.0 if kind.task is SPATIAL else 0.0])
    for trial in range(40):
        obs = random_obstacle(rng, kind)
        p0 = rng.uniform(-0.12, 0.12, 3) * mask
        p1 = p0 if trial % 8 == 0 else rng.uniform(-0.12, 0.12, 3) * mask
        r = float(rng.uniform(0.0, 0.02))
        cands = capsule_gaps(obs, p0, p1, r)
        gap = min(c[0] for c in cands)
        sampled = sampled_min(obs, p0, p1, r)
        coal_kind = kind in (ObstacleKind.BOX, ObstacleKind.MESH)
        if coal_kind and sampled < 0.0:
            # coal's depth is the shortest translation that separates the two (EPA), at least
            # the depth of the capsule's deepest point, which is -sampled
            assert gap <= sampled + 1e-9, (trial, obs)
            continue
        assert gap == pytest.approx(sampled, abs=1e-9), (trial, obs)
        for g, s, n in cands:
            assert 0.0 <= s <= 1.0 and np.linalg.norm(n) == pytest.approx(1.0)
            assert n[2] == 0.0 or kind.task is SPATIAL
            x = p0 + s * (p1 - p0)
            tol = 1e-9 if coal_kind else 1e-12     # coal: GJK tolerance
            assert g == pytest.approx(pointwise(obs, x[None])[0] - r, abs=tol)  # gap at s
        if gap + r > 1e-3:  # apart: moving the link along the normal opens the gap 1:1
            h = 1e-6
            moved = min(c[0] for c in capsule_gaps(obs, p0 + h * n, p1 + h * n, r))
            assert (moved - gap) / h == pytest.approx(1.0, abs=1e-3), (trial, obs)


def test_a_box_obstacle_is_the_same_box_as_a_mesh() -> None:
    """A capsule against a box obstacle and against the 12-triangle unit cube scaled and
    placed as that box: the same gap (the two solids' signed distance, to coal's tolerance)
    at poses apart, overlapping, and with the capsule's axis deep inside the box (there the
    depth is the translation that separates the solids, beyond that of the axis' deepest
    point), and the same normal where it is unique."""
    rng = np.random.default_rng(58)
    deep = 0
    for _ in range(200):
        centre, half = rng.uniform(-0.02, 0.02, 3), rng.uniform(0.01, 0.05, 3)
        rpy = rng.uniform(-math.pi, math.pi, 3).tolist()
        box = one({'type': 'box', 'center': centre.tolist(), 'half_extents': half.tolist(),
                   'rpy': rpy}, SPATIAL)
        mesh = one({'type': 'mesh', 'file': str(BOX12), 'center': centre.tolist(),
                    'scale': (2.0 * half).tolist(), 'rpy': rpy}, SPATIAL)
        p0, p1 = rng.uniform(-0.06, 0.06, 3), rng.uniform(-0.06, 0.06, 3)
        r = float(rng.uniform(0.0, 0.01))
        (a,), (b,) = capsule_gaps(box, p0, p1, r), capsule_gaps(mesh, p0, p1, r)
        assert a[0] == pytest.approx(b[0], abs=1e-9)
        deep += a[0] < sampled_min(box, p0, p1, r) - 1e-6
        if abs(a[0]) > 1e-6:
            assert_allclose(a[2], b[2], atol=1e-6)
    assert deep > 10        # poses where the axis' deepest point is not the depth


# --- config ---------------------------------------------------------------------------------

def test_planar_config_parses() -> None:
    wall, rail, disc = obstacles_from_config([
        {'type': 'half_plane', 'point': [0.1, 0.2], 'normal': [3, 4]},
        {'type': 'segment', 'a': [0, 0, 0], 'b': [0.1, 0], 'name': 'rail'},
        {'type': 'disc', 'center': [0.05, -0.03], 'radius': 0.02},
    ], W, PLANAR)
    assert (wall.kind, wall.name) == (ObstacleKind.HALF_PLANE, 'half_plane0')
    assert_allclose(wall.point, [0.1, 0.2, 0.0])
    assert_allclose(wall.normal, [0.6, 0.8, 0.0])  # (3, 4) / 5
    assert (rail.kind, rail.name, rail.radius) == (ObstacleKind.SEGMENT, 'rail', 0.0)
    assert_allclose(rail.point, [0, 0, 0])
    assert_allclose(rail.end, [0.1, 0, 0])
    assert_allclose(rail.normal, np.zeros(3))
    assert (disc.name, disc.radius) == ('disc2', 0.02)
    assert_allclose(disc.point, [0.05, -0.03, 0.0])
    assert_allclose(disc.rotation, np.eye(3))
    assert not disc.point.flags.writeable
    assert obstacles_from_config([], W, PLANAR) == ()


def test_spatial_config_parses() -> None:
    yaw = 0.3
    plane, sph, box, tilted = obstacles_from_config([
        {'type': 'plane', 'point': [0, 0, -0.1], 'normal': [0, 0, 2], 'name': 'floor'},
        {'type': 'sphere', 'center': [0.1, 0.2, 0.3], 'radius': 0.05},
        {'type': 'box', 'center': [0.1, 0, 0], 'half_extents': [0.1, 0.2, 0.3],
         'rpy': [0, 0, yaw]},
        {'type': 'box', 'center': [0, 0, 0], 'half_extents': [0.1, 0.1, 0.1],
         'rpy': [0.1, 0.2, 0.3]},
    ], W, SPATIAL)
    assert plane.name == 'floor'
    assert_allclose(plane.normal, [0, 0, 1])
    assert (sph.kind, sph.radius) == (ObstacleKind.SPHERE, 0.05)
    assert_allclose(sph.point, [0.1, 0.2, 0.3])
    assert_allclose(box.half_extents, [0.1, 0.2, 0.3])
    c, s = math.cos(yaw), math.sin(yaw)
    assert_allclose(box.rotation, np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), atol=1e-15)

    def rot(axis: int, a: float) -> np.ndarray:
        i, j = [k for k in range(3) if k != axis]
        m = np.eye(3)
        m[i, i] = m[j, j] = math.cos(a)
        m[i, j], m[j, i] = -math.sin(a), math.sin(a)
        return m if axis != 1 else m.T  # Ry: [[c, 0, s], [0, 1, 0], [-s, 0, c]]

    assert_allclose(tilted.rotation, rot(2, 0.3) @ rot(1, 0.2) @ rot(0, 0.1), atol=1e-15)
    assert_allclose(rot(1, 0.2)[0, 2], math.sin(0.2))


@pytest.mark.parametrize('items, task, field, expected', [
    ([{'type': 'cube', 'center': [0, 0]}], PLANAR, 'obstacles[0].type',
     "expected one of half_plane, segment, disc (a planar scenario), got 'cube'"),
    ([{'type': 'sphere', 'center': [0, 0, 0], 'radius': 0.1}], PLANAR, 'obstacles[0].type',
     "'sphere' is a spatial obstacle; a planar scenario expects one of half_plane, segment, "
     'disc'),
    ([{'type': 'disc', 'center': [0, 0], 'radius': 0.1}], SPATIAL, 'obstacles[0].type',
     "'disc' is a planar obstacle; a spatial scenario expects one of plane, sphere, box"),
    ([{'type': 'half_plane', 'point': [0, 0], 'normal': [0, 0]}], PLANAR, 'obstacles[0].normal',
     'expected a nonzero vector'),
    ([{'type': 'disc', 'center': [0, 0], 'radius': 0.1},
      {'type': 'disc', 'center': [0, 0], 'radius': -0.01}], PLANAR, 'obstacles[1].radius',
     'expected a value > 0.0, got -0.01'),
    ([{'type': 'segment', 'a': [0, 0], 'b': [1, 1]},
      {'type': 'segment', 'a': [0, 0], 'b': [1, 1], 'radius': -0.01}], PLANAR,
     'obstacles[1].radius', 'expected a value >= 0.0, got -0.01'),
    ([{'type': 'segment', 'a': [0.1, 0.2], 'b': [0.1, 0.2, 0]}], PLANAR, 'obstacles[0].b',
     'expected an end different from a'),
    ([{'type': 'box', 'center': [0, 0, 0], 'half_extents': [0.1, 0, 0.1]}], SPATIAL,
     'obstacles[0].half_extents[1]', 'expected a value > 0.0, got 0.0'),
    ([{'type': 'box', 'center': [0, 0, 0], 'half_extents': [0.1, 0.1]}], SPATIAL,
     'obstacles[0].half_extents', 'expected 3 numbers, got 2'),
    ([{'type': 'disc', 'center': [0, 0], 'radius': 0.1, 'colour': 'red'}], PLANAR,
     'obstacles[0].colour', 'unknown key (expected one of: center, name, radius, type)'),
    ([{'type': 'disc', 'center': [0, 0]}], PLANAR, 'obstacles[0].radius',
     'missing required key'),
    ([{'center': [0, 0]}], PLANAR, 'obstacles[0].type', 'missing required key'),
    ([{'type': 'disc', 'center': [0, 0, 0.1], 'radius': 0.1}], PLANAR,
     'obstacles[0].center[2]', 'expected z = 0 in a planar scenario'),
    ([{'type': 'disc', 'center': [0], 'radius': 0.1}], PLANAR, 'obstacles[0].center',
     'expected 2 or 3 numbers'),
    ([{'type': 'disc', 'center': [0, 0], 'radius': 0.1, 'name': 'a'},
      {'type': 'disc', 'center': [1, 0], 'radius': 0.1, 'name': 'a'}], PLANAR,
     'obstacles[1].name', "expected a unique name, 'a' is already used"),
    (['disc'], PLANAR, 'obstacles[0]', 'expected a mapping'),
    ({'type': 'disc'}, PLANAR, 'obstacles', 'expected a list of obstacles, got dict'),
    (None, PLANAR, 'obstacles', 'expected a list of obstacles, got NoneType'),
])
def test_config_errors_name_the_field(items: Any, task: TaskSpace, field: str,
                                      expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        obstacles_from_config(items, W, task)
    msg = str(err.value)
    assert msg.startswith(f'fig.yaml: scenario.contacts.{field}: '), msg
    assert expected in msg, msg
    assert re.search(r'\s{2,}', msg) is None, msg
