"""Boxes and cylinders on links (a URDF's ``<collision>`` primitives) against the obstacles.

The contacts of eq. 1 need, per link shape and obstacle, candidate contacts ``(gap, point,
normal)``: the signed distance ``gap`` (m, negative: penetration depth), the point on the link's
shape where the obstacle pushes (m, world) and the unit normal from the obstacle towards the
link (world). :mod:`haptic_topology.model.obstacles` does this for capsules; this module does it
for the other URDF primitives, exactly (no shape is replaced by another):

* **box**: centre ``c`` (m, world), rotation ``R`` (world_R_box), half extents ``h`` (m).
* **cylinder**: centre ``c``, rotation ``R`` (axis along ``R[:, 2]``), ``radius`` r and half
  length ``h`` (m; the URDF's ``length`` is ``2 h``).
* **polygon** (planar tasks): the projection of a box, or of a cylinder whose axis lies in the
  plane, on the xy plane, a convex polygon (k x 3 world vertices, z = 0, counter-clockwise). The
  planar obstacles extend along z, so the distance between a link's solid and an obstacle is
  the distance between their projections.

Against a plane or half-plane (the gap is linear in the position of a point of the solid)
the candidates are the points of the solid that can be deepest: a box's 8 vertices (a
polygon's k vertices), a cylinder's 2 rim points deepest along the plane's normal (one per end
cap; a cap parallel to the plane gives its centre). A box lying on a table is held at its 4
lower corners, as a capsule lying flat is held at both ends. Against a sphere the candidate is
the point of the solid closest to the centre; against a box or mesh obstacle (spatial) it is
the witness point of the signed distance between the two convex solids. Both are computed by
coal (GJK/EPA, ``meshes.COAL_TOLERANCE``), but for a cylinder and a sphere; against a segment
obstacle (planar, ``radius`` ρ) the candidate is the signed distance of the polygon and the
segment (closest features when apart, the separating-axis minimum when they overlap) less ρ.

**Kept here, because coal's answer is not the penalty contact's:**

* a box's corners and a cylinder's rim points against a plane (:func:`box_vertices`,
  :func:`cylinder_rims`): coal gives one witness point, so a box lying on a table would be
  held at one corner, not at its four lower corners (``box_table``);
* a cylinder against a sphere (:func:`cylinder_sdf`): once the sphere's centre is inside the
  cylinder coal's depth is not their signed distance (on the axis: -0.021 m with a zero normal
  where -0.006 m is right; off by up to 32 mm in 20-27 % of random such poses), while the
  sphere's signed distance to a convex solid is the solid's at its centre less its radius,
  closed form here;
* polygons (planar tasks: :func:`convex_hull_xy`, :func:`rectangle_of_cylinder`,
  :func:`polygon_segment`): a polygon in the plane has no volume, so coal can build no convex
  hull of it (qhull needs a volume) and EPA gives no depth for it.

Each ``gap`` is the signed distance of the two shapes (or of a point of the solid to a plane),
so ``d gap / dt = n^T (v_p - 0)`` for the link's velocity ``v_p`` at ``point`` (the envelope
theorem: the witness point may move along the surface, the distance's rate is the normal
velocity of the point attached to the link) and the penalty force ``f_n n`` at ``point`` is
passive (``test_core_contacts_solids``). Units SI, world frame.
"""

from __future__ import annotations

import math
from typing import Any

import coal
import numpy as np

from haptic_topology.model.meshes import MeshGeometry, distance_request
from haptic_topology.model.obstacles import EPS, Obstacle, ObstacleKind, coal_geometry

#: (gap m, point (3,) m world, normal (3,) unit world from the obstacle towards the link)
SolidGap = tuple[float, np.ndarray, np.ndarray]

_PLANES = (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE)
#: The 8 corner signs of a box, in a fixed order (the candidates' order).
_CORNERS = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)
                     for sz in (-1.0, 1.0)])


