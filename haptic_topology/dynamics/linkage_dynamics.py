"""Configuration-space dynamics of a serial linkage on Pinocchio (eqs. 1-2, 6, 7).

``LinkageDynamics`` holds a Pinocchio ``Model`` and its ``Data`` workspace (allocated once);
every method takes the configuration explicitly, Pinocchio style. Units SI; joint coordinates
in rad (revolute) or m (prismatic); task quantities at the grasp point in the world-aligned
frame (see :mod:`haptic_topology.dynamics.taskspace`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from haptic_topology.dynamics.constraints import (
    ConstraintDirections,
    constraint_directions,
    joint_scale,
)
from haptic_topology.dynamics.loops import LoopClosures
from haptic_topology.dynamics.spd import spd_factor, spd_solve
from haptic_topology.dynamics.taskspace import pose_from_placement
from haptic_topology.model.build import LinkageModel, build_model
from haptic_topology.model.linkage import Linkage
from haptic_topology.vocabulary import TaskSpace

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


@dataclass(frozen=True)
class DynamicsSnapshot:
    """Everything the LMI needs from the full simulation at one instant (eqs. 17-19).

    ``mass_matrix`` D (d x d), ``gravity`` G (d), ``coriolis`` B (d), ``hand_jacobian`` J_h
    (m x d), ``hand_pose``/``hand_twist`` (m), ``constraints`` (SVD and directions).
    """

    q: np.ndarray
    dq: np.ndarray
    mass_matrix: np.ndarray
    gravity: np.ndarray
    coriolis: np.ndarray
    hand_jacobian: np.ndarray
    hand_pose: np.ndarray
    hand_twist: np.ndarray
    constraints: ConstraintDirections
    #: A closed chain's ``N`` (d x f, :meth:`LinkageDynamics.mechanism_basis`) that the
    #: snapshot is reduced with; None for a serial linkage.
    mechanism: np.ndarray | None = None


class LinkageDynamics:
    """D(q), B(q, dq), G(q), J_h(q) and friends for one linkage and grasp."""

    def __init__(self, linkage: Linkage | LinkageModel) -> None:
        lm = linkage if isinstance(linkage, LinkageModel) else build_model(linkage)
        self.linkage: Linkage = lm.linkage
        self.model: pin.Model = lm.model
        self.data: pin.Data = lm.model.createData()
        self.hand_frame: int = lm.hand_frame
        self.task: TaskSpace = lm.linkage.task
        self.dof: int = lm.model.nv
        #: Rows of Pinocchio's 6-row frame Jacobian ``(v, w)`` that make up the task space
        #: (:attr:`~haptic_topology.vocabulary.TaskSpace.frame_rows`: a point grasp takes the
        #: translation rows only, the velocity of the grasp point).
        self.task_rows: tuple[int, ...] = self.task.frame_rows
        self._rows = list(self.task_rows)
        scale = joint_scale(self.linkage)
        # Revolute joints only: S = I, and scaling by ones would change nothing.
        self._joint_scale = None if np.all(scale == 1.0) else scale
        self._lower = np.tril(np.ones((self.dof, self.dof), dtype=bool), -1)
        #: G(q) is identically zero (no gravity): the snapshot skips its RNEA pass.
        self._no_gravity = not np.any(np.asarray(self.model.gravity.linear))
        #: The loop closures of a closed chain (None: a serial linkage), see
        #: :meth:`mechanism_basis`.
        self.loops = LoopClosures(lm) if lm.linkage.loops else None

    # -- configuration-space terms (eq. 1) ------------------------------------------------
    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """D(q) (d x d), symmetric positive definite (kg m^2 / kg), by CRBA."""
        m = pin.crba(self.model, self.data, q)  # a copy; only its upper triangle is set
        np.copyto(m, m.T, where=self._lower)
        return m

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G(q) (d), generalized gravity torques (N m / N)."""
        return np.array(pin.computeGeneralizedGravity(self.model, self.data, q))

    def bias(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """B(q, dq) + G(q) (d), by RNEA with zero acceleration."""
        return np.array(pin.nonLinearEffects(self.model, self.data, q, dq))

    def coriolis(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """B(q, dq) (d): Coriolis and centripetal torques of eq. 1."""
        return self.bias(q, dq) - self.gravity(q)

    def coriolis_matrix(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """C(q, dq) (d x d) with ``C dq = B`` and ``Ddot - 2C`` skew-symmetric."""
        return np.array(pin.computeCoriolisMatrix(self.model, self.data, q, dq))

    def forward_dynamics(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """qdd of eq. 2 for joint torques ``tau`` (d), by the articulated-body algorithm."""
        return np.array(pin.aba(self.model, self.data, q, dq, tau))

    # -- hand (grasp frame) ---------------------------------------------------------------
    def hand_placement(self, q: np.ndarray) -> pin.SE3:
        """World placement of the grasp frame."""
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.hand_frame].copy()

    def hand_pose(self, q: np.ndarray) -> np.ndarray:
        """Task pose of the grasp point (m entries, see taskspace)."""
        return pose_from_placement(self.hand_placement(q), self.task)

    def hand_frame_jacobian(self, q: np.ndarray) -> np.ndarray:
        """The grasp frame's 6 x d Jacobian, rows (vx, vy, vz, wx, wy, wz) world-aligned at
        the grasp point (eq. 7 before the task rows are taken); also updates the grasp
        frame's placement in ``data`` (read by :meth:`hand_pose_in_data`)."""
        j = pin.computeFrameJacobian(self.model, self.data, q, self.hand_frame, _LWA)
        # Pinocchio hands a 6x1 Jacobian (one joint) back as a flat vector of 6.
        return np.asarray(j, dtype=float).reshape(6, self.dof)

    def hand_jacobian(self, q: np.ndarray) -> np.ndarray:
        """J_h(q) (m x d) of eq. 7: ``xdot_h = J_h qdot`` at the grasp point, world-aligned.

        Planar rows (vx, vy, wz); spatial rows (vx, vy, vz, wx, wy, wz); a point grasp the
        grasp point's velocity, (vx, vy) planar_point and (vx, vy, vz) spatial_point.
        """
        return self.hand_frame_jacobian(q)[self._rows, :]

    def hand_pose_in_data(self) -> np.ndarray:
        """Task pose of the grasp frame placement last computed in ``data`` (by
        :meth:`hand_frame_jacobian` or :meth:`hand_placement`)."""
        return pose_from_placement(self.data.oMf[self.hand_frame], self.task)

    def wrench6(self, wrench: np.ndarray) -> np.ndarray:
        """A task wrench (m: planar ``(fx, fy, tau_z)``, spatial ``(f, tau)``, a point grasp's
        force ``(fx, fy)`` / ``(fx, fy, fz)``; N, N m, world frame at the grasp point) as the
        6-vector of the frame Jacobian's rows, zero in the rows the task lacks (a point grasp
        transmits no torque), so ``J_6^T F_6 = J_h^T F`` (eq. 12)."""
        w6 = np.zeros(6)
        w6[self._rows] = wrench
        return w6

    def hand_twist(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Hand twist ``J_h dq`` (m entries)."""
        return self.hand_jacobian(q) @ dq

    def hand_wrench_torques(self, q: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        """``J_h^T F`` (d): joint torques of a wrench at the grasp point (eq. 12)."""
        # J_6^T F_6 with zeros in the rows outside the task: equal to J_h^T F bit for bit
        # (the zero terms add exactly 0) and without copying the task rows out of J_6.
        return self.hand_frame_jacobian(q).T.dot(self.wrench6(wrench))

    def inverse_operational_inertia(self, q: np.ndarray) -> np.ndarray:
        """``Lambda_h^-1 = J_h D^-1 J_h^T`` (m x m) of eq. 6; defined at any rank of J_h."""
        return inverse_operational_inertia(self.hand_jacobian(q), self.mass_matrix(q))

    def inverse_operational_inertia_aba(self, q: np.ndarray,
                                        jacobian: np.ndarray) -> np.ndarray:
        """``Lambda_h^-1 = J_h D^-1 J_h^T`` (m x m, eq. 6) for ``jacobian`` = J_h(q), with
        ``D^-1`` from Pinocchio's ABA-based ``computeMinverse`` (O(d^2)) instead of a LAPACK
        factorization: OpenBLAS runs the latter on threads from about 100 joints on, and on a
        loaded machine those took 0.4-1.5 ms at p99 instead of 0.1-0.4 ms. Equal to
        :meth:`inverse_operational_inertia` to rounding (1e-15 relative for Table I, up to
        ~1e-11 for a 100-link chain whose D has a condition number of ~1e8)."""
        minv = pin.computeMinverse(self.model, self.data, q)  # a copy; upper triangle set
        np.copyto(minv, minv.T, where=self._lower)
        return jacobian @ minv @ jacobian.T

    def mechanism_basis(self, q: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        """``N`` (d x f): the closed chain's velocities are ``dq = N v`` (``N = S N_w``,
        ``N_w`` an orthonormal basis of ``N(J_c S)``, so that ``v`` is unit-independent like
        the weighted joint rates); the identity for a serial linkage. ``dq``: the joint rates
        at ``q``, which choose the free directions at a singular configuration of the
        closures (:meth:`~haptic_topology.dynamics.loops.LoopClosures.basis`)."""
        if self.loops is None:
            return np.eye(self.dof)
        return self.loops.column_scale[:, None] * self.loops.basis(q, velocity=dq).scaled_null

    def constraints(self, q: np.ndarray) -> ConstraintDirections:
        """Weighted SVD of J_h and directions of topological constraint (eq. 13, 18); of
        ``J_h N`` for a closed chain (``t = m - rank(J_h N)``)."""
        if self.loops is not None:
            return constraint_directions(self.hand_jacobian(q) @ self.mechanism_basis(q),
                                         self.task, self.linkage.constraints)
        return constraint_directions(self.hand_jacobian(q), self.task,
                                     self.linkage.constraints, self._joint_scale)

    def acceleration(self, q: np.ndarray, dq: np.ndarray, hand_wrench: np.ndarray) -> np.ndarray:
        """qdd of eq. 2 with the hand wrench as the only external load (no contacts)."""
        return self.forward_dynamics(q, dq, self.hand_wrench_torques(q, hand_wrench))

    def snapshot(self, q: np.ndarray, dq: np.ndarray,
                 hand: tuple[np.ndarray, np.ndarray] | None = None) -> DynamicsSnapshot:
        """All LMI quantities at (q, dq) in one pass (CRBA, RNEA, frame Jacobian, SVD); for a
        closed chain in its independent velocities (``D_r = N^T D N``, ``G_r = N^T G``,
        ``J_r = J_h N`` with ``N`` of :meth:`mechanism_basis`; ``q`` 0, ``dq = v``).

        ``hand``: the grasp frame's 6 x d Jacobian (:meth:`hand_frame_jacobian`) and task pose
        at this ``q`` when the caller has them already (the VE after an integration).
        """
        q = np.array(q, dtype=float)
        dq = np.array(dq, dtype=float)
        d = self.mass_matrix(q)
        g = np.zeros(self.dof) if self._no_gravity else self.gravity(q)
        b = self.bias(q, dq) - g
        if hand is None:
            j6 = self.hand_frame_jacobian(q)  # also updates the grasp frame placement
            pose = self.hand_pose_in_data()
        else:
            j6, pose = hand
        j = j6[self._rows, :]
        if self.loops is not None:
            return self._reduced(q, dq, d, g, b, j, pose)
        cons = constraint_directions(j, self.task, self.linkage.constraints, self._joint_scale)
        return DynamicsSnapshot(q, dq, d, g, b, j, pose, j @ dq, cons)

    def _reduced(self, q: np.ndarray, dq: np.ndarray, d: np.ndarray, g: np.ndarray,
                 b: np.ndarray, j: np.ndarray, pose: np.ndarray) -> DynamicsSnapshot:
        """The closed chain's snapshot in its ``f`` independent velocities ``v``
        (``dq = N v``, :meth:`mechanism_basis`): ``D_r = N^T D N``, ``G_r = N^T G``,
        ``B_r = N^T B``, ``J_r = J_h N`` (eqs. 17-19 on the mechanism); ``q`` is the local
        coordinate of ``v`` (0 at the snapshot) and ``dq = v``."""
        n = self.mechanism_basis(q, dq)
        v = np.linalg.lstsq(n, dq, rcond=None)[0]
        jr = j @ n
        cons = constraint_directions(jr, self.task, self.linkage.constraints)
        dr = n.T @ d @ n
        return DynamicsSnapshot(np.zeros(v.size), v, 0.5 * (dr + dr.T), n.T @ g, n.T @ b, jr,
                                pose, jr @ v, cons, n)


def inverse_operational_inertia(jacobian: np.ndarray, mass_matrix: np.ndarray) -> np.ndarray:
    """``Lambda^-1 = J D^-1 J^T`` (eq. 6 and eq. 19, with the transpose the text drops).

    Uses a Cholesky solve of D, never an explicit inverse.
    """
    lam = jacobian @ spd_solve(spd_factor(mass_matrix), jacobian.T)
    return 0.5 * (lam + lam.T)
