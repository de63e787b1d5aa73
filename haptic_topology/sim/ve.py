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
from dataclasses import replace

import numpy as np
import pinocchio as pin

from haptic_topology.control.laws import StableHold
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.compiled import rk4_finish, rk4_stage
from haptic_topology.dynamics.constraints import task_scale
from haptic_topology.dynamics.contacts import ContactModel
from haptic_topology.dynamics.linkage_dynamics import (
    LinkageDynamics,
    inverse_operational_inertia,
)
from haptic_topology.dynamics.rk4 import rk4_step
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.errors import SimulationError

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
#: ABA in world coordinates: the same qdd as the local form to rounding (1e-16 relative for
#: Table I, 1e-11 for a 100-link chain whose D has a condition number of 1e8) and 10-18 %
#: faster from ~100 joints on.
_ABA_FRAME = pin.Convention.WORLD


def _frame_jacobian_6x1(model: pin.Model, data: pin.Data, q: np.ndarray, frame: int,
                        ref: pin.ReferenceFrame) -> np.ndarray:
    """``pin.computeFrameJacobian`` of a 1-DOF model, which Pinocchio returns as a flat
    vector of 6, as the 6 x 1 matrix it is."""
    return pin.computeFrameJacobian(model, data, q, frame, ref).reshape(6, 1)


