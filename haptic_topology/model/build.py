"""The Pinocchio model of a :class:`~haptic_topology.model.linkage.Linkage`, with the grasp as
the operational frame ``hand`` (where ``J_h`` of eq. 1 and eq. 7 is taken)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from haptic_topology.model.links import JointType, LinkSpec
from haptic_topology.vocabulary import TaskSpace

if TYPE_CHECKING:
    from haptic_topology.model.linkage import Linkage


@dataclass(frozen=True)
class LinkageModel:
    """Pinocchio model of a :class:`~haptic_topology.model.linkage.Linkage` with the grasp as an
    operational frame."""

    linkage: Linkage
    model: pin.Model
    hand_frame: int
    #: Per loop closure (``linkage.loops``): the frames at its two points, ``(link side,
    #: to side)``, oriented as the link's and the ``to`` link's (or world's) frame.
    loop_frames: tuple[tuple[int, int], ...] = ()


def _joint_model(link: LinkSpec, task: TaskSpace) -> Any:
    """Pinocchio joint for ``link``: RZ / PX for the default planar axes, else unaligned."""
    if task.planar:
        if link.joint is JointType.REVOLUTE and np.array_equal(link.axis, [0.0, 0.0, 1.0]):
            return pin.JointModelRZ()
        if link.joint is JointType.PRISMATIC and np.array_equal(link.axis, [1.0, 0.0, 0.0]):
            return pin.JointModelPX()
    return (pin.JointModelRevoluteUnaligned(link.axis) if link.joint is JointType.REVOLUTE
            else pin.JointModelPrismaticUnaligned(link.axis))


def build_model(linkage: Linkage) -> LinkageModel:
    """Build the Pinocchio model of ``linkage`` and add the operational frame ``hand``.

    Gravity is ``linkage.gravity`` (m/s^2, world frame); the base of joint 1 is the world
    origin (or its ``origin`` placement). Joint i sits at ``origin`` in link i-1's frame
    (default ``[length of link i-1, 0, 0]``) and moves about / along its ``axis``.
    """
    model = pin.Model()
    model.name = linkage.name
    parent = 0
    for i, link in enumerate(linkage.links):
        if link.origin_xyz is not None:
            xyz = link.origin_xyz
        else:
            xyz = np.array([linkage.links[i - 1].length, 0.0, 0.0]) if i > 0 else np.zeros(3)
        rot = pin.rpy.rpyToMatrix(*link.origin_rpy)
        placement = pin.SE3(rot, xyz)
        jid = model.addJoint(parent, _joint_model(link, linkage.task), placement,
                             link.joint_label)
        model.appendBodyToJoint(jid, pin.Inertia(link.mass, link.com, link.inertia),
                                pin.SE3.Identity())
        joint_frame = model.addJointFrame(jid, -1)
        model.addBodyFrame(link.name, jid, pin.SE3.Identity(), joint_frame)
        parent = jid
    model.gravity = pin.Motion(np.asarray(linkage.gravity, dtype=float), np.zeros(3))
    jid = linkage.link_names.index(linkage.grasp_link) + 1
    hand = model.addFrame(pin.Frame('hand', jid, 0, pin.SE3(np.eye(3), linkage.grasp_point),
                                    pin.FrameType.OP_FRAME))
    names = linkage.link_names
    loop_frames = []
    for loop in linkage.loops:
        ends = []
        for side, end, point in (('a', loop.link, loop.point), ('b', loop.to, loop.to_point)):
            parent = names.index(end) + 1 if end in names else 0    # 0: the world
            ends.append(model.addFrame(pin.Frame(f'loop:{loop.name}:{side}', parent, 0,
                                                 pin.SE3(np.eye(3), point),
                                                 pin.FrameType.OP_FRAME)))
        loop_frames.append((ends[0], ends[1]))
    return LinkageModel(linkage, model, hand, tuple(loop_frames))


