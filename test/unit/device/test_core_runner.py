"""LoopRunner: the hosted loop thread's pacing, stamping and hand-over, with a fake clock.

* lock-step through the runner, with the VE fed from its outbox, equals ``simulate`` exactly;
* wall clock: deadlines, skipped deadlines counted as cycles not answered in time, stamps;
* a lock-step state waits for its update at most ``lockstep_wait``, then goes on (notice);
* ``run_duration`` ends the loop; ``submit`` runs between cycles; a full outbox drops (wall)
  and counts; the real thread starts, publishes and stops.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop import ns_to_seconds, period_ns
from haptic_topology.device.runner import LoopRunner, Published, RunnerConfig
from haptic_topology.errors import ConfigError
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    simulate,
    virtual_environment,
)
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.vocabulary import ControlMode, DeviceStatus


class FakeClock:
    """Monotonic time that only moves when slept on (or by the test)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.wall_ns = 1_700_000_000_000_000_000

    def clock(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.now += s

    def wall(self) -> int:
        return self.wall_ns + int(round((self.now - 100.0) * 1e9))


def _runner(sc: Scenario, cfg: RunnerConfig, fake: FakeClock,
            mode: ControlMode = ControlMode.PENALTY) -> LoopRunner:
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, mode, update_period=sc.update_period))
    runner = LoopRunner(cycle, cfg, wall_ns=fake.wall, clock=fake.clock, sleep=fake.sleep)
    runner.may_engage = True
    return runner


@pytest.mark.parametrize(('name', 'mode'), [('fig6', ControlMode.PENALTY),
                                            ('fig8', ControlMode.ACCELERATION_ONLY)])
def test_lockstep_through_the_runner_equals_simulate(name: str, mode: ControlMode) -> None:
    sc = replace(load_scenario(name), duration=0.5)
    ref = simulate(sc, mode)
    fake = FakeClock()
    runner = _runner(sc, RunnerConfig(sc.dt, lockstep=True, run_duration=sc.duration), fake,
                     mode)
    ve = virtual_environment(sc)
    runner.cycle.offer_update(ve.snapshot(seq=0))
    states: list[Published] = []
    inputs, update_seq = 0, 1
    while not runner.finished:
        entry = runner.cycle_once()
        assert entry is not None and runner.drain() == [entry]
        states.append(entry)
        hand = entry.step.answer.hand if entry.step.answer else None
        if hand is not None:        # what ve_sim does with the hand inputs the outbox carries
            ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
            inputs += 1
            if inputs % sc.update_period == 0:
                runner.cycle.offer_update(ve.snapshot(seq=update_seq))
                update_seq += 1
    idle, run = states[0], states[1:]
    assert idle.stamp_ns == 0 and idle.step.tick.status & DeviceStatus.IDLE
    assert len(run) == ref.t.size
    assert [e.stamp_ns for e in run] == [k * period_ns(sc.dt) for k in range(len(run))]
    pose = np.array([e.step.tick.reading.pose for e in run])
    command = np.array([e.step.answer.out.wrench for e in run if e.step.answer])
    np.testing.assert_array_equal(pose, ref.columns['device_pose'])
    np.testing.assert_array_equal(command, ref.columns['command'])
    assert runner.lockstep_timeouts == 0 and runner.outbox_dropped == 0


def test_wall_clock_paces_stamps_and_counts_skipped_deadlines() -> None:
    sc = load_scenario('fig6')
    fake = FakeClock()
    runner = _runner(sc, RunnerConfig(sc.dt), fake)
    runner.cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    runner.pacer.start()
    first = runner.cycle_once()            # idle: engages the device
    assert first is not None and first.step.tick.status & DeviceStatus.IDLE
    assert runner.cycle.device.engaged
    entries = [runner.cycle_once() for _ in range(5)]
    stamps = [e.stamp_ns for e in entries if e is not None]
    assert np.diff(stamps).tolist() == [period_ns(sc.dt)] * 4       # one period apart
    # The loop wakes 3.5 periods after the last release (the cycle before overran): the
    # deadlines 1 and 2 periods on are skipped, the one 3 periods on is released at once.
    fake.now += 3.5 * sc.dt
    late = runner.cycle_once()
    assert late is not None
    assert runner.missed_deadlines == 2 and runner.max_missed_deadlines == 2
    answered, expected = runner.answered_in_time()
    d = runner.cycle.device
    assert expected == d.expected + 2 and answered == d.answered
    assert answered == expected - 2        # every cycle that ran was answered within it
    assert late.stamp_ns - stamps[-1] == pytest.approx(3.5 * sc.dt * 1e9, abs=2)
    assert runner.cycle_once() is not None and runner.missed_deadlines == 2   # on the grid


