"""Directions of topological constraint: the left null space of ``J_h`` (Section V, eq. 13).

``J_h`` mixes units: translational rows are in m/s and rotational rows in rad/s per joint rate,
and prismatic columns are per m/s instead of per rad/s. Its singular values therefore change when
the unit of length changes, and with short links (the paper's are 3-4 cm) a relative threshold
``sigma_i < tol * sigma_max`` marks the translational directions as constrained almost
everywhere, because ``sigma_max`` comes from the unit rotation rows. We weight the Jacobian with
a characteristic length ``L_c`` (m)::

    J_w = W J_h S,   W = diag(1 for translation rows, L_c for rotation rows),
                     S = diag(1 for revolute joints, L_c for prismatic joints)

so that every entry of ``J_w`` is a length, and call the i-th direction constrained when
``sigma_i(J_w) < rank_tolerance * L_c``. Scaling every length of the problem (including L_c)
by the same factor scales every ``sigma_i`` by that factor: the decision is independent of the
unit of length. ``S`` is invertible, so it does not change ``N(J_h^T)``; ``W`` maps it
(``N(J_w^T) = W^-1 N(J_h^T)``), so an exactly singular ``J_h`` is detected exactly.

The penalty of eq. 13, ``M_d sum_i (k_tc n_i^T e + b_tc n_i^T e_dot) n_i``, acts along a basis
``n_i`` of ``N(J_h^T)`` (``penalty_direction: nullspace``, the default): the weighting decides
only the rank, i.e. how many directions are constrained. The directions are ``W u_i`` for the
constrained columns ``u_i`` of ``U_w`` (``N(J_w^T) = W^-1 N(J_h^T)``), orthonormalised in the
metric ``M_d^-1`` of the device inertia that multiplies the penalty in eq. 14
(``n_i^T M_d^-1 n_j = delta_ij``), so the penalty wrench ``f = M_d P a`` satisfies
``f . (J_h qd) = 0`` for every joint rate ``qd`` (it does no work on any motion the linkage
allows) and is the same physical wrench in any unit of length: eq. 13's plain ``n_i^T n_i = 1``
adds N and N m, so it would change with the unit. Where ``J_h`` is exactly singular,
``P = I - J_h (J_h^T M_d J_h)^+ J_h^T M_d``; with ``M_d = I`` (SI, the paper's device) it is
eq. 13 exactly. Inside the tolerance band (``J_h`` nearly but not exactly singular) the ``n_i``
span the left null space of the rank-r truncation of ``J_h`` that the weighted SVD chose. The
projector is ``P = M_d^-1 sum_i w_i n_i n_i^T`` (``M_d P`` symmetric, ``0 <= M_d P <= M_d``).

``penalty_direction: weighted`` uses the weighted projector
``P = W^-1 U_w diag(w) U_w^T W``: the penalty in the weighted coordinates ``e_w = W e``
mapped back. Its force lies along ``W^-1 m`` instead of ``W m`` (m in ``N(J_w^T)``): tilted off
``N(J_h^T)`` by up to ~48 deg with Table I's L_c = 0.114 m, so it does work on allowed motion.
With ``L_c = 1`` both settings are the paper's formula.

Switching: with ``blend = 0`` a direction is either fully penalised (w = 1) or free (w = 0), as
in the paper, so the penalty switches on abruptly when the linkage enters the tolerance band.
With ``blend > 0`` the weight falls smoothly (C1 smoothstep) from 1 at ``tol*L_c`` to 0 at
``tol*(1+blend)*L_c``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from haptic_topology.model.linkage import ConstraintSettings, JointType, Linkage, PenaltyDirection
from haptic_topology.vocabulary import TaskSpace


@dataclass(frozen=True)
class ConstraintDirections:
    """SVD of the weighted hand Jacobian and the penalty weight of each left singular vector.

    Attributes:
        singular_values: ``sigma_i(J_w)`` in m, descending, ``min(m, d)`` entries (eq. 18).
        left_vectors: ``U_w`` (m x m), columns are directions in the weighted task space.
        weights: penalty weight in [0, 1] of each column of ``U_w``.
        count: t = m - rank(J_h), the number of directions of topological constraint.
        task_scale: diagonal of ``W`` (m entries).
        direction: the directions the penalty of eq. 13 acts along (see module docstring).
    """

    singular_values: np.ndarray
    left_vectors: np.ndarray
    weights: np.ndarray
    count: int
    task_scale: np.ndarray
    direction: PenaltyDirection = PenaltyDirection.NULLSPACE

    def projector(self, inertia: np.ndarray | None = None) -> np.ndarray:
        """Penalty projector ``P`` of eq. 13 (m x m, task coordinates), for the device inertia
        ``M_d`` (m x m, kg / kg m^2; default ``I``) that multiplies it in eq. 14.

        ``nullspace``: ``P = M_d^-1 sum_i w_i n_i n_i^T`` with ``n_i`` a basis of
        ``N(J_h^T)`` orthonormal in the metric ``M_d^-1`` of wrenches, the most constrained
        direction first, so that the penalty wrench ``M_d P a`` lies in ``N(J_h^T)`` and is
        the same physical wrench whatever the unit of length (see the module docstring).
        With ``M_d = I`` this is the paper's ``sum_i w_i n_i n_i^T``, bit for bit.
        ``weighted``: ``W^-1 U diag(w) U^T W`` (``inertia`` not used).
        """
        u = self.left_vectors
        if self.direction is PenaltyDirection.WEIGHTED:
            pw = (u * self.weights) @ u.T
            return (pw * self.task_scale[None, :]) / self.task_scale[:, None]
        # M_d = R R^T: with C the columns W u_i (a basis of N(J_h^T); those of U_w are in
        # descending singular value, the most constrained is last), Q = qr(R^-1 C) is
        # orthonormal, n = R Q has n^T M_d^-1 n = I, and P = M_d^-1 n diag(w) n^T =
        # R^-T Q diag(w) Q^T R^T. A diagonal M_d (the usual case; I without one) is one
        # compiled call: numpy's QR alone costs ~15 us a call on these 3 x 3 to 6 x 6.
        m = u.shape[0]
        if inertia is None or not np.any(inertia - np.diag(np.diag(inertia))):
            r = np.ones(m) if inertia is None else np.sqrt(np.diag(inertia))
            return _projector()(_own(u), _own(self.weights), _own(self.task_scale), r)
        order = [i for i in range(m - 1, -1, -1) if self.weights[i] > 0.0]
        if not order:
            return np.zeros((m, m))
        c = self.task_scale[:, None] * u[:, order]
        w = self.weights[order]
        r_low = np.linalg.cholesky(inertia)
        basis, _ = np.linalg.qr(np.linalg.solve(r_low, c))
        return np.linalg.solve(r_low.T, (basis * w) @ basis.T) @ r_low.T


_nullspace_projector: Callable[..., np.ndarray] | None = None


def _projector() -> Callable[..., np.ndarray]:
    """The compiled projector (:func:`~haptic_topology.dynamics.compiled.nullspace_projector`),
    loaded with its first use (importing numba's cache costs a process that never renders a
    constraint, e.g. a bag reader, about half a second)."""
    global _nullspace_projector
    if _nullspace_projector is None:
        from haptic_topology.dynamics.compiled import nullspace_projector
        _nullspace_projector = nullspace_projector
    return _nullspace_projector


def _own(a: np.ndarray) -> np.ndarray:
    """``a`` as compiled code takes it: float64 and writeable (a read-only view, e.g. of a
    message's buffer, is copied)."""
    return a if a.dtype == np.float64 and a.flags.writeable else np.array(a, dtype=float)


def task_scale(task: TaskSpace, characteristic_length: float) -> np.ndarray:
    """Diagonal of ``W``: 1 for translation rows, L_c (m) for rotation rows."""
    w = np.full(task.dim, characteristic_length)
    w[task.translation_rows] = 1.0
    return w


def joint_scale(linkage: Linkage) -> np.ndarray:
    """Diagonal of ``S``: 1 for revolute joints, L_c for prismatic joints."""
    lc = linkage.constraints.characteristic_length
    return np.array([lc if link.joint is JointType.PRISMATIC else 1.0
                     for link in linkage.links])


def penalty_weight(ratio: np.ndarray, tolerance: float, blend: float) -> np.ndarray:
    """Weight in [0, 1] of a direction whose singular value is ``ratio * L_c``.

    1 below ``tolerance``; 0 above ``tolerance * (1 + blend)``; a C1 smoothstep between.
    """
    if blend <= 0.0:
        return (ratio < tolerance).astype(float)
    s = np.clip((ratio - tolerance) / (tolerance * blend), 0.0, 1.0)
    return 1.0 - s * s * (3.0 - 2.0 * s)


def constraint_directions(jacobian: np.ndarray, task: TaskSpace, settings: ConstraintSettings,
                          column_scale: np.ndarray | None = None) -> ConstraintDirections:
    """Directions of topological constraint ``N(J_h^T)`` from the weighted SVD (eq. 13, 18).

    The rank decision uses ``J_w = W J_h S`` (L_c in m); the penalty directions follow
    ``settings.penalty_direction`` (see :meth:`ConstraintDirections.projector`).

    Args:
        jacobian: ``J_h`` (m x d), rows (vx, vy, wz) planar or (v, w) spatial.
        task: planar or spatial.
        settings: characteristic length, rank tolerance, blend.
        column_scale: diagonal of ``S`` (d entries), default all ones (revolute joints).

    Example: Table I grasped at the middle link's COM has a zero third column in eq. 8, so
    ``count == 1`` at every configuration (the paper's Fig. 2).
    """
    m, d = jacobian.shape
    if m != task.dim:
        raise ValueError(f'hand_jacobian must have {task.dim} rows, got {m}')
    lc = settings.characteristic_length
    w = task_scale(task, lc)
    jw = w[:, None] * jacobian
    if column_scale is not None:
        jw = jw * column_scale[None, :]
    # U (m x m) is all that is used: the full V (d x d) is needed only to get a square U
    # when d < m (numpy returns U, s bit for bit the same either way; V costs O(d^2)).
    u, s, _ = np.linalg.svd(jw, full_matrices=d < m)
    ratio = np.zeros(m)
    ratio[: s.size] = s / lc
    weights = penalty_weight(ratio, settings.rank_tolerance, settings.blend)
    # Rows beyond min(m, d) have no singular value: structurally constrained.
    weights[s.size:] = 1.0
    count = int(np.count_nonzero(ratio < settings.rank_tolerance))
    return ConstraintDirections(s, u, weights, count, w, settings.penalty_direction)
