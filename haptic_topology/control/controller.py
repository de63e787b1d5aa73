"""One haptic cycle: LMI step, coordination wrench, control law (the lmi_controller's core).

The ROS node ``lmi_controller`` and the offline lock-step simulation both call
:meth:`HapticController.cycle` once per device state and :meth:`HapticController.update` once
per LMI update, so the graph can be checked against the offline result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from haptic_topology.control.laws import (
    ControlGains,
    ControlMode,
    control_wrench,
    coordination_wrench,
)
from haptic_topology.control.lmi import LmiModel, LmiSnapshot, LocalModel
from haptic_topology.model.linkage import TaskSpace


@dataclass(frozen=True)
class CycleOutput:
    """Result of one cycle (task vectors, m entries).

    ``wrench`` u for the device (eq. 14 / eq. 10); ``coupling`` F_pc; ``vt_wrench`` the wrench
    on the VT at the hand (``F_h - F_pc`` with VT coupling, else ``F_h``); ``vt_pose``/
    ``vt_twist`` the LMI's VT hand at this state; ``constraint_count`` t.
    """

    wrench: np.ndarray
    coupling: np.ndarray
    vt_wrench: np.ndarray
    vt_pose: np.ndarray
    vt_twist: np.ndarray
    constraint_count: int
    mode: ControlMode


class HapticController:
    """Eq. 14 / eq. 10 on top of the LMI, for a device of inertia ``M_d`` (eq. 9)."""

    def __init__(self, task: TaskSpace, mode: ControlMode, gains: ControlGains,
                 device_mass: np.ndarray, device_christoffel: np.ndarray,
                 lmi_model: LmiModel = LmiModel.EQ17, vt_coupling: bool = True) -> None:
        m = task.dim
        for name, arr, shape in (('device_mass', device_mass, (m, m)),
                                 ('device_christoffel', device_christoffel, (m, m)),
                                 ('k_pc', gains.k_pc, (m,)), ('b_pc', gains.b_pc, (m,))):
            if np.shape(arr) != shape:
                raise ValueError(f'{name} must have shape {shape}, got {np.shape(arr)}')
        self.task = task
        self.mode = mode
        self.gains = gains
        self.m_d = np.asarray(device_mass, dtype=float)
        self.c_d = np.asarray(device_christoffel, dtype=float)
        self.vt_coupling = vt_coupling
        self.lmi = LocalModel(task, lmi_model)
        #: Longest LMI step (s) this model integrates stably (see :meth:`_stable_dt`).
        self.stable_dt = math.inf

    def update(self, snap: LmiSnapshot) -> None:
        """Re-sync the LMI to an update of the full simulation (eqs. 17-19)."""
        self.lmi.sync(snap)
        self.stable_dt = self._stable_dt()

    def _stable_dt(self) -> float:
        """Half the longest step (s) for which the VT side of the coordination spring stays
        stable. Eq. 17 is stepped (semi-implicit Euler) with ``F_vt = F_h - F_pc`` held over
        the measured period, so a long period (a late device state) steps the spring
        explicitly: for ``x'' = -k x - b x'`` that is stable while ``k dt^2 + 2 b dt < 4``,
        with ``k``, ``b`` (1/s^2, 1/s) the largest eigenvalues of ``K_pc^1/2 Lambda^-1
        K_pc^1/2`` and ``B_pc^1/2 Lambda^-1 B_pc^1/2`` (eq. 19's task-space inverse
        inertia). Without VT coupling (``F_vt = F_h``) nothing feeds back: inf."""
        if not self.vt_coupling:
            return math.inf
        lam = self.lmi.lambda_inv

        def largest(gain: np.ndarray) -> float:
            r = np.sqrt(np.maximum(gain, 0.0))
            return float(np.linalg.eigvalsh(r[:, None] * lam * r[None, :]).max())

        k, b = max(largest(self.gains.k_pc), 0.0), max(largest(self.gains.b_pc), 0.0)
        if k <= 0.0 and b <= 0.0:
            return math.inf
        limit = (-b + math.sqrt(b * b + 4.0 * k)) / k if k > 0.0 else 2.0 / b
        return 0.5 * limit

    def cycle(self, seq: int, dt: float, x_h: np.ndarray, xd_h: np.ndarray,
              f_h: np.ndarray) -> CycleOutput:
        """Answer device state ``seq`` (pose ``x_h``, twist ``xd_h``, hand wrench ``f_h``).

        ``dt`` is the measured time (s) since the previous answered state. Before the first
        LMI update there is no model of the VT: the answer is zero force (mode ZERO).
        """
        m = self.task.dim
        lmi = self.lmi
        if not lmi.synced:
            zero = np.zeros(m)
            return CycleOutput(zero, zero, zero, x_h.copy(), xd_h.copy(), 0, ControlMode.ZERO)
        lmi.advance(seq, dt)
        f_pc = coordination_wrench(lmi.x_vt, lmi.xd_vt, x_h, xd_h, self.gains.k_pc,
                                   self.gains.b_pc, self.task)
        u = control_wrench(self.mode, lmi.lambda_inv, self.m_d, self.c_d, f_h, f_pc, x_h,
                           xd_h, lmi.x_vt, lmi.xd_vt, lmi.projector, self.gains, self.task)
        f_vt = f_h - f_pc if self.vt_coupling else f_h.copy()
        lmi.record_input(seq, f_vt)
        return CycleOutput(u, f_pc, f_vt, lmi.x_vt.copy(), lmi.xd_vt.copy(),
                           lmi.constraint_count, self.mode)
