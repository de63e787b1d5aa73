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
    """``sim_maglev`` is in the registry; ``ros_topics`` and ``network`` are named there as
    ``module:Class`` and imported when selected (the ROS one needs rclpy, which the core does
    not import: test_core_imports.py)."""
    assert backend_class('sim_maglev') is SimMaglevBackend
    assert BUILTIN_BACKENDS['ros_topics'] == 'haptic_topology.nodes.topic_backend:RosTopicBackend'
    for name in ('ros_topics', 'network'):
        cls = backend_class(name)
        assert cls.name == name and cls.__module__ == str(BUILTIN_BACKENDS[name]).split(':')[0]


def test_module_class_resolves_a_backend_outside_the_package() -> None:
    assert backend_class('fake_backend:CircleBackend') is fake_backend.CircleBackend


@pytest.mark.parametrize(('name', 'text'), [
    ('nope', "backend 'nope': unknown; expected one of network, ros_topics, sim_maglev"),
    # the placeholder of earlier versions is gone (README: "Bring your own device")
    ('hardware', "backend 'hardware': unknown; expected one of network, ros_topics, "),
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
