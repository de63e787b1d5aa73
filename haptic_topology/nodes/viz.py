"""Visualisation messages of the VE (``ve_sim``): the linkage as a robot, frames, markers and
standard mirrors, for RViz, Foxglove and PlotJuggler with no plugin of ours.

Frames and what each header names: :mod:`haptic_topology.model.frames`. Topics (names and QoS in
:mod:`haptic_topology.vocabulary` and :mod:`haptic_topology.nodes.qos`):

* ``/robot_description`` (``std_msgs/String``, transient local, once): the URDF of
  :func:`haptic_topology.model.urdf.robot_description`;
* ``/tf`` (``tf2_msgs/TFMessage``): world -> root link -> every URDF link (parent -> child per
  URDF joint) -> ``vt_hand``, and world -> ``device_base``, stamped with the time they are
  published at (the VE's state then); ``device_base`` -> ``device`` with the stamp of the
  device state it shows;
* ``haptic/joint_states`` (``sensor_msgs/JointState``): named after the URDF's joints (the
  chain's, then locked side-branch joints at their positions, zero velocity);
* ``haptic/markers``: in the world frame: the linkage as a line through its joints, the VT
  grasp point, the device as a translucent box with its orientation (the device ghost; a
  translucent ball for a point grasp, whose device pose is a point), an
  arrow :data:`~haptic_topology.nodes.markers.ARROW_LENGTH` long (times the penalty weight)
  along each direction of topological constraint ``n_tc`` (eq. 13) at the grasp point
  (deleted while not constrained), and force arrows
  :data:`~haptic_topology.nodes.markers.FORCE_SCALE` m per N: ``F_h`` (the user's hand) and
  ``u`` (applied by the device) at the device, ``F_pc`` (coordination, on the VT) and
  ``F_env`` (the controller's contacts, eqs. 10 and 14) at the grasp point;
* mirrors (``geometry_msgs``): ``PoseStamped``/``TwistStamped`` of the device (frame
  ``device_base``; twist: the device point's velocity and the angular velocity, world axes)
  and of the VT hand (world frame, same convention); ``WrenchStamped`` of the applied wrench
  ``u`` and the hand wrench ``F_h`` in frame ``device``, and of the coupling wrench ``F_pc``
  in frame ``vt_hand`` (components in that frame's axes, acting at its origin). The device
  ones carry the stamp of the ``DeviceState`` (or ``HandInputs`` sample) they copy, the
  coupling one that of its ``HandInputs`` sample, expressed in the VT hand's axes at that
  sample (the VE's state after it).

A planar task has no z: the device is drawn in the plane of the grasp point. A point grasp
(``planar_point``, ``spatial_point``) has no orientation: ``vt_hand`` and ``device`` keep the
world's axes, the pose mirrors carry the identity quaternion, the twists no angular velocity
and the wrenches no torque.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (
    PoseStamped,
    TransformStamped,
    TwistStamped,
    WrenchStamped,
)
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.model import frames
from haptic_topology.model.urdf import LinkFrames, RobotDescription
from haptic_topology.nodes.markers import (
    CouplingSample,
    DeviceSample,
    linkage_markers,
)


def _set_transform(ts: TransformStamped, stamp: Time, row: list[float]) -> None:
    ts.header.stamp = stamp
    t, r = ts.transform.translation, ts.transform.rotation
    t.x, t.y, t.z, r.x, r.y, r.z, r.w = row


def _set_pose(msg: PoseStamped, stamp: Time, t: np.ndarray, quat: np.ndarray) -> None:
    msg.header.stamp = stamp
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = t.tolist()
    o.x, o.y, o.z, o.w = quat.tolist()


def _set_twist(msg: TwistStamped, stamp: Time, v6: np.ndarray) -> None:
    msg.header.stamp = stamp
    lin, ang = msg.twist.linear, msg.twist.angular
    lin.x, lin.y, lin.z, ang.x, ang.y, ang.z = v6.tolist()


def _set_wrench(msg: WrenchStamped, stamp: Time, w6: np.ndarray) -> None:
    msg.header.stamp = stamp
    f, tau = msg.wrench.force, msg.wrench.torque
    f.x, f.y, f.z, tau.x, tau.y, tau.z = w6.tolist()


def _stamped(cls: Any, frame: str) -> Any:
    msg = cls()
    msg.header.frame_id = frame
    return msg


class RobotViz:
    """The visualisation messages of one linkage, allocated once and filled per call.

    ``dyn``: a Pinocchio workspace of its own (not the VE's); ``world``: the world frame
    (``ve_sim`` parameter ``frame_id``).
    """

    def __init__(self, description: RobotDescription, dyn: LinkageDynamics,
                 world: str) -> None:
        self.description = description
        self.dyn = dyn
        self.task = dyn.task
        self.world = world
        self.frames = LinkFrames(description, world)
        self.robot_description = String(data=description.urdf)
        tf = self.tf_ve = TFMessage()
        for parent, child in (*self.frames.edges, (world, frames.DEVICE_BASE)):
            ts = _stamped(TransformStamped, parent)
            ts.child_frame_id = child
            tf.transforms.append(ts)
        self._identity = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        self.tf_device = TFMessage()
        ts = _stamped(TransformStamped, frames.DEVICE_BASE)
        ts.child_frame_id = frames.DEVICE
        self.tf_device.transforms.append(ts)
        self.joint_state = _stamped(JointState, description.root_link)
        self.joint_state.name = list(description.joint_names)
        self._zeros = np.zeros(len(description.locked))
        self.vt_pose = _stamped(PoseStamped, world)
        self.vt_twist = _stamped(TwistStamped, world)
        self.device_pose = _stamped(PoseStamped, frames.DEVICE_BASE)
        self.device_twist = _stamped(TwistStamped, frames.DEVICE_BASE)
        self.applied_wrench = _stamped(WrenchStamped, frames.DEVICE)
        self.hand_wrench = _stamped(WrenchStamped, frames.DEVICE)
        self.coupling_wrench = _stamped(WrenchStamped, frames.VT_HAND)
        self._markers: dict[tuple[str, int], Marker] = {}     # linkage_markers' own

    def _hand_rotation(self, link: np.ndarray) -> np.ndarray:
        """The ``vt_hand`` frame's rotation in the world: the grasped link's (``link``), the
        identity for a point grasp (the world's axes, as on ``/tf``)."""
        return np.eye(3) if self.task.point else link

    def plane_z(self, q: np.ndarray) -> float:
        """Height (m) of the grasp point: the plane a planar device pose is drawn in."""
        return float(self.dyn.hand_placement(q).translation[2])

    # -- the VE ----------------------------------------------------------------------------------
    def ve(self, q: np.ndarray, dq: np.ndarray, stamp: Time
           ) -> tuple[TFMessage, JointState, PoseStamped, TwistStamped]:
        """``/tf`` of the links and ``vt_hand``, the joint state and the VT hand mirrors at the
        VE state ``(q, dq)``."""
        rows = self.frames.transforms(q).tolist() + [self._identity]
        for ts, row in zip(self.tf_ve.transforms, rows, strict=True):
            _set_transform(ts, stamp, row)
        js = self.joint_state
        js.header.stamp = stamp
        js.position = self.description.positions(q).tolist()
        js.velocity = np.concatenate([dq, self._zeros]).tolist()
        hand = self.dyn.hand_placement(q)
        _set_pose(self.vt_pose, stamp, np.asarray(hand.translation),
                  frames.quaternion(self._hand_rotation(hand.rotation)))
        _set_twist(self.vt_twist, stamp, frames.spatial(self.dyn.hand_twist(q, dq), self.task))
        return self.tf_ve, js, self.vt_pose, self.vt_twist

    # -- the device ------------------------------------------------------------------------------
    def device(self, sample: DeviceSample, z: float
               ) -> tuple[TFMessage, PoseStamped, TwistStamped, WrenchStamped,
                          WrenchStamped | None]:
        """``device_base -> device``, the device's pose and twist, its hand wrench and (from a
        ``DeviceState``) the applied wrench, stamped with the sample's stamp; ``z``: the
        plane of a planar pose."""
        stamp, task = sample.stamp, self.task
        t, quat = frames.pose_transform(sample.pose, task, z)
        _set_transform(self.tf_device.transforms[0], stamp, t.tolist() + quat.tolist())
        _set_pose(self.device_pose, stamp, t, quat)
        _set_twist(self.device_twist, stamp, frames.spatial(sample.twist, task))
        rot = frames.pose_rotation(sample.pose, task)
        _set_wrench(self.hand_wrench, stamp, frames.wrench_in_frame(sample.hand_wrench, rot,
                                                                    task))
        applied = None
        if sample.applied is not None:
            applied = self.applied_wrench
            _set_wrench(applied, stamp, frames.wrench_in_frame(sample.applied, rot, task))
        return self.tf_device, self.device_pose, self.device_twist, self.hand_wrench, applied

    def coupling(self, sample: CouplingSample) -> WrenchStamped:
        """``F_pc`` in the ``vt_hand`` frame at the VE state after its sample."""
        rot = self._hand_rotation(self.dyn.hand_placement(sample.q).rotation)
        _set_wrench(self.coupling_wrench, sample.stamp,
                    frames.wrench_in_frame(sample.wrench, rot, self.task))
        return self.coupling_wrench

    # -- markers ---------------------------------------------------------------------------------
    def markers(self, q: np.ndarray, device: DeviceSample | None,
                coupling: CouplingSample | None, snap: LmiSnapshot, stamp: Time
                ) -> MarkerArray:
        """The markers of the module doc at the VE's ``q``."""
        return linkage_markers(self.dyn, q, device, coupling, snap, self.world, stamp,
                               self._markers)


