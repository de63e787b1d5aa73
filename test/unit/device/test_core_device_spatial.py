"""6-DOF simulated device (eq. 9 with a 6 x 6 inertia, stops, saturation) and the realism
options of the simulated maglev (sensor, velocity estimate, delay, friction)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

from haptic_topology.device import DeviceParams, MaglevModel
from haptic_topology.device.backend import BackendConfig, SimMaglevBackend
from haptic_topology.device.maglev import (
    DeviceRealism,
    PositionSensor,
    VelocitySource,
    device_from_config,
)
from haptic_topology.errors import ConfigError
from haptic_topology.vocabulary import DeviceStatus, TaskSpace

S = TaskSpace.SPATIAL
DT = 1e-3
# A 6 x 6 inertia with translation-rotation coupling (kg, kg m, kg m^2), symmetric and
# positive definite.
M6 = np.array([[2.0, 0.1, 0.0, 0.0, 0.02, 0.0],
               [0.1, 1.5, 0.0, -0.02, 0.0, 0.0],
               [0.0, 0.0, 1.0, 0.0, 0.0, 0.01],
               [0.0, -0.02, 0.0, 0.01, 0.0, 0.0],
               [0.02, 0.0, 0.0, 0.0, 0.02, 0.0],
               [0.0, 0.0, 0.01, 0.0, 0.0, 0.03]])


def _spatial(**kw: Any) -> DeviceParams:
    inf = np.full(6, np.inf)
    base = DeviceParams(S, M6, np.zeros((6, 6)), -inf, inf, np.full(6, 100.0))
    return replace(base, **kw)


def test_eq9_with_a_6x6_inertia_under_a_constant_wrench() -> None:
    """From rest, a constant wrench F gives xdd = M_d^-1 F (eq. 9 with C_d = 0): after T
    seconds the twist is T M_d^-1 F, the translation T^2/2 M_d^-1 F (semi-implicit Euler:
    T^2/2 (1 + dt/T)), and the orientation the rotation vector of T^2/2 times the angular
    acceleration (a constant axis here)."""
    f = np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.0])
    f[3:] = 0.0
    acc = np.linalg.solve(M6, f)
    dev = MaglevModel(_spatial(), np.zeros(6))
    n = 500
    for _ in range(n):
        assert dev.step(np.zeros(6), f, DT) == DeviceStatus.OK
    t = n * DT
    np.testing.assert_allclose(dev.twist, acc * t, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(dev.pose[:3], acc[:3] * t * t / 2 * (1 + DT / t), rtol=1e-9)
    # The coupling makes a pure force turn the device: the angular acceleration is constant,
    # so the rotation is about one world axis.
    assert np.linalg.norm(acc[3:]) > 0.1
    np.testing.assert_allclose(dev.pose[3:], acc[3:] * t * t / 2 * (1 + DT / t), rtol=1e-9)


def test_spatial_translation_stops_and_orientation_cone() -> None:
    params = _spatial(mass=np.eye(6) * 0.1,
                      workspace_lo=np.array([-0.01, -0.01, -0.01, -np.inf, -np.inf, -np.inf]),
                      workspace_hi=np.array([0.01, 0.01, 0.01, np.inf, np.inf, np.inf]),
                      max_angle=0.2)
    start = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3])   # 0.3 rad about z: the cone's centre
    dev = MaglevModel(params, start)
    w = np.array([0.0, 0.0, 1.0, 0.05, 0.0, 0.0])       # push up and tilt about x
    status = DeviceStatus.OK
    for _ in range(2000):
        status = dev.step(w, np.zeros(6), DT)
    assert status & DeviceStatus.WORKSPACE_LIMIT
    assert dev.pose[2] == 0.01 and dev.twist[2] == 0.0
    away = pin.log3(pin.exp3(dev.pose[3:]) @ pin.exp3(start[3:]).T)
    assert np.linalg.norm(away) == pytest.approx(0.2, abs=1e-9)
    np.testing.assert_allclose(away / np.linalg.norm(away), [1.0, 0.0, 0.0], atol=1e-9)
    assert abs(dev.twist[3]) < 1e-12          # no angular velocity out of the cone


def test_force_and_torque_saturation() -> None:
    limit = np.array([1.0, 1.0, 1.0, 0.01, 0.01, 0.01])
    dev = MaglevModel(_spatial(wrench_limit=limit), np.zeros(6))
    assert dev.step(np.array([5.0, 0, 0, 0, 0, -0.5]), np.zeros(6), DT) == DeviceStatus.SATURATED
    np.testing.assert_array_equal(dev.applied, [1.0, 0, 0, 0, 0, -0.01])
    assert dev.step(np.array([0.5, 0, 0, 0, 0, 0.005]), np.zeros(6), DT) == DeviceStatus.OK


def _block(**extra: Any) -> dict[str, Any]:
    return {'mass': [1.0] * 6, **extra}


def test_spatial_device_block_is_parsed_and_checked() -> None:
    params, _ = device_from_config(_block(
        mass=M6.tolist(), workspace={'lo': [-0.1, -0.1, 0.0], 'hi': [0.1, 0.1, 0.2],
                                     'max_angle': 'pi/8'}), 'f: scenario.device', S)
    np.testing.assert_array_equal(params.mass, M6)
    assert params.max_angle == pytest.approx(math.pi / 8)
    assert np.all(np.isinf(params.workspace_lo[3:]))
    assert params.realism.is_ideal
    bad = [
        ({'workspace': {'lo': [0] * 6, 'hi': [1] * 6}},
         r'workspace.lo: a spatial device takes 3 translation stops'),
        ({'workspace': {'max_angle': 4.0}}, r'workspace.max_angle: expected a value <= 3.14159'),
        ({'workspace': {'lo': [0, 0, 0]}}, r'workspace: give both lo and hi'),
        ({'mass': [[1, 0.5], [0.5, 1]]}, r'mass: expected 6 rows of 6 numbers'),
        ({'mass': np.diag([-1.0, 1, 1, 1, 1, 1]).tolist()}, r'mass: expected a positive '
                                                             r'definite matrix'),
        ({'mass': (np.eye(6) + np.eye(6, k=1)).tolist()}, r'mass: expected a symmetric'),
    ]
    for extra, msg in bad:
        with pytest.raises(ConfigError, match=r'f: scenario\.device\.' + msg):
            device_from_config(_block(**extra), 'f: scenario.device', S)


def test_the_simulated_device_refuses_to_start_beyond_its_stops() -> None:
    """A start outside ``workspace.lo``/``hi`` or farther than ``max_angle`` from ``center``
    is refused in one line naming the coordinate (at the stop is a valid start)."""
    params, _ = device_from_config(_block(workspace={
        'lo': [-0.1, -0.1, 0.0], 'hi': [0.1, 0.1, 0.2], 'max_angle': 0.3,
        'center': [0.0, 0.0, 0.0]}), 'f: scenario.device', S)

    def start(pose: list[float]) -> None:
        SimMaglevBackend().configure(BackendConfig(params, np.array(pose), {
            'type': 'constant_wrench', 'wrench': [0.0] * 6}, {}, 'f.yaml'))

    start([0.1, -0.1, 0.0, 0.0, 0.3, 0.0])                  # on the stops: fine
    with pytest.raises(ConfigError, match=r'^f\.yaml: the device would start at pose\[2\] = '
                       r'0\.25, outside device\.workspace \[lo, hi\] = \[0, 0\.2\] \(the VT '
                       r'hand at scenario\.q0 plus device\.offset\)'):
        start([0.0, 0.0, 0.25, 0.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match=r'start 0\.4 rad from device\.workspace\.center, '
                       r'beyond max_angle = 0\.3 rad'):
        start([0.0, 0.0, 0.1, 0.4, 0.0, 0.0])


@pytest.mark.parametrize(('extra', 'msg'), [
    ({'sensor': {'quantization': [1e-6, 1e-6]}}, r'sensor\.quantization: expected 3'),
    ({'sensor': {'noise_std': [-1.0, 0, 0]}}, r'sensor\.noise_std\[0\]: expected a value >= 0'),
    ({'sensor': {'seed': 1.5}}, r'sensor\.seed: expected an integer'),
    ({'sensor': {'velocity': 'kalman'}}, r'sensor\.velocity: expected one of model, '
                                        r'difference'),
    ({'sensor': {'velocity_cutoff_hz': 50}}, r'sensor\.velocity_cutoff_hz: only used with '
                                            r'velocity: difference'),
    ({'sensor': {'velocity': 'difference', 'velocity_cutoff_hz': -1}},
     r'sensor\.velocity_cutoff_hz: expected'),
    ({'actuation_delay': 2}, r'actuation_delay: expected an integer <= 1'),
    ({'friction': {'viscous': [1, 1, -1]}}, r'friction\.viscous\[2\]: expected a value >= 0'),
    ({'friction': {'stiction': [1, 1, 1]}},
     r'friction\.stiction: unknown key \(expected one of: coulomb, viscous\)'),
    ({'sensor': {'bias': 1}}, r'sensor\.bias: unknown key'),
])
def test_realism_options_are_validated_by_field(extra: dict[str, Any], msg: str) -> None:
    with pytest.raises(ConfigError, match=r'f: scenario\.device\.' + msg):
        device_from_config(extra, 'f: scenario.device', TaskSpace.PLANAR)


def _planar(**realism: Any) -> DeviceParams:
    params, _ = device_from_config({'mass': [1.0, 1.0, 0.01], **realism}, 'd',
                                   TaskSpace.PLANAR)
    return params


def _run_backend(params: DeviceParams, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Reported poses and twists (rows: idle, then n cycles) of a simulated maglev pushed by
    a constant 0.4 N along x (the paper's user)."""
    b = SimMaglevBackend()
    b.configure(BackendConfig(params, np.zeros(3), {'type': 'constant_wrench',
                                                    'wrench': [0.4, 0.0, 0.0]}))
    b.activate()
    first = b.idle(DT)
    poses, twists = [first.pose], [first.twist]
    for _ in range(n):
        b.write(np.zeros(3))
        r = b.read(DT)
        poses.append(r.pose)
        twists.append(r.twist)
    return np.array(poses), np.array(twists)


