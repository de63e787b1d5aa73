"""What the controller and the VE take of their own graph's messages
(:mod:`haptic_topology.control.admission`, :class:`~haptic_topology.messages.check.
SourceGate`): exact refusals by reason, and no refusal of what the offline simulation
sends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from haptic_topology.control.admission import HandAdmission, UpdateAdmission
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import MessageError
from haptic_topology.messages.check import SourceGate
from haptic_topology.sim import load_scenario
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    initial_device_pose,
    virtual_environment,
)
from haptic_topology.sim.scenario import Scenario


def _reason(call: object, *args: object) -> tuple[str, str]:
    with pytest.raises(MessageError) as info:
        call(*args)                                        # type: ignore[operator]
    return info.value.reason, str(info.value)


def _run(sc: Scenario) -> tuple[list[tuple[object, float]], list[tuple]]:
    """The LMI updates (with their time, s) and the hand-input batches of ``sc`` run as
    ``simulate`` runs it (the VE takes every input; an update every update period); each
    batch as ``HandAdmission.admit``'s arguments (seqs, state seqs, stamps, pose, twist)."""
    ve = virtual_environment(sc)
    cycle = HostedCycle(build_device_loop(sc),
                        build_controller_loop(sc, sc.mode, update_period=sc.update_period))
    updates = [(ve.snapshot(seq=0), 0.0)]
    cycle.offer_update(updates[0][0])
    batches: list[tuple] = []
    batch: list[tuple] = []
    inputs = 0
    cycle.step(0.0, sc.dt, 0.0)     # engagement: one idle state, as simulate's
    for k in range(int(round(sc.duration / sc.dt))):
        t = k * sc.dt
        done = cycle.step(t, sc.dt, t)
        hand = done.answer.hand if done.answer is not None else None
        if hand is None:
            continue
        ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
        inputs += 1
        batch.append((hand.seq, hand.state_seq, t, done.tick.reading.pose.copy(),
                      done.tick.reading.twist.copy()))
        if inputs % sc.update_period == 0:
            seqs, state_seqs, stamps, pose, twist = zip(*batch, strict=True)
            batches.append((list(seqs), list(state_seqs), list(stamps), np.array(pose),
                            np.array(twist)))
            batch = []
            updates.append((ve.snapshot(seq=len(updates)), t))
            cycle.offer_update(updates[-1][0])
    return updates, batches


@pytest.mark.parametrize('name', ['fig8', 'wall', 'spatial_arm4'])
def test_every_update_and_batch_of_a_run_is_admitted(name: str) -> None:
    sc = load_scenario(name)
    updates, batches = _run(sc)
    gate = SourceGate('lmi/update', 've_sim')
    gate.observe(frozenset({b've'}), ())
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    for snap, _ in updates:
        admit.admit(snap)                                  # raises on a refusal
    # as the wall clock's VE checks them, and as the lock-step one (every input, in order,
    # the first where simulate starts the device)
    for hands in (HandAdmission(sc.linkage.task),
                  HandAdmission(sc.linkage.task, complete=True,
                                origin=initial_device_pose(sc))):
        for batch in batches:
            hands.admit(*batch)
    assert len(updates) > 100 and len(batches) == len(updates) - 1


def test_an_update_of_another_model_or_an_older_input_is_refused_and_the_own_ones_go_on(
        ) -> None:
    sc = load_scenario('fig8')
    updates = [u for u, _ in _run(dataclasses.replace(sc, duration=0.2))[0]]
    admit = UpdateAdmission(LinkageDynamics(sc.linkage))
    admit.admit(updates[0])
    # each LMI quantity altered in turn: named in the refusal
    for field, change in (('mass_matrix', lambda a: a * 1.001),
                          ('gravity', lambda a: a + 0.01),
                          ('hand_jacobian', lambda a: a + 1e-6),
                          ('hand_pose', lambda a: a + np.array([0.02, 0.0, 0.0])),
                          ('hand_twist', lambda a: a + 1e-6)):
        bad = dataclasses.replace(updates[1], **{field: change(getattr(updates[1], field))})
        reason, text = _reason(admit.admit, bad)
        assert reason == 'model' and text.startswith(f'LmiUpdate 1: {field} differs'), text
    # the VE's own code at another q is consistent with the model: it passes this check
    far = virtual_environment(dataclasses.replace(sc, q0=sc.q0 + 0.3)).snapshot(seq=1)
    UpdateAdmission(LinkageDynamics(sc.linkage)).admit(far)
    for snap in updates[1:]:                               # the own ones go on
        admit.admit(snap)
    # an update of the run numbered as the next: consistent, but the VE went back in time
    stale = dataclasses.replace(updates[5], seq=len(updates))
    reason, text = _reason(admit.admit, stale)
    assert reason == 'continuity' and text == (
        f'LmiUpdate {len(updates)}: consumed hand input {updates[5].hand_input_seq} after '
        f'update {len(updates) - 1} had consumed {updates[-1].hand_input_seq}: a VE never '
        'goes back (it drops its inputs only for a new controller)')
    # an update of before the first input (-1), numbered as the next: refused too ...
    idle = dataclasses.replace(updates[0], seq=len(updates))
    assert idle.hand_input_seq == -1
    reason, text = _reason(admit.admit, idle)
    assert reason == 'continuity' and 'consumed no hand input after' in text
    # ... unless this controller's loop started over (the VE then says -1 for it)
    admit.forget()
    admit.admit(idle)


