"""The linkage as a robot: its URDF (generated, or the user's own) and its link frames.

:func:`linkage_urdf` writes the URDF of a :class:`~haptic_topology.model.linkage.Linkage`:
a root link (``base_link``) at the world origin, then per link ``i`` the joint that moves it
(``joint_label``; ``continuous`` for revolute joints, ``prismatic``) placed at ``origin`` in
the previous link's frame exactly as :func:`~haptic_topology.model.build.build_model` places
it (default ``[length of link i-1, 0, 0]``), and the link with its inertial (mass, COM, inertia
about the COM in the link's axes) and a cylinder from its joint to the next joint (the distal
link: ``length`` along its x axis) as visual. Link ``i``'s frame is joint ``i``'s frame, as in
the Pinocchio model, so a URDF tool computes the same forward kinematics as the dynamics.
Numbers are written with ``repr`` (shortest round trip): reading the URDF back gives the same
floats. The VE sets no joint limits; URDF demands some for a prismatic joint:
:data:`PRISMATIC_LIMIT`.

:func:`robot_description` is what ``ve_sim`` publishes on ``/robot_description``: for a
linkage read from a URDF the user's own file, unchanged (its meshes, its side branches), once
every joint of the linkage is checked to be in it with the same name, kind and child link;
else the generated URDF. A closed chain's loop closures follow as ``<haptic_topology_loop>``
elements (:func:`loop_elements`), in both. Its movable joints not on the linkage's chain (side
branches: a gripper's fingers) stand at the linkage YAML's ``locked_joints`` positions
(default 0).

:class:`LinkFrames` is the workspace (Pinocchio model and data of that URDF, as
``model``/``data`` elsewhere) that turns joint positions into the transforms of ``/tf``:
world -> root link, parent -> child link for every URDF joint (as ``robot_state_publisher``
would), and grasped link -> ``vt_hand`` (the grasp point, in the link's axes; a point grasp's
``vt_hand`` has the world's axes: the hand holds a point, which has no orientation). No rclpy
here.

Example (Table I, q = 0: link 3's frame sits at x = l1 + l2)::

    >>> import numpy as np
    >>> from haptic_topology.model.linkage import load_linkage
    >>> from haptic_topology.paths import config_dir
    >>> lk = load_linkage(config_dir() / 'linkages' / 'table1_planar3.yaml')
    >>> frames = LinkFrames(robot_description(lk))
    >>> frames.link_placement(np.zeros(3), 'link3').translation.round(12).tolist()
    [0.084, 0.0, 0.0]
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from haptic_topology.errors import LinkageError
from haptic_topology.model import frames
from haptic_topology.model.linkage import JointType, Linkage, LinkSpec, reach
from haptic_topology.model.loops import WORLD
from haptic_topology.model.urdf_import import UrdfJoint, UrdfSource, parse_urdf, read_urdf

#: Name of the generated URDF's root link (``<linkage name>_base_link`` if a link has it).
ROOT_LINK = 'base_link'
#: +- position limit (m) of a generated prismatic joint: URDF requires one, the VE has none.
PRISMATIC_LIMIT = 1000.0
#: Radius of the generated visuals, as a fraction of the linkage's reach.
VISUAL_RADIUS = 0.03
#: URDF joint types that move (one DOF); ``fixed`` joints do not.
MOVABLE = ('revolute', 'continuous', 'prismatic')


def _num(x: float) -> str:
    return repr(float(x))


def _vec(v: np.ndarray | list[float]) -> str:
    return ' '.join(_num(x) for x in v)


def joint_placement(linkage: Linkage, i: int) -> pin.SE3:
    """Placement of joint ``i`` (0-based) in the previous link's frame (the world for i = 0),
    as :func:`~haptic_topology.model.build.build_model` computes it."""
    link = linkage.links[i]
    if link.origin_xyz is not None:
        xyz = np.asarray(link.origin_xyz, dtype=float)
    elif i > 0:
        xyz = np.array([linkage.links[i - 1].length, 0.0, 0.0])
    else:
        xyz = np.zeros(3)
    return pin.SE3(pin.rpy.rpyToMatrix(*link.origin_rpy), xyz)


def _z_onto(v: np.ndarray) -> np.ndarray:
    """A rotation taking the z axis onto the unit vector ``v``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, v)
    s, c = float(np.linalg.norm(axis)), float(v @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0.0 else np.diag([1.0, -1.0, -1.0])
    return np.asarray(pin.exp3(axis / s * math.atan2(s, c)))


def _visual(parent: ET.Element, span: np.ndarray, radius: float) -> None:
    """A cylinder from the link frame's origin to ``span`` (link frame), or a sphere."""
    visual = ET.SubElement(parent, 'visual')
    length = float(np.linalg.norm(span))
    geometry = ET.Element('geometry')
    if length < 1e-9:
        ET.SubElement(visual, 'origin', xyz='0 0 0', rpy='0 0 0')
        ET.SubElement(geometry, 'sphere', radius=_num(radius))
    else:
        rpy = pin.rpy.matrixToRpy(_z_onto(span / length))
        ET.SubElement(visual, 'origin', xyz=_vec(span / 2.0), rpy=_vec(rpy))
        ET.SubElement(geometry, 'cylinder', radius=_num(radius), length=_num(length))
    visual.append(geometry)
    ET.SubElement(visual, 'material', name='haptic_topology_link')


def _inertial(parent: ET.Element, link: LinkSpec) -> None:
    inertial = ET.SubElement(parent, 'inertial')
    ET.SubElement(inertial, 'origin', xyz=_vec(link.com), rpy='0 0 0')
    ET.SubElement(inertial, 'mass', value=_num(link.mass))
    i = link.inertia
    ET.SubElement(inertial, 'inertia', ixx=_num(i[0, 0]), ixy=_num(i[0, 1]),
                  ixz=_num(i[0, 2]), iyy=_num(i[1, 1]), iyz=_num(i[1, 2]), izz=_num(i[2, 2]))


def root_link_name(linkage: Linkage) -> str:
    """:data:`ROOT_LINK`, or ``<linkage name>_base_link`` when a link is named so."""
    return ROOT_LINK if ROOT_LINK not in linkage.link_names else f'{linkage.name}_{ROOT_LINK}'


def linkage_urdf(linkage: Linkage, radius: float | None = None) -> str:
    """The URDF (XML text) of ``linkage`` (module doc); ``radius`` (m) of the visuals,
    default :data:`VISUAL_RADIUS` times the reach."""
    if radius is None:
        radius = VISUAL_RADIUS * max(reach(linkage.links), 1e-3)
    robot = ET.Element('robot', name=linkage.name)
    robot.append(ET.Comment(
        f' Generated by haptic_topology from {linkage.source} ({linkage.task.value} linkage '
        f'{linkage.name}, grasped on {linkage.grasp_link} at {linkage.grasp_point.tolist()} '
        'in its frame). Each link frame sits at the joint that moves it; inertials about the '
        'COM. '))
    if linkage.task.planar:   # load_linkage reads a bare URDF back as planar
        ET.SubElement(robot, 'haptic_topology', task='planar')
    material = ET.SubElement(robot, 'material', name='haptic_topology_link')
    ET.SubElement(material, 'color', rgba='0.2 0.4 0.9 1.0')
    parent = root_link_name(linkage)
    ET.SubElement(robot, 'link', name=parent)
    for i, link in enumerate(linkage.links):
        placement = joint_placement(linkage, i)
        kind = 'continuous' if link.joint is JointType.REVOLUTE else 'prismatic'
        joint = ET.SubElement(robot, 'joint', name=link.joint_label, type=kind)
        ET.SubElement(joint, 'parent', link=parent)
        ET.SubElement(joint, 'child', link=link.name)
        ET.SubElement(joint, 'origin', xyz=_vec(placement.translation),
                      rpy=_vec(link.origin_rpy))
        ET.SubElement(joint, 'axis', xyz=_vec(link.axis))
        if link.joint is JointType.PRISMATIC:
            ET.SubElement(joint, 'limit', lower=_num(-PRISMATIC_LIMIT),
                          upper=_num(PRISMATIC_LIMIT), effort='1000000.0',
                          velocity='1000000.0')
        element = ET.SubElement(robot, 'link', name=link.name)
        _inertial(element, link)
        span = (joint_placement(linkage, i + 1).translation if i + 1 < linkage.dof
                else np.array([link.length, 0.0, 0.0]))
        _visual(element, np.asarray(span, dtype=float), radius)
        parent = link.name
    for element in loop_elements(linkage, root_link_name(linkage)):
        robot.append(element)
    ET.indent(robot, space='  ')
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding='unicode') + '\n'


