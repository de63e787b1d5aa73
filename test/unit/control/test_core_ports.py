"""The separate layout's core objects, without ROS: ``ExecutorLoop`` (the device stepped by
executor callbacks) and ``ControllerPort`` (the controller with hand batches, the lock-step
hold and figures).

* lock-step, with the messages in the worst order the graph can deliver them (the device's
  next state before the VE's update), the two objects fed by the VE from the hand batches
  reproduce ``simulate`` bit for bit: what the separate-layout lock-step graph runs;
* a held state waits at most ``lockstep_wait``, then is answered from the local model;
* wall clock: the device integrates over the measured period, clipped; ``run_duration``
  marks the last state; a stalled lock-step answer is named; engagement and takeover lines;
* live parameter changes apply all or none;
* ``UpdateGap``: while states come, an update waits for the next answer; once they stop, it
  is taken at once or by the timer; always in arrival order.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.control.port import (
    ARRIVALS_KEPT,
    STATES_COMING,
    ControllerPort,
    UpdateGap,
    live_change,
)
from haptic_topology.device.executor_loop import Emitted, ExecutorLoop
from haptic_topology.device.hosted import HostedCycle, state_sample
from haptic_topology.device.loop import CommandVerdict, ns_to_seconds, period_ns
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    simulate,
    virtual_environment,
)
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.vocabulary import ControlMode, DeviceStatus


def _pair(sc: Scenario, mode: ControlMode, lockstep: bool = True,
          lockstep_wait: float = 5.0) -> tuple[ExecutorLoop, ControllerPort]:
    stepper = ExecutorLoop(build_device_loop(sc), sc.dt, lockstep, sc.duration)
    port = ControllerPort(build_controller_loop(sc, mode, update_period=sc.update_period),
                          sc.update_period, sc.linkage.task.dim, sc.dt, lockstep,
                          lockstep_wait)
    return stepper, port


def _sample(e: Emitted) -> object:
    return state_sample(e.tick, ns_to_seconds(e.stamp_ns))


@pytest.mark.parametrize(('name', 'mode', 'late_keepalive'),
                         [('fig6', ControlMode.PENALTY, False),
                          ('fig6', ControlMode.ACCELERATION_ONLY, True),
                          ('fig8', ControlMode.ACCELERATION_ONLY, False),
                          ('fig8', ControlMode.PENALTY, True)])
def test_separate_lockstep_objects_equal_simulate(name: str, mode: ControlMode,
                                                  late_keepalive: bool) -> None:
    """``late_keepalive``: one of the VE's idle updates (its initial state, published at
    its idle rate until the first hand input) reaches the controller after the loop's first
    state, as DDS may deliver it: the result does not change."""
    sc = replace(load_scenario(name), duration=0.5)
    ref = simulate(sc, mode)
    stepper, port = _pair(sc, mode)
    ve = virtual_environment(sc)
    port.on_update(ve.snapshot(seq=0), 0.0)
    e = stepper.idle_tick(0.0)
    assert e is not None and e.stamp_ns == 0 and e.tick.status & DeviceStatus.IDLE
    queued = None         # the VE's update on its way to the controller
    run: list[Emitted] = []
    commands = []
    inputs, update_seq, held = 0, 1, 0
    if late_keepalive:
        port.on_state(_sample(e), e.stamp_ns, 0.0)          # type: ignore[arg-type]
        keepalive = ve.snapshot(seq=update_seq)
        update_seq += 1
        assert keepalive.hand_input_seq < 0
        assert port.on_update(keepalive, 0.0) is None
    while True:
        out = port.on_state(_sample(e), e.stamp_ns, 0.0)   # type: ignore[arg-type]
        if queued is not None:
            # The update came after the device's next state (the worst order DDS can
            # deliver them in): a state that needs it is held until it has come.
            held += out is None
            released = port.on_update(queued, 0.0)
            out = out or released
            queued = None
        assert out is not None
        ans = out.answer
        if e.ends_run:
            commands.append(ans.out.wrench)
            break
        if ans.hand is not None:
            hand = ans.hand
            ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
            inputs += 1
            if inputs % sc.update_period == 0:
                queued = ve.snapshot(seq=update_seq)
                update_seq += 1
        res = stepper.on_command(ans.state_seq, int(ans.out.mode), ans.out.wrench, 0.0, True, 7)
        assert res.verdict == CommandVerdict.APPLIED and res.emitted is not None
        if run:
            commands.append(ans.out.wrench)
        e = res.emitted
        assert e.clock                  # lock-step steps publish /clock first
        run.append(e)
    assert len(run) == ref.t.size
    assert [x.stamp_ns for x in run] == [k * period_ns(sc.dt) for k in range(len(run))]
    np.testing.assert_array_equal(np.array([x.tick.reading.pose for x in run]),
                                  ref.columns['device_pose'])
    np.testing.assert_array_equal(np.array(commands), ref.columns['command'])
    assert held >= update_seq - 3 and port.lockstep_timeouts == 0     # nearly every update
    assert port.commands == len(run) + 1 + late_keepalive   # the idle state's answer(s)


def test_a_held_state_is_answered_from_the_local_model_after_lockstep_wait() -> None:
    sc = replace(load_scenario('fig6'), duration=0.5)
    stepper, port = _pair(sc, ControlMode.PENALTY, lockstep_wait=0.05)
    port.on_update(virtual_environment(sc).snapshot(seq=0), 0.0)
    e = stepper.idle_tick(0.0)
    now = 0.0
    held_at = None
    for _ in range(3 * sc.update_period + 3):   # the VE is silent after its first update
        assert e is not None
        out = port.on_state(_sample(e), e.stamp_ns, now)    # type: ignore[arg-type]
        if out is None:
            held_at = now
            assert port.check_wait(now + 0.049) is None     # not yet
            out = port.check_wait(now + 0.05)
            assert out is not None
            break
        e = stepper.on_command(out.answer.state_seq, int(out.answer.out.mode),
                               out.answer.out.wrench, now, True, 7).emitted
    assert held_at is not None, 'no state was held for its update'
    assert port.lockstep_timeouts == 1
    assert any('no LMI update for state' in n for n in port.loop.notices)
    assert np.all(np.isfinite(out.answer.out.wrench))


def test_wall_ticks_clip_the_period_and_mark_the_end_of_the_run() -> None:
    sc = replace(load_scenario('fig6'), duration=0.003)
    stepper, port = _pair(sc, ControlMode.PENALTY, lockstep=False)
    port.on_update(virtual_environment(sc).snapshot(seq=0), 0.0)
    t, ns = 10.0, 1_000_000_000
    e = stepper.wall_tick(t, ns)
    assert e.tick.status & DeviceStatus.IDLE and not e.clock and not e.ends_run
    out = port.on_state(_sample(e), e.stamp_ns, t)          # type: ignore[arg-type]
    assert out is not None
    res = stepper.on_command(out.answer.state_seq, int(out.answer.out.mode),
                             out.answer.out.wrench, t, True, 7)
    assert res.info == 'controller 7 engaged at state 1' and res.emitted is None  # wall
    ends = []
    for k in range(1, 6):
        # A 1 s stall of the executor counts as 20 periods, not as one 1 s step.
        gap = 1.0 if k == 2 else sc.dt
        t += gap
        e = stepper.wall_tick(t, ns + round(1e9 * (t - 10.0)))
        ends.append(e.ends_run)
        if k == 2:
            assert e.tick.run_index == 1
    assert stepper.stats.periods[1] == pytest.approx(1.0)
    assert ends.index(True) == 1           # the second engaged state is >= 3 ms after the first
    assert stepper.stalled(t) == ''         # wall clock: never


def test_lockstep_names_a_stalled_answer_and_a_takeover() -> None:
    sc = replace(load_scenario('fig6'), duration=0.5)
    stepper, port = _pair(sc, ControlMode.PENALTY)
    port.on_update(virtual_environment(sc).snapshot(seq=0), 0.0)
    e = stepper.idle_tick(0.0)
    assert e is not None
    out = port.on_state(_sample(e), e.stamp_ns, 0.0)        # type: ignore[arg-type]
    assert out is not None
    wrench = out.answer.out.wrench
    res = stepper.on_command(out.answer.state_seq, int(out.answer.out.mode), wrench, 1.0,
                             True, 7)
    assert res.emitted is not None and stepper.idle_tick(1.0) is None   # engaged: no idle
    assert stepper.stalled(1.0 + 4.9) == ''
    assert stepper.stalled(1.0 + 5.0) == ('lock-step: no answer to state 2 for 5.0 s (is '
                                          'lmi_controller running, and ve_sim?)')
    # Another controller, after the followed one was silent for takeover_after.
    seq = res.emitted.tick.seq
    res = stepper.on_command(seq, int(ControlMode.PENALTY), wrench, 10.0, True, 9)
    assert res.warning == 'controller 9 took over from the silent 7'
    assert res.verdict == CommandVerdict.APPLIED and res.emitted is not None


def test_live_changes_apply_all_or_none() -> None:
    sc = load_scenario('fig6')
    gains, mode = sc.gains, ControlMode.PENALTY
    changed = live_change(gains, mode, [('k_tc', 500.0), ('mode', 'acceleration_only')])
    assert not isinstance(changed, str)
    assert changed[0].k_tc == 500.0 and changed[0].b_tc == gains.b_tc
    assert changed[1] is ControlMode.ACCELERATION_ONLY
    refused = live_change(gains, mode, [('k_tc', 500.0), ('b_tc', -1.0)])
    assert isinstance(refused, str) and 'b_tc must be >= 0' in refused
    assert live_change(gains, mode, [('mode', 'fast')]) == (
        'mode must be one of penalty, acceleration_only, got \'fast\'')


def test_the_update_age_is_never_negative() -> None:
    """Hosted, the publishing thread's ``now`` may precede the arrival the executor thread
    recorded: the age is then 0, never negative (a malformed ``update_age``)."""
    sc = load_scenario('fig6')
    stepper, port = _pair(sc, ControlMode.PENALTY)
    assert port.update_age(1.0) == float('inf')
    port.on_update(virtual_environment(sc).snapshot(seq=0), 5.0, apply=False)
    assert port.update_age(4.9) == 0.0
    assert port.update_age(5.25) == 0.25


def test_an_update_waits_for_the_next_answer_while_states_come() -> None:
    gap = UpdateGap()
    assert gap.arrived('u1', now=10.0002, state_time=10.0) == []
    assert gap.arrived('u2', now=10.0008, state_time=10.0) == []
    assert gap.due(10.0009, state_time=10.0) == []          # the timer: states still come
    assert gap.answered() == ['u1', 'u2']                    # after the next command
    assert gap.answered() == []
    assert gap.deferred == 2


def test_an_update_is_taken_at_once_when_no_state_comes() -> None:
    gap = UpdateGap()
    assert STATES_COMING == 0.005
    assert gap.arrived('u0', now=1.0, state_time=None) == ['u0']    # before any state
    assert gap.arrived('u1', now=2.0, state_time=1.998) == []
    # the states stopped: the next update takes the waiting one first, in arrival order
    assert gap.arrived('u2', now=2.01, state_time=1.998) == ['u1', 'u2']
    assert gap.arrived('u3', now=3.0, state_time=2.999) == []
    assert gap.due(3.002, state_time=2.999) == []
    assert gap.due(3.006, state_time=2.999) == ['u3']
    assert gap.deferred == 2


def test_an_answer_given_by_its_hand_block_is_accounted_as_the_answer_itself() -> None:
    """The hosted publisher hands the port each answer's hand input as a 4 x m block
    (``answered_block``, from the cycle record): the same batches, update ages, command
    count and period statistics as ``answered`` of the answer object."""
    sc = load_scenario('circle')
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, sc.mode, update_period=sc.update_period))
    cycle.offer_update(virtual_environment(sc).snapshot(seq=0))
    by_object, by_block = (ControllerPort(build_controller_loop(sc, sc.mode), sc.update_period,
                                          sc.linkage.task.dim, sc.dt) for _ in range(2))
    for port in (by_object, by_block):
        port.on_update(virtual_environment(sc).snapshot(seq=0), 0.5, apply=False)
    batches = 0
    for k in range(25):
        t = k * sc.dt
        ans = cycle.step(t, sc.dt, t).answer
        assert ans is not None
        ns, now = k * 1_000_000, 1.0 + 0.001 * k
        out = by_object.answered(ans, ns, now, t if k else None)
        h = ans.hand
        age, batch = by_block.answered_block(
            None if h is None else (h.seq, h.state_seq,
                                    np.stack([h.pose, h.twist, h.hand_wrench, h.coupling])),
            ns, now, t if k else None)
        assert age == out.update_age
        assert (batch is None) == (out.batch is None)
        if batch is not None and out.batch is not None:
            batches += 1
            for a, b in zip(vars(batch).values(), vars(out.batch).values(), strict=True):
                np.testing.assert_array_equal(a, b)
    assert batches == 2
    assert by_block.commands == by_object.commands == 25
    assert by_block.stats.values() == by_object.stats.values()


def test_the_age_of_the_update_an_answer_used_at_its_states_time() -> None:
    """The hosted publisher takes several cycles at once, milliseconds after they ran: each
    command's update age is that of the update its answer names (``update_seq``), at the
    time of its state, not the newest update's when it is published."""
    sc = load_scenario('circle')
    port = ControllerPort(build_controller_loop(sc, sc.mode), sc.update_period,
                          sc.linkage.task.dim, sc.dt)
    ve = virtual_environment(sc)
    assert port.age_of(-1, 1.0) == math.inf          # no update yet
    port.on_update(ve.snapshot(seq=0), 0.500, apply=False)
    port.on_update(ve.snapshot(seq=1), 0.510, apply=False)
    assert port.age_of(0, 0.5075) == pytest.approx(0.0075, abs=1e-15)
    assert port.age_of(1, 0.5125) == pytest.approx(0.0025, abs=1e-15)
    assert port.age_of(1, 0.509) == 0.0               # never negative
    assert port.age_of(7, 0.52) == port.update_age(0.52)   # not one it took: the newest's
    # the block form: published at 0.515, the cycles ran at 0.5075 with update 0
    age, _ = port.answered_block(None, 507_500_000, 0.515, 0.5075, used=(0, 0.5075))
    assert age == port.age_of(0, 0.5075)
    age, _ = port.answered_block(None, 507_500_000, 0.515, 0.5075)
    assert age == port.update_age(0.515)
    # a restarted VE numbers from 0 again: the newest arrival counts
    port.on_update(ve.snapshot(seq=0), 0.600, apply=False)
    assert port.age_of(0, 0.601) == pytest.approx(0.001, abs=1e-15)
    # only the newest ARRIVALS_KEPT are remembered
    for k in range(2, 2 + ARRIVALS_KEPT):
        port.on_update(ve.snapshot(seq=k), 0.7 + 0.01 * k, apply=False)
    assert port.age_of(1, 2.0) == port.update_age(2.0)
    assert port.age_of(2, 0.73) == pytest.approx(0.01, abs=1e-15)
