"""HostedCycle: device tick -> controller -> device command as one object (no ROS).

* ``simulate`` through the cycle equals the direct wiring it replaced, bit for bit;
* LMI updates offered from another thread are all applied, in order, at step starts;
* the applied wrench stays finite and within the limit whatever the controller computes.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from haptic_topology.control.controller import CycleOutput, PreparedUpdate
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.loop import Answer, UpdateVerdict
from haptic_topology.device.hosted import HostedCycle, HostedStep, state_sample
from haptic_topology.device.loop import (
    CommandVerdict,
    DeviceTick,
    ns_to_seconds,
    period_ns,
)
from haptic_topology.errors import ConfigError
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    simulate,
    virtual_environment,
)
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.sim.trace import ENERGY_FLOATS, Trace
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import ControlMode, DeviceStatus


def _cycle(sc: Scenario, mode: ControlMode, **kwargs: Any) -> tuple[HostedCycle,
                                                                     VirtualEnvironment]:
    loop = build_controller_loop(sc, mode, update_period=sc.update_period)
    return HostedCycle(build_device_loop(sc), loop, **kwargs), virtual_environment(sc)


def _simulate_direct(sc: Scenario, mode: ControlMode) -> Trace:
    """``simulate`` as it was before HostedCycle: DeviceLoop and ControllerLoop wired by hand
    (the reference the hosted cycle must reproduce exactly). It applies each LMI update
    right after the cycle whose input completed it, where the hosted cycle applies it at the
    start of the next one (as the loop process does when it sleeps); both must agree."""
    task = sc.linkage.task
    ve = virtual_environment(sc)      # shared with simulate: the VE is not under test here
    dyn = ve.dyn
    device = build_device_loop(sc)
    loop = build_controller_loop(sc, mode, update_period=sc.update_period)
    first = ve.snapshot(seq=0)
    loop.on_update(first)
    counts = [(0, first.constraint_count)]
    step_ns = period_ns(sc.dt)

    def answer(tick: DeviceTick, stamp: float) -> Answer:
        ans = loop.on_state(state_sample(tick, stamp))
        assert ans is not None
        device.on_command(ans.state_seq, int(ans.out.mode), ans.out.wrench, stamp)
        return ans

    answer(device.tick(0.0, sc.dt), 0.0)
    n = int(round(sc.duration / sc.dt)) + 1
    trace = Trace.empty(n, task.dim, dyn.dof, mode=mode.label, scenario=sc.name, dt=sc.dt)
    vt_pose = dyn.hand_pose(ve.q)
    inputs = 0
    update_seq = 1
    for k in range(n):
        t = ns_to_seconds(k * step_ns)
        assert not loop.waiting_for_update()
        tick = device.tick(t, sc.dt)
        ans = answer(tick, t)
        hand = ans.hand
        if hand is not None:
            ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
            inputs += 1
        path = ve.take_path()
        if path:
            vt_pose = path[-1][1]
        r = tick.reading
        trace.record(k, t=t, device_pose=r.pose, device_twist=r.twist,
                     hand_wrench=r.hand_wrench, command=ans.out.wrench, applied=tick.applied,
                     vt_pose=vt_pose, lmi_pose=ans.out.vt_pose, q=ve.q,
                     lmi_constraint_count=ans.out.constraint_count, status=int(tick.status))
        if hand is not None and inputs % sc.update_period == 0:
            snap = ve.snapshot(seq=update_seq)
            loop.on_update(snap)
            counts.append((k, snap.constraint_count))
            update_seq += 1
    trace.hold_constraint_counts([r for r, _ in counts], [c for _, c in counts])
    return trace


@pytest.mark.parametrize(('name', 'mode', 'duration'), [
    ('fig6', ControlMode.PENALTY, None),
    ('fig8', ControlMode.ACCELERATION_ONLY, None),     # reaches the workspace limit
    ('spatial_arm4', ControlMode.PENALTY, 0.3),
], ids=['fig6-eq14', 'fig8-eq10', 'spatial_arm4-eq14'])
def test_simulate_through_the_cycle_equals_the_direct_wiring(
        name: str, mode: ControlMode, duration: float | None) -> None:
    sc = load_scenario(name)
    if duration is not None:
        sc = replace(sc, duration=duration)
    ours, ref = simulate(sc, mode), _simulate_direct(sc, mode)
    np.testing.assert_array_equal(ours.t, ref.t)
    # simulate adds its controller's energy account (not in the hand-wired reference)
    assert ours.columns.keys() - set(ENERGY_FLOATS) == ref.columns.keys()
    for key, col in ref.columns.items():
        np.testing.assert_array_equal(ours.columns[key], col, err_msg=key)
    if name == 'fig8':
        assert np.any(ref.columns['status'] & DeviceStatus.WORKSPACE_LIMIT)


def test_step_is_tick_then_answer_then_command() -> None:
    sc = load_scenario('fig8')
    cycle, ve = _cycle(sc, ControlMode.PENALTY)
    cycle.offer_update(ve.snapshot(seq=0))
    idle = cycle.step(0.0, sc.dt, cycle.lockstep_stamp())
    assert idle.updates == (UpdateVerdict.APPLIED,)
    assert idle.tick.seq == 1 and idle.tick.run_index == -1
    assert idle.tick.status & DeviceStatus.IDLE
    assert idle.answer is not None and idle.answer.hand is None
    assert idle.answer.out.mode is ControlMode.PENALTY       # synced: this answer engages
    assert idle.verdict == CommandVerdict.APPLIED and cycle.device.engaged
    step_ns = period_ns(sc.dt)
    for k in range(5):
        stamp = cycle.lockstep_stamp()
        assert stamp == ns_to_seconds(k * step_ns)            # device_driver's lock-step stamp
        done = cycle.step(stamp, sc.dt, stamp)
        assert isinstance(done, HostedStep) and done.updates == ()
        assert (done.tick.seq, done.tick.run_index, done.stamp) == (k + 2, k, stamp)
        assert done.answer is not None and done.answer.state_seq == done.tick.seq
        assert done.answer.hand is not None and done.answer.hand.seq == k + 1
        assert done.verdict == CommandVerdict.APPLIED and cycle.device.answered_current


def _snapshots(sc: Scenario, n: int) -> list[LmiSnapshot]:
    first = virtual_environment(sc).snapshot(seq=0)
    return [replace(first, seq=i) for i in range(n)]


def _record_updates(cycle: HostedCycle, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The seq of every update the controller takes, in order (asserting the loop thread, and
    that the update comes prepared: its matrices were computed by the thread that offered it)."""
    seen: list[int] = []
    on_update = cycle.controller.on_update

    def record(update: PreparedUpdate) -> str:
        assert threading.current_thread() is threading.main_thread()
        assert isinstance(update, PreparedUpdate)
        seen.append(update.snapshot.seq)
        return on_update(update)

    monkeypatch.setattr(cycle.controller, 'on_update', record)
    return seen


