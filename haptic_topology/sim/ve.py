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
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.control.laws import stable_hold
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.constraints import task_scale
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.validate import as_bool, as_float, check_keys


@dataclass(frozen=True)
class VeSettings:
    """The ``ve:`` block of a scenario: RK4 ``internal_step`` (s, in (0, dt]) and whether the
    coordination wrench acts on the VT (``vt_coupling``: ``F_vt = F_h - F_pc``, else ``F_h``)."""

    internal_step: float = 2.5e-4
    vt_coupling: bool = True

    @classmethod
    def from_config(cls, raw: Any, where: str, dt: float) -> VeSettings:
        """Parse the block (``where``: its path); ``dt``: the scenario's device period (s)."""
        ve = check_keys(raw, where, optional=('internal_step', 'vt_coupling'))
        step = as_float(ve.get('internal_step', 2.5e-4), f'{where}.internal_step', lo=0.0,
                        lo_open=True, hi=dt)
        return cls(step, as_bool(ve.get('vt_coupling', True), f'{where}.vt_coupling'))


class VirtualEnvironment:
    """Full VT simulation (eq. 2, no contacts) with RK4 at ``internal_step`` seconds."""

    def __init__(self, dynamics: LinkageDynamics, q0: np.ndarray, dq0: np.ndarray,
                 internal_step: float = 2.5e-4, max_gap: float = 0.05,
                 coupling: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        d = dynamics.dof
        if np.shape(q0) != (d,) or np.shape(dq0) != (d,):
            raise ValueError(f'q0 and dq0 must have {d} entries, got {np.shape(q0)} and '
                             f'{np.shape(dq0)}')
        self.dyn = dynamics
        self.q = np.array(q0, dtype=float)
        self.dq = np.array(dq0, dtype=float)
        self.internal_step = internal_step
        self.max_gap = max_gap
        #: ``(K_pc, B_pc)`` when the hand input carries the coordination wrench (VT
        #: coupling): a held input is then integrated for at most :attr:`hold_limit`.
        self.coupling = coupling
        self.hold_limit = max_gap
        self.held_capped = 0        # inputs whose gap exceeded the stable hold
        self.time = 0.0
        self.hand_input_seq = -1
        self._held: tuple[int, float, np.ndarray] | None = None
        #: ``(input seq, VT hand pose)`` after each consumed input, until :meth:`take_path`.
        self.path: list[tuple[int, np.ndarray]] = []

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
        pause of the haptic loop does not make the VT jump, and with VT coupling at most the
        stable hold of the coordination spring at the last snapshot's inertia, see
        :func:`~haptic_topology.control.laws.stable_hold`: inputs seconds apart on a starved
        machine must not blow the VE up), then this one is held.
        """
        if self._held is not None:
            held_seq, held_stamp, held_wrench = self._held
            if seq <= held_seq:
                return  # duplicate or out-of-order input: ignore
            gap = stamp - held_stamp
            if gap > self.hold_limit:
                self.held_capped += 1
            self.integrate(held_wrench, min(gap, self.hold_limit))
            self.hand_input_seq = held_seq
            self.path.append((held_seq, self.dyn.hand_pose(self.q)))
        self._held = (seq, stamp, np.array(wrench, dtype=float))

    def place_hand(self, pose: np.ndarray, twist: np.ndarray, iterations: int = 100,
                   damping: float = 1e-3) -> float:
        """Move the VT so that its grasp point is at ``pose`` moving with ``twist`` (damped
        least squares from the current ``q``, rotations weighted by ``L_c``); return the
        remaining weighted pose error (m).

        Used by a ``ve_sim`` that joins a running loop (restarted): the hand is where the
        device is, so starting the VT there (instead of at the scenario's ``q0``) does not
        make the coordination spring yank it across the workspace.
        """
        task = self.dyn.task
        scale = task_scale(task, self.dyn.linkage.constraints.characteristic_length)
        q = self.q.copy()
        err = np.inf
        for _ in range(iterations):
            e = scale * pose_difference(pose, self.dyn.hand_pose(q), task)
            err = float(np.linalg.norm(e))
            if err < 1e-9:
                break
            j = scale[:, None] * self.dyn.hand_jacobian(q)
            step = j.T @ np.linalg.solve(j @ j.T + damping ** 2 * np.eye(j.shape[0]), e)
            q = q + step * min(1.0, 0.2 / max(float(np.abs(step).max()), 1e-12))
        j = scale[:, None] * self.dyn.hand_jacobian(q)
        dq = j.T @ np.linalg.solve(j @ j.T + 1e-6 * np.eye(j.shape[0]), scale * twist)
        self.q, self.dq = q, dq
        return err

    def take_path(self) -> list[tuple[int, np.ndarray]]:
        """The VT hand poses after the inputs consumed since the last call (oldest first):
        entry ``(s, x)`` is the grasp frame pose at the time of device state ``s + 1``."""
        path, self.path = self.path, []
        return path

    def reset_inputs(self) -> None:
        """Forget the held input and the consumed seq (a new controller numbers its inputs
        afresh): the next input is held without integrating the gap before it."""
        self._held = None
        self.hand_input_seq = -1

    def snapshot(self, seq: int) -> LmiSnapshot:
        """The LMI update for the current state (eqs. 17-19)."""
        snap = self.dyn.snapshot(self.q, self.dq)
        out = LmiSnapshot.from_dynamics(snap, self.dyn.task,
                                        self.dyn.linkage.constraints.characteristic_length,
                                        seq, self.hand_input_seq)
        if self.coupling is not None:
            j = out.hand_jacobian
            lambda_inv = j @ np.linalg.solve(out.mass_matrix, j.T)
            self.hold_limit = min(self.max_gap, stable_hold(lambda_inv, *self.coupling))
        return out

    def kinetic_energy(self) -> float:
        """``0.5 dq^T D(q) dq`` (J)."""
        return 0.5 * float(self.dq @ self.dyn.mass_matrix(self.q) @ self.dq)


class HandFeed:
    """``ve_sim``'s policy for the hand inputs of the haptic loop, one input at a time.

    The inputs come in ``HandInputs`` batches, but each goes through :meth:`take` on its own,
    so how the controller cut them into messages changes nothing the VE computes:

    * ``seq`` (the controller's input counter) not above the previous one: a restarted
      controller; the held input is dropped (:meth:`VirtualEnvironment.reset_inputs`);
    * ``seq`` jumping: the inputs in between were lost (counted in :attr:`lost`);
    * the first input, if not the controller's first (``seq > 1``): this VE joins a running
      loop (it was restarted): the VT is placed where the hand is
      (:meth:`VirtualEnvironment.place_hand`), not left at ``q0``;
    * :meth:`VirtualEnvironment.push_input` with the stamp relative to the first input's;
    * every ``update_period``-th input the caller publishes an LMI update (``take`` returns
      True), also when that input is in the middle of a batch.

    Events for the node's log go to :attr:`notices` (drained by the node).
    """

    def __init__(self, ve: VirtualEnvironment, update_period: int) -> None:
        if update_period < 1:
            raise ValueError(f'update_period must be >= 1, got {update_period}')
        self.ve = ve
        self.update_period = update_period
        self.inputs = 0
        self.last_seq = 0
        self.lost = 0
        self.controller_restarts = 0
        self.t0: float | None = None
        #: Device pose of the newest input (task vector), None before the first.
        self.device_pose: np.ndarray | None = None
        self.notices: list[str] = []

    def take(self, seq: int, state_seq: int, stamp: float, pose: np.ndarray,
             twist: np.ndarray, f_vt: np.ndarray) -> bool:
        """Take the input ``seq`` of loop state ``state_seq`` stamped ``stamp`` (s): device
        ``pose``/``twist``, wrench ``f_vt`` on the VT; True when an LMI update is due now."""
        if self.last_seq and seq <= self.last_seq:
            self.controller_restarts += 1
            self.notices.append(f'hand input seq {seq} after {self.last_seq}: a new '
                                'controller; the held input is dropped')
            self.ve.reset_inputs()
            self.last_seq = 0
        if self.last_seq and seq > self.last_seq + 1:
            self.lost += seq - self.last_seq - 1
        self.last_seq = seq
        if self.t0 is None:
            self.t0 = stamp
            if seq > 1:
                err = self.ve.place_hand(pose, twist)
                self.notices.append(f'joined a running loop (hand input {seq}): VT placed at '
                                    f'the device pose (residual {err:.2e} m)')
        self.device_pose = pose
        self.ve.push_input(state_seq, stamp - self.t0, f_vt)
        self.inputs += 1
        return self.inputs % self.update_period == 0
