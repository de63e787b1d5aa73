"""Device control laws of the paper as pure functions: eq. 10 and eq. 14 (with eq. 13).

All vectors are task vectors at the user's hand (m = 3 planar, 6 spatial; layouts in
:mod:`haptic_topology.dynamics.taskspace`), all matrices m x m. Units: wrenches N / N m,
poses m / rad, twists m/s / rad/s; ``M_d`` kg / kg m^2; ``k_tc`` N/(m kg), ``b_tc`` N s/(m kg)
(the penalty of eq. 13 is an acceleration, multiplied by ``M_d``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.validate import as_float, as_vector, check_keys
from haptic_topology.vocabulary import LAW_MODES, ControlMode, TaskSpace

# -- the penalty gains' one range -------------------------------------------------------------
#: Upper end of the live penalty gains' range (N/(m kg), N s/(m kg)).
GAIN_MAX = 1.0e5


def check_gain(name: str, value: Any) -> str | None:
    """Why ``value`` is not an acceptable ``k_tc``/``b_tc``, or None if it is."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f'{name} must be a number, got {value!r}'
    if not math.isfinite(value):
        return f'{name} must be finite, got {value}'
    if value < 0.0:
        return f'{name} must be >= 0 (a negative penalty pushes off the manifold), got {value}'
    if value > GAIN_MAX:
        return f'{name} must be <= {GAIN_MAX:g}, got {value}'
    return None


def check_live(name: str, value: Any) -> str | None:
    """Why ``value`` is not acceptable for the live lmi_controller parameter ``name``
    (``mode``, ``k_tc``, ``b_tc``), or None; for an on-set-parameters callback."""
    if name in ('k_tc', 'b_tc'):
        return check_gain(name, value)
    if name == 'mode' and value not in LAW_MODES:
        return f'mode must be one of {", ".join(LAW_MODES)}, got {value!r}'
    return None


@dataclass(frozen=True)
class ControlGains:
    """Gains of the coordination channel and of the topological penalty.

    ``k_pc``/``b_pc`` (m): coordination stiffness/damping (eqs. 15-16, N/m, N m/rad,
    N s/m, N m s/rad); ``k_tc``/``b_tc``: penalty stiffness and damping of eq. 13;
    ``b_d``/``k_d`` (m x m): desired VT damping and stiffness of eq. 4 (zero in the paper).
    """

    k_pc: np.ndarray
    b_pc: np.ndarray
    k_tc: float
    b_tc: float
    b_d: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    k_d: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def with_penalty(self, k_tc: float, b_tc: float) -> ControlGains:
        return ControlGains(self.k_pc, self.b_pc, k_tc, b_tc, self.b_d, self.k_d)

    @classmethod
    def from_config(cls, raw: Any, where: str, m: int) -> ControlGains:
        """The ``control:`` block of a scenario: ``k_pc``, ``b_pc`` (m values >= 0, required),
        ``k_tc``, ``b_tc`` (in [0, GAIN_MAX], default 0). ``where``: the block's path."""
        ctl = check_keys(raw, where, required=('k_pc', 'b_pc'), optional=('k_tc', 'b_tc'))
        return cls(k_pc=as_vector(ctl['k_pc'], f'{where}.k_pc', m, lo=0.0),
                   b_pc=as_vector(ctl['b_pc'], f'{where}.b_pc', m, lo=0.0),
                   k_tc=as_float(ctl.get('k_tc', 0.0), f'{where}.k_tc', lo=0.0, hi=GAIN_MAX),
                   b_tc=as_float(ctl.get('b_tc', 0.0), f'{where}.b_tc', lo=0.0, hi=GAIN_MAX))


def coordination_wrench(x_vt: np.ndarray, xd_vt: np.ndarray, x_h: np.ndarray,
                        xd_h: np.ndarray, k_pc: np.ndarray, b_pc: np.ndarray,
                        task: TaskSpace, *, error: np.ndarray | None = None) -> np.ndarray:
    """``F_pc = K_pc (x_vt - x_h) + B_pc (xd_vt - xd_h)``: the spring-damper of Fig. 1.

    Acts on the device towards the VT; the VT feels ``-F_pc``. ``error``: ``x_vt (-) x_h``
    when the caller has it (eq. 13 takes the same).
    """
    e = pose_difference(x_vt, x_h, task) if error is None else error
    return k_pc * e + b_pc * (xd_vt - xd_h)


def acceleration_control(lambda_inv: np.ndarray, m_d: np.ndarray, c_d: np.ndarray,
                         f_h: np.ndarray, f_env: np.ndarray, f_pc: np.ndarray,
                         x_h: np.ndarray, xd_h: np.ndarray,
                         b_d: np.ndarray | None = None,
                         k_d: np.ndarray | None = None, *,
                         ml: np.ndarray | None = None) -> np.ndarray:
    """Impedance control at the acceleration level, eq. 10::

        u = (M_d L - I) F_h + M_d L (F_env + F_pc) + (C_d - M_d L b_d) xd_h - M_d L k_d x_h

    with ``L = Lambda_h^-1`` (eq. 6). Applied to the device of eq. 9 it gives
    ``xdd_h = Lambda_h^-1 (F_h + F_env + F_pc - b_d xd_h - k_d x_h)`` (eq. 5).
    ``ml``: ``M_d L`` when the caller holds it (it changes only with ``L``, at a re-sync).
    """
    if ml is None:
        ml = m_d @ lambda_inv
    u = ml @ (f_h + f_env + f_pc) - f_h + c_d @ xd_h
    if b_d is not None and b_d.size:
        u -= ml @ (b_d @ xd_h)
    if k_d is not None and k_d.size:
        u -= ml @ (k_d @ x_h)
    return u


