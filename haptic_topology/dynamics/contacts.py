"""Contacts between the linkage and static obstacles: the ``sum_i J_i^T F_i`` of eqs. 1, 2, 17.

(One module of ~900 lines on purpose: the contact candidates, gaps, forces and torques of every
shape pair share one set of arrays per step, which the VE and the LMI both run.)

**Geometry.** Each link carries capsules (a sphere is a capsule of zero length); obstacles
are static shapes in the world frame (:mod:`haptic_topology.model.obstacles`). By default a
link is one capsule around its axis, from its joint's origin to the next joint's origin (the
last link: ``length`` along its x axis), radius ``contacts.link_radius`` (m). A link read from a
URDF takes the URDF's ``<collision>`` shapes instead, all modelled exactly: spheres and
capsules (``<capsule radius length>``, axis along the collision frame's z) as capsules, boxes
and cylinders as solids (:mod:`haptic_topology.model.solids`; in a planar task a box, or a
cylinder whose axis lies in the plane, as its projection, a convex polygon, and a cylinder
along z as a disc), meshes as their convex hulls
(:mod:`haptic_topology.model.meshes`: the file found through ``package://``, the ament index,
``ROS_PACKAGE_PATH`` or the URDF's directory, and why the hull is the right shape for a
penalty contact; in a planar task the hull's projection, a convex polygon, as a box's: the
planar obstacles extend along z, so every part of the link meets them where its projection
does, which a section in the plane would miss); a URDF link without ``<collision>`` does
not collide. In a planar task a cylinder tilted out of the plane (its projection has
elliptic ends) cannot be modelled without approximating it, so such a link is refused unless
``contacts.links.<name>`` says what to do: ``radius: r`` (the default capsule along the link,
also for YAML links) or ``collide: false`` (the link does not collide); both also replace a
link's meshes.
A contact candidate is a point ``p_i`` on a capsule's axis with its signed gap ``g_i`` to an
obstacle (m, negative: penetration depth ``delta_i = -g_i``) and the obstacle's normal ``n_i``
(unit, world, from the obstacle towards the link). Against a half-plane or plane the
candidates are the axis ends (the gap is linear along the axis, so a link lying flat is held
at both ends); a joint shared by two default capsules counts once (as the tip of the proximal
link). Against the other shapes each capsule has one candidate, its closest point; where two
links' closest points are both their common joint, that point is held by both (stiffer there,
still passive). In a planar task the capsules are projected onto the xy plane (the planar
obstacles extend along z). A solid's candidates are those of
:func:`~haptic_topology.model.solids.solid_gaps` (a box's corners and a cylinder's deepest rim
points against planes, the
closest or deepest point against the other shapes), each at its own point of the solid; a
mesh's candidate against every obstacle is the witness point of coal's signed distance
between its hull and the obstacle (a plane as a half space, a mesh obstacle as its hull).

**Contact model** (penalty with damping and regularized Coulomb friction), per candidate with
``delta_i > 0``, ``v_i = J_i qdot`` the velocity of the contact point (m/s, world)::

    f_n = max(0, k delta_i - b gdot_i),       gdot_i = n_i^T v_i
    f_t = -mu f_n v_t / sqrt(|v_t|^2 + v_s^2), v_t = v_i - gdot_i n_i
    F_i = (f_n n_i + f_t, 0)                   (a force at p_i, no torque: eq. 1)

``k`` (N/m) ``stiffness``, ``b`` (N s/m) ``damping``, ``mu`` ``friction``, ``v_s`` (m/s)
``slip_velocity``. It is passive: with ``U = sum_i k delta_i^2 / 2`` the contacts' power on the
VT is ``P = sum_i F_i^T v_i = -dU/dt - b gdot^2 + f_t^T v_t`` while ``f_n > 0`` (and
``-dU/dt - k delta gdot`` with ``gdot > 0`` while the max clips it), so
``W(t) + U(t) - U(0) <= 0`` for the work ``W = int P dt``: the VE integrates ``W`` with the
same RK4 stages as ``q`` and reports the largest positive excess as the energy the contact
model injected (integration error only; ``test_core_contacts``).

``J_i`` (3 x d) is the linear velocity Jacobian of the link point ``p_i`` (Pinocchio's joint
Jacobian, world-aligned at the joint, shifted to ``p_i``). Units SI, world frame.

**Self-collisions** (``self_collisions: true``, spatial tasks): the same model between pairs
of the linkage's own links, the SRDF's disabled pairs left out
(:mod:`haptic_topology.dynamics.self_contacts`); their torques, power, elastic energy and
candidates are added to this model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from haptic_topology.errors import ConfigError
from haptic_topology.model.linkage import Linkage
from haptic_topology.model.meshes import MeshGeometry, capsule_shape, load_mesh, resolve_mesh
from haptic_topology.model.obstacles import (
    EPS,
    Obstacle,
    ObstacleKind,
    capsule_gaps,
    obstacles_from_config,
)
from haptic_topology.model.solids import (
    CoalPair,
    box_vertices,
    convex_hull_xy,
    cylinder_rims,
    polygon_segment_xy,
    rectangle_of_cylinder,
    solid_gaps,
)
from haptic_topology.validate import as_bool, as_float, check_keys

if TYPE_CHECKING:
    from haptic_topology.dynamics.self_contacts import SelfContacts

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_PLANES = (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE)
_ROUND = (ObstacleKind.DISC, ObstacleKind.SPHERE)
#: Obstacles a box or cylinder meets through coal (a mesh solid meets every obstacle so, a box
#: also a sphere).
_COAL = (ObstacleKind.BOX, ObstacleKind.MESH)
#: Chains up to this many links take discs and spheres in scalar arithmetic.
_SCALAR_LINKS = 8
#: The joint placements of a model whose broad phases have nothing to place.
_NO_PLACEMENTS = np.zeros((0, 4, 4))


@dataclass(frozen=True)
class ContactParams:
    """Penalty contact model (see module doc): ``stiffness`` k (N/m), ``damping`` b (N s/m),
    ``friction`` mu, ``slip_velocity`` v_s (m/s), and ``margin`` (m): candidates whose gap is
    below it at an update are sent to the LMI (eq. 17), so it renders the contacts that start
    before the next update."""

    stiffness: float = 2000.0
    damping: float = 20.0
    friction: float = 0.0
    slip_velocity: float = 1e-3
    margin: float = 0.005


@dataclass(frozen=True)
class LinkCapsule:
    """One capsule of link ``link`` (index): axis ``a -> b`` ((3,) m, in the link's joint
    frame; ``a == b``: a sphere) and ``radius`` (m). ``chained``: the default capsule of a link
    whose parent link also has its default capsule, so ``a`` is the parent's ``b``."""

    link: int
    a: np.ndarray
    b: np.ndarray
    radius: float
    chained: bool = False
    urdf_link: str = ''


