"""The project's vocabulary: the one source of its modes, status bits, task spaces, clocks,
topic names and types, and QoS roles.

Every other module derives its strings, integers and labels from here (the CLI's choices, the
parameters' choices, the message checks, the bag analysis, the nodes' publishers). This module
imports nothing of the project but :mod:`haptic_topology.errors`, and no rclpy: the QoS roles
are plain data that ``haptic_topology.nodes.qos`` turns into ``rclpy`` profiles.

The integer values of :class:`ControlMode` and :class:`DeviceStatus` are those of the
messages' constants (``haptic_topology_msgs/DeviceCommand.MODE_*``,
``DeviceState.STATUS_*``); ``haptic_topology.nodes.convert`` checks them against the
generated message classes at import.
"""

from __future__ import annotations

import enum
import functools
import operator
from dataclasses import dataclass

from haptic_topology.errors import ConfigError


# -- modes, status, task spaces, clocks --------------------------------------------------------
class ControlMode(enum.IntEnum):
    """Control law; values equal ``haptic_topology_msgs/DeviceCommand.MODE_*``."""

    PENALTY = 0             # eq. 14: eq. 10 plus penalties along N(J_h^T) (eq. 13)
    ACCELERATION_ONLY = 1   # eq. 10: topology at the acceleration level only
    ZERO = 2                # no force (safe state)

    @classmethod
    def parse(cls, name: str) -> ControlMode:
        """Mode from its CLI / parameter name: penalty, acceleration_only, zero."""
        try:
            return cls[name.upper()]
        except KeyError:
            raise ValueError(f'mode: expected one of penalty, acceleration_only, zero, got '
                             f'{name!r}') from None

    @property
    def label(self) -> str:
        return self.name.lower()


class DeviceStatus(enum.IntFlag):
    """Bits of ``haptic_topology_msgs/DeviceState.status``."""

    OK = 0
    WORKSPACE_LIMIT = 1
    SATURATED = 2
    WATCHDOG = 4    # output is not the plain command: none yet, stale, or fading in/out
    FAULT = 8       # the backend reports a device fault: the driver writes zero while it lasts
    IDLE = 16       # not engaged yet (always with WATCHDOG): controllers integrate nothing


_STATUS_MEMBERS: dict[int, DeviceStatus] = {}


def device_status(bits: int) -> DeviceStatus:
    """``DeviceStatus(bits)``, looked up: building an ``IntFlag`` value (or or-ing two) costs
    microseconds, a lookup a tenth of one, and the device cycle makes one per state."""
    status = _STATUS_MEMBERS.get(bits)
    if status is None:
        status = _STATUS_MEMBERS[bits] = DeviceStatus(bits)
    return status


class Axis(enum.Enum):
    """One axis of a device in the world frame: a translation (force along it) or a rotation
    (torque about it). What a task needs (:attr:`TaskSpace.axes`) and what a device backend
    senses and actuates (``haptic_topology.device.backend.DeviceAxes``) are sets of these."""

    X = 'x'
    Y = 'y'
    Z = 'z'
    RX = 'rx'
    RY = 'ry'
    RZ = 'rz'

    @property
    def rotation(self) -> bool:
        return self in (Axis.RX, Axis.RY, Axis.RZ)

    @property
    def label(self) -> str:
        """``force along x`` / ``torque about z``: how a message names the axis."""
        return f'torque about {self.value[1]}' if self.rotation else f'force along {self.value}'


#: Every axis, translations first.
ALL_AXES: frozenset[Axis] = frozenset(Axis)


def axes_text(axes: frozenset[Axis] | set[Axis]) -> str:
    """``x, y, z forces and torque about z``: a set of axes in one phrase (world order)."""
    forces = [a.value for a in Axis if a in axes and not a.rotation]
    torques = [a.value[1] for a in Axis if a in axes and a.rotation]
    parts = []
    if forces:
        parts.append(f'{", ".join(forces)} force{"s" if len(forces) > 1 else ""}')
    if torques:
        parts.append(f'torque{"s" if len(torques) > 1 else ""} about {", ".join(torques)}')
    return ' and '.join(parts) if parts else 'nothing'


