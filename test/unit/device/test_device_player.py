"""The device ``topic_device`` plays (:class:`~haptic_topology.device.player.DevicePlayer`):
when it unparks, with and without a published hand wrench."""

from __future__ import annotations

import numpy as np

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.player import DevicePlayer
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

MS = 1_000_000


def _player(hand_published: bool) -> DevicePlayer:
    sc = load_scenario('fig8')
    config = BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {}, sc.source)
    return DevicePlayer(config, 20 * MS, hand_published)


def _poses(player: DevicePlayer, n: int, command: np.ndarray | None) -> list[np.ndarray]:
    """``n`` cycles of 1 ms, each after ``command`` (None: no command) arrived."""
    out = []
    for k in range(n):
        if command is not None:
            player.command(k * MS, command)
        out.append(player.cycle(k * MS, 1e-3).pose)
    return out


def test_without_a_hand_wrench_topic_the_hand_pushes_from_the_first_command() -> None:
    """The driver idles with zero commands and the controller sees no hand wrench: the
    simulated hand (fig8: 0.4 N along x) moves the device from the first command on."""
    p = _player(hand_published=False)
    start = _poses(p, 5, None)
    assert not p.engaged and all(np.array_equal(x, start[0]) for x in start)
    moved = _poses(p, 200, np.zeros(3))
    assert p.engaged and p.nonzero_commands == 0
    assert moved[-1][0] - start[0][0] > 1e-4, moved[-1] - start[0]


def test_with_a_hand_wrench_topic_the_device_waits_for_a_non_zero_command() -> None:
    p = _player(hand_published=True)
    start = _poses(p, 1, None)[0]
    parked = _poses(p, 200, np.zeros(3))
    assert not p.engaged and all(np.array_equal(x, start) for x in parked)
    moved = _poses(p, 200, np.array([0.1, 0.0, 0.0]))
    assert p.engaged and moved[-1][0] - start[0] > 1e-4