def test_defaults_are_the_ideal_device() -> None:
    poses, twists = _run_backend(_planar())
    model = MaglevModel(_planar(), np.zeros(3))
    for k in range(1, len(poses)):
        model.step(np.zeros(3), np.array([0.4, 0.0, 0.0]), DT)
        np.testing.assert_array_equal(poses[k], model.pose)
        np.testing.assert_array_equal(twists[k], model.twist)


def test_quantization_rounds_the_reported_pose_to_counts() -> None:
    q = 1e-5
    poses, _ = _run_backend(_planar(sensor={'quantization': [q, q, 0.0]}))
    true, _ = _run_backend(_planar())
    np.testing.assert_allclose(poses[:, :2] / q, np.round(true[:, :2] / q), atol=1e-6)
    np.testing.assert_array_equal(poses[:, 2], true[:, 2])
    assert np.abs(poses[:, 0] - true[:, 0]).max() > 0.1 * q


def test_noise_is_seeded_and_deterministic() -> None:
    noisy = _planar(sensor={'noise_std': [1e-5, 1e-5, 0.0], 'seed': 7})
    a, b = _run_backend(noisy)[0], _run_backend(noisy)[0]
    c = _run_backend(_planar(sensor={'noise_std': [1e-5, 1e-5, 0.0], 'seed': 8}))[0]
    true = _run_backend(_planar())[0]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert 0.8e-5 < float(np.std(a[:, 0] - true[:, 0])) < 1.2e-5
    np.testing.assert_array_equal(a[:, 2], true[:, 2])


