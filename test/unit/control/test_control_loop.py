"""ControllerLoop: what reaches the VE while the sync guard fades the device's force."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.control.loop import StateSample
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.sim.lockstep import build_controller_loop
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import ControlMode, DeviceStatus


@pytest.mark.parametrize('vt_coupling', [True, False])
def test_coupling_sent_to_the_ve_fades_with_the_device_force(vt_coupling: bool) -> None:
    """Fresh model: the hand input carries the law's F_pc and F_vt = F_h - F_pc. Updates
    stop for longer than ``degrade_after`` + ``ramp_time``: the device force fades to zero
    and so does the coupling the VE is given (F_vt = F_h), although the stale local model's
    own F_pc is not zero. Without VT coupling the VE gets F_h throughout."""
    sc = replace(load_scenario('fig8'), vt_coupling=vt_coupling)
    loop = build_controller_loop(sc, ControlMode.PENALTY)
    dyn = LinkageDynamics(sc.linkage)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step)
    loop.on_update(ve.snapshot(seq=0))
    pose = dyn.hand_pose(sc.q0) + np.array([0.01, -0.005, 0.0])   # 1 cm off the VT
    f_h = np.array([0.5, 0.2, 0.0])
    twist = np.zeros(3)
    dt = sc.dt
    first = loop.on_state(StateSample(1, 0.0, pose, twist, f_h, int(DeviceStatus.OK)))
    assert first is not None and first.hand is not None
    np.testing.assert_array_equal(first.hand.coupling, first.out.coupling)
    np.testing.assert_array_equal(first.hand.vt_wrench,
                                  f_h - first.out.coupling if vt_coupling else f_h)
    assert np.linalg.norm(first.out.coupling) > 1.0
    loop.guard.update_arrived(0.0)     # an update at t = 0, then none
    cfg = loop.guard.config
    n = int((cfg.degrade_after + 2 * cfg.ramp_time) / dt) + 1
    ans = first
    for k in range(2, n + 2):
        ans = loop.on_state(StateSample(k, (k - 1) * dt, pose, twist, f_h,
                                        int(DeviceStatus.OK)))
        assert ans is not None and ans.hand is not None
    assert loop.guard.scale == 0.0
    np.testing.assert_array_equal(ans.out.wrench, np.zeros(3))
    assert np.linalg.norm(ans.out.coupling) > 0.1        # the stale model's own spring
    np.testing.assert_array_equal(ans.hand.coupling, np.zeros(3))
    np.testing.assert_array_equal(ans.hand.vt_wrench, f_h)


def test_late_states_do_not_make_the_local_model_unstable() -> None:
    """States 40 ms apart (a loaded machine): eq. 17 stepped with the coordination spring held
    over 40 ms is unstable for the circle scenario's rotation axis (b' ~ 72 1/s), so the
    step is cut to the model's stable step and the VT settles at the device."""
    sc = load_scenario('circle')
    assert sc.vt_coupling
    loop = build_controller_loop(sc, ControlMode.PENALTY)
    dyn = LinkageDynamics(sc.linkage)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step)
    loop.on_update(ve.snapshot(seq=0))
    stable = loop.ctrl.stable_dt
    assert 0.005 < stable < 0.04
    pose = dyn.hand_pose(sc.q0) + np.array([0.005, 0.0, 0.05])
    zero = np.zeros(3)
    late = 0.04
    for k in range(1, 401):
        ans = loop.on_state(StateSample(k, (k - 1) * late, pose, zero, zero,
                                        int(DeviceStatus.OK)))
        assert ans is not None
        assert np.all(np.isfinite(ans.out.vt_pose))
    assert loop.dt_capped == 399
    assert np.abs(ans.out.vt_pose - pose).max() < 0.05


def test_stable_step_bound_matches_the_recurrence() -> None:
    """The bound behind ``stable_dt``: semi-implicit Euler on x'' = -k x - b x' has spectral
    radius < 1 just below (-b + sqrt(b^2 + 4k)) / k and > 1 just above it."""
    for k, b in ((96.0, 72.0), (1e4, 10.0), (5.0, 300.0)):
        limit = (-b + np.sqrt(b * b + 4.0 * k)) / k

        def radius(dt: float, k: float = k, b: float = b) -> float:
            step = np.array([[1.0 - k * dt * dt, dt * (1.0 - b * dt)], [-k * dt, 1.0 - b * dt]])
            return float(np.abs(np.linalg.eigvals(step)).max())

        assert radius(0.99 * limit) < 1.0 < radius(1.01 * limit)
