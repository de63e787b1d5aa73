"""One haptic cycle: LMI step, coordination wrench, control law (the lmi_controller's core).

The ROS node ``lmi_controller`` and the offline lock-step simulation both call
:meth:`HapticController.cycle` once per device state and :meth:`HapticController.update` once
per LMI update, so the graph can be checked against the offline result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from haptic_topology.control.laws import ControlGains, stable_hold
from haptic_topology.control.lmi import LmiModel, LmiSnapshot, LmiSync, LocalModel
from haptic_topology.control.passivity import EnergyAccount, PassivityConfig
from haptic_topology.vocabulary import ControlMode, TaskSpace


class CycleOutput(NamedTuple):
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


@dataclass(frozen=True, slots=True)
class PreparedUpdate:
    """An LMI update with everything a re-sync computes from it
    (:meth:`HapticController.prepare`): the LMI's matrices and the stable step (s)."""

    sync: LmiSync
    stable_dt: float
    #: ``M_d Lambda_h^-1`` of eq. 10 (m x m), for the device inertia of the controller that
    #: prepared it.
    ml: np.ndarray

    @property
    def snapshot(self) -> LmiSnapshot:
        return self.sync.snapshot


class HapticController:
    """Eq. 14 / eq. 10 on top of the LMI, for a device of inertia ``M_d`` (eq. 9), with its
    energy account and passivity controller (``passivity``, for the nominal device period
    ``period``, s; :mod:`haptic_topology.control.passivity`)."""

    def __init__(self, task: TaskSpace, mode: ControlMode, gains: ControlGains,
                 device_mass: np.ndarray, device_christoffel: np.ndarray,
                 lmi_model: LmiModel = LmiModel.EQ17, vt_coupling: bool = True,
                 passivity: PassivityConfig | None = None, period: float = 1e-3) -> None:
        m = task.dim
        for name, arr, shape in (('device_mass', device_mass, (m, m)),
                                 ('device_christoffel', device_christoffel, (m, m)),
                                 ('k_pc', gains.k_pc, (m,)), ('b_pc', gains.b_pc, (m,))):
            if np.shape(arr) != shape:
                raise ValueError(f'{name} must have shape {shape}, got {np.shape(arr)}')
        if np.any(gains.b_d) or np.any(gains.k_d):
            raise ValueError('gains.b_d and gains.k_d (eq. 4) must be zero: the controller '
                             'renders the VT with b_d = k_d = 0, as the paper does')
        # Imported here, as in LocalModel.__init__: loading the compiled code costs ~1 s.
        from haptic_topology.control.compiled import task_force_step
        from haptic_topology.control.energy import task_law_energy
        self._law, self._force_step = task_law_energy, task_force_step
        self.task = task
        self._rot = task.rotation_dim
        self.mode = mode
        self.gains = gains
        self.m_d = np.asarray(device_mass, dtype=float)
        self.c_d = np.asarray(device_christoffel, dtype=float)
        self.vt_coupling = vt_coupling
        self.lmi = LocalModel(task, lmi_model, device_inertia=self.m_d)
        #: Longest LMI step (s) this model integrates stably (see ``_stable_dt``).
        self.stable_dt = math.inf
        self._ml = np.zeros((m, m))           # M_d Lambda_h^-1 at the newest re-sync
        #: Energy at the device port and the passivity controller.
        self.energy = EnergyAccount(m, passivity or PassivityConfig(), period, self.m_d)

    def __getstate__(self) -> dict[str, object]:
        # A compiled function pickles by value and compiles again where it is unpickled
        # (seconds): the loop process takes its own from its import instead.
        state = self.__dict__.copy()
        del state['_law'], state['_force_step']
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        from haptic_topology.control.compiled import task_force_step
        from haptic_topology.control.energy import task_law_energy
        self.__dict__.update(state)
        self._law, self._force_step = task_law_energy, task_force_step

    def prepare(self, snap: LmiSnapshot) -> PreparedUpdate:
        """What :meth:`update` computes from ``snap`` alone (the LMI's matrices, eqs. 17-19,
        and the stable step): a function of the update and of this controller's fixed
        settings (task, LMI model, ``K_pc``, ``B_pc``, VT coupling), so any thread may call it
        (the one that receives the update) and the loop only adopts the result."""
        sync = self.lmi.prepare(snap)
        return PreparedUpdate(sync, self._stable_dt(sync.lambda_inv),
                              self.m_d @ sync.lambda_inv)

    def update(self, update: LmiSnapshot | PreparedUpdate) -> None:
        """Re-sync the LMI to an update of the full simulation (eqs. 17-19), or to its
        :meth:`prepare`-d form."""
        p = update if isinstance(update, PreparedUpdate) else self.prepare(update)
        self.lmi.sync(p.sync)
        self.stable_dt = p.stable_dt
        self._ml = p.ml

    def force_step(self, pose: np.ndarray, twist: np.ndarray, vt_pose: np.ndarray,
                   vt_twist: np.ndarray) -> float:
        """Estimated force step (N or N m, largest axis) of moving the VT hand from
        ``vt_pose``, ``vt_twist`` to ``pose``, ``twist`` under the current LMI's projector
        (:func:`~haptic_topology.control.compiled.force_step`)."""
        g = self.gains
        return float(self._force_step(self._rot, self.m_d, self.lmi.projector, g.k_pc, g.b_pc,
                                      g.k_tc,
                                      g.b_tc, pose, twist, vt_pose, vt_twist))

    def _stable_dt(self, lambda_inv: np.ndarray) -> float:
        """Longest LMI step (s) that keeps the VT side of the coordination spring stable at
        ``Lambda_h^-1`` = ``lambda_inv`` (eq. 19). Eq. 17 is stepped (semi-implicit Euler)
        with ``F_vt = F_h - F_pc`` held over the measured period, so a long period (a late
        device state) steps the spring explicitly
        (:func:`~haptic_topology.control.laws.stable_hold`). Without VT coupling
        (``F_vt = F_h``) nothing feeds back: inf."""
        if not self.vt_coupling:
            return math.inf
        return stable_hold(lambda_inv, self.gains.k_pc, self.gains.b_pc)

    def cycle(self, seq: int, dt: float, x_h: np.ndarray, xd_h: np.ndarray,
              f_h: np.ndarray) -> CycleOutput:
        """Answer device state ``seq`` (pose ``x_h``, twist ``xd_h``, hand wrench ``f_h``).

        ``dt`` is the measured time (s) since the previous answered state. Before the first
        LMI update there is no model of the VT: the answer is zero force (mode ZERO). The
        arithmetic (LMI step, eqs. 10 and 13-16, the energy account and the passivity
        controller) is compiled (:mod:`haptic_topology.control.compiled`,
        :mod:`haptic_topology.control.energy`).
        """
        m = self.task.dim
        lmi = self.lmi
        if not lmi.synced:
            self.energy.break_period()
            zero = np.zeros(m)
            return CycleOutput(zero, zero, zero, x_h.copy(), xd_h.copy(), 0, ControlMode.ZERO)
        lmi.advance(seq, dt)
        g = self.gains
        f_env = lmi.env_wrench
        u, f_pc, f_vt = np.empty(m), np.empty(m), np.empty(m)
        en = self.energy
        self._law(self._rot, int(self.mode), self.vt_coupling, self._ml, self.m_d, self.c_d,
                  lmi.projector,
                  g.k_pc, g.b_pc, g.k_tc, g.b_tc, lmi.x_vt, lmi.xd_vt, x_h, xd_h, f_h, f_env,
                  u, f_pc, f_vt, dt, en.state)
        lmi.record_input(seq, f_vt)
        return CycleOutput(u, f_pc, f_vt, lmi.x_vt.copy(), lmi.xd_vt.copy(),
                           lmi.constraint_count, self.mode, f_env.copy())
