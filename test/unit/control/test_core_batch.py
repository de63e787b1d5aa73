"""Hand inputs in batches: the controller's batcher, the message round trip, and the VE's
per-input policy, which must compute the same run however the inputs were cut into batches."""

from __future__ import annotations

import doctest
from dataclasses import replace

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from haptic_topology.control import batch as batch_module
from haptic_topology.control.batch import HandBatch, HandBatcher
from haptic_topology.control.loop import HandSample
from haptic_topology.device.hosted import state_sample
from haptic_topology.device.loop import ns_to_seconds, period_ns
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.nodes.convert import (
    hand_inputs_msg,
    stamp_ns,
    stamp_seconds,
    vt_wrenches_from_hand_inputs,
)
from haptic_topology.sim.lockstep import build_controller_loop, build_device_loop, simulate
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.sim.ve import HandFeed, VirtualEnvironment
from haptic_topology.vocabulary import ControlMode
from haptic_topology_msgs.msg import HandInputs


def _sample(k: int, m: int = 3) -> HandSample:
    row = np.arange(m, dtype=float) + 0.1 * k
    return HandSample(k, 1000 + k, 1e-3 * k, row, row + 1.0, row + 2.0, row + 3.0, row)


def test_docstring_example() -> None:
    assert doctest.testmod(batch_module).failed == 0


def test_batches_end_where_the_seq_completes_a_period() -> None:
    """The first batch of a controller that starts at seq 1 holds 1..10; one that starts
    within a period (a flush before) ends at the next multiple, never later."""
    b = HandBatcher(10, 3, max_age=0.02)
    ends = [k for k in range(1, 31) if b.add(_sample(k), k, 0.0) is not None]
    assert ends == [10, 20, 30] and b.pending == 0
    b.add(_sample(31), 31, 0.0)
    partial = b.due(0.02)
    assert partial is not None and partial.seq.tolist() == [31]
    got = [b.add(_sample(k), k, 0.03) for k in range(32, 41)]
    last = got[-1]
    assert all(x is None for x in got[:-1]) and last is not None
    assert last.seq.tolist() == list(range(32, 41))
    assert (b.batches, b.partial) == (5, 1)


def test_flush_waits_for_the_oldest_sample_to_age() -> None:
    b = HandBatcher(10, 3, max_age=0.02)
    b.add(_sample(1), 1, 10.0)
    b.add(_sample(2), 2, 10.015)
    assert b.due(10.0195) is None
    out = b.due(10.0205)
    assert out is not None and len(out) == 2
    assert b.due(11.0) is None and b.flush() is None


def test_batch_keeps_every_value_and_is_not_overwritten_later() -> None:
    b = HandBatcher(4, 3, max_age=1.0)
    out = [b.add(_sample(k), 10 ** 18 + k, 0.0) for k in range(1, 5)][-1]
    assert out is not None
    for k in range(5, 8):
        b.add(_sample(k), k, 0.0)       # reuses the buffers
    for i, k in enumerate(range(1, 5)):
        s = _sample(k)
        assert (out.seq[i], out.state_seq[i], out.stamp_ns[i]) == (k, 1000 + k, 10 ** 18 + k)
        for got, want in ((out.pose, s.pose), (out.twist, s.twist),
                          (out.hand_wrench, s.hand_wrench), (out.coupling, s.coupling)):
            np.testing.assert_array_equal(got[i], want)


def test_bad_batcher_settings_are_refused() -> None:
    with pytest.raises(ValueError, match='period must be >= 1, got 0'):
        HandBatcher(0, 3, 0.02)
    with pytest.raises(ValueError, match='max_age must be > 0 s'):
        HandBatcher(10, 3, 0.0)


@pytest.mark.parametrize('vt_coupling', [True, False])
def test_message_round_trip_is_exact(vt_coupling: bool) -> None:
    """Batch -> HandInputs -> CDR -> back: every sample's integers, stamp (as the nodes
    compute seconds from a stamp) and vectors exactly; F_vt = F_h - F_pc or F_h."""
    b = HandBatcher(3, 6, max_age=1.0)
    wall_ns = 1_763_000_000_123_456_789   # a wall-clock stamp: exact as integer ns only
    out = [b.add(_sample(k, 6), wall_ns + k, 0.0) for k in range(1, 4)][-1]
    assert isinstance(out, HandBatch)
    msg = deserialize_message(serialize_message(hand_inputs_msg(HandInputs(), out)), HandInputs)
    assert stamp_ns(msg.header.stamp) == wall_ns + 3
    assert [stamp_ns(s) for s in msg.stamp] == [wall_ns + k for k in range(1, 4)]
    task = load_scenario('panda_link4').linkage.task
    seqs, state_seqs, stamps, pose, twist, f_vt = vt_wrenches_from_hand_inputs(
        msg, task, vt_coupling, 100.0)
    assert seqs == [1, 2, 3] and state_seqs == [1001, 1002, 1003]
    assert stamps == [stamp_seconds(s) for s in msg.stamp]
    np.testing.assert_array_equal(pose, out.pose)
    np.testing.assert_array_equal(twist, out.twist)
    np.testing.assert_array_equal(
        f_vt, out.hand_wrench - out.coupling if vt_coupling else out.hand_wrench)