def test_a_lockstep_state_waits_at_most_lockstep_wait_for_its_update() -> None:
    sc = load_scenario('fig6')
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, ControlMode.PENALTY,
                                              update_period=sc.update_period))
    runner = LoopRunner(cycle, RunnerConfig(sc.dt, lockstep=True, lockstep_wait=0.05))
    runner.may_engage = True
    cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    runner.cycle_once()                    # idle, engages
    for _ in range(sc.update_period + 1):  # the VE is silent: no update after the batch
        runner.cycle_once()
    assert cycle.waiting_for_update()
    t0 = time.monotonic()
    entry = runner.cycle_once()
    waited = time.monotonic() - t0
    assert entry is not None and waited >= 0.05
    assert runner.lockstep_timeouts == 1 and 'no LMI update' in runner.notices[-1]


def test_run_duration_ends_the_loop_after_the_state_that_reaches_it() -> None:
    sc = load_scenario('fig6')
    fake = FakeClock()
    runner = _runner(sc, RunnerConfig(sc.dt, run_duration=0.01), fake)
    runner.cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    runner.pacer.start()
    stamps = []
    while not runner.finished:
        e = runner.cycle_once()
        assert e is not None
        if e.step.tick.run_index >= 0:
            stamps.append(e.stamp_ns)
    assert stamps[-1] - stamps[0] >= 10_000_000 > stamps[-2] - stamps[0]


def test_submit_runs_between_cycles_in_the_loop_thread_or_at_once_when_stopped() -> None:
    sc = load_scenario('fig6')
    fake = FakeClock()
    runner = _runner(sc, RunnerConfig(sc.dt), fake)
    ran: list[str] = []
    runner.submit(lambda: ran.append(threading.current_thread().name))
    assert ran == [threading.current_thread().name]       # not running: at once
    runner.cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    runner.start(name='loop_under_test')
    try:
        runner.submit(lambda: ran.append(threading.current_thread().name))
        deadline = time.monotonic() + 10.0
        while len(ran) < 2 and time.monotonic() < deadline:
            time.sleep(0.001)
    finally:
        runner.stop()
    assert ran[1] == 'loop_under_test' and runner.error is None


def test_a_full_outbox_drops_the_oldest_on_the_wall_clock_and_counts_it() -> None:
    sc = load_scenario('fig6')
    fake = FakeClock()
    runner = _runner(sc, RunnerConfig(sc.dt, outbox=3), fake)
    runner.pacer.start()
    entries = [runner.cycle_once() for _ in range(5)]
    assert runner.outbox_dropped == 2
    assert runner.drain() == entries[2:]


def test_the_real_thread_publishes_every_cycle_in_order_and_stops() -> None:
    sc = load_scenario('fig6')
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, ControlMode.PENALTY))
    woken = threading.Event()
    runner = LoopRunner(cycle, RunnerConfig(sc.dt), wake=woken.set)
    runner.may_engage = True
    cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    got: list[Published] = []
    runner.start()
    try:
        deadline = time.monotonic() + 20.0
        while len(got) < 50 and time.monotonic() < deadline:
            woken.wait(0.1)
            woken.clear()
            got.extend(runner.drain())
    finally:
        runner.stop()
    got.extend(runner.drain())
    assert runner.error is None and not runner.running
    assert [e.step.tick.seq for e in got] == list(range(1, len(got) + 1))
    assert len(got) >= 50 and cycle.device.engaged
    assert all(np.all(np.isfinite(e.step.tick.applied)) for e in got)
    assert ns_to_seconds(got[-1].stamp_ns) > ns_to_seconds(got[0].stamp_ns)


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'period': 0.0}, 'period must be'),
    ({'period': 0.001, 'run_duration': -1.0}, 'run_duration'),
    ({'period': 0.001, 'lockstep_wait': 0.0}, 'lockstep_wait'),
    ({'period': 0.001, 'outbox': 0}, 'outbox'),
])
def test_bad_runner_settings_are_refused(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        RunnerConfig(**kwargs)  # type: ignore[arg-type]


def test_a_restarted_runner_runs_a_new_run_of_run_duration() -> None:
    """Deactivate after run_duration, activate again: the loop runs (and ends) again."""
    sc = load_scenario('fig6')
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, ControlMode.PENALTY))
    runner = LoopRunner(cycle, RunnerConfig(sc.dt, run_duration=0.005))
    runner.may_engage = True
    cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    runs = []
    for _ in range(2):
        runner.start()
        deadline = time.monotonic() + 20.0
        while not runner.finished and time.monotonic() < deadline:
            time.sleep(0.001)
        runner.stop()
        assert runner.finished and runner.error is None
        runs.append([e for e in runner.drain() if e.step.tick.run_index >= 0])
    # Each run ran until its stamps spanned run_duration (wall clock: how many cycles that
    # took depends on the machine, a late cycle skips deadlines), the second after the first.
    for run in runs:
        assert len(run) >= 2 and run[-1].stamp_ns - run[0].stamp_ns >= 5_000_000
    assert runs[1][0].step.tick.seq > runs[0][-1].step.tick.seq