class TaskSpace(enum.Enum):
    """What the hand holds and how it moves: the task vectors' layout and size ``m``.

    A rigid grasp holds the link's frame: ``planar`` (x, y, theta; m = 3) or ``spatial``
    (x, y, z and a rotation vector; m = 6). A point grasp holds the link at a point through
    a pin (``planar_point``: x, y; m = 2) or a ball joint (``spatial_point``: x, y, z; m = 3):
    the link turns freely about that point, so the task has the translation rows only, the
    hand wrench is a force and ``J_h`` is the translational rows of the grasp frame's
    Jacobian.
    """

    PLANAR = 'planar'
    SPATIAL = 'spatial'
    PLANAR_POINT = 'planar_point'
    SPATIAL_POINT = 'spatial_point'

    @property
    def planar(self) -> bool:
        """Whether the linkage moves in the world xy plane (``planar``, ``planar_point``)."""
        return self in (TaskSpace.PLANAR, TaskSpace.PLANAR_POINT)

    @property
    def point(self) -> bool:
        """Whether the hand holds a point (no rotation rows): ``planar_point``,
        ``spatial_point``."""
        return self in (TaskSpace.PLANAR_POINT, TaskSpace.SPATIAL_POINT)

    @property
    def dim(self) -> int:
        """Task dimension m: 3 planar (vx, vy, wz), 6 spatial (vx, vy, vz, wx, wy, wz),
        2 planar_point (vx, vy), 3 spatial_point (vx, vy, vz)."""
        return _TASK_DIMS[self]

    @property
    def translation_rows(self) -> slice:
        """Rows of a task vector that are translations (m, m/s, N); the others are rotations."""
        return slice(0, 2) if self.planar else slice(0, 3)

    @property
    def rotation_dim(self) -> int:
        """Number of rotation rows: 1 planar (theta), 3 spatial (a rotation vector), 0 for a
        point grasp. The compiled pose arithmetic dispatches on it."""
        return self.dim - (2 if self.planar else 3)

    @property
    def frame_rows(self) -> tuple[int, ...]:
        """Rows of a 6-row frame Jacobian / wrench ``(v, w)`` (world-aligned at the grasp
        point) that make up the task: planar (0, 1, 5), spatial 0-5, planar_point (0, 1),
        spatial_point (0, 1, 2)."""
        return _FRAME_ROWS[self]

    @property
    def axes(self) -> tuple[Axis, ...]:
        """The device axes the task needs, one per row of its task vectors."""
        return tuple(_AXIS_BY_ROW[r] for r in self.frame_rows)

    @property
    def rigid(self) -> TaskSpace:
        """The rigid grasp of the same space (``planar_point`` -> ``planar``)."""
        return TaskSpace.PLANAR if self.planar else TaskSpace.SPATIAL

    @property
    def point_grasp(self) -> TaskSpace:
        """The point grasp of the same space (``planar`` -> ``planar_point``)."""
        return TaskSpace.PLANAR_POINT if self.planar else TaskSpace.SPATIAL_POINT

    @classmethod
    def for_dim(cls, m: int) -> TaskSpace:
        """The rigid task of dimension ``m`` (3 planar, 6 spatial): what a message of
        ``task_dim`` m was recorded with before point grasps existed."""
        return TaskSpace.PLANAR if m == TaskSpace.PLANAR.dim else TaskSpace.SPATIAL


_TASK_DIMS = {TaskSpace.PLANAR: 3, TaskSpace.SPATIAL: 6, TaskSpace.PLANAR_POINT: 2,
              TaskSpace.SPATIAL_POINT: 3}
_FRAME_ROWS = {TaskSpace.PLANAR: (0, 1, 5), TaskSpace.SPATIAL: (0, 1, 2, 3, 4, 5),
               TaskSpace.PLANAR_POINT: (0, 1), TaskSpace.SPATIAL_POINT: (0, 1, 2)}
_AXIS_BY_ROW = (Axis.X, Axis.Y, Axis.Z, Axis.RX, Axis.RY, Axis.RZ)
#: The task names a linkage or scenario file may give (``task:``).
TASK_NAMES: tuple[str, ...] = tuple(t.value for t in TaskSpace)


class Clock(enum.Enum):
    """What paces the device (``device_driver`` parameter ``clock``)."""

    WALL = 'wall'            # a wall timer at rate_hz
    LOCKSTEP = 'lockstep'    # simulated time, one period per answered state

    @classmethod
    def parse(cls, text: str) -> Clock:
        try:
            return cls(text)
        except ValueError:
            raise ConfigError(f'clock: expected one of {", ".join(c.value for c in cls)}, '
                              f'got {text!r}') from None


#: The control laws a user chooses (CLI ``--mode``, parameter ``mode``), by label.
LAW_MODES: tuple[str, ...] = (ControlMode.PENALTY.label, ControlMode.ACCELERATION_ONLY.label)
#: Every ``DeviceCommand.mode`` value a message may carry.
MESSAGE_MODES: tuple[int, ...] = tuple(int(m) for m in ControlMode)
#: Every bit a ``DeviceState.status`` may carry.
STATUS_BITS: int = int(functools.reduce(operator.or_, DeviceStatus))


