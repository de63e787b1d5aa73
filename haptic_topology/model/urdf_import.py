"""A URDF file read once, and the serial chain of a linkage taken from it.

:func:`read_urdf` reads and parses a file once (a cache keyed on the file's path, size and
modification time: the loader, the bare-URDF task check and the robot description all use the
same parse) into a :class:`UrdfSource`: its text, its ``<robot>`` element, its tree (root link,
joints, links) and its declared task. :func:`links_from_urdf` reduces it to the serial chain
of :class:`~haptic_topology.model.links.LinkSpec` (Pinocchio ``buildModelFromXML`` for the
kinematics and inertias, fixed joints merged, side branches locked with
``buildReducedModel``), with the ``<collision>`` shapes of each chain link.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pinocchio as pin

from haptic_topology.errors import LinkageError
from haptic_topology.model.links import CollisionShape, JointType, LinkSpec
from haptic_topology.vocabulary import TaskSpace


@dataclass(frozen=True)
class UrdfJoint:
    """One joint of a URDF: its name, type, parent and child link."""

    name: str
    kind: str
    parent: str
    child: str


def parse_urdf(text: str, where: str) -> tuple[str, tuple[UrdfJoint, ...], tuple[str, ...]]:
    """``(root link, joints in document order, link names)`` of a URDF text.

    Raises:
        LinkageError: not XML, no ``<robot>``, a joint without parent/child, or not one tree
            (no root or several).
    """
    return _tree(_parse_xml(text, where), where)


def _parse_xml(text: str, where: str) -> ET.Element:
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as exc:
        raise LinkageError(f'{where}: not a valid URDF ({exc})') from None
    if robot.tag != 'robot':
        raise LinkageError(f'{where}: expected a <robot> element, got <{robot.tag}>')
    return robot


def _tree(robot: ET.Element, where: str) -> tuple[str, tuple[UrdfJoint, ...], tuple[str, ...]]:
    """``(root link, joints, link names)`` of a parsed ``<robot>`` (see :func:`parse_urdf`)."""
    links = tuple(str(e.get('name', '')) for e in robot.findall('link'))
    joints = []
    for e in robot.findall('joint'):
        parent, child = e.find('parent'), e.find('child')
        name = str(e.get('name', ''))
        if parent is None or child is None:
            raise LinkageError(f'{where}: joint {name!r} needs <parent> and <child>')
        joints.append(UrdfJoint(name, str(e.get('type', '')), str(parent.get('link', '')),
                                str(child.get('link', ''))))
    children = {j.child for j in joints}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise LinkageError(f'{where}: expected one root link, got {roots}')
    return roots[0], tuple(joints), links

@dataclass(frozen=True, eq=False)
class UrdfSource:
    """A URDF file as read once: ``text``, the parsed ``robot`` element (never changed: see
    :meth:`without`), its tree (``root_link``, ``joints`` in document order, ``link_names``),
    the ``task`` its ``<haptic_topology task=...>`` declares (None: none), and ``locked``:
    positions (rad or m) of the side-branch joints a linkage locked (set by the loader)."""

    path: Path
    text: str
    robot: ET.Element
    root_link: str
    joints: tuple[UrdfJoint, ...]
    link_names: tuple[str, ...]
    task: TaskSpace | None
    locked: tuple[tuple[str, float], ...] = field(default=())

    def without(self, tags: Sequence[str]) -> str:
        """The URDF text without the links' elements ``tags`` (e.g. ``collision``: urdfdom
        does not know every geometry, e.g. ``<capsule>``), from the one parse."""
        robot = copy.deepcopy(self.robot)
        for link in robot.findall('link'):
            for tag in tags:
                for element in link.findall(tag):
                    link.remove(element)
        return ET.tostring(robot, encoding='unicode')


def read_urdf(path: Path) -> UrdfSource:
    """The URDF at ``path``, read and parsed once (see the module doc).

    Raises:
        LinkageError: no such file, not XML, no ``<robot>``, not one tree, or a bad
            ``<haptic_topology>`` tag.
    """
    try:
        st = path.stat()
    except OSError:
        raise LinkageError(f'{path}: file not found') from None
    if not path.is_file():
        raise LinkageError(f'{path}: file not found')
    return _read(str(path), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=32)
def _read(path: str, size: int, mtime_ns: int) -> UrdfSource:
    p = Path(path)
    try:
        text = p.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as exc:
        raise LinkageError(f'{p}: cannot read ({exc})') from None
    robot = _parse_xml(text, path)
    root, joints, links = _tree(robot, path)
    return UrdfSource(p, text, robot, root, joints, links, _declared_task(robot, p))


def _declared_task(robot: ET.Element, path: Path) -> TaskSpace | None:
    """The task of ``<haptic_topology task="planar|spatial"/>`` under ``<robot>``, if any."""
    tag = robot.find('haptic_topology')
    if tag is None:
        return None
    value = tag.get('task', '')
    if value not in ('planar', 'spatial'):
        raise LinkageError(f'{path}: <haptic_topology task=...>: expected planar or spatial, '
                           f'got {value!r}')
    return TaskSpace(value)


def _joint_child_link(model: pin.Model, j: int) -> str:
    """Name of the URDF link a joint moves (the body frame right after the joint frame)."""
    for f in model.frames:
        if (f.type == pin.FrameType.BODY and f.parentJoint == j
                and model.frames[f.parentFrame].type == pin.FrameType.JOINT):
            return str(f.name)
    return str(model.names[j])


def _urdf_joint_kind(model: pin.Model, j: int, path: Path) -> tuple[JointType, np.ndarray]:
    """Kind and unit axis (joint frame) of a 1-DOF Pinocchio joint read from a URDF.

    URDF ``revolute`` and ``continuous`` joints are revolute here (joint limits are not part
    of eq. 1); ``continuous`` is Pinocchio's unbounded revolute (RUBx, q = (cos, sin)).
    """
    joint = model.joints[j]
    shortname = joint.shortname()  # JointModelRZ, JointModelRUBZ, JointModelPrismaticUnaligned
    if joint.nv != 1 or not shortname.startswith(('JointModelR', 'JointModelP')):
        raise LinkageError(f'{path}: joint {model.names[j]!r} is {shortname} with {joint.nv} '
                           'DOF; only revolute, continuous, prismatic and fixed joints are '
                           'supported')
    kind = JointType.PRISMATIC if shortname.startswith('JointModelP') else JointType.REVOLUTE
    # The motion subspace S (6 x 1, [v; w] in the joint frame) holds the axis for every
    # 1-DOF joint class (RX..RZ, RUBX..RUBZ, the unaligned ones, PX..PZ).
    data = joint.createData()
    joint.calc(data, pin.neutral(model))
    s = np.asarray(data.S, dtype=float).reshape(6)
    axis = s[0:3] if kind is JointType.PRISMATIC else s[3:6]
    return kind, axis / np.linalg.norm(axis)


def _serial_chain_ids(model: pin.Model, grasp_link: str | None, path: Path) -> list[int]:
    """Joint ids of the chain: root -> grasped link, then on until the tree first branches.

    Without a grasp link, the chain is the main branch from the root (see below); its last
    link becomes the default grasp.
    """
    children: dict[int, list[int]] = {j: [] for j in range(model.njoints)}
    for j in range(1, model.njoints):
        children[model.parents[j]].append(j)
    movable = {_joint_child_link(model, j): j for j in range(1, model.njoints)}
    if grasp_link is not None:
        if grasp_link not in movable:
            raise LinkageError(
                f'{path}: grasp.link: {grasp_link!r} is not a link moved by a joint (expected '
                f'one of: {", ".join(movable)})')
        chain = [j for j in model.supports[movable[grasp_link]] if j != 0]
        tip = chain[-1]
        while len(children[tip]) == 1:
            tip = children[tip][0]
            chain.append(tip)
        return chain
    # No grasp given: the main chain follows, from the root, the child with the unique
    # deepest subtree (a camera on link 1 is a side branch of the arm) and ends where two
    # subtrees are equally deep (the two fingers of a gripper) or at a leaf.
    depth: dict[int, int] = {}
    for j in range(model.njoints - 1, -1, -1):  # children have larger ids than parents
        depth[j] = 1 + max((depth[c] for c in children[j]), default=0)
    chain = []
    tip = 0
    while children[tip]:
        ranked = sorted(children[tip], key=lambda c: depth[c], reverse=True)
        if len(ranked) > 1 and depth[ranked[0]] == depth[ranked[1]]:
            break
        tip = ranked[0]
        chain.append(tip)
    if not chain:
        if not children[0]:
            raise LinkageError(f'{path}: no movable joints')
        names = ', '.join(repr(model.names[j]) for j in children[0])
        raise LinkageError(f'{path}: the tree branches at its root into equally long chains '
                           f'(joints {names}); give grasp.link to choose one')
    return chain


def links_from_urdf(src: UrdfSource, grasp_link: str | None, locked: dict[str, float],
                    locked_where: str) -> tuple[tuple[LinkSpec, ...], tuple[str, ...]]:
    """Read the serial chain of a URDF into LinkSpecs (plus a one-line note of what was locked).

    Fixed joints are merged by Pinocchio (``buildModelFromXML``). Joints off the chain
    (``_serial_chain_ids``) are locked at ``locked`` (default 0) with
    ``buildReducedModel``, which keeps their bodies' mass and inertia on the chain link that
    carries them.
    """
    path = src.path
    try:
        # Kinematics and inertia only: the <collision> elements are read by _urdf_collisions
        # (urdfdom does not know <capsule> and would print an error for it).
        full = pin.buildModelFromXML(src.without(('collision',)))
    except (RuntimeError, ValueError) as exc:
        raise LinkageError(f'{path}: not a valid URDF ({exc})') from None
    for j in range(1, full.njoints):
        _urdf_joint_kind(full, j, path)
    chain = _serial_chain_ids(full, grasp_link, path)
    off = [j for j in range(1, full.njoints) if j not in chain]
    off_names = {str(full.names[j]): j for j in off}
    for name in locked:
        if name in off_names:
            continue
        if full.existJointName(name):
            raise LinkageError(f'{locked_where}.{name}: joint {name!r} is on the chain; only '
                               f'side-branch joints can be locked (expected one of: '
                               f'{", ".join(off_names) or "none"})')
        raise LinkageError(f'{locked_where}.{name}: unknown side-branch joint (expected one '
                           f'of: {", ".join(off_names) or "none"})')
    notes: tuple[str, ...] = ()
    model = full
    if off:
        q_ref = pin.neutral(full)
        for name, j in off_names.items():
            value = locked.get(name, 0.0)
            jm = full.joints[j]
            if jm.nq == 2:   # continuous: q = (cos, sin)
                q_ref[jm.idx_q:jm.idx_q + 2] = [math.cos(value), math.sin(value)]
            else:
                q_ref[jm.idx_q] = value
        model = pin.buildReducedModel(full, off, q_ref)
        chain_names = ' -> '.join(str(full.names[j]) for j in chain)
        locks = ', '.join(f'{n}={locked.get(n, 0.0):g}' for n in off_names)
        notes = (f'{path}: kept the serial chain {chain_names}; locked {len(off)} side-branch '
                 f'joint(s) at {locks} (rad or m), their mass kept',)
    collisions = _urdf_collisions(src, model)
    links: list[LinkSpec] = []
    for j in range(1, model.njoints):
        if model.parents[j] != j - 1:  # pragma: no cover - the reduced model is a chain
            raise LinkageError(f'{path}: joint {model.names[j]!r} does not continue the chain')
        kind, axis = _urdf_joint_kind(model, j, path)
        inertia = model.inertias[j]
        mass = float(inertia.mass)
        where = f'{path}: link of joint {model.names[j]!r}'
        if mass <= 0.0:
            raise LinkageError(f'{where}: mass must be > 0, got {mass}')
        inertia_c = np.array(inertia.inertia)
        if np.linalg.eigvalsh(inertia_c).min() <= 0.0:
            raise LinkageError(f'{where}: inertia must be positive definite')
        placement = model.jointPlacements[j]
        if j + 1 < model.njoints:
            length = float(np.linalg.norm(model.jointPlacements[j + 1].translation))
        else:  # the farthest frame fixed to the last link (a tip, a gripper), or 0
            length = max([float(np.linalg.norm(f.placement.translation))
                          for f in model.frames if f.parentJoint == j] + [0.0])
        links.append(LinkSpec(
            name=_joint_child_link(model, j), joint=kind, length=length, mass=mass,
            com=np.array(inertia.lever).reshape(3), inertia=inertia_c, axis=axis,
            origin_xyz=np.array(placement.translation).reshape(3),
            origin_rpy=np.array(pin.rpy.matrixToRpy(placement.rotation)).reshape(3),
            joint_name=str(model.names[j]), collision=tuple(collisions.get(j, ()))))
    return tuple(links), notes


def _urdf_mesh(shape: ET.Element, where: str) -> tuple[tuple[float, ...], str]:
    """The ``scale`` (3,) and ``filename`` of a URDF ``<mesh>`` (resolved by the contacts)."""
    filename = shape.get('filename')
    if not filename:
        raise LinkageError(f'{where}: <mesh> needs the attribute filename')
    text = shape.get('scale', '1 1 1')
    try:
        scale = [float(v) for v in text.split()]
    except ValueError:
        raise LinkageError(f'{where}: <mesh scale="{text}">: expected numbers') from None
    if len(scale) == 1:
        scale *= 3
    if len(scale) != 3 or not all(math.isfinite(v) and v > 0.0 for v in scale):
        raise LinkageError(f'{where}: <mesh scale="{text}">: expected 1 or 3 finite '
                           f'numbers > 0')
    return tuple(scale), filename


def _urdf_geometry(geom: ET.Element, where: str) -> tuple[str, tuple[float, ...], str]:
    """Kind, sizes (m; a mesh: its scale) and mesh filename ('' for the primitives) of a
    URDF ``<geometry>`` element (see :class:`CollisionShape`)."""
    shapes = list(geom)
    if len(shapes) != 1:
        raise LinkageError(f'{where}: <geometry> must hold exactly one shape, got '
                           f'{len(shapes)}')
    shape = shapes[0]
    kind = shape.tag
    if kind == 'mesh':
        scale, filename = _urdf_mesh(shape, where)
        return kind, scale, filename
    attrs = {'sphere': ('radius',), 'capsule': ('radius', 'length'),
             'cylinder': ('radius', 'length'), 'box': ('size',), 'mesh': ()}
    if kind not in attrs:
        raise LinkageError(f'{where}: unknown geometry <{kind}> (expected one of: '
                           f'{", ".join(attrs)})')
    sizes: list[float] = []
    for attr in attrs[kind]:
        text = shape.get(attr)
        if text is None:
            raise LinkageError(f'{where}: <{kind}> needs the attribute {attr}')
        try:
            values = [float(v) for v in text.split()]
        except ValueError:
            raise LinkageError(f'{where}: <{kind} {attr}="{text}">: expected numbers') from None
        expected = 3 if attr == 'size' else 1
        if len(values) != expected or not all(math.isfinite(v) and v > 0.0 for v in values):
            raise LinkageError(f'{where}: <{kind} {attr}="{text}">: expected {expected} '
                               f'finite number(s) > 0 (m)')
        sizes.extend(values)
    return kind, tuple(sizes), ''


def _urdf_collisions(src: UrdfSource, model: pin.Model) -> dict[int, list[CollisionShape]]:
    """The URDF's ``<collision>`` elements per joint of the (reduced) chain ``model``, each
    placed in that joint's frame: a link merged by a fixed joint or carried by a locked side
    branch gives its shapes to the chain link that carries it (its Pinocchio body frame).
    Shapes on the root link (joint 0) are static and left out: the contacts are between the
    moving links and the scenario's obstacles."""
    path = src.path
    out: dict[int, list[CollisionShape]] = {}
    for link in src.robot.findall('link'):
        name = link.get('name', '')
        elements = link.findall('collision')
        if not elements or not model.existFrame(name, pin.FrameType.BODY):
            continue
        frame = model.frames[model.getFrameId(name, pin.FrameType.BODY)]
        if frame.parentJoint == 0:
            continue
        for k, col in enumerate(elements):
            where = f'{path}: link {name!r} <collision> {k + 1}'
            geom = col.find('geometry')
            if geom is None:
                raise LinkageError(f'{where}: missing <geometry>')
            kind, size, mesh = _urdf_geometry(geom, where)
            origin = col.find('origin')
            xyz = rpy = np.zeros(3)
            if origin is not None:
                try:
                    xyz = np.array([float(v) for v in origin.get('xyz', '0 0 0').split()])
                    rpy = np.array([float(v) for v in origin.get('rpy', '0 0 0').split()])
                except ValueError:
                    raise LinkageError(f'{where}: <origin>: expected numbers') from None
                if xyz.shape != (3,) or rpy.shape != (3,):
                    raise LinkageError(f'{where}: <origin>: xyz and rpy take 3 numbers each')
            placement = frame.placement * pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)
            out.setdefault(frame.parentJoint, []).append(CollisionShape(
                kind, size, tuple(np.asarray(placement.translation, dtype=float).tolist()),
                tuple(np.asarray(placement.rotation, dtype=float).ravel().tolist()), name,
                mesh))
    return out


