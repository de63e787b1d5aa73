"""Static obstacles of the virtual environment (VE) and their signed distance to a link.

This is the VE's collision geometry for the contact terms of eq. 1 for links that are
*capsules* (the set of points within ``radius`` of its axis segment ``p0 -> p1``; the URDF's
boxes, cylinders and meshes: :mod:`haptic_topology.model.solids`); every obstacle is
static. :func:`capsule_gaps` returns candidate contacts ``(gap, s, normal)`` for one link and
one obstacle; a penalty model turns the negative gaps into forces.

Units and frames: SI (m, rad), everything in the world frame. A planar scenario lives in the
xy plane with z = 0 (``half_plane``, ``segment``, ``disc``); a spatial one uses ``plane``,
``sphere``, ``box`` and ``mesh``.

Sign conventions:

* ``gap`` is the signed distance (m) between the capsule's surface and the obstacle: positive
  when apart, negative when they overlap (then ``-gap`` is the penetration depth).
* ``normal`` is a unit world vector pointing from the obstacle towards the capsule, i.e. the
  direction in which the obstacle pushes the link. A half-plane's or plane's ``normal`` points
  out of the obstacle into free space.
* ``s`` in [0, 1] places the contact on the link's axis at ``p0 + s (p1 - p0)``.

YAML layout of ``scenario.contacts.obstacles`` (planar points take 2 or 3 numbers, z = 0)::

    - {type: half_plane, point: [x, y], normal: [nx, ny], name: wall}   # name optional
    - {type: segment, a: [x, y], b: [x, y], radius: 0.0}   # radius: half thickness, >= 0
    - {type: disc, center: [x, y], radius: r}               # r > 0
    - {type: plane, point: [x, y, z], normal: [nx, ny, nz]}
    - {type: sphere, center: [x, y, z], radius: r}
    - {type: box, center: [x, y, z], half_extents: [hx, hy, hz], rpy: [r, p, y]}  # rpy opt.
    - {type: mesh, file: table.stl, center: [x, y, z], rpy: [r, p, y], scale: s}  # opt.

A ``mesh`` obstacle (STL, DAE, OBJ) is placed with its file's frame at ``center`` turned by
``rpy``; ``file`` is found as a URDF's mesh (``package://``, absolute, or relative to the
scenario file: :mod:`haptic_topology.model.meshes`), ``scale`` is 1 or 3 numbers (default 1;
e.g. 0.001 for a file in mm). It is rendered by its convex hull (the module doc of
:mod:`~haptic_topology.model.meshes` says why), through coal.

**What coal computes and what is kept here.** A capsule against a box or a mesh obstacle is
coal's signed distance of the two solids (GJK apart, EPA overlapping, tolerance
``meshes.COAL_TOLERANCE``; the capsule's coal shape is made once per link), its witness point
projected on the axis, and coal's normal. So a box obstacle and the same box as a mesh give
the same contact, and once the axis is inside the box the depth is the translation that
separates the two solids. Three closed forms stay, each because coal's answer is not the one
the penalty contact needs:

* **planes and half-planes**: one candidate per axis end. Coal gives one witness point, so a
  link lying flat on a table would be held at one end (the witness jumping between the ends
  as the link rocks), not at both.
* **discs and spheres**: where the centre is on the capsule's axis coal returns the axis
  direction as the normal with the depth across it (a sphere of radius 10 mm at the middle of
  a 100 mm link along x of radius 10 mm: -0.02 m with normal (1, 0, 0)), a force along the
  link for a depth across it; this form takes a perpendicular. Elsewhere the two agree to
  1e-16 m, and ``ContactModel`` computes every capsule against a disc in one array operation.
* **segments** (``_segment_params``): where the axis crosses the segment coal's normal is
  zero (crossing at the axis' middle) or points away from the side the axis' middle is on,
  and for parallel overlapping segments its witness is an end of the overlap, not its middle.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import coal
import numpy as np

from haptic_topology.errors import ConfigError
from haptic_topology.model.meshes import (
    MeshGeometry,
    capsule_convex_gap,
    load_mesh,
    resolve_mesh,
)
from haptic_topology.validate import as_float, as_str, as_vector, check_keys
from haptic_topology.vocabulary import TaskSpace

#: Lengths (m) below this count as zero: degenerate axes, coincident points, touching segments.
EPS = 1e-12

Gap = tuple[float, float, np.ndarray]


class ObstacleKind(enum.Enum):
    """Obstacle shape; the first three are planar (xy plane), the last three spatial."""

    HALF_PLANE = 'half_plane'
    SEGMENT = 'segment'
    DISC = 'disc'
    PLANE = 'plane'
    SPHERE = 'sphere'
    BOX = 'box'
    MESH = 'mesh'

    @property
    def task(self) -> TaskSpace:
        """The scenario kind this obstacle belongs to."""
        planar = self in (ObstacleKind.HALF_PLANE, ObstacleKind.SEGMENT, ObstacleKind.DISC)
        return TaskSpace.PLANAR if planar else TaskSpace.SPATIAL


@dataclass(frozen=True, eq=False)
class Obstacle:
    """One static obstacle, world frame, m. Unused fields are zeros (``rotation``: identity).

    ``point``: on the boundary (half_plane, plane), the centre (disc, sphere, box) or end a
    (segment). ``normal``: unit outward normal into free space (half_plane, plane). ``end``:
    end b (segment). ``radius``: disc/sphere radius or segment half thickness (>= 0).
    ``half_extents``: box half sizes (> 0). ``rotation``: box (mesh) orientation
    ``world_R_box``; a mesh's ``point`` is its frame's origin and ``mesh`` its geometry.
    Arrays are stored as read-only float copies; equality is identity (arrays do not compare).
    """

    kind: ObstacleKind
    name: str
    point: np.ndarray
    normal: np.ndarray = field(default_factory=lambda: np.zeros(3))
    end: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0
    half_extents: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    mesh: MeshGeometry | None = None

    def __post_init__(self) -> None:
        for name, shape in (('point', (3,)), ('normal', (3,)), ('end', (3,)),
                            ('half_extents', (3,)), ('rotation', (3, 3))):
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != shape:
                raise ValueError(f'Obstacle.{name}: expected shape {shape}, got {arr.shape}')
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, 'radius', float(self.radius))


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` for ``rpy = (roll, pitch, yaw)`` in rad."""
    cr, sr = math.cos(rpy[0]), math.sin(rpy[0])
    cp, sp = math.cos(rpy[1]), math.sin(rpy[1])
    cy, sy = math.cos(rpy[2]), math.sin(rpy[2])
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


