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
    control_wrench,
    coordination_wrench,
    stable_hold,
)
from haptic_topology.control.lmi import LmiModel, LmiSnapshot, LocalModel
from haptic_topology.vocabulary import ControlMode, TaskSpace


@dataclass(frozen=True)
class CycleOutput:
    """Result of one cycle (task vectors, m entries).

    ``wrench`` u for the device (eq. 14 / eq. 10); ``coupling`` F_pc; ``vt_wrench`` the wrench
    on the VT at the hand (``F_h - F_pc`` with VT coupling, else ``F_h``); ``vt_pose``/
    ``vt_twist`` the LMI's VT hand at this state; ``constraint_count`` t; ``env_wrench``
    ``F_env`` of eqs. 10 and 14 (the LMI's contacts as a wrench at the hand; None: zero).
    """

    wrench: np.ndarray
    coupling: np.ndarray
    vt_wrench: np.ndarray
    vt_pose: np.ndarray
    vt_twist: np.ndarray
    constraint_count: int
    mode: ControlMode
    env_wrench: np.ndarray | None = None


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
        #: Longest LMI step (s) this model integrates stably (see ``_stable_dt``).
        self.stable_dt = math.inf

    def update(self, snap: LmiSnapshot) -> None:
        """Re-sync the LMI to an update of the full simulation (eqs. 17-19)."""
        self.lmi.sync(snap)
        self.stable_dt = self._stable_dt()

    def _stable_dt(self) -> float:
        """Longest LMI step (s) that keeps the VT side of the coordination spring stable.
        Eq. 17 is stepped (semi-implicit Euler) with ``F_vt = F_h - F_pc`` held over the
        measured period, so a long period (a late device state) steps the spring explicitly
        (:func:`~haptic_topology.control.laws.stable_hold`). Without VT coupling
        (``F_vt = F_h``) nothing feeds back: inf."""
        if not self.vt_coupling:
            return math.inf
        return stable_hold(self.lmi.lambda_inv, self.gains.k_pc, self.gains.b_pc)

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
        f_env = lmi.env_wrench
        u = control_wrench(self.mode, lmi.lambda_inv, self.m_d, self.c_d, f_h, f_pc, x_h,
                           xd_h, lmi.x_vt, lmi.xd_vt, lmi.projector, self.gains, self.task,
                           f_env)
        f_vt = f_h - f_pc if self.vt_coupling else f_h.copy()
        lmi.record_input(seq, f_vt)
        return CycleOutput(u, f_pc, f_vt, lmi.x_vt.copy(), lmi.xd_vt.copy(),
                           lmi.constraint_count, self.mode, f_env.copy())
