"""Frames of the node graph, and task vectors as 3-D poses, twists and wrenches (no rclpy).

The one place for frame names. The TF tree ``ve_sim`` publishes on ``/tf``::

    <world>                      ve_sim's frame_id (default "world"): the VE's world frame;
     |                           the linkage's base (joint 1's parent) is at its origin
     +- <root link>              the URDF's root link (identity; left out when it is <world>)
     |   +- <link i> ...         one frame per URDF link, at its joint (parent -> child per
     |        +- vt_hand         URDF joint); vt_hand: the grasp point on the grasped link
     |                           (the link's axes; a point grasp's: the world's), where J_h
     |                           and F_pc act
     +- device_base              the device's base (identity: the device's poses are in the
         +- device               VE's world coordinates); device: the device handle's pose

Headers: ``DeviceState``, ``DeviceCommand`` and ``HandInputs`` (device-side quantities) carry
:data:`DEVICE_BASE`; ``LmiUpdate``, ``VtPath``, the markers and the VT hand's pose and twist
mirrors carry the world frame; a wrench mirror carries the frame at whose origin it acts, its
components in that frame's axes (``device`` for the applied and hand wrenches, ``vt_hand``
for the coupling wrench), as a force-torque sensor reports it and as RViz draws it.

Task vectors (see :mod:`haptic_topology.dynamics.taskspace`): planar pose ``[x, y, theta]``,
twist ``[vx, vy, wz]``, wrench ``[fx, fy, tz]``; spatial pose ``[x, y, z, rotation vector]``,
twist ``[v, w]``, wrench ``[f, tau]``, all world-aligned at their point. A point grasp's
pose is its point alone (``[x, y]`` / ``[x, y, z]``): its frame has the world's axes (no
orientation), its twist and wrench are a velocity and a force.

Example (a planar device pose; quaternions are ``[x, y, z, w]``)::

    >>> import numpy as np
    >>> from haptic_topology.model.linkage import TaskSpace
    >>> t, quat = pose_transform(np.array([0.1, 0.2, np.pi / 2]), TaskSpace.PLANAR, z=0.05)
    >>> t.tolist(), np.round(quat, 12).tolist()
    ([0.1, 0.2, 0.05], [0.0, 0.0, 0.707106781187, 0.707106781187])
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from haptic_topology.vocabulary import TaskSpace

#: Default world frame (``ve_sim`` parameter ``frame_id``).
WORLD = 'world'
#: The haptic device's base: the frame of the device-side messages' poses, twists, wrenches.
DEVICE_BASE = 'device_base'
#: The device handle (the device's pose), child of :data:`DEVICE_BASE`.
DEVICE = 'device'
#: The grasp point on the virtual tool, child of the grasped link.
VT_HAND = 'vt_hand'
#: Frame names of the graph that no URDF link may take.
RESERVED = (DEVICE_BASE, DEVICE, VT_HAND)


def quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` (ROS order) of a 3x3 rotation matrix."""
    return np.asarray(pin.Quaternion(np.asarray(rotation, dtype=float)).coeffs(),
                      dtype=float).reshape(4)


def pose_rotation(pose: np.ndarray, task: TaskSpace) -> np.ndarray:
    """Rotation matrix of a task pose (planar: about z by theta; a point grasp: the identity,
    its pose has no orientation)."""
    if task.point:
        return np.eye(3)
    if task is TaskSpace.PLANAR:
        c, s = float(np.cos(pose[2])), float(np.sin(pose[2]))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(pin.exp3(np.asarray(pose[3:6], dtype=float)))


def pose_transform(pose: np.ndarray, task: TaskSpace,
                   z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(translation (3,), quaternion [x, y, z, w])`` of a task pose; ``z`` (m): the height
    of a planar pose (its plane), ignored for a spatial one. A point grasp: its point and the
    identity quaternion."""
    if task.point:
        t = np.array([float(pose[0]), float(pose[1]),
                      float(z) if task.planar else float(pose[2])])
        return t, np.array([0.0, 0.0, 0.0, 1.0])
    if task is TaskSpace.PLANAR:
        t = np.array([float(pose[0]), float(pose[1]), float(z)])
        half = 0.5 * float(pose[2])
        return t, np.array([0.0, 0.0, np.sin(half), np.cos(half)])
    return np.array(pose[0:3], dtype=float), quaternion(pose_rotation(pose, task))


def spatial(vector: np.ndarray, task: TaskSpace) -> np.ndarray:
    """A task twist or wrench as 6 entries ``[linear (3), angular (3)]``: planar
    ``[a, b, c]`` -> ``[a, b, 0, 0, 0, c]``; a point grasp's force with zero torque."""
    out = np.zeros(6)
    out[list(task.frame_rows)] = np.asarray(vector, dtype=float)[:task.dim]
    return out


def wrench_in_frame(wrench: np.ndarray, rotation: np.ndarray, task: TaskSpace) -> np.ndarray:
    """A world-aligned task wrench at a frame's origin, in that frame's axes (6 entries
    ``[f, tau]``): ``[R^T f, R^T tau]`` with ``rotation`` R the frame's orientation in the
    world. The point is unchanged, so no moment is added."""
    w = spatial(wrench, task)
    r = np.asarray(rotation, dtype=float)
    return np.concatenate([r.T @ w[0:3], r.T @ w[3:6]])


__all__ = ['DEVICE', 'DEVICE_BASE', 'RESERVED', 'VT_HAND', 'WORLD', 'pose_rotation',
           'pose_transform', 'quaternion', 'spatial', 'wrench_in_frame']
