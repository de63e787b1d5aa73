"""The contacts' broad phase (compiled): which link solid and obstacle pairs may be within a limit.

:class:`~haptic_topology.dynamics.contacts.ContactModel` queries a link solid (box, cylinder,
mesh hull, planar polygon) against an obstacle only where a lower bound of their gap is below
the query's limit; this module computes those bounds for every pair at once, in one compiled
call per RK4 stage (numba: about 5 us with the joints' placements for the Panda's 16 solids
and 2 obstacles, where the same in numpy arrays takes about 40 us).
Two bounds, both at most the pair's signed distance (apart or overlapping):

* **sphere**: the obstacle's signed distance to the centre of a sphere around the solid, less
  its radius (the signed distance to a convex set is 1-Lipschitz). A box or mesh obstacle
  stands for the box around it. In a planar task the centre is projected on the xy plane (the
  planar obstacles extend along z).
* **box** (spatial tasks): the solid's oriented box (a box itself, a cylinder's box, the box
  around a mesh's hull, in the link frame) against the obstacle: the plane's signed distance
  to the box's deepest corner; the sphere's to the box, less its radius; against a box or the
  box around a mesh, the largest separation of their projections on the 15 axes of the
  separating-axis test (both boxes' faces and the cross products of their edges: the
  separation along any unit axis is at most the signed distance of two convex sets, which is
  the largest separation over all axes).

A pair is a candidate when ``sphere < limit`` and ``box < limit + SLACK``. The second test
drops pairs only where coal's gap (or a box corner's, or the closed forms') is at least
``limit`` anyway: GJK's distance of two shapes apart by ``d`` is the norm of a point of their
Minkowski difference, at least ``d``, and below the GJK tolerance (``meshes.COAL_TOLERANCE``,
1e-10 m) coal runs EPA and may report a touching pair as penetrating; ``SLACK`` covers that
tolerance and the rounding of the bounds (1e-15 m at these sizes). So the contacts found are
those of every pair computed one by one, bit for bit (``test_core_contact_bounds``). One
caveat is coal's: its box support function (coal 3.0) scales boxes by a static set on the
process's first box query, so skipping a query that would have been that first one moves
later box contacts in their last bits, unless the process fixed the static beforehand.

**Self pairs** (:func:`near_self_pairs`, ``contacts.self_collisions``): two shapes of the
linkage's own links (capsules, boxes, cylinders, mesh hulls), each with a sphere and an oriented
box around it (a capsule's along its axis), both placed by their links: the distance of the
spheres' centres less both radii, and the boxes' separating-axis bound, each below
``limit + SLACK``, for the same reasons (the proof:
:meth:`~haptic_topology.dynamics.self_contacts.SelfContacts.hits_at`).

Units SI (m), world frame; rotations act on column vectors.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit

#: Obstacle kinds of the obstacle rows (column 0).
PLANE, ROUND, BOX, SEGMENT = 0, 1, 2, 3
#: Above the GJK tolerance (1e-10 m) and the bounds' rounding: see the module doc.
SLACK = 1e-9
#: Solid rows: sphere centre (link frame) 0:3, radius 3, box centre (link frame) 4:7, box
#: axes (link_R_box, row-major) 7:16, half extents 16:19, 1.0 if it has a box 19.
SOLID_COLUMNS = 20
#: Obstacle rows: kind 0, point 1:4 (plane: its normal; round: centre; box: centre; segment:
#: a), axes (world_R_box, row-major) 4:13, half extents (segment: its end b) 13:16, radius
#: (plane: its offset n.p) 16.
OBSTACLE_COLUMNS = 17
#: Two edges whose cross product's squared length is below this (within 1e-6 rad of
#: parallel) give no axis: the axis's rounding, divided by its length, would exceed SLACK.
_PARALLEL = 1e-12


@njit(float64(float64, float64, float64, float64[:], float64[:, :], float64[:]), cache=True)
def _box_point(px: float, py: float, pz: float, c: np.ndarray, a: np.ndarray,
               h: np.ndarray) -> float:
    """Signed distance (m) of the point ``p`` to the box (centre ``c``, axes the columns of
    ``a``, half extents ``h``)."""
    dx, dy, dz = px - c[0], py - c[1], pz - c[2]
    outside = 0.0
    inside = -math.inf
    for i in range(3):
        q = abs(dx * a[0, i] + dy * a[1, i] + dz * a[2, i]) - h[i]
        if q > 0.0:
            outside += q * q
        if q > inside:
            inside = q
    return math.sqrt(outside) + min(inside, 0.0)


@njit(float64(float64[:], float64[:, :], float64[:], float64[:], float64[:, :], float64[:],
              float64[:, :]), cache=True)
def _separation(c1: np.ndarray, a1: np.ndarray, h1: np.ndarray, c2: np.ndarray,
                a2: np.ndarray, h2: np.ndarray, r: np.ndarray) -> float:
    """The largest separation (m) of two boxes (centre ``c``, axes the columns of ``a``,
    half extents ``h``) over the 15 axes of the separating-axis test: at most their signed
    distance. ``r``: 3 x 3 scratch (``a1^T a2``)."""
    tx, ty, tz = c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2]
    best = -math.inf
    for i in range(3):          # box 1's faces
        for j in range(3):
            r[i, j] = a1[0, i] * a2[0, j] + a1[1, i] * a2[1, j] + a1[2, i] * a2[2, j]
        sep = (abs(tx * a1[0, i] + ty * a1[1, i] + tz * a1[2, i]) - h1[i]
               - h2[0] * abs(r[i, 0]) - h2[1] * abs(r[i, 1]) - h2[2] * abs(r[i, 2]))
        best = max(best, sep)
    for j in range(3):          # box 2's faces
        sep = (abs(tx * a2[0, j] + ty * a2[1, j] + tz * a2[2, j]) - h2[j]
               - h1[0] * abs(r[0, j]) - h1[1] * abs(r[1, j]) - h1[2] * abs(r[2, j]))
        best = max(best, sep)
    for i in range(3):          # edge i of box 1 x edge j of box 2: L = a1_i x a2_j
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        t1 = tx * a1[0, i1] + ty * a1[1, i1] + tz * a1[2, i1]
        t2 = tx * a1[0, i2] + ty * a1[1, i2] + tz * a1[2, i2]
        for j in range(3):
            sine2 = 1.0 - r[i, j] * r[i, j]         # |L|^2
            if sine2 < _PARALLEL:
                continue
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            sep = (abs(t2 * r[i1, j] - t1 * r[i2, j])
                   - h1[i1] * abs(r[i2, j]) - h1[i2] * abs(r[i1, j])
                   - h2[j1] * abs(r[i, j2]) - h2[j2] * abs(r[i, j1])) / math.sqrt(sine2)
            best = max(best, sep)
    return best


@njit(int64(float64[:, :, :], int64[:], float64[:, :], float64[:, :], boolean, float64,
            int64[:]), cache=True)
def near_pairs(placements: np.ndarray, slot: np.ndarray, solids: np.ndarray,
               obstacles: np.ndarray, planar: bool, limit: float, out: np.ndarray) -> int:
    """The pairs (solid ``s``, obstacle ``k``) whose bounds (module doc) are below ``limit``
    (m): their indices ``s * len(obstacles) + k`` in ``out[:count]``, ascending; returns
    ``count``. ``placements``: the homogeneous world placements (4 x 4) of the joints
    carrying solids, ``slot[s]`` solid ``s``'s; ``solids``, ``obstacles``: rows as
    :data:`SOLID_COLUMNS` and :data:`OBSTACLE_COLUMNS` say."""
    n_ob = obstacles.shape[0]
    count = 0
    centre = np.empty(3)
    box_c = np.empty(3)
    box_a = np.empty((3, 3))
    ob_c = np.empty(3)
    ob_a = np.empty((3, 3))
    scratch = np.empty((3, 3))
    for s in range(solids.shape[0]):
        m = placements[slot[s]]
        row = solids[s]
        for i in range(3):
            centre[i] = (m[i, 0] * row[0] + m[i, 1] * row[1] + m[i, 2] * row[2]) + m[i, 3]
        if planar:
            centre[2] = 0.0
        radius = row[3]
        boxed = row[19] > 0.0 and not planar
        if boxed:
            for i in range(3):
                box_c[i] = (m[i, 0] * row[4] + m[i, 1] * row[5] + m[i, 2] * row[6]) + m[i, 3]
                for j in range(3):
                    box_a[i, j] = (m[i, 0] * row[7 + j] + m[i, 1] * row[10 + j]
                                   + m[i, 2] * row[13 + j])
        half = row[16:19]
        for k in range(n_ob):
            o = obstacles[k]
            kind = int(o[0])
            if kind == PLANE:
                bound = (o[1] * centre[0] + o[2] * centre[1] + o[3] * centre[2]) - o[16]
            elif kind == ROUND:
                dx, dy, dz = centre[0] - o[1], centre[1] - o[2], centre[2] - o[3]
                bound = math.sqrt(dx * dx + dy * dy + dz * dz) - o[16]
            elif kind == BOX:
                for i in range(3):
                    ob_c[i] = o[1 + i]
                    for j in range(3):
                        ob_a[i, j] = o[4 + 3 * i + j]
                bound = _box_point(centre[0], centre[1], centre[2], ob_c, ob_a, o[13:16])
            else:
                ex, ey, ez = o[13] - o[1], o[14] - o[2], o[15] - o[3]
                dx, dy, dz = centre[0] - o[1], centre[1] - o[2], centre[2] - o[3]
                t = (dx * ex + dy * ey + dz * ez) / (ex * ex + ey * ey + ez * ez)
                t = min(max(t, 0.0), 1.0)
                dx, dy, dz = dx - t * ex, dy - t * ey, dz - t * ez
                bound = math.sqrt(dx * dx + dy * dy + dz * dz) - o[16]
            if bound - radius >= limit:
                continue
            if boxed:
                if kind == PLANE:
                    bound = (o[1] * box_c[0] + o[2] * box_c[1] + o[3] * box_c[2]) - o[16]
                    for i in range(3):
                        bound -= half[i] * abs(o[1] * box_a[0, i] + o[2] * box_a[1, i]
                                               + o[3] * box_a[2, i])
                elif kind == ROUND:
                    bound = _box_point(o[1], o[2], o[3], box_c, box_a, half) - o[16]
                elif kind == BOX:       # ob_c, ob_a: filled for the sphere bound above
                    bound = _separation(box_c, box_a, half, ob_c, ob_a, o[13:16], scratch)
                if bound - SLACK >= limit:
                    continue
            out[count] = s * n_ob + k
            count += 1
    return count


@njit(int64(float64[:, :, :], int64[:], float64[:, :], int64[:], int64[:], float64, int64[:]),
      cache=True)
def near_self_pairs(placements: np.ndarray, slot: np.ndarray, shapes: np.ndarray,
                    first: np.ndarray, second: np.ndarray, limit: float,
                    out: np.ndarray) -> int:
    """The pairs ``n`` of a linkage's own shapes (``first[n]``, ``second[n]``) whose bounds
    are below ``limit`` (m) with :data:`SLACK`: the distance of their spheres' centres less
    both radii, and (both boxed) the separating-axis bound of their boxes. Their indices in
    ``out[:count]``, ascending; returns ``count``. ``placements``: the homogeneous world
    placements (4 x 4) of the joints carrying the shapes, ``slot[s]`` shape ``s``'s;
    ``shapes``: rows as :data:`SOLID_COLUMNS` says (link frame)."""
    n_shapes = shapes.shape[0]
    centres = np.empty((n_shapes, 3))
    box_c = np.empty((n_shapes, 3))
    box_a = np.empty((n_shapes, 3, 3))
    for s in range(n_shapes):       # every shape's sphere and box, placed once
        m = placements[slot[s]]
        row = shapes[s]
        for i in range(3):
            centres[s, i] = (m[i, 0] * row[0] + m[i, 1] * row[1] + m[i, 2] * row[2]) + m[i, 3]
            box_c[s, i] = (m[i, 0] * row[4] + m[i, 1] * row[5] + m[i, 2] * row[6]) + m[i, 3]
            for j in range(3):
                box_a[s, i, j] = (m[i, 0] * row[7 + j] + m[i, 1] * row[10 + j]
                                  + m[i, 2] * row[13 + j])
    scratch = np.empty((3, 3))
    count = 0
    for n in range(first.shape[0]):
        a, b = first[n], second[n]
        dx = centres[a, 0] - centres[b, 0]
        dy = centres[a, 1] - centres[b, 1]
        dz = centres[a, 2] - centres[b, 2]
        bound = math.sqrt(dx * dx + dy * dy + dz * dz) - (shapes[a, 3] + shapes[b, 3])
        if bound - SLACK >= limit:
            continue
        if shapes[a, 19] > 0.0 and shapes[b, 19] > 0.0:
            bound = _separation(box_c[a], box_a[a], shapes[a, 16:19], box_c[b], box_a[b],
                                shapes[b, 16:19], scratch)
            if bound - SLACK >= limit:
                continue
        out[count] = n
        count += 1
    return count