def penalty_acceleration(projector: np.ndarray, error: np.ndarray, error_rate: np.ndarray,
                         k_tc: float, b_tc: float) -> np.ndarray:
    """``sum_i (k_tc n_i^T e + b_tc n_i^T edot) n_i`` of eq. 13 (without ``M_d``).

    ``projector`` is ``sum_i w_i n_i n_i^T`` in the task coordinates (see
    ``ConstraintDirections.projector``); ``e = x_vt - x_h``, ``edot = xd_vt - xd_h``.
    """
    return projector @ (k_tc * error + b_tc * error_rate)


def penalty_control(lambda_inv: np.ndarray, m_d: np.ndarray, c_d: np.ndarray,
                    f_h: np.ndarray, f_env: np.ndarray, f_pc: np.ndarray,
                    x_h: np.ndarray, xd_h: np.ndarray, x_vt: np.ndarray, xd_vt: np.ndarray,
                    projector: np.ndarray, k_tc: float, b_tc: float, task: TaskSpace,
                    b_d: np.ndarray | None = None,
                    k_d: np.ndarray | None = None, *, ml: np.ndarray | None = None,
                    error: np.ndarray | None = None) -> np.ndarray:
    """The proposed control, eq. 14: eq. 10 plus ``u_add = M_d * penalty`` (eq. 13).
    ``ml``: see :func:`acceleration_control`; ``error``: ``x_vt (-) x_h`` when the caller
    has it (the coordination wrench takes the same)."""
    u = acceleration_control(lambda_inv, m_d, c_d, f_h, f_env, f_pc, x_h, xd_h, b_d, k_d,
                             ml=ml)
    e = pose_difference(x_vt, x_h, task) if error is None else error
    return u + m_d @ penalty_acceleration(projector, e, xd_vt - xd_h, k_tc, b_tc)


def control_wrench(mode: ControlMode, lambda_inv: np.ndarray, m_d: np.ndarray,
                   c_d: np.ndarray, f_h: np.ndarray, f_pc: np.ndarray, x_h: np.ndarray,
                   xd_h: np.ndarray, x_vt: np.ndarray, xd_vt: np.ndarray,
                   projector: np.ndarray, gains: ControlGains, task: TaskSpace,
                   f_env: np.ndarray | None = None, *, ml: np.ndarray | None = None,
                   error: np.ndarray | None = None) -> np.ndarray:
    """Device wrench ``u`` for ``mode``: eq. 14, eq. 10, or zero (``ml``, ``error``: see
    :func:`penalty_control`)."""
    if mode is ControlMode.ZERO:
        return np.zeros(task.dim)
    fe = np.zeros(task.dim) if f_env is None else f_env
    if mode is ControlMode.ACCELERATION_ONLY:
        return acceleration_control(lambda_inv, m_d, c_d, f_h, fe, f_pc, x_h, xd_h,
                                    gains.b_d, gains.k_d, ml=ml)
    return penalty_control(lambda_inv, m_d, c_d, f_h, fe, f_pc, x_h, xd_h, x_vt, xd_vt,
                           projector, gains.k_tc, gains.b_tc, task, gains.b_d, gains.k_d,
                           ml=ml, error=error)


def stable_hold(lambda_inv: np.ndarray, k_pc: np.ndarray, b_pc: np.ndarray) -> float:
    """Half the longest time (s) a coordination wrench ``F_pc`` (eq. 10's spring-damper
    ``K_pc``, ``B_pc``) may be held constant on a body of task-space inverse inertia
    ``lambda_inv`` (eq. 19) and stay stable. Holding it for ``h`` steps the spring
    explicitly: for ``x'' = -k x - b x'`` stepped that way the step is stable while
    ``k h^2 + 2 b h < 4``, with ``k``, ``b`` (1/s^2, 1/s) the largest eigenvalues of
    ``K^1/2 lambda_inv K^1/2`` and ``B^1/2 lambda_inv B^1/2``. inf when both are zero."""
    return StableHold(k_pc, b_pc)(lambda_inv)


class StableHold:
    """:func:`stable_hold` for fixed gains ``K_pc``, ``B_pc`` (m values each, N/m and N m/rad,
    N s/m and N m s/rad): their square roots are taken once, and both eigenvalue problems go
    to LAPACK in one call (the VE evaluates this at every LMI update)."""

    def __init__(self, k_pc: np.ndarray, b_pc: np.ndarray) -> None:
        gains = np.stack([np.asarray(k_pc, dtype=float), np.asarray(b_pc, dtype=float)])
        self._roots = np.sqrt(np.maximum(gains, 0.0))       # rows: K^1/2, B^1/2 diagonals
        self._left = self._roots[:, :, None]
        self._right = self._roots[:, None, :]

    def __call__(self, lambda_inv: np.ndarray) -> float:
        """The stable hold (s) at ``lambda_inv`` (m x m, eq. 19)."""
        lam = 0.5 * (lambda_inv + lambda_inv.T)
        top = np.linalg.eigvalsh(self._left * lam * self._right).max(axis=1)
        k, b = max(float(top[0]), 0.0), max(float(top[1]), 0.0)
        if k <= 0.0 and b <= 0.0:
            return math.inf
        limit = (-b + math.sqrt(b * b + 4.0 * k)) / k if k > 0.0 else 2.0 / b
        return 0.5 * limit