@dataclass(frozen=True, eq=False)
class LinkSolid:
    """A URDF box or cylinder on link ``link`` (index), placed in the link's joint frame:
    ``kind`` ``box`` (``size``: half extents, m) or ``cylinder`` (``size``: radius, half
    length, m; axis along ``rotation[:, 2]``) at ``centre`` ((3,) m) with ``rotation``
    (link_R_solid); ``kind`` ``mesh`` (spatial tasks): the convex hull of ``mesh`` (``size``:
    its scale) with its frame at ``centre``, turned by ``rotation``; in a planar task ``kind``
    ``polygon``: the projection of a box, cylinder or mesh hull on the link's xy plane,
    ``vertices`` (k x 3, z = 0, counter-clockwise, link frame). ``urdf_link``: the URDF link
    whose ``<collision>`` it is."""

    link: int
    kind: str
    centre: np.ndarray
    rotation: np.ndarray
    size: tuple[float, ...]
    vertices: np.ndarray | None = None
    mesh: MeshGeometry | None = None
    urdf_link: str = ''


LinkShape = LinkCapsule | LinkSolid

#: |z| of a planar cylinder's axis (link frame) within this of 1 or 0: along z or in the plane.
_AXIS_TOL = 1e-9


@dataclass(frozen=True)
class ContactSettings:
    """The scenario's ``contacts:`` block: model, obstacles, the default capsule radius
    ``link_radius`` (m), per-link choices ``links`` (name -> radius in m, or None: the link
    does not collide), and whether the LMI computes the contacts every cycle (``lmi_local``;
    False: it holds the VE's contact forces of the update, contacts at the VE's rate only)."""

    params: ContactParams
    obstacles: tuple[Obstacle, ...]
    link_radius: float = 0.005
    links: tuple[tuple[str, float | None], ...] = ()
    lmi_local: bool = True
    where: str = 'contacts'
    #: Penalty contacts between the linkage's own links too (spatial tasks:
    #: :mod:`haptic_topology.dynamics.self_contacts`).
    self_collisions: bool = False

    @classmethod
    def from_config(cls, raw: Any, where: str, linkage: Linkage, base: Path | None = None
                    ) -> ContactSettings:
        """Parse the block (``where``: its path) and check it against ``linkage`` (link
        names, collision shapes it can model: :meth:`capsules`); ``base``: the directory
        of the scenario file (relative mesh obstacle files)."""
        c = check_keys(raw, where, required=('obstacles',), optional=(
            'stiffness', 'damping', 'friction', 'slip_velocity', 'margin', 'link_radius',
            'links', 'lmi_local', 'self_collisions'))
        params = ContactParams(
            stiffness=as_float(c.get('stiffness', 2000.0), f'{where}.stiffness', lo=0.0,
                               lo_open=True),
            damping=as_float(c.get('damping', 20.0), f'{where}.damping', lo=0.0),
            friction=as_float(c.get('friction', 0.0), f'{where}.friction', lo=0.0),
            slip_velocity=as_float(c.get('slip_velocity', 1e-3), f'{where}.slip_velocity',
                                   lo=0.0, lo_open=True),
            margin=as_float(c.get('margin', 0.005), f'{where}.margin', lo=0.0))
        default = as_float(c.get('link_radius', 0.005), f'{where}.link_radius', lo=0.0)
        choices: list[tuple[str, float | None]] = []
        links = check_keys(c.get('links', {}), f'{where}.links',
                           optional=linkage.link_names)
        for name, spec in links.items():
            w = f'{where}.links.{name}'
            s = check_keys(spec, w, optional=('radius', 'collide'))
            collide = as_bool(s.get('collide', True), f'{w}.collide')
            if collide != ('radius' in s):
                raise ConfigError(f'{w}: give either radius (m, a capsule along the link) '
                                  f'or collide: false')
            choices.append((name, as_float(s['radius'], f'{w}.radius', lo=0.0)
                            if collide else None))
        obstacles = obstacles_from_config(c['obstacles'], f'{where}.obstacles', linkage.task,
                                          base)
        self_collisions = as_bool(c.get('self_collisions', False), f'{where}.self_collisions')
        if self_collisions and linkage.task.planar:
            raise ConfigError(f'{where}.self_collisions: only for spatial tasks (a planar '
                              f'linkage\'s links move in parallel planes and pass over one '
                              f'another, so their projections overlapping is no collision); '
                              f'remove the key or set it false')
        settings = cls(params, obstacles, default, tuple(choices),
                       as_bool(c.get('lmi_local', True), f'{where}.lmi_local'), where,
                       self_collisions)
        settings.shapes(linkage)
        return settings

    def capsules(self, linkage: Linkage) -> tuple[LinkCapsule, ...]:
        """The capsules of :meth:`shapes`, in link order."""
        return tuple(c for c in self.shapes(linkage) if isinstance(c, LinkCapsule))

    def shapes(self, linkage: Linkage) -> tuple[LinkShape, ...]:
        """Every link's contact shapes (see module doc), in link order. Raises ConfigError
        for a choice naming a link ``linkage`` lacks, and for a URDF collision shape that
        cannot be modelled exactly (planar: a cylinder tilted out of the plane) on a link
        without a choice."""
        planar = linkage.task.planar
        chosen = dict(self.links)
        unknown = sorted(set(chosen) - set(linkage.link_names))
        if unknown:
            raise ConfigError(f'{self.where}.links: unknown link(s) {", ".join(unknown)} '
                              f'(expected: {", ".join(linkage.link_names)})')
        out: list[LinkShape] = []
        default_prev = False
        for i, link in enumerate(linkage.links):
            w = f'{self.where}.links.{link.name}'
            if link.name in chosen or link.collision is None:
                radius = chosen.get(link.name, self.link_radius)
                if radius is None:
                    default_prev = False
                    continue
                if i + 1 < linkage.dof:
                    nxt = linkage.links[i + 1].origin_xyz
                    tip = (np.array(nxt, dtype=float) if nxt is not None
                           else np.array([link.length, 0.0, 0.0]))
                else:
                    tip = np.array([link.length, 0.0, 0.0])
                out.append(LinkCapsule(i, np.zeros(3), tip, radius,
                                       chained=default_prev and i > 0))
                default_prev = True
                continue
            default_prev = False
            for shape in link.collision:
                centre = np.array(shape.xyz, dtype=float)
                rot = np.array(shape.rotation, dtype=float).reshape(3, 3)
                what, u = shape.kind, shape.urdf_link
                if shape.kind == 'sphere':
                    out.append(LinkCapsule(i, centre, centre.copy(), shape.size[0], urdf_link=u))
                    continue
                if shape.kind == 'capsule':
                    half = 0.5 * shape.size[1] * rot[:, 2]
                    out.append(LinkCapsule(i, centre - half, centre + half, shape.size[0],
                                           urdf_link=u))
                    continue
                if shape.kind == 'box':
                    half_extents = 0.5 * np.array(shape.size)
                    out.append(LinkSolid(i, 'polygon', centre, rot, tuple(half_extents.tolist()),
                                         convex_hull_xy(box_vertices(centre, rot, half_extents)),
                                         urdf_link=u)
                               if planar else
                               LinkSolid(i, 'box', centre, rot, tuple(half_extents.tolist()),
                                         urdf_link=u))
                    continue
                if shape.kind == 'mesh':
                    where = f'{linkage.urdf_path}: link {shape.urdf_link!r} <mesh>'
                    base = linkage.urdf_path.parent if linkage.urdf_path else None
                    geometry = load_mesh(resolve_mesh(shape.mesh, base, where), (
                        shape.size[0], shape.size[1], shape.size[2]), where)
                    out.append(LinkSolid(i, 'polygon', centre, rot, shape.size, convex_hull_xy(
                        centre + geometry.vertices @ rot.T), urdf_link=u) if planar else
                               LinkSolid(i, 'mesh', centre, rot, shape.size, mesh=geometry,
                                         urdf_link=u))
                    continue
                if shape.kind == 'cylinder':
                    radius, half_length = shape.size[0], 0.5 * shape.size[1]
                    axis_z = abs(float(rot[2, 2]))
                    if not planar:
                        out.append(LinkSolid(i, 'cylinder', centre, rot, (radius, half_length),
                                             urdf_link=u))
                        continue
                    if axis_z >= 1.0 - _AXIS_TOL:       # along z: projects to a disc
                        out.append(LinkCapsule(i, centre, centre.copy(), radius, urdf_link=u))
                        continue
                    if axis_z <= _AXIS_TOL:             # in the plane: a rectangle
                        out.append(LinkSolid(i, 'polygon', centre, rot, (radius, half_length),
                                             rectangle_of_cylinder(centre, rot, radius,
                                                                   half_length), urdf_link=u))
                        continue
                    what = (f'cylinder tilted out of the plane (axis z = {rot[2, 2]:.6g} in the '
                            f'link frame, whose projection has elliptic ends)')
                raise ConfigError(
                    f'{w}: the URDF gives link {link.name!r} a {what} collision shape (on '
                    f'{shape.urdf_link!r}, {linkage.urdf_path}); contacts model spheres, '
                    f'capsules, boxes, cylinders and meshes (their hulls) exactly and would '
                    f'have to approximate it: set links.{link.name}.radius (m) in this '
                    f'contacts block for a capsule along the link, or '
                    f'links.{link.name}.collide: false to leave the link out')
        return tuple(out)