def loop_elements(linkage: Linkage, root: str) -> list[ET.Element]:
    """The linkage's loop closures as ``<haptic_topology_loop>`` elements, the documented
    extras of its URDF (URDF has no closed chains; tools ignore unknown elements): ``name``,
    ``kind``, ``link`` and ``point`` (m, link frame), ``to`` (a link, or ``root`` for the
    world) and ``to_point``, and for a revolute closure ``axis`` and ``to_axis``."""
    out = []
    for loop in linkage.loops:
        attrs = {'name': loop.name, 'kind': loop.kind.value, 'link': loop.link,
                 'point': _vec(loop.point), 'to': root if loop.to == WORLD else loop.to,
                 'to_point': _vec(loop.to_point)}
        if loop.axis is not None and loop.to_axis is not None:
            attrs.update(axis=_vec(loop.axis), to_axis=_vec(loop.to_axis))
        out.append(ET.Element('haptic_topology_loop', attrs))
    return out


@dataclass(frozen=True)
class RobotDescription:
    """A linkage's URDF and what its frames need (see :func:`robot_description`).

    ``joint_names``: the URDF's movable joints, the linkage's chain first (in its order, so
    the first ``dof`` positions are ``q``), then the side-branch joints, which stand at
    ``locked`` (rad or m, one per side-branch joint).
    """

    linkage: Linkage
    urdf: str
    generated: bool
    root_link: str
    joints: tuple[UrdfJoint, ...]
    joint_names: tuple[str, ...]
    locked: tuple[float, ...]
    #: The user's URDF as read once (None: generated).
    source: UrdfSource | None = None

    def positions(self, q: np.ndarray) -> np.ndarray:
        """Positions of every joint of ``joint_names``: ``q``, then the locked ones."""
        return np.concatenate([np.asarray(q, dtype=float), self.locked])