def test_after_the_loop_starts_over_updates_on_the_old_loops_input_set_no_reference(
        ) -> None:
    """Until the VE has the new loop's first batch, its updates consume the input it held
    from the loop before, numbered beyond anything the new loop has sent: taken, and not
    what the new loop's inputs are compared with. Those then are, as always."""
    sc = load_scenario('fig8')
    updates = [u for u, _ in _run(dataclasses.replace(sc, duration=0.2))[0]]
    admit = UpdateAdmission(LinkageDynamics(sc.linkage))
    for snap in updates[:10]:
        admit.admit(snap)
    held = updates[9].hand_input_seq
    assert held > 20

    def consumed(k: int, seq: int) -> object:
        return dataclasses.replace(updates[k], hand_input_seq=seq)

    admit.forget()
    admit.admit(consumed(10, held))         # the VE's updates before the new loop's batch
    admit.admit(consumed(11, held))
    admit.sent(10)                          # the new loop's first batch: inputs 1-10
    admit.admit(consumed(12, held))         # sent before the VE had it
    admit.admit(consumed(13, 3))            # the VE dropped its held input, took 1-3
    admit.admit(consumed(14, 10))
    reason, text = _reason(admit.admit, consumed(15, 5))
    assert (reason, text) == ('continuity', 'LmiUpdate 15: consumed hand input 5 after '
                              'update 14 had consumed 10: a VE never goes back (it drops its '
                              'inputs only for a new controller)')


def test_after_the_loop_starts_over_an_old_update_is_still_no_restart() -> None:
    """A new loop process (``forget``) drops the comparison of consumed inputs, not the
    numbering: an exact copy of an earlier update that comes then is refused (one CI run
    took such an echo, sent by an impostor with the graph's id, for a restarted VE)."""
    sc = load_scenario('fig8')
    updates = [u for u, _ in _run(dataclasses.replace(sc, duration=0.1))[0]]
    gate = SourceGate('lmi/update', 've_sim')
    gate.observe(frozenset({b've'}), ())
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    for snap in updates[:6]:
        admit.admit(snap)
    admit.forget()
    reason, text = _reason(admit.admit, updates[2])
    assert (reason, text) == ('session', 'lmi/update: seq 2 after 5 but no new ve_sim '
                              'endpoint: not a restart, refused')
    # the VE's next update, saying -1 for the new loop's inputs, is taken; then the inputs
    # are compared again
    admit.admit(dataclasses.replace(updates[6], hand_input_seq=-1))
    admit.admit(updates[7])
    reason, _ = _reason(admit.admit, dataclasses.replace(updates[8], hand_input_seq=-1))
    assert reason == 'continuity'


def test_a_restart_is_believed_only_with_a_new_endpoint_of_the_own_publisher() -> None:
    sc = load_scenario('fig8')
    updates, _ = _run(dataclasses.replace(sc, duration=0.1))
    gate = SourceGate('lmi/update', 've_sim')
    gate.observe(frozenset({b'old'}), ())
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    for snap, _ in updates[:5]:
        admit.admit(snap)
    moved = virtual_environment(dataclasses.replace(sc, q0=sc.q0 + 0.3))
    restart = moved.snapshot(seq=0)
    reason, text = _reason(admit.admit, restart)
    assert (reason, text) == ('session', 'lmi/update: seq 0 after 4 but no new ve_sim '
                              'endpoint: not a restart, refused')
    gate.observe(frozenset({b'old', b'new'}), ())          # a ve_sim endpoint it never saw
    admit.admit(restart)                                   # a new session
    admit.admit(moved.snapshot(seq=1))
    reason, _ = _reason(admit.admit, moved.snapshot(seq=0))          # same endpoints again
    assert reason == 'session'