def _bounding_sphere(solid: LinkSolid, corners: np.ndarray | None
                     ) -> tuple[np.ndarray, float]:
    """A sphere around ``solid`` (link frame): centre (3,) m and radius m. A box or polygon:
    around its corners' mean; a cylinder: around its centre, ``hypot(r, h)``; a mesh: its
    hull's sphere."""
    if solid.mesh is not None:
        return solid.centre + solid.rotation @ solid.mesh.centre, solid.mesh.radius
    if corners is None:
        return solid.centre, math.hypot(solid.size[0], solid.size[1])
    centre = corners.mean(axis=0)
    return centre, float(np.max(np.linalg.norm(corners - centre, axis=1)))


def _solid_row(solid: LinkSolid, corners: np.ndarray | None) -> np.ndarray:
    """``solid``'s row of the broad phase (:data:`contact_bounds.SOLID_COLUMNS`, link frame):
    its bounding sphere and, but for a polygon, its oriented box (a box; a cylinder's; the box
    around a mesh's hull)."""
    from haptic_topology.dynamics import contact_bounds as bounds  # numba: see ContactModel
    row = np.zeros(bounds.SOLID_COLUMNS)
    row[0:3], row[3] = _bounding_sphere(solid, corners)
    if solid.kind == 'polygon':
        return row
    centre, half = solid.centre, np.array(solid.size)
    if solid.mesh is not None:
        centre, half = solid.centre + solid.rotation @ solid.mesh.box_centre, solid.mesh.box_half
    elif solid.kind == 'cylinder':
        half = np.array([solid.size[0], solid.size[0], solid.size[1]])
    row[4:7], row[7:16], row[16:19], row[19] = centre, solid.rotation.ravel(), half, 1.0
    return row


