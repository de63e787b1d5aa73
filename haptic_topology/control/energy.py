"""The energy account and the passivity controller's per-cycle arithmetic, compiled.

:class:`~haptic_topology.control.passivity.EnergyAccount` owns the arrays; its layout and the
method are described there. One call per answered device state
(:func:`task_law_energy`): the control law of
:func:`~haptic_topology.control.compiled.task_law`, unchanged, then :func:`account`, a few
dozen flops: the observer over the period just ended, the passivity controller's damping,
the parts of the new command.

Sign convention: *work* is the energy the controller puts into the device port,
``W = sum u . dx`` (J; u the wrench commanded over a period, dx the device's displacement
over it: ``F v dT`` with ``v dT`` measured as the displacement, the work of a wrench held
over the period whatever the velocity did within it). The passivity observer is
``E = D - W + W_hand + W_vt``, with ``D = sum dx . C_d v`` the energy the device's own
damping ``C_d`` (eq. 9) dissipated, ``W_hand`` the work of eq. 10's hand term and ``W_vt``
the work of the coupling parts (penalty, coordination, contacts) at the VT's end,
``sum u_c . xd_vt dT`` (the module doc of :mod:`~haptic_topology.control.passivity` says
why): >= 0 while the law is passive (Hannaford & Ryu).
"""

from __future__ import annotations

import numpy as np
from numba import boolean, float64, int64, njit, void

from haptic_topology.control.compiled import ZERO, task_law
from haptic_topology.dynamics.compiled import MAT, VEC, task_pose_difference

# -- the state vector's layout (EnergyAccount mirrors it) ------------------------------------
#: Parts of a command, in this order (see EnergyAccount): eq. 13's penalty, the coordination
#: wrench of eqs. 15-16, the contacts' F_env, the device damping's compensation C_d xd_h,
#: the hand term (M_d L - I) F_h of eq. 10, the passivity controller's damping.
N_PARTS = 6
PART_PENALTY, PART_COORDINATION, PART_CONTACTS, PART_DAMPING, PART_HAND, PART_PASSIVITY = (
    range(N_PARTS))
(HAVE, WORK, DISSIPATED, OBSERVER, WINDOWED, ALPHA, ACTED, ALPHA_PEAK, MINIMUM, RING_AT,
 VT_WORK) = range(11)
HEAD = 11
#: The parameters after the head: PC on (1/0), the floor of the squared speed ((m/s)^2),
#: damping cap (N s/m), window (cycles, 0: none); then the wrench limit (m values).
P_ENABLED, P_V2_FLOOR, P_ALPHA_MAX, P_WINDOW = range(HEAD, HEAD + 4)
#: Where the limit starts; the m-vectors and parts follow it (EnergyAccount's layout).
LIMIT = HEAD + 4


@njit(void(int64, int64, MAT, MAT, VEC, VEC, VEC, VEC, VEC, VEC, VEC, float64, VEC),
      cache=True)
