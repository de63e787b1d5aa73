"""Mesh collision geometry: where a mesh file is, and the convex shape coal computes with.

**Where.** A URDF ``<mesh filename=...>`` (and a ``mesh`` obstacle's ``file``) is found by
:func:`resolve_mesh`:

* ``package://NAME/REL``: ``REL`` under ``share/NAME`` of every prefix of
  ``AMENT_PREFIX_PATH`` (the ament index of a ROS install or a colcon workspace), then under
  every directory ``NAME`` found in or directly below an entry of ``ROS_PACKAGE_PATH``, then in
  an installed Python distribution ``NAME`` whose files include ``share/NAME/REL`` (wheels such
  as ``example-robot-data``), then in the nearest directory above the URDF that is named
  ``NAME`` or holds ``NAME`` (a package checked out anywhere, its URDF in ``NAME/urdf/``);
* ``file:///abs/path`` and absolute paths as they are;
* a relative path, relative to the directory of the URDF (or of the scenario file).

A file found nowhere is refused in one line naming it and every place looked at.

**What.** :func:`load_mesh` reads the file once (STL, DAE, OBJ: whatever coal's assimp loader
reads; a file it cannot read is refused in one line with coal's reason), scales it (URDF
``scale``, and a COLLADA file's ``<unit meter>``, as ROS's mesh loaders do; the file's
``up_axis`` is ignored, as they do: a URDF's meshes are z up) and keeps its **convex hull**
(``coal.Convex``, qhull): the contacts compute signed distances, witness points and normals
between the hull and each obstacle with coal's GJK/EPA.
A convex mesh is its own hull, so for convex meshes (most robots' collision meshes, made
convex for collision checking) the result is exact to coal's tolerance. A non-convex mesh is
rendered by its hull, also when apart: the contacts are a penalty model, whose force must be
the gradient of a potential continuous in the configuration to be passive (no energy
injected, eq. 1's contact terms). The hull's signed distance is continuous (1-Lipschitz in
the placement); a mesh's BVH distance while apart, with the hull's depth once touching, is not
(an obstacle in a concavity jumps from a positive distance to the hull's depth), and coal's
BVH signed distance while overlapping is per triangle, not the mesh's penetration depth. A
concave part that matters is described as several convex ``<collision>`` meshes (a convex
decomposition): each is used exactly, and the sum of their penalty forces stays passive.
"""

from __future__ import annotations

import importlib.metadata as md
import math
import os
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import coal
import numpy as np

from haptic_topology.errors import ConfigError
from haptic_topology.paths import PACKAGE_URI

FILE_URI = 'file://'


@dataclass(frozen=True, eq=False)
class MeshGeometry:
    """A mesh as the contacts use it: ``path`` (the file read), ``scale`` (3,), its convex
    hull ``convex`` (a ``coal.Convex``, in the mesh's frame, scaled, m), the hull's
    ``vertices`` (k x 3, m, mesh frame), a sphere around them (``centre`` (3,) m, mesh
    frame, and ``radius`` m) and their axis-aligned box in the mesh frame (``box_centre``
    (3,) m and ``box_half`` (3,) m): bounds that skip far pairs without a coal query."""

    path: Path
    scale: tuple[float, float, float]
    convex: Any
    vertices: np.ndarray
    centre: np.ndarray
    radius: float
    box_centre: np.ndarray
    box_half: np.ndarray


def _search_path(name: str, rel: str) -> list[Path]:
    """The ament prefixes' and ``ROS_PACKAGE_PATH``'s places of ``package://name/rel``."""
    out = []
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        out.append(Path(prefix) / 'share' / name / rel)
    for root in filter(None, os.environ.get('ROS_PACKAGE_PATH', '').split(os.pathsep)):
        r = Path(root)
        out.append(r / rel if r.name == name else r / name / rel)
    return out


def _from_distribution(name: str, rel: str, looked: list[str]) -> Path | None:
    """``share/name/rel`` among the files of the Python distribution ``name``, if any."""
    try:
        dist = md.distribution(name)
    except md.PackageNotFoundError:
        looked.append(f'no Python distribution {name!r}')
        return None
    suffix = f'share/{name}/{rel}'
    for f in dist.files or ():
        if f.as_posix().endswith(suffix):
            return Path(str(dist.locate_file(f)))
    looked.append(f'Python distribution {name} {dist.version}')
    return None


