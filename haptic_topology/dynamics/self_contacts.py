"""Self-collisions: penalty contacts between pairs of a linkage's own links (eq. 1's
``sum J_i^T F_i``), on with ``contacts.self_collisions: true`` (spatial tasks).

**Pairs.** Every pair of link contact shapes
(:meth:`~haptic_topology.dynamics.contacts.ContactSettings.shapes`: capsules, spheres, boxes,
cylinders, mesh hulls) on two different links is checked, except

* the shapes of adjacent links, a link and its parent (and two links joined by a loop
  closure, or through links of zero length: joints at one point, as in a wrist): they meet
  at their joint, where their shapes overlap by construction;
* the pairs the linkage's SRDF disables (``Linkage.disabled_collisions``, URDF link names). A
  shape of a URDF ``<collision>`` counts as the URDF link it is declared on, also when that
  link is merged into a chain link by a fixed joint or carried by a locked side branch (the
  Panda's ``panda_hand`` on ``panda_link7``: the SRDF's pairs of ``panda_hand`` apply to the
  hand's mesh, those of ``panda_link7`` to the link's own); a link's default capsule (or its
  ``contacts.links.<name>.radius``) counts as the chain link's name.

A YAML linkage (no SRDF) checks every pair of non-adjacent links. Two shapes of one link are
one rigid body and never meet; the root link's shapes are no contact shapes (static, see
:mod:`~haptic_topology.model.urdf_import`), so no link is checked against the base.

**Geometry.** Per pair, coal's signed distance of the two shapes placed by the link
placements (GJK apart, EPA overlapping, tolerance ``meshes.COAL_TOLERANCE``; a capsule as
coal's capsule, :func:`~haptic_topology.model.meshes.capsule_shape`, a box, a cylinder, a mesh
as its convex hull): the gap ``g`` (m, negative: penetration), the witness points ``p_a`` on
link a's shape and ``p_b`` on link b's (m, world) and the unit normal ``n`` from b towards a.
A pair is skipped without a coal query where a lower bound of its gap is at least the query's
limit: its shapes' bounding spheres, or their oriented boxes (the separating-axis test), in one
compiled call (:mod:`~haptic_topology.dynamics.contact_bounds`; why this keeps every pair below
the limit: :meth:`SelfContacts.hits_at`).

**Force** (the penalty model of :mod:`haptic_topology.dynamics.contacts` applied to the pair):
``F = f_n n + f_t`` with ``v = v_a(p_a) - v_b(p_b)`` (m/s, world) the relative velocity of the
witness points, ``F`` on link a at ``p_a`` and ``-F`` on link b at ``p_b``; the torques
``J_a(p_a)^T F - J_b(p_b)^T F`` (``J(p)``: the 3 x d linear Jacobian of the link point ``p``)
and the contacts' power ``F^T (v_a - v_b)`` (W). The gap's rate is
``dg/dt = n^T (v_a(p_a) - v_b(p_b))`` (the envelope theorem: the witness points may slide on
the surfaces, the distance changes with the normal velocity of the points attached to the
links), so with ``U = sum k delta^2 / 2`` (in ``ContactModel.potential``) the power is
``-dU/dt - b gdot^2 + f_t^T v_t`` as against an obstacle: passive, and the VE's energy check
(``contact_energy_balance``) covers the self-contacts.

**LMI** (eq. 17). A self-contact is a candidate of ``ContactModel.detect`` (obstacle index -1,
link a, point ``p_a``, normal ``n``) with the relative Jacobian ``J = J_a(p_a) - J_b(p_b)``.
:class:`~haptic_topology.dynamics.contacts.LocalContacts` holds for it as it is: its
``g + n^T J (q - q_u)`` is the gap's first-order expansion (the gradient above), ``J qdot`` is
the relative velocity the force law takes, and ``J^T F = J_a^T F - J_b^T F`` are the torques
on both links, so at the update the LMI's contact torques equal the VE's.

**Limits.** A pair pushed deeper than its shapes' thickness (two capsules' axes crossing) is
pushed on through, not back: the normal follows the side the other shape is on, as for any
penalty contact; the stiffness must stop the links before. Each pair has one witness pair: two
long shapes lying along each other are held at one point. A non-convex mesh is its hull
(:mod:`haptic_topology.model.meshes`). Units SI, world frame.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import coal
import numpy as np
import pinocchio as pin

from haptic_topology.dynamics.contacts import (
    ContactParams,
    LinkCapsule,
    LinkSolid,
    _bounding_sphere,
    _force,
    _solid_row,
    point_jacobian,
)
from haptic_topology.model.linkage import Linkage, _placement_offset
from haptic_topology.model.meshes import capsule_shape, distance_request
from haptic_topology.model.solids import box_vertices

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED

#: One self-contact: ``(link_a, link_b, p_a, p_b, gap, normal)``, links by index, points (3,)
#: m world, gap m, normal (3,) unit from b towards a.
SelfHit = tuple[int, int, np.ndarray, np.ndarray, float, np.ndarray]


def self_pairs(linkage: Linkage, shapes: Sequence[LinkCapsule | LinkSolid]
               ) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, ``i < j``, of ``shapes`` (indices) checked against each other:
    on different links, not adjacent, not disabled by the SRDF (see the module doc)."""
    names = linkage.link_names
    adjacent = {(i, i + 1) for i in range(linkage.dof - 1)}
    # through links of zero length: joints i + 1 ... j at one point
    for i in range(linkage.dof):
        j = i + 1
        while j + 1 < linkage.dof and _placement_offset(linkage.links, j + 1) == 0.0:
            j += 1
            adjacent.add((i, j))
    for loop in linkage.loops:
        if loop.to in names:
            ends = sorted((names.index(loop.link), names.index(loop.to)))
            adjacent.add((ends[0], ends[1]))
    disabled = set(linkage.disabled_collisions)
    urdf = [s.urdf_link or names[s.link] for s in shapes]
    out = []
    for i, j in itertools.combinations(range(len(shapes)), 2):
        la, lb = sorted((shapes[i].link, shapes[j].link))
        if la == lb or (la, lb) in adjacent:
            continue
        if (min(urdf[i], urdf[j]), max(urdf[i], urdf[j])) in disabled:
            continue
        out.append((i, j))
    return out