def locked_positions(linkage: Linkage) -> dict[str, float]:
    """``locked_joints`` (joint -> rad or m) of a URDF linkage's YAML description, ``{}`` for
    anything else (as the loader validated and kept them with the URDF it read)."""
    return {} if linkage.urdf is None else dict(linkage.urdf.locked)


def robot_description(linkage: Linkage,
                      locked: Mapping[str, float] | None = None) -> RobotDescription:
    """The URDF to publish for ``linkage`` (module doc); ``locked``: positions of side-branch
    joints (default :func:`locked_positions`, missing ones 0).

    Raises:
        LinkageError: the user's URDF cannot be read, lacks a joint of the linkage (or has it
            with another kind or child link), or has a link named as a frame of the graph
            (:data:`haptic_topology.model.frames.RESERVED`).
    """
    src: UrdfSource | None = None
    if linkage.urdf_path is None:
        text, generated, where = linkage_urdf(linkage), True, f'{linkage.source} (generated)'
        root, joints, links = parse_urdf(text, where)
    else:
        src = linkage.urdf or read_urdf(linkage.urdf_path)
        text, generated, where = src.text, False, str(src.path)
        root, joints, links = src.root_link, src.joints, src.link_names
        if linkage.loops:       # the closures of the YAML on top, before </robot>
            extras = ''.join('  ' + ET.tostring(e, encoding='unicode') + '\n'
                             for e in loop_elements(linkage, root))
            end = text.rindex('</robot>')
            text = text[:end] + extras + text[end:]
    clash = sorted(set(links) & set(frames.RESERVED))
    if clash:
        raise LinkageError(f'{where}: link name(s) {", ".join(clash)} are frames of the graph '
                           f'({", ".join(frames.RESERVED)}); rename the link(s)')
    by_name = {j.name: j for j in joints}
    for link in linkage.links:
        j = by_name.get(link.joint_label)
        kinds = ('revolute', 'continuous') if link.joint is JointType.REVOLUTE else (
            'prismatic',)
        if j is None or j.kind not in kinds or j.child != link.name:
            found = 'none' if j is None else f'a {j.kind} joint moving {j.child!r}'
            raise LinkageError(
                f'{where}: the linkage {linkage.name} has joint {link.joint_label!r} '
                f'({link.joint.value}) moving link {link.name!r}; the URDF has {found}')
    chain = [link.joint_label for link in linkage.links]
    side = [j.name for j in joints if j.kind in MOVABLE and j.name not in chain]
    values = locked_positions(linkage) if locked is None else dict(locked)
    return RobotDescription(linkage, text, generated, root, joints,
                            tuple(chain + side), tuple(float(values.get(n, 0.0)) for n in side),
                            src)


def _kinematics_only(text: str) -> str:
    """The URDF without its ``<collision>`` and ``<visual>`` elements (urdfdom does not know
    every geometry a URDF may hold, e.g. ``<capsule>``, and the frames need none)."""
    robot = ET.fromstring(text)
    for link in robot.findall('link'):
        for tag in ('collision', 'visual'):
            for element in link.findall(tag):
                link.remove(element)
    return ET.tostring(robot, encoding='unicode')


