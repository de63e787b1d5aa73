"""What a haptic device's own ROS 2 driver publishes, from task vectors: ``PoseStamped``,
``TwistStamped`` and the hand's ``WrenchStamped`` in the device's frame and units (a
:class:`~haptic_topology.device.topic_mapping.TopicMapping`), stamped ``ns`` (wall clock).
The simulated device of :mod:`haptic_topology.nodes.topic_device` fills its messages so."""

from __future__ import annotations

from typing import Any

import numpy as np

from haptic_topology.device.topic_mapping import TopicMapping


def _stamp(msg: Any, ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)


def _set3(v: Any, a: np.ndarray) -> None:
    v.x, v.y, v.z = (float(x) for x in a)


def fill_pose(msg: Any, mapping: TopicMapping, pose: np.ndarray, ns: int) -> Any:
    """``msg`` (a ``PoseStamped``) at the task pose ``pose``; returns ``msg``."""
    p, q = mapping.device_pose(pose)
    _stamp(msg, ns)
    _set3(msg.pose.position, p)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = q
    return msg


def fill_twist(msg: Any, mapping: TopicMapping, twist: np.ndarray, ns: int) -> Any:
    """``msg`` (a ``TwistStamped``) at the task twist ``twist``; returns ``msg``."""
    v, w = mapping.device_twist(twist)
    _stamp(msg, ns)
    _set3(msg.twist.linear, v)
    _set3(msg.twist.angular, w)
    return msg


def fill_wrench(msg: Any, mapping: TopicMapping, wrench: np.ndarray, ns: int) -> Any:
    """``msg`` (a ``WrenchStamped``) holding the task wrench ``wrench`` (the hand's);
    returns ``msg``."""
    f, tq = mapping.device_wrench(wrench)
    _stamp(msg, ns)
    _set3(msg.wrench.force, f)
    _set3(msg.wrench.torque, tq)
    return msg
