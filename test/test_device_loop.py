"""DeviceLoop statistics: answered cycles and the longest run of consecutive misses."""

from __future__ import annotations

import numpy as np

from haptic_topology.control.laws import ControlMode
from haptic_topology.device.backend import BackendConfig, SimMaglevBackend
from haptic_topology.device.loop import DeviceLoop
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario


def _loop() -> DeviceLoop:
    sc = load_scenario('fig8')
    backend = SimMaglevBackend()
    backend.configure(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {},
                                    sc.source))
    backend.activate()
    return DeviceLoop(backend, sc.device.wrench_limit,
                      CommandWatchdog(WatchdogConfig(), sc.linkage.task.dim), sc.dt)


def test_longest_run_of_missed_cycles_is_counted() -> None:
    loop = _loop()
    dt, t = loop.period, 0.0
    zero = np.zeros(3)
    tick = loop.tick(t, dt)                       # idle; its answer engages the device
    loop.on_command(tick.seq, int(ControlMode.PENALTY), zero, t)
    t += dt
    tick = loop.tick(t, dt)                       # the run's first (resting) state
    # Each later tick checks whether the previous state was answered before it.
    pattern = [True] + [False] * 3 + [True] + [False] * 5 + [True, True]
    for answered in pattern:
        if answered:
            loop.on_command(tick.seq, int(ControlMode.PENALTY), zero, t)
        t += dt
        tick = loop.tick(t, dt)
    assert loop.expected == len(pattern)
    assert loop.answered == pattern.count(True)
    assert loop.max_missed_run == 5
    assert loop.missed_run == 0
    assert loop.figures()['max_consecutive_missed'] == 5.0
    assert loop.values(t)['max_consecutive_missed'] == '5'
