"""Kinematics and dynamics of loop closures (:mod:`haptic_topology.model.loops`).

A closed-chain linkage is its serial chain (eq. 1 with ``d`` joints) plus closures
``phi(q) = 0`` (``c`` rows) with Jacobian ``J_c = d phi / dq`` (c x d). Its velocities lie in
``N(J_c)``; ``f = d - rank(J_c)`` is the mechanism's mobility at ``q``.

Rank decision: as for ``J_h`` (:mod:`~haptic_topology.dynamics.constraints`), ``J_c`` is
weighted so that every entry is a length, ``J_w = W_c J_c S`` (``W_c``: 1 for the rows of
point equations, ``L_c`` for the rows of axis equations; ``S``: ``L_c`` for prismatic
columns), and a singular value of ``J_w`` counts when it is at least ``tolerance * L_c``; the
decision does not depend on the unit of length. Redundant equations (a planar loop closed
with a 3-D ``spherical`` point, whose z row is zero) are dropped by the same decision.

Singular configurations of the closures (a four-bar's change point, where its links lie on
one line) have a larger mobility than the configurations around them, and a run could pass
exactly through one. A run keeps the rank of its start (:meth:`LoopClosures.keep_rank`; a
start cannot be singular, see :func:`check_assembled`), so the mechanism's mobility and the
size of the LMI's updates never change. Where fewer singular values than that rank count, the
directions that stay free are chosen, among those whose singular value does not count, as
the ones the velocity points along (the branch the chain came in on); the closures give no
acceleration condition along the others (their ``row_map`` rows are 0: ``Jdot_c qd`` has no
component there to divide by a zero singular value), and the Gauss-Newton steps of the
projection use only the counted singular values.

Dynamics (eq. 1 with constraint forces): ``D qdd + B + G = tau + J_c^T lambda`` with
``J_c qdd = -Jdot_c qd``, solved with the ``r`` independent rows the rank decision keeps
(Gauss's principle: ``qdd`` is the unconstrained acceleration corrected in the metric ``D``).
Drift: after each integration step :meth:`LoopClosures.project` moves ``q`` back onto
``phi = 0`` (Gauss-Newton, minimum-norm steps in the weighted coordinates) and removes the
velocity component that violates ``J_c qd = 0`` in the metric ``D`` (the smallest change of
kinetic energy that satisfies the closures).

Units SI; rows of ``phi`` in m (points) and rad (axes, to first order); frames world-aligned.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pinocchio as pin

from haptic_topology.dynamics.constraints import joint_scale
from haptic_topology.dynamics.rk4 import rk4_step
from haptic_topology.dynamics.spd import spd_factor, spd_solve
from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.model.build import LinkageModel, build_model
from haptic_topology.model.linkage import Linkage
from haptic_topology.model.loops import LoopKind

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
#: Default rank tolerance of ``J_c``, a fraction of ``L_c``: only exact (to rounding)
#: rank drops change the mobility.
LOOP_RANK_TOLERANCE = 1e-8


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of the 3-vector ``a`` with the 3-vector ``b`` or with each row of
    ``b`` (k x 3), the same bits (each entry the difference of two rounded products) without
    ``np.cross``'s cost per call (~15 us: it runs at every RK4 stage of a closed chain)."""
    a0, a1, a2 = a.tolist()
    if b.ndim == 1:
        b0, b1, b2 = b.tolist()
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    return np.array([[a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0]
                     for b0, b1, b2 in b.tolist()]).reshape(b.shape)


