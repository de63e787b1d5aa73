"""The backend conformance checks (``backend_conformance.py``, the same as for the simulated
maglev, the example backend and ``ros_topics``) for the ``network`` backend: selected by its
built-in name, against ``haptic-topology device-server`` in another process; what reached the
device is the server's own per-cycle log, and ``settle`` watches its monitor stream.

Twice: over the loopback directly, and through the fault-injecting relay of
``network_harness.py`` (drops, duplicates, reorders, delays by 3 ms, corrupts, NaNs and
truncates datagrams by index, both ways), with the same checks and assertions: what the
device gets is the same whether or not the network between them misbehaves.

The device's own timeouts (its command timeout, each command's ttl, the backend's
``stale_ms``) are set to 2 s here: these checks are about the driver's pipeline, and a stall
of this test process on a loaded machine must not trip them (it would make the device output
zero in the middle of a fade: safe, but not what a check expects). Those timeouts have tests
of their own in ``test_device_network.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from backend_conformance import CHECKS, Bench, Subject
from network_harness import MALFORMING, Relay, ServerDevice, wait_for
from service_process import made_devices, paced

from haptic_topology.device.backend import backend_class
from haptic_topology.remote.network import NetworkBackend

#: Generous device timeouts (module doc).
OPTIONS = {'stale_ms': 2000.0, 'command_ttl_ms': 2000.0}
SERVER = ('--command-timeout-ms', '2000')


@pytest.fixture
def device_factory(tmp_path: Path) -> Iterator[Callable[[str], ServerDevice]]:
    yield from made_devices(
        tmp_path, lambda d, scenario: ServerDevice(d, scenario, SERVER))


def test_network_is_a_built_in_backend() -> None:
    assert backend_class('network') is NetworkBackend


@pytest.mark.parametrize(('scenario', 'check'), [
    ('fig8', 'clamping'), ('fig8', 'nonfinite'), ('fig8', 'watchdog'), ('fig8', 'lifecycle'),
    ('spatial_arm4', 'clamping'), ('spatial_arm4', 'watchdog')])
def test_backend_conforms(scenario: str, check: str,
                          device_factory: Callable[[str], ServerDevice]) -> None:
    device = device_factory(scenario)
    opts: dict[str, Any] = {'port': device.port, **OPTIONS}
    bench = Bench(Subject('network', lambda: device, opts, scenario, paced()), device)
    CHECKS[check](bench)
    res = device.result
    assert res is not None and res.returncode == 0, res
    c = res.counters
    assert c['malformed'] == c['foreign'] == c['duplicate'] == c['late'] == 0
    assert c['releases'] >= 1


@pytest.mark.parametrize('check', sorted(CHECKS))
def test_backend_conforms_through_a_faulty_network(
        check: str, device_factory: Callable[[str], ServerDevice]) -> None:
    device = device_factory('fig8')
    relay = Relay(('127.0.0.1', device.port))
    try:
        opts: dict[str, Any] = {'port': relay.port, **OPTIONS}
        bench = Bench(Subject('network', lambda: device, opts, 'fig8', paced()), device)
        CHECKS[check](bench)
        wait_for(lambda: relay.idle, 5.0, 'the relay to flush what it held')
    finally:
        relay.stop()
    res = device.result
    assert res is not None and res.returncode == 0, res
    c, a = res.counters, relay.c2s.actions
    assert c['malformed'] <= sum(a[k] for k in MALFORMING)
    assert c['duplicate'] <= a['duplicate'] and c['foreign'] == 0
    if relay.c2s.index >= 50:           # a full pattern went through: each kind happened
        assert min(a.values()) >= 1 and c['malformed'] >= 1
    # no spoiled command was applied: every applied (session, seq) reached the server intact
    applied = {(int(s), int(q)) for s, q in zip(res.session, res.seq, strict=True) if q}
    assert applied and not applied & relay.c2s.spoiled
