"""Serial-linkage description: the :class:`Linkage` and its YAML form (the link types are in
:mod:`~haptic_topology.model.links`, the URDF import in :mod:`~haptic_topology.model.urdf_import`,
the Pinocchio model with the grasp frame in :mod:`~haptic_topology.model.build`).

A linkage is a chain of ``d`` links, each moved by one joint (revolute or prismatic) relative to
the previous link. The user grasps one link at a point of it (default: the link's centre of
mass, COM); that grasp frame is where the hand Jacobian ``J_h`` of eq. 1 and eq. 7 is taken.

Frames and units: SI throughout (m, kg, kg m^2, rad). Link ``i``'s frame sits at joint ``i``.
In a *planar* linkage every revolute joint turns about the world z axis, every prismatic joint
slides in the xy plane (default: along its link's x axis), and the task space is (x, y, theta)
of the grasp frame; a link's next joint sits ``length`` along its x axis unless an ``origin``
places it (rotations about z only). In a *spatial* linkage joint axes and placements are given
explicitly and the task space is the 6-D twist (v, w) of the grasp frame. A planar linkage
read from a URDF is checked joint by joint (axis, origin rpy) and refused if it is not planar.

YAML layout (``config/linkages/table1_planar3.yaml`` is the paper's Table I)::

    linkage:
      name: table1_planar3
      task: planar              # planar | spatial | planar_point | spatial_point
      gravity: [0.0, 0.0, 0.0]  # m/s^2, world frame
      links:
        - {name: link1, joint: revolute, length: 0.042, mass: 3.0, inertia: 0.015}
        ...
      grasp: {link: link3}      # point: [x, y, z] in the link frame, default the COM
      constraints: {rank_tolerance: 0.05, blend: 0.0, penalty_direction: nullspace}
      loops: [...]              # optional loop closures, see haptic_topology.model.loops

Per link: ``com`` (default ``[length/2, 0, 0]``), ``inertia`` about the COM (planar: the scalar
Izz; spatial: ``[ixx, iyy, izz]``, ``[ixx, iyy, izz, ixy, ixz, iyz]`` or a 3x3 list),
``axis`` (joint axis in the link frame; default z, planar prismatic x) and ``origin``
(``{xyz: [...], rpy: [...]}``: placement of this joint in the previous link's frame, default
``xyz = [previous length, 0, 0]``).

Instead of ``links``, ``robot: NAME`` takes a robot of example-robot-data by name (an optional
extra, :mod:`~haptic_topology.model.robots`; spatial, named NAME unless ``name`` says
otherwise, with its SRDF), and ``urdf: file.urdf`` reads the chain from a URDF (a path relative
to the YAML file, or ``package://NAME/PATH`` for a file of an installed package, see
``haptic_topology.paths.resolve_package_uri``; with it, ``srdf: file.srdf`` (the same kinds of
path) gives the collision pairs the robot disables, ``Linkage.disabled_collisions``; ``revolute``,
``continuous``, ``prismatic`` and ``fixed`` joints; fixed links are merged into their parent).
A URDF tree is reduced to the serial chain from the root through the grasped link, continued
beyond it until the tree first branches; every other joint is locked at ``locked_joints:
{name: position}`` (rad or m, default 0) with its mass kept (Pinocchio ``buildReducedModel``),
and ``Linkage.notes`` says in one line what was locked. A bare ``.urdf`` file loads as
spatial unless it holds ``<haptic_topology task="planar"/>`` under ``<robot>``.

The default characteristic length (``constraints.characteristic_length``, m) is the reach: the
sum of the distances between successive joints plus the extent of the last link (the largest
of its ``length``, the distance of the farthest frame fixed to it in a URDF, and the grasp
point's distance from the last joint when the last link is grasped). An explicit value 100
times larger or smaller than the reach is warned about (a unit mismatch, e.g. mm vs m).
"""

from __future__ import annotations

import enum
import logging
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.model.build import LinkageModel, build_model
from haptic_topology.model.links import CollisionShape, JointType, LinkSpec
from haptic_topology.model.loops import LoopClosure, parse_loops
from haptic_topology.model.robots import ROBOT_PREFIX, read_srdf, robot_files
from haptic_topology.model.urdf_import import UrdfSource, links_from_urdf, read_urdf
from haptic_topology.paths import PACKAGE_URI, resolve_package_uri
from haptic_topology.validate import (
    as_angles,
    as_float,
    as_str,
    as_vector,
    check_keys,
    load_yaml,
)
from haptic_topology.vocabulary import TASK_NAMES, TaskSpace