# -- the run does not depend on how the inputs were batched ----------------------------------
def _run(sc: Scenario, mode: ControlMode, period: int | None,
         stalls: frozenset[int] = frozenset()) -> tuple[np.ndarray, dict[int, np.ndarray], int]:
    """The loop of :func:`simulate` with the VE behind a :class:`HandFeed`; the hand inputs
    reach it one by one (``period`` None) or through a :class:`HandBatcher` and the message
    round trip, with the flush timer running on a steady clock that stalls 50 ms before each
    cycle of ``stalls`` (a partial batch goes out there). Returns the commands, the VE's hand
    path (input seq -> pose) and the number of partial batches."""
    dyn = LinkageDynamics(sc.linkage)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step,
                            coupling=sc.coupling_gains())
    feed = HandFeed(ve, sc.update_period)
    device = build_device_loop(sc)
    loop = build_controller_loop(sc, mode, update_period=sc.update_period)
    loop.on_update(ve.snapshot(seq=0))
    batcher = None if period is None else HandBatcher(period, sc.linkage.task.dim,
                                                      2.0 * sc.dt * period)
    update_seq = 1
    path: dict[int, np.ndarray] = {}

    def deliver(samples: list[tuple[int, int, float, np.ndarray, np.ndarray, np.ndarray]]
                ) -> None:
        nonlocal update_seq
        for s in samples:
            if feed.take(*s):
                loop.on_update(ve.snapshot(seq=update_seq))
                update_seq += 1
        path.update(ve.take_path())

    def send(b: HandBatch | None) -> None:
        if b is None:
            return
        msg = deserialize_message(serialize_message(hand_inputs_msg(HandInputs(), b)),
                                  HandInputs)
        seqs, state_seqs, stamps, pose, twist, f_vt = vt_wrenches_from_hand_inputs(
            msg, sc.linkage.task, sc.vt_coupling)
        deliver(list(zip(seqs, state_seqs, stamps, pose, twist, f_vt, strict=True)))

    def answer(k: int, t: float) -> np.ndarray:
        ans = loop.on_state(state_sample(device.tick(t, sc.dt), t))
        assert ans is not None
        device.on_command(ans.state_seq, int(ans.out.mode), ans.out.wrench, t)
        h = ans.hand
        if h is not None:
            if batcher is None:
                deliver([(h.seq, h.state_seq, h.stamp, h.pose, h.twist, h.vt_wrench)])
            else:
                send(batcher.add(h, k * step_ns, steady))
        return ans.out.wrench

    step_ns = period_ns(sc.dt)
    steady = 0.0
    answer(0, 0.0)              # engagement (idle state)
    n = int(round(sc.duration / sc.dt)) + 1
    commands = np.zeros((n, sc.linkage.task.dim))
    for k in range(n):
        steady += sc.dt + (0.05 if k in stalls else 0.0)
        if batcher is not None:
            send(batcher.due(steady))       # the controller's flush timer
        assert not loop.waiting_for_update(), f'state {k}: the VE update was not taken'
        commands[k] = answer(k, ns_to_seconds(k * step_ns))
    if batcher is not None:
        send(batcher.flush())               # the timer after the run's last state
    return commands, path, 0 if batcher is None else batcher.partial


@pytest.mark.parametrize('scenario', ['fig8', 'panda_link4'])
def test_lockstep_run_does_not_depend_on_batching(scenario: str) -> None:
    """One input at a time reproduces simulate(); batches of the update period, with partial
    batches flushed after stalls (a few samples, one sample, all but the period's last),
    give the same commands and the same VT path bit for bit."""
    sc = replace(load_scenario(scenario), duration=0.1)
    mode = ControlMode.PENALTY
    ref_cmd, ref_path, _ = _run(sc, mode, None)
    np.testing.assert_array_equal(ref_cmd, simulate(sc, mode).columns['command'])
    stalls = frozenset({4, 13, 29, 35, 36, 65})
    cmd, path, partial = _run(sc, mode, sc.update_period, stalls)
    assert partial == len(stalls) + 1       # and the flush after the last state
    np.testing.assert_array_equal(cmd, ref_cmd)
    assert sorted(path) == sorted(ref_path)
    for seq, pose in ref_path.items():
        np.testing.assert_array_equal(path[seq], pose)


def _feed() -> tuple[HandFeed, VirtualEnvironment]:
    sc = load_scenario('fig8')
    ve = VirtualEnvironment(LinkageDynamics(sc.linkage), sc.q0, sc.dq0, sc.internal_step)
    return HandFeed(ve, 10), ve


def test_feed_counts_lost_inputs_and_sees_a_restarted_controller() -> None:
    feed, ve = _feed()
    z = np.zeros(3)
    pose = ve.dyn.hand_pose(ve.q)
    due = [feed.take(k, k, 1e-3 * k, pose, z, z) for k in (1, 2, 3, 7, 8)]
    assert feed.lost == 3 and not any(due) and feed.notices == []
    feed.take(1, 9, 9e-3, pose, z, z)       # seq back to 1: a new controller
    assert feed.controller_restarts == 1 and feed.last_seq == 1
    assert 'hand input seq 1 after 8: a new controller' in feed.notices[0]
    assert ve.hand_input_seq == -1          # the held input was dropped
    # The update is due after every 10th input taken, wherever the batches were cut.
    due = [feed.take(k, 8 + k, 1e-3 * (8 + k), pose, z, z) for k in range(2, 18)]
    assert [i + 2 for i, d in enumerate(due) if d] == [5, 15] and feed.inputs == 22


def test_feed_of_a_restarted_ve_places_the_vt_at_the_hand() -> None:
    feed, ve = _feed()
    target = ve.dyn.hand_pose(ve.q + np.array([0.05, -0.05, 0.02]))
    feed.take(5000, 5000, 5.0, target, np.zeros(3), np.zeros(3))
    assert feed.t0 == 5.0
    assert 'joined a running loop (hand input 5000)' in feed.notices[0]
    np.testing.assert_allclose(ve.dyn.hand_pose(ve.q), target, atol=1e-6)