class VirtualEnvironment:
    """Full VT simulation (eq. 2, with the contacts of ``contacts`` when given) with RK4 at
    ``internal_step`` seconds.

    ``q`` (rad / m) and ``dq`` (rad/s / m/s) are replaced by new arrays when the VE
    moves, never changed in place; the arrays the VE makes itself are read-only.
    """

    def __init__(self, dynamics: LinkageDynamics, q0: np.ndarray, dq0: np.ndarray,
                 internal_step: float = 2.5e-4, max_gap: float = 0.05,
                 coupling: tuple[np.ndarray, np.ndarray] | None = None,
                 contacts: ContactModel | None = None) -> None:
        d = dynamics.dof
        if np.shape(q0) != (d,) or np.shape(dq0) != (d,):
            raise ValueError(f'q0 and dq0 must have {d} entries, got {np.shape(q0)} and '
                             f'{np.shape(dq0)}')
        self.dyn = dynamics
        self.q = np.array(q0, dtype=float)
        self.dq = np.array(dq0, dtype=float)
        if dynamics.loops is not None:      # the mobility of the start, through the run
            dynamics.loops.keep_rank(self.q)
        self.internal_step = internal_step
        self.max_gap = max_gap
        #: ``(K_pc, B_pc)`` when the hand input carries the coordination wrench (VT
        #: coupling): a held input is then integrated for at most ``hold_limit``.
        self.coupling = coupling
        self._stable_hold = None if coupling is None else StableHold(*coupling)
        self.hold_limit = max_gap
        self.held_capped = 0        # inputs whose gap exceeded the stable hold
        self.time = 0.0
        self.hand_input_seq = -1
        self._held: tuple[int, float, np.ndarray] | None = None
        #: ``(input seq, VT hand pose)`` after each consumed input, until :meth:`take_path`.
        self.path: list[tuple[int, np.ndarray]] = []
        # RK4 workspace, allocated once. Row i of _stage is stage i's [q_i, dq_i, qdd_i]
        # (3d): [q_i, dq_i] is the state the stage is evaluated at and [dq_i, qdd_i] its
        # derivative k_i, both contiguous views of the same row.
        z = self._stage = np.zeros((4, 3 * d))
        stages = range(4)
        self._views = (tuple(z[i, :d] for i in stages), tuple(z[i, d:2 * d] for i in stages),
                       tuple(z[i, 2 * d:] for i in stages),
                       tuple(z[i, :2 * d] for i in stages),   # stage states [q_i, dq_i]
                       z[:, d:])                               # derivatives [dq_i, qdd_i]
        self._wrench6 = np.zeros(6)
        self._pin = (dynamics.model, dynamics.data, dynamics.hand_frame,
                     pin.computeFrameJacobian if d > 1 else _frame_jacobian_6x1)
        #: ``(q, dq)`` arrays the last integration left in stage 1 of the workspace.
        self._state_out: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        # The frame Jacobian's rows of the task: a slice where it is all of them (spatial).
        task_rows = dynamics.task_rows
        self._task_rows: slice | list[int] = (slice(0, 6) if task_rows == tuple(range(6))
                                              else list(task_rows))
        #: ``(q, J_6, pose)``: the grasp frame's 6 x d Jacobian and task pose at the array
        #: ``q`` (identity: one of the VE's own read-only arrays), for the next integration's
        #: first stage, the path and the snapshot.
        self._hand: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        #: Contacts with the obstacles (eq. 1's ``sum J_i^T F_i``), None: no obstacles.
        self.contacts = contacts
        #: Work of the contact forces on the VT since the start (J), integrated by RK4.
        self.contact_work = 0.0
        self._potential0 = 0.0 if contacts is None else contacts.potential(self.q)

    def contact_energy_balance(self) -> float:
        """``W + U - U(0)`` (J): the contacts' work on the VT plus their elastic energy now
        minus at the start; <= 0 for the passive contact model up to integration error
        (:mod:`haptic_topology.dynamics.contacts`)."""
        if self.contacts is None:
            return 0.0
        return self.contact_work + self.contacts.potential(self.q) - self._potential0

    def _hand_now(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasp frame's 6 x d Jacobian and task pose at the current ``q``."""
        if self._hand is not None and self._hand[0] is self.q:
            return self._hand[1], self._hand[2]
        j6 = self.dyn.hand_frame_jacobian(self.q)
        pose = self.dyn.hand_pose_in_data()
        if not self.q.flags.writeable:  # the VE's own array: nobody can change it in place
            self._hand = (self.q, j6, pose)
        return j6, pose

    def integrate(self, wrench: np.ndarray, duration: float) -> None:
        """Integrate eq. 2, ``qdd = D^-1 (J_h^T F - B - G)`` (eq. 1 without contacts), for
        ``duration`` s under a constant hand wrench ``F`` (m entries: N and N m, world-aligned
        at the grasp point) with classical RK4 substeps of at most ``internal_step`` s;
        ``q`` in rad (m for prismatic joints), ``dq`` in rad/s (m/s).

        Each stage costs two Pinocchio calls: the grasp frame's 6 x d Jacobian (eq. 7), for the
        joint torques ``J_h^T F`` of eq. 12, and the articulated-body algorithm for ``qdd``
        (eq. 2, without forming ``D^-1``; in world coordinates, see ``_ABA_FRAME``). The
        stage arithmetic runs on preallocated arrays in the order of the textbook form
        ``x + h/6 (k1 + 2 k2 + 2 k3 + k4)``, so the result is that form's bit for bit
        (``test_core_ve``).
        """
        if duration <= 0.0:
            return
        n = max(1, math.ceil(duration / self.internal_step - 1e-9))
        h = duration / n
        if self.dyn.loops is not None:
            self._integrate_loops(wrench, n, h)
            self.time += duration
            return
        if self.contacts is not None:
            self._integrate_contacts(wrench, n, h)
            self.time += duration
            return
        model, data, frame, jacobian = self._pin
        aba = pin.aba
        w6 = self._wrench6
        w6[self._task_rows] = wrench   # zero in the rows outside the task (planar)
        (q1, q2, q3, q4), (v1, v2, v3, v4), (a1, a2, a3, a4), (x1, x2, x3, x4), \
            derivs = self._views
        j6 = self._hand_now()[0]
        if self.q is not self._state_out[0] or self.dq is not self._state_out[1]:
            q1[:] = self.q      # else stage 1 still holds the state the last call left
            v1[:] = self.dq
        half = 0.5 * h
        sixth = h / 6.0
        # Each stage: the acceleration a_i from Pinocchio, then one compiled call stores it
        # and forms the next stage's state x + c k_i (w6.dot(J): ~0.2-0.4 us less per call
        # than J.T.dot, same bits).
        for step in range(n):
            if step:
                j6 = jacobian(model, data, q1, frame, _LWA)
            rk4_stage(x1, v1, aba(model, data, q1, v1, w6.dot(j6), _ABA_FRAME), half, a1,
                      x2)                                       # x + h/2 k1
            rk4_stage(x1, v2, aba(model, data, q2, v2,
                                  w6.dot(jacobian(model, data, q2, frame, _LWA)),
                                  _ABA_FRAME), half, a2, x3)    # x + h/2 k2
            rk4_stage(x1, v3, aba(model, data, q3, v3,
                                  w6.dot(jacobian(model, data, q3, frame, _LWA)),
                                  _ABA_FRAME), h, a3, x4)       # x + h k3
            a4[:] = aba(model, data, q4, v4,
                        w6.dot(jacobian(model, data, q4, frame, _LWA)), _ABA_FRAME)
            rk4_finish(derivs, sixth, x1)     # x += h/6 (k1 + 2 k2 + 2 k3 + k4)
        q = q1.copy()
        dq = v1.copy()
        q.flags.writeable = False
        dq.flags.writeable = False
        self.q, self.dq = self._state_out = q, dq
        self.time += duration

    def _integrate_contacts(self, wrench: np.ndarray, n: int, h: float) -> None:
        """``n`` RK4 steps of ``h`` s of eq. 2 with the contacts,
        ``qdd = D^-1 (sum_i J_i^T F_i + J_h^T F - B - G)``, and of the contacts' work
        ``W`` (``Wdot = sum_i F_i^T v_i``) with the same stages."""
        model, data, frame, jacobian = self._pin
        contacts = self.contacts
        assert contacts is not None
        w6 = self._wrench6
        w6[self._task_rows] = wrench
        q, dq = np.array(self.q), np.array(self.dq)
        work = 0.0

        def deriv(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, float]:
            tau_c, power = contacts.torques(qs, vs)
            tau = w6.dot(jacobian(model, data, qs, frame, _LWA)) + tau_c
            return np.array(pin.aba(model, data, qs, vs, tau, _ABA_FRAME)), power

        for _ in range(n):
            q, dq, step_work = rk4_step(deriv, q, dq, h)
            work += step_work
        self.contact_work += work
        q.flags.writeable = False
        dq.flags.writeable = False
        self.q, self.dq = q, dq
        self._state_out = (None, None)

    def _integrate_loops(self, wrench: np.ndarray, n: int, h: float) -> None:
        """``n`` RK4 steps of ``h`` s of the closed chain, ``D qdd = J_h^T F + sum_i J_i^T F_i
        - B - G + J_c^T lambda`` (:meth:`~haptic_topology.dynamics.loops.LoopClosures.step`:
        the closures held by a projection after each step), and of the contacts' work."""
        model, data, frame, jacobian = self._pin
        loops, contacts = self.dyn.loops, self.contacts
        assert loops is not None
        w6 = self._wrench6
        w6[self._task_rows] = wrench
        dyn = self.dyn

        def stage(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
            tau = w6.dot(jacobian(model, data, qs, frame, _LWA)) - dyn.bias(qs, vs)
            if contacts is None:
                return dyn.mass_matrix(qs), tau, 0.0
            tau_c, power = contacts.torques(qs, vs)
            return dyn.mass_matrix(qs), tau + tau_c, power

        q, dq = np.array(self.q), np.array(self.dq)
        for _ in range(n):
            q, dq, work = loops.step(q, dq, h, stage, dyn.mass_matrix)
            self.contact_work += work
        q.flags.writeable = False
        dq.flags.writeable = False
        self.q, self.dq = q, dq
        self._state_out = (None, None)

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
            self.path.append((held_seq, self._hand_now()[1].copy()))
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
        if self.dyn.loops is not None:     # back onto the closures, in the metric of D
            q, dq = self.dyn.loops.project(q, dq, self.dyn.mass_matrix)
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

    @property
    def state_finite(self) -> bool:
        """Whether ``q`` and ``dq`` are finite (False: the integration diverged)."""
        return bool(np.isfinite(self.q).all() and np.isfinite(self.dq).all())

    def snapshot(self, seq: int) -> LmiSnapshot:
        """The LMI update for the current state (eqs. 17-19); a state that is no longer
        finite (the integration diverged) is a :class:`~haptic_topology.errors.SimulationError`
        naming when, never an update."""
        if not self.state_finite:
            raise SimulationError(
                f'VE state not finite at t = {self.time:.6g} s (hand input '
                f'{self.hand_input_seq}): the integration of eq. 2 diverged (q = '
                f'{self.q.tolist()[:6]}{" ..." if self.q.size > 6 else ""}); the inputs drove '
                'the linkage beyond what it can model (an unbounded hand wrench, or an '
                'internal_step too long for its inertias)')
        j6, pose = self._hand_now()
        snap = self.dyn.snapshot(self.q, self.dq, (j6, pose.copy()))
        local = None if self.contacts is None else self.contacts.local(self.q)
        n = snap.mechanism
        if local is not None and n is not None:
            # In the closed chain's independent velocities, as the rest of the snapshot.
            local = replace(local, q=np.zeros(n.shape[1]),
                            jacobians=np.einsum('cid,df->cif', local.jacobians, n))
        out = LmiSnapshot.from_dynamics(snap, self.dyn.task,
                                        self.dyn.linkage.constraints.characteristic_length,
                                        seq, self.hand_input_seq, local,
                                        self.contact_energy_balance())
        if self._stable_hold is not None:
            lambda_inv = (self.dyn.inverse_operational_inertia_aba(self.q, out.hand_jacobian)
                          if self.dyn.loops is None else inverse_operational_inertia(
                              out.hand_jacobian, out.mass_matrix))
            self.hold_limit = min(self.max_gap, self._stable_hold(lambda_inv))
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
    * ``seq`` jumping: the inputs in between were lost (counted in ``lost``);
    * the first input, if not the controller's first (``seq > 1``): this VE joins a running
      loop (it was restarted): the VT is placed where the hand is
      (:meth:`VirtualEnvironment.place_hand`), not left at ``q0``;
    * :meth:`VirtualEnvironment.push_input` with the stamp relative to the first input's;
    * every ``update_period``-th input the caller publishes an LMI update (``take`` returns
      True), also when that input is in the middle of a batch.

    Events for the node's log go to ``notices`` (drained by the node).
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
