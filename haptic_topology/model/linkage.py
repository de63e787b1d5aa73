"""Serial-linkage description (YAML or URDF) and its Pinocchio model with the grasp frame.

A linkage is a chain of ``d`` links, each moved by one joint (revolute or prismatic) relative to
the previous link. The user grasps one link at a point of it (default: the link's centre of
mass, COM); that grasp frame is where the hand Jacobian ``J_h`` of eq. 1 and eq. 7 is taken.

Frames and units: SI throughout (m, kg, kg m^2, rad). Link ``i``'s frame sits at joint ``i``.
In a *planar* linkage every revolute joint turns about the world z axis, every prismatic joint
slides along its link's x axis, and the task space is (x, y, theta) of the grasp frame; a link's
next joint sits ``length`` along its x axis. In a *spatial* linkage joint axes and placements
are given explicitly and the task space is the 6-D twist (v, w) of the grasp frame.

YAML layout (``config/linkages/table1_planar3.yaml`` is the paper's Table I)::

    linkage:
      name: table1_planar3
      task: planar              # planar | spatial
      gravity: [0.0, 0.0, 0.0]  # m/s^2, world frame
      links:
        - {name: link1, joint: revolute, length: 0.042, mass: 3.0, inertia: 0.015}
        ...
      grasp: {link: link3}      # point: [x, y, z] in the link frame, default the COM
      constraints: {rank_tolerance: 0.05, blend: 0.0}   # see dynamics.constraints

Per link: ``com`` (default ``[length/2, 0, 0]``), ``inertia`` about the COM (planar: the scalar
Izz; spatial: ``[ixx, iyy, izz]``, ``[ixx, iyy, izz, ixy, ixz, iyz]`` or a 3x3 list),
spatial only: ``axis`` (joint axis in the link frame, default z) and ``origin``
(``{xyz: [...], rpy: [...]}``: placement of this joint in the previous link's frame, default
``xyz = [previous length, 0, 0]``).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.validate import (
    as_float,
    as_str,
    as_vector,
    check_keys,
    load_yaml,
)


class TaskSpace(enum.Enum):
    """Dimension of the hand's rigid-body motion: planar (3-DOF) or spatial (6-DOF)."""

    PLANAR = 'planar'
    SPATIAL = 'spatial'

    @property
    def dim(self) -> int:
        """Task dimension m: 3 planar (vx, vy, wz), 6 spatial (vx, vy, vz, wx, wy, wz)."""
        return 3 if self is TaskSpace.PLANAR else 6

    @property
    def translation_rows(self) -> slice:
        """Rows of a task vector that are translations (m, m/s, N); the others are rotations."""
        return slice(0, 2) if self is TaskSpace.PLANAR else slice(0, 3)


class JointType(enum.Enum):
    """One-DOF joint kinds of a serial linkage."""

    REVOLUTE = 'revolute'
    PRISMATIC = 'prismatic'


@dataclass(frozen=True)
class LinkSpec:
    """One link and the joint that moves it (SI units, link frame at the joint)."""

    name: str
    joint: JointType
    length: float
    mass: float
    com: np.ndarray                     # (3,) m, link frame
    inertia: np.ndarray                 # (3, 3) kg m^2 about the COM, link frame
    axis: np.ndarray                    # (3,) unit joint axis, link frame
    origin_xyz: np.ndarray | None = None  # (3,) m in the previous link frame; None = default
    origin_rpy: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class ConstraintSettings:
    """How directions of topological constraint are decided (see dynamics.constraints).

    ``characteristic_length`` L_c (m) weights the rotational rows of ``J_h`` so that its
    singular values are all lengths; ``rank_tolerance`` is the fraction of L_c below which a
    weighted singular value counts as zero; ``blend`` > 0 ramps the penalty weight of a
    direction continuously from 1 at ``rank_tolerance`` to 0 at ``rank_tolerance*(1+blend)``.
    """

    characteristic_length: float
    rank_tolerance: float = 0.05
    blend: float = 0.0


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
        return Linkage(self.name, self.task, self.links, self.gravity, link, p,
                       self.constraints, self.urdf_path, self.source)