def _perpendiculars(axis: np.ndarray) -> np.ndarray:
    """Two unit vectors (2 x 3) perpendicular to the unit ``axis`` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    p1 = np.cross(axis, helper)
    p1 /= np.linalg.norm(p1)
    return np.array([p1, np.cross(axis, p1)])


@dataclass(frozen=True)
class ClosureBasis:
    """The rank decision on ``J_c`` at one ``q``: ``rows`` (r x d) are ``r`` independent
    combinations of the closure rows (``A = Sigma_r^-1 U_r^T W_c J_c``, so ``A = V_r^T
    S^-1``), :attr:`null` (d x f) an orthonormal basis of ``N(J_c)``, ``singular_values`` of
    ``J_w`` (m, descending) and ``mobility`` f = d - r."""

    rows: np.ndarray
    singular_values: np.ndarray
    row_map: np.ndarray
    #: ``N_w`` (d x f): an orthonormal basis of ``N(J_c S)`` (:attr:`null` is ``S N_w``
    #: orthonormalised).
    scaled_null: np.ndarray
    #: ``S`` (d): the column scale of ``J_w``.
    column_scale: np.ndarray

    @cached_property
    def null(self) -> np.ndarray:
        """An orthonormal basis (d x f) of ``N(J_c)``: ``S N_w`` orthonormalised (QR), made
        when first asked for (the RK4 stages of a closed chain use only ``rows`` and
        ``row_map``)."""
        return np.linalg.qr(self.column_scale[:, None] * self.scaled_null)[0]

    @property
    def mobility(self) -> int:
        return int(self.scaled_null.shape[1])


class LoopClosures:
    """``phi(q)``, ``J_c(q)``, ``Jdot_c qd`` of a linkage's closures, the mechanism's
    velocity space, assembly, projection and the constrained acceleration.

    ``tolerance``: the rank decision on ``J_c`` (a fraction of ``L_c``).
    """

    def __init__(self, linkage: Linkage | LinkageModel,
                 tolerance: float = LOOP_RANK_TOLERANCE) -> None:
        lm = linkage if isinstance(linkage, LinkageModel) else build_model(linkage)
        self.linkage: Linkage = lm.linkage
        if not self.linkage.loops:
            raise LinkageError(f'{self.linkage.source}: linkage.loops: none (a serial '
                               'linkage has no closures)')
        self.model = lm.model
        self.data = lm.model.createData()
        self.dof = lm.model.nv
        self.tolerance = tolerance
        lc = self.linkage.constraints.characteristic_length
        self.length = lc
        #: Per closure, the frames at its two points (``model`` frame ids: link side, ``to``
        #: side); ``data.oMf`` holds their placements after a kinematics pass.
        self.ends: tuple[tuple[int, int], ...] = lm.loop_frames
        self._rows: list[list[int]] = []          # point rows of each closure
        self._axes: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
        weights: list[float] = []
        for loop in self.linkage.loops:
            rows = [0, 1] if loop.kind is LoopKind.PIN else [0, 1, 2]
            self._rows.append(rows)
            weights += [1.0] * len(rows)
            if loop.kind is LoopKind.REVOLUTE:
                assert loop.axis is not None and loop.to_axis is not None
                self._axes.append((loop.axis, loop.to_axis, _perpendiculars(loop.axis)))
                weights += [lc, lc]
            else:
                self._axes.append(None)
        #: ``W_c``: 1 for point rows, ``L_c`` for axis rows (c entries).
        self.row_scale = np.array(weights)
        #: ``S``: ``L_c`` for prismatic columns, 1 for revolute (d entries).
        self.column_scale = joint_scale(self.linkage)
        self.equations = int(self.row_scale.size)
        #: The rank of ``J_c`` kept through a run (:meth:`keep_rank`); None: decided at each
        #: ``q``.
        self.rank: int | None = None

    # -- kinematics -----------------------------------------------------------------------
    def residual(self, q: np.ndarray) -> np.ndarray:
        """``phi(q)`` (c): point a minus point b (m), and for revolute closures
        ``p_i . (b x a)`` with ``a``, ``b`` the world axes and ``p_i`` perpendicular to ``a``
        (rad to first order)."""
        model, data = self.model, self.data
        pin.framesForwardKinematics(model, data, q)
        out = []
        for (fa, fb), rows, axes in zip(self.ends, self._rows, self._axes, strict=True):
            oa, ob = data.oMf[fa], data.oMf[fb]
            out.extend((oa.translation - ob.translation)[rows])
            if axes is not None:
                a, b = oa.rotation @ axes[0], ob.rotation @ axes[1]
                out.extend((oa.rotation @ axes[2].T).T @ _cross(b, a))
        return np.array(out)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """``J_c(q)`` (c x d): ``J_c qd`` is the rate of ``phi`` on the closed chain (the point
        rows exactly, the axis rows where the axes are parallel)."""
        model, data = self.model, self.data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        out = []
        for (fa, fb), rows, axes in zip(self.ends, self._rows, self._axes, strict=True):
            rel = (pin.getFrameJacobian(model, data, fa, _LWA)
                   - pin.getFrameJacobian(model, data, fb, _LWA)).reshape(6, self.dof)
            out.append(rel[rows])
            if axes is not None:
                out.append((data.oMf[fa].rotation @ axes[2].T).T @ rel[3:])
        return np.vstack(out)

    def drift(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """``Jdot_c qd`` (c): the closure rows' acceleration at ``qdd = 0`` (classical
        accelerations of the points; for axis rows ``(w_a x p_i) . w_rel + p_i . alpha_rel``)."""
        model, data = self.model, self.data
        pin.forwardKinematics(model, data, q, dq, np.zeros(self.dof))
        pin.updateFramePlacements(model, data)
        out = []
        for (fa, fb), rows, axes in zip(self.ends, self._rows, self._axes, strict=True):
            acc = (pin.getFrameClassicalAcceleration(model, data, fa, _LWA).vector
                   - pin.getFrameClassicalAcceleration(model, data, fb, _LWA).vector)
            out.extend(acc[:3][rows])
            if axes is not None:
                w_a = pin.getFrameVelocity(model, data, fa, _LWA).angular
                w_rel = w_a - pin.getFrameVelocity(model, data, fb, _LWA).angular
                perp = (data.oMf[fa].rotation @ axes[2].T).T
                out.extend(_cross(w_a, perp) @ w_rel + perp @ acc[3:])
        return np.array(out)

    def basis(self, q: np.ndarray, jacobian: np.ndarray | None = None,
              rank: int | None = None, velocity: np.ndarray | None = None) -> ClosureBasis:
        """The rank decision on the weighted ``J_c`` at ``q`` (module docstring); ``rank``:
        keep that many directions instead (a configuration slightly off the closures, e.g. a
        Runge-Kutta stage, where the redundant equations of an overconstrained loop are no
        longer exactly dependent; default: :attr:`rank`, else decided here). Where fewer
        singular values count than are kept, the free directions are chosen along
        ``velocity`` (joint rates at ``q``; module docstring)."""
        j = self.jacobian(q) if jacobian is None else jacobian
        jw = self.row_scale[:, None] * j * self.column_scale[None, :]
        u, s, vt = np.linalg.svd(jw, full_matrices=True)
        counted = int(np.count_nonzero(s >= self.tolerance * self.length))
        r = rank if rank is not None else self.rank if self.rank is not None else counted
        if r > counted:
            vt = np.vstack([vt[:counted], self._free_last(vt[counted:], velocity)])
        rows = vt[:r] / self.column_scale[None, :]                   # V_r^T S^-1
        k = min(r, counted)
        row_map = (u[:, :k] / s[:k]).T * self.row_scale[None, :]       # Sigma^-1 U^T W_c
        if k < r:       # no acceleration condition along the rows that do not count
            row_map = np.vstack([row_map, np.zeros((r - k, j.shape[0]))])
        return ClosureBasis(rows, s, row_map, vt[r:].T, self.column_scale)

    def _free_last(self, near: np.ndarray, velocity: np.ndarray | None) -> np.ndarray:
        """Another orthonormal basis (rows) of the span of the rows ``near`` (weighted joint
        space: the directions whose singular value does not count), whose last row is the
        direction of ``velocity``'s component in it: :meth:`basis` keeps the last rows free
        (without a velocity along them, ``near`` as it is)."""
        if velocity is None:
            return near
        w = near @ (np.asarray(velocity, dtype=float) / self.column_scale)
        norm = float(np.linalg.norm(w))
        if norm <= 1e-12 * max(1.0, float(np.linalg.norm(velocity))):
            return near                 # at rest along them: the SVD's order
        # An orthonormal basis of the rows' span whose last vector is the velocity's direction.
        basis, _ = np.linalg.qr(np.column_stack([w / norm, np.eye(w.size)]))
        coeff = np.roll(basis[:, :w.size], -1, axis=1)
        return (near.T @ coeff).T

    def keep_rank(self, q: np.ndarray) -> int:
        """Keep the rank of ``J_c`` at ``q`` (a run's start, not a singular configuration:
        :func:`check_assembled`) for every later :meth:`basis`; returns it."""
        self.rank = None
        self.rank = int(self.basis(q).rows.shape[0])
        return self.rank

    def mobility(self, q: np.ndarray) -> int:
        """f = d - rank(J_c) at ``q``."""
        return self.basis(q).mobility

    # -- assembly and projection ----------------------------------------------------------
    def assemble(self, q0: np.ndarray, fixed: tuple[int, ...] = (),
                 iterations: int = 50, tol: float = 1e-13,
                 rank: int | None = None) -> tuple[np.ndarray, float]:
        """The assembled configuration nearest ``q0`` (Gauss-Newton from ``q0``, minimum-norm
        steps in the weighted coordinates, the joints ``fixed`` held; ``rank``: the steps
        use that many singular directions, see :meth:`basis`), and the weighted residual
        norm (m) it reached."""
        q = np.array(q0, dtype=float)
        free = [i for i in range(self.dof) if i not in fixed]
        err = np.inf
        for _ in range(iterations):
            phi = self.row_scale * self.residual(q)
            err = float(np.linalg.norm(phi))
            if err <= tol * max(self.length, 1.0):
                break
            jw = (self.row_scale[:, None] * self.jacobian(q)[:, free]
                  * self.column_scale[None, free])
            if rank is None:
                step = np.linalg.lstsq(jw, phi, rcond=self.tolerance)[0]
            else:       # at most the singular values that count (module docstring)
                u, sv, vt = np.linalg.svd(jw, full_matrices=False)
                k = min(rank, int(np.count_nonzero(sv >= self.tolerance * self.length)))
                step = vt[:k].T @ ((u[:, :k].T @ phi) / sv[:k])
            q[free] -= self.column_scale[free] * step
        return q, err

    def project(self, q: np.ndarray, dq: np.ndarray,
                mass_matrix: Callable[[np.ndarray], np.ndarray], rank: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """``q`` moved back onto ``phi = 0`` (:meth:`assemble`) and ``dq`` with the component
        that violates ``J_c dq = 0`` removed in the metric ``D = mass_matrix(q)`` at the
        projected ``q``."""
        q, _ = self.assemble(q, iterations=10, rank=rank)
        a = self.basis(q, rank=rank, velocity=dq).rows
        factor = spd_factor(mass_matrix(q))
        dinv_at = spd_solve(factor, a.T)
        lam = np.linalg.solve(a @ dinv_at, a @ dq)
        return q, dq - dinv_at @ lam

    def acceleration(self, q: np.ndarray, dq: np.ndarray, mass_matrix: np.ndarray,
                     free_torque: np.ndarray, rank: int | None = None,
                     basis: ClosureBasis | None = None) -> np.ndarray:
        """``qdd`` of eq. 1 with the closures' forces: ``D qdd = free_torque + J_c^T
        lambda`` (``free_torque = tau - B - G``), ``J_c qdd = -Jdot_c qd``; ``basis``: the
        rank decision at ``q`` when the caller has it."""
        basis = self.basis(q, rank=rank, velocity=dq) if basis is None else basis
        a = basis.rows
        rhs = -(basis.row_map @ self.drift(q, dq))
        factor = spd_factor(mass_matrix)
        free = spd_solve(factor, free_torque)
        dinv_at = spd_solve(factor, a.T)
        lam = np.linalg.solve(a @ dinv_at, rhs - a @ free)
        return free + dinv_at @ lam

    def step(self, q: np.ndarray, dq: np.ndarray, h: float,
             stage: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, float]],
             mass_matrix: Callable[[np.ndarray], np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray, float]:
        """One classical RK4 step of ``h`` s of the closed chain, then :meth:`project`;
        ``stage(q, dq)`` gives ``(D, tau - B - G, P)`` at a stage, ``P`` a power (W) whose
        integral over the step is returned (e.g. the contacts' work on the chain, J);
        ``mass_matrix(q)``: the ``D`` that ``stage`` gives, alone, for the projection
        (default: ``stage``'s, computing its torques for nothing). The
        rank of ``J_c`` is decided once, at ``q`` (on the closures), and kept for the stages
        and the projection: off the closures the redundant equations of an overconstrained
        loop (a Bennett linkage) become independent and would lock it."""
        first = self.basis(q, velocity=dq)
        rank = first.rows.shape[0]

        def deriv(qs: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, float]:
            d, free, power = stage(qs, vs)
            return self.acceleration(qs, vs, d, free, rank, first if qs is q else None), power

        q_new, dq_new, work = rk4_step(deriv, q, dq, h)
        q_new, dq_new = self.project(q_new, dq_new, mass_matrix if mass_matrix is not None
                                     else lambda qp: stage(qp, dq_new)[0], rank)
        return q_new, dq_new, work


#: How far apart (weighted, m) a closure's points may be at a scenario's ``q0``.
ASSEMBLY_TOLERANCE = 1e-9
#: Step (rad, or L_c-scaled m) along each free direction at which a start is probed for
#: being a singular configuration of the closures.
SINGULAR_PROBE = 1e-3


def check_assembled(linkage: Linkage, q0: np.ndarray, dq0: np.ndarray, where: str) -> None:
    """Refuse (:class:`~haptic_topology.errors.ConfigError`, naming ``where``'s field) a
    start ``(q0, dq0)`` of a closed chain whose closures are open beyond
    :data:`ASSEMBLY_TOLERANCE` (offering the nearest assembled ``q0``), whose mobility is 0,
    that is a singular configuration of the closures (a change point: more mobility than
    around it), or whose ``dq0`` violates ``J_c dq0 = 0``."""
    cl = LoopClosures(linkage)
    gap = float(np.linalg.norm(cl.row_scale * cl.residual(q0)))
    if gap > ASSEMBLY_TOLERANCE:
        q, err = cl.assemble(q0)
        offer = (f'the nearest assembled q0 is [{", ".join(f"{v:.12g}" for v in q)}]'
                 if err <= ASSEMBLY_TOLERANCE else 'no assembled configuration was found '
                 'near it')
        raise ConfigError(f'{where}.q0: the loop closures of linkage {linkage.name} are open '
                          f'by {gap:.3g} m at q0 (expected <= {ASSEMBLY_TOLERANCE:g} m); '
                          f'{offer}')
    basis = cl.basis(q0)
    if basis.mobility == 0:
        raise ConfigError(f'{where}.q0: linkage {linkage.name} cannot move at q0: mobility 0 '
                          f'({cl.dof} joints, {cl.dof} independent closure equations)')
    # A singular configuration of the closures themselves (a four-bar's change point, where
    # its links are collinear) has a larger mobility than the configurations around it:
    # the LMI's updates would change size as the linkage leaves it.
    around = min(cl.mobility(cl.assemble(q0 + SINGULAR_PROBE * v)[0]) for v in basis.null.T)
    if around < basis.mobility:
        raise ConfigError(f'{where}.q0: a singular configuration of the loop closures of '
                          f'linkage {linkage.name} (mobility {basis.mobility} there, {around} '
                          "around it, e.g. a four-bar's change point): start away from it")
    rate = float(np.linalg.norm(basis.rows @ dq0)) * cl.length
    if rate > ASSEMBLY_TOLERANCE * max(1.0, float(np.linalg.norm(dq0))):
        raise ConfigError(f'{where}.dq0: violates the loop closures of linkage '
                          f'{linkage.name} (J_c dq0 = {rate:.3g} m/s, expected 0)')
