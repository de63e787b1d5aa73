"""The simulated device's and hand's per-cycle arithmetic in compiled code (eq. 9).

:class:`~haptic_topology.device.maglev.MaglevModel` and
:class:`~haptic_topology.device.users.SpringDamperUser` call these once per device cycle, so
the offline simulation and the loop process compute the same numbers; they are the compiled
form of what those classes compute (``test/unit/device/test_compiled_device.py`` checks them
against the same computation written out in numpy, bit for bit where no matrix product is
involved, else to rounding). See :mod:`haptic_topology.dynamics.compiled` for why and how.

Vectors are task vectors (m = 3 planar, 6 spatial; poses m and rad, twists m/s and rad/s,
wrenches N and N m); matrices m x m.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit, void

from haptic_topology.dynamics.compiled import MAT, VEC, integrate_pose, task_pose_difference

#: :func:`maglev_step`'s bit: the command was clamped (``DeviceStatus.SATURATED``).
SATURATED = 1
#: :func:`maglev_step`'s bit: a hard stop held the pose (``DeviceStatus.WORKSPACE_LIMIT``).
STOPPED = 2

#: :func:`spring_damper_wrench`'s straight path at constant velocity.
LINE = 0
#: :func:`spring_damper_wrench`'s circle in the x-y plane.
CIRCLE = 1


@njit(float64(float64), cache=True)
def _sign(x: float) -> float:
    """``np.sign``: -1, 0 or 1 (NaN stays NaN)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return x


@njit(boolean(VEC, VEC, VEC), cache=True)
def clamp(wrench: np.ndarray, limit: np.ndarray, out: np.ndarray) -> bool:
    """``out`` = ``wrench`` clamped per coordinate to ``[-limit, limit]``, non-finite entries
    replaced by 0; returns whether any entry was changed (saturated). Sizes are the caller's
    to check (``maglev.saturate``)."""
    saturated = False
    for i in range(out.size):
        w = wrench[i]
        if not math.isfinite(w):
            w = 0.0
            saturated = True
        elif w > limit[i]:
            w = limit[i]
            saturated = True
        elif w < -limit[i]:
            w = -limit[i]
            saturated = True
        out[i] = w
    return saturated


@njit(void(VEC, VEC), cache=True)
def max_abs_into(u: np.ndarray, peak: np.ndarray) -> None:
    """``peak = max(peak, |u|)`` per coordinate, in place (NaN propagates, as in
    ``np.maximum``): :class:`~haptic_topology.device.loop.DeviceLoop`'s largest applied
    wrench, once per engaged cycle."""
    for i in range(u.size):
        a = abs(u[i])
        if a > peak[i] or math.isnan(a):
            peak[i] = a


@njit(int64(VEC, VEC, float64, VEC, MAT, VEC, MAT, VEC, VEC, VEC, VEC, boolean, boolean,
            boolean, boolean, boolean, VEC, VEC, VEC, VEC), cache=True)