_LOG = logging.getLogger(__name__)


class PenaltyDirection(enum.Enum):
    """Along which directions the penalty of eq. 13 acts (see dynamics.constraints)."""

    NULLSPACE = 'nullspace'   # an orthonormal basis of N(J_h^T), as the paper writes eq. 13
    WEIGHTED = 'weighted'     # W^-1 U_w diag(w) U_w^T W: the L_c-weighted projector (before #12)


@dataclass(frozen=True)
class ConstraintSettings:
    """How directions of topological constraint are decided (see dynamics.constraints).

    ``characteristic_length`` L_c (m) weights the rotational rows of ``J_h`` so that its
    singular values are all lengths; ``rank_tolerance`` is the fraction of L_c below which a
    weighted singular value counts as zero; ``blend`` > 0 ramps the penalty weight of a
    direction continuously from 1 at ``rank_tolerance`` to 0 at ``rank_tolerance*(1+blend)``;
    ``penalty_direction`` chooses the directions the penalty of eq. 13 acts along (L_c only
    decides the rank with ``nullspace``, the default).
    """

    characteristic_length: float
    rank_tolerance: float = 0.05
    blend: float = 0.0
    penalty_direction: PenaltyDirection = PenaltyDirection.NULLSPACE


@dataclass(frozen=True)
class Linkage:
    """A validated serial-linkage description with its grasp."""

    name: str
    task: TaskSpace
    links: tuple[LinkSpec, ...]
    gravity: np.ndarray                 # (3,) m/s^2, world frame
    grasp_link: str
    grasp_point: np.ndarray             # (3,) m, in the grasped link's frame
    constraints: ConstraintSettings
    urdf_path: Path | None = None
    source: str = '<memory>'
    notes: tuple[str, ...] = ()         # one line each: what loading did (URDF joints locked)
    #: The URDF the chain was read from, as read once (None: a YAML chain).
    urdf: UrdfSource | None = None
    #: Loop closures (:mod:`~haptic_topology.model.loops`): empty for a serial linkage.
    loops: tuple[LoopClosure, ...] = ()
    #: Link pairs (names, each pair sorted) whose collisions the SRDF disables
    #: (:func:`~haptic_topology.model.robots.read_srdf`), left out of the self-collisions
    #: (:mod:`~haptic_topology.dynamics.self_contacts`).
    disabled_collisions: tuple[tuple[str, str], ...] = ()

    @property
    def dof(self) -> int:
        """Number of joints d."""
        return len(self.links)

    @property
    def link_names(self) -> tuple[str, ...]:
        return tuple(link.name for link in self.links)

    def with_grasp(self, link: str, point: np.ndarray | None = None) -> Linkage:
        """Same linkage grasped at ``link`` (default point: that link's COM)."""
        names = self.link_names
        if link not in names:
            raise LinkageError(
                f'{self.source}: grasp.link: unknown link {link!r} (expected one of: '
                f'{", ".join(names)})')
        spec = self.links[names.index(link)]
        p = spec.com.copy() if point is None else np.asarray(point, dtype=float).reshape(3)
        return replace(self, grasp_link=link, grasp_point=p)


_LINK_KEYS = ('name', 'joint', 'length', 'mass', 'com', 'inertia', 'axis', 'origin')


def _inertia_matrix(value: Any, task: TaskSpace, where: str) -> np.ndarray:
    """Parse a link inertia about its COM and check it is symmetric positive definite."""
    if task.planar and isinstance(value, (int, float)) and not isinstance(
            value, bool):
        izz = as_float(value, where, lo=0.0, lo_open=True, error=LinkageError)
        # Only Izz acts in planar motion; the others are set equal so the tensor is valid.
        return np.eye(3) * izz
    if isinstance(value, list) and value and isinstance(value[0], list):
        rows = [as_vector(r, f'{where}[{i}]', 3, error=LinkageError)
                for i, r in enumerate(value)]
        if len(rows) != 3:
            raise LinkageError(f'{where}: expected a 3x3 matrix, got {len(rows)} rows')
        inertia = np.array(rows)
    else:
        expected = ('a positive number (Izz) or ' if task.planar else '') + \
            '[ixx, iyy, izz], [ixx, iyy, izz, ixy, ixz, iyz] or a 3x3 list'
        if not isinstance(value, list) or len(value) not in (3, 6):
            raise LinkageError(f'{where}: expected {expected}, got {value!r}')
        v = as_vector(value, where, len(value), error=LinkageError)
        ixy, ixz, iyz = (v[3], v[4], v[5]) if len(v) == 6 else (0.0, 0.0, 0.0)
        inertia = np.array([[v[0], ixy, ixz], [ixy, v[1], iyz], [ixz, iyz, v[2]]])
    if not np.allclose(inertia, inertia.T, atol=1e-12):
        raise LinkageError(f'{where}: inertia must be symmetric, got {inertia.tolist()}')
    eig = np.linalg.eigvalsh(inertia)
    if eig.min() <= 0.0:
        raise LinkageError(
            f'{where}: inertia must be positive definite, got eigenvalues {eig.tolist()}')
    return inertia


