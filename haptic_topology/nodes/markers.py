"""The linkage as markers (``visualization_msgs/MarkerArray``): links, grasp point, the closing
joints of a closed chain, device ghost (a box with the device's orientation; a ball for a
point grasp, which has none), constraint directions and wrenches, from the VE's state and the
newest device and coupling samples (:class:`DeviceSample`, :class:`CouplingSample`). Used by
:class:`~haptic_topology.nodes.viz.RobotViz`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (
    Point,
)
from visualization_msgs.msg import Marker, MarkerArray

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.messages.check import check_state, env_wrench
from haptic_topology.model import frames
from haptic_topology.vocabulary import TaskSpace

#: Length (m) of a constraint-direction arrow at full penalty weight.
ARROW_LENGTH = 0.02


#: Length (m) of a force arrow per newton.
FORCE_SCALE = 0.05


#: Side (m) of the device ghost.
DEVICE_SIZE = 0.008


@dataclass(frozen=True)
class DeviceSample:
    """The device at one cycle, as shown: from a ``DeviceState`` (``applied`` and ``env``
    known) or a ``HandInputs`` sample (None). Task vectors, world axes."""

    stamp: Time
    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    applied: np.ndarray | None = None
    env: np.ndarray | None = None

    @property
    def ns(self) -> int:
        return int(self.stamp.sec) * 1_000_000_000 + int(self.stamp.nanosec)


@dataclass(frozen=True)
class CouplingSample:
    """The coordination wrench ``F_pc`` of one ``HandInputs`` sample (world axes, at the grasp
    point) and the VE's joint positions after that sample."""

    stamp: Time
    wrench: np.ndarray
    q: np.ndarray

    @property
    def ns(self) -> int:
        return int(self.stamp.sec) * 1_000_000_000 + int(self.stamp.nanosec)


def device_sample(msg: Any, task: TaskSpace) -> DeviceSample:
    """A checked ``DeviceState`` as a :class:`DeviceSample` (raises
    :class:`~haptic_topology.messages.check.MessageError` naming the bad field)."""
    _, _, pose, twist, f_h, applied, _ = check_state(msg, task.dim)
    return DeviceSample(msg.header.stamp, pose, twist, f_h, applied, env_wrench(msg, task.dim))


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


def linkage_markers(dyn: LinkageDynamics, q: np.ndarray, device: DeviceSample | None,
                    coupling: CouplingSample | None, snap: LmiSnapshot, frame: str,
                    stamp: Time, kept: dict[tuple[str, int], Marker] | None = None
                    ) -> MarkerArray:
    """The markers of the module doc (``dyn``: a Pinocchio workspace of its own).

    ``kept``: the markers of the previous call, by ``(ns, id)``, filled again in place (a
    ``Marker`` costs ~50 us to construct, ten of them at 30 Hz; the caller publishes the
    array before the next call)."""
    task = dyn.task
    hand = np.asarray(dyn.hand_placement(q).translation)
    store: dict[tuple[str, int], Marker] = {} if kept is None else kept

    def marker(mid: int, ns: str, kind: int, rgb: tuple[float, float, float],
               scale: float, alpha: float = 1.0) -> Marker:
        mk = store.get((ns, mid))
        if mk is None:
            mk = store[(ns, mid)] = Marker()
            mk.header.frame_id = frame
            mk.ns, mk.id, mk.type = ns, mid, kind
            mk.pose.orientation.w = 1.0
            mk.color.r, mk.color.g, mk.color.b = rgb
            mk.color.a = alpha
        mk.header.stamp = stamp
        mk.action = Marker.ADD
        mk.scale.x = mk.scale.y = mk.scale.z = scale
        return mk

    def arrow(mid: int, ns: str, rgb: tuple[float, float, float], start: np.ndarray,
              vector: np.ndarray | None) -> Marker:
        mk = marker(mid, ns, Marker.ARROW, rgb, 0.002)
        if vector is None or float(np.linalg.norm(vector)) < 1e-9:
            mk.action = Marker.DELETE
            mk.points = []
            return mk
        mk.points = [_point(start), _point(start + vector)]
        mk.scale.y = mk.scale.z = 0.004
        return mk

    link = marker(0, 'linkage', Marker.LINE_STRIP, (0.2, 0.4, 0.9), 0.004)
    link.points = [_point(p) for p in joint_points(dyn, q)]
    grasp = marker(1, 'grasp', Marker.SPHERE, (0.1, 0.8, 0.1), 0.006)
    grasp.pose.position = _point(hand)
    markers = MarkerArray()
    markers.markers = [link, grasp]
    if dyn.loops is not None:      # the closing joints: both points of each closure
        closing = marker(3, 'loops', Marker.SPHERE_LIST, (0.2, 0.4, 0.9), 0.006)
        closing.points = [_point(np.asarray(dyn.data.oMf[f].translation))
                          for ends in dyn.loops.ends for f in ends]
        markers.markers.append(closing)
    dev_point = None
    if device is not None:
        # A point grasp's device pose is a point: a ball, which shows no orientation.
        ghost = marker(2, 'device', Marker.SPHERE if task.point else Marker.CUBE,
                       (0.9, 0.2, 0.2), DEVICE_SIZE, alpha=0.5)
        t, quat = frames.pose_transform(device.pose, task, float(hand[2]))
        dev_point = t
        ghost.pose.position = _point(t)
        o = ghost.pose.orientation
        o.x, o.y, o.z, o.w = quat.tolist()
        markers.markers.append(ghost)
    rows = task.translation_rows
    for i in range(snap.left_vectors.shape[1]):
        direction = snap.left_vectors[rows, i]
        norm = float(np.linalg.norm(direction))
        vec = None
        if snap.weights[i] > 0.0 and norm >= 1e-9:
            vec = np.zeros(3)
            vec[: direction.size] = ARROW_LENGTH * float(snap.weights[i]) * direction / norm
        markers.markers.append(arrow(10 + i, 'constraint', (1.0, 0.6, 0.0), hand, vec))

    def force(w: np.ndarray | None) -> np.ndarray | None:
        return None if w is None else FORCE_SCALE * frames.spatial(w, task)[0:3]

    at_device = dev_point if dev_point is not None else hand
    markers.markers += [
        arrow(20, 'F_h', (0.1, 0.7, 0.1), at_device,
              force(None if device is None else device.hand_wrench)),
        arrow(21, 'u', (0.9, 0.1, 0.1), at_device,
              force(None if device is None else device.applied)),
        arrow(22, 'F_pc', (0.7, 0.1, 0.8), hand,
              force(None if coupling is None else coupling.wrench)),
        arrow(23, 'F_env', (0.5, 0.35, 0.2), hand,
              force(None if device is None else device.env)),
    ]
    return markers