# -- diagnostics status names ------------------------------------------------------------------
#: The ``/diagnostics`` status each node publishes (``name`` of its ``DiagnosticStatus``):
#: ``run``'s watcher and a bag's index find a node's figures by these.
STATUS_DEVICE = 'device_driver: loop'
STATUS_VE = 've_sim: loop'
STATUS_CONTROLLER = 'lmi_controller: loop'
STATUS_TOPIC_DEVICE = 'topic_device: device'
STATUS_FOXGLOVE = 'foxglove_bridge: server'
STATUS_RECORDER = 'recorder: bag'


# -- topics ------------------------------------------------------------------------------------
TOPIC_STATE = 'haptic/device/state'
#: ``sampled_state_rate_hz`` of the states a second, by ``device_driver``'s monotonic clock
#: when it publishes them (the same messages): for readers that want the newest state now and
#: then (``ve_sim``'s picture), so that they are not sent every state of the 1 kHz loop.
TOPIC_STATE_SAMPLED = 'haptic/device/state_sampled'
TOPIC_COMMAND = 'haptic/device/command'
TOPIC_LMI = 'haptic/lmi/update'
TOPIC_HAND_INPUTS = 'haptic/hand_inputs'
TOPIC_JOINTS = 'haptic/joint_states'
TOPIC_MARKERS = 'haptic/markers'
TOPIC_DIAGNOSTICS = '/diagnostics'
TOPIC_VT_PATH = 'haptic/ve/path'
TOPIC_LMI_ACK = 'haptic/lmi/ack'
TOPIC_CLOCK = '/clock'
# The linkage as a robot and standard mirrors, published by ve_sim (frames:
# haptic_topology.model.frames; messages: haptic_topology.nodes.viz).
TOPIC_ROBOT_DESCRIPTION = '/robot_description'
TOPIC_TF = '/tf'
TOPIC_DEVICE_POSE = 'haptic/viz/device/pose'
TOPIC_DEVICE_TWIST = 'haptic/viz/device/twist'
TOPIC_VT_POSE = 'haptic/viz/vt_hand/pose'
TOPIC_VT_TWIST = 'haptic/viz/vt_hand/twist'
TOPIC_WRENCH_APPLIED = 'haptic/viz/wrench/applied'
TOPIC_WRENCH_HAND = 'haptic/viz/wrench/hand'
TOPIC_WRENCH_COUPLING = 'haptic/viz/wrench/coupling'
#: The standard mirrors (``geometry_msgs/*Stamped``), at viz_rate_hz.
MIRROR_TOPICS = (TOPIC_DEVICE_POSE, TOPIC_DEVICE_TWIST, TOPIC_VT_POSE, TOPIC_VT_TWIST,
                 TOPIC_WRENCH_APPLIED, TOPIC_WRENCH_HAND, TOPIC_WRENCH_COUPLING)
#: The per-sample hand topic of bags recorded before ``haptic/hand_inputs`` (read, not
#: published).
TOPIC_HAND_LEGACY = 'haptic/hand'


#: Topic (a key of :data:`TOPIC_ROLES`) -> full type name of its messages: what a tool that
#: subscribes by topic alone (``foxglove_bridge``) serves it as. Every topic of
#: :data:`TOPIC_ROLES` has one (test/graph/test_foxglove.py checks it).
TOPIC_TYPES: dict[str, str] = {
    TOPIC_STATE: 'haptic_topology_msgs/msg/DeviceState',
    TOPIC_STATE_SAMPLED: 'haptic_topology_msgs/msg/DeviceState',
    TOPIC_COMMAND: 'haptic_topology_msgs/msg/DeviceCommand',
    TOPIC_HAND_INPUTS: 'haptic_topology_msgs/msg/HandInputs',
    TOPIC_LMI: 'haptic_topology_msgs/msg/LmiUpdate',
    TOPIC_VT_PATH: 'haptic_topology_msgs/msg/VtPath',
    TOPIC_JOINTS: 'sensor_msgs/msg/JointState',
    TOPIC_MARKERS: 'visualization_msgs/msg/MarkerArray',
    TOPIC_DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    TOPIC_ROBOT_DESCRIPTION: 'std_msgs/msg/String',
    TOPIC_TF: 'tf2_msgs/msg/TFMessage',
    TOPIC_DEVICE_POSE: 'geometry_msgs/msg/PoseStamped',
    TOPIC_DEVICE_TWIST: 'geometry_msgs/msg/TwistStamped',
    TOPIC_VT_POSE: 'geometry_msgs/msg/PoseStamped',
    TOPIC_VT_TWIST: 'geometry_msgs/msg/TwistStamped',
    TOPIC_WRENCH_APPLIED: 'geometry_msgs/msg/WrenchStamped',
    TOPIC_WRENCH_HAND: 'geometry_msgs/msg/WrenchStamped',
    TOPIC_WRENCH_COUPLING: 'geometry_msgs/msg/WrenchStamped',
}