def _parse_link(raw: Any, i: int, task: TaskSpace, where: str) -> LinkSpec:
    w = f'{where}.links[{i}]'
    check_keys(raw, w, required=('joint', 'length', 'mass', 'inertia'),
               optional=('name', 'com', 'axis', 'origin'), error=LinkageError)
    name = as_str(raw.get('name', f'link{i + 1}'), f'{w}.name', error=LinkageError)
    joint = JointType(as_str(raw['joint'], f'{w}.joint', ('revolute', 'prismatic'),
                             error=LinkageError))
    length = as_float(raw['length'], f'{w}.length', lo=0.0, error=LinkageError)
    mass = as_float(raw['mass'], f'{w}.mass', lo=0.0, lo_open=True, error=LinkageError)
    com = (as_vector(raw['com'], f'{w}.com', 3, error=LinkageError) if 'com' in raw
           else np.array([length / 2.0, 0.0, 0.0]))
    inertia = _inertia_matrix(raw['inertia'], task, f'{w}.inertia')
    if task.planar and com[2] != 0.0:
        raise LinkageError(f'{w}.com: z must be 0 for a planar linkage, got {com[2]}')
    default_axis = [1.0, 0.0, 0.0] if (task.planar
                                       and joint is JointType.PRISMATIC) else [0.0, 0.0, 1.0]
    axis = as_vector(raw.get('axis', default_axis), f'{w}.axis', 3, error=LinkageError)
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:
        raise LinkageError(f'{w}.axis: expected a non-zero vector, got {axis.tolist()}')
    origin_xyz: np.ndarray | None = None
    origin_rpy = np.zeros(3)
    if 'origin' in raw:
        o = check_keys(raw['origin'], f'{w}.origin', optional=('xyz', 'rpy'),
                       error=LinkageError)
        if 'xyz' in o:
            origin_xyz = as_vector(o['xyz'], f'{w}.origin.xyz', 3, error=LinkageError)
        if 'rpy' in o:
            origin_rpy = as_angles(o['rpy'], f'{w}.origin.rpy', 3, error=LinkageError)
    return LinkSpec(name, joint, length, mass, com, inertia, axis / norm, origin_xyz,
                    origin_rpy)


_PLANAR_TOL = 1e-9


def _check_planar(links: tuple[LinkSpec, ...], where: str) -> None:
    """Refuse a linkage that does not move in the xy plane, naming the joint and field.

    Planar (eq. 8's 3-DOF task): every joint placement rotates about z only (so every link
    frame keeps the world z axis), revolute axes are parallel to z and prismatic axes lie in
    the xy plane. Offsets along z are allowed: they move nothing out of the plane.
    """
    for i, link in enumerate(links):
        name = f'{where}: joint {link.joint_label!r} (links[{i}] {link.name!r})'
        rot = pin.rpy.rpyToMatrix(*link.origin_rpy)
        if rot[2, 2] < 1.0 - _PLANAR_TOL:
            raise LinkageError(
                f'{name}: origin rpy {np.round(link.origin_rpy, 6).tolist()} tilts the joint '
                'off the world z axis; a planar linkage needs rpy = [0, 0, yaw]')
        axis = link.axis
        if link.joint is JointType.REVOLUTE and abs(axis[2]) < 1.0 - _PLANAR_TOL:
            raise LinkageError(
                f'{name}: axis {np.round(axis, 6).tolist()} must be parallel to z for a planar '
                'linkage (revolute joints turn in the xy plane: axis [0, 0, +-1])')
        if link.joint is JointType.PRISMATIC and abs(axis[2]) > _PLANAR_TOL:
            raise LinkageError(
                f'{name}: axis {np.round(axis, 6).tolist()} must lie in the xy plane for a '
                'planar linkage (prismatic joints slide in the plane: axis [x, y, 0])')


