"""A device backend test double, selected as ``backend:=fake_backend:CircleBackend``.

It lives only in ``test/`` (on PYTHONPATH for the node processes) and is a plain subclass of
:class:`~haptic_topology.device.backend.DeviceBackend`: selecting it needs no change in the
driver, controller, VE or recorder. Kinematic: the "device" moves on a circle of ``radius``
(option, m) around its initial pose with period ``period`` (option, s), ignores the commanded
wrench (it only counts writes) and measures no hand wrench.
"""

from __future__ import annotations

import math

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceBackend, DeviceReading
from haptic_topology.errors import DeviceError


def circle(center: np.ndarray, radius: float, period: float, t: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Pose and twist on the circle at time ``t`` (starts at ``center``, moving along +x)."""
    w = 2.0 * math.pi / period
    pose = center.copy()
    twist = np.zeros_like(center)
    pose[0] += radius * math.sin(w * t)
    pose[1] += radius * (1.0 - math.cos(w * t))
    twist[0] = radius * w * math.cos(w * t)
    twist[1] = radius * w * math.sin(w * t)
    return pose, twist


class CircleBackend(DeviceBackend):
    name = 'circle_test_double'

    def configure(self, config: BackendConfig) -> None:
        unknown = set(config.options) - {'radius', 'period'}
        if unknown:
            raise DeviceError(f'{self.name}: unknown options {sorted(unknown)}')
        self.center = np.array(config.initial_pose, dtype=float)
        self.radius = float(config.options.get('radius', 0.002))
        self.period = float(config.options.get('period', 1.0))
        self.t = 0.0
        self.writes = 0
        self.active = False

    def task_dim(self) -> int:
        return int(self.center.size)

    def activate(self) -> None:
        self.active = True

    def deactivate(self) -> None:
        self.active = False

    def write(self, wrench: np.ndarray) -> None:
        self.writes += 1

    def read(self, dt: float) -> DeviceReading:
        self.t += dt
        pose, twist = circle(self.center, self.radius, self.period, self.t)
        return DeviceReading(pose, twist, np.zeros_like(pose))

    def idle(self, dt: float) -> DeviceReading:
        pose, twist = circle(self.center, self.radius, self.period, 0.0)
        return DeviceReading(pose, np.zeros_like(twist), np.zeros_like(pose))


class NotABackend:
    """Selecting this must fail with a clear message."""
