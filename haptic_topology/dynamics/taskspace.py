"""Poses, twists and their arithmetic in the task spaces of
:class:`~haptic_topology.vocabulary.TaskSpace`.

Planar pose ``[x, y, theta]`` (m, m, rad), twist ``[vx, vy, wz]``. Spatial pose
``[x, y, z, rx, ry, rz]`` with the orientation as a rotation vector (rad, world frame), twist
``[vx, vy, vz, wx, wy, wz]`` with the angular velocity in the world frame (Pinocchio's
LOCAL_WORLD_ALIGNED convention at the grasp point). A point grasp (``planar_point``,
``spatial_point``) has the translation rows only: pose ``[x, y]`` / ``[x, y, z]`` of the grasp
point (m), twist its velocity (m/s); its arithmetic is that of vectors.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from haptic_topology.vocabulary import TaskSpace


def wrap_angle(a: float) -> float:
    """Wrap an angle (rad) to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def pose_from_placement(placement: pin.SE3, task: TaskSpace) -> np.ndarray:
    """Task pose of an SE3 placement (world frame)."""
    h = placement.homogeneous   # [R p; 0 1], one conversion for rotation and translation
    if task.point:
        return h[:task.dim, 3].copy()
    if task is TaskSpace.PLANAR:
        r0, r1 = h[:2].tolist()  # Python floats: cheaper to index than numpy scalars
        return np.array([r0[3], r1[3], math.atan2(r1[0], r0[0])])
    return np.concatenate([h[:3, 3], pin.log3(h[:3, :3])])


def pose_difference(a: np.ndarray, b: np.ndarray, task: TaskSpace) -> np.ndarray:
    """``a (-) b``: translation difference and the rotation taking b to a (world frame).

    Planar: ``[xa - xb, ya - yb, wrap(theta_a - theta_b)]``. Spatial: ``[pa - pb,
    log3(Ra Rb^T)]``. Point grasp: ``a - b``. This is the error ``x_vt - x_h`` of eq. 13 and
    of the coordination spring ``F_pc``.
    """
    if task.point:
        return np.asarray(a, dtype=float) - b
    if task is TaskSpace.PLANAR:
        d = a - b
        return np.array([d[0], d[1], wrap_angle(float(d[2]))])
    ra = pin.exp3(a[3:6])
    rb = pin.exp3(b[3:6])
    return np.concatenate([a[0:3] - b[0:3], pin.log3(ra @ rb.T)])


def integrate_pose(pose: np.ndarray, twist: np.ndarray, dt: float,
                   task: TaskSpace) -> np.ndarray:
    """Pose after moving with a constant world-frame twist for ``dt`` seconds.

    Planar angles are not wrapped, so a device angle stays continuous.
    """
    if task is TaskSpace.PLANAR or task.point:
        return pose + twist * dt
    r = pin.exp3(twist[3:6] * dt) @ pin.exp3(pose[3:6])
    return np.concatenate([pose[0:3] + twist[0:3] * dt, pin.log3(r)])


def translation_distance(a: np.ndarray, b: np.ndarray, task: TaskSpace) -> float:
    """Euclidean distance (m) between the translational parts of two poses."""
    rows = task.translation_rows
    return float(np.linalg.norm(a[rows] - b[rows]))
