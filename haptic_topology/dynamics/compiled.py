"""Compiled pose arithmetic for the 1 kHz loop (numba, no Python objects per call).

The loop's per-cycle arithmetic runs in compiled code (:mod:`haptic_topology.control.compiled`)
so that a cycle costs microseconds, not the ~100 numpy calls on 3- and 6-vectors that a
cycle makes in Python (about 1 us each on a 2-core machine). These are the pose operations
of :mod:`haptic_topology.dynamics.taskspace` written for it: the same conventions (planar
``[x, y, theta]``, spatial ``[p, rotation vector]``, world frame), for use *inside* other
compiled functions (each one called from Python costs a dispatch of about 1 us).

``exp3``/``log3`` are Rodrigues' formula and its inverse (as Pinocchio's ``exp3``/``log3``,
which the Python functions call): a second-order Taylor expansion below 1e-4 rad and, above
pi/2, the rotation vector from the unit quaternion. ``exp3`` agrees with Pinocchio's to
2e-15 and ``log3`` returns the rotation vector to 4e-15 up to pi, where Pinocchio's loses up
to 5e-11 within 0.01 rad of pi (``test/unit/dynamics/test_compiled_poses.py``). Not bit for
bit, then, but the simulation and the graph call the same compiled functions, so they stay
equal to each other exactly.

Each function has one signature (float64 arrays of any layout), compiled when the module is
imported: from numba's cache next to this file (``cache=True``; about 0.5 s per process),
or, the first time on a machine, from source (a few seconds). Never inside the loop.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit, void

#: Array types of the signatures: float64, any memory layout (one compiled specialization per
#: function, compiled or loaded from the cache at import, never in the loop).
VEC = float64[:]
MAT = float64[:, :]

#: Below this angle (rad) exp3/log3 use the Taylor expansions of sin(t)/t etc.
_SMALL = 1e-4
#: Above this angle (rad) log3 takes the rotation vector from the unit quaternion: towards pi
#: the antisymmetric part vanishes and ``theta / sin(theta)`` amplifies its rounding.
_LARGE = 0.5 * math.pi


@njit(float64(float64), cache=True)
def wrap_angle(a: float) -> float:
    """An angle (rad) wrapped to [-pi, pi), as ``taskspace.wrap_angle``."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(void(VEC, MAT), cache=True)
def exp3(w: np.ndarray, out: np.ndarray) -> None:
    """``out`` (3 x 3) = the rotation of rotation vector ``w`` (rad): Rodrigues' formula."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    t = math.sqrt(t2)
    if t < _SMALL:
        a = 1.0 - t2 / 6.0                 # sin(t)/t
        b = 0.5 - t2 / 24.0                # (1 - cos(t))/t^2
    else:
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    x, y, z = w[0], w[1], w[2]
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[2, 2] = 1.0 - b * (x * x + y * y)
    out[0, 1] = b * x * y - a * z
    out[1, 0] = b * x * y + a * z
    out[0, 2] = b * x * z + a * y
    out[2, 0] = b * x * z - a * y
    out[1, 2] = b * y * z - a * x
    out[2, 1] = b * y * z + a * x


@njit(void(MAT, VEC), cache=True)
def log3(r: np.ndarray, out: np.ndarray) -> None:
    """``out`` (3) = the rotation vector (rad, angle in [0, pi]) of rotation ``r``."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    c = 0.5 * (tr - 1.0)
    if c >= 1.0:
        theta = 0.0
    elif c <= -1.0:
        theta = math.pi
    else:
        theta = math.acos(c)
    if theta > _LARGE:
        # Towards pi the antisymmetric part vanishes: the axis from the unit quaternion, taken
        # from the largest diagonal entry (Shepperd's method), with w >= 0.
        i0 = 0
        if r[1, 1] > r[i0, i0]:
            i0 = 1
        if r[2, 2] > r[i0, i0]:
            i0 = 2
        i1 = (i0 + 1) % 3
        i2 = (i0 + 2) % 3
        s = math.sqrt(max(1.0 + r[i0, i0] - r[i1, i1] - r[i2, i2], 0.0))
        if r[i2, i1] < r[i1, i2]:
            s = -s
        v = np.empty(3)
        v[i0] = 0.5 * s
        v[i1] = (r[i1, i0] + r[i0, i1]) / (2.0 * s)
        v[i2] = (r[i2, i0] + r[i0, i2]) / (2.0 * s)
        w = (r[i2, i1] - r[i1, i2]) / (2.0 * s)
        norm = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        angle = 2.0 * math.atan2(norm, w)
        for i in range(3):
            out[i] = angle * v[i] / norm
        return
    if theta < _SMALL:
        k = 0.5 * (1.0 + theta * theta / 6.0)       # t / (2 sin t)
    else:
        k = 0.5 * theta / math.sin(theta)
    out[0] = k * (r[2, 1] - r[1, 2])
    out[1] = k * (r[0, 2] - r[2, 0])
    out[2] = k * (r[1, 0] - r[0, 1])


