"""The virtual environment (VE): full configuration-space dynamics of the VT (eqs. 1-2).

Driven by the hand inputs of the haptic loop: each input carries the wrench applied to the VT
at the grasp point (``F_vt``: the user's ``F_h``, minus the coordination wrench when the
coupling acts on the VT) and the time of the device state it was computed at. The VE holds
each input over the interval to the next one (zero-order hold) and integrates eq. 2 with RK4
at a fine internal step. After consuming input k the VE state is the VT at the time of device
state k+1, the same convention as the LMI (:mod:`haptic_topology.control.lmi`).
"""

from __future__ import annotations

import math

import numpy as np

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics


class VirtualEnvironment:
    """Full VT simulation (eq. 2, no contacts) with RK4 at ``internal_step`` seconds."""

    def __init__(self, dynamics: LinkageDynamics, q0: np.ndarray, dq0: np.ndarray,
                 internal_step: float = 2.5e-4, max_gap: float = 0.05) -> None:
        d = dynamics.dof
        if np.shape(q0) != (d,) or np.shape(dq0) != (d,):
            raise ValueError(f'q0 and dq0 must have {d} entries, got {np.shape(q0)} and '
                             f'{np.shape(dq0)}')
        self.dyn = dynamics
        self.q = np.array(q0, dtype=float)
        self.dq = np.array(dq0, dtype=float)
        self.internal_step = internal_step
        self.max_gap = max_gap
        self.time = 0.0
        self.hand_input_seq = -1
        self._held: tuple[int, float, np.ndarray] | None = None

    def _accel(self, q: np.ndarray, dq: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        return self.dyn.acceleration(q, dq, wrench)

    def integrate(self, wrench: np.ndarray, duration: float) -> None:
        """Integrate eq. 2 for ``duration`` s under a constant hand wrench (RK4 substeps)."""
        if duration <= 0.0:
            return
        n = max(1, math.ceil(duration / self.internal_step - 1e-9))
        h = duration / n
        q, dq = self.q, self.dq
        for _ in range(n):
            k1q, k1v = dq, self._accel(q, dq, wrench)
            k2q = dq + 0.5 * h * k1v
            k2v = self._accel(q + 0.5 * h * k1q, k2q, wrench)
            k3q = dq + 0.5 * h * k2v
            k3v = self._accel(q + 0.5 * h * k2q, k3q, wrench)
            k4q = dq + h * k3v
            k4v = self._accel(q + h * k3q, k4q, wrench)
            q = q + h / 6.0 * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
            dq = dq + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
        self.q, self.dq = q, dq
        self.time += duration

    def push_input(self, seq: int, stamp: float, wrench: np.ndarray) -> None:
        """Take the hand input of device state ``seq`` at time ``stamp`` (s).

        The previously held input is integrated up to ``stamp`` (at most ``max_gap`` s, so a
        pause of the haptic loop does not make the VT jump), then this one is held.
        """
        if self._held is not None:
            held_seq, held_stamp, held_wrench = self._held
            if seq <= held_seq:
                return  # duplicate or out-of-order input: ignore
            self.integrate(held_wrench, min(stamp - held_stamp, self.max_gap))
            self.hand_input_seq = held_seq
        self._held = (seq, stamp, np.array(wrench, dtype=float))

    def snapshot(self, seq: int) -> LmiSnapshot:
        """The LMI update for the current state (eqs. 17-19)."""
        snap = self.dyn.snapshot(self.q, self.dq)
        return LmiSnapshot.from_dynamics(snap, self.dyn.task,
                                         self.dyn.linkage.constraints.characteristic_length,
                                         seq, self.hand_input_seq)

    def kinetic_energy(self) -> float:
        """``0.5 dq^T D(q) dq`` (J)."""
        return 0.5 * float(self.dq @ self.dyn.mass_matrix(self.q) @ self.dq)