_KEYS: dict[ObstacleKind, tuple[tuple[str, ...], tuple[str, ...]]] = {
    ObstacleKind.HALF_PLANE: (('point', 'normal'), ()),
    ObstacleKind.SEGMENT: (('a', 'b'), ('radius',)),
    ObstacleKind.DISC: (('center', 'radius'), ()),
    ObstacleKind.PLANE: (('point', 'normal'), ()),
    ObstacleKind.SPHERE: (('center', 'radius'), ()),
    ObstacleKind.BOX: (('center', 'half_extents'), ('rpy',)),
    ObstacleKind.MESH: (('file', 'center'), ('rpy', 'scale')),
}


def _names(task: TaskSpace) -> str:
    return ', '.join(k.value for k in ObstacleKind if k.task is task)


def _point(value: Any, where: str, task: TaskSpace) -> np.ndarray:
    """A world point or direction: planar ``[x, y]`` or ``[x, y, 0]``, spatial ``[x, y, z]``."""
    if not task.planar:
        return as_vector(value, where, 3)
    v = as_vector(value, where)
    if len(v) not in (2, 3):
        raise ConfigError(f'{where}: expected 2 or 3 numbers [x, y] or [x, y, 0] in a planar '
                          f'scenario, got {len(v)}')
    if len(v) == 3 and v[2] != 0.0:
        raise ConfigError(f'{where}[2]: expected z = 0 in a planar scenario, got {v[2]}')
    return np.array([v[0], v[1], 0.0])


def _unit(value: Any, where: str, task: TaskSpace) -> np.ndarray:
    v = _point(value, where, task)
    norm = float(np.linalg.norm(v))
    if norm <= EPS:
        raise ConfigError(f'{where}: expected a nonzero vector (length > {EPS}), got '
                          f'{v[:2 if task.planar else 3].tolist()}')
    return v / norm


def _mesh_obstacle(item: Mapping[str, Any], w: str, name: str, base: Path | None
                   ) -> Obstacle:
    scale_raw = item.get('scale', 1.0)
    scale = (as_vector(scale_raw, f'{w}.scale', 3, lo=0.0, lo_open=True)
             if isinstance(scale_raw, list)
             else np.full(3, as_float(scale_raw, f'{w}.scale', lo=0.0, lo_open=True)))
    path = resolve_mesh(as_str(item['file'], f'{w}.file'), base, f'{w}.file')
    mesh = load_mesh(path, (float(scale[0]), float(scale[1]), float(scale[2])), f'{w}.file')
    rpy = as_vector(item.get('rpy', [0.0, 0.0, 0.0]), f'{w}.rpy', 3)
    return Obstacle(ObstacleKind.MESH, name, as_vector(item['center'], f'{w}.center', 3),
                    rotation=rpy_matrix(rpy), mesh=mesh)


