"""The four-bar of ``config/linkages/fourbar.yaml`` in closed form (Freudenstein's equation):
an independent reference for the closed-chain kinematics and dynamics."""

from __future__ import annotations

import math

import numpy as np

A, B, C, D_GROUND = 0.04, 0.09, 0.07, 0.10        # crank, coupler, rocker, ground (m)
COUPLER_POINT = np.array([0.045, 0.03])            # grasp point in the coupler frame (m)


def freudenstein(theta2: float, branch: float) -> tuple[np.ndarray, float]:
    """Coupler point (m) and rocker angle at crank angle ``theta2`` from Freudenstein's
    equation ``K1 cos t4 - K2 cos t2 + K3 = cos(t2 - t4)``, ``K1 = d/a``, ``K2 = d/c``,
    ``K3 = (a^2 - b^2 + c^2 + d^2) / (2 a c)``; ``branch`` +-1 picks the assembly."""
    k1, k2 = D_GROUND / A, D_GROUND / C
    k3 = (A * A - B * B + C * C + D_GROUND * D_GROUND) / (2 * A * C)
    # (K1 - cos t2) cos t4 - sin t2 sin t4 = K2 cos t2 - K3
    pa, pb, pc = k1 - math.cos(theta2), -math.sin(theta2), k2 * math.cos(theta2) - k3
    theta4 = math.atan2(pb, pa) + branch * math.acos(pc / math.hypot(pa, pb))
    b_pt = A * np.array([math.cos(theta2), math.sin(theta2)])
    c_pt = np.array([D_GROUND, 0.0]) + C * np.array([math.cos(theta4), math.sin(theta4)])
    assert abs(np.linalg.norm(c_pt - b_pt) - B) < 1e-12        # the closed form closes
    u = (c_pt - b_pt) / B
    return b_pt + COUPLER_POINT[0] * u + COUPLER_POINT[1] * np.array([-u[1], u[0]]), theta4


def branch_of(q: np.ndarray) -> float:
    """The assembly (+-1) of joint positions ``q`` (crank, coupler, rocker; the chain runs
    from the coupler joint C to the ground pivot O4, so O4 -> C is the rocker angle + pi)."""
    rocker = q[0] + q[1] + q[2] + math.pi
    return min((1.0, -1.0), key=lambda br: abs(math.remainder(
        freudenstein(q[0], br)[1] - rocker, 2 * math.pi)))
