"""Device backend test doubles, selected as ``backend:=fake_backend:CircleBackend`` (or
``fake_backend:FaultBackend``, the simulated maglev with a fault switch, and
``fake_backend:ForceOnlyBackend``, a 3-axis force device, at the end).

They live only in ``test/`` (on PYTHONPATH for the node processes) and are plain subclasses
of :class:`~haptic_topology.device.backend.DeviceBackend`: selecting one needs no change in the
driver, controller, VE or recorder. ``CircleBackend`` is kinematic: the "device" moves on a
circle of ``radius`` (option, m) around its initial pose with period ``period`` (option, s),
ignores the commanded wrench (it only counts writes) and measures no hand wrench.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from haptic_topology.device.backend import (
    TRANSLATION_AXES,
    BackendConfig,
    DeviceAxes,
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


class CallLogBackend(SimMaglevBackend):
    """The simulated maglev, selected as ``fake_backend:CallLogBackend``, for tests of a loop
    in another process (the loop process): it appends ``activate``, ``zero`` (a zero wrench
    written), ``deactivate`` and ``cleanup`` to the file named by the environment variable
    ``HAPTIC_TEST_CALL_LOG``, one line each, and misbehaves as ``HAPTIC_TEST_MISBEHAVE``
    says: ``activate`` (raises DeviceError after enabling the output), ``write`` (every
    write raises RuntimeError: a backend's own bug), ``stall:<n>:<s>`` (the n-th read or
    idle reading notes ``stall`` and blocks for s seconds, as a hung vendor call)."""

    name = 'call_log_test_double'

    def __init__(self) -> None:
        super().__init__()
        self._log = os.environ['HAPTIC_TEST_CALL_LOG']
        self._misbehave = os.environ.get('HAPTIC_TEST_MISBEHAVE', '')
        self._reads = 0

    def _note(self, what: str) -> None:
        with open(self._log, 'a', encoding='utf-8') as f:
            f.write(what + '\n')

    def activate(self) -> None:
        self._note('activate')
        super().activate()
        if self._misbehave == 'activate':
            raise DeviceError(f'{self.name}: activation failed half-way (test)')

    def write(self, wrench: np.ndarray) -> None:
        if self._misbehave == 'write':
            raise RuntimeError(f'{self.name}: write failed (test)')
        if not np.any(wrench):
            self._note('zero')
        super().write(wrench)

    def _stall(self) -> None:
        self._reads += 1
        if self._misbehave.startswith('stall:'):
            _, n, seconds = self._misbehave.split(':')
            if self._reads == int(n):
                self._note('stall')
                time.sleep(float(seconds))

    def read(self, dt: float) -> DeviceReading:
        self._stall()
        return super().read(dt)

    def idle(self, dt: float) -> DeviceReading:
        self._stall()
        return super().idle(dt)

    def deactivate(self) -> None:
        self._note('deactivate')
        super().deactivate()

    def cleanup(self) -> None:
        self._note('cleanup')
        super().cleanup()


class ForceOnlyBackend(SimMaglevBackend):
    """A 3-axis force device (most desktop haptic devices): it senses and actuates the three
    translations only (:data:`~haptic_topology.device.backend.TRANSLATION_AXES`). Selected as
    ``fake_backend:ForceOnlyBackend``; a scenario with a rigid grasp is refused at configure
    (its torques have no actuator), a ``spatial_point`` or ``planar_point`` one runs on the
    simulated maglev underneath."""

    name = 'force3_test_double'

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        del options
        return TRANSLATION_AXES


class RefusingBackend(SimMaglevBackend):
    """The simulated maglev whose ``configure`` raises, selected as
    ``fake_backend:RefusingBackend``: with ``backend_options`` ``{refuse: device}`` a
    :class:`DeviceError` with its own one-line reason (what a backend is asked to raise),
    with ``{refuse: bug}`` a ``RuntimeError`` (a backend's own bug)."""

    name = 'refusing_test_double'
    #: The reason given with ``refuse: device``.
    REASON = 'refusing_test_double: backend_options.unit: no unit 7 on this bus (test)'

    def configure(self, config: BackendConfig) -> None:
        refuse = config.options.get('refuse')
        if refuse == 'device':
            raise DeviceError(self.REASON)
        if refuse == 'bug':
            raise RuntimeError('index 7 out of range (test)')
        super().configure(BackendConfig(config.params, config.initial_pose, config.user, {},
                                        config.source))
