"""The controller's per-cycle arithmetic in compiled code: the LMI step and eqs. 10-16.

:class:`~haptic_topology.control.controller.HapticController` calls these once per device
state (and :class:`~haptic_topology.control.lmi.LocalModel` once per input it integrates);
the offline simulation, the lock-step graph and the real-time loop therefore compute the
same numbers. They are the compiled form of the pure functions of
:mod:`haptic_topology.control.laws` and of ``LocalModel``'s step, which stay the reference:
``test/unit/control/test_compiled_laws.py`` checks that both agree to 1e-12 (the compiled loops
sum in another order than numpy's BLAS calls, so they agree to rounding, not bit for bit).

Why compiled: in Python the controller's cycle is about 40 numpy calls on 3- and 6-vectors
(about 1 us each on a 2-core machine) and the 1 kHz loop's budget is the millisecond. Each
function here is one call from Python, and works in place on arrays the caller owns.

Vectors are task vectors at the hand (m = 3 planar, 6 spatial, 2 or 3 for a point grasp;
layouts in :mod:`haptic_topology.dynamics.taskspace`), matrices m x m unless stated; units as
in :mod:`haptic_topology.control.laws`. ``law`` and ``force_step`` tell a rigid grasp's task
by the vectors' size; ``task_law`` and ``task_force_step`` take the task's rotation rows.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit, void

from haptic_topology.dynamics.compiled import MAT, VEC, integrate_pose, task_pose_difference

#: ``law`` modes, as ``ControlMode`` values (eq. 14, eq. 10, zero).
PENALTY = 0
ACCELERATION_ONLY = 1
ZERO = 2


@njit(void(MAT, VEC, VEC), cache=True)
def _matvec(a: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """``out = a x`` in plain loops."""
    for i in range(a.shape[0]):
        s = 0.0
        for k in range(a.shape[1]):
            s += a[i, k] * x[k]
        out[i] = s


@njit(void(MAT, VEC, VEC, MAT, VEC, VEC, VEC, VEC, VEC, float64), cache=True)
def lmi_step(accel_map: np.ndarray, accel_bias: np.ndarray, contact_accel: np.ndarray,
             jacobian: np.ndarray, q: np.ndarray, dq: np.ndarray, x_vt: np.ndarray,
             xd_vt: np.ndarray, wrench: np.ndarray, dt: float) -> None:
    """One semi-implicit Euler step of eq. 17 (eq. 20: ``accel_bias`` zero) with the frozen
    matrices, in place on the LMI's state ``q``, ``dq`` (d, rad and rad/s or m and m/s) and
    its VT hand ``x_vt``, ``xd_vt`` (m)::

        qdd = D^-1 J_h^T F_vt - D^-1 G + D^-1 sum_i J_i^T F_i
        dq += qdd dt;  q += dq dt;  xd_vt = J_h dq;  x_vt moved by xd_vt for dt

    ``accel_map`` ``D^-1 J_h^T`` (d x m), ``accel_bias`` ``D^-1 G`` (d), ``contact_accel``
    the contacts' ``D^-1 sum_i J_i^T F_i`` (d, or empty: none), ``jacobian`` ``J_h``
    (m x d), ``wrench`` ``F_vt`` (m, N and N m), ``dt`` (s)."""
    d = q.size
    qdd = np.empty(d)
    _matvec(accel_map, wrench, qdd)
    for i in range(d):
        qdd[i] = qdd[i] - accel_bias[i]
    if contact_accel.size:
        for i in range(d):
            qdd[i] = qdd[i] + contact_accel[i]
    for i in range(d):
        dq[i] = dq[i] + qdd[i] * dt
    for i in range(d):
        q[i] = q[i] + dq[i] * dt
    _matvec(jacobian, dq, xd_vt)
    integrate_pose(x_vt, xd_vt, dt)


@njit(int64(MAT, VEC, MAT, VEC, VEC, VEC, VEC, int64[:], MAT, VEC, int64, int64, int64),
      cache=True)
def lmi_replay(accel_map: np.ndarray, accel_bias: np.ndarray, jacobian: np.ndarray,
               q: np.ndarray, dq: np.ndarray, x_vt: np.ndarray, xd_vt: np.ndarray,
               seqs: np.ndarray, wrenches: np.ndarray, dts: np.ndarray, count: int,
               consumed: int, bound: int) -> int:
    """:func:`lmi_step` for each recorded input not consumed yet, oldest first (no
    contacts); returns the seq of the last one consumed (``consumed`` if none).

    The inputs are a ring of the newest ``seqs.size`` in seq order (row ``k % size`` of
    ``seqs``, ``wrenches`` (size x m, F_vt) and ``dts`` (s; NaN: no duration yet, skipped)),
    ``count`` recorded in all. The replay stops before the first input whose seq is
    ``bound`` or more (``bound`` < 0: no bound)."""
    size = seqs.size
    first = count
    while first > max(count - size, 0) and seqs[(first - 1) % size] > consumed:
        first -= 1
    none = np.empty(0)
    for k in range(first, count):
        i = k % size
        if math.isnan(dts[i]):
            continue
        if bound >= 0 and seqs[i] >= bound:
            break
        lmi_step(accel_map, accel_bias, none, jacobian, q, dq, x_vt, xd_vt, wrenches[i],
                 dts[i])
        consumed = seqs[i]
    return consumed


@njit(void(int64, int64, boolean, MAT, MAT, MAT, MAT, VEC, VEC, float64, float64,
           VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC), cache=True)
def task_law(rotation_dim: int, mode: int, vt_coupling: bool, ml: np.ndarray, m_d: np.ndarray,
             c_d: np.ndarray, projector: np.ndarray, k_pc: np.ndarray, b_pc: np.ndarray,
             k_tc: float, b_tc: float, x_vt: np.ndarray, xd_vt: np.ndarray, x_h: np.ndarray,
             xd_h: np.ndarray, f_h: np.ndarray, f_env: np.ndarray, u: np.ndarray,
             f_pc: np.ndarray, f_vt: np.ndarray) -> None:
    """The device wrench ``u`` of ``mode`` (eq. 14, eq. 10, or zero), the coordination
    wrench ``f_pc`` and the VT's wrench ``f_vt``, written into the three m-vectors, for a
    task with ``rotation_dim`` rotation rows (``TaskSpace.rotation_dim``: 0 for a point
    grasp, whose pose error is a difference of points)::

        e = x_vt (-) x_h;  edot = xd_vt - xd_h
        F_pc = K_pc e + B_pc edot                                         (eqs. 15-16)
        u = M_d L (F_h + F_env + F_pc) - F_h + C_d xd_h                   (eq. 10)
        u += M_d P (k_tc e + b_tc edot)                      (eq. 14 only, eq. 13)
        F_vt = F_h - F_pc with VT coupling, else F_h

    ``ml``: ``M_d Lambda_h^-1`` (eq. 19); ``projector`` P: ``sum_i w_i n_i n_i^T`` of the
    directions of topological constraint (eq. 13); ``k_pc``, ``b_pc`` the diagonals (m);
    ``k_tc``, ``b_tc`` the penalty gains; ``f_env`` ``F_env`` (m; zeros without contacts).
    ``b_d = k_d = 0`` (eq. 4 as in the paper)."""
    m = x_h.size
    e = np.empty(m)
    task_pose_difference(x_vt, x_h, rotation_dim, e)
    edot = np.empty(m)
    for i in range(m):
        edot[i] = xd_vt[i] - xd_h[i]
    for i in range(m):
        f_pc[i] = k_pc[i] * e[i] + b_pc[i] * edot[i]
    for i in range(m):
        f_vt[i] = f_h[i] - f_pc[i] if vt_coupling else f_h[i]
    if mode == ZERO:
        for i in range(m):
            u[i] = 0.0
        return
    s = np.empty(m)
    for i in range(m):
        s[i] = f_h[i] + f_env[i] + f_pc[i]
    a = np.empty(m)
    c = np.empty(m)
    _matvec(ml, s, a)
    _matvec(c_d, xd_h, c)
    for i in range(m):
        u[i] = a[i] - f_h[i] + c[i]
    if mode == PENALTY:
        acc = np.empty(m)
        for i in range(m):
            s[i] = k_tc * e[i] + b_tc * edot[i]
        _matvec(projector, s, acc)
        _matvec(m_d, acc, a)
        for i in range(m):
            u[i] = u[i] + a[i]


@njit(void(int64, boolean, MAT, MAT, MAT, MAT, VEC, VEC, float64, float64,
           VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC), cache=True)
def law(mode: int, vt_coupling: bool, ml: np.ndarray, m_d: np.ndarray, c_d: np.ndarray,
        projector: np.ndarray, k_pc: np.ndarray, b_pc: np.ndarray, k_tc: float, b_tc: float,
        x_vt: np.ndarray, xd_vt: np.ndarray, x_h: np.ndarray, xd_h: np.ndarray,
        f_h: np.ndarray, f_env: np.ndarray, u: np.ndarray, f_pc: np.ndarray,
        f_vt: np.ndarray) -> None:
    """:func:`task_law` of a rigid grasp, told by the size (3 planar, 6 spatial)."""
    task_law(1 if x_h.size == 3 else 3, mode, vt_coupling, ml, m_d, c_d, projector, k_pc,
             b_pc, k_tc, b_tc, x_vt, xd_vt, x_h, xd_h, f_h, f_env, u, f_pc, f_vt)


@njit(float64(int64, MAT, MAT, VEC, VEC, float64, float64, VEC, VEC, VEC, VEC), cache=True)
def task_force_step(rotation_dim: int, m_d: np.ndarray, projector: np.ndarray,
                    k_pc: np.ndarray, b_pc: np.ndarray, k_tc: float, b_tc: float,
                    pose: np.ndarray, twist: np.ndarray, vt_pose: np.ndarray,
                    vt_twist: np.ndarray) -> float:
    """The largest component (N or N m) of the step in force that moving the VT hand from
    ``vt_pose``, ``vt_twist`` to ``pose``, ``twist`` gives eq. 14, bounded term by term::

        |K_pc| dx + |B_pc| dv + |M_d P (k_tc dx + b_tc dv)|,  dx = |pose (-) vt_pose|,
        dv = |twist - vt_twist|

    (the coordination wrench of eqs. 15-16 and the penalty of eq. 13; ``projector`` P)."""
    m = pose.size
    dx = np.empty(m)
    task_pose_difference(pose, vt_pose, rotation_dim, dx)
    dv = np.empty(m)
    s = np.empty(m)
    for i in range(m):
        dx[i] = abs(dx[i])
        dv[i] = abs(twist[i] - vt_twist[i])
        s[i] = k_tc * dx[i] + b_tc * dv[i]
    p = np.empty(m)
    pen = np.empty(m)
    _matvec(projector, s, p)
    _matvec(m_d, p, pen)
    top = -np.inf
    for i in range(m):
        top = max(top, k_pc[i] * dx[i] + b_pc[i] * dv[i] + abs(pen[i]))
    return top


@njit(float64(MAT, MAT, VEC, VEC, float64, float64, VEC, VEC, VEC, VEC), cache=True)
def force_step(m_d: np.ndarray, projector: np.ndarray, k_pc: np.ndarray, b_pc: np.ndarray,
               k_tc: float, b_tc: float, pose: np.ndarray, twist: np.ndarray,
               vt_pose: np.ndarray, vt_twist: np.ndarray) -> float:
    """:func:`task_force_step` of a rigid grasp, told by the size (3 planar, 6 spatial)."""
    return task_force_step(1 if pose.size == 3 else 3, m_d, projector, k_pc, b_pc, k_tc, b_tc,
                           pose, twist, vt_pose, vt_twist)