def resolve_mesh(ref: str, base: Path | None, where: str,
                 error: type[ConfigError] = ConfigError) -> Path:
    """The mesh file ``ref`` (see the module doc), relative references against ``base`` (the
    URDF's or scenario's directory; None: the working directory). ``where``: the field or
    element, for the error, raised as ``error`` in one line naming the file and where it
    looked."""
    looked: list[str] = []
    if ref.startswith(PACKAGE_URI):
        name, _, rel = ref[len(PACKAGE_URI):].partition('/')
        if not name or not rel:
            raise error(f'{where}: expected package://NAME/PATH, got {ref!r}')
        for c in _search_path(name, rel):
            if c.is_file():
                return c
            looked.append(str(c))
        for var in ('AMENT_PREFIX_PATH', 'ROS_PACKAGE_PATH'):
            if not os.environ.get(var):
                looked.append(f'{var} unset')
        found = _from_distribution(name, rel, looked)
        if found is not None:
            return found
        for parent in ((base, *base.parents) if base is not None else ()):
            if parent.name == name or (parent / name).is_dir():
                c = parent / rel if parent.name == name else parent / name / rel
                if c.is_file():
                    return c
                looked.append(str(c))
                break
    else:
        path = Path(ref[len(FILE_URI):] if ref.startswith(FILE_URI) else ref)
        if not path.is_absolute():
            path = (base if base is not None else Path.cwd()) / path
        if path.is_file():
            return path
        looked.append(str(path))
    raise error(f'{where}: mesh file {ref!r} not found (looked in: {"; ".join(looked)})')


def load_mesh(path: Path, scale: tuple[float, float, float], where: str,
              error: type[ConfigError] = ConfigError) -> MeshGeometry:
    """The mesh at ``path`` scaled by ``scale`` and its convex hull (see the module doc),
    read once per file and scale. A file coal cannot read, or whose hull has no volume, is
    refused in one line (raised as ``error``, naming ``where`` and the file)."""
    try:
        st = path.stat()
    except OSError:
        raise error(f'{where}: mesh file {path} not found') from None
    try:
        return _load(str(path), st.st_size, st.st_mtime_ns, scale)
    except ConfigError as exc:
        raise error(f'{where}: {exc}') from None


def _collada_unit(path: str) -> float:
    """The length unit of a COLLADA file in metres (``<asset><unit meter="..."/>``, 1 without
    one), which coal's loader does not apply and ROS's mesh loaders (rviz, MoveIt) do.
    A file that is no XML is left to coal to refuse; a unit that is no number > 0 is refused
    here (ConfigError)."""
    try:
        for _, element in ElementTree.iterparse(path):
            tag = element.tag.rsplit('}', 1)[-1]
            if tag == 'unit':
                text = element.get('meter', '1')
                try:
                    meter = float(text)
                except ValueError:
                    meter = math.nan
                if not (math.isfinite(meter) and meter > 0.0):
                    raise ConfigError(f'the mesh {path}: <unit meter="{text}">: expected a '
                                      f'number > 0 (metres per unit of the file)')
                return meter
            if tag == 'asset':      # the file's first asset has no unit: metres
                return 1.0
    except ElementTree.ParseError:
        pass
    return 1.0


@lru_cache(maxsize=64)
def _load(path: str, size: int, mtime_ns: int, scale: tuple[float, float, float]
          ) -> MeshGeometry:
    """:func:`load_mesh` of one file version (raises ConfigError, its message without the
    field)."""
    unit = _collada_unit(path) if path.lower().endswith('.dae') else 1.0
    try:
        bvh = coal.MeshLoader().load(path, unit * np.array(scale, dtype=float))
    except (ValueError, RuntimeError) as exc:
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        reason = next((ln for ln in lines[1:] if not ln.startswith(
            ('From file', 'in function', 'at line', 'message', 'Hint'))), lines[-1] if lines
            else type(exc).__name__)
        raise ConfigError(f'coal cannot read the mesh {path} ({reason})') from None
    if bvh.num_vertices < 4:
        raise ConfigError(f'the mesh {path} has {bvh.num_vertices} vertices; expected a '
                          f'solid (at least 4 vertices not in one plane)')
    try:
        bvh.buildConvexHull(True, 'Qt')
    except (ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f'the mesh {path} has no convex hull with volume ({first})'
                          ) from None
    convex = bvh.convex
    vertices = np.array(convex.points(), dtype=float).reshape(-1, 3)
    vertices.setflags(write=False)
    centre = vertices.mean(axis=0)
    radius = float(np.max(np.linalg.norm(vertices - centre, axis=1)))
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return MeshGeometry(Path(path), scale, convex, vertices, centre, radius, 0.5 * (lo + hi),
                        0.5 * (hi - lo))


#: GJK and EPA tolerance (m) of every coal query of the contacts: far below the contact
#: model's resolution (a 1e-10 m error of depth is 2e-7 N at k = 2000 N/m).
COAL_TOLERANCE = 1e-10


def distance_request() -> Any:
    """A coal signed-distance request with tolerance ``COAL_TOLERANCE`` and no cached guess
    (every query is independent of the previous one, so runs repeat exactly)."""
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    req.gjk_tolerance = COAL_TOLERANCE
    req.epa_tolerance = COAL_TOLERANCE
    return req


_REQUEST = distance_request()
_EYE = np.eye(3)


