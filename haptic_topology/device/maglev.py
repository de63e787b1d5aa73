"""Simulated haptic device: ``M_d xdd + C_d xd = F_h + u`` (eq. 9) with hard stops and saturation.

Task vectors at the user's hand as in :mod:`haptic_topology.dynamics.taskspace` (planar: x, y,
theta; spatial: x, y, z, rotation vector). ``M_d`` is the device inertia (kg, kg m^2),
``C_d`` the Christoffel (velocity) matrix, here constant (N s/m). The planar maglev of the
paper's lab is modelled with ``M_d = I`` (Section VI).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.dynamics.taskspace import integrate_pose
from haptic_topology.errors import ConfigError
from haptic_topology.model.linkage import TaskSpace
from haptic_topology.validate import as_angles, as_vector, check_keys


class DeviceStatus(enum.IntFlag):
    """Bits of ``haptic_topology_msgs/DeviceState.status``."""

    OK = 0
    WORKSPACE_LIMIT = 1
    SATURATED = 2
    WATCHDOG = 4    # output is not the plain command: none yet, stale, or fading in/out
    FAULT = 8
    IDLE = 16       # not engaged yet (always with WATCHDOG): controllers integrate nothing


@dataclass(frozen=True)
class DeviceParams:
    """Device model parameters (task vectors of length m = task.dim).

    ``workspace_lo``/``workspace_hi``: hard stops per pose coordinate (m / rad; +-inf for
    none). ``wrench_limit``: symmetric saturation of u per coordinate (N / N m).
    """

    task: TaskSpace
    mass: np.ndarray
    christoffel: np.ndarray
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    wrench_limit: np.ndarray

    @classmethod
    def unlimited(cls, task: TaskSpace, mass: float = 1.0) -> DeviceParams:
        m = task.dim
        inf = np.full(m, np.inf)
        return cls(task, np.eye(m) * mass, np.zeros((m, m)), -inf, inf, inf.copy())


def device_from_config(raw: Any, where: str, task: TaskSpace) -> tuple[DeviceParams, np.ndarray]:
    """The ``device:`` block of a scenario: its :class:`DeviceParams` and the initial offset
    (device pose - VT hand pose, m / rad). ``where``: the block's path (``file: scenario.device``).

    Keys (all optional): ``offset`` (m values, default 0), ``mass`` and ``christoffel``
    (diagonals of M_d > 0 and C_d >= 0; default 1 and 0), ``workspace: {lo, hi}`` (absolute hard
    stops, m / rad, ``pi`` expressions accepted; default none), ``wrench_limit`` (> 0 per axis,
    N / N m; default 1e9).
    """
    m = task.dim
    dev = check_keys(raw, where, optional=(
        'offset', 'mass', 'christoffel', 'workspace', 'wrench_limit'))
    offset = as_vector(dev.get('offset', [0.0] * m), f'{where}.offset', m)
    mass = np.diag(as_vector(dev.get('mass', [1.0] * m), f'{where}.mass', m, lo=0.0,
                             lo_open=True))
    chris = np.diag(as_vector(dev.get('christoffel', [0.0] * m), f'{where}.christoffel', m,
                              lo=0.0))
    lo = np.full(m, -np.inf)
    hi = np.full(m, np.inf)
    if 'workspace' in dev:
        ws = check_keys(dev['workspace'], f'{where}.workspace', required=('lo', 'hi'))
        lo = as_angles(ws['lo'], f'{where}.workspace.lo', m)
        hi = as_angles(ws['hi'], f'{where}.workspace.hi', m)
        if np.any(lo >= hi):
            raise ConfigError(f'{where}.workspace: expected lo < hi on every axis, got lo='
                              f'{lo.tolist()} hi={hi.tolist()}')
    limit = as_vector(dev.get('wrench_limit', [1e9] * m), f'{where}.wrench_limit', m,
                      lo=0.0, lo_open=True)
    return DeviceParams(task, mass, chris, lo, hi, limit), offset


def saturate(wrench: np.ndarray, limit: np.ndarray) -> tuple[np.ndarray, bool]:
    """Clamp each coordinate of ``wrench`` to ``[-limit, limit]``; report whether any was.

    Non-finite entries are replaced by 0 (and reported as saturated), so that nothing but a
    finite wrench within the limits ever leaves this function.
    """
    finite = np.isfinite(wrench)
    w = np.where(finite, wrench, 0.0)
    clamped = np.clip(w, -limit, limit)
    return clamped, bool((not finite.all()) or np.any(clamped != w))


class MaglevModel:
    """State and one-step integration of the simulated device (semi-implicit Euler)."""

    def __init__(self, params: DeviceParams, pose: np.ndarray,
                 twist: np.ndarray | None = None) -> None:
        m = params.task.dim
        if np.shape(pose) != (m,):
            raise ValueError(f'device pose must have {m} entries, got {np.shape(pose)}')
        self.params = params
        self.pose = np.array(pose, dtype=float)
        self.twist = np.zeros(m) if twist is None else np.array(twist, dtype=float)
        self._mass_inv = np.linalg.inv(params.mass)  # constant, factored once
        self.applied = np.zeros(m)

    def step(self, u: np.ndarray, f_h: np.ndarray, dt: float) -> DeviceStatus:
        """Advance by ``dt`` (s) under control wrench ``u`` and hand wrench ``f_h`` (eq. 9)."""
        p = self.params
        u_sat, saturated = saturate(u, p.wrench_limit)
        self.applied = u_sat
        xdd = self._mass_inv @ (f_h + u_sat - p.christoffel @ self.twist)
        self.twist = self.twist + xdd * dt
        self.pose = integrate_pose(self.pose, self.twist, dt, p.task)
        status = DeviceStatus.SATURATED if saturated else DeviceStatus.OK
        below = self.pose < p.workspace_lo
        above = self.pose > p.workspace_hi
        if below.any() or above.any():
            # Inelastic hard stop: hold at the limit, cancel the velocity into it.
            self.pose = np.clip(self.pose, p.workspace_lo, p.workspace_hi)
            self.twist = np.where((below & (self.twist < 0)) | (above & (self.twist > 0)),
                                  0.0, self.twist)
            status |= DeviceStatus.WORKSPACE_LIMIT
        return status