def _along_z(d: np.ndarray) -> np.ndarray:
    """A rotation (3 x 3) whose z column is the unit vector ``d``."""
    x = np.cross(d, np.eye(3)[int(np.argmin(np.abs(d)))])
    x /= float(np.linalg.norm(x))
    return np.column_stack((x, np.cross(d, x), d))


def _coal_shape(shape: LinkCapsule | LinkSolid
                ) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, float]:
    """``(geometry, rotation, centre, bound_centre, bound_radius)`` of a link shape for coal:
    its coal geometry placed at ``(centre, rotation)`` in the link's joint frame, and a sphere
    around it (link frame, m)."""
    if isinstance(shape, LinkCapsule):
        axis = shape.b - shape.a
        length = float(np.linalg.norm(axis))
        centre = 0.5 * (shape.a + shape.b)
        rotation = _along_z(axis / length) if length > 1e-12 else np.eye(3)
        return (capsule_shape(shape.radius, length), rotation, centre, centre,
                0.5 * length + shape.radius)
    if shape.mesh is not None:
        geometry: Any = shape.mesh.convex
    elif shape.kind == 'box':
        geometry = coal.Box(*(2.0 * np.array(shape.size)))
    else:
        geometry = coal.Cylinder(shape.size[0], 2.0 * shape.size[1])
    corners = (box_vertices(shape.centre, shape.rotation, np.array(shape.size))
               if shape.kind == 'box' else None)
    bound, radius = _bounding_sphere(shape, corners)
    if shape.mesh is not None:      # the sphere around the hull's box where it is smaller
        around_box = float(np.max(np.linalg.norm(shape.mesh.vertices - shape.mesh.box_centre,
                                                 axis=1)))
        if around_box < radius:
            bound, radius = shape.centre + shape.rotation @ shape.mesh.box_centre, around_box
    return geometry, shape.rotation, shape.centre, bound, radius