def account(rotation_dim: int, mode: int, ml: np.ndarray, c_d: np.ndarray, x_h: np.ndarray,
            xd_h: np.ndarray, xd_vt: np.ndarray, f_h: np.ndarray, f_env: np.ndarray,
            f_pc: np.ndarray, u: np.ndarray, dt: float, state: np.ndarray) -> None:
    """Account for the period ``dt`` (s) that ends at this state (pose ``x_h``, twist
    ``xd_h``; the LMI's VT hand twist ``xd_vt`` after integrating the period) and for the
    command ``u`` of the law (``mode``), in place on ``state`` (which holds the parameters
    and the wrench ``limit`` too: one array to pass); with the passivity controller on add
    its damping ``-alpha xd_h`` to ``u``.

    1. observer: ``dW = u_prev . dx`` (``u_prev``: the previous command clamped to ``limit``,
       ``dx = x_h (-) x_prev``), per axis, per part and in total; ``dD = dx . C_d xd_h``;
       the VT end's work of the coupling parts (penalty, coordination, contacts)
       ``dW_vt = u_c,prev . xd_vt dt`` (``xd_vt dt``: the VT's motion over the period as the
       LMI's semi-implicit step integrates it, a re-sync's jump left out);
       ``E += dD - dW + dW_hand + dW_vt`` (two-port: see
       :mod:`~haptic_topology.control.passivity`); the windowed observer ``E_w`` sums the
       newest ``window`` of these increments;
    2. passivity controller (Hannaford & Ryu, on ``E_w``): when ``E_w < 0``,
       ``alpha = -E_w / (dt max(|xd_h|^2, floor))``, at most the cap, and ``u -= alpha
       xd_h`` with the added wrench clipped to ``limit_i`` on each axis (an axis moving
       fast against a small limit does not lower the damping of the others);
    3. the parts of ``u`` (module :mod:`~haptic_topology.control.passivity`) and ``u``
       clamped, kept for the next period.

    ``ml`` ``M_d Lambda_h^-1``, ``c_d`` ``C_d`` (m x m), ``f_h``, ``f_env``, ``f_pc`` the
    law's inputs (m); ``dt`` is also the period the new command is assumed held for."""
    m = x_h.size
    n_ring = int(state[P_WINDOW])
    limit = state[LIMIT:LIMIT + m]
    at = LIMIT + m
    prev_x = state[at:at + m]
    prev_u = state[at + m:at + 2 * m]
    axis = state[at + 2 * m:at + 3 * m]
    parts = state[at + 3 * m:at + 3 * m + N_PARTS]
    prev_parts = state[at + 3 * m + N_PARTS:at + 3 * m + N_PARTS + N_PARTS * m]
    ring = state[at + 3 * m + N_PARTS + N_PARTS * m:]
    if state[HAVE] > 0.0:
        dx = np.empty(m)
        task_pose_difference(x_h, prev_x, rotation_dim, dx)
        w = 0.0
        d = 0.0
        for i in range(m):
            wi = prev_u[i] * dx[i]
            axis[i] += wi
            w += wi
            s = 0.0
            for k in range(m):
                s += c_d[i, k] * xd_h[k]
            d += dx[i] * s
        wh = 0.0
        for p in range(N_PARTS):
            s = 0.0
            for i in range(m):
                s += prev_parts[p * m + i] * dx[i]
            parts[p] += s
            if p == PART_HAND:
                wh = s
        wv = 0.0                    # the coupling parts' work at the VT's end
        for p in (PART_PENALTY, PART_COORDINATION, PART_CONTACTS):
            for i in range(m):
                wv += prev_parts[p * m + i] * xd_vt[i] * dt
        state[WORK] += w
        state[DISSIPATED] += d
        state[VT_WORK] += wv
        fb = d - (w - wh) + wv      # two-port, without the hand part (passivity module doc)
        state[OBSERVER] += fb
        state[MINIMUM] = min(state[MINIMUM], state[OBSERVER])
        if n_ring > 0:
            r = int(state[RING_AT])
            state[WINDOWED] += fb - ring[r]
            ring[r] = fb
            state[RING_AT] = (r + 1) % n_ring
        else:
            state[WINDOWED] += fb
    alpha = 0.0
    if state[P_ENABLED] > 0.0 and mode != ZERO and state[WINDOWED] < 0.0 and dt > 0.0:
        v2 = 0.0
        for i in range(m):
            v2 += xd_h[i] * xd_h[i]
        alpha = -state[WINDOWED] / (dt * max(v2, state[P_V2_FLOOR]))
        alpha = min(alpha, state[P_ALPHA_MAX])
        for i in range(m):
            u[i] = u[i] + min(max(-alpha * xd_h[i], -limit[i]), limit[i])
        state[ACTED] += 1.0
        state[ALPHA_PEAK] = max(state[ALPHA_PEAK], alpha)
    state[ALPHA] = alpha
    for i in range(m):
        prev_x[i] = x_h[i]
        prev_u[i] = min(max(u[i], -limit[i]), limit[i])
    if mode == ZERO:
        for j in range(N_PARTS * m):
            prev_parts[j] = 0.0
    else:
        for i in range(m):
            c = 0.0
            e = 0.0
            h = 0.0
            d = 0.0
            for k in range(m):
                c += ml[i, k] * f_pc[k]
                e += ml[i, k] * f_env[k]
                h += ml[i, k] * f_h[k]
                d += c_d[i, k] * xd_h[k]
            h -= f_h[i]
            pc = min(max(-alpha * xd_h[i], -limit[i]), limit[i])
            prev_parts[PART_COORDINATION * m + i] = c
            prev_parts[PART_CONTACTS * m + i] = e
            prev_parts[PART_HAND * m + i] = h
            prev_parts[PART_DAMPING * m + i] = d
            prev_parts[PART_PASSIVITY * m + i] = pc
            prev_parts[PART_PENALTY * m + i] = u[i] - pc - c - e - h - d
    state[HAVE] = 1.0


@njit(void(int64, int64, boolean, MAT, MAT, MAT, MAT, VEC, VEC, float64, float64,
           VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC, VEC, float64, VEC), cache=True)
def task_law_energy(rotation_dim: int, mode: int, vt_coupling: bool, ml: np.ndarray,
                    m_d: np.ndarray, c_d: np.ndarray, projector: np.ndarray, k_pc: np.ndarray,
                    b_pc: np.ndarray, k_tc: float, b_tc: float, x_vt: np.ndarray,
                    xd_vt: np.ndarray, x_h: np.ndarray, xd_h: np.ndarray, f_h: np.ndarray,
                    f_env: np.ndarray, u: np.ndarray, f_pc: np.ndarray, f_vt: np.ndarray,
                    dt: float, state: np.ndarray) -> None:
    """:func:`~haptic_topology.control.compiled.task_law` (the same ``u``, ``f_pc``,
    ``f_vt``), then :func:`account` of its command, in one call."""
    task_law(rotation_dim, mode, vt_coupling, ml, m_d, c_d, projector, k_pc, b_pc, k_tc, b_tc,
             x_vt, xd_vt, x_h, xd_h, f_h, f_env, u, f_pc, f_vt)
    account(rotation_dim, mode, ml, c_d, x_h, xd_h, xd_vt, f_h, f_env, f_pc, u, dt, state)