def test_updates_offered_from_another_thread_are_all_applied_in_order(
        monkeypatch: pytest.MonkeyPatch) -> None:
    sc = load_scenario('fig8')
    n = 1000
    cycle, _ = _cycle(sc, ControlMode.PENALTY, max_pending=n)   # whatever the interleaving
    seen = _record_updates(cycle, monkeypatch)
    snaps = _snapshots(sc, n)
    start = threading.Barrier(2)

    def produce() -> None:
        start.wait()
        for i, s in enumerate(snaps):
            cycle.offer_update(s)
            if i % 5 == 0:
                time.sleep(0)           # let the loop thread step between offers

    producer = threading.Thread(target=produce)
    producer.start()
    start.wait()
    steps: list[HostedStep] = []
    while producer.is_alive() or cycle.values()['updates_pending'] != '0':
        steps.append(cycle.step(0.0, sc.dt, 0.0))
    producer.join()
    assert seen == list(range(n))
    assert sum(len(s.updates) for s in steps) == n
    assert (cycle.updates_offered, cycle.updates_applied, cycle.updates_dropped) == (n, n, 0)
    assert cycle.controller.updates == n


def test_an_update_is_prepared_by_the_thread_that_offers_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The re-sync's matrices are computed where the update arrives (the executor thread),
    never in the loop thread's step, which only adopts them."""
    sc = load_scenario('fig8')
    cycle, _ = _cycle(sc, ControlMode.PENALTY)
    ctrl = cycle.controller.ctrl
    prepared_in: list[str] = []
    prepare = ctrl.prepare

    def record(snap: LmiSnapshot) -> PreparedUpdate:
        prepared_in.append(threading.current_thread().name)
        return prepare(snap)

    monkeypatch.setattr(ctrl, 'prepare', record)
    offer = threading.Thread(target=cycle.offer_update, args=(_snapshots(sc, 1)[0],),
                             name='executor')
    offer.start()
    offer.join()
    done = cycle.step(0.0, sc.dt, 0.0)
    assert done.updates == (UpdateVerdict.APPLIED,) and ctrl.lmi.synced
    assert prepared_in == ['executor']