def _bound_row(shape: LinkCapsule | LinkSolid,
               made: tuple[Any, np.ndarray, np.ndarray, np.ndarray, float]) -> np.ndarray:
    """The broad phase's row of ``shape`` (:data:`contact_bounds.SOLID_COLUMNS`, link frame):
    the sphere of :func:`_coal_shape` (``made``) and an oriented box around the shape (a
    capsule's: along its axis, half extents ``(r, r, length / 2 + r)``; a solid's as against
    the obstacles: a box, a cylinder's box, the box around a mesh's hull)."""
    _, rotation, centre, bound, radius = made
    if isinstance(shape, LinkCapsule):
        from haptic_topology.dynamics.contact_bounds import SOLID_COLUMNS
        r = shape.radius
        row = np.zeros(SOLID_COLUMNS)
        row[4:7], row[7:16], row[19] = centre, rotation.ravel(), 1.0
        row[16:19] = (r, r, radius)         # radius: half the length plus r
    else:
        row = _solid_row(shape, None)       # its box; the sphere is set below
    row[0:3], row[3] = bound, radius
    return row


class SelfContacts:
    """The self-collision pairs of a linkage's contact ``shapes`` and their contacts (see the
    module doc). Works on the world placements of the ``joints`` (each a homogeneous 4 x 4,
    stacked in that order, forward kinematics current): the
    :class:`~haptic_topology.dynamics.contacts.ContactModel`'s, which stacks them once per
    call for its solids and these pairs (default: the joints carrying the pairs' shapes)."""

    def __init__(self, linkage: Linkage, shapes: Sequence[LinkCapsule | LinkSolid],
                 joints: Sequence[int] | None = None) -> None:
        if linkage.task.planar:
            raise ValueError('SelfContacts: self-collisions are for spatial tasks')
        pairs = self_pairs(linkage, shapes)
        used = sorted({k for pair in pairs for k in pair})
        slot = {k: n for n, k in enumerate(used)}
        #: The pairs, by their shapes' places in ``used``.
        self.pairs = [(slot[i], slot[j]) for i, j in pairs]
        self._a = np.array([a for a, _ in self.pairs], dtype=np.int64)
        self._b = np.array([b for _, b in self.pairs], dtype=np.int64)
        self._links = [shapes[k].link for k in used]
        #: The joints whose placements the ``placements`` arguments stack, in order.
        self.joints = (list(joints) if joints is not None
                       else sorted({link + 1 for link in self._links}))
        self._joint_slot = np.array([self.joints.index(link + 1) for link in self._links],
                                    dtype=np.int64)
        self._slot = self._joint_slot.tolist()
        made = [_coal_shape(shapes[k]) for k in used]
        self._geometry = [m[0] for m in made]
        self._rotation = [m[1] for m in made]
        self._centre = [m[2] for m in made]
        # the broad phase's rows (contact_bounds: sphere and box, link frame), its output,
        # and each shape's coal placement, and the result, made once
        from haptic_topology.dynamics import contact_bounds as bounds
        self._near_pairs = bounds.near_self_pairs
        self._rows = np.array([_bound_row(shapes[k], m) for k, m in zip(used, made, strict=True)
                               ]).reshape(-1, bounds.SOLID_COLUMNS)
        self._near = np.empty(len(self.pairs), dtype=np.int64)
        self._poses = [coal.Transform3s() for _ in used]
        self._result = coal.DistanceResult()
        self._request = distance_request()

    def __len__(self) -> int:
        return len(self.pairs)

    def hits(self, oMi: Any, limit: float) -> list[SelfHit]:
        """:meth:`hits_at` the placements ``oMi`` (a Pinocchio ``Data``'s, forward kinematics
        current)."""
        return self.hits_at(np.array([oMi[j].homogeneous for j in self.joints]), limit)

    def hits_at(self, placements: np.ndarray, limit: float) -> list[SelfHit]:
        """The pairs with ``gap < limit`` (m, ``limit >= 0``) at ``placements`` (the
        ``joints``' homogeneous world placements, m x 4 x 4), pair by pair in a fixed order.

        A pair is queried (coal) only where both lower bounds of its gap are below
        ``limit + SLACK`` (:func:`~haptic_topology.dynamics.contact_bounds.near_self_pairs`,
        one compiled call): the distance of the centres of two spheres around the shapes less
        both radii, and the largest separation of two oriented boxes around them over the
        separating-axis test's 15 axes (a capsule's box: ``L + 2 r`` along its axis of length
        ``L``, ``2 r`` across; a mesh's: the box around its hull). Each is at most the signed
        distance of the two shapes: a convex set's signed distance to a point is 1-Lipschitz,
        the separation of two convex sets along any unit axis is at most their signed
        distance, and a shape's signed distance to another only grows when either shrinks
        into its box. A skipped pair is therefore apart by at least ``limit + SLACK`` less
        the bounds' rounding (1e-15 m at a robot's sizes), and coal's gap for it is not
        below ``limit``: GJK's distance is the norm of a point of
        the Minkowski difference, at least the true distance, and only within its tolerance
        (1e-10 m, below ``SLACK``) of touching can EPA report a penetration. So the hits are
        those of every pair queried one by one, bit for bit (``test_core_self_contacts``):
        the same coal query on the same placements, each shape's placement and the result
        being coal objects made once and overwritten (the result cleared first)."""
        if not self.pairs:
            return []
        count = self._near_pairs(placements, self._joint_slot, self._rows, self._a, self._b,
                                 limit, self._near)
        if not count:
            return []
        out: list[SelfHit] = []
        placed: set[int] = set()
        poses, res = self._poses, self._result
        for n in self._near[:count].tolist():
            a, b = self.pairs[n]
            for k in (a, b):
                if k not in placed:
                    frame = placements[self._slot[k]]
                    rot, origin = frame[:3, :3], frame[:3, 3]
                    poses[k].setRotation(rot @ self._rotation[k])
                    poses[k].setTranslation(rot @ self._centre[k] + origin)
                    placed.add(k)
            res.clear()
            gap = float(coal.distance(self._geometry[a], poses[a], self._geometry[b],
                                      poses[b], self._request, res))
            if gap < limit:
                # coal's normal points from the first shape (a) to the second (b)
                out.append((self._links[a], self._links[b], np.array(res.getNearestPoint1()),
                            np.array(res.getNearestPoint2()), gap, -np.array(res.normal)))
        return out

    def gaps(self, placements: np.ndarray) -> list[float]:
        """The gaps (m) of the penetrating pairs at ``placements`` (:meth:`hits_at`)."""
        return [hit[4] for hit in self.hits_at(placements, 0.0)]

    def detect(self, model: pin.Model, data: Any, q: np.ndarray, placements: np.ndarray,
               margin: float, jacobians: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                        np.ndarray, np.ndarray]:
        """``(links, points, normals, gaps, jacobians)`` of the pairs with ``gap < margin`` at
        ``q`` (``data``'s forward kinematics at ``q``, ``placements`` its joints'): link a,
        ``p_a``, ``n``, ``g`` and the relative Jacobian ``J_a(p_a) - J_b(p_b)`` (c x 3 x d;
        zeros unless ``jacobians``)."""
        hits = self.hits_at(placements, margin)
        dof = model.nv
        jac = np.zeros((len(hits), 3, dof))
        if jacobians and hits:
            pin.computeJointJacobians(model, data, q)
            for r, (la, lb, pa, pb, _, _) in enumerate(hits):
                jac[r] = (point_jacobian(model, data, la + 1, pa)
                          - point_jacobian(model, data, lb + 1, pb))
        return (np.array([h[0] for h in hits], dtype=int),
                np.array([h[2] for h in hits], dtype=float).reshape(-1, 3),
                np.array([h[5] for h in hits], dtype=float).reshape(-1, 3),
                np.array([h[4] for h in hits], dtype=float), jac)

    def torques(self, model: pin.Model, data: Any, q: np.ndarray, dq: np.ndarray,
                params: ContactParams, placements: np.ndarray
                ) -> tuple[np.ndarray, float] | None:
        """``sum J_a(p_a)^T F - J_b(p_b)^T F`` (d, N m / N) of the penetrating pairs at
        ``(q, dq)`` (``data``'s forward kinematics at ``q``, ``placements`` its joints') and
        their power ``sum F^T (v_a - v_b)`` (W); None when no pair penetrates."""
        hits = self.hits_at(placements, 0.0)
        if not hits:
            return None
        tau = np.zeros(model.nv)
        pin.computeJointJacobians(model, data, q)
        power = 0.0
        for la, lb, pa, pb, gap, n in hits:
            ja = point_jacobian(model, data, la + 1, pa)
            jb = point_jacobian(model, data, lb + 1, pb)
            v = (ja - jb) @ dq
            force = np.array(_force(params, gap, *n.tolist(), *v.tolist()))
            tau += (ja - jb).T @ force
            power += float(force @ v)
        return tau, power
