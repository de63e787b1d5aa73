"""A complete, minimal device backend for haptic_topology, in a distribution of its own.

:class:`SpringBackend` stands in for a real device: a handle of mass ``mass`` on a spring of
``stiffness`` and a damper ``damping`` around where it started, on every task axis, with an
amplifier that saturates at ``max_force``. Replace the three marked places (open/enable,
send, receive) with your device's API and keep the rest: option checks that name the field,
a finite and saturated output, zero on ``deactivate``, a fault reported as a status bit.

It is registered by ``pyproject.toml`` in the entry point group
``haptic_topology.device_backends`` as ``my_spring``, so ``backend: my_spring`` selects it.
haptic_topology's tests install this directory and run it through the same conformance checks
as the built-in backends (``test/unit/device/test_device_conformance.py``).

Options (``backend_options``; all optional): ``mass`` (kg, > 0, default 0.2), ``stiffness``
(N/m per axis, >= 0, default 50), ``damping`` (N s/m, >= 0, default 2), ``max_force`` (N,
> 0, default 10: the amplifier's limit), ``travel`` (m, > 0, default 0.05: farther than this
from the start on an axis, the device reports a fault until it is back), ``hand``
(``scenario``, default: a simulated hand pushes the handle as the scenario's user does, and
the handle measures that push as its hand wrench; ``none``: nothing pushes it). On a real
device your hand is the hand: drop the simulated one.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceBackend, DeviceReading
from haptic_topology.device.users import UserModel, user_from_config
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import DeviceStatus

DEFAULTS = {'mass': 0.2, 'stiffness': 50.0, 'damping': 2.0, 'max_force': 10.0,
            'travel': 0.05}
HANDS = ('scenario', 'none')


def _option(options: dict[str, Any], key: str, positive: bool) -> float:
    value = options.get(key, DEFAULTS[key])
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and math.isfinite(value) and (value > 0.0 if positive else value >= 0.0))
    if not ok:
        raise DeviceError(f'my_spring: backend_options.{key}: expected a number '
                          f'{"> 0" if positive else ">= 0"}, got {value!r}')
    return float(value)


class SpringBackend(DeviceBackend):
    """A simulated spring-loaded handle (module doc)."""

    name = 'my_spring'

    def __init__(self) -> None:
        self._x0 = np.zeros(0)
        self._x = np.zeros(0)
        self._v = np.zeros(0)
        self._u = np.zeros(0)
        self.applied = np.zeros(0)      # what the amplifier output in the newest step
        self._active = False
        self._reason = ''
        self._hand: UserModel | None = None     # the simulated hand (simulation only)
        self._t = 0.0

    def configure(self, config: BackendConfig) -> None:
        unknown = sorted(set(config.options) - set(DEFAULTS) - {'hand'})
        if unknown:
            raise DeviceError(f'my_spring: backend_options: unknown option {unknown[0]!r} '
                              f'(expected some of: {", ".join(sorted([*DEFAULTS, "hand"]))})')
        opts = dict(config.options)
        hand = opts.get('hand', 'scenario')
        if hand not in HANDS:
            raise DeviceError(f'my_spring: backend_options.hand: expected one of '
                              f'{", ".join(HANDS)}, got {hand!r}')
        self.mass = _option(opts, 'mass', True)
        self.stiffness = _option(opts, 'stiffness', False)
        self.damping = _option(opts, 'damping', False)
        self.max_force = _option(opts, 'max_force', True)
        self.travel = _option(opts, 'travel', True)
        self.keep_task(config)      # task() and task_dim() answer it (hardware_id names it)
        self._x0 = np.array(config.initial_pose, dtype=float)
        self._x = self._x0.copy()
        self._v = np.zeros_like(self._x0)
        self._u = np.zeros_like(self._x0)
        self.applied = np.zeros_like(self._x0)
        self._t = 0.0
        # Simulation only: the scenario's user pushes the handle, as a person's hand would.
        self._hand = (user_from_config(config.user, config.params.task, 'scenario.user',
                                       self._x0) if hand == 'scenario' and config.user
                      else None)

    @property
    def hardware_id(self) -> str:
        return f'{super().hardware_id} (simulated spring, {self.stiffness:g} N/m)' \
            if self._x0.size else super().hardware_id

    def activate(self) -> None:
        self.task_dim()
        self._active = True           # <- open the device, enable the amplifiers

    def deactivate(self) -> None:
        self._u = np.zeros_like(self._u)
        self.applied = np.zeros_like(self._u)   # <- send zero, disable the amplifiers
        self._active = False

    def write(self, wrench: np.ndarray) -> None:
        if not self._active:
            raise DeviceError('my_spring: write() before activate()')
        u = np.asarray(wrench, dtype=float)
        # Never a non-finite or out-of-range value to the amplifier (the driver clamps to
        # its limits before; this is the device's own saturation).
        self._u = np.clip(np.where(np.isfinite(u), u, 0.0), -self.max_force, self.max_force)

    def read(self, dt: float) -> DeviceReading:
        if not self._active:
            raise DeviceError('my_spring: read() before activate()')
        # <- on a real device: send self._u, receive pose, twist and the hand's wrench
        self.applied = self._u.copy()
        push = (self._hand.wrench(self._t, self._x, self._v) if self._hand is not None
                else np.zeros_like(self._x))
        spring = -self.stiffness * (self._x - self._x0) - self.damping * self._v
        self._v = self._v + (self.applied + spring + push) / self.mass * dt
        self._x = self._x + self._v * dt
        self._t += dt
        out = np.abs(self._x - self._x0) > self.travel
        status = DeviceStatus.OK
        if out.any():
            status = DeviceStatus.FAULT
            self._reason = (f'my_spring: out of travel on axis {int(np.argmax(out))} '
                            f'(> {self.travel:g} m from the start)')
        return DeviceReading(self._x.copy(), self._v.copy(), push, status)

    def fault_reason(self) -> str:
        return self._reason or super().fault_reason()