@njit(MAT(MAT, MAT, boolean), cache=True)
def _mul3(a: np.ndarray, b: np.ndarray, b_transposed: bool) -> np.ndarray:
    """``a b`` (or ``a b^T``) of two 3 x 3 matrices, in plain loops (no BLAS call)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += a[i, k] * (b[j, k] if b_transposed else b[k, j])
            out[i, j] = s
    return out


@njit(void(VEC, VEC, int64, VEC), cache=True)
def task_pose_difference(a: np.ndarray, b: np.ndarray, rotation_dim: int,
                         out: np.ndarray) -> None:
    """``out`` = ``a (-) b`` (``taskspace.pose_difference``) for a task with ``rotation_dim``
    rotation rows (``TaskSpace.rotation_dim``): 0, a point grasp: ``a - b``; 1, planar: the
    angle wrapped to [-pi, pi); 3, spatial: the rotation taking ``b`` to ``a`` (world
    frame)."""
    if rotation_dim == 0:
        for i in range(a.size):
            out[i] = a[i] - b[i]
        return
    if rotation_dim == 1:
        out[0] = a[0] - b[0]
        out[1] = a[1] - b[1]
        out[2] = wrap_angle(a[2] - b[2])
        return
    ra = np.empty((3, 3))
    rb = np.empty((3, 3))
    exp3(a[3:6], ra)
    exp3(b[3:6], rb)
    rel = _mul3(ra, rb, True)
    for i in range(3):
        out[i] = a[i] - b[i]
    log3(rel, out[3:6])


@njit(void(VEC, VEC, VEC), cache=True)
def pose_difference(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out`` = ``a (-) b`` of a rigid grasp, told by the size: 3 planar, 6 spatial
    (:func:`task_pose_difference` for any task)."""
    task_pose_difference(a, b, 1 if a.size == 3 else 3, out)


@njit(void(VEC, VEC, float64), cache=True)
def integrate_pose(pose: np.ndarray, twist: np.ndarray, dt: float) -> None:
    """Move ``pose`` in place with the constant world-frame ``twist`` for ``dt`` s
    (``taskspace.integrate_pose``; planar angles are not wrapped). Up to 3 entries (planar,
    and a point grasp's point) the step is linear; 6 entries turn the rotation vector."""
    if pose.size <= 3:
        for i in range(pose.size):
            pose[i] = pose[i] + twist[i] * dt
        return
    step = np.empty((3, 3))
    rot = np.empty((3, 3))
    w = np.empty(3)
    for i in range(3):
        w[i] = twist[3 + i] * dt
    exp3(w, step)
    exp3(pose[3:6], rot)
    r = _mul3(step, rot, False)
    for i in range(3):
        pose[i] = pose[i] + twist[i] * dt
    log3(r, pose[3:6])


