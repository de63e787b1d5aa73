"""Device frame <-> task vectors for a haptic device that speaks standard ROS messages.

Haptic devices with ROS 2 drivers (Geomagic/3D Systems Touch, Force Dimension, Haply, ...)
publish the handle's pose (``geometry_msgs/PoseStamped``) and twist (``TwistStamped``), some a
measured force (``WrenchStamped``), and take a wrench command (``WrenchStamped``), each in the
device's own base frame ``D`` and units. The ``ros_topics`` backend
(``haptic_topology.nodes.topic_backend``) maps them to the task vectors of
:mod:`haptic_topology.device.maglev` with a :class:`TopicMapping`; the device player of the
tests (``haptic_topology.nodes.topic_device``) maps the other way. No ROS here: messages are
taken apart by the caller.

The mapping is a rigid transform plus units. ``M = R_o A`` is the rotation from ``D`` to the
task (world) frame ``T``: ``A`` the axis mapping (option ``axes``), ``R_o`` and ``p_o`` the
task pose of the (re-axed) device base (option ``origin``); ``s`` metres per device length
unit (``scale``), ``k_f`` newtons per device force unit (``force_scale``), ``k_t`` newton
metres per device torque unit (``torque_scale``)::

    p_T = p_o + M s p_D        R_T = M R_D           (handle pose in T)
    v_T = M s v_D              w_T = M w_D           (twist in the header frame, D)
    f_T = M k_f f_D            t_T = M k_t t_D       (measured hand wrench)
    f_D = M^T f_T / k_f        t_D = M^T t_T / k_t   (command)

Task vectors: planar ``(x, y, theta)`` with ``theta`` the rotation of ``R_T`` about the task
z axis, kept continuous from sample to sample (no jump at +-pi); spatial ``(x, y, z, r)`` with
``r`` the rotation vector of ``R_T`` (``log3``, world frame, as
:func:`haptic_topology.dynamics.taskspace.integrate_pose`). A planar wrench ``(f_x, f_y,
t_z)`` is the spatial ``(f_x, f_y, 0, 0, 0, t_z)``.

Example (checked by
``test/unit/device/test_topic_mapping.py``): a device in millimetres whose axes are
those of the task turned by +90 degrees about z (``axes: [y, -x, z]``: task x is device y,
task y is device -x) at ``origin: [0.1, 0.0, 0.0]``, planar task. The handle at
``p_D = (10, 20, 0)`` mm, unrotated, is at task ``(0.1 + 0.020, -0.010, theta)`` with
``theta = -pi/2`` (the device's unrotated handle, seen in the task's axes); a command
``u = (1, 0, 0)`` N is ``f_D = (0, 1, 0)``: task x is device y.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import TaskSpace

#: Backend name used in the options' error messages.
BACKEND = 'ros_topics'
_AXES = {'x': 0, 'y': 1, 'z': 2}
#: |det - 1| and |A A^T - I| allowed for an axis matrix given as numbers.
_ORTHO_TOL = 1e-6
#: ``|q|`` allowed away from 1 for a device quaternion (farther: the sample is refused).
QUAT_NORM_TOL = 1e-2


class Reliability(enum.Enum):
    """QoS reliability of the device topics."""

    BEST_EFFORT = 'best_effort'
    RELIABLE = 'reliable'


def option_error(key: str, expected: str, value: Any, backend: str = BACKEND) -> DeviceError:
    """The error of a bad ``backend_options`` entry of ``backend``: names the field and what it
    must be."""
    return DeviceError(f'{backend}: backend_options.{key}: expected {expected}, got {value!r}')


#: Options and their defaults (None: required). See :class:`TopicOptions`.
DEFAULTS: dict[str, Any] = {
    'pose_topic': None, 'twist_topic': None, 'command_topic': None, 'wrench_topic': '',
    'frame_id': '', 'axes': ['x', 'y', 'z'], 'origin': None, 'scale': 1.0,
    'force_scale': 1.0, 'torque_scale': 1.0, 'stale_ms': 20.0, 'qos': 'best_effort',
    'command_qos': 'best_effort', 'connect_timeout_ms': 5000.0,
    'node_name': 'device_topic_backend',
}


def rotz(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray | None:
    """The rotation matrix of the quaternion ``(x, y, z, w)`` (geometry_msgs order), normalised;
    None when it is not finite or its norm is not within :data:`QUAT_NORM_TOL` of 1 (an
    all-zero, unset quaternion is the common case)."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(n) and abs(n - 1.0) <= QUAT_NORM_TOL):
        return None
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)]])


