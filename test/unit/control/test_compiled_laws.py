"""The controller's compiled arithmetic against the reference functions of ``laws`` and the
LMI step written out in numpy (eqs. 10, 13-17, 20)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from haptic_topology.control import compiled
from haptic_topology.control.laws import ControlGains, control_wrench, coordination_wrench
from haptic_topology.dynamics.taskspace import integrate_pose, pose_difference
from haptic_topology.vocabulary import ControlMode, TaskSpace


def _pose(rng: np.random.Generator, task: TaskSpace) -> np.ndarray:
    x = rng.normal(size=task.dim)
    if task is TaskSpace.SPATIAL:
        x[3:] = pin.log3(pin.exp3(x[3:]))
    return x


@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
@pytest.mark.parametrize('mode', list(ControlMode))
@pytest.mark.parametrize('vt_coupling', [True, False])
def test_law_is_eq14_eq10_and_the_coordination_wrench(task: TaskSpace, mode: ControlMode,
                                                      vt_coupling: bool) -> None:
    rng = np.random.default_rng(int(mode) + 10 * task.dim + vt_coupling)
    m = task.dim
    for _ in range(200):
        a = rng.normal(size=(m, m))
        lam = a @ a.T
        m_d = np.diag(rng.uniform(0.1, 2.0, m))
        c_d = 0.1 * rng.normal(size=(m, m))
        n = np.linalg.qr(rng.normal(size=(m, m)))[0][:, :2]
        projector = n @ np.diag(rng.uniform(0, 1, 2)) @ n.T
        gains = ControlGains(rng.uniform(0, 500, m), rng.uniform(0, 5, m),
                             float(rng.uniform(0, 1e4)), float(rng.uniform(0, 100)))
        x_vt, x_h = _pose(rng, task), _pose(rng, task)
        xd_vt, xd_h, f_h, f_env = (rng.normal(size=m) for _ in range(4))
        u, f_pc, f_vt = np.empty(m), np.empty(m), np.empty(m)
        compiled.law(int(mode), vt_coupling, m_d @ lam, m_d, c_d, projector, gains.k_pc,
                     gains.b_pc, gains.k_tc, gains.b_tc, x_vt, xd_vt, x_h, xd_h, f_h, f_env,
                     u, f_pc, f_vt)
        ref_pc = coordination_wrench(x_vt, xd_vt, x_h, xd_h, gains.k_pc, gains.b_pc, task)
        ref_u = control_wrench(mode, lam, m_d, c_d, f_h, ref_pc, x_h, xd_h, x_vt, xd_vt,
                               projector, gains, task, f_env)
        np.testing.assert_allclose(f_pc, ref_pc, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(u, ref_u, rtol=1e-12, atol=1e-9)
        np.testing.assert_array_equal(f_vt, f_h - f_pc if vt_coupling else f_h)


@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
@pytest.mark.parametrize('contacts', [False, True])
def test_lmi_step_is_semi_implicit_euler_of_eq17(task: TaskSpace, contacts: bool) -> None:
    rng = np.random.default_rng(task.dim + contacts)
    m, d = task.dim, 5
    for _ in range(200):
        accel_map, jac = rng.normal(size=(d, m)), rng.normal(size=(m, d))
        bias, q, dq, wrench = (rng.normal(size=k) for k in (d, d, d, m))
        contact = rng.normal(size=d) if contacts else np.zeros(0)
        x_vt, xd_vt = _pose(rng, task), rng.normal(size=m)
        dt = float(rng.uniform(0, 0.002))
        qdd = accel_map @ wrench - bias + (contact if contacts else 0.0)
        ref_dq = dq + qdd * dt
        ref_q = q + ref_dq * dt
        ref_xd = jac @ ref_dq
        ref_x = integrate_pose(x_vt, ref_xd, dt, task)
        compiled.lmi_step(accel_map, bias, contact, jac, q, dq, x_vt, xd_vt, wrench, dt)
        np.testing.assert_allclose(dq, ref_dq, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(q, ref_q, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(xd_vt, ref_xd, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x_vt[:3], ref_x[:3], rtol=1e-13, atol=1e-13)
        if task is TaskSpace.SPATIAL:
            np.testing.assert_allclose(pin.exp3(x_vt[3:]), pin.exp3(ref_x[3:]), atol=1e-12)
        else:
            np.testing.assert_allclose(x_vt, ref_x, rtol=1e-13, atol=1e-13)


def test_a_controller_with_eq4_damping_or_stiffness_is_refused() -> None:
    from haptic_topology.control import HapticController
    g = ControlGains(np.ones(3), np.ones(3), 0.0, 0.0, b_d=np.eye(3))
    with pytest.raises(ValueError, match=r'gains.b_d and gains.k_d \(eq. 4\) must be zero'):
        HapticController(TaskSpace.PLANAR, ControlMode.PENALTY, g, np.eye(3), np.zeros((3, 3)))


@pytest.mark.parametrize('task', [TaskSpace.PLANAR, TaskSpace.SPATIAL])
def test_force_step_bounds_eq14_term_by_term(task: TaskSpace) -> None:
    rng = np.random.default_rng(40 + task.dim)
    m = task.dim
    for _ in range(200):
        m_d = np.diag(rng.uniform(0.1, 2.0, m))
        n = np.linalg.qr(rng.normal(size=(m, m)))[0][:, :2]
        projector = n @ n.T
        k_pc, b_pc = rng.uniform(0, 500, m), rng.uniform(0, 5, m)
        k_tc, b_tc = float(rng.uniform(0, 1e4)), float(rng.uniform(0, 100))
        pose, vt_pose = _pose(rng, task), _pose(rng, task)
        twist, vt_twist = rng.normal(size=m), rng.normal(size=m)
        dx = np.abs(pose_difference(pose, vt_pose, task))
        dv = np.abs(twist - vt_twist)
        ref = (k_pc * dx + b_pc * dv + np.abs(m_d @ projector @ (k_tc * dx + b_tc * dv))).max()
        got = compiled.force_step(m_d, projector, k_pc, b_pc, k_tc, b_tc, pose, twist,
                                  vt_pose, vt_twist)
        assert got == pytest.approx(ref, rel=1e-12, abs=1e-12)