_UNIT_RATIO = 100.0


def _parse_constraints(raw: Any, where: str, reach: float) -> ConstraintSettings:
    """``constraints:`` block; ``reach`` (m) is the default characteristic length.

    Warns (``UserWarning``) when an explicit characteristic length is 100 times larger or
    smaller than the reach: the lengths and L_c are then almost surely in different units.
    """
    check_keys(raw, where, optional=('characteristic_length', 'rank_tolerance', 'blend',
                                     'penalty_direction'), error=LinkageError)
    length = as_float(raw.get('characteristic_length', reach if reach > 0.0 else 1.0),
                      f'{where}.characteristic_length', lo=0.0, lo_open=True,
                      error=LinkageError)
    if 'characteristic_length' in raw and reach > 0.0:
        ratio = max(length / reach, reach / length)
        if ratio >= _UNIT_RATIO:
            warnings.warn(
                f'{where}.characteristic_length = {length:g} m is {ratio:.0f}x '
                f'{"larger" if length > reach else "smaller"} than the linkage\'s reach '
                f'{reach:g} m: are the link lengths and characteristic_length in the same '
                'unit (m)? The rank decision of eq. 13 depends on it', UserWarning,
                stacklevel=4)
    tol = as_float(raw.get('rank_tolerance', 0.05), f'{where}.rank_tolerance', lo=0.0,
                   lo_open=True, hi=1.0, error=LinkageError)
    blend = as_float(raw.get('blend', 0.0), f'{where}.blend', lo=0.0, hi=100.0,
                     error=LinkageError)
    direction = PenaltyDirection(as_str(
        raw.get('penalty_direction', PenaltyDirection.NULLSPACE.value),
        f'{where}.penalty_direction', tuple(d.value for d in PenaltyDirection),
        error=LinkageError))
    return ConstraintSettings(length, tol, blend, direction)


def reach(links: tuple[LinkSpec, ...], grasp_link: str | None = None,
          grasp_point: np.ndarray | None = None) -> float:
    """Reach of the chain (m): the default characteristic length L_c.

    Sum of the distances between successive joints (constant: joint i sits at
    ``origin_xyz`` in the frame of link i-1, whose origin is joint i-1) plus the extent of the
    last link: the larger of its ``length`` and, when the last link is grasped, the grasp
    point's distance from the last joint. Table I: 0.042 + 0.042 + 0.030 = 0.114 m.
    """
    total = sum(_placement_offset(links, i) for i in range(1, len(links)))
    last = links[-1].length
    if grasp_point is not None and grasp_link == links[-1].name:
        last = max(last, float(np.linalg.norm(grasp_point)))
    return float(total + last)