def test_a_false_update_as_the_restarted_ve_appears_uses_nothing_up() -> None:
    """A forged update numbered below the last (seq 0) arrives just as a restarted VE's new
    endpoint appears: it is refused by the model check, and the restarted VE's own first
    update is still taken as a new session (not refused as 'session' until its numbers pass
    the old ones)."""
    sc = load_scenario('fig8')
    updates, _ = _run(dataclasses.replace(sc, duration=0.1))
    gate = SourceGate('lmi/update', 've_sim')
    gate.observe(frozenset({b'old'}), ())
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    for snap, _ in updates[:5]:
        admit.admit(snap)
    gate.observe(frozenset({b'new'}), ())                   # the VE restarted
    forged = dataclasses.replace(updates[0][0], gravity=updates[0][0].gravity + 1.0)
    reason, _ = _reason(admit.admit, forged)
    assert reason == 'model'
    admit.admit(dataclasses.replace(updates[0][0], hand_input_seq=-1))   # the real one
    admit.admit(updates[1][0])


def test_a_false_batch_as_a_restarted_controller_appears_uses_nothing_up() -> None:
    """The hand-input side of the same: a copy numbered from 1 again and refused for its
    continuity does not use up the new controller endpoint's session."""
    sc = load_scenario('fig8')
    _, batches = _run(dataclasses.replace(sc, duration=0.1))
    gate = SourceGate('hand_inputs', 'lmi_controller')
    gate.observe(frozenset({b'old'}), ())
    hands = HandAdmission(sc.linkage.task, gate, complete=True)
    for batch in batches[:3]:
        hands.admit(*batch)
    gate.observe(frozenset({b'new'}), ())                   # the controller restarted
    seqs, states, stamps, pose, twist = batches[0]
    reason, _ = _reason(hands.admit, [5, 6], states[:2], [0.0, 0.0], pose[:2], twist[:2])
    assert reason == 'continuity'                           # not input 1: refused
    hands.admit(seqs, states, stamps, pose, twist)          # the new controller's own


def test_updates_taken_before_their_publisher_was_discovered_are_the_sessions() -> None:
    """Under load the VE's first updates can arrive before its endpoint is in the graph the
    controller sees: the endpoint discovered then is the session's, so a copy numbered below
    is no restart (one CI run under load believed such a restart)."""
    sc = load_scenario('fig8')
    updates, _ = _run(dataclasses.replace(sc, duration=0.1))
    gate = SourceGate('lmi/update', 've_sim')
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    for snap, _ in updates[:3]:
        admit.admit(snap)                                  # no ve_sim endpoint seen yet
    gate.observe(frozenset({b've'}), ('/intruder',))       # discovered now
    reason, text = _reason(admit.admit, updates[0][0])     # an echo of the first update
    assert (reason, text) == ('session', 'lmi/update: seq 0 after 2 but no new ve_sim '
                              'endpoint: not a restart, refused')
    admit.admit(updates[3][0])
    gate.observe(frozenset({b've', b'new'}), ())           # a restarted VE is still believed
    admit.admit(dataclasses.replace(updates[0][0], hand_input_seq=-1))


def test_no_update_is_taken_while_the_own_publisher_is_gone_and_a_foreign_one_is_there() -> None:
    sc = load_scenario('fig8')
    updates, _ = _run(dataclasses.replace(sc, duration=0.05))
    gate = SourceGate('lmi/update', 've_sim')
    admit = UpdateAdmission(LinkageDynamics(sc.linkage), gate)
    gate.observe(frozenset(), ('/intruder',))              # no ve_sim seen yet: none gone
    admit.admit(updates[0][0])
    gate.observe(frozenset({b've'}), ())
    gate.observe(frozenset(), ('/intruder',))              # the VE gone, a foreign one there
    reason, text = _reason(admit.admit, updates[1][0])
    assert reason == 'source' and text == (
        "lmi/update: no ve_sim of this graph publishes it and /intruder does: this graph's "
        'messages on it cannot be told from foreign ones: refused')
    gate.observe(frozenset({b've'}), ('/intruder',))       # back: told apart by graph_id
    admit.admit(updates[1][0])