def _obstacle(raw: Any, w: str, i: int, task: TaskSpace, base: Path | None = None
              ) -> Obstacle:
    if not isinstance(raw, Mapping):
        raise ConfigError(f'{w}: expected a mapping {{type: ..., ...}}, got {type(raw).__name__}')
    if 'type' not in raw:
        raise ConfigError(f'{w}.type: missing required key (expected one of {_names(task)})')
    kind_name = as_str(raw['type'], f'{w}.type')
    if kind_name not in {k.value for k in ObstacleKind}:
        raise ConfigError(f'{w}.type: expected one of {_names(task)} (a {task.value} scenario), '
                          f'got {kind_name!r}')
    kind = ObstacleKind(kind_name)
    if kind.task is not task:
        raise ConfigError(f'{w}.type: {kind.value!r} is a {kind.task.value} obstacle; a '
                          f'{task.value} scenario expects one of {_names(task)}')
    required, optional = _KEYS[kind]
    item = check_keys(raw, w, required=('type', *required), optional=('name', *optional))
    name = as_str(item.get('name', f'{kind.value}{i}'), f'{w}.name')
    if not name:
        raise ConfigError(f'{w}.name: expected a non-empty string')
    if kind is ObstacleKind.MESH:
        return _mesh_obstacle(item, w, name, base)
    if kind in (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE):
        return Obstacle(kind, name, _point(item['point'], f'{w}.point', task),
                        normal=_unit(item['normal'], f'{w}.normal', task))
    if kind is ObstacleKind.SEGMENT:
        a, b = _point(item['a'], f'{w}.a', task), _point(item['b'], f'{w}.b', task)
        if np.linalg.norm(b - a) <= EPS:
            raise ConfigError(f'{w}.b: expected an end different from a = {a[:2].tolist()} '
                              f'(a segment of nonzero length), got {b[:2].tolist()}')
        return Obstacle(kind, name, a, end=b,
                        radius=as_float(item.get('radius', 0.0), f'{w}.radius', lo=0.0))
    center = _point(item['center'], f'{w}.center', task)
    if kind is ObstacleKind.BOX:
        half = as_vector(item['half_extents'], f'{w}.half_extents', 3, lo=0.0, lo_open=True)
        rpy = as_vector(item.get('rpy', [0.0, 0.0, 0.0]), f'{w}.rpy', 3)
        return Obstacle(kind, name, center, half_extents=half, rotation=rpy_matrix(rpy))
    return Obstacle(kind, name, center,
                    radius=as_float(item['radius'], f'{w}.radius', lo=0.0, lo_open=True))


def obstacles_from_config(raw: Any, where: str, task: TaskSpace, base: Path | None = None
                          ) -> tuple[Obstacle, ...]:
    """Parse the scenario's ``contacts.obstacles`` list (see the module docstring).

    ``where`` is the path of the list, e.g. ``'fig.yaml: scenario.contacts.obstacles'``; item
    ``i`` is reported as ``f'{where}[{i}]'``. Names must be unique. Raises
    :class:`~haptic_topology.errors.ConfigError`. A point grasp's linkage takes the
    obstacles of its space (``planar_point``: the planar ones). ``base``: the directory a
    mesh obstacle's relative ``file`` is relative to (the scenario file's).
    """
    task = task.rigid
    if not isinstance(raw, list):
        raise ConfigError(f'{where}: expected a list of obstacles, got {type(raw).__name__}')
    out: list[Obstacle] = []
    for i, item in enumerate(raw):
        obs = _obstacle(item, f'{where}[{i}]', i, task, base)
        if any(o.name == obs.name for o in out):
            raise ConfigError(f'{where}[{i}].name: expected a unique name, {obs.name!r} is '
                              'already used')
        out.append(obs)
    return tuple(out)


def _clamp01(x: float) -> float:
    return 0.0 if x < 0.0 else 1.0 if x > 1.0 else x


def _perpendicular(d: np.ndarray, planar: bool) -> np.ndarray:
    """A deterministic unit vector perpendicular to ``d`` (planar: in the xy plane)."""
    n = np.array([-d[1], d[0], 0.0]) if planar else np.cross(d, np.eye(3)[np.argmin(abs(d))])
    norm = float(np.linalg.norm(n))
    return n / norm if norm > EPS else np.array([1.0, 0.0, 0.0])


