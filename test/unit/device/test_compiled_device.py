"""The simulated device's and hand's compiled arithmetic against eq. 9 and the target path
written out in numpy."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from haptic_topology.device import compiled
from haptic_topology.device.users import TargetPath
from haptic_topology.dynamics.taskspace import integrate_pose, pose_difference
from haptic_topology.vocabulary import TaskSpace


def _reference(u, f_h, dt, limit, mass, christoffel, viscous, coulomb, lo, hi, pending,
               pose, twist, task):
    """Eq. 9 as the device integrates it (see ``maglev_step``), in numpy."""
    finite = np.isfinite(u)
    u_sat = np.clip(np.where(finite, u, 0.0), -limit, limit)
    saturated = bool((~finite).any() or (u_sat != u).any())
    applied = u_sat if pending is None else pending
    force = f_h + applied - christoffel @ twist - viscous * twist
    mass_inv = np.linalg.inv(mass)
    twist = twist + mass_inv @ force * dt
    stop = -np.diag(mass) * twist / dt
    friction = np.where(np.abs(stop) <= coulomb, stop, -np.sign(twist) * coulomb)
    twist = twist + mass_inv @ friction * dt
    pose = integrate_pose(pose, twist, dt, task)
    below, above = pose < lo, pose > hi
    stopped = bool(below.any() or above.any())
    pose = np.clip(pose, lo, hi)
    twist = np.where((below & (twist < 0)) | (above & (twist > 0)), 0.0, twist)
    return pose, twist, applied, u_sat, saturated, stopped


@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
@pytest.mark.parametrize('delay', [False, True])
def test_maglev_step_is_eq9_with_saturation_friction_and_stops(task: TaskSpace,
                                                             delay: bool) -> None:
    rng = np.random.default_rng(task.dim + 10 * delay)
    m = task.dim
    counts = np.zeros(2, dtype=int)
    for k in range(400):
        a = rng.normal(size=(m, m))
        mass = a @ a.T + m * np.eye(m)
        christoffel = 0.1 * rng.normal(size=(m, m))
        viscous, coulomb = rng.uniform(0, 2, m), rng.uniform(0, 0.5, m)
        limit = rng.uniform(0.5, 5, m)
        u = rng.normal(scale=1.5, size=m)
        if k % 17 == 0:
            u[rng.integers(m)] = [np.nan, np.inf, -np.inf][k % 3]
        f_h, twist = rng.normal(size=m), rng.normal(size=m)
        pose = rng.normal(scale=0.1, size=m)
        if task is TaskSpace.SPATIAL:
            pose[3:] = pin.log3(pin.exp3(pose[3:]))
        lo, hi = pose - rng.uniform(0, 0.003, m), pose + rng.uniform(0, 0.003, m)
        pending = rng.normal(size=m)
        dt = 1e-3
        ref = _reference(u, f_h, dt, limit, mass, christoffel, viscous, coulomb, lo, hi,
                         pending if delay else None, pose, twist, task)
        p, t, applied, pend = pose.copy(), twist.copy(), np.empty(m), pending.copy()
        bits = compiled.maglev_step(u, f_h, dt, limit, np.linalg.inv(mass),
                                    np.diag(mass).copy(), christoffel, viscous, coulomb, lo,
                                    hi, delay, True, True, True, True, pend, p, t, applied)
        np.testing.assert_allclose(t, ref[1], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(p[:3], ref[0][:3], rtol=1e-12, atol=1e-14)
        if task is TaskSpace.SPATIAL:
            # Orientation: the same rotation (clipped rotation vectors are compared as is).
            np.testing.assert_allclose(p[3:], ref[0][3:], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(applied, ref[2])
        if delay:
            np.testing.assert_array_equal(pend, ref[3])
        assert bits == compiled.SATURATED * ref[4] + compiled.STOPPED * ref[5]
        counts += ref[4], ref[5]
    assert counts.min() > 50          # both branches taken, and not taken, many times
    assert counts.max() < 350


@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
@pytest.mark.parametrize('kind', ['line', 'circle'])
def test_spring_damper_wrench_tracks_the_target_path(task: TaskSpace, kind: str) -> None:
    rng = np.random.default_rng(task.dim)
    m = task.dim
    path = TargetPath(kind, rng.normal(scale=0.1, size=m), rng.normal(size=m), 0.05, 2.0)
    k, b = rng.uniform(0, 500, m), rng.uniform(0, 5, m)
    for t in np.linspace(0.0, 5.0, 101):
        pose, twist = rng.normal(scale=0.1, size=m), rng.normal(size=m)
        target, rate = path.at(t)
        ref = k * pose_difference(target, pose, task) + b * (rate - twist)
        got = compiled.spring_damper_wrench(compiled.LINE if kind == 'line' else compiled.CIRCLE,
                                            path.start, path.velocity, path.radius,
                                            path.period, k, b, float(t), pose, twist)
        if task is TaskSpace.PLANAR:
            np.testing.assert_array_equal(got, ref)
        else:
            np.testing.assert_array_equal(got[:3], ref[:3])
            # Pinocchio's log3 (in the reference's pose_difference) loses up to 5e-11 rad
            # near pi; the compiled one does not (test_compiled_poses.py).
            np.testing.assert_allclose(got[3:], ref[3:], rtol=0, atol=1e-10 * k[3:].max())


def test_max_abs_into_is_numpys_running_maximum_of_the_absolute_values() -> None:
    rng = np.random.default_rng(7)
    peak, expected = np.zeros(6), np.zeros(6)
    for _ in range(50):
        u = rng.normal(scale=3.0, size=6)
        compiled.max_abs_into(u, peak)
        np.maximum(expected, np.abs(u), out=expected)
        np.testing.assert_array_equal(peak, expected)
    # a NaN stays, as in np.maximum
    compiled.max_abs_into(np.array([np.nan, 0.0, -1e9, 0.0, 0.0, 0.0]), peak)
    np.maximum(expected, np.abs([np.nan, 0.0, -1e9, 0.0, 0.0, 0.0]), out=expected)
    compiled.max_abs_into(np.full(6, 1e12), peak)
    np.maximum(expected, np.full(6, 1e12), out=expected)
    np.testing.assert_array_equal(peak, expected)
    assert np.isnan(peak[0]) and peak[1] == 1e12