def maglev_step(u: np.ndarray, f_h: np.ndarray, dt: float, limit: np.ndarray,
                mass_inv: np.ndarray, mass_diag: np.ndarray, christoffel: np.ndarray,
                viscous: np.ndarray, coulomb: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                delay: bool, has_christoffel: bool, has_viscous: bool, has_coulomb: bool,
                has_stops: bool, pending: np.ndarray, pose: np.ndarray, twist: np.ndarray,
                applied: np.ndarray) -> int:
    """One semi-implicit Euler step of eq. 9, ``M_d xdd = F_h + u - C_d xd - F_friction``,
    in place on ``pose`` and ``twist``; returns :data:`SATURATED` | :data:`STOPPED` bits.

    ``u`` is clamped per coordinate to ``[-limit, limit]`` (non-finite entries to 0, counted
    as saturated); with ``delay`` the wrench applied is the one clamped in the previous step
    (``pending``, which takes this one). ``applied`` receives the wrench applied. Viscous
    friction ``viscous * xd``; Coulomb friction per axis implicit (stick when the force that
    stops the axis within the step is within ``coulomb``, else slide against the motion);
    then the hard stops ``[lo, hi]`` (inelastic: the pose held at the limit, the velocity
    into it cancelled). ``mass_diag``: the diagonal of ``M_d``; ``has_*``: whether the term
    is non-zero (a zero term is skipped: ``x - 0.0`` is ``x``)."""
    m = pose.size
    clamped = np.empty(m)
    bits = SATURATED if clamp(u, limit, clamped) else 0
    for i in range(m):
        if delay:
            applied[i] = pending[i]
            pending[i] = clamped[i]
        else:
            applied[i] = clamped[i]
    force = np.empty(m)
    for i in range(m):
        force[i] = f_h[i] + applied[i]
    if has_christoffel:
        for i in range(m):
            s = 0.0
            for k in range(m):
                s += christoffel[i, k] * twist[k]
            force[i] = force[i] - s
    if has_viscous:
        for i in range(m):
            force[i] = force[i] - viscous[i] * twist[i]
    new = np.empty(m)
    for i in range(m):
        s = 0.0
        for k in range(m):
            s += mass_inv[i, k] * force[k]
        new[i] = twist[i] + s * dt
    if has_coulomb:
        friction = np.empty(m)
        for i in range(m):
            stop = -mass_diag[i] * new[i] / dt
            friction[i] = stop if abs(stop) <= coulomb[i] else -_sign(new[i]) * coulomb[i]
        for i in range(m):
            s = 0.0
            for k in range(m):
                s += mass_inv[i, k] * friction[k]
            force[i] = new[i] + s * dt
        for i in range(m):
            new[i] = force[i]
    for i in range(m):
        twist[i] = new[i]
    integrate_pose(pose, twist, dt)
    if has_stops:
        hit = False
        for i in range(m):
            if pose[i] < lo[i] or pose[i] > hi[i]:
                hit = True
        if hit:
            for i in range(m):
                below = pose[i] < lo[i]
                above = pose[i] > hi[i]
                pose[i] = min(max(pose[i], lo[i]), hi[i])
                if (below and twist[i] < 0.0) or (above and twist[i] > 0.0):
                    twist[i] = 0.0
            bits |= STOPPED
    return bits


@njit(float64[:](int64, int64, VEC, VEC, float64, float64, VEC, VEC, float64, VEC, VEC),
      cache=True)
def task_spring_damper_wrench(rotation_dim: int, path: int, start: np.ndarray,
                              velocity: np.ndarray, radius: float, period: float, k: np.ndarray,
                              b: np.ndarray, t: float, pose: np.ndarray,
                              twist: np.ndarray) -> np.ndarray:
    """``F_h = K_u (x_target(t) (-) x_h) + B_u (xd_target(t) - xd_h)`` (a new m-vector) for a
    task with ``rotation_dim`` rotation rows (``TaskSpace.rotation_dim``; 0: a point grasp,
    ``F_h`` a force): a hand tracking a target path with stiffness ``k`` and damping ``b``
    (m each). ``path`` :data:`LINE`: ``x(t) = start + velocity t``; :data:`CIRCLE`: centre
    ``start``, ``radius`` (m), ``period`` (s) in the x-y plane, the other coordinates at
    ``start``."""
    m = pose.size
    target = np.empty(m)
    rate = np.empty(m)
    if path == LINE:
        for i in range(m):
            target[i] = start[i] + velocity[i] * t
            rate[i] = velocity[i]
    else:
        w = 2.0 * math.pi / period
        for i in range(m):
            target[i] = start[i]
            rate[i] = 0.0
        target[0] += radius * math.cos(w * t)
        target[1] += radius * math.sin(w * t)
        rate[0] = -radius * w * math.sin(w * t)
        rate[1] = radius * w * math.cos(w * t)
    e = np.empty(m)
    task_pose_difference(target, pose, rotation_dim, e)
    out = np.empty(m)
    for i in range(m):
        out[i] = k[i] * e[i] + b[i] * (rate[i] - twist[i])
    return out


@njit(float64[:](int64, VEC, VEC, float64, float64, VEC, VEC, float64, VEC, VEC), cache=True)
def spring_damper_wrench(path: int, start: np.ndarray, velocity: np.ndarray, radius: float,
                         period: float, k: np.ndarray, b: np.ndarray, t: float,
                         pose: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """:func:`task_spring_damper_wrench` of a rigid grasp, told by the size (3 planar, 6
    spatial)."""
    return task_spring_damper_wrench(1 if pose.size == 3 else 3, path, start, velocity, radius,
                                     period, k, b, t, pose, twist)