def linkage_from_dict(doc: Any, source: str = '<memory>') -> Linkage:
    """Validate a parsed YAML document (top-level key ``linkage``) into a :class:`Linkage`.

    Raises:
        LinkageError: naming ``source`` and the offending field.
    """
    top = check_keys(doc, source, required=('linkage',), error=LinkageError)
    where = f'{source}: linkage'
    raw = check_keys(top['linkage'], where,
                     optional=('name', 'task', 'gravity', 'links', 'grasp', 'constraints',
                               'urdf', 'srdf', 'robot', 'locked_joints', 'loops'),
                     error=LinkageError)
    if 'robot' in raw:      # a robot of example-robot-data by name: its URDF, spatial
        if 'urdf' in raw or 'links' in raw or 'srdf' in raw:
            raise LinkageError(f'{where}: give one of robot, urdf and links (a robot brings '
                               'its own SRDF)')
        robot = as_str(raw['robot'], f'{where}.robot', error=LinkageError)
        urdf_uri, srdf_uri = robot_files(robot, f'{where}.robot')
        raw = {'name': robot, 'task': 'spatial', **raw, 'urdf': urdf_uri}
        if srdf_uri is not None:
            raw['srdf'] = srdf_uri
        del raw['robot']
    if 'srdf' in raw and 'urdf' not in raw:
        raise LinkageError(f'{where}.srdf: only allowed with urdf (it names the URDF\'s links)')
    name = as_str(raw.get('name', Path(source).stem), f'{where}.name', error=LinkageError)
    task = TaskSpace(as_str(raw.get('task', 'planar'), f'{where}.task', TASK_NAMES,
                            error=LinkageError))
    gravity = as_vector(raw.get('gravity', [0.0, 0.0, 0.0]), f'{where}.gravity', 3,
                        error=LinkageError)
    grasp = check_keys(raw.get('grasp', {}), f'{where}.grasp', optional=('link', 'point'),
                       error=LinkageError)
    wanted_grasp = (as_str(grasp['link'], f'{where}.grasp.link', error=LinkageError)
                    if 'link' in grasp else None)
    urdf_path: Path | None = None
    urdf: UrdfSource | None = None
    notes: tuple[str, ...] = ()
    disabled: tuple[tuple[str, str], ...] = ()
    if 'urdf' in raw:
        if 'links' in raw:
            raise LinkageError(f'{where}: give either links or urdf, not both')
        urdf_path = _file_ref(raw['urdf'], f'{where}.urdf', source)
        locks = raw.get('locked_joints', {})
        if not isinstance(locks, dict):
            raise LinkageError(f'{where}.locked_joints: expected a mapping joint name -> '
                               f'position (rad or m), got {locks!r}')
        locked = {str(k): as_float(v, f'{where}.locked_joints.{k}', error=LinkageError)
                  for k, v in locks.items()}
        urdf = read_urdf(urdf_path)
        links, notes = links_from_urdf(urdf, wanted_grasp, locked, f'{where}.locked_joints')
        urdf = replace(urdf, locked=tuple(locked.items()))
        if 'srdf' in raw:
            disabled = read_srdf(_file_ref(raw['srdf'], f'{where}.srdf', source),
                                 urdf.link_names, f'{where}.srdf')
    else:
        if 'locked_joints' in raw:
            raise LinkageError(f'{where}.locked_joints: only allowed with urdf (a YAML chain '
                               'has no side branches)')
        if 'links' not in raw:
            raise LinkageError(f'{where}.links: missing required key (or give urdf)')
        raw_links = raw['links']
        if not isinstance(raw_links, list) or not raw_links:
            raise LinkageError(f'{where}.links: expected a non-empty list of links, got '
                               f'{raw_links!r}')
        links = tuple(_parse_link(r, i, task, where) for i, r in enumerate(raw_links))
    names = [link.name for link in links]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise LinkageError(f'{where}.links: duplicate link names {sorted(dup)}')
    if task.planar:
        _check_planar(links, str(urdf_path) if urdf_path is not None else f'{where}.links')
    grasp_link = wanted_grasp if wanted_grasp is not None else names[-1]
    if grasp_link not in names:
        raise LinkageError(f'{where}.grasp.link: unknown link {grasp_link!r} (expected one '
                           f'of: {", ".join(names)})')
    point = (as_vector(grasp['point'], f'{where}.grasp.point', 3, error=LinkageError)
             if 'point' in grasp else links[names.index(grasp_link)].com.copy())
    if task.planar and urdf_path is None and point[2] != 0.0:
        raise LinkageError(f'{where}.grasp.point: z must be 0 for a planar linkage')
    constraints = _parse_constraints(raw.get('constraints', {}), f'{where}.constraints',
                                     reach(links, grasp_link, point))
    loops = (parse_loops(raw['loops'], f'{where}.loops', task, tuple(names))
             if 'loops' in raw else ())
    for note in notes:
        _LOG.info(note)
    linkage = Linkage(name, task, links, gravity, grasp_link, point, constraints, urdf_path,
                      source, notes, urdf, loops, disabled)
    build_model(linkage)  # fail now, not later, on anything Pinocchio rejects
    return linkage


def _file_ref(ref: Any, where: str, source: str) -> Path:
    """A ``urdf:`` or ``srdf:`` file: ``package://NAME/PATH``, or a path relative to the YAML
    file ``source``."""
    text = as_str(ref, where, error=LinkageError)
    if text.startswith(PACKAGE_URI):
        return resolve_package_uri(text, where, LinkageError)
    path = Path(text)
    if not path.is_absolute() and source != '<memory>':
        path = Path(source).parent / path
    return path


def load_linkage(path: str | Path) -> Linkage:
    """Load a linkage from a YAML description, a bare URDF file, or ``robot:NAME`` (a robot
    of example-robot-data: :mod:`~haptic_topology.model.robots`).

    A bare URDF is spatial unless ``<robot>`` holds ``<haptic_topology task="planar"/>``;
    the grasp (of a robot too) is the COM of the last link of its serial chain.
    """
    if isinstance(path, str) and path.startswith(ROBOT_PREFIX):
        return linkage_from_dict({'linkage': {'robot': path[len(ROBOT_PREFIX):]}}, path)
    p = Path(path)
    if p.suffix.lower() == '.urdf':
        task = read_urdf(p).task or TaskSpace.SPATIAL
        return linkage_from_dict({'linkage': {'task': task.value, 'urdf': str(p.resolve()),
                                              'name': p.stem}}, str(p))
    try:
        doc = load_yaml(p, error=LinkageError)
    except LinkageError:
        raise
    except ConfigError as exc:  # pragma: no cover - load_yaml raises the given class
        raise LinkageError(str(exc)) from None
    return linkage_from_dict(doc, str(p))


