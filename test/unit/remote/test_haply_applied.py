"""What the ``haply`` backend says it sent (``written``, the loop's ``applied``: the states',
bags' and traces') against what the Haply Inverse Service emulator received: zero while the
VerseGrip's engage button is up, the faded force while the grasp fades in, the command once
faded in. Waits are on conditions with deadlines; no timing is asserted."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from haply_harness import Emulator, read_log

from haptic_topology.device.backend import BackendConfig, create_backend
from haptic_topology.remote.haply import HaplyBackend
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

WAIT = 60.0


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[Emulator]:
    e = Emulator(tmp_path / 'e', ('--grip', '61548', '--press', 'a@100-300'))
    yield e
    e.kill()


def _subsequence(sent: list[float], written: list[float]) -> bool:
    """Whether ``sent`` is ``written`` with some entries left out (a throttled cycle sends
    nothing), in order."""
    it = iter(written)
    return all(any(s == w for w in it) for s in sent)


def test_written_is_what_the_service_got(emulator: Emulator) -> None:
    """``engage_button: 0``, ``grasp_ramp_ms: 10``, the grip's button held from the
    emulator's message 100 to 300, the loop writing 0.5 N along x every cycle: ``written``
    is 0 while the button is up, a fraction of 0.5 while the grasp fades in, 0.5 after; and
    the forces the service received are those, in order."""
    sc = load_scenario('fig8_point')
    b = create_backend('haply')
    assert isinstance(b, HaplyBackend)
    b.configure(BackendConfig(sc.device, initial_device_pose(sc), {},
                              {'port': emulator.port, 'engage_button': 0,
                               'grasp_ramp_ms': 10.0, 'max_in_flight': 64}, sc.source))
    b.activate()
    u = np.array([0.5, 0.0])
    written: list[np.ndarray] = []
    deadline = time.monotonic() + WAIT
    while b.states < 400:
        assert time.monotonic() < deadline
        b.write(u)
        written.append(b.written(u).copy())
        b.read(0.001)
        time.sleep(0.0005)
    b.deactivate()
    emulator.stop()
    _, _, f = read_log(emulator.log)
    wx = [float(w[0]) for w in written]
    assert all(w[1] == 0.0 for w in written)
    assert wx[0] == 0.0 and wx[-1] == 0.0, 'applied while the button is up'
    fading = [w for w in wx if 0.0 < w < 0.5]
    assert fading and 0.5 in wx, 'no fade-in, or never the whole command'
    # The service got: activation's zero, then what was written (a throttled cycle: nothing),
    # then deactivation's zero and the idle on close.
    assert _subsequence([float(x) for x in f[1:, 0]], [*wx, 0.0, 0.0]), (f[:, 0], wx)
