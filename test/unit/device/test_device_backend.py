"""Device backends: registry by name (built-in, lazily imported built-in, module:Class), the
simulated maglev."""

from __future__ import annotations

import re

import fake_backend
import numpy as np
import pytest

from haptic_topology.device.backend import (
    BUILTIN_BACKENDS,
    BackendConfig,
    SimMaglevBackend,
    backend_class,
    create_backend,
)
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import DeviceError
from haptic_topology.sim.scenario import load_scenario


def _config(options: dict[str, object] | None = None) -> BackendConfig:
    sc = load_scenario('fig6')
    x0 = LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset
    return BackendConfig(sc.device, x0, dict(sc.user), options or {}, sc.source)


def test_builtin_names_resolve() -> None:
    """``sim_maglev`` is in the registry; ``ros_topics``, ``network``, ``openhaptics`` and
    ``haply`` are named there as ``module:Class`` and imported when selected (the ROS one
    needs rclpy, which the core does not import: test_core_imports.py)."""
    assert backend_class('sim_maglev') is SimMaglevBackend
    assert BUILTIN_BACKENDS['ros_topics'] == 'haptic_topology.nodes.topic_backend:RosTopicBackend'
    for name in ('ros_topics', 'network', 'openhaptics', 'haply'):
        cls = backend_class(name)
        assert cls.name == name and cls.__module__ == str(BUILTIN_BACKENDS[name]).split(':')[0]


def test_module_class_resolves_a_backend_outside_the_package() -> None:
    assert backend_class('fake_backend:CircleBackend') is fake_backend.CircleBackend


@pytest.mark.parametrize(('name', 'text'), [
    ('nope', "backend 'nope': unknown; expected one of forcedimension, "
             'forcedimension_emulator, haply, network, openhaptics, ros_topics, sim_maglev'),
    # the placeholder of earlier versions is gone (README: "Bring your own device")
    ('hardware', "backend 'hardware': unknown; expected one of forcedimension, "),
    ('fake_backend:Missing', "module 'fake_backend' has no 'Missing'"),
    ('no_such_module_xyz:Thing', "cannot import module 'no_such_module_xyz'"),
    ('fake_backend:NotABackend', 'is not a subclass of DeviceBackend'),
])
def test_bad_backend_names_are_refused_with_a_reason(name: str, text: str) -> None:
    with pytest.raises(DeviceError, match=re.escape(text)):
        backend_class(name)


def test_sim_maglev_parks_until_engaged_then_follows_eq9() -> None:
    be = create_backend('sim_maglev')
    cfg = _config()
    be.configure(cfg)
    be.activate()
    first = be.idle(0.001)
    again = be.idle(0.05)
    np.testing.assert_array_equal(first.pose, cfg.initial_pose)
    np.testing.assert_array_equal(again.pose, cfg.initial_pose)   # parked: no integration
    np.testing.assert_allclose(first.hand_wrench, [0.4, 0.0, 0.0])
    be.write(np.zeros(3))
    r = be.read(0.001)
    # M_d = I, u = 0, F_h = 0.4 N along x: xd = 0.4 * dt after one semi-implicit step.
    np.testing.assert_allclose(r.twist, [0.4e-3, 0.0, 0.0])
    np.testing.assert_allclose(r.pose - cfg.initial_pose, [0.4e-6, 0.0, 0.0], atol=1e-12)


def test_sim_maglev_refuses_options() -> None:
    with pytest.raises(DeviceError, match='backend_options: expected none'):
        create_backend('sim_maglev').configure(_config({'port': 1}))


def _realistic_circle() -> BackendConfig:
    """circle's device and user with every sensor and actuator imperfection on (noise from a
    generator, quantization, a filtered differenced velocity, a one-cycle actuation delay),
    so that every piece of state a resumed device needs is exercised."""
    from dataclasses import replace

    from haptic_topology.device.maglev import DeviceRealism, VelocitySource
    from haptic_topology.sim.lockstep import initial_device_pose

    sc = load_scenario('circle')
    realism = DeviceRealism(quantization=np.full(3, 1e-6), noise_std=np.full(3, 2e-6),
                            seed=7, velocity=VelocitySource.DIFFERENCE,
                            velocity_cutoff_hz=200.0, actuation_delay=1)
    return BackendConfig(replace(sc.device, realism=realism), initial_device_pose(sc),
                         dict(sc.user), {}, sc.source)


def _drive(be: SimMaglevBackend, cycles: int, k0: int) -> list[np.ndarray]:
    """``cycles`` engaged cycles with a wrench that changes every cycle; each reading as one
    array (pose, twist, hand wrench)."""
    out = []
    for k in range(k0, k0 + cycles):
        be.write(np.array([0.3 * np.sin(0.01 * k), -0.2 * np.cos(0.013 * k), 0.01]))
        r = be.read(0.001)
        out.append(np.concatenate((r.pose, r.twist, r.hand_wrench)))
    return out


def test_sim_maglev_resumed_from_its_carry_over_continues_bit_for_bit() -> None:
    """What the loop process does at each activation (a new backend in a new process):
    configured the same and resumed from the last one's ``carry_over`` after ``deactivate``,
    the device continues exactly as the same instance activated again would (its pose, its
    sensor's noise and filter, the delayed wrench, the user's clock), and not from the
    scenario's initial pose."""
    cfg = _realistic_circle()
    kept = SimMaglevBackend()
    kept.configure(cfg)
    kept.activate()
    _drive(kept, 300, 0)
    kept.write(np.zeros(3))
    kept.deactivate()
    carried = kept.carry_over()

    resumed = SimMaglevBackend()
    resumed.configure(cfg)
    resumed.resume(carried)
    kept.activate()
    resumed.activate()
    parked = resumed.idle(0.001).pose
    assert np.linalg.norm(parked[:2] - cfg.initial_pose[:2]) > 1e-3   # it had moved
    np.testing.assert_array_equal(parked, kept.idle(0.001).pose)
    np.testing.assert_array_equal(_drive(resumed, 200, 300), _drive(kept, 200, 300))


def test_sim_maglev_refuses_a_carried_state_of_another_task() -> None:
    planar = SimMaglevBackend()
    planar.configure(_config())
    spatial = create_backend('sim_maglev')
    sc = load_scenario('spatial_arm4')
    from haptic_topology.sim.lockstep import initial_device_pose
    spatial.configure(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {},
                                    sc.source))
    with pytest.raises(DeviceError, match='a carried state of task dimension 3, configured '
                                          'for 6'):
        spatial.resume(planar.carry_over())


def test_a_backend_without_state_to_carry_refuses_resume() -> None:
    be = fake_backend.CircleBackend()
    assert be.carry_over() is None
    with pytest.raises(DeviceError, match=r'resume\(\): this backend carries no state over'):
        be.resume(b'')