def _placement_offset(links: tuple[LinkSpec, ...], i: int) -> float:
    """Distance (m) from joint i-1 to joint i, used for the default characteristic length."""
    xyz = links[i].origin_xyz
    if xyz is not None:
        return float(np.linalg.norm(xyz))
    return links[i - 1].length


def to_dict(linkage: Linkage) -> dict[str, Any]:
    """The inverse of :func:`linkage_from_dict` for YAML-described linkages (for bags/tests)."""
    links = []
    for link in linkage.links:
        entry: dict[str, Any] = {
            'name': link.name, 'joint': link.joint.value, 'length': link.length,
            'mass': link.mass, 'com': link.com.tolist()}
        planar = linkage.task.planar
        if planar and np.array_equal(link.inertia, np.eye(3) * link.inertia[2, 2]):
            entry['inertia'] = float(link.inertia[2, 2])
        else:
            entry['inertia'] = link.inertia.tolist()
        default_axis = [1.0, 0.0, 0.0] if (planar and link.joint is JointType.PRISMATIC) \
            else [0.0, 0.0, 1.0]
        if not planar or not np.array_equal(link.axis, default_axis):
            entry['axis'] = link.axis.tolist()
        if not planar or link.origin_xyz is not None or np.any(link.origin_rpy):
            origin: dict[str, Any] = {'rpy': link.origin_rpy.tolist()}
            if link.origin_xyz is not None:
                origin['xyz'] = link.origin_xyz.tolist()
            entry['origin'] = origin
        links.append(entry)
    c = linkage.constraints
    return {'linkage': {
        'name': linkage.name, 'task': linkage.task.value, 'gravity': linkage.gravity.tolist(),
        'links': links,
        'grasp': {'link': linkage.grasp_link, 'point': linkage.grasp_point.tolist()},
        'constraints': {'characteristic_length': c.characteristic_length,
                        'rank_tolerance': c.rank_tolerance, 'blend': c.blend,
                        'penalty_direction': c.penalty_direction.value},
        **({'loops': [lp.to_dict() for lp in linkage.loops]} if linkage.loops else {})}}


__all__ = ['CollisionShape', 'ConstraintSettings', 'JointType', 'LinkSpec', 'Linkage',
           'LinkageModel',
           'PenaltyDirection', 'TaskSpace', 'build_model', 'linkage_from_dict', 'load_linkage',
           'reach', 'serial_chain', 'serial_chain_dict', 'to_dict']


def serial_chain_dict(n: int, task: TaskSpace = TaskSpace.PLANAR, length: float = 0.05,
                      mass: float = 0.5) -> dict[str, Any]:
    """The linkage YAML document (as a dict) of :func:`serial_chain`: write it with
    ``yaml.safe_dump`` to get a linkage file of the chain."""
    if n < 1:
        raise LinkageError(f'serial_chain: n must be >= 1, got {n}')
    inertia = mass * length * length / 12.0 + 1e-6
    links = []
    for i in range(n):
        entry: dict[str, Any] = {'name': f'link{i + 1}', 'joint': 'revolute', 'length': length,
                                 'mass': mass}
        if task.planar:
            entry['inertia'] = inertia
        else:
            entry['inertia'] = [1e-6 + mass * 1e-4, inertia, inertia]
            entry['axis'] = [[0, 0, 1], [0, 1, 0], [1, 0, 0]][i % 3]
        links.append(entry)
    return {'linkage': {'name': f'chain{n}_{task.value}', 'task': task.value, 'links': links}}


def serial_chain(n: int, task: TaskSpace = TaskSpace.PLANAR, length: float = 0.05,
                 mass: float = 0.5) -> Linkage:
    """A uniform n-link chain of revolute joints grasped at the distal COM (benchmarks, tests).

    Planar: all joints about z. Spatial: joint axes alternate z, y, x so the chain moves in 3-D.
    """
    return linkage_from_dict(serial_chain_dict(n, task, length, mass), f'<serial_chain {n}>')
