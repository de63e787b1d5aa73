"""The compiled pose arithmetic against Pinocchio and the Python task-space functions."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from hypothesis import given, settings
from hypothesis import strategies as st

from haptic_topology.dynamics import compiled
from haptic_topology.dynamics.taskspace import integrate_pose, pose_difference
from haptic_topology.vocabulary import TaskSpace

#: Angles where the formulas switch (Taylor, quaternion) and pi itself.
ANGLES = [0.0, 1e-12, 1e-6, 1e-4 * (1 - 1e-9), 1e-4, 1e-4 * (1 + 1e-9), 0.3, math.pi / 2 - 1e-9,
          math.pi / 2 + 1e-9, 2.0, math.pi - 1e-2, math.pi - 1e-6, math.pi - 1e-12]

finite = st.floats(-10.0, 10.0, allow_nan=False)
vec3 = st.lists(finite, min_size=3, max_size=3).map(np.array)


def _axes(n: int = 40) -> np.ndarray:
    a = np.random.default_rng(7).normal(size=(n, 3))
    return np.vstack([np.eye(3), a / np.linalg.norm(a, axis=1)[:, None]])


def test_exp3_and_log3_are_rodrigues_at_every_branch() -> None:
    r = np.empty((3, 3))
    w = np.empty(3)
    for axis in _axes():
        for angle in ANGLES:
            v = angle * axis
            compiled.exp3(v, r)
            np.testing.assert_allclose(r, pin.exp3(v), rtol=0, atol=2e-15)
            compiled.log3(pin.exp3(v), w)
            if angle < math.pi - 1e-9:
                # The rotation vector itself, to rounding (Pinocchio's log3 loses up to
                # 5e-11 within 0.01 rad of pi; this one does not).
                np.testing.assert_allclose(w, v, rtol=0, atol=4e-15)
            else:   # at pi, +axis and -axis are the same rotation
                np.testing.assert_allclose(min(np.abs(w - v).max(), np.abs(w + v).max()), 0,
                                           atol=1e-11)
            compiled.exp3(w, r)
            np.testing.assert_allclose(r, pin.exp3(v), rtol=0, atol=4e-15)


@settings(max_examples=300, deadline=None)
@given(vec3, vec3, vec3, vec3, vec3, st.floats(0.0, 0.01))
def test_spatial_pose_operations_equal_the_python_ones(pa, ra, pb, rb, v,
                                                      dt: float) -> None:
    a = np.concatenate([pa, pin.log3(pin.exp3(ra))])     # rotation vectors of angle <= pi
    b = np.concatenate([pb, pin.log3(pin.exp3(rb))])
    out = np.empty(6)
    compiled.pose_difference(a, b, out)
    ref = pose_difference(a, b, TaskSpace.SPATIAL)
    np.testing.assert_allclose(out[:3], ref[:3], rtol=0, atol=1e-15)
    # The rotations as matrices (Pinocchio's log3, which the Python function calls, loses up
    # to 5e-11 near pi: compare with the rotation itself, R_a R_b^T).
    np.testing.assert_allclose(pin.exp3(out[3:]), pin.exp3(a[3:]) @ pin.exp3(b[3:]).T,
                               rtol=0, atol=1e-14)
    twist = np.concatenate([v, -v])
    moved = a.copy()
    compiled.integrate_pose(moved, twist, dt)
    ref = integrate_pose(a, twist, dt, TaskSpace.SPATIAL)
    np.testing.assert_allclose(moved[:3], ref[:3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(pin.exp3(moved[3:]), pin.exp3(-v * dt) @ pin.exp3(a[3:]),
                               rtol=0, atol=1e-14)


@settings(max_examples=300, deadline=None)
@given(vec3, vec3, vec3, st.floats(0.0, 0.01))
def test_planar_pose_operations_equal_the_python_ones_exactly(a, b, twist, dt: float) -> None:
    out = np.empty(3)
    compiled.pose_difference(a, b, out)
    assert np.array_equal(out, pose_difference(a, b, TaskSpace.PLANAR))
    moved = a.copy()
    compiled.integrate_pose(moved, twist, dt)
    assert np.array_equal(moved, integrate_pose(a, twist, dt, TaskSpace.PLANAR))