def matrix_to_quat(r: np.ndarray) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation matrix (w >= 0)."""
    q = pin.Quaternion(np.asarray(r, dtype=float))
    q.normalize()
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    return (-x, -y, -z, -w) if w < 0.0 else (x, y, z, w)


def _text(options: Mapping[str, Any], key: str, required: bool = False) -> str:
    value = options.get(key, DEFAULTS[key])
    if not isinstance(value, str) or (required and not value.strip()):
        raise option_error(key, 'a topic name (text)' if key.endswith('_topic') else 'text',
                           value)
    return value.strip()


def _positive(options: Mapping[str, Any], key: str, hi: float = math.inf) -> float:
    value = options.get(key, DEFAULTS[key])
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not (math.isfinite(value) and 0.0 < value <= hi)):
        raise option_error(key, f'a number in (0, {hi:g}]', value)
    return float(value)


def parse_axes(value: Any, backend: str = BACKEND) -> np.ndarray:
    """``axes``: 3 signed axis names (task axis i = that device axis) or a 3 x 3 rotation
    (rows: task axes in device coordinates); right-handed either way. A bad value raises
    :class:`~haptic_topology.errors.DeviceError` naming ``backend``'s option."""
    expected = ('3 signed device axis names such as [x, -z, y] (task x, y, z), or a 3 x 3 '
                'rotation matrix (rows), right-handed')
    if (isinstance(value, list) and len(value) == 3
            and all(isinstance(v, str) for v in value)):
        a = np.zeros((3, 3))
        for i, name in enumerate(value):
            text = name.strip().lower()
            sign = -1.0 if text.startswith('-') else 1.0
            axis = _AXES.get(text.lstrip('+-'))
            if axis is None:
                raise option_error('axes', expected, value, backend)
            a[i, axis] = sign
    elif (isinstance(value, list) and len(value) == 3
          and all(isinstance(r, list) and len(r) == 3 for r in value)
          and all(isinstance(v, int | float) and not isinstance(v, bool)
                  for r in value for v in r)):
        a = np.array(value, dtype=float)
    else:
        raise option_error('axes', expected, value, backend)
    if (not np.all(np.isfinite(a)) or np.abs(a @ a.T - np.eye(3)).max() > _ORTHO_TOL
            or abs(np.linalg.det(a) - 1.0) > _ORTHO_TOL):
        raise option_error('axes', expected + ' (orthonormal, determinant +1)', value,
                           backend)
    return a


def _origin(value: Any, task: TaskSpace) -> tuple[np.ndarray, np.ndarray]:
    """``origin``: the task pose of the device base (planar x, y, theta; spatial x, y, z and a
    rotation vector) -> (p_o, R_o)."""
    m = task.dim
    if value is None:
        return np.zeros(3), np.eye(3)
    if (not isinstance(value, list) or len(value) != m
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) for v in value)):
        what = ('3 numbers: x, y (m), theta (rad)' if task is TaskSpace.PLANAR
                else '6 numbers: x, y, z (m), rotation vector (rad)')
        raise option_error('origin', what, value)
    v = np.array(value, dtype=float)
    if task is TaskSpace.PLANAR:
        return np.array([v[0], v[1], 0.0]), rotz(float(v[2]))
    return v[:3].copy(), pin.exp3(v[3:6])


