"""Visualisation messages of the VE (``ve_sim``): joint states and the linkage as markers.

Markers in ``frame_id`` (the world frame of the linkage), metres: the linkage as a line
through its joints and the distal link's end, the VT grasp point, the device point, and an
arrow 20 mm long (times the penalty weight) along each direction of topological constraint
``n_tc`` (eq. 13) at the grasp point, deleted while that direction is not constrained.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pinocchio as pin
from geometry_msgs.msg import Point
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker, MarkerArray

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.model.linkage import Linkage

#: Length (m) of a constraint-direction arrow at full penalty weight.
ARROW_LENGTH = 0.02


def joint_state(linkage: Linkage, q: np.ndarray, dq: np.ndarray, stamp: Any) -> JointState:
    js = JointState()
    js.header.stamp = stamp
    js.name = list(linkage.link_names)
    js.position = q.tolist()
    js.velocity = dq.tolist()
    return js


def joint_points(dyn: LinkageDynamics, q: np.ndarray) -> np.ndarray:
    """World positions (m) of every joint and of the distal link's end, (d + 1) x 3."""
    pin.framesForwardKinematics(dyn.model, dyn.data, q)
    pts = [np.array(dyn.data.oMi[j].translation) for j in range(1, dyn.model.njoints)]
    last = dyn.linkage.links[-1]
    pts.append(np.array(dyn.data.oMi[dyn.model.njoints - 1].act(
        np.array([last.length, 0.0, 0.0]))))
    return np.array(pts)


def _point(p: np.ndarray) -> Point:
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]) if p.size > 2 else 0.0)


def linkage_markers(dyn: LinkageDynamics, q: np.ndarray, device_pose: np.ndarray | None,
                    snap: LmiSnapshot, frame: str, stamp: Any) -> MarkerArray:
    """The markers of the module doc (``dyn``: a Pinocchio workspace of its own)."""
    task = dyn.task
    hand = dyn.hand_placement(q).translation

    def marker(mid: int, ns: str, kind: int, rgb: tuple[float, float, float],
               scale: float) -> Marker:
        mk = Marker()
        mk.header.stamp = stamp
        mk.header.frame_id = frame
        mk.ns, mk.id, mk.type, mk.action = ns, mid, kind, Marker.ADD
        mk.pose.orientation.w = 1.0
        mk.scale.x = mk.scale.y = mk.scale.z = scale
        mk.color.r, mk.color.g, mk.color.b = rgb
        mk.color.a = 1.0
        return mk

    link = marker(0, 'linkage', Marker.LINE_STRIP, (0.2, 0.4, 0.9), 0.004)
    link.points = [_point(p) for p in joint_points(dyn, q)]
    grasp = marker(1, 'grasp', Marker.SPHERE, (0.1, 0.8, 0.1), 0.006)
    grasp.pose.position = _point(hand)
    markers = MarkerArray()
    markers.markers = [link, grasp]
    if device_pose is not None:
        dev = marker(2, 'device', Marker.SPHERE, (0.9, 0.2, 0.2), 0.006)
        dev.pose.position = _point(device_pose[:3] if task.dim == 6 else device_pose[:2])
        markers.markers.append(dev)
    rows = task.translation_rows
    for i in range(snap.left_vectors.shape[1]):
        arrow = marker(10 + i, 'constraint', Marker.ARROW, (1.0, 0.6, 0.0), 0.002)
        direction = snap.left_vectors[rows, i]
        norm = float(np.linalg.norm(direction))
        if snap.weights[i] <= 0.0 or norm < 1e-9:
            arrow.action = Marker.DELETE
        else:
            tip = hand.copy()
            tip[: direction.size] += ARROW_LENGTH * float(snap.weights[i]) * direction / norm
            arrow.points = [_point(hand), _point(tip)]
            arrow.scale.y = arrow.scale.z = 0.004
        markers.markers.append(arrow)
    return markers