@njit(void(VEC, VEC, VEC, float64, VEC, VEC), cache=True)
def rk4_stage(x: np.ndarray, v: np.ndarray, a: np.ndarray, c: float, k_a: np.ndarray,
              out: np.ndarray) -> None:
    """One stage of classical RK4 on the state ``x = [q, dq]`` (2d) of a second-order system
    whose stage derivative is ``[v, a]`` (``v`` the stage's velocity, ``a`` its acceleration,
    d each): ``k_a`` (d) takes ``a``, and ``out`` (2d) = ``x + c [v, a]``, each entry
    computed as ``x_i + (k_i c)`` (the bits of numpy's ``x + c * k``)."""
    d = v.size
    for i in range(d):
        k_a[i] = a[i]
        out[i] = x[i] + v[i] * c
        out[d + i] = x[d + i] + a[i] * c


@njit(void(MAT, float64, VEC), cache=True)
def rk4_finish(k: np.ndarray, sixth: float, x: np.ndarray) -> None:
    """The end of a classical RK4 step, in place: ``x += sixth (k1 + 2 k2 + 2 k3 + k4)``
    with the stage derivatives ``k`` (4 x 2d) summed in that order and ``sixth = h / 6``
    (the bits of numpy's ``x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)``)."""
    for i in range(x.size):
        s = k[0, i] * 1.0 + k[1, i] * 2.0
        s = s + k[2, i] * 2.0
        s = s + k[3, i] * 1.0
        x[i] = x[i] + s * sixth


@njit(MAT(MAT, MAT), cache=True)
def cho_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``X`` (n x k, new) with ``L L^T X = rhs`` for the lower Cholesky factor ``L`` =
    ``factor`` (n x n) and ``rhs`` (n x k): forward substitution with ``L``, then back
    substitution with ``L^T``, column by column (``spd.spd_solve``)."""
    n, k = rhs.shape
    x = np.empty((n, k))
    for c in range(k):
        for i in range(n):
            s = rhs[i, c]
            for j in range(i):
                s -= factor[i, j] * x[j, c]
            x[i, c] = s / factor[i, i]
        for i in range(n - 1, -1, -1):
            s = x[i, c]
            for j in range(i + 1, n):
                s -= factor[j, i] * x[j, c]
            x[i, c] = s / factor[i, i]
    return x


@njit(MAT(MAT, VEC, VEC, VEC), cache=True)
def nullspace_projector(u: np.ndarray, weights: np.ndarray, scale: np.ndarray,
                        r: np.ndarray) -> np.ndarray:
    """The penalty projector ``P`` (m x m, new) of eq. 13 for a diagonal device inertia
    ``M_d = diag(r)^2``, as
    :meth:`~haptic_topology.dynamics.constraints.ConstraintDirections.projector` defines it:
    with ``C`` the columns ``W u_i`` of ``U_w`` (``u``) whose ``weights`` are > 0, the most
    constrained (last) first, ``W = diag(scale)``, and ``Q`` an orthonormal basis of
    ``diag(r)^-1 C`` column by column (Gram-Schmidt, each column orthogonalised twice: the
    ``Q`` of a QR factorisation up to the columns' signs, which ``P`` does not see),
    ``P[a, b] = sum_j Q[a, j] w_j Q[b, j] r[b] / r[a]``; zero if no weight is > 0."""
    m = u.shape[0]
    q = np.empty((m, m))
    w = np.empty(m)
    t = 0
    for i in range(m - 1, -1, -1):
        if weights[i] <= 0.0:
            continue
        for k in range(m):
            q[k, t] = scale[k] * u[k, i] / r[k]
        for _ in range(2):
            for j in range(t):
                d = 0.0
                for k in range(m):
                    d += q[k, j] * q[k, t]
                for k in range(m):
                    q[k, t] -= d * q[k, j]
        n = 0.0
        for k in range(m):
            n += q[k, t] * q[k, t]
        n = math.sqrt(n)
        for k in range(m):
            q[k, t] /= n
        w[t] = weights[i]
        t += 1
    p = np.zeros((m, m))
    for a in range(m):
        for b in range(m):
            s = 0.0
            for j in range(t):
                s += q[a, j] * w[j] * q[b, j]
            p[a, b] = s * r[b] / r[a]
    return p