def box_vertices(centre: np.ndarray, rotation: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The 8 corners (8 x 3, m, world) of the box ``(centre, rotation, half)``."""
    return centre + (_CORNERS * half) @ rotation.T


def rectangle_of_cylinder(centre: np.ndarray, rotation: np.ndarray, radius: float,
                          half_length: float) -> np.ndarray:
    """The projection (4 x 3, z = 0, counter-clockwise) on the xy plane of a cylinder whose
    axis ``rotation[:, 2]`` lies in that plane: its axis is a side of length ``2 half_length``,
    its end discs project to sides of length ``2 radius``."""
    axis = rotation[:, 2].copy()
    axis[2] = 0.0
    axis /= float(np.linalg.norm(axis))
    side = np.array([-axis[1], axis[0], 0.0])
    c = np.array([centre[0], centre[1], 0.0])
    return np.array([c - half_length * axis - radius * side,
                     c + half_length * axis - radius * side,
                     c + half_length * axis + radius * side,
                     c - half_length * axis + radius * side])


def convex_hull_xy(points: np.ndarray) -> np.ndarray:
    """Convex hull (k x 3, z = 0, counter-clockwise, no repeated or collinear points) of the
    projections of ``points`` (n x 3) on the xy plane (Andrew's monotone chain)."""
    pts = sorted({(round(float(x), 15), round(float(y), 15)) for x, y in points[:, :2]})
    if len(pts) < 3:
        raise ValueError('convex_hull_xy: the projection has no area')

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    upper: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= EPS * EPS:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= EPS * EPS:
            upper.pop()
        upper.append(p)
    hull = lower[:-1] + upper[:-1]
    return np.array([[x, y, 0.0] for x, y in hull])


def cylinder_sdf(point: np.ndarray, centre: np.ndarray, rotation: np.ndarray, radius: float,
                 half_length: float) -> tuple[float, np.ndarray]:
    """Signed distance (m) from ``point`` to the cylinder and its gradient (unit, world).

    In the cylinder's frame, ``d_r = rho - r`` (``rho``: distance from the axis) and
    ``d_z = |z| - h``: outside, the distance to the nearest of side, cap and rim; inside,
    ``max(d_r, d_z)`` and the normal of that surface. A point on the axis, nearer the side
    than the caps, takes the frame's x direction (any radial direction is a gradient there).
    """
    x, y, z = (rotation.T @ (point - centre)).tolist()
    rho = math.hypot(x, y)
    d_r, d_z = rho - radius, abs(z) - half_length
    sz = -1.0 if z < 0.0 else 1.0
    ux, uy = (x / rho, y / rho) if rho > EPS else (1.0, 0.0)
    if d_r > 0.0 and d_z > 0.0:
        dist = math.hypot(d_r, d_z)
        g = (d_r * ux / dist, d_r * uy / dist, d_z * sz / dist)
        sdf = dist
    elif d_r >= d_z:
        sdf, g = d_r, (ux, uy, 0.0)
    else:
        sdf, g = d_z, (0.0, 0.0, sz)
    return sdf, rotation @ np.array(g)


def cylinder_rims(centre: np.ndarray, rotation: np.ndarray, radius: float, half_length: float,
                  normal: np.ndarray) -> np.ndarray:
    """The two points (2 x 3, m, world) of the cylinder's rims deepest along ``-normal``
    (a plane's outward normal): ``c -+ h a - r u / |u|`` with ``u`` the part of ``normal``
    perpendicular to the axis ``a``; a cap parallel to the plane gives its centre."""
    ax, ay, az = rotation[:, 2].tolist()
    nx, ny, nz = normal.tolist()
    cx, cy, cz = centre.tolist()
    along = nx * ax + ny * ay + nz * az
    ux, uy, uz = nx - along * ax, ny - along * ay, nz - along * az
    norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    scale = -radius / norm if norm > 1e-12 else 0.0
    ix, iy, iz = scale * ux, scale * uy, scale * uz
    hx, hy, hz = half_length * ax, half_length * ay, half_length * az
    return np.array([[cx - hx + ix, cy - hy + iy, cz - hz + iz],
                     [cx + hx + ix, cy + hy + iy, cz + hz + iz]])


def _closest_xy(px: float, py: float, ax: float, ay: float, bx: float, by: float
                ) -> tuple[float, float]:
    """The point of the segment ``a -> b`` (xy) closest to ``p``."""
    dx, dy = bx - ax, by - ay
    dd = dx * dx + dy * dy
    if dd <= EPS * EPS:
        return ax, ay
    t = ((px - ax) * dx + (py - ay) * dy) / dd
    t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
    return ax + t * dx, ay + t * dy


def polygon_segment_xy(vs: list[tuple[float, float]], ax: float, ay: float, bx: float,
                       by: float) -> tuple[float, float, float, float, float]:
    """:func:`polygon_segment` in plain floats: vertices ``vs`` (xy, counter-clockwise), the
    segment ``(ax, ay) -> (bx, by)``; returns ``(sd, px, py, nx, ny)``. Runs at every RK4
    stage of the VE, so scalar arithmetic (a polygon has at most 6 vertices)."""
    k = len(vs)
    best, bux, buy, best_edge = math.inf, 0.0, 0.0, -1
    for e in range(k):      # axes -m_e: the polygon pushed across its edge e
        x0, y0 = vs[e]
        x1, y1 = vs[(e + 1) % k]
        ex, ey = x1 - x0, y1 - y0
        length = math.sqrt(ex * ex + ey * ey)
        ux, uy = -ey / length, ex / length
        sa, sb = ax * ux + ay * uy, bx * ux + by * uy
        pen = (sa if sa > sb else sb) - min(x * ux + y * uy for x, y in vs)
        if pen < best:
            best, bux, buy, best_edge = pen, ux, uy, e
    dx, dy = bx - ax, by - ay
    seg = math.sqrt(dx * dx + dy * dy)
    if seg > EPS:           # axes +-m_s: across the segment
        mx, my = -dy / seg, dx / seg
        for ux, uy in ((mx, my), (-mx, -my)):
            pen = ax * ux + ay * uy - min(x * ux + y * uy for x, y in vs)
            if pen < best:
                best, bux, buy, best_edge = pen, ux, uy, -1
    if best > 0.0:          # overlapping: the smallest separating translation
        if best_edge >= 0:
            da, db = ax * bux + ay * buy, bx * bux + by * buy
            if abs(da - db) <= EPS:
                qx, qy = 0.5 * (ax + bx), 0.5 * (ay + by)
            else:
                qx, qy = (ax, ay) if da > db else (bx, by)
            x0, y0 = vs[best_edge]
            x1, y1 = vs[(best_edge + 1) % k]
            px, py = _closest_xy(qx, qy, x0, y0, x1, y1)
        else:
            px, py = min(vs, key=lambda v: v[0] * bux + v[1] * buy)
        return -best, px, py, bux, buy
    dist, px, py, nx, ny = math.inf, 0.0, 0.0, 0.0, 0.0
    for x, y in vs:
        sx, sy = _closest_xy(x, y, ax, ay, bx, by)
        r = math.hypot(x - sx, y - sy)
        if r < dist:
            dist, px, py, nx, ny = r, x, y, x - sx, y - sy
    for qx, qy in (((ax, ay),) if seg <= EPS else ((ax, ay), (bx, by))):
        for e in range(k):
            x0, y0 = vs[e]
            x1, y1 = vs[(e + 1) % k]
            cx, cy = _closest_xy(qx, qy, x0, y0, x1, y1)
            r = math.hypot(cx - qx, cy - qy)
            if r < dist:
                dist, px, py, nx, ny = r, cx, cy, cx - qx, cy - qy
    if dist <= EPS:         # touching: the separating axis found above
        return 0.0, px, py, bux, buy
    return dist, px, py, nx / dist, ny / dist


def polygon_segment(vertices: np.ndarray, a: np.ndarray, b: np.ndarray
                    ) -> tuple[float, np.ndarray, np.ndarray]:
    """Signed distance (m) of a convex polygon (k x 3, z = 0, counter-clockwise) and the
    segment ``a -> b`` (``a == b``: a point), the witness point on the polygon (world) and the
    unit normal from the segment towards the polygon.

    Apart: the nearest of every vertex to the segment and each segment end to the polygon (in
    the plane the closest pair of two disjoint convex polygons has a vertex on one side).
    Overlapping: the minimum over the separating axes (the polygon's edge normals and the
    segment's normal) of the translation that separates them, as a negative distance; on a
    polygon edge's axis the witness is the segment's deepest end projected on that edge, on the
    segment's axis the polygon's deepest vertex."""
    sd, px, py, nx, ny = polygon_segment_xy([(float(x), float(y)) for x, y, _ in vertices],
                                            float(a[0]), float(a[1]), float(b[0]),
                                            float(b[1]))
    return sd, np.array([px, py, 0.0]), np.array([nx, ny, 0.0])


class CoalPair:
    """A link solid (box, cylinder, or a mesh's convex hull: ``mesh``) against a spatial
    obstacle: coal's signed distance with nearest points (GJK when apart, EPA when
    overlapping), tolerance ``meshes.COAL_TOLERANCE``, no cached guess (every query is independent
    of the previous one, so runs repeat exactly). The solid's placement and the result are
    coal objects made once and overwritten by each query (the result cleared first: coal
    keeps a smaller distance already in it)."""

    def __init__(self, kind: str, size: tuple[float, ...], obstacle: Obstacle,
                 mesh: MeshGeometry | None = None) -> None:
        self.link_geometry: Any = (mesh.convex if mesh is not None
                                   else coal.Box(*(2.0 * np.array(size))) if kind == 'box'
                                   else coal.Cylinder(size[0], 2.0 * size[1]))
        self.obstacle_geometry, self.obstacle_pose = coal_geometry(obstacle)
        self.request = distance_request()
        self._pose = coal.Transform3s()
        self._result = coal.DistanceResult()

    def gap(self, centre: np.ndarray, rotation: np.ndarray) -> SolidGap:
        """``(gap, point, normal)`` of the solid placed at ``(centre, rotation)``."""
        dist, res = self._query(centre, rotation)
        # coal's normal points from the first shape (the link) to the second
        return dist, np.array(res.getNearestPoint1()), -np.array(res.normal)

    def gap_floats(self, centre: np.ndarray, rotation: np.ndarray
                   ) -> tuple[float, list[float], list[float]]:
        """:meth:`gap` in Python floats (the same numbers): the VE's path, at every RK4
        stage."""
        dist, res = self._query(centre, rotation)
        nx, ny, nz = res.normal.tolist()
        return dist, res.getNearestPoint1().tolist(), [-nx, -ny, -nz]

    def _query(self, centre: np.ndarray, rotation: np.ndarray) -> tuple[float, Any]:
        """coal's signed distance (m) and its result (read before the next query)."""
        pose, res = self._pose, self._result
        pose.setRotation(rotation)
        pose.setTranslation(centre)
        res.clear()
        return float(coal.distance(self.link_geometry, pose, self.obstacle_geometry,
                                   self.obstacle_pose, self.request, res)), res


def solid_gaps(obstacle: Obstacle, kind: str, centre: np.ndarray, rotation: np.ndarray,
               size: tuple[float, ...], polygon: np.ndarray | None = None,
               pair: CoalPair | None = None) -> list[SolidGap]:
    """Candidate contacts of one link solid and ``obstacle`` (see module doc).

    ``kind``: ``box`` (``size``: half extents), ``cylinder`` (``size``: radius, half length) or
    ``polygon`` (``polygon``: its world vertices, planar tasks); ``centre`` and ``rotation``
    place a box or cylinder (world). ``pair``: a :class:`CoalPair` for this solid and box
    obstacle (made here if None)."""
    ok = obstacle.kind
    if kind == 'polygon':
        assert polygon is not None
        if ok is ObstacleKind.HALF_PLANE:
            n = obstacle.normal
            return [(float(n @ (v - obstacle.point)), v.copy(), n.copy()) for v in polygon]
        if ok is ObstacleKind.DISC:
            sd, point, normal = polygon_segment(polygon, obstacle.point, obstacle.point)
        elif ok is ObstacleKind.SEGMENT:
            sd, point, normal = polygon_segment(polygon, obstacle.point, obstacle.end)
        else:
            raise ValueError(f'solid_gaps: a polygon meets planar obstacles, not {ok.value}')
        return [(sd - obstacle.radius, point, normal)]
    if ok is ObstacleKind.PLANE:
        n = obstacle.normal
        points = (box_vertices(centre, rotation, np.array(size)) if kind == 'box'
                  else cylinder_rims(centre, rotation, size[0], size[1], n))
        return [(float(n @ (p - obstacle.point)), p, n.copy()) for p in points]
    if ok is ObstacleKind.SPHERE and kind == 'cylinder':
        sdf, grad = cylinder_sdf(obstacle.point, centre, rotation, size[0], size[1])
        return [(sdf - obstacle.radius, obstacle.point - sdf * grad, -grad)]
    if ok in (ObstacleKind.SPHERE, ObstacleKind.BOX, ObstacleKind.MESH):
        return [(pair or CoalPair(kind, size, obstacle)).gap(centre, rotation)]
    raise ValueError(f'solid_gaps: a {kind} meets spatial obstacles, not {ok.value}')