def test_a_full_inbox_drops_the_oldest_and_counts_it(monkeypatch: pytest.MonkeyPatch) -> None:
    sc = load_scenario('fig8')
    cycle, _ = _cycle(sc, ControlMode.PENALTY, max_pending=4)
    seen = _record_updates(cycle, monkeypatch)
    for s in _snapshots(sc, 7):
        cycle.offer_update(s)
    assert cycle.values() == {'updates_offered': '7', 'updates_applied': '0',
                              'updates_pending': '4', 'updates_dropped': '3'}
    done = cycle.step(0.0, sc.dt, 0.0)
    assert len(done.updates) == 4 and seen == [3, 4, 5, 6]


def test_wait_offered_wakes_on_an_update_from_another_thread() -> None:
    sc = load_scenario('fig8')
    cycle, ve = _cycle(sc, ControlMode.PENALTY)
    assert not cycle.wait_offered(0.0)
    producer = threading.Thread(target=cycle.offer_update, args=(ve.snapshot(seq=0),))
    producer.start()
    assert cycle.wait_offered(60.0)
    producer.join()
    assert cycle.apply_updates() == (UpdateVerdict.APPLIED,)
    assert not cycle.wait_offered(0.0)


def test_waiting_for_update_applies_what_was_offered() -> None:
    # Lock-step: after every update_period-th hand input the next state waits for the update.
    sc = load_scenario('fig8')
    cycle, ve = _cycle(sc, ControlMode.PENALTY)
    cycle.offer_update(ve.snapshot(seq=0))
    cycle.step(0.0, sc.dt, 0.0)
    inputs = 0
    while not cycle.waiting_for_update():
        done = cycle.step(cycle.lockstep_stamp(), sc.dt, cycle.lockstep_stamp())
        assert done.answer is not None and done.answer.hand is not None
        ve.push_input(done.answer.hand.state_seq, done.answer.hand.stamp,
                      done.answer.hand.vt_wrench)
        inputs += 1
    assert inputs == sc.update_period
    cycle.offer_update(ve.snapshot(seq=1))
    assert not cycle.waiting_for_update() and cycle.updates_applied == 2


@pytest.mark.parametrize('bad', [np.nan, np.inf, -np.inf, 1e300, -1e300])
def test_applied_wrench_stays_finite_and_within_the_limit(
        bad: float, monkeypatch: pytest.MonkeyPatch) -> None:
    sc = load_scenario('fig8')
    cycle, ve = _cycle(sc, ControlMode.PENALTY)
    limit = cycle.device.limit
    ctrl = cycle.controller.ctrl
    law = ctrl.cycle
    outputs: list[np.ndarray] = []

    def broken(*args: Any) -> CycleOutput:
        out = law(*args)
        wrench = out.wrench.copy()
        wrench[len(outputs) % wrench.size] = bad
        wrench[(len(outputs) + 1) % wrench.size] = 1e6 * limit[0]
        outputs.append(wrench)
        return out._replace(wrench=wrench)

    monkeypatch.setattr(ctrl, 'cycle', broken)
    cycle.offer_update(ve.snapshot(seq=0))
    cycle.step(0.0, sc.dt, 0.0)
    for k in range(30):
        t = ns_to_seconds(k * period_ns(sc.dt))
        done = cycle.step(t, sc.dt, t)
        assert done.answer is not None
        assert not np.all(np.abs(done.answer.out.wrench) <= limit)    # the law's output
        u = done.tick.applied
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= limit), (k, u)
        r = done.tick.reading
        assert all(np.all(np.isfinite(v)) for v in (r.pose, r.twist, r.hand_wrench))
        if k > 0:                        # the previous (bad) command is what was written
            assert done.tick.status & DeviceStatus.SATURATED
    assert len(outputs) == 30


def test_device_and_controller_must_match() -> None:
    fig8, spatial = load_scenario('fig8'), load_scenario('spatial_arm4')
    with pytest.raises(ConfigError, match='same task dimension, got 3 and 6'):
        HostedCycle(build_device_loop(fig8), build_controller_loop(spatial, ControlMode.PENALTY))
    with pytest.raises(ConfigError, match='max_pending must be >= 1 update, got 0'):
        HostedCycle(build_device_loop(fig8), build_controller_loop(fig8, ControlMode.PENALTY),
                    max_pending=0)
