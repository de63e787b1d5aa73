"""Simulated users: the wrench ``F_h`` a hand applies to the device (eq. 9).

* :class:`ConstantWrenchUser` - the paper's user (Sections VI and VIII: ``F_h = (0.4 N, 0, 0)``;
  footnote 2: a worst case for stability of an impedance-type device).
* :class:`SpringDamperUser` - a hand that follows a target path with a spring-damper,
  ``F_h = K_u (x_target(t) - x_h) + B_u (xd_target(t) - xd_h)``.
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field
from typing import Any, Protocol

import numpy as np

from haptic_topology.errors import ConfigError
from haptic_topology.validate import as_float, as_str, as_vector, check_keys
from haptic_topology.vocabulary import TaskSpace


class UserModel(Protocol):
    """A simulated hand."""

    def wrench(self, t: float, pose: np.ndarray, twist: np.ndarray) -> np.ndarray:
        """``F_h`` (N, N m) at time ``t`` (s) for the device pose and twist."""
        ...


@dataclass(frozen=True)
class ConstantWrenchUser:
    """A constant hand wrench."""

    value: np.ndarray

    def wrench(self, t: float, pose: np.ndarray, twist: np.ndarray) -> np.ndarray:
        return self.value.copy()


@dataclass(frozen=True)
class TargetPath:
    """A target hand path: a straight line at constant velocity or a circle in x-y.

    ``line``: ``x(t) = start + velocity * t``. ``circle``: centre ``start``, radius (m), period
    (s), in the x-y plane; other coordinates stay at ``start``.
    """

    kind: str
    start: np.ndarray
    velocity: np.ndarray
    radius: float = 0.0
    period: float = 1.0

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The target pose and twist at time ``t`` (s)."""
        if self.kind == 'line':
            return self.start + self.velocity * t, self.velocity.copy()
        w = 2.0 * math.pi / self.period
        pose = self.start.copy()
        twist = np.zeros_like(self.start)
        pose[0] += self.radius * math.cos(w * t)
        pose[1] += self.radius * math.sin(w * t)
        twist[0] = -self.radius * w * math.sin(w * t)
        twist[1] = self.radius * w * math.cos(w * t)
        return pose, twist


@dataclass(frozen=True)
class SpringDamperUser:
    """A hand that tracks :class:`TargetPath` with stiffness ``k`` and damping ``b``."""

    path: TargetPath
    k: np.ndarray
    b: np.ndarray
    task: TaskSpace
    #: Load the compiled wrench now (False: a user built only to check a scenario's
    #: ``user`` block, whose :meth:`wrench` must not be called).
    compile: InitVar[bool] = True

    #: The compiled wrench (:func:`~haptic_topology.device.compiled.spring_damper_wrench`)
    #: and its path code, set at construction.
    _wrench: Any = field(init=False, repr=False, compare=False, default=None)
    _path_code: int = field(init=False, repr=False, compare=False, default=0)

    def __post_init__(self, compile: bool) -> None:
        if not compile:
            return
        # Imported here: loading the compiled code costs about 1 s and 60 MB, which a
        # process that never steps a device (one that reads bags) does not pay.
        from haptic_topology.device.compiled import CIRCLE, LINE, task_spring_damper_wrench
        object.__setattr__(self, '_wrench', task_spring_damper_wrench)
        object.__setattr__(self, '_path_code', LINE if self.path.kind == 'line' else CIRCLE)

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt from its fields (the compiled function would pickle by value and compile
        # again where it is unpickled).
        return (SpringDamperUser, (self.path, self.k, self.b, self.task))

    def wrench(self, t: float, pose: np.ndarray, twist: np.ndarray) -> np.ndarray:
        """``K_u (x_target(t) (-) x_h) + B_u (xd_target(t) - xd_h)`` for the path's
        :meth:`~haptic_topology.device.users.TargetPath.at`, compiled (one call per cycle)."""
        p = self.path
        return self._wrench(self.task.rotation_dim, self._path_code, p.start, p.velocity,
                            p.radius, p.period, self.k, self.b, t, np.asarray(pose, dtype=float),
                            np.asarray(twist, dtype=float))


def user_from_config(raw: Any, task: TaskSpace, where: str,
                     start_pose: np.ndarray, compile: bool = True) -> UserModel:
    """Build a user from a scenario's ``user`` mapping (``compile``: as
    :class:`SpringDamperUser`'s; False to check the mapping only).

    ``{type: constant_wrench, wrench: [...]}`` or ``{type: spring_damper, path: line|circle,
    velocity: [...], radius: R, period: T, stiffness: [...], damping: [...]}`` (the path
    starts at the device's initial pose unless ``start`` is given).
    """
    m = task.dim
    kind = as_str(check_keys(raw, where, required=('type',), optional=(
        'wrench', 'path', 'start', 'velocity', 'radius', 'period', 'stiffness', 'damping'))[
        'type'], f'{where}.type', ('constant_wrench', 'spring_damper'))
    if kind == 'constant_wrench':
        if 'wrench' not in raw:
            raise ConfigError(f'{where}.wrench: missing required key')
        return ConstantWrenchUser(as_vector(raw['wrench'], f'{where}.wrench', m))
    path_kind = as_str(raw.get('path', 'line'), f'{where}.path', ('line', 'circle'))
    start = (as_vector(raw['start'], f'{where}.start', m) if 'start' in raw
             else np.array(start_pose, dtype=float))
    velocity = as_vector(raw.get('velocity', [0.0] * m), f'{where}.velocity', m)
    radius = as_float(raw.get('radius', 0.0), f'{where}.radius', lo=0.0)
    period = as_float(raw.get('period', 1.0), f'{where}.period', lo=0.0, lo_open=True)
    for key in ('stiffness', 'damping'):
        if key not in raw:
            raise ConfigError(f'{where}.{key}: missing required key')
    k = as_vector(raw['stiffness'], f'{where}.stiffness', m, lo=0.0)
    b = as_vector(raw['damping'], f'{where}.damping', m, lo=0.0)
    return SpringDamperUser(TargetPath(path_kind, start, velocity, radius, period), k, b, task,
                            compile)
