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
from haptic_topology.dynamics.spd import spd_factor, spd_solve
from haptic_topology.dynamics.taskspace import pose_from_placement
from haptic_topology.model.linkage import Linkage, LinkageModel, TaskSpace, build_model

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
        self._rows = [0, 1, 5] if self.task is TaskSpace.PLANAR else list(range(6))
        self._joint_scale = joint_scale(self.linkage)

    # -- configuration-space terms (eq. 1) ------------------------------------------------
    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """D(q) (d x d), symmetric positive definite (kg m^2 / kg), by CRBA."""
        m = pin.crba(self.model, self.data, q)
        return np.triu(m) + np.triu(m, 1).T

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

    def hand_jacobian(self, q: np.ndarray) -> np.ndarray:
        """J_h(q) (m x d) of eq. 7: ``xdot_h = J_h qdot`` at the grasp point, world-aligned.

        Planar rows (vx, vy, wz); spatial rows (vx, vy, vz, wx, wy, wz).
        """
        j = pin.computeFrameJacobian(self.model, self.data, q, self.hand_frame, _LWA)
        # Pinocchio hands a 6x1 Jacobian (one joint) back as a flat vector of 6.
        return np.asarray(j, dtype=float).reshape(6, self.dof)[self._rows, :]

    def hand_twist(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Hand twist ``J_h dq`` (m entries)."""
        return self.hand_jacobian(q) @ dq

    def hand_wrench_torques(self, q: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        """``J_h^T F`` (d): joint torques of a wrench at the grasp point (eq. 12)."""
        return self.hand_jacobian(q).T @ wrench

    def inverse_operational_inertia(self, q: np.ndarray) -> np.ndarray:
        """``Lambda_h^-1 = J_h D^-1 J_h^T`` (m x m) of eq. 6; defined at any rank of J_h."""
        return inverse_operational_inertia(self.hand_jacobian(q), self.mass_matrix(q))

    def constraints(self, q: np.ndarray) -> ConstraintDirections:
        """Weighted SVD of J_h and directions of topological constraint (eq. 13, 18)."""
        return constraint_directions(self.hand_jacobian(q), self.task,
                                     self.linkage.constraints, self._joint_scale)

    def acceleration(self, q: np.ndarray, dq: np.ndarray, hand_wrench: np.ndarray) -> np.ndarray:
        """qdd of eq. 2 with the hand wrench as the only external load (no contacts)."""
        return self.forward_dynamics(q, dq, self.hand_wrench_torques(q, hand_wrench))

    def snapshot(self, q: np.ndarray, dq: np.ndarray) -> DynamicsSnapshot:
        """All LMI quantities at (q, dq) in one pass (CRBA, RNEA, frame Jacobian, SVD)."""
        q = np.array(q, dtype=float)
        dq = np.array(dq, dtype=float)
        d = self.mass_matrix(q)
        g = self.gravity(q)
        b = self.bias(q, dq) - g
        j = self.hand_jacobian(q)  # also updates the frame placements
        pose = pose_from_placement(self.data.oMf[self.hand_frame], self.task)
        cons = constraint_directions(j, self.task, self.linkage.constraints, self._joint_scale)
        return DynamicsSnapshot(q, dq, d, g, b, j, pose, j @ dq, cons)


def inverse_operational_inertia(jacobian: np.ndarray, mass_matrix: np.ndarray) -> np.ndarray:
    """``Lambda^-1 = J D^-1 J^T`` (eq. 6 and eq. 19, with the transpose the text drops).

    Uses a Cholesky solve of D, never an explicit inverse.
    """
    lam = jacobian @ spd_solve(spd_factor(mass_matrix), jacobian.T)
    return 0.5 * (lam + lam.T)
