"""Device backends: registry by name, module:Class, the hardware stub, the simulated maglev."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_topology.device.backend import (
    BackendConfig,
    HardwareBackend,
    SimMaglevBackend,
    backend_class,
    create_backend,
)
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import DeviceError
from haptic_topology.sim.scenario import load_scenario

sys.path.insert(0, str(Path(__file__).parent))
import fake_backend


def _config(options: dict[str, object] | None = None) -> BackendConfig:
    sc = load_scenario('fig6')
    x0 = LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset
    return BackendConfig(sc.device, x0, dict(sc.user), options or {}, sc.source)


def test_builtin_names_resolve() -> None:
    assert backend_class('sim_maglev') is SimMaglevBackend
    assert backend_class('hardware') is HardwareBackend


def test_module_class_resolves_a_backend_outside_the_package() -> None:
    assert backend_class('fake_backend:CircleBackend') is fake_backend.CircleBackend


@pytest.mark.parametrize(('name', 'text'), [
    ('nope', "backend 'nope': unknown; expected one of hardware, sim_maglev"),
    ('fake_backend:Missing', "module 'fake_backend' has no 'Missing'"),
    ('no_such_module_xyz:Thing', "cannot import module 'no_such_module_xyz'"),
    ('fake_backend:NotABackend', 'is not a subclass of DeviceBackend'),
])
def test_bad_backend_names_are_refused_with_a_reason(name: str, text: str) -> None:
    with pytest.raises(DeviceError, match=re.escape(text)):
        backend_class(name)


def test_hardware_stub_refuses_to_activate_and_says_what_to_implement() -> None:
    hw = create_backend('hardware')
    hw.configure(_config())
    with pytest.raises(DeviceError) as err:
        hw.activate()
    msg = str(err.value)
    for word in ('DeviceBackend', 'configure()', 'write(u)', 'read(dt)', 'deactivate()',
                 'haptic_topology.device_backends'):
        assert word in msg


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