def test_hand_inputs_copied_shifted_or_back_in_time_are_refused() -> None:
    sc = load_scenario('fig8')
    _, batches = _run(dataclasses.replace(sc, duration=0.1))
    hands = HandAdmission(sc.linkage.task, SourceGate('hand_inputs', 'lmi_controller'))
    (seqs, states, stamps, pose, twist), nxt = batches[0], batches[1]
    hands.admit(seqs, states, stamps, pose, twist)
    shift = np.array([0.02, 0.0, 0.0])
    # a copy 2 cm off, numbered and stamped as the batch taken: not a new controller
    reason, _ = _reason(hands.admit, seqs, states, stamps, pose + shift, twist)
    assert reason == 'session'
    # the next batch 2 cm off: the device cannot get there in one cycle at its twist
    reason, text = _reason(hands.admit, *nxt[:3], nxt[3] + shift, nxt[4])
    assert reason == 'continuity' and 'device pose row 0 moved 0.02' in text, text
    reason, text = _reason(hands.admit, nxt[0], nxt[1], [s - 0.5 for s in nxt[2]], *nxt[3:])
    assert reason == 'continuity' and 'before the previous sample' in text
    hands.admit(*nxt)
    # after lost inputs (a gap in the seqs) the device may be anywhere: not checked
    third = batches[3]
    hands.admit(*third[:3], third[3] + shift, third[4])
    # ... and after a device state it did not answer (the state seqs jump): not checked
    fourth = batches[4]
    skipped = [s + 1 for s in fourth[1]]
    hands.admit(fourth[0], skipped, fourth[2], fourth[3] - shift, fourth[4])
    # a controller that numbers from 1 again, later (a reactivated driver): a new session
    hands.admit([1, 2], [9000, 9001], [1.0, 1.001], nxt[3][:2] + shift, nxt[4][:2])


def test_in_lockstep_a_batch_that_skips_inputs_is_refused_and_the_own_one_goes_on() -> None:
    """Lock-step delivers every input in order: a copy 2 cm off of the batch after next,
    arriving before the controller's next one (delayed on the wire), is refused instead of
    taken unchecked after a gap; the controller's two batches then go on. (A CI run took such
    a copy and then refused every batch of the controller's: the run waited for ever.)"""
    sc = load_scenario('fig8')
    _, b = _run(dataclasses.replace(sc, duration=0.1))
    hands = HandAdmission(sc.linkage.task, complete=True)
    hands.admit(*b[0])
    seqs, states, stamps, pose, twist = b[2]
    reason, text = _reason(hands.admit, seqs, states, stamps, pose + [0.02, 0.0, 0.0], twist)
    assert reason == 'continuity' and text == (
        f'HandInputs seq {seqs[0]} after {b[0][0][-1]}: inputs {b[1][0][0]}-{b[1][0][-1]} '
        'missing, and in lock-step every input arrives, in order')
    hands.admit(*b[1])
    hands.admit(*b[2])
    # the wall clock can lose inputs: there the same batch after a gap is taken (see above)
    wall = HandAdmission(sc.linkage.task)
    wall.admit(*b[0])
    wall.admit(seqs, states, stamps, pose + [0.02, 0.0, 0.0], twist)


def test_in_lockstep_a_copy_of_the_first_batch_is_refused_and_the_own_one_goes_on() -> None:
    """The session's first batch continues no earlier one: in lock-step it starts where the
    run starts (``origin``, the device's pose at t = 0). A copy 2 cm off, arriving before the
    controller's first batch, is refused; the controller's batches are then taken. (A CI run
    took such a copy first and refused the controller's as its copy: the run waited for
    ever.) The controller's own copy moved by less than the slack is taken."""
    sc = load_scenario('fig8')
    _, b = _run(dataclasses.replace(sc, duration=0.1))
    origin = initial_device_pose(sc)
    hands = HandAdmission(sc.linkage.task, complete=True, origin=origin)
    seqs, states, stamps, pose, twist = b[0]
    assert stamps[0] == 0.0 and np.array_equal(pose[0], origin)
    reason, text = _reason(hands.admit, seqs, states, stamps, pose + [0.02, 0.0, 0.0], twist)
    assert reason == 'continuity' and text == (
        f'HandInputs seq {seqs[0]}: device pose row 0 is 0.02 from where the run starts, '
        'expected at most 0.005')
    hands.admit(*b[0])
    hands.admit(*b[1])
    # within the slack (5 mm): taken
    near = HandAdmission(sc.linkage.task, complete=True, origin=origin)
    near.admit(seqs, states, stamps, pose + [0.004, 0.0, 0.0], twist)
    # without an origin (the wall clock) the first batch has nothing to continue: taken
    HandAdmission(sc.linkage.task).admit(seqs, states, stamps, pose + [0.02, 0.0, 0.0], twist)


