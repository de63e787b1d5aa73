"""One classical Runge-Kutta (RK4) step of a second-order system with a power integrated
alongside: the VE's integration with contacts and the closed chains' share it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ``deriv(q, dq) -> (qdd, power)``: the acceleration at a stage and a power (W) to integrate.
Derivative = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, float]]


def rk4_step(deriv: Derivative, q: np.ndarray, dq: np.ndarray,
             h: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(q, dq)`` after ``h`` s of ``qdd = deriv(q, dq)[0]`` by classical RK4, and the
    integral of the power over the step (J), with the same stages and weights:
    ``x + h/6 (k1 + 2 k2 + 2 k3 + k4)``."""
    a1, p1 = deriv(q, dq)
    q2, v2 = q + 0.5 * h * dq, dq + 0.5 * h * a1
    a2, p2 = deriv(q2, v2)
    q3, v3 = q + 0.5 * h * v2, dq + 0.5 * h * a2
    a3, p3 = deriv(q3, v3)
    q4, v4 = q + h * v3, dq + h * a3
    a4, p4 = deriv(q4, v4)
    return (q + h / 6.0 * (dq + 2.0 * v2 + 2.0 * v3 + v4),
            dq + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
            h / 6.0 * (p1 + 2.0 * p2 + 2.0 * p3 + p4))