def _obstacle_row(obstacle: Obstacle) -> np.ndarray:
    """``obstacle``'s row of the broad phase (:data:`contact_bounds.OBSTACLE_COLUMNS`, world;
    a mesh: the box around it)."""
    from haptic_topology.dynamics import contact_bounds as bounds
    row = np.zeros(bounds.OBSTACLE_COLUMNS)
    kind = obstacle.kind
    if kind in _PLANES:
        row[0], row[1:4], row[16] = (bounds.PLANE, obstacle.normal,
                                     float(obstacle.normal @ obstacle.point))
    elif kind in _ROUND:
        row[0], row[1:4], row[16] = bounds.ROUND, obstacle.point, obstacle.radius
    elif kind is ObstacleKind.SEGMENT:
        row[0], row[1:4], row[13:16], row[16] = (bounds.SEGMENT, obstacle.point, obstacle.end,
                                                 obstacle.radius)
    else:
        centre, half = obstacle.point, obstacle.half_extents
        if obstacle.mesh is not None:
            centre = obstacle.rotation @ obstacle.mesh.box_centre + obstacle.point
            half = obstacle.mesh.box_half
        row[0], row[1:4], row[4:13], row[13:16] = (bounds.BOX, centre,
                                                   obstacle.rotation.ravel(), half)
    return row


@dataclass(frozen=True)
class ContactSet:
    """Contact candidates at one configuration (c of them): ``links`` (c,) link index,
    ``obstacles`` (c,) obstacle index, ``points`` (c x 3, m, world, on the link axes),
    ``normals`` (c x 3, unit, from the obstacle towards the link), ``gaps`` (c,) m (negative:
    penetration), ``jacobians`` (c x 3 x d): linear velocity of each point, ``v_i = J_i qdot``.
    A self-contact (:mod:`~haptic_topology.dynamics.self_contacts`) has obstacle -1, its link
    a's index and point, the normal from link b towards a and the relative Jacobian
    ``J_a(p_a) - J_b(p_b)``."""

    links: np.ndarray
    obstacles: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    gaps: np.ndarray
    jacobians: np.ndarray

    def __len__(self) -> int:
        return int(self.gaps.size)


def _force(params: ContactParams, gap: float, nx: float, ny: float, nz: float, vx: float,
           vy: float, vz: float) -> tuple[float, float, float]:
    """One candidate's force (N, world) at ``gap`` (m) with normal ``n`` and point velocity
    ``v`` (m/s): the model of the module doc."""
    if gap >= 0.0:
        return 0.0, 0.0, 0.0
    rate = nx * vx + ny * vy + nz * vz
    f_n = -params.stiffness * gap - params.damping * rate
    if f_n <= 0.0:
        return 0.0, 0.0, 0.0
    fx, fy, fz = f_n * nx, f_n * ny, f_n * nz
    mu = params.friction
    if mu > 0.0:
        tx, ty, tz = vx - rate * nx, vy - rate * ny, vz - rate * nz
        scale = mu * f_n / math.sqrt(tx * tx + ty * ty + tz * tz
                                     + params.slip_velocity * params.slip_velocity)
        fx, fy, fz = fx - scale * tx, fy - scale * ty, fz - scale * tz
    return fx, fy, fz


def contact_forces(params: ContactParams, gaps: np.ndarray, normals: np.ndarray,
                   velocities: np.ndarray) -> np.ndarray:
    """Forces ``F_i`` (c x 3, N, world) on the link points of the candidates with ``gaps``
    (c,), ``normals`` (c x 3) and point ``velocities`` (c x 3, m/s): the model of the module
    doc (zero where ``gap >= 0``). The VE (at every RK4 stage) and the LMI (every cycle) use
    it with a few contacts: scalar arithmetic per contact costs a tenth of a dozen numpy
    calls on arrays of three."""
    return np.array([_force(params, g, *n, *v) for g, n, v in zip(
        gaps.tolist(), normals.tolist(), velocities.tolist(), strict=True)]).reshape(-1, 3)


def contact_potential(params: ContactParams, gaps: np.ndarray) -> float:
    """``U = sum_i k delta_i^2 / 2`` (J) of the penetrating candidates."""
    depth = np.maximum(-gaps, 0.0)
    return 0.5 * params.stiffness * float(depth @ depth)


def point_jacobian(model: pin.Model, data: Any, joint: int, point: np.ndarray) -> np.ndarray:
    """The linear velocity Jacobian (3 x d, world) of the point ``point`` ((3,) m, world) fixed
    to the body of ``joint``, from ``data``'s joint Jacobians (``computeJointJacobians``
    current): ``v_p = v_o + w x (p - o) = J_v qdot + [p - o]x^T J_w qdot``."""
    j6 = pin.getJointJacobian(model, data, joint, _LWA).reshape(6, model.nv)
    ax, ay, az = point - data.oMi[joint].translation
    return j6[:3] + np.array([[0.0, az, -ay], [-az, 0.0, ax], [ay, -ax, 0.0]]) @ j6[3:]


