"""Device model of eq. 9: dynamics, hard stops, saturation (planar and spatial)."""

from __future__ import annotations

import numpy as np

from haptic_topology.device import (
    ConstantWrenchUser,
    DeviceParams,
    MaglevModel,
    SpringDamperUser,
    TargetPath,
    saturate,
)
from haptic_topology.vocabulary import DeviceStatus, TaskSpace


def test_free_device_follows_eq9() -> None:
    params = DeviceParams(TaskSpace.PLANAR, np.diag([2.0, 2.0, 0.5]), np.diag([1.0, 0, 0]),
                          np.full(3, -np.inf), np.full(3, np.inf), np.full(3, 100.0))
    dev = MaglevModel(params, np.zeros(3))
    f_h, u = np.array([0.4, 0.0, 0.0]), np.array([0.0, 0.2, 0.05])
    for _ in range(1000):
        assert dev.step(u, f_h, 1e-3) == DeviceStatus.OK
    # x: M xdd + C xd = F -> xd -> F/C (1 - exp(-C t / M)); y, theta: constant acceleration
    np.testing.assert_allclose(dev.twist[0], 0.4 * (1 - np.exp(-0.5)), rtol=1e-3)
    np.testing.assert_allclose(dev.twist[1:], [0.1, 0.1], rtol=1e-9)
    np.testing.assert_allclose(dev.pose[1], 0.5 * 0.1 * 1.0, rtol=2e-3)


def test_hard_stop_and_saturation_are_reported() -> None:
    params = DeviceParams(TaskSpace.PLANAR, np.eye(3), np.zeros((3, 3)),
                          np.array([-0.01, -1, -1]), np.array([0.01, 1, 1]),
                          np.array([1.0, 1.0, 0.1]))
    dev = MaglevModel(params, np.zeros(3))
    status = DeviceStatus.OK
    for _ in range(500):
        status = dev.step(np.array([5.0, 0.0, 0.0]), np.zeros(3), 1e-3)
    assert status == DeviceStatus.SATURATED | DeviceStatus.WORKSPACE_LIMIT
    assert dev.pose[0] == 0.01 and dev.twist[0] == 0.0
    np.testing.assert_array_equal(dev.applied, [1.0, 0.0, 0.0])


def test_saturate_never_passes_non_finite_values() -> None:
    w, sat = saturate(np.array([np.nan, np.inf, -3.0, 0.5]), np.full(4, 1.0))
    np.testing.assert_array_equal(w, [0.0, 0.0, -1.0, 0.5])
    assert sat
    w, sat = saturate(np.array([0.2, -0.3]), np.full(2, 1.0))
    assert not sat


def test_spatial_device_rotates_about_the_world_axis() -> None:
    dev = MaglevModel(DeviceParams.unlimited(TaskSpace.SPATIAL, mass=1.0), np.zeros(6),
                      twist=np.array([0, 0, 0, 0, 0, np.pi / 2]))
    for _ in range(1000):
        dev.step(np.zeros(6), np.zeros(6), 1e-3)
    np.testing.assert_allclose(dev.pose[3:], [0, 0, np.pi / 2], atol=1e-9)


def test_users() -> None:
    assert ConstantWrenchUser(np.array([0.4, 0, 0])).wrench(3.0, np.ones(3), np.ones(3))[0] == 0.4
    path = TargetPath('circle', np.zeros(3), np.zeros(3), radius=0.01, period=2.0)
    user = SpringDamperUser(path, np.full(3, 100.0), np.zeros(3), TaskSpace.PLANAR)
    np.testing.assert_allclose(user.wrench(0.5, np.zeros(3), np.zeros(3)), [0.0, 1.0, 0.0],
                               atol=1e-12)