def test_velocity_from_positions_lags_the_true_velocity() -> None:
    """Under a constant acceleration a = 0.4 m/s^2 the backward difference of the poses is the
    model's velocity (semi-implicit Euler: x_k = x_{k-1} + v_k dt) and the first-order filter
    (a = 1 - exp(-2 pi f_c dt)) lags a ramp by dt (1 - a) / a, about 1/(2 pi f_c) - dt/2."""
    fc = 50.0
    est = _run_backend(_planar(sensor={'velocity': 'difference', 'velocity_cutoff_hz': fc}))[1]
    ideal = _run_backend(_planar())[1]
    alpha = 1.0 - math.exp(-2 * math.pi * fc * DT)
    acc = 0.4
    k = 300
    lag = (ideal[k, 0] - est[k, 0]) / acc
    assert lag == pytest.approx(DT * (1 - alpha) / alpha, rel=1e-6)
    assert lag == pytest.approx(1 / (2 * math.pi * fc) - DT / 2, rel=0.02)
    unfiltered = _run_backend(_planar(sensor={'velocity': 'difference',
                                              'velocity_cutoff_hz': 0.0}))[1]
    np.testing.assert_allclose(unfiltered[2:], ideal[2:], rtol=1e-9, atol=1e-12)


def test_actuation_delay_applies_the_previous_command() -> None:
    params = _planar(actuation_delay=1)
    dev = MaglevModel(params, np.zeros(3))
    dev.step(np.array([1.0, 0.0, 0.0]), np.zeros(3), DT)
    np.testing.assert_array_equal(dev.applied, [0.0, 0.0, 0.0])
    assert np.all(dev.twist == 0.0)
    dev.step(np.array([2.0, 0.0, 0.0]), np.zeros(3), DT)
    np.testing.assert_array_equal(dev.applied, [1.0, 0.0, 0.0])


def test_viscous_friction_gives_the_terminal_velocity() -> None:
    """``M xdd = F - b xd`` -> ``xd -> F / b`` (0.4 N / 2 N s/m = 0.2 m/s)."""
    dev = MaglevModel(_planar(friction={'viscous': [2.0, 0.0, 0.0]}), np.zeros(3))
    for _ in range(10000):   # 20 time constants M / b
        dev.step(np.zeros(3), np.array([0.4, 0.0, 0.0]), DT)
    assert dev.twist[0] == pytest.approx(0.2, rel=1e-7)


def test_coulomb_friction_sticks_below_and_slides_above_its_bound() -> None:
    dev = MaglevModel(_planar(friction={'coulomb': [0.5, 0.5, 0.0]}), np.zeros(3))
    for _ in range(1000):
        dev.step(np.zeros(3), np.array([0.4, 0.6, 0.0]), DT)
    assert dev.twist[0] == 0.0 and dev.pose[0] == 0.0          # 0.4 N < 0.5 N: sticks
    assert dev.twist[1] == pytest.approx(0.1, rel=1e-9)        # (0.6 - 0.5) N / 1 kg x 1 s


def test_sensor_without_options_reports_the_truth() -> None:
    sensor = PositionSensor(DeviceParams.unlimited(S))
    pose, twist = np.arange(6.0), np.ones(6)
    p, v = sensor.measure(pose, twist, DT)
    np.testing.assert_array_equal(p, pose)
    np.testing.assert_array_equal(v, twist)
    assert DeviceRealism().is_ideal and DeviceRealism().labels() == []
    assert DeviceRealism(velocity=VelocitySource.DIFFERENCE).labels() == [
        'velocity from positions']