_LINK_KEYS = ('name', 'joint', 'length', 'mass', 'com', 'inertia', 'axis', 'origin')


def _inertia_matrix(value: Any, task: TaskSpace, where: str) -> np.ndarray:
    """Parse a link inertia about its COM and check it is symmetric positive definite."""
    if task is TaskSpace.PLANAR and isinstance(value, (int, float)) and not isinstance(
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
        expected = ('a positive number (Izz) or ' if task is TaskSpace.PLANAR else '') + \
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
    if task is TaskSpace.PLANAR:
        for key in ('axis', 'origin'):
            if key in raw:
                raise LinkageError(f'{w}.{key}: not allowed for a planar linkage (revolute '
                                   'joints turn about z, prismatic ones slide along x)')
        if com[2] != 0.0:
            raise LinkageError(f'{w}.com: z must be 0 for a planar linkage, got {com[2]}')
        axis = np.array([0.0, 0.0, 1.0]) if joint is JointType.REVOLUTE else np.array(
            [1.0, 0.0, 0.0])
        return LinkSpec(name, joint, length, mass, com, inertia, axis)
    axis = as_vector(raw.get('axis', [0.0, 0.0, 1.0]), f'{w}.axis', 3, error=LinkageError)
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
            origin_rpy = as_vector(o['rpy'], f'{w}.origin.rpy', 3, error=LinkageError)
    return LinkSpec(name, joint, length, mass, com, inertia, axis / norm, origin_xyz,
                    origin_rpy)


def _parse_constraints(raw: Any, where: str, default_length: float) -> ConstraintSettings:
    check_keys(raw, where, optional=('characteristic_length', 'rank_tolerance', 'blend'),
               error=LinkageError)
    length = as_float(raw.get('characteristic_length', default_length),
                      f'{where}.characteristic_length', lo=0.0, lo_open=True,
                      error=LinkageError)
    tol = as_float(raw.get('rank_tolerance', 0.05), f'{where}.rank_tolerance', lo=0.0,
                   lo_open=True, hi=1.0, error=LinkageError)
    blend = as_float(raw.get('blend', 0.0), f'{where}.blend', lo=0.0, hi=100.0,
                     error=LinkageError)
    return ConstraintSettings(length, tol, blend)


def linkage_from_dict(doc: Any, source: str = '<memory>') -> Linkage:
    """Validate a parsed YAML document (top-level key ``linkage``) into a :class:`Linkage`.

    Raises:
        LinkageError: naming ``source`` and the offending field.
    """
    top = check_keys(doc, source, required=('linkage',), error=LinkageError)
    where = f'{source}: linkage'
    raw = check_keys(top['linkage'], where,
                     optional=('name', 'task', 'gravity', 'links', 'grasp', 'constraints',
                               'urdf'), error=LinkageError)
    name = as_str(raw.get('name', Path(source).stem), f'{where}.name', error=LinkageError)
    task = TaskSpace(as_str(raw.get('task', 'planar'), f'{where}.task',
                            ('planar', 'spatial'), error=LinkageError))
    gravity = as_vector(raw.get('gravity', [0.0, 0.0, 0.0]), f'{where}.gravity', 3,
                        error=LinkageError)
    urdf_path: Path | None = None
    if 'urdf' in raw:
        if 'links' in raw:
            raise LinkageError(f'{where}: give either links or urdf, not both')
        urdf_path = Path(as_str(raw['urdf'], f'{where}.urdf', error=LinkageError))
        if not urdf_path.is_absolute() and source != '<memory>':
            urdf_path = Path(source).parent / urdf_path
        links = _links_from_urdf(urdf_path, task)
    else:
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
    default_lc = sum(_placement_offset(links, i) for i in range(1, len(links))) + \
        links[-1].length
    if default_lc <= 0.0:
        default_lc = 1.0
    constraints = _parse_constraints(raw.get('constraints', {}), f'{where}.constraints',
                                     default_lc)
    grasp = check_keys(raw.get('grasp', {}), f'{where}.grasp', optional=('link', 'point'),
                       error=LinkageError)
    grasp_link = as_str(grasp.get('link', names[-1]), f'{where}.grasp.link',
                        error=LinkageError)
    if grasp_link not in names:
        raise LinkageError(f'{where}.grasp.link: unknown link {grasp_link!r} (expected one '
                           f'of: {", ".join(names)})')
    point = (as_vector(grasp['point'], f'{where}.grasp.point', 3, error=LinkageError)
             if 'point' in grasp else links[names.index(grasp_link)].com.copy())
    if task is TaskSpace.PLANAR and point[2] != 0.0:
        raise LinkageError(f'{where}.grasp.point: z must be 0 for a planar linkage')
    linkage = Linkage(name, task, links, gravity, grasp_link, point, constraints, urdf_path,
                      source)
    build_model(linkage)  # fail now, not later, on anything Pinocchio rejects
    return linkage


def load_linkage(path: str | Path) -> Linkage:
    """Load a linkage from a YAML description or a bare URDF file (spatial, distal grasp)."""
    p = Path(path)
    if p.suffix.lower() == '.urdf':
        if not p.is_file():
            raise LinkageError(f'{p}: file not found')
        return linkage_from_dict({'linkage': {'task': 'spatial', 'urdf': str(p.resolve()),
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


def _links_from_urdf(path: Path, task: TaskSpace) -> tuple[LinkSpec, ...]:
    """Read a serial chain of 1-DOF joints from a URDF file into LinkSpecs."""
    if not path.is_file():
        raise LinkageError(f'{path}: file not found')
    try:
        model = pin.buildModelFromUrdf(str(path))
    except (RuntimeError, ValueError) as exc:
        raise LinkageError(f'{path}: not a valid URDF ({exc})') from None
    links: list[LinkSpec] = []
    for j in range(1, model.njoints):
        joint = model.joints[j]
        if joint.nq != 1 or joint.nv != 1:
            raise LinkageError(f'{path}: joint {model.names[j]!r} has {joint.nv} DOF; only '
                               'revolute, continuous and prismatic joints are supported')
        if model.parents[j] != j - 1:
            raise LinkageError(f'{path}: joint {model.names[j]!r} does not continue the '
                               'chain (the linkage must be serial)')
        shortname = joint.shortname()  # e.g. JointModelRZ, JointModelPX, JointModelRUBZ
        if not shortname.startswith(('JointModelR', 'JointModelP')):
            raise LinkageError(f'{path}: joint {model.names[j]!r} is {shortname}; only '
                               'revolute, continuous and prismatic joints are supported')
        kind = JointType.PRISMATIC if shortname.startswith('JointModelP') \
            else JointType.REVOLUTE
        if shortname.endswith('Unaligned'):
            axis = np.asarray(joint.extract().axis, dtype=float).reshape(3)
        else:
            axis = np.eye(3)['XYZ'.index(shortname[-1])]
        inertia = model.inertias[j]
        mass = float(inertia.mass)
        where = f'{path}: link of joint {model.names[j]!r}'
        if mass <= 0.0:
            raise LinkageError(f'{where}: mass must be > 0, got {mass}')
        inertia_c = np.array(inertia.inertia)
        if np.linalg.eigvalsh(inertia_c).min() <= 0.0:
            raise LinkageError(f'{where}: inertia must be positive definite')
        placement = model.jointPlacements[j]
        child = [f.name for f in model.frames
                 if f.parentJoint == j and f.type == pin.FrameType.BODY]
        links.append(LinkSpec(
            name=child[0] if child else model.names[j], joint=kind, length=0.0, mass=mass,
            com=np.array(inertia.lever).reshape(3), inertia=inertia_c, axis=axis,
            origin_xyz=np.array(placement.translation).reshape(3),
            origin_rpy=np.array(pin.rpy.matrixToRpy(placement.rotation)).reshape(3)))
    if not links:
        raise LinkageError(f'{path}: no movable joints')
    del task
    return tuple(links)


@dataclass(frozen=True)
class LinkageModel:
    """Pinocchio model of a :class:`Linkage` with the grasp as an operational frame."""

    linkage: Linkage
    model: pin.Model
    hand_frame: int


def build_model(linkage: Linkage) -> LinkageModel:
    """Build the Pinocchio model of ``linkage`` and add the operational frame ``hand``.

    Gravity is ``linkage.gravity`` (m/s^2, world frame); the base of joint 1 is the world
    origin (or its ``origin`` placement).
    """
    model = pin.Model()
    model.name = linkage.name
    parent = 0
    for i, link in enumerate(linkage.links):
        if linkage.task is TaskSpace.PLANAR:
            joint_model: Any = (pin.JointModelRZ() if link.joint is JointType.REVOLUTE
                                else pin.JointModelPX())
            xyz = np.array([linkage.links[i - 1].length, 0.0, 0.0]) if i > 0 else np.zeros(3)
            rot = np.eye(3)
        else:
            joint_model = (pin.JointModelRevoluteUnaligned(link.axis)
                           if link.joint is JointType.REVOLUTE
                           else pin.JointModelPrismaticUnaligned(link.axis))
            if link.origin_xyz is not None:
                xyz = link.origin_xyz
            else:
                xyz = (np.array([linkage.links[i - 1].length, 0.0, 0.0]) if i > 0
                       else np.zeros(3))
            rot = pin.rpy.rpyToMatrix(*link.origin_rpy)
        placement = pin.SE3(rot, xyz)
        jid = model.addJoint(parent, joint_model, placement, f'joint_{link.name}')
        model.appendBodyToJoint(jid, pin.Inertia(link.mass, link.com, link.inertia),
                                pin.SE3.Identity())
        joint_frame = model.addJointFrame(jid, -1)
        model.addBodyFrame(link.name, jid, pin.SE3.Identity(), joint_frame)
        parent = jid
    model.gravity = pin.Motion(np.asarray(linkage.gravity, dtype=float), np.zeros(3))
    jid = linkage.link_names.index(linkage.grasp_link) + 1
    hand = model.addFrame(pin.Frame('hand', jid, 0, pin.SE3(np.eye(3), linkage.grasp_point),
                                    pin.FrameType.OP_FRAME))
    return LinkageModel(linkage, model, hand)


def to_dict(linkage: Linkage) -> dict[str, Any]:
    """The inverse of :func:`linkage_from_dict` for YAML-described linkages (for bags/tests)."""
    links = []
    for link in linkage.links:
        entry: dict[str, Any] = {
            'name': link.name, 'joint': link.joint.value, 'length': link.length,
            'mass': link.mass, 'com': link.com.tolist()}
        if linkage.task is TaskSpace.PLANAR:
            entry['inertia'] = float(link.inertia[2, 2])
        else:
            entry['inertia'] = link.inertia.tolist()
            entry['axis'] = link.axis.tolist()
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
                        'rank_tolerance': c.rank_tolerance, 'blend': c.blend}}}


__all__ = ['ConstraintSettings', 'JointType', 'LinkSpec', 'Linkage', 'LinkageModel',
           'TaskSpace', 'build_model', 'linkage_from_dict', 'load_linkage', 'serial_chain',
           'to_dict']


def serial_chain(n: int, task: TaskSpace = TaskSpace.PLANAR, length: float = 0.05,
                 mass: float = 0.5) -> Linkage:
    """A uniform n-link chain of revolute joints grasped at the distal COM (benchmarks, tests).

    Planar: all joints about z. Spatial: joint axes alternate z, y, x so the chain moves in 3-D.
    """
    if n < 1:
        raise LinkageError(f'serial_chain: n must be >= 1, got {n}')
    inertia = mass * length * length / 12.0 + 1e-6
    links = []
    for i in range(n):
        entry: dict[str, Any] = {'name': f'link{i + 1}', 'joint': 'revolute', 'length': length,
                                 'mass': mass}
        if task is TaskSpace.PLANAR:
            entry['inertia'] = inertia
        else:
            entry['inertia'] = [1e-6 + mass * 1e-4, inertia, inertia]
            entry['axis'] = [[0, 0, 1], [0, 1, 0], [1, 0, 0]][i % 3]
        links.append(entry)
    return linkage_from_dict({'linkage': {'name': f'chain{n}_{task.value}',
                                          'task': task.value, 'links': links}},
                             f'<serial_chain {n}>')