# -- QoS roles ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class QosRole:
    """What a topic's publisher offers: reliability, keep-last depth, durability (the table
    of why in ``haptic_topology.nodes.qos``, which turns a role into an rclpy profile)."""

    reliable: bool
    depth: int
    transient_local: bool = False


LOOP = QosRole(False, 1)                   # state, command
#: Lock-step: the device steps only on the answer, so nothing may be lost (and nothing waits);
#: a deep history so that a recorder that falls behind a fast lock-step run loses nothing.
LOOP_LOCKSTEP = QosRole(True, 10000)
CLOCK = QosRole(False, 1)
#: The sampled states: the newest counts, under either clock (nothing steps on them).
SAMPLED = QosRole(False, 1)
#: Reliable topics keep 5 s of messages: a reader (the recorder) that falls behind by less
#: than that loses nothing (a keep-last writer overwrites what is not acknowledged).
HAND_INPUTS = QosRole(True, 500)           # 100 Hz batches
#: Lock-step: as deep as the loop topics (a recorder behind a fast lock-step run).
HAND_INPUTS_LOCKSTEP = QosRole(True, 10000)
LMI = QosRole(True, 5000)
VIZ = QosRole(True, 5)
#: /tf as tf2_ros's TransformBroadcaster offers it (reliable, volatile, keep last 100).
TF = QosRole(True, 100)
#: /robot_description as robot_state_publisher offers it: a late subscriber (RViz started
#: later) still gets the one message (reliable, transient local, keep last 1).
LATCHED = QosRole(True, 1, transient_local=True)
DIAGNOSTICS = QosRole(True, 10)
#: The recorder's readers: what DDS holds between two of its takes (every 10 ms) and through
#: a stall of its writer thread; at the graph's rates at 14x (14,000 states/s) 10,000 is
#: 0.7 s (1,000 overflowed in a 20 s benchmark run: gaps of up to 2,500 states).
RECORD_BEST_EFFORT = QosRole(False, 10000)
RECORD_RELIABLE = QosRole(True, 10000)

#: Topic -> role of its publisher under the wall clock (the recorder mirrors the reliability).
TOPIC_ROLES: dict[str, QosRole] = {
    TOPIC_STATE: LOOP, TOPIC_STATE_SAMPLED: SAMPLED, TOPIC_COMMAND: LOOP,
    TOPIC_HAND_INPUTS: HAND_INPUTS,
    TOPIC_LMI: LMI, TOPIC_VT_PATH: LMI,
    TOPIC_JOINTS: VIZ, TOPIC_MARKERS: VIZ, TOPIC_DIAGNOSTICS: DIAGNOSTICS,
    TOPIC_ROBOT_DESCRIPTION: LATCHED, TOPIC_TF: TF,
    **{t: VIZ for t in MIRROR_TOPICS},
}


def loop_role(clock: Clock) -> QosRole:
    """Role of the 1 kHz state/command topics under ``clock``."""
    return LOOP_LOCKSTEP if clock is Clock.LOCKSTEP else LOOP


def hand_inputs_role(clock: Clock) -> QosRole:
    """Role of ``haptic/hand_inputs`` under ``clock``: reliable either way (the VE must
    integrate every input); keep last 500 batches (5 s at 100 Hz), 10000 in lock-step."""
    return HAND_INPUTS_LOCKSTEP if clock is Clock.LOCKSTEP else HAND_INPUTS


def publisher_role(topic: str, clock: Clock) -> QosRole:
    """Role the graph's publisher of ``topic`` (a key of :data:`TOPIC_ROLES`) offers under
    ``clock`` (what the recorder mirrors and writes into the bag)."""
    if topic in (TOPIC_STATE, TOPIC_COMMAND):
        return loop_role(clock)
    if topic == TOPIC_HAND_INPUTS:
        return hand_inputs_role(clock)
    return TOPIC_ROLES[topic]
