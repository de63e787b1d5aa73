"""The ``ros_topics`` device backend: a haptic device that already has a ROS 2 driver.

Many haptic devices have ROS 2 drivers that publish the handle's pose and twist and take a
wrench (Geomagic/3D Systems Touch, Force Dimension, Haply, ...). :class:`RosTopicBackend`
reads such a device from ``geometry_msgs/PoseStamped`` + ``TwistStamped`` (+ optionally a
force sensor's ``WrenchStamped``) and commands it with ``WrenchStamped``, with topic names,
frames, axis mapping and units set by ``backend_options``
(:mod:`haptic_topology.device.topic_mapping`: the transform, the options and their checks).
It is selected as ``backend: ros_topics`` (the registry imports this module only then: the
core never imports rclpy).

**Threads.** The backend makes its own rclpy node (``node_name``; no global ROS arguments, so
the driver's remappings and parameters do not apply to it) with the subscriptions and the
command publisher, spun by its own :class:`~rclpy.experimental.EventsExecutor` in its own
thread (``ros_topics``), not the driver's executor and never the loop thread. A subscription
callback maps its message to task vectors and stores ``(arrival time, vector)`` as one tuple
(an attribute assignment: atomic under the GIL). In the driver's process rclpy is initialised
and the node joins its context (domain); elsewhere (a test, a tool without ROS) the backend
initialises a context of its own and shuts it down on ``deactivate``.

**Per cycle** (the 1 kHz deadline path): :meth:`~RosTopicBackend.read` takes the newest
stored samples and checks their age against a monotonic clock: no DDS call, no lock, no
wait. :meth:`~RosTopicBackend.write` fills one ``WrenchStamped`` (reused) and publishes it:
the publish *is* the device I/O here, as in ros2_control's topic-based hardware interfaces.

**Stale or missing device data is a device fault.** While a configured input (pose, twist,
wrench if given) has not delivered a sample within ``stale_ms`` (by arrival time), has
delivered none yet, or its newest sample was not valid (NaN/inf anywhere, a quaternion that
is not a unit quaternion), the reading carries :attr:`DeviceStatus.FAULT` and
:meth:`~RosTopicBackend.fault_reason` says which (``device data stale (23.1 ms on
/touch/pose, stale_ms 20)``). The driver then writes zero from the next cycle on, its states
carry ``STATUS_FAULT | STATUS_WATCHDOG``, its diagnostics are at ERROR, and the output fades
back in over the watchdog ramp once the data are fresh again: the same fade as for a stale
command (:class:`~haptic_topology.device.loop.DeviceLoop`). A faulted reading repeats the
newest valid pose with zero twist and zero hand wrench: nothing non-finite is passed on. A
restarted device driver (new publishers on the same topics) is picked up by DDS discovery;
once its samples arrive the fault clears by itself.

**Lifecycle** (ros2_control's). ``configure`` checks the options (no ROS yet);
``activate`` creates the node, subscriptions and publisher, starts the thread (or reuses
those a deactivated activation left) and waits up to ``connect_timeout_ms`` for a fresh valid
sample of every input (else :class:`DeviceError` naming what is missing); ``deactivate``
publishes zero (three copies: best effort may lose one) and stops commanding; ``cleanup``
(the driver's lifecycle cleanup and shutdown) stops the thread and destroys the node, so
nothing is left behind. The node outlives ``deactivate`` so that the zero reaches the device:
with the node destroyed right after it, the device's last command was not the zero in one of
a few runs of the lifecycle test (a reader may drop what it has not delivered yet of a writer
that is gone). Wall clock only: a device on its own clock cannot run lock-step.
A non-finite wrench given to ``write`` is sent as 0 on that axis and counted (the driver
clamps and checks before, so this does not happen through it).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node

from haptic_topology.device.backend import BackendConfig, DeviceBackend, DeviceReading
from haptic_topology.device.topic_mapping import (
    BACKEND,
    Sample,
    TopicOptions,
    input_fault,
    parse_topic_options,
)
from haptic_topology.errors import DeviceError
from haptic_topology.nodes.node_thread import NodeThread
from haptic_topology.nodes.qos import topic_qos
from haptic_topology.vocabulary import DeviceStatus, TaskSpace

#: Copies of the zero wrench sent by ``deactivate`` (best effort may lose one).
_ZERO_COPIES = 3


def _xyz(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


class RosTopicBackend(DeviceBackend):
    """A device behind ROS topics (module doc). ``clock_ns``: the monotonic clock (ns) of
    the samples' ages (tests may inject one)."""

    name = BACKEND
    # The device's ROS driver publishes on its own clock; the backend is a node of its own,
    # so it never runs in the rclpy-free loop process.
    lockstep, needs_ros = False, True

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock_ns = clock_ns
        self._opts: TopicOptions | None = None
        self._ros: NodeThread | None = None   # the backend's node, executor and thread
        self._ready = threading.Event()
        self._pub: Any = None
        self._enabled = False                 # between activate and deactivate
        self._msg = WrenchStamped()
        # Newest sample per input (None: none yet); written by the callbacks (activate
        # resets them).
        self._pose: Sample | None = None
        self._twist: Sample | None = None
        self._wrench: Sample | None = None
        self._theta: float | None = None      # previous planar angle (callback thread)
        self._device_frame = ''               # frame_id of the newest pose message
        # Kept by read for the faulted readings and fault_reason.
        self._last_pose = np.zeros(0)
        self._zero = np.zeros(0)
        self._reason = ''
        self._stale = False
        # Counters (read by any thread as they are).
        self.samples = {'pose': 0, 'twist': 0, 'wrench': 0}
        self.invalid_samples = 0
        self.commands_sent = 0
        self.nonfinite_writes = 0
        self.stale_cycles = self.stale_onsets = 0

    # -- configuration -----------------------------------------------------------------------
    def configure(self, config: BackendConfig) -> None:
        self._opts = parse_topic_options(config.options, config.params.task)
        # Until the device has sent a valid pose, a faulted reading reports the initial one.
        self._last_pose = np.array(config.initial_pose, dtype=float)
        self._zero = np.zeros(self.keep_task(config).dim)

    @property
    def options(self) -> TopicOptions:
        if self._opts is None:
            raise DeviceError(f'{self.name}: used before configure()')
        return self._opts

    @property
    def hardware_id(self) -> str:
        """``'ros_topics <task> <pose topic>'`` once configured (the task of :meth:`task`)."""
        return f'{super().hardware_id} {self._opts.pose_topic}' if self._opts else self.name

    def fault_reason(self) -> str:
        return self._reason or super().fault_reason()

    # -- lifecycle ---------------------------------------------------------------------------
    def activate(self) -> None:
        """Create the node, subscriptions, publisher and thread (unless a deactivated
        activation left them), then wait for a fresh valid sample of every input."""
        opts = self.options
        if self._enabled:
            return
        if self._ros is None:
            self._ros = NodeThread(opts.node_name, 'ros_topics',
                                   lambda node: self._setup(node, opts))
        self._ready.clear()
        self._pose = self._twist = self._wrench = None
        self._stale = False
        self._reason = ''
        if opts.connect_timeout > 0.0 and not self._ready.wait(opts.connect_timeout):
            missing = [t for t, s in self._inputs() if s is None or s[1] is None]
            self.cleanup()
            raise DeviceError(
                f'{self.name}: no valid device sample on {", ".join(missing)} within '
                f'connect_timeout_ms {1e3 * opts.connect_timeout:g} (is the device driver '
                'running, on this ROS_DOMAIN_ID, with these topic names and a compatible '
                'QoS? a best-effort publisher does not match qos: reliable)')
        self._enabled = True

    def _setup(self, node: Node, opts: TopicOptions) -> None:
        qos = topic_qos(opts.qos)
        node.create_subscription(PoseStamped, opts.pose_topic, self._on_pose, qos)
        node.create_subscription(TwistStamped, opts.twist_topic, self._on_twist, qos)
        if opts.wrench_topic:
            node.create_subscription(WrenchStamped, opts.wrench_topic, self._on_wrench, qos)
        self._pub = node.create_publisher(WrenchStamped, opts.command_topic,
                                          topic_qos(opts.command_qos))
        self._msg.header.frame_id = opts.frame_id

    def _context_ok(self) -> bool:
        return self._ros is not None and self._ros.context_ok()

    def deactivate(self) -> None:
        """Publish zero (three copies: best effort may lose one) and stop commanding. The
        node stays until :meth:`cleanup`, so that the zero reaches the device (module doc)."""
        if self._enabled and self._pub is not None and self._context_ok():
            for _ in range(_ZERO_COPIES):
                self._publish(self._zero)
        self._enabled = False

    def cleanup(self) -> None:
        """Stop the thread, destroy the node (and the context the backend made)."""
        self.deactivate()
        self._pub = None
        if self._ros is not None:
            self._ros.close()
        self._ros = None

    # -- callbacks (the backend's thread) ----------------------------------------------------
    def _bad(self, what: str, topic: str) -> Sample:
        self.invalid_samples += 1
        return (self._clock_ns(), None, f'device data not valid: {what} on {topic}')

    def _on_pose(self, msg: PoseStamped) -> None:
        opts = self.options
        pose = opts.mapping.pose(_xyz(msg.pose.position),
                                 (*_xyz(msg.pose.orientation), msg.pose.orientation.w),
                                 self._theta)
        self.samples['pose'] += 1
        if pose is None:
            self._pose = self._bad('non-finite position or not a unit quaternion',
                                   opts.pose_topic)
        else:
            if opts.mapping.task is TaskSpace.PLANAR:
                self._theta = float(pose[2])
            if not opts.frame_id and msg.header.frame_id != self._device_frame:
                self._device_frame = msg.header.frame_id
            self._pose = (self._clock_ns(), pose, '')
        self._check_ready()

    def _on_twist(self, msg: TwistStamped) -> None:
        opts = self.options
        twist = opts.mapping.twist(_xyz(msg.twist.linear), _xyz(msg.twist.angular))
        self.samples['twist'] += 1
        self._twist = (self._bad('non-finite twist', opts.twist_topic) if twist is None
                       else (self._clock_ns(), twist, ''))
        self._check_ready()

    def _on_wrench(self, msg: WrenchStamped) -> None:
        opts = self.options
        wrench = opts.mapping.hand_wrench(_xyz(msg.wrench.force), _xyz(msg.wrench.torque))
        self.samples['wrench'] += 1
        self._wrench = (self._bad('non-finite wrench', opts.wrench_topic) if wrench is None
                        else (self._clock_ns(), wrench, ''))
        self._check_ready()

    def _check_ready(self) -> None:
        if not self._ready.is_set() and all(s is not None and s[1] is not None
                                            for _, s in self._inputs()):
            self._ready.set()

    def _inputs(self) -> list[tuple[str, Sample | None]]:
        opts = self.options
        out = [(opts.pose_topic, self._pose), (opts.twist_topic, self._twist)]
        if opts.wrench_topic:
            out.append((opts.wrench_topic, self._wrench))
        return out

    # -- the device cycle (the loop thread) --------------------------------------------------
    def write(self, wrench: np.ndarray) -> None:
        if not self._enabled:
            raise DeviceError(f'{self.name}: write() while not active (before activate() '
                              'or after deactivate())')
        u = np.asarray(wrench, dtype=float)
        if not np.all(np.isfinite(u)):
            self.nonfinite_writes += 1
            u = np.where(np.isfinite(u), u, 0.0)
        self._publish(u)

    def _publish(self, u: np.ndarray) -> None:
        assert self._opts is not None
        f, t = self._opts.mapping.command(u)
        msg = self._msg
        sec, nsec = divmod(time.time_ns(), 1_000_000_000)
        msg.header.stamp.sec = sec
        msg.header.stamp.nanosec = nsec
        if not self._opts.frame_id and msg.header.frame_id != self._device_frame:
            msg.header.frame_id = self._device_frame
        w = msg.wrench
        w.force.x, w.force.y, w.force.z = f
        w.torque.x, w.torque.y, w.torque.z = t
        self._pub.publish(msg)
        self.commands_sent += 1

    def read(self, dt: float) -> DeviceReading:
        opts = self.options
        now = self._clock_ns()
        pose_s, twist_s = self._pose, self._twist
        wrench_s = self._wrench if opts.wrench_topic else (0, self._zero, '')
        ros = self._ros
        if not self._enabled or ros is None:
            raise DeviceError(f'{self.name}: read() while not active (before activate() or '
                              'after deactivate())')
        reason = ('' if ros.alive() else
                  f'{self.name}: the thread taking the device data has ended (see log)') or \
            input_fault(((opts.pose_topic, pose_s), (opts.twist_topic, twist_s),
                         (opts.wrench_topic, wrench_s)), now, opts.stale_ns)
        if reason:
            self._reason = reason
            self.stale_cycles += 1
            if not self._stale:
                self.stale_onsets += 1
            self._stale = True
            return DeviceReading(self._last_pose, self._zero, self._zero, DeviceStatus.FAULT)
        self._stale = False
        assert pose_s is not None and twist_s is not None and wrench_s is not None
        pose = pose_s[1]
        assert pose is not None and twist_s[1] is not None and wrench_s[1] is not None
        self._last_pose = pose
        return DeviceReading(pose, twist_s[1], wrench_s[1])
