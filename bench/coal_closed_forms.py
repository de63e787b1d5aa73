"""Coal against the contact geometry's closed forms, pair by pair, over random poses.

For each pair the contacts compute by a closed form (:mod:`haptic_topology.model.obstacles`,
:mod:`haptic_topology.model.solids`): the largest difference of the gap (m), of the normal
(where ``|gap| > 1 um``) and of the contact point (m) between the closed form and coal's
signed distance of the same two shapes (``meshes.COAL_TOLERANCE``), over ``--poses`` random
poses (10-100 mm shapes, apart and overlapping), split where they differ; and the cost of one
query each way (``time.thread_time_ns``, p50/p99, coal's shapes made once as the contacts
make them). Planes: the closed form's deepest candidate against coal's one witness point.
Run: ``.venv/bin/python bench/coal_closed_forms.py [--poses N]``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import coal
import numpy as np

from haptic_topology.model.meshes import capsule_convex_gap, capsule_shape
from haptic_topology.model.obstacles import Obstacle, ObstacleKind, capsule_gaps
from haptic_topology.model.solids import CoalPair, cylinder_sdf, solid_gaps

K = ObstacleKind
#: (gap m, normal (3,), point (3,) or None)
Answer = tuple[float, np.ndarray, np.ndarray | None]


def _rotation(rng: np.random.Generator) -> np.ndarray:
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _capsule(rng: np.random.Generator, i: int, planar: bool = False
             ) -> tuple[np.ndarray, np.ndarray, float]:
    mask = np.array([1.0, 1.0, 0.0 if planar else 1.0])
    p0 = rng.uniform(-0.1, 0.1, 3) * mask
    p1 = p0 if i % 8 == 0 else rng.uniform(-0.1, 0.1, 3) * mask
    return p0, p1, float(rng.uniform(0.0, 0.02))


def _ours(ob: Obstacle, p0: np.ndarray, p1: np.ndarray, r: float) -> Answer:
    gap, s, n = min(capsule_gaps(ob, p0, p1, r), key=lambda c: c[0])
    return gap, n, p0 + s * (p1 - p0)


def _coal(shape: Any, pose: Any, p0: np.ndarray, p1: np.ndarray, r: float) -> Answer:
    gap, s, n = capsule_convex_gap(shape, pose, p0, p1, r,
                                   capsule_shape(r, float(np.linalg.norm(p1 - p0))))
    return gap, n, p0 + s * (p1 - p0)


def _segment_shape(ob: Obstacle) -> tuple[Any, Any]:
    d = ob.end - ob.point
    length = float(np.linalg.norm(d))
    z = d / length
    x = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    x /= np.linalg.norm(x)
    return (coal.Capsule(ob.radius, length),
            coal.Transform3s(np.column_stack((x, np.cross(z, x), z)), 0.5 * (ob.point + ob.end)))


Case = tuple[str, Callable[[int], tuple[Any, ...]], Callable[..., Answer],
             Callable[..., Answer], Callable[..., str]]


def cases(rng: np.random.Generator) -> list[Case]:
    def round_(planar: bool) -> Callable[[int], tuple[Any, ...]]:
        def make(i: int) -> tuple[Any, ...]:
            c = rng.uniform(-0.05, 0.05, 3) * (np.array([1.0, 1.0, 0.0]) if planar else 1.0)
            ob = Obstacle(K.DISC if planar else K.SPHERE, 'o', c,
                          radius=float(rng.uniform(0.002, 0.05)))
            return (ob, *_capsule(rng, i, planar))
        return make

    def sphere_coal(ob: Obstacle, *cap: Any) -> Answer:
        return _coal(coal.Sphere(ob.radius), coal.Transform3s(np.eye(3), ob.point), *cap)

    def segment(i: int) -> tuple[Any, ...]:
        a, b = (rng.uniform(-0.1, 0.1, 3) * [1.0, 1.0, 0.0] for _ in range(2))
        rho = float(rng.choice([0.0, rng.uniform(0.0, 0.02)]))
        return (Obstacle(K.SEGMENT, 'o', a, end=b, radius=rho), *_capsule(rng, i, True))

    def plane(i: int) -> tuple[Any, ...]:
        n = rng.normal(size=3)
        return (Obstacle(K.PLANE, 'o', rng.uniform(-0.05, 0.05, 3), normal=n / np.linalg.norm(n)),
                *_capsule(rng, i))

    def solid(kind: str, ob_kind: ObstacleKind) -> Callable[[int], tuple[Any, ...]]:
        def make(i: int) -> tuple[Any, ...]:
            size = (tuple(rng.uniform(0.005, 0.08, 3).tolist()) if kind == 'box' else
                    (float(rng.uniform(0.005, 0.05)), float(rng.uniform(0.005, 0.08))))
            if ob_kind is K.PLANE:
                n = rng.normal(size=3)
                ob = Obstacle(K.PLANE, 'o', rng.uniform(-0.05, 0.05, 3),
                              normal=n / np.linalg.norm(n))
            else:
                ob = Obstacle(K.SPHERE, 'o', rng.uniform(-0.08, 0.08, 3),
                              radius=float(rng.uniform(0.002, 0.05)))
            return ob, kind, rng.uniform(-0.02, 0.02, 3), _rotation(rng), size
        return make

    def solid_ours(ob: Obstacle, kind: str, c: Any, rot: Any, size: Any) -> Answer:
        gap, p, n = min(solid_gaps(ob, kind, c, rot, size), key=lambda x: x[0])
        return gap, n, p

    def solid_coal(ob: Obstacle, kind: str, c: Any, rot: Any, size: Any) -> Answer:
        gap, p, n = CoalPair(kind, size, ob).gap(c, rot)
        return gap, n, p

    def round_where(ob: Obstacle, p0: Any, p1: Any, r: float) -> str:
        d = p1 - p0
        s = 0.0 if d @ d == 0.0 else min(max(float((ob.point - p0) @ d / (d @ d)), 0.0), 1.0)
        return 'centre on the axis' if np.linalg.norm(p0 + s * d - ob.point) < 1e-12 else 'all'

    def segment_where(ob: Obstacle, p0: Any, p1: Any, r: float) -> str:
        return 'axes crossing' if _ours(ob, p0, p1, 0.0)[0] <= -ob.radius + 1e-12 else \
            'axes apart'

    def cylinder_where(ob: Obstacle, kind: str, c: Any, rot: Any, size: Any) -> str:
        inside = cylinder_sdf(ob.point, c, rot, size[0], size[1])[0] < 0.0
        return 'centre inside the cylinder' if inside else 'centre outside'

    def everywhere(*_: Any) -> str:
        return 'all'

    return [
        ('capsule-sphere', round_(False), _ours, sphere_coal, round_where),
        ('capsule-disc', round_(True), _ours, sphere_coal, round_where),
        ('capsule-segment', segment, _ours, lambda ob, *c: _coal(*_segment_shape(ob), *c),
         segment_where),
        ('capsule-plane (deepest end)', plane, _ours,
         lambda ob, *c: _coal(coal.Halfspace(ob.normal, float(ob.normal @ ob.point)),
                              coal.Transform3s(), *c), everywhere),
        ('box-plane (deepest corner)', solid('box', K.PLANE), solid_ours, solid_coal,
         everywhere),
        ('cylinder-plane (deepest rim)', solid('cylinder', K.PLANE), solid_ours, solid_coal,
         everywhere),
        ('cylinder-sphere', solid('cylinder', K.SPHERE), solid_ours, solid_coal,
         cylinder_where),
    ]


def compare(poses: int, seed: int = 58) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    for name, make, ours, theirs, where in cases(rng):
        groups: dict[str, dict[str, Any]] = {}
        for i in range(poses):
            args = make(i)
            (g1, n1, p1), (g2, n2, p2) = ours(*args), theirs(*args)
            row = groups.setdefault(where(*args), {'pair': name, 'where': where(*args), 'n': 0,
                                                   'overlapping': 0, 'gap_m': 0.0,
                                                   'normal': 0.0, 'point_m': 0.0,
                                                   'differ_1e-9': 0})
            row['n'] += 1
            row['overlapping'] += g1 < 0.0
            row['gap_m'] = max(row['gap_m'], abs(g1 - g2))
            row['differ_1e-9'] += abs(g1 - g2) > 1e-9
            if abs(g1) > 1e-6:
                row['normal'] = max(row['normal'], float(np.max(np.abs(n1 - n2))))
            if 'deepest' not in name and p1 is not None and p2 is not None:
                row['point_m'] = max(row['point_m'], float(np.max(np.abs(p1 - p2))))
        rows += groups.values()
    return rows


def costs(n: int = 3000) -> dict[str, tuple[float, float]]:
    """p50/p99 (us) of one query: the closed forms kept, and coal with its shapes made once."""
    rng = np.random.default_rng(1)
    p0, p1, r = np.array([0.0, 0.0, 0.01]), np.array([0.1, 0.02, 0.0]), 0.005
    sphere = Obstacle(K.SPHERE, 's', np.array([0.05, 0.0, -0.02]), radius=0.02)
    box = Obstacle(K.BOX, 'b', np.array([0.05, 0.0, -0.03]),
                   half_extents=np.array([0.03, 0.02, 0.025]), rotation=_rotation(rng))
    cap = capsule_shape(r, float(np.linalg.norm(p1 - p0)))
    sphere_coal = (coal.Sphere(0.02), coal.Transform3s(np.eye(3), sphere.point))
    centre, rot = np.array([0.05, 0.0, 0.01]), _rotation(rng)
    box_pair = CoalPair('box', (0.02, 0.01, 0.03), sphere)
    cyl_pair = CoalPair('cylinder', (0.01, 0.03), sphere)
    calls: dict[str, Callable[[], Any]] = {
        'capsule-sphere, closed form': lambda: capsule_gaps(sphere, p0, p1, r),
        'capsule-sphere, coal': lambda: capsule_convex_gap(*sphere_coal, p0, p1, r, cap),
        'capsule-box, coal': lambda: capsule_gaps(box, p0, p1, r, cap),
        'box-sphere, coal': lambda: box_pair.gap(centre, rot),
        'cylinder-sphere, closed form': lambda: solid_gaps(sphere, 'cylinder', centre, rot,
                                                           (0.01, 0.03)),
        'cylinder-sphere, coal': lambda: cyl_pair.gap(centre, rot),
    }
    out = {}
    for name, call in calls.items():
        for _ in range(200):
            call()
        samples = []
        for _ in range(n):
            t0 = time.thread_time_ns()
            call()
            samples.append(time.thread_time_ns() - t0)
        a = np.array(samples) / 1e3
        out[name] = (float(np.percentile(a, 50)), float(np.percentile(a, 99)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--poses', type=int, default=2000)
    a = ap.parse_args()
    print(f'{"pair":30s} {"where":28s} {"n":>5s} {"overl.":>6s} {"max dgap [m]":>12s} '
          f'{"max dnormal":>11s} {"max dpoint [m]":>14s} {">1e-9":>6s}')
    for r in compare(a.poses):
        print(f'{r["pair"]:30s} {r["where"]:28s} {r["n"]:5d} {r["overlapping"]:6d} '
              f'{r["gap_m"]:12.2e} {r["normal"]:11.2e} {r["point_m"]:14.2e} '
              f'{r["differ_1e-9"]:6d}')
    print()
    for name, (p50, p99) in costs().items():
        print(f'{name:32s} p50 {p50:6.1f} us  p99 {p99:6.1f} us')


if __name__ == '__main__':
    main()
