"""The contacts' broad phase (``dynamics/contact_bounds``) and coal pairs answering each query
afresh: skipping a pair, or reusing coal's objects, changes no contact.

The expectations do not come from the bounds under test: every pair is computed one by one
(coal, the closed forms of ``solids.solid_gaps``, no bound) and the candidates the model keeps
below a limit must be exactly those; a box bound is checked on a shape whose gaps are known by
hand."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import coal
import numpy as np
import pinocchio as pin
import pytest
from two_links import two_link_urdf

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics import contact_bounds as bounds
from haptic_topology.dynamics.contacts import ContactModel, ContactParams, ContactSettings
from haptic_topology.model.meshes import distance_request
from haptic_topology.model.obstacles import obstacles_from_config
from haptic_topology.model.solids import CoalPair, solid_gaps
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

BOX12 = Path(__file__).resolve().parents[2] / 'fixtures' / 'meshes' / 'box12.stl'
#: A plane, a sphere, a box and a mesh around the links' reach (0.1 m, 0.3 m).
OBSTACLES: list[dict[str, Any]] = [
    {'type': 'plane', 'point': [0.0, 0.0, -0.06], 'normal': [0.1, -0.2, 1.0]},
    {'type': 'sphere', 'center': [0.12, 0.06, 0.01], 'radius': 0.02},
    {'type': 'box', 'center': [0.03, 0.12, 0.0], 'half_extents': [0.02, 0.03, 0.04],
     'rpy': [0.1, 0.2, 0.3]},
    {'type': 'mesh', 'file': str(BOX12), 'center': [0.08, -0.11, 0.05],
     'scale': [0.03, 0.05, 0.04], 'rpy': [0.3, -0.1, 0.2]}]


def _model(tmp_path: Path) -> tuple[Any, ContactModel, list[Any]]:
    """Link 1 (yaw) carries a box, a cylinder and a mesh (the 12-triangle box, off its
    frame); link 2 (about (0, 1, 1) at x = 0.1) a long thin box and a mesh; OBSTACLES."""

    def col(origin: str, geometry: str) -> str:
        return f'<collision><origin {origin}/><geometry>{geometry}</geometry></collision>'

    l1 = (col('xyz="0.05 0 0" rpy="0.1 -0.2 0.3"', '<box size="0.1 0.02 0.03"/>')
          + col('xyz="0.02 0.03 0" rpy="0.5 0 0"', '<cylinder radius="0.01" length="0.04"/>')
          + col('xyz="0.06 -0.02 0.01" rpy="0 0.4 -0.2"',
                f'<mesh filename="{BOX12}" scale="0.04 0.02 0.02"/>'))
    l2 = (col('xyz="0.15 0 0" rpy="0 0 0.05"', '<box size="0.3 0.01 0.01"/>')
          + col('xyz="0.25 0.01 0" rpy="0.2 0.1 0"',
                f'<mesh filename="{BOX12}" scale="0.03 0.03 0.03"/>'))
    linkage = two_link_urdf(tmp_path, l1, l2, 'b.urdf')
    dyn = LinkageDynamics(linkage)
    settings = ContactSettings(ContactParams(), obstacles_from_config(
        OBSTACLES, 'test', TaskSpace.SPATIAL), 0.003, where='test')
    shapes = [s for s in settings.shapes(linkage) if s.kind in ('box', 'cylinder', 'mesh')]
    return dyn.model, ContactModel(dyn.model, linkage, settings), shapes


def _every_pair(model: Any, cm: ContactModel, shapes: list[Any], q: np.ndarray, exact: bool
                ) -> list[tuple[int, int, float, list[float], list[float]]]:
    """Every candidate of every solid and obstacle at ``q``, no pair skipped: ``(link,
    obstacle, gap, point, normal)``, solid by solid, obstacle by obstacle. ``exact``: every
    pair through coal (the robots' meshes and boxes), placed as the model places them."""
    data = model.createData()
    pin.forwardKinematics(model, data, q)
    out = []
    for sol in shapes:
        placement = data.oMi[sol.link + 1]
        rot = np.array(placement.rotation, order='C')   # as the model's (Pinocchio's: F)
        centre, rotation = rot @ sol.centre + placement.translation, rot @ sol.rotation
        for k, ob in enumerate(cm.settings.obstacles):
            # coal: a mesh against anything, a box or cylinder against a box or a mesh, a box
            # against a sphere; else the closed forms (a plane's corners and rims, a
            # cylinder against a sphere)
            if exact or sol.mesh is not None or ob.kind.value in ('box', 'mesh') or (
                    sol.kind == 'box' and ob.kind.value == 'sphere'):
                found = [CoalPair(sol.kind, sol.size, ob, sol.mesh).gap(centre, rotation)]
            else:
                found = solid_gaps(ob, sol.kind, centre, rotation, sol.size)
            out += [(sol.link, k, gap, point.tolist(), normal.tolist())
                    for gap, point, normal in found]
    return out


def _kept(cm: ContactModel, q: np.ndarray, limit: float
          ) -> list[tuple[int, int, float, list[float], list[float]]]:
    cs = cm.detect(q, margin=limit, jacobians=False)
    return list(zip(cs.links.tolist(), cs.obstacles.tolist(), cs.gaps.tolist(),
                    cs.points.tolist(), cs.normals.tolist(), strict=True))


def test_every_pair_below_the_limit_is_kept(tmp_path: Path) -> None:
    """Boxes, a cylinder and meshes (two links) against a plane, a sphere, a box and a mesh,
    at 300 configurations and four limits: the candidates kept are those of every pair
    computed one by one that are below the limit (a box's corners and a cylinder's rims
    against the plane computed by ``solid_gaps``' own arithmetic: to 1e-15 m), and pairs were
    skipped."""
    model, cm, shapes = _model(tmp_path)
    rng = np.random.default_rng(58)
    kept = skipped = 0
    for _ in range(300):
        q = rng.uniform(-np.pi, np.pi, 2)
        every = _every_pair(model, cm, shapes, q, exact=False)
        for limit in (0.0, 0.002, 0.01, 0.05):
            want = [c for c in every if c[2] < limit]
            got = _kept(cm, q, limit)
            assert [c[:2] for c in got] == [c[:2] for c in want], (q, limit)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_allclose([g[2], *g[3], *g[4]], [w[2], *w[3], *w[4]],
                                           rtol=0.0, atol=1e-15)
            kept += len(got)
            skipped += int(bounds.near_pairs(
                np.array([cm.data.oMi[j].homogeneous for j in (1, 2)]),
                np.array([s.link for s in shapes], dtype=np.int64), cm._solid_rows,
                cm._obstacle_rows, False, limit, np.empty(40, dtype=np.int64)) < 20)
    assert kept > 100 and skipped > 100


@pytest.mark.parametrize('name', ['panda_table', 'ur5_table'])
def test_the_robots_contacts_are_every_pairs_bit_for_bit(name: str) -> None:
    """The robots' meshes and boxes against the mesh table and the box, at the configurations
    of a VE run pushed onto them (contacts from the first updates) and around them: the
    candidates kept below 0 and below the margin are every pair's below it, bit for bit (the
    same coal queries on the same placements)."""
    sc = load_scenario(name)
    assert sc.contacts is not None
    dyn = LinkageDynamics(sc.linkage)
    cm = ContactModel(dyn.model, sc.linkage, sc.contacts)
    shapes = [s for s in sc.contacts.shapes(sc.linkage) if s.kind in ('box', 'mesh')]
    ve = VirtualEnvironment(LinkageDynamics(sc.linkage), sc.q0, sc.dq0, sc.internal_step,
                            coupling=sc.coupling_gains(), contacts=ContactModel(
                                dyn.model, sc.linkage, sc.contacts))
    wrench = np.array(sc.user['wrench'], dtype=float)
    rng = np.random.default_rng(7)
    touching = 0
    for update in range(40):
        for i in range(10):
            ve.push_input(10 * update + i, (10 * update + i) * 1e-3, wrench)
        ve.snapshot(update)
        for q in (ve.q, ve.q + rng.uniform(-0.02, 0.02, sc.linkage.dof)):
            every = _every_pair(dyn.model, cm, shapes, q, exact=True)
            for limit in (0.0, sc.contacts.params.margin):
                assert _kept(cm, q, limit) == [c for c in every if c[2] < limit], (q, limit)
            touching += any(c[2] < 0.0 for c in every)
    assert touching > 20


def test_the_box_bound_skips_what_the_sphere_keeps() -> None:
    """A rod (a 1 m x 2 cm x 2 cm box) lying 50 mm above a plane, parallel to it, beside a
    sphere and a box: its bounding sphere (radius 0.5 m) reaches all three, its box none; the
    pairs are candidates only from a limit above the rod's gap to each (by hand: 40 mm to the
    plane, 40 mm to the sphere's surface, 20 mm to the box)."""
    solid = np.zeros(bounds.SOLID_COLUMNS)
    solid[3] = float(np.sqrt(0.5 ** 2 + 2 * 0.01 ** 2))
    solid[7:16] = np.eye(3).ravel()
    solid[16:19] = (0.5, 0.01, 0.01)
    solid[19] = 1.0
    plane = np.zeros(bounds.OBSTACLE_COLUMNS)
    plane[0], plane[1:4], plane[16] = bounds.PLANE, (0.0, 0.0, 1.0), -0.05
    sphere = np.zeros(bounds.OBSTACLE_COLUMNS)
    sphere[0], sphere[1:4], sphere[16] = bounds.ROUND, (0.3, 0.0, 0.1), 0.05
    box = np.zeros(bounds.OBSTACLE_COLUMNS)
    box[0], box[1:4], box[4:13], box[13:16] = (bounds.BOX, (-0.3, 0.13, 0.0),
                                              np.eye(3).ravel(), (0.1, 0.1, 0.1))
    placement = np.eye(4)[None].copy()
    out = np.empty(3, dtype=np.int64)

    def near(limit: float) -> list[int]:
        n = bounds.near_pairs(placement, np.zeros(1, dtype=np.int64), solid[None],
                              np.array([plane, sphere, box]), False, limit, out)
        return out[:n].tolist()

    assert near(0.0) == []
    assert near(0.0199) == []
    assert near(0.0201) == [2]
    assert near(0.0401) == [0, 1, 2]
    solid[19] = 0.0             # the sphere alone (a planar polygon's bound)
    assert near(0.0) == [0, 1, 2]


def test_a_coal_pair_answers_each_query_afresh() -> None:
    """One pair's queries do not depend on its earlier ones (the placement and the result are
    reused): a gap after a penetrating one and after a distant one equals a new pair's."""
    ob = obstacles_from_config([{'type': 'box', 'center': [0.0, 0.0, 0.0],
                                 'half_extents': [0.05, 0.05, 0.05]}], 'test',
                               TaskSpace.SPATIAL)[0]
    rot = np.array(pin.rpy.rpyToMatrix(0.2, -0.1, 0.3))
    poses = [np.array([0.0, 0.0, 0.06]), np.array([0.3, 0.1, 0.2]),
             np.array([0.02, 0.07, 0.0]), np.array([0.0, 0.0, 0.3])]
    pair = CoalPair('box', (0.02, 0.03, 0.04), ob)
    for first in poses:
        for then in poses:
            pair.gap(first, rot)
            got = pair.gap(then, rot)
            want = CoalPair('box', (0.02, 0.03, 0.04), ob).gap(then, rot)
            assert got[0] == want[0]
            assert got[1].tolist() == want[1].tolist() and got[2].tolist() == want[2].tolist()
            assert pair.gap_floats(then, rot) == (want[0], want[1].tolist(), want[2].tolist())


def test_no_bound_exceeds_the_signed_distance() -> None:
    """2000 random boxes (half extents 5-100 mm, any rotation, apart, touching, overlapping)
    against a random box, sphere and plane: a pair whose signed distance (coal, by the
    placement; a plane's: the deepest corner by hand) is ``g`` is a candidate at every limit
    above ``g`` (at ``g + 1e-12`` m)."""
    rng = np.random.default_rng(17)
    out = np.empty(3, dtype=np.int64)
    request = distance_request()
    for _ in range(2000):
        rots = [np.array(pin.exp3(rng.normal(size=3))) for _ in range(3)]
        halves = rng.uniform(0.005, 0.1, size=(2, 3))
        centres = rng.uniform(-0.15, 0.15, size=(3, 3))
        solid = np.zeros(bounds.SOLID_COLUMNS)
        solid[0:3], solid[3] = centres[0], float(np.linalg.norm(halves[0]))
        solid[4:7], solid[7:16], solid[16:19], solid[19] = (centres[0], rots[0].ravel(),
                                                            halves[0], 1.0)
        box = np.zeros(bounds.OBSTACLE_COLUMNS)
        box[0], box[1:4], box[4:13], box[13:16] = (bounds.BOX, centres[1], rots[1].ravel(),
                                                  halves[1])
        sphere = np.zeros(bounds.OBSTACLE_COLUMNS)
        sphere[0], sphere[1:4], sphere[16] = bounds.ROUND, centres[2], 0.03
        normal = rots[2][:, 2]
        plane = np.zeros(bounds.OBSTACLE_COLUMNS)
        plane[0], plane[1:4], plane[16] = bounds.PLANE, normal, float(normal @ centres[2])
        pose = coal.Transform3s(rots[0], centres[0])
        gaps = []
        for shape, at in ((coal.Box(*(2.0 * halves[1])), coal.Transform3s(rots[1], centres[1])),
                          (coal.Sphere(0.03), coal.Transform3s(np.eye(3), centres[2]))):
            gaps.append(coal.distance(coal.Box(*(2.0 * halves[0])), pose, shape, at, request,
                                      coal.DistanceResult()))
        corners = centres[0] + (np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1)
                                          for z in (-1, 1)]) * halves[0]) @ rots[0].T
        gaps.append(float(np.min(corners @ normal)) - plane[16])
        for k, (ob, gap) in enumerate(zip((box, sphere, plane), gaps, strict=True)):
            n = bounds.near_pairs(np.eye(4)[None].copy(), np.zeros(1, dtype=np.int64),
                                  solid[None], ob[None], False, gap + 1e-12, out)
            assert n == 1, (k, gap)