def _choice(options: Mapping[str, Any], key: str) -> Reliability:
    value = options.get(key, DEFAULTS[key])
    try:
        return Reliability(value)
    except ValueError:
        raise option_error(key, ' or '.join(r.value for r in Reliability), value) from None


@dataclass(frozen=True)
class TopicMapping:
    """The transform of the module doc: ``rotation`` M (3 x 3, D -> T), ``origin`` p_o (m),
    ``scale`` s (m per device unit), ``force_scale`` k_f, ``torque_scale`` k_t, for
    ``task``."""

    task: TaskSpace
    rotation: np.ndarray
    origin: np.ndarray
    scale: float = 1.0
    force_scale: float = 1.0
    torque_scale: float = 1.0
    _m: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _o: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Plain floats for the per-message and per-cycle products: for 3-vectors they cost a
        # fraction of numpy's calls (as maglev.saturate does).
        r = [float(v) for v in np.asarray(self.rotation, dtype=float).ravel()]
        object.__setattr__(self, '_m', tuple(r))
        object.__setattr__(self, '_o', tuple(float(v) for v in self.origin))

    def _rot(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """M (x, y, z)."""
        m = self._m
        return (m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z,
                m[6] * x + m[7] * y + m[8] * z)

    def _rot_t(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """M^T (x, y, z)."""
        m = self._m
        return (m[0] * x + m[3] * y + m[6] * z, m[1] * x + m[4] * y + m[7] * z,
                m[2] * x + m[5] * y + m[8] * z)

    # -- a point (3-axis vendor devices, haptic_topology.device.vendor) ----------------------
    def point(self, p: tuple[float, float, float]) -> tuple[float, float, float]:
        """Task position ``p_o + M s p_D`` (m) of the device position ``p`` (device units)."""
        s, o = self.scale, self._o
        tx, ty, tz = self._rot(s * p[0], s * p[1], s * p[2])
        return o[0] + tx, o[1] + ty, o[2] + tz

    def point_velocity(self, v: tuple[float, float, float]) -> tuple[float, float, float]:
        """Task velocity ``M s v_D`` (m/s) of the device velocity ``v``."""
        s = self.scale
        return self._rot(s * v[0], s * v[1], s * v[2])

    def point_force(self, f: tuple[float, float, float]) -> tuple[float, float, float]:
        """Device force ``M^T f_T / k_f`` (device units) of the task force ``f`` (N)."""
        k = 1.0 / self.force_scale
        return self._rot_t(k * f[0], k * f[1], k * f[2])

    # -- device -> task (the backend) --------------------------------------------------------
    def pose(self, p: tuple[float, float, float], q: tuple[float, float, float, float],
             previous_theta: float | None = None) -> np.ndarray | None:
        """Task pose of the handle at device position ``p`` and quaternion ``q`` (x, y, z, w);
        ``previous_theta``: the planar angle of the previous sample (keeps theta continuous).
        None: not a valid pose (non-finite, or not a unit quaternion)."""
        px, py, pz = p
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            return None
        x, y, z, w = q
        n2 = x * x + y * y + z * z + w * w
        if not (math.isfinite(n2) and abs(math.sqrt(n2) - 1.0) <= QUAT_NORM_TOL):
            return None
        s = self.scale
        o = self._o
        tx, ty, tz = self._rot(s * px, s * py, s * pz)
        if self.task is TaskSpace.PLANAR:
            # Column 0 of R_D (the handle's x axis in D), turned into T: theta is its heading.
            k = 2.0 / n2
            cx, cy, cz = self._rot(1.0 - k * (y * y + z * z), k * (x * y + z * w),
                                   k * (x * z - y * w))
            theta = math.atan2(cy, cx)
            if previous_theta is not None and math.isfinite(previous_theta):
                theta = previous_theta + math.remainder(theta - previous_theta, 2.0 * math.pi)
            return np.array([o[0] + tx, o[1] + ty, theta])
        r_d = quat_to_matrix(x, y, z, w)
        assert r_d is not None
        r_t = self.rotation @ r_d
        return np.array([o[0] + tx, o[1] + ty, o[2] + tz, *pin.log3(r_t).tolist()])

    def twist(self, v: tuple[float, float, float], w: tuple[float, float, float]
              ) -> np.ndarray | None:
        """Task twist of the device twist ``(v, w)`` (header frame D); None if not finite."""
        return self._pair(v, w, self.scale, 1.0)

    def hand_wrench(self, f: tuple[float, float, float], t: tuple[float, float, float]
                    ) -> np.ndarray | None:
        """Task hand wrench of a measured device wrench; None if not finite."""
        return self._pair(f, t, self.force_scale, self.torque_scale)

    def _pair(self, a: tuple[float, float, float], b: tuple[float, float, float],
              ka: float, kb: float) -> np.ndarray | None:
        if not all(math.isfinite(v) for v in (*a, *b)):
            return None
        lx, ly, lz = self._rot(ka * a[0], ka * a[1], ka * a[2])
        ax, ay, az = self._rot(kb * b[0], kb * b[1], kb * b[2])
        if self.task is TaskSpace.PLANAR:
            return np.array([lx, ly, az])
        return np.array([lx, ly, lz, ax, ay, az])

    # -- task -> device (commands; the player's publications) --------------------------------
    def _split(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = np.asarray(u, dtype=float)
        if self.task is TaskSpace.PLANAR:
            return np.array([u[0], u[1], 0.0]), np.array([0.0, 0.0, u[2]])
        return u[:3], u[3:6]

    def command(self, u: np.ndarray) -> tuple[tuple[float, float, float],
                                               tuple[float, float, float]]:
        """Device force and torque (device units, frame D) of the task wrench ``u``."""
        v = [float(x) for x in u]
        kf, kt = 1.0 / self.force_scale, 1.0 / self.torque_scale
        if self.task is TaskSpace.PLANAR:
            f = self._rot_t(kf * v[0], kf * v[1], 0.0)
            return f, self._rot_t(0.0, 0.0, kt * v[2])
        return (self._rot_t(kf * v[0], kf * v[1], kf * v[2]),
                self._rot_t(kt * v[3], kt * v[4], kt * v[5]))

    def device_pose(self, pose: np.ndarray
                    ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
        """Device position and quaternion of the task pose ``pose`` (inverse of :meth:`pose`;
        a planar pose is at task z = 0, rotated about task z)."""
        pose = np.asarray(pose, dtype=float)
        if self.task is TaskSpace.PLANAR:
            pos, r_t = np.array([pose[0], pose[1], 0.0]), rotz(float(pose[2]))
        else:
            pos, r_t = pose[:3], pin.exp3(pose[3:6])
        mt = self.rotation.T
        return mt @ (pos - self.origin) / self.scale, matrix_to_quat(mt @ r_t)

    def device_twist(self, twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Device linear and angular velocity of a task twist (inverse of :meth:`twist`)."""
        v, w = self._split(twist)
        mt = self.rotation.T
        return mt @ v / self.scale, mt @ w

    def device_wrench(self, wrench: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Device force and torque of a task hand wrench (inverse of :meth:`hand_wrench`)."""
        f, t = self.command(wrench)
        return np.array(f), np.array(t)

    def task_command(self, f: tuple[float, float, float], t: tuple[float, float, float]
                     ) -> np.ndarray | None:
        """Task wrench of a device command (inverse of :meth:`command`); None if not
        finite."""
        return self.hand_wrench(f, t)


@dataclass(frozen=True)
class TopicOptions:
    """The ``ros_topics`` backend's ``backend_options``, checked (see
    :func:`parse_topic_options` and the table in docs/devices.md)."""

    pose_topic: str
    twist_topic: str
    command_topic: str
    wrench_topic: str
    frame_id: str
    mapping: TopicMapping
    stale_ns: int
    qos: Reliability
    command_qos: Reliability
    connect_timeout: float
    node_name: str

    @property
    def inputs(self) -> tuple[str, ...]:
        """The device topics read (pose, twist and, if given, wrench)."""
        return tuple(t for t in (self.pose_topic, self.twist_topic, self.wrench_topic) if t)


def parse_topic_options(options: Mapping[str, Any], task: TaskSpace) -> TopicOptions:
    """Check ``backend_options`` for the task space ``task``; a bad or unknown entry raises
    :class:`~haptic_topology.errors.DeviceError` naming the field and what it must be."""
    if not isinstance(options, Mapping):
        raise DeviceError(f'{BACKEND}: backend_options: expected a mapping, got {options!r}')
    if task.point:
        raise DeviceError(f'{BACKEND}: a {task.value} task (a point grasp) is not supported by '
                          'this backend yet; expected a planar or spatial scenario')
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise DeviceError(f'{BACKEND}: backend_options: unknown option {unknown[0]!r} '
                          f'(expected some of: {", ".join(sorted(DEFAULTS))})')
    missing = [k for k, v in DEFAULTS.items() if v is None and k != 'origin'
               and k not in options]
    if missing:
        raise option_error(missing[0], 'a topic name (text)', None)
    p_o, r_o = _origin(options.get('origin'), task)
    a = parse_axes(options.get('axes', DEFAULTS['axes']))
    mapping = TopicMapping(task, r_o @ a, p_o, _positive(options, 'scale'),
                           _positive(options, 'force_scale'),
                           _positive(options, 'torque_scale'))
    timeout = options.get('connect_timeout_ms', DEFAULTS['connect_timeout_ms'])
    if (isinstance(timeout, bool) or not isinstance(timeout, int | float)
            or not (math.isfinite(timeout) and 0.0 <= timeout <= 600_000.0)):
        raise option_error('connect_timeout_ms', 'a number in [0, 600000] (0: do not wait)',
                           timeout)
    node_name = _text(options, 'node_name', required=True)
    if not node_name.replace('_', 'a').isalnum() or node_name[0].isdigit():
        raise option_error('node_name', 'a ROS node name (letters, digits, _)', node_name)
    out = TopicOptions(
        pose_topic=_text(options, 'pose_topic', required=True),
        twist_topic=_text(options, 'twist_topic', required=True),
        command_topic=_text(options, 'command_topic', required=True),
        wrench_topic=_text(options, 'wrench_topic'),
        frame_id=_text(options, 'frame_id'),
        mapping=mapping,
        stale_ns=round(1e6 * _positive(options, 'stale_ms', 10_000.0)),
        qos=_choice(options, 'qos'), command_qos=_choice(options, 'command_qos'),
        connect_timeout=1e-3 * float(timeout), node_name=node_name)
    topics = out.inputs + (out.command_topic,)
    if len(set(topics)) != len(topics):
        raise DeviceError(f'{BACKEND}: backend_options: expected distinct topics, got '
                          f'{", ".join(topics)}')
    return out


#: A sample of one input: (arrival ns on the backend's monotonic clock, task vector or None
#: when the newest message was not valid, the text of what was wrong).
Sample = tuple[int, np.ndarray | None, str]


def input_fault(inputs: Iterable[tuple[str, Sample | None]], now_ns: int,
                stale_ns: int) -> str:
    """Why the newest samples of ``inputs`` (``(topic, sample)``; the first that fails is
    named) cannot be used at ``now_ns``, or ``''``: none yet, not valid, or older than
    ``stale_ns`` (an input with an empty topic name is never stale: a constant)."""
    for topic, s in inputs:
        if s is None:
            return f'no device data yet on {topic}'
        if s[1] is None:
            return s[2]
        if topic and now_ns - s[0] > stale_ns:
            return (f'device data stale ({1e-6 * (now_ns - s[0]):.1f} ms on {topic}, '
                    f'stale_ms {1e-6 * stale_ns:g})')
    return ''