def test_in_lockstep_a_copy_of_a_later_batch_before_the_first_is_refused() -> None:
    """A session's first batch starts at input 1: a copy 2 cm off of the controller's
    *second* batch, arriving before its first (delayed on the wire), is refused; the
    controller's batches are then taken. (A CI run took such a copy, then the copies after
    it, which continue it, and refused the controller's own: the run waited for ever.)"""
    sc = load_scenario('fig8')
    _, b = _run(dataclasses.replace(sc, duration=0.1))
    hands = HandAdmission(sc.linkage.task, complete=True, origin=initial_device_pose(sc))
    seqs, states, stamps, pose, twist = b[1]
    reason, text = _reason(hands.admit, seqs, states, stamps, pose + [0.02, 0.0, 0.0], twist)
    assert reason == 'continuity' and text == (
        f"HandInputs seq {seqs[0]}: a session's first batch, expected to start at input 1: "
        'in lock-step every input arrives, in order')
    for batch in b:
        hands.admit(*batch)


@pytest.mark.parametrize('lag', [0.0, 1.0, 5.0, 20.0])
def test_in_lockstep_the_controllers_batches_are_taken_in_any_arrival_order(
        lag: float) -> None:
    """Every order in which a copy 2 cm off of each batch (published once the batch is)
    and the controller's batches (in their order, each up to ``lag`` publication intervals
    late) can arrive: the VE takes exactly the controller's batches, each once. 200 seeded
    orders per lag, batches cut at random as the controller cuts partial ones."""
    sc = load_scenario('fig8')
    _, b = _run(dataclasses.replace(sc, duration=0.3))
    inputs = [tuple(np.asarray(f)[i] for f in batch) for batch in b
              for i in range(len(batch[0]))]
    for seed in range(200):
        rng = np.random.default_rng([seed, int(lag)])
        cuts, start = [], 0
        while start < len(inputs):      # at most up to the next multiple of the period
            end = min(start + int(rng.integers(1, sc.update_period + 1)),
                      (start // sc.update_period + 1) * sc.update_period, len(inputs))
            cuts.append(inputs[start:end])
            start = end
        own = [tuple(np.array([x[f] for x in cut]) for f in range(5)) for cut in cuts]
        published = np.cumsum(rng.random(len(own)))
        arrive_own = np.maximum.accumulate(published + lag * rng.random(len(own)))
        arrive_copy = published + 0.3 * rng.random(len(own))
        order = sorted([(t, 0, i) for i, t in enumerate(arrive_own)]
                       + [(t, 1, i) for i, t in enumerate(arrive_copy)])
        hands = HandAdmission(sc.linkage.task, complete=True, origin=initial_device_pose(sc))
        taken = []
        for _, copy, i in order:
            seqs, states, stamps, pose, twist = own[i]
            try:
                hands.admit(list(seqs), list(states), stamps,
                            pose + [0.02, 0.0, 0.0] if copy else pose, twist)
            except MessageError:
                continue
            taken.append((copy, i))
        assert taken == [(0, i) for i in range(len(own))], (seed, order[:8], taken[:8])


def test_a_recorded_message_is_checked_as_its_snapshot() -> None:
    """``UpdateFields.from_msg`` (what ``read_graph_bag`` checks): the wire's fields, with
    ``hand_input_seq`` 0 read as -1 (none consumed), as the node reads them."""
    from types import SimpleNamespace

    from haptic_topology.control.admission import UpdateFields

    sc = load_scenario('fig8')
    updates = [u for u, _ in _run(dataclasses.replace(sc, duration=0.05))[0]]

    def wire(u: object, **change: object) -> SimpleNamespace:
        fields = {k: getattr(u, k) for k in ('seq', 'q', 'dq', 'gravity', 'hand_pose',
                                              'hand_twist')}
        fields.update(hand_input_seq=max(u.hand_input_seq, 0),        # type: ignore[attr-defined]
                      mass_matrix=u.mass_matrix.ravel().tolist(),     # type: ignore[attr-defined]
                      hand_jacobian=u.hand_jacobian.ravel().tolist())  # type: ignore[attr-defined]
        fields.update(change)
        return SimpleNamespace(**fields)

    dof, task = sc.linkage.dof, sc.linkage.task
    first = UpdateFields.from_msg(wire(updates[0]), task, dof)
    assert first.hand_input_seq == -1 == updates[0].hand_input_seq
    admit = UpdateAdmission(LinkageDynamics(sc.linkage))
    for u in updates:
        admit.admit(UpdateFields.from_msg(wire(u), task, dof))
    shifted = wire(updates[-1], seq=len(updates),
                   hand_pose=updates[-1].hand_pose + np.array([0.02, 0.0, 0.0]))
    reason, _ = _reason(admit.admit, UpdateFields.from_msg(shifted, task, dof))
    assert reason == 'model'
    reason, _ = _reason(UpdateFields.from_msg, wire(updates[0], q=[0.0]), task, dof)
    assert reason == 'size'
