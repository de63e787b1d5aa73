"""``ve_sim``'s picture of the linkage: ``/robot_description`` once, and at ``viz_rate_hz``
``/tf``, the joint state, the markers and the standard mirrors (see :mod:`.ve_sim` and
:mod:`.viz`), from the VE's state and the newest device and coupling samples.

The device's applied wrench and ``F_env`` come from the newest ``DeviceState`` of
``haptic/device/state_sampled`` (the states ``device_driver`` samples at
``sampled_state_rate_hz``, 30 a second by default; not every one of the 1 kHz loop's), taken
at the viz rate from a keep-last-1 reader that no executor spins
(:class:`~haptic_topology.nodes.take.LatestTaker`, no callback per state). Until one comes
(or with sampling off) the device is drawn from the hand input batches, without them.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.model.urdf import robot_description
from haptic_topology.nodes import markers, viz
from haptic_topology.nodes.convert import GraphFilter, MessageError, stamp_ns
from haptic_topology.nodes.qos import QOS_LATCHED, QOS_SAMPLED, QOS_TF, QOS_VIZ
from haptic_topology.nodes.take import LatestTaker
from haptic_topology.sim.scenario import Scenario
from haptic_topology.vocabulary import (
    TOPIC_DEVICE_POSE,
    TOPIC_DEVICE_TWIST,
    TOPIC_JOINTS,
    TOPIC_MARKERS,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_STATE_SAMPLED,
    TOPIC_TF,
    TOPIC_VT_POSE,
    TOPIC_VT_TWIST,
    TOPIC_WRENCH_APPLIED,
    TOPIC_WRENCH_COUPLING,
    TOPIC_WRENCH_HAND,
)
from haptic_topology_msgs.msg import DeviceState, HandInputs


class VeViz:
    """The viz publishers of ``node`` (the VE) for ``scenario``, with a Pinocchio workspace
    of their own; ``q0``: the VE's initial joint positions (the plane of a planar picture)."""

    def __init__(self, node: Node, scenario: Scenario, frame_id: str, q0: np.ndarray,
                 graph: GraphFilter) -> None:
        self.node = node
        self.graph = graph          # device states of other graphs are not drawn
        self.task = scenario.linkage.task
        self._viz_dyn = LinkageDynamics(scenario.linkage)     # separate Pinocchio workspace
        self.robot = robot_description(scenario.linkage)
        self.viz = viz.RobotViz(self.robot, self._viz_dyn, frame_id)
        self.joint_pub = node.create_publisher(JointState, TOPIC_JOINTS, QOS_VIZ)
        self.marker_pub = node.create_publisher(MarkerArray, TOPIC_MARKERS, QOS_VIZ)
        self.description_pub = node.create_publisher(
            String, TOPIC_ROBOT_DESCRIPTION, QOS_LATCHED)
        self.tf_pub = node.create_publisher(TFMessage, TOPIC_TF, QOS_TF)
        self.mirror_pubs = {
            topic: node.create_publisher(kind, topic, QOS_VIZ) for topic, kind in (
                (TOPIC_DEVICE_POSE, PoseStamped),
                (TOPIC_DEVICE_TWIST, TwistStamped),
                (TOPIC_VT_POSE, PoseStamped), (TOPIC_VT_TWIST, TwistStamped),
                (TOPIC_WRENCH_APPLIED, WrenchStamped),
                (TOPIC_WRENCH_HAND, WrenchStamped),
                (TOPIC_WRENCH_COUPLING, WrenchStamped))}
        #: The newest device sample (a DeviceState, or a HandInputs sample before the
        #: state reader has one) and F_pc sample; stamps (ns) last sent.
        self._state_taker: LatestTaker | None = LatestTaker(
            node, TOPIC_STATE_SAMPLED, DeviceState, QOS_SAMPLED, suffix='viz_reader')
        self._device: markers.DeviceSample | None = None
        self._from_states = False       # _device is (was) a sampled state
        self._coupling: markers.CouplingSample | None = None
        self._sent_device_ns = self._sent_coupling_ns = self._sent_ve_ns = -1
        self.rejected_states = 0
        self._plane_z = self.viz.plane_z(q0)
        self.description_pub.publish(self.viz.robot_description)

    @property
    def device_states(self) -> int:
        """Device states taken for the picture."""
        return 0 if self._state_taker is None else self._state_taker.taken

    def keep_samples(self, msg: HandInputs, pose: np.ndarray, twist: np.ndarray,
                     q: np.ndarray) -> None:
        """The batch's newest sample for the viz (the VE now holds the state after it,
        ``q``); for the device too until a sampled state has come."""
        m = self.task.dim
        stamp = msg.stamp[-1]
        if not self._from_states and (self._device is None
                                      or self._device.ns < stamp_ns(stamp)):
            self._device = markers.DeviceSample(stamp, pose, twist,
                                            np.array(msg.hand_wrench[-m:], dtype=float))
        self._coupling = markers.CouplingSample(stamp, np.array(msg.coupling_wrench[-m:],
                                                            dtype=float), q)

    def _take_device_state(self) -> None:
        """The newest sampled DeviceState, if one came since the last viz tick: from then on
        the device is drawn from these only (a hand input sample, often newer, has no
        applied wrench and ``F_env``). Checked; a bad one is skipped and counted in
        ``rejected_states``, apart from the messages the VE takes: it changes nothing but
        the picture."""
        if self._state_taker is None:
            return
        msg = self._state_taker.take()
        if msg is None or not self.graph.own(msg, TOPIC_STATE_SAMPLED):
            return
        try:
            sample = markers.device_sample(msg, self.task)
        except MessageError:
            self.rejected_states += 1
            return
        self._device = sample
        self._from_states = True

    def publish(self, q: np.ndarray, dq: np.ndarray, snapshot: LmiSnapshot) -> None:
        """Joint state, markers, /tf and the mirrors (module doc). The VE's (stamped now)
        only when the clock moved since the last ones (tf2 drops a repeated stamp, and one
        stamp is one VE state; in lock-step simulated time may stand still between two
        ticks), the device's and the coupling's only for a sample not sent yet."""
        stamp = self.node.get_clock().now().to_msg()
        v = self.viz
        self._take_device_state()
        device, coupling, pubs = self._device, self._coupling, self.mirror_pubs
        if stamp_ns(stamp) != self._sent_ve_ns:
            self._sent_ve_ns = stamp_ns(stamp)
            tf, joints, vt_pose, vt_twist = v.ve(q, dq, stamp)
            self.joint_pub.publish(joints)
            self.tf_pub.publish(tf)
            pubs[TOPIC_VT_POSE].publish(vt_pose)
            pubs[TOPIC_VT_TWIST].publish(vt_twist)
            self.marker_pub.publish(v.markers(q, device, coupling, snapshot, stamp))
        if device is not None and device.ns != self._sent_device_ns:
            self._sent_device_ns = device.ns
            tf, pose, twist, hand, applied = v.device(device, self._plane_z)
            self.tf_pub.publish(tf)
            pubs[TOPIC_DEVICE_POSE].publish(pose)
            pubs[TOPIC_DEVICE_TWIST].publish(twist)
            pubs[TOPIC_WRENCH_HAND].publish(hand)
            if applied is not None:
                pubs[TOPIC_WRENCH_APPLIED].publish(applied)
        if coupling is not None and coupling.ns != self._sent_coupling_ns:
            self._sent_coupling_ns = coupling.ns
            pubs[TOPIC_WRENCH_COUPLING].publish(v.coupling(coupling))

    def close(self) -> None:
        """Destroy the device-state reader's helper node."""
        if self._state_taker is not None:
            self._state_taker.destroy()
            self._state_taker = None