class LinkFrames:
    """The transforms of ``/tf`` for a :class:`RobotDescription` (module doc): a Pinocchio
    model of its URDF (built from the text, meshes are not read) and data, allocated once.

    ``edges`` lists ``(parent, child)`` of every transform :meth:`transforms` returns, in
    its row order: ``world -> root link`` (left out when the root link is ``world``), one per
    URDF joint (fixed ones included), then ``grasped link -> vt_hand`` (for a point grasp
    turned back to the world's axes).
    """

    def __init__(self, description: RobotDescription, world: str = frames.WORLD) -> None:
        self.description = d = description
        try:
            self.model = pin.buildModelFromXML(
                _kinematics_only(d.urdf) if d.source is None
                else d.source.without(('collision', 'visual')))
        except (RuntimeError, ValueError, ET.ParseError) as exc:
            raise LinkageError(f'robot description of {d.linkage.name}: Pinocchio cannot read '
                               f'its URDF ({exc})') from None
        self.data = self.model.createData()
        self._q = pin.neutral(self.model)
        # Joint positions -> slots of the model's q: (index, nq); continuous joints (nq 2)
        # take (cos, sin).
        self._slots = []
        for name in d.joint_names:
            if not self.model.existJointName(name):  # pragma: no cover - checked above
                raise LinkageError(f'{d.linkage.name}: no joint {name!r} in the URDF model')
            jm = self.model.joints[self.model.getJointId(name)]
            self._slots.append((int(jm.idx_q), int(jm.nq)))
        self._set(np.zeros(d.linkage.dof))
        body = pin.FrameType.BODY
        self._frame_ids = [(self.model.getFrameId(j.parent, body),
                            self.model.getFrameId(j.child, body)) for j in d.joints]
        self.world = world
        edges = [] if d.root_link == world else [(world, d.root_link)]
        edges += [(j.parent, j.child) for j in d.joints]
        edges.append((d.linkage.grasp_link, frames.VT_HAND))
        self.edges: tuple[tuple[str, str], ...] = tuple(edges)
        self._out = np.zeros((len(edges), 7))
        self._out[:, 6] = 1.0
        self._out[-1, 0:3] = d.linkage.grasp_point
        self._first = 0 if d.root_link == world else 1
        #: A point grasp: the grasped link's frame, whose world rotation vt_hand undoes.
        self._grasp_frame = (self.model.getFrameId(d.linkage.grasp_link, body)
                             if d.linkage.task.point else None)

    def _set(self, q: np.ndarray) -> None:
        """The model's q from the linkage's ``q`` and the locked positions."""
        values = self.description.positions(q)
        for (idx, nq), v in zip(self._slots, values.tolist(), strict=True):
            if nq == 2:
                self._q[idx] = math.cos(v)
                self._q[idx + 1] = math.sin(v)
            else:
                self._q[idx] = v

    def transforms(self, q: np.ndarray) -> np.ndarray:
        """Rows ``[tx, ty, tz, qx, qy, qz, qw]`` (m; unit quaternion) of the child frame in
        the parent frame for every edge of ``edges``, at the linkage's joint positions
        ``q``. The array is reused by the next call."""
        dof = self.description.linkage.dof
        if np.shape(q) != (dof,):
            raise ValueError(f'q must have {dof} entries, got shape {np.shape(q)}')
        self._set(q)
        pin.framesForwardKinematics(self.model, self.data, self._q)
        out, omf = self._out, self.data.oMf
        for row, (p, c) in enumerate(self._frame_ids, start=self._first):
            rel = omf[p].actInv(omf[c])
            out[row, 0:3] = rel.translation
            out[row, 3:7] = pin.Quaternion(rel.rotation).coeffs()
        if self._grasp_frame is not None:
            out[-1, 3:7] = pin.Quaternion(omf[self._grasp_frame].rotation.T).coeffs()
        return out

    def link_placement(self, q: np.ndarray, link: str) -> pin.SE3:
        """World placement of URDF link ``link`` (or ``vt_hand``) at ``q``: the transforms of
        :meth:`transforms` composed from the world down (what a TF listener computes)."""
        rows = self.transforms(q)
        parent_of = {c: (p, i) for i, (p, c) in enumerate(self.edges)}
        placement = pin.SE3.Identity()
        frame = link
        while frame != self.world:
            if frame not in parent_of:
                raise KeyError(f'no frame {frame!r} below {self.world!r}')
            parent, i = parent_of[frame]
            r = rows[i]
            quat = pin.Quaternion(float(r[6]), float(r[3]), float(r[4]), float(r[5]))
            placement = pin.SE3(quat.matrix(), r[0:3].copy()) * placement
            frame = parent
        return placement


__all__ = ['MOVABLE', 'PRISMATIC_LIMIT', 'ROOT_LINK', 'VISUAL_RADIUS', 'LinkFrames',
           'RobotDescription', 'UrdfJoint', 'joint_placement', 'linkage_urdf',
           'locked_positions', 'parse_urdf', 'robot_description', 'root_link_name']