class ContactModel:
    """Detection and contact torques of a linkage's shapes against the obstacles, and against
    each other with ``self_collisions`` (eqs. 1-2).

    Holds its own Pinocchio ``Data`` (the VE's workspace stays untouched)."""

    def __init__(self, model: pin.Model, linkage: Linkage, settings: ContactSettings) -> None:
        self.model = model
        self.data = model.createData()
        # the joints' world placements: references into self.data (forwardKinematics
        # updates them), one list made once
        self._oMi = self.data.oMi.tolist()
        self.settings = settings
        self.params = settings.params
        self.dof = linkage.dof
        self._planar = linkage.task.planar
        shapes = settings.shapes(linkage)
        caps = [c for c in shapes if isinstance(c, LinkCapsule)]
        self._solids = solids = [c for c in shapes if isinstance(c, LinkSolid)]
        self._cap_a = [c.a for c in caps]
        self._cap_b = [c.b for c in caps]
        self._cap_joint = [c.link + 1 for c in caps]
        self._cap_link = cap_link = np.array([c.link for c in caps], dtype=int)
        self._radii = radii = np.array([c.radius for c in caps], dtype=float)
        # each capsule's coal shape (against boxes and meshes), made once
        self._coal_caps = [capsule_shape(c.radius, float(np.linalg.norm(c.b - c.a)))
                           for c in caps]
        n = self._ncaps = len(caps)
        # Candidate layout (static), by capsule: planes (row-major: end e times plane; the
        # ends are every capsule's b, then the a of every capsule that is neither a sphere nor
        # chained to its parent's b), then discs/spheres (n each), then the others (their
        # count per capsule and obstacle is fixed by capsule_gaps: 1).
        obstacles = settings.obstacles
        planes = [k for k, ob in enumerate(obstacles) if ob.kind in _PLANES]
        self._round = [ob for ob in obstacles if ob.kind in _ROUND]
        round_k = [k for k, ob in enumerate(obstacles) if ob.kind in _ROUND]
        self._other = [ob for ob in obstacles if ob.kind not in _PLANES + _ROUND]
        other_k = [k for k, ob in enumerate(obstacles) if ob.kind not in _PLANES + _ROUND]
        self._plane_k = np.array(planes, dtype=int)
        self._plane_n = np.array([obstacles[k].normal for k in planes]).reshape(-1, 3)
        self._plane_offset = np.array([float(obstacles[k].normal @ obstacles[k].point)
                                       for k in planes])
        bases = [c for c, cap in enumerate(caps)
                 if not cap.chained and not np.array_equal(cap.a, cap.b)]
        self._bases = np.array(bases, dtype=int)
        end_caps = np.append(np.arange(n), self._bases).astype(int)
        self._plane_radii = np.repeat(radii[end_caps], len(planes))
        self._plane_s = np.repeat(np.append(np.ones(n), np.zeros(len(bases))), len(planes))
        self._plane_normals = np.tile(self._plane_n, (end_caps.size, 1))
        self._caps = np.concatenate([np.repeat(end_caps, len(planes))]
                                    + [np.arange(n)] * len(round_k)
                                    + [np.arange(n)] * len(other_k)).astype(int)
        self._obstacles = np.concatenate([np.tile(self._plane_k, end_caps.size)]
                                         + [np.full(n, k) for k in round_k]
                                         + [np.full(n, k) for k in other_k]).astype(int)
        self._links = cap_link[self._caps]
        # Solid candidates (after the capsules'), solid by solid, obstacle by obstacle; a pair
        # whose lower bound (bounding sphere, box) is at least the query's limit is skipped
        # (its gaps are at least that). A coal pair's query objects are made once.
        self._pairs_of = [[(k, CoalPair(sol.kind, sol.size, ob, sol.mesh)
                            if ob.kind in _COAL or sol.mesh is not None
                            or (sol.kind == 'box' and ob.kind is ObstacleKind.SPHERE)
                            else None)
                           for k, ob in enumerate(obstacles)] for sol in solids]
        self._plane_of = {k: (float(ob.normal @ ob.point), ob.normal.tolist())
                          for k, ob in enumerate(obstacles) if ob.kind in _PLANES}
        self._corners_local = [
            None if sol.kind in ('cylinder', 'mesh') else sol.vertices if sol.vertices is not None
            else box_vertices(sol.centre, sol.rotation, np.array(sol.size)) for sol in solids]
        # the broad phase (contact_bounds; imported here, not with this module: reading a
        # scenario's contacts block loads no numba), its rows and output made once
        from haptic_topology.dynamics import contact_bounds as bounds
        self._near_pairs = bounds.near_pairs
        self._solid_rows = np.array([_solid_row(sol, corners) for sol, corners in zip(
            solids, self._corners_local, strict=True)]).reshape(-1, bounds.SOLID_COLUMNS)
        self._obstacle_rows = np.array([_obstacle_row(ob) for ob in obstacles]).reshape(
            -1, bounds.OBSTACLE_COLUMNS)
        self._near = np.empty(len(solids) * len(obstacles), dtype=np.int64)
        # the joints carrying solids or self-contact shapes, whose world placements are
        # stacked once per call for both broad phases (_placements), and each solid's index
        # among them
        self._joints = sorted({sol.link + 1 for sol in solids} | (
            {shape.link + 1 for shape in shapes} if settings.self_collisions else set()))
        self._stack = bool(solids and obstacles) or settings.self_collisions
        self._self: SelfContacts | None = None
        if settings.self_collisions:
            from haptic_topology.dynamics.self_contacts import SelfContacts
            self._self = SelfContacts(linkage, shapes, self._joints)
        self._solid_slot = np.array([self._joints.index(sol.link + 1) for sol in solids],
                                    dtype=np.int64)
        self._slot_of = self._solid_slot.tolist()

    def _axes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World ends of every capsule's axis (n x 3 each) at ``q`` (forward kinematics;
        planar: on the xy plane)."""
        model, data = self.model, self.data
        pin.forwardKinematics(model, data, q)
        p0 = np.empty((self._ncaps, 3))
        p1 = np.empty((self._ncaps, 3))
        for c, (joint, a, b) in enumerate(zip(self._cap_joint, self._cap_a, self._cap_b,
                                              strict=True)):
            placement = data.oMi[joint]
            p0[c] = placement.act(a)
            p1[c] = placement.act(b)
        if self._planar:
            p0[:, 2] = 0.0
            p1[:, 2] = 0.0
        return p0, p1

    def candidates(self, p0: np.ndarray, p1: np.ndarray, gaps_only: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every candidate of the module doc for capsule axes ``p0 -> p1`` (n x 3 each):
        ``(capsules, obstacles, s, gaps, normals)`` (``gaps_only``: the gaps, the rest
        empty). Planes and half-planes in one product for all capsule ends and planes, discs
        and spheres for all capsules at once (the same numbers as
        :func:`~haptic_topology.model.obstacles.capsule_gaps`, tested), segments and boxes
        capsule by capsule through it."""
        parts_gap: list[np.ndarray] = []
        parts_s: list[np.ndarray] = []
        parts_n: list[np.ndarray] = []
        radii = self._radii
        if not self._ncaps:
            return (self._caps, self._obstacles, np.zeros(0), np.zeros(0), np.zeros((0, 3)))
        if self._plane_k.size:
            # Every capsule's b and the a's not shared (each point once), against every plane.
            ends = np.vstack((p1, p0[self._bases]))
            parts_gap.append((ends @ self._plane_n.T - self._plane_offset).ravel()
                             - self._plane_radii)
            parts_s.append(self._plane_s)
            parts_n.append(self._plane_normals)
        for ob in self._round:
            if self._ncaps <= _SCALAR_LINKS:
                gap, s, normal = self._round_scalar(ob, p0, p1)
            else:
                axis = p1 - p0
                length2 = np.einsum('ij,ij->i', axis, axis)
                along = np.einsum('ij,ij->i', ob.point - p0, axis)
                s = np.clip(np.divide(along, length2, out=np.zeros(self._ncaps),
                                      where=length2 > EPS * EPS), 0.0, 1.0)
                v = p0 + s[:, None] * axis - ob.point
                dist = np.sqrt(np.einsum('ij,ij->i', v, v))
                gap = dist - ob.radius - radii
                normal = v / np.maximum(dist, EPS)[:, None]
                for j in np.nonzero(dist <= EPS)[0].tolist():   # on the centre: fallback
                    gap[j], s[j], normal[j] = capsule_gaps(ob, p0[j], p1[j], radii[j])[0]
            parts_gap.append(gap)
            if not gaps_only:
                parts_s.append(s)
                parts_n.append(normal)
        for ob in self._other:
            for i in range(self._ncaps):
                for gap_i, s_i, n_i in capsule_gaps(ob, p0[i], p1[i], radii[i],
                                                    self._coal_caps[i]):
                    parts_gap.append(np.array([gap_i]))
                    parts_s.append(np.array([s_i]))
                    parts_n.append(n_i[None, :])
        if not parts_gap:
            return (self._caps, self._obstacles, np.zeros(0), np.zeros(0), np.zeros((0, 3)))
        gaps = np.concatenate(parts_gap)
        if gaps_only:
            return self._caps, self._obstacles, np.zeros(0), gaps, np.zeros((0, 3))
        return (self._caps, self._obstacles, np.concatenate(parts_s), gaps,
                np.concatenate(parts_n))

    def _round_scalar(self, ob: Obstacle, p0: np.ndarray, p1: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Disc/sphere candidates of a short chain in scalar arithmetic (the numbers of the
        array form in :meth:`candidates`, a fifth of its cost for a few links)."""
        cx, cy, cz = ob.point.tolist()
        gaps, ss, normals = [], [], []
        for i, ((ax, ay, az), (bx, by, bz), r) in enumerate(zip(
                p0.tolist(), p1.tolist(), self._radii.tolist(), strict=True)):
            dx, dy, dz = bx - ax, by - ay, bz - az
            length2 = dx * dx + dy * dy + dz * dz
            s = 0.0
            if length2 > EPS * EPS:
                s = min(max(((cx - ax) * dx + (cy - ay) * dy + (cz - az) * dz) / length2, 0.0),
                        1.0)
            vx, vy, vz = ax + s * dx - cx, ay + s * dy - cy, az + s * dz - cz
            dist = math.sqrt(vx * vx + vy * vy + vz * vz)
            if dist <= EPS:     # on the centre: its own fallback
                gap, s, n = capsule_gaps(ob, p0[i], p1[i], r)[0]
                gaps.append(gap)
                ss.append(s)
                normals.append(n.tolist())
                continue
            gaps.append(dist - ob.radius - r)
            ss.append(s)
            normals.append([vx / dist, vy / dist, vz / dist])
        return np.array(gaps), np.array(ss), np.array(normals)

    def _placements(self) -> np.ndarray:
        """The world placements (homogeneous, m x 4 x 4) of the joints carrying solids or
        self-contact shapes, at the last :meth:`_axes`: both broad phases' input, stacked
        once per call."""
        if not self._stack:         # nothing to place: no solid meets an obstacle
            return _NO_PLACEMENTS
        oMi = self._oMi
        return np.array([oMi[j].homogeneous for j in self._joints])

    def _solid_hits(self, limit: float, placements: np.ndarray
                    ) -> tuple[list[int], list[int], list[list[float]], list[float],
                               list[list[float]]]:
        """The solid candidates with ``gap < limit`` (``limit >= 0``) at ``placements``
        (:meth:`_placements`): ``(links, obstacles, points, gaps, normals)``, solid by solid and
        obstacle by obstacle, each pair's candidates in the order of
        :func:`~haptic_topology.model.solids.solid_gaps` (the same numbers, tested). A pair is
        skipped when a lower bound of its gaps is at least ``limit``: the obstacle's distance
        to the solid's bounding sphere, or (spatial) its separation from the solid's box less
        1e-9 m (:mod:`~haptic_topology.dynamics.contact_bounds`). Then the two are apart by
        at least that much (each bound is at most the signed distance of the solid and the
        obstacle, and the signed distance of two disjoint shapes is their distance), and
        coal's gap of a pair that far apart is not below ``limit`` (GJK's distance is at
        least the true one, its tolerance 1e-10 m). Runs at every RK4 stage."""
        links: list[int] = []
        obs: list[int] = []
        points: list[list[float]] = []
        gaps: list[float] = []
        normals: list[list[float]] = []
        obstacles = self.settings.obstacles
        if not obstacles:
            return links, obs, points, gaps, normals
        # the pairs whose lower bounds are below the limit, solid by solid, obstacle by
        # obstacle (contact_bounds)
        count = self._near_pairs(placements, self._solid_slot, self._solid_rows,
                                 self._obstacle_rows, self._planar, limit, self._near)
        if not count:
            return links, obs, points, gaps, normals
        # every joint's rotation and origin, laid out as numpy's products need them to give
        # the same bits as ever (C order: a Pinocchio rotation is a column-major view)
        rots = placements[:, :3, :3].copy()
        origins = placements[:, :3, 3].copy()
        n_ob = len(obstacles)
        placed: tuple[np.ndarray, np.ndarray] | None = None
        last = -1
        for index in self._near[:count].tolist():
            j, k = divmod(index, n_ob)
            sol, pair, ob = self._solids[j], self._pairs_of[j][k][1], obstacles[k]
            rot, origin = rots[self._slot_of[j]], origins[self._slot_of[j]]
            if j != last:
                placed, last = None, j
            local = self._corners_local[j]
            if local is None or ob.kind not in _PLANES:
                if placed is None:
                    placed = (rot @ sol.centre + origin, rot @ sol.rotation)
                centre, rotation = placed
            found: list[tuple[float, list[float], list[float]]]
            if pair is not None:        # coal: a mesh, or a box or cylinder with solid_gaps'
                gap, point_t, normal_t = pair.gap_floats(centre, rotation)
                if gap < limit:
                    links.append(sol.link)
                    obs.append(k)
                    points.append(point_t)
                    gaps.append(gap)
                    normals.append(normal_t)
                continue
            if ob.kind in _PLANES:
                if local is not None:
                    world = local @ rot.T + origin
                    if self._planar:
                        world[:, 2] = 0.0
                else:
                    world = cylinder_rims(centre, rotation, sol.size[0], sol.size[1],
                                          ob.normal)
                offset, normal_t = self._plane_of[k]
                world_t = world.tolist()
                for i, gap in enumerate((world @ ob.normal).tolist()):
                    if gap - offset < limit:
                        links.append(sol.link)
                        obs.append(k)
                        points.append(world_t[i])
                        gaps.append(gap - offset)
                        normals.append(normal_t)
                continue
            if sol.kind == 'polygon':
                assert local is not None
                world = local @ rot.T + origin
                a, b = ob.point, (ob.end if ob.kind is ObstacleKind.SEGMENT else ob.point)
                sd, px, py, nx, ny = polygon_segment_xy(
                    [(x, y) for x, y, _ in world.tolist()],
                    float(a[0]), float(a[1]), float(b[0]), float(b[1]))
                found = [(sd - ob.radius, [px, py, 0.0], [nx, ny, 0.0])]
            else:
                found = [(gap, point.tolist(), normal.tolist()) for gap, point, normal
                         in solid_gaps(ob, sol.kind, centre, rotation, sol.size, None, pair)]
            for gap, point_t, normal_t in found:
                if gap < limit:
                    links.append(sol.link)
                    obs.append(k)
                    points.append(point_t)
                    gaps.append(gap)
                    normals.append(normal_t)
        return links, obs, points, gaps, normals

    def detect(self, q: np.ndarray, margin: float = 0.0,
               jacobians: bool = True) -> ContactSet:
        """Candidates with ``gap < margin`` at ``q`` (see module doc), the capsules', the
        solids', then the self-contacts', with their Jacobians when ``jacobians`` (else
        zeros)."""
        p0, p1 = self._axes(q)
        caps, obs, s, gaps, normals = self.candidates(p0, p1)
        keep = np.nonzero(gaps < margin)[0]
        caps, obs, s, gaps = caps[keep], obs[keep], s[keep], gaps[keep]
        normals = normals.reshape(-1, 3)[keep]
        points = p0[caps] + s[:, None] * (p1[caps] - p0[caps])
        links = self._cap_link[caps]
        placements = self._placements()
        if self._solids:
            s_links, s_obs, s_points, s_gaps, s_normals = self._solid_hits(margin, placements)
            if s_links:
                links = np.concatenate((links, s_links)).astype(int)
                obs = np.concatenate((obs, s_obs)).astype(int)
                points = np.vstack([points, *s_points])
                gaps = np.concatenate((gaps, s_gaps))
                normals = np.vstack([normals, *s_normals])
        jac = np.zeros((links.size, 3, self.dof))
        if jacobians and links.size:
            model, data = self.model, self.data
            pin.computeJointJacobians(model, data, q)
            for r in range(links.size):
                jac[r] = point_jacobian(model, data, int(links[r]) + 1, points[r])
        normals = np.array(normals)
        if self._self is not None:      # self-contacts: obstacle -1, relative Jacobians
            parts = self._self.detect(self.model, self.data, q, placements, margin,
                                      jacobians)
            links = np.concatenate((links, parts[0])).astype(int)
            obs = np.concatenate((obs, np.full(parts[0].size, -1))).astype(int)
            points, normals = np.vstack((points, parts[1])), np.vstack((normals, parts[2]))
            gaps, jac = np.concatenate((gaps, parts[3])), np.concatenate((jac, parts[4]))
        return ContactSet(links, obs, points, normals, gaps, jac)

    def torques(self, q: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, float]:
        """``sum_i J_i^T F_i`` (d, N m / N) at ``(q, dq)`` and the contacts' power on the VT
        ``sum_i F_i^T v_i`` (W). Called at every RK4 stage, so written for few contacts: per
        link in contact one joint Jacobian ``J`` (6 x d, world-aligned at the joint), per
        penetrating candidate the point's velocity ``v_o + w x a`` (``a``: point - joint
        origin), and the torques ``J^T (sum F, sum a x F)`` (``sum_i J_i^T F_i`` with
        :meth:`detect`'s ``J_i``, to rounding), plus the self-contacts' if on."""
        p0, p1 = self._axes(q)
        # (joint, point, gap, normal) of every penetrating candidate, capsules then solids
        hits: list[tuple[int, Any, float, Any]] = []
        if self._ncaps:
            caps, _, s, gaps, normals = self.candidates(p0, p1)
            hits = [(self._cap_joint[int(caps[i])],
                     (p0[caps[i]] + s[i] * (p1[caps[i]] - p0[caps[i]])).tolist(),
                     float(gaps[i]), normals[i].tolist())
                    for i in np.flatnonzero(gaps < 0.0).tolist()]
        placements = self._placements()
        if self._solids:
            s_links, _, s_points, s_gaps, s_normals = self._solid_hits(0.0, placements)
            hits += [(link + 1, point, gap, normal) for link, point, gap, normal in zip(
                s_links, s_points, s_gaps, s_normals, strict=True)]
        tau = np.zeros(self.dof)
        if not hits:
            return self._with_self(q, dq, tau, 0.0, placements)
        model, data, params = self.model, self.data, self.params
        pin.computeJointJacobians(model, data, q)
        by_joint: dict[int, list[tuple[Any, float, Any]]] = {}
        for joint, point, gap, normal in hits:
            by_joint.setdefault(joint, []).append((point, gap, normal))
        power = 0.0
        oMi = self._oMi
        for joint, items in by_joint.items():
            j6 = pin.getJointJacobian(model, data, joint, _LWA).reshape(6, self.dof)
            ox, oy, oz = oMi[joint].translation.tolist()
            v0x, v0y, v0z, wx, wy, wz = (j6 @ dq).tolist()
            fx_sum = fy_sum = fz_sum = mx = my = mz = 0.0
            for point, gap, normal in items:
                px, py, pz = point
                ax, ay, az = px - ox, py - oy, pz - oz
                vx = v0x + wy * az - wz * ay
                vy = v0y + wz * ax - wx * az
                vz = v0z + wx * ay - wy * ax
                nx, ny, nz = normal
                fx, fy, fz = _force(params, gap, nx, ny, nz, vx, vy, vz)
                fx_sum, fy_sum, fz_sum = fx_sum + fx, fy_sum + fy, fz_sum + fz
                mx += ay * fz - az * fy
                my += az * fx - ax * fz
                mz += ax * fy - ay * fx
                power += fx * vx + fy * vy + fz * vz
            # one joint's contacts: J^T (sum F, sum a x F)
            tau += j6.T @ np.array([fx_sum, fy_sum, fz_sum, mx, my, mz])
        return self._with_self(q, dq, tau, power, placements)

    def _with_self(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, power: float,
                   placements: np.ndarray) -> tuple[np.ndarray, float]:
        """``tau`` and ``power`` plus the self-contacts' (:mod:`.self_contacts`), if on; the
        link placements of :meth:`_axes` at ``q`` current, ``placements`` their
        :meth:`_placements`."""
        if self._self is None:
            return tau, power
        found = self._self.torques(self.model, self.data, q, dq, self.params, placements)
        if found is None:       # no pair penetrates: tau and power as they are
            return tau, power
        return tau + found[0], power + found[1]

    def potential(self, q: np.ndarray) -> float:
        """``U`` (J) at ``q`` (see module doc)."""
        return contact_potential(self.params, self.gaps(q))

    def gaps(self, q: np.ndarray) -> np.ndarray:
        """The gaps (m) at ``q`` of every capsule candidate and of the solids' and the
        self-contacts' penetrating candidates (the others are culled, see ``_solid_hits``):
        all that ``U`` and the penetration depth need, without normals or Jacobians."""
        gaps = self.candidates(*self._axes(q), gaps_only=True)[3]
        placements = self._placements()
        if self._solids:
            gaps = np.concatenate((gaps, self._solid_hits(0.0, placements)[3]))
        if self._self is not None:
            gaps = np.concatenate((gaps, self._self.gaps(placements)))
        return gaps

    def local(self, q: np.ndarray) -> LocalContacts:
        """The LMI's contacts for an update at ``q``: the candidates within ``margin``."""
        cs = self.detect(q, self.params.margin)
        return LocalContacts(self.params, np.array(q, dtype=float), cs.points, cs.normals,
                             cs.gaps, cs.jacobians, self.settings.lmi_local)


@dataclass(frozen=True)
class LocalContacts:
    """Contacts frozen at an LMI update (eq. 17): the candidates of :meth:`ContactModel.local`
    at configuration ``q`` (d). Between updates the LMI evaluates them linearised,
    ``g_i(q) = g_i + n_i^T J_i (q - q_update)``, ``v_i = J_i qdot``, with the same contact
    model as the VE (:func:`contact_forces`): at the update's ``(q, qdot)`` the two agree.
    A self-contact's ``J_i`` is the relative Jacobian ``J_a(p_a) - J_b(p_b)``: then
    ``n_i^T J_i`` is its gap's gradient, ``J_i qdot`` the relative velocity its force takes and
    ``J_i^T F_i`` the torques on both links, so all of this holds for it unchanged
    (:mod:`~haptic_topology.dynamics.self_contacts`).
    ``local`` False: the LMI holds the forces of the update instead (contacts at the VE's
    rate only)."""

    params: ContactParams
    q: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    gaps: np.ndarray
    jacobians: np.ndarray
    local: bool = True
    _nj: np.ndarray = field(init=False, repr=False, compare=False)
    _flat: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, '_nj', np.einsum('ci,cid->cd', self.normals,
                                                  self.jacobians))
        object.__setattr__(self, '_flat', self.jacobians.reshape(-1, self.q.size))

    @property
    def stacked_jacobian(self) -> np.ndarray:
        """The ``J_i`` stacked (3c x d): ``sum_i J_i^T F_i = stacked^T F`` for the forces
        ``F`` (c x 3) flattened row by row."""
        return self._flat

    def forces(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray | None:
        """``F_i`` (c x 3, N, world) at ``(q, dq)``; None when no contact penetrates."""
        gaps = self.gaps + self._nj @ (q - self.q)
        if not gaps.size or gaps.min() >= 0.0:
            return None
        vel = (self._flat @ dq).reshape(-1, 3)
        return contact_forces(self.params, gaps, self.normals, vel)

    def __len__(self) -> int:
        return int(self.gaps.size)