def _pin_coal_box() -> bool:
    """Fix the shape of coal's ``Box`` for this process, the same in every process; True
    when it is the one every run uses.

    coal 3.0's box support function (``getShapeSupport(const Box*, ...)``) scales the half
    extents on the side away from the query direction by a ``static const inflate``,
    initialised on the process's first box support call: ``1 + 1e-10`` if that call's
    direction has a zero component, 1 otherwise. So the first box query a process makes fixes
    every later box query's witness points and normals in their last bits, and a scenario's
    run depended on which scenarios ran before it in the process. This query, made on import
    before any of the contacts' queries, has a direction with zero components (coal's default
    first direction (1, 0, 0) on a box at the identity): every process renders boxes with
    ``inflate = 1 + 1e-10`` (5e-12 m on a 5 cm box's far side), the box a process gets whose
    first box query is axis-aligned, as the contact scenarios' first queries are. If coal made
    a box query before this module was imported (another library, the caller's own code), the
    box may already be the other one: warned, as results then differ from a fresh process's
    in their last bits."""
    res = coal.DistanceResult()
    # two 2 m cubes 1 m apart along x: 1 - 1e-10 m with the inflated box, else 1 m
    dist = coal.distance(coal.Box(2.0, 2.0, 2.0), coal.Transform3s(), coal.Box(2.0, 2.0, 2.0),
                         coal.Transform3s(_EYE, np.array([-3.0, 0.0, 0.0])),
                         coal.DistanceRequest(), res)
    if dist < 1.0 - 0.5e-10:
        return True
    warnings.warn('coal made a box query before haptic_topology.model.meshes was imported '
                  'and so fixed its box shape otherwise (coal 3.0: a static in the box '
                  'support function): contacts with boxes differ in their last bits from a '
                  'fresh process; import haptic_topology.model.meshes before using coal',
                  RuntimeWarning, stacklevel=2)
    return False


#: Whether this process renders coal boxes as every fresh process does: coal 3.0 takes its
#: box's shape from the first box query of a process, and this module makes that query on
#: import (False, warned: coal had made one before).
COAL_BOX_PINNED = _pin_coal_box()


def capsule_shape(radius: float, length: float) -> Any:
    """coal's capsule of ``radius`` and ``length`` (m; a sphere below 1e-12 m). A link's
    capsule is rigid: the contacts make its shape once (making one costs ten queries)."""
    return coal.Sphere(radius) if length <= 1e-12 else coal.Capsule(radius, length)


def capsule_convex_gap(geometry: Any, pose: Any, p0: np.ndarray, p1: np.ndarray,
                       radius: float, capsule: Any = None) -> tuple[float, float, np.ndarray]:
    """``(gap, s, normal)`` of the capsule ``p0 -> p1`` of ``radius`` (m, world) and the coal
    shape ``geometry`` placed at ``pose`` (a ``coal.Transform3s``): the signed distance, the
    contact at ``p0 + s (p1 - p0)`` on the axis (the projection of coal's witness point) and
    the unit normal from the shape towards the capsule. ``capsule``: the capsule's coal
    shape (:func:`capsule_shape`) if made already."""
    ax, ay, az = (float(v) for v in p0)
    bx, by, bz = (float(v) for v in p1)
    dx, dy, dz = bx - ax, by - ay, bz - az
    length2 = dx * dx + dy * dy + dz * dz
    length = math.sqrt(length2)
    if capsule is None:
        capsule = capsule_shape(radius, length)
    rot = _EYE
    if length > 1e-12:
        # the capsule's frame: z along the axis, x across it (scalar arithmetic: a numpy
        # cross product costs more than coal's query)
        zx, zy, zz = dx / length, dy / length, dz / length
        k = min(range(3), key=(abs(zx), abs(zy), abs(zz)).__getitem__)
        ex, ey, ez = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))[k]
        xx, xy, xz = zy * ez - zz * ey, zz * ex - zx * ez, zx * ey - zy * ex
        n = math.sqrt(xx * xx + xy * xy + xz * xz)
        xx, xy, xz = xx / n, xy / n, xz / n
        rot = np.array([[xx, zy * xz - zz * xy, zx],
                        [xy, zz * xx - zx * xz, zy],
                        [xz, zx * xy - zy * xx, zz]])
    res = coal.DistanceResult()
    dist = coal.distance(capsule, coal.Transform3s(rot, np.array(
        [0.5 * (ax + bx), 0.5 * (ay + by), 0.5 * (az + bz)])), geometry, pose, _REQUEST, res)
    s = 0.0
    if length > 1e-12:
        wx, wy, wz = res.getNearestPoint1().tolist()
        s = min(max(((wx - ax) * dx + (wy - ay) * dy + (wz - az) * dz) / length2, 0.0), 1.0)
    # coal's normal points from the first shape (the capsule) to the second
    return float(dist), s, -np.array(res.normal)
