"""Device backend test doubles, selected as ``backend:=fake_backend:CircleBackend`` (or
``fake_backend:FaultBackend``, the simulated maglev with a fault switch, at the end).

They live only in ``test/`` (on PYTHONPATH for the node processes) and are plain subclasses
of :class:`~haptic_topology.device.backend.DeviceBackend`: selecting one needs no change in the
driver, controller, VE or recorder. ``CircleBackend`` is kinematic: the "device" moves on a
circle of ``radius`` (option, m) around its initial pose with period ``period`` (option, s),
ignores the commanded wrench (it only counts writes) and measures no hand wrench.
"""

from __future__ import annotations

import math

import numpy as np

from haptic_topology.device.backend import (
    BackendConfig,
    DeviceBackend,
    DeviceReading,
    SimMaglevBackend,
)
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import DeviceStatus


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


class FaultBackend(SimMaglevBackend):
    """The simulated maglev with a fault switch, selected as ``fake_backend:FaultBackend``.

    While :attr:`fault` holds a reason (set by the test) every reading carries
    ``DeviceStatus.FAULT`` and :meth:`fault_reason` returns it. Every wrench written is kept in
    :attr:`writes` (N, N m), so a test sees exactly what would have reached the device. Its
    :attr:`hardware_id` names a unit, as a real device's backend would.
    """

    name = 'fault_test_double'

    def __init__(self) -> None:
        super().__init__()
        self.fault = ''
        self.writes: list[np.ndarray] = []

    @property
    def hardware_id(self) -> str:
        return f'{self.name} unit 7'

    def fault_reason(self) -> str:
        return self.fault

    def write(self, wrench: np.ndarray) -> None:
        self.writes.append(np.array(wrench, dtype=float))
        super().write(wrench)

    def _flag(self, reading: DeviceReading) -> DeviceReading:
        if not self.fault:
            return reading
        return DeviceReading(reading.pose, reading.twist, reading.hand_wrench,
                             reading.status | DeviceStatus.FAULT)

    def read(self, dt: float) -> DeviceReading:
        return self._flag(super().read(dt))

    def idle(self, dt: float) -> DeviceReading:
        return self._flag(super().idle(dt))
