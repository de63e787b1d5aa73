"""The backend conformance checks (``backend_conformance.py``, the same as for every backend)
for the ``haply`` backend: selected by its built-in name, against the Haply Inverse Service
emulator in another process; what reached the device is the emulator's own per-command log,
and ``settle`` watches its monitor stream. Planar (``fig8_point``, m = 2) and spatial
(``spatial_arm4_point``, m = 3) point tasks.

``stale_ms`` is 2 s here: these checks are about the driver's pipeline, and a stall of this
test process on a loaded machine must not trip it (staleness has tests of its own in
``test_haply_backend.py``). ``max_force`` is above the scenarios' limits and the vendor
layer's fade-in at the grasp is off (``grasp_ramp_ms: 0``; the driver's own watchdog ramp
stays), so what the device gets is exactly what the loop wrote.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from backend_conformance import CHECKS, Bench, Subject
from haply_harness import EmulatorDevice
from service_process import made_devices, paced

from haptic_topology.device.backend import backend_class
from haptic_topology.remote.haply import HaplyBackend
from haptic_topology.sim.scenario import load_scenario

OPTIONS = {'stale_ms': 2000.0, 'max_force': 1000.0, 'grasp_ramp_ms': 0.0}


@pytest.fixture
def device_factory(tmp_path: Path) -> Iterator[Callable[[str], EmulatorDevice]]:
    yield from made_devices(tmp_path, lambda d, scenario: EmulatorDevice(
        d, load_scenario(scenario).linkage.task.dim))


def test_haply_is_a_built_in_backend() -> None:
    assert backend_class('haply') is HaplyBackend


@pytest.mark.parametrize(('scenario', 'check'), [
    ('fig8_point', 'clamping'), ('fig8_point', 'nonfinite'), ('fig8_point', 'watchdog'),
    ('fig8_point', 'lifecycle'), ('spatial_arm4_point', 'clamping'),
    ('spatial_arm4_point', 'watchdog')])
def test_backend_conforms(scenario: str, check: str,
                          device_factory: Callable[[str], EmulatorDevice]) -> None:
    device = device_factory(scenario)
    opts: dict[str, Any] = {'port': device.port, **OPTIONS}
    bench = Bench(Subject('haply', lambda: device, opts, scenario, paced()), device)
    CHECKS[check](bench)
    out = device.emulator.output
    assert '"bad_messages": 0' in out and '"unknown_device": 0' in out, out