def _segment_params(p0: np.ndarray, d1: np.ndarray, a: np.ndarray, d2: np.ndarray
                    ) -> tuple[float, float]:
    """Parameters (s, t) of closest points of ``p0 + s d1`` and ``a + t d2`` (Ericson 5.1.9).

    Parallel segments (sin^2 of their angle < 1e-14) take the middle of their overlap along
    the link's axis (or the nearest ends if they do not overlap), so the result is symmetric.
    """
    r = p0 - a
    aa, ee, ff = float(d1 @ d1), float(d2 @ d2), float(d2 @ r)
    if aa <= EPS**2:
        return 0.0, (_clamp01(ff / ee) if ee > EPS**2 else 0.0)
    cc = float(d1 @ r)
    if ee <= EPS**2:
        return _clamp01(-cc / aa), 0.0
    bb = float(d1 @ d2)
    denom = aa * ee - bb * bb
    if denom > 1e-14 * aa * ee:
        s = _clamp01((bb * ff - cc * ee) / denom)
    else:
        ends = sorted((-cc / aa, (bb - cc) / aa))  # a and b projected on the link's axis
        lo, hi = max(ends[0], 0.0), min(ends[1], 1.0)
        s = 0.5 * (lo + hi) if lo <= hi else (0.0 if ends[1] < 0.0 else 1.0)
    t = (bb * s + ff) / ee
    if t < 0.0:
        return _clamp01(-cc / aa), 0.0
    if t > 1.0:
        return _clamp01((bb - cc) / aa), 1.0
    return s, t


def capsule_gaps(obstacle: Obstacle, p0: np.ndarray, p1: np.ndarray, radius: float,
                 capsule: Any = None) -> list[Gap]:
    """Candidate contacts ``(gap, s, normal)`` of a capsule and ``obstacle`` (world frame, m).

    The capsule has axis ``p0 -> p1`` ((3,) each; ``p0 == p1`` is a sphere) and ``radius``
    (>= 0). ``gap`` is the signed surface distance (negative: penetration depth), ``s`` in
    [0, 1] puts the contact at ``p0 + s (p1 - p0)``, ``normal`` is a unit vector from the
    obstacle towards the capsule. Half-planes and planes give one candidate per axis end
    (``s = 0`` and ``s = 1``; the distance is linear along the axis, and a link lying flat on a
    wall is supported at both ends), or one if the axis is degenerate; every other kind gives
    one candidate at the closest point. A link axis that touches or crosses an obstacle
    segment (distance < 1e-12) is deeper than the penalty model can resolve: it gets
    ``gap = -radius - obstacle.radius`` and the segment's xy perpendicular, oriented towards
    the axis midpoint.
    """
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    d = p1 - p0
    degenerate = float(np.linalg.norm(d)) <= EPS
    kind = obstacle.kind
    if kind in (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE):
        n = obstacle.normal
        ends = (0.0,) if degenerate else (0.0, 1.0)
        return [(float(n @ (p0 + s * d - obstacle.point)) - radius, s, n.copy()) for s in ends]
    if kind in (ObstacleKind.DISC, ObstacleKind.SPHERE):
        c = obstacle.point
        s = 0.0 if degenerate else _clamp01(float((c - p0) @ d) / float(d @ d))
        v = p0 + s * d - c
        dist = float(np.linalg.norm(v))
        n = v / dist if dist > EPS else _perpendicular(d, kind is ObstacleKind.DISC)
        return [(dist - obstacle.radius - radius, s, n)]
    if kind is ObstacleKind.SEGMENT:
        a, d2 = obstacle.point, obstacle.end - obstacle.point
        s, t = _segment_params(p0, d, a, d2)
        v = (p0 + s * d) - (a + t * d2)
        dist = float(np.linalg.norm(v))
        if dist > EPS:
            return [(dist - radius - obstacle.radius, s, v / dist)]
        n = _perpendicular(d2, True)
        if float(n @ (p0 + 0.5 * d - a)) < -EPS:
            n = -n
        return [(-radius - obstacle.radius, s, n)]
    return [capsule_convex_gap(*coal_geometry(obstacle), p0, p1, radius, capsule)]


@lru_cache(maxsize=256)
def coal_geometry(obstacle: Obstacle) -> tuple[Any, Any]:
    """``(shape, pose)``: a spatial obstacle as coal computes with it (a plane as a
    ``Halfspace``, a sphere, a box, a mesh's convex hull) and its placement
    (``coal.Transform3s``, world); made once per obstacle."""
    kind = obstacle.kind
    if kind is ObstacleKind.PLANE:
        n = np.array(obstacle.normal)
        return coal.Halfspace(n, float(n @ obstacle.point)), coal.Transform3s()
    pose = coal.Transform3s(np.array(obstacle.rotation), np.array(obstacle.point))
    if kind is ObstacleKind.SPHERE:
        return coal.Sphere(obstacle.radius), pose
    if kind is ObstacleKind.BOX:
        return coal.Box(*(2.0 * obstacle.half_extents)), pose
    if kind is ObstacleKind.MESH:
        assert obstacle.mesh is not None
        return obstacle.mesh.convex, pose
    raise ValueError(f'coal_geometry: a spatial obstacle, not {kind.value}')
