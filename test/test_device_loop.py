"""DeviceLoop statistics: answered cycles and the longest run of consecutive misses."""

from __future__ import annotations

import numpy as np

from haptic_topology.control.laws import ControlMode
from haptic_topology.sim.lockstep import build_device_loop
from haptic_topology.sim.scenario import load_scenario


def test_longest_run_of_missed_cycles_is_counted() -> None:
    loop = build_device_loop(load_scenario('fig8'))
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
