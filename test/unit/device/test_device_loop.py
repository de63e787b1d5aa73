"""DeviceLoop statistics (answered cycles, the longest run of consecutive misses) and which
controller it follows (engaged controller, foreign commands, take-over after silence)."""

from __future__ import annotations

import numpy as np

from haptic_topology.device.loop import CommandVerdict, DeviceLoop
from haptic_topology.sim.lockstep import build_device_loop
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode


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


# -- which controller the loop follows --------------------------------------------------------
PENALTY = int(ControlMode.PENALTY)
A, B = 7, 9                                   # controller ids: the engaged one, another
APPLIED, FOREIGN = CommandVerdict.APPLIED, CommandVerdict.FOREIGN


def _engaged(cid: int = A) -> tuple[DeviceLoop, float]:
    """A fig8 device loop engaged by controller ``cid`` and its first running state published;
    returns the loop and the time (s) of that state."""
    loop = build_device_loop(load_scenario('fig8'))
    tick = loop.tick(0.0, loop.period)
    assert loop.on_command(tick.seq, PENALTY, np.zeros(3), 0.0, controller_id=cid) == APPLIED
    loop.tick(loop.period, loop.period)
    assert loop.engaged and loop.controller_id == cid
    return loop, loop.period


def test_module_doc_example() -> None:
    """The example of :mod:`haptic_topology.device.loop`, verdict by verdict."""
    loop = build_device_loop(load_scenario('fig8'))
    for k in range(4):
        loop.tick(0.001 * k, 0.001)           # states 1 to 4
    u, v = np.array([1.0, 0.0, 0.0]), np.array([-5.0, 5.0, 0.5])
    assert loop.on_command(1, PENALTY, u, now=0.000, controller_id=7) == APPLIED
    assert loop.on_command(2, PENALTY, v, now=0.001, controller_id=9) == FOREIGN
    assert loop.on_command(2, PENALTY, u, now=0.001, controller_id=7) == APPLIED
    assert loop.on_command(3, PENALTY, v, now=0.400, controller_id=9) == FOREIGN
    assert loop.on_command(3, PENALTY, v, now=0.501, controller_id=9) == APPLIED
    assert loop.on_command(4, PENALTY, u, now=0.502, controller_id=7) == FOREIGN
    assert (loop.controller_id, loop.takeovers, loop.foreign_commands) == (9, 1, 3)


def test_engaged_controller_applied_impostor_counted_and_never_applied() -> None:
    """While the engaged controller answers every state, another controller's well-formed
    commands answering the same states (before and after the real answer, and states not
    published yet) are rejected and counted, and the device applies exactly the engaged
    controller's wrenches."""
    loop, t = _engaged()
    dt = loop.period
    hostile = np.array([15.0, -15.0, 1.5])
    n = 200
    for k in range(n):
        seq = loop.seq
        u = np.array([0.01 * k, -0.02 * k, 0.001 * k])
        assert loop.on_command(seq, PENALTY, hostile, t, controller_id=B) == FOREIGN
        assert loop.on_command(seq, PENALTY, u, t, controller_id=A) == APPLIED
        assert loop.on_command(seq, PENALTY, hostile, t, controller_id=B) == FOREIGN
        assert loop.on_command(seq + 1, PENALTY, hostile, t, controller_id=B) == FOREIGN
        t += dt
        tick = loop.tick(t, dt)
        np.testing.assert_array_equal(tick.applied, u)      # exactly A's, every cycle
    assert loop.foreign_commands == 3 * n
    assert loop.rejected_commands == 3 * n and loop.rejected_seq == 0
    assert loop.answered == loop.expected == n
    assert (loop.controller_id, loop.takeovers, loop.watchdog.trips) == (A, 0, 0)
    values = loop.values(t)
    assert values['foreign_commands'] == str(3 * n)
    assert values['controller_id'] == str(A) and values['controller_takeovers'] == '0'


def test_restarted_controller_takes_over_once_the_engaged_one_is_silent() -> None:
    """Controller A answers 100 states and dies; the device keeps ticking (the watchdog fades
    the output to zero). A restarted controller B answers every state from 0.2 s after A's
    last command: rejected until A has been silent for takeover_after (0.5 s), then applied,
    faded in by the watchdog; a late command of A is then foreign."""
    loop, t = _engaged()
    dt = loop.period
    u_a, u_b = np.array([1.0, -1.0, 0.1]), np.array([2.0, 3.0, -0.2])
    for _ in range(100):
        assert loop.on_command(loop.seq, PENALTY, u_a, t, controller_id=A) == APPLIED
        t += dt
        loop.tick(t, dt)
    last_a = t - dt                                          # A's last command
    verdicts: list[str] = []
    applied: list[np.ndarray] = []
    for k in range(1, 1000):
        now = last_a + k * dt
        if k >= 200:                                         # B answers from 0.2 s on
            verdicts.append(loop.on_command(loop.seq, PENALTY, u_b, now, controller_id=B))
        t = now + dt
        applied.append(loop.tick(t, dt).applied)
    # B's answers at 0.200 ... 0.499 s of silence are foreign; at 0.5 s (k = 500) it takes over.
    first = verdicts.index(APPLIED)
    assert first == 300 and set(verdicts[:first]) == {FOREIGN}
    assert set(verdicts[first:]) == {APPLIED}
    assert loop.foreign_commands == 300 and loop.takeovers == 1 and loop.controller_id == B
    # The watchdog had faded the output to zero during the silence and fades B in.
    assert loop.watchdog.trips == 1
    np.testing.assert_array_equal(applied[400], np.zeros(3))  # 0.4 s into the silence
    np.testing.assert_array_equal(applied[-1], u_b)          # faded in: exactly B's
    assert loop.on_command(loop.seq, PENALTY, u_a, t, controller_id=A) == FOREIGN
    assert loop.values(t)['controller_takeovers'] == '1'


def test_takeover_needs_a_command_that_would_be_applied() -> None:
    """After the silence a command of another controller answering a state not published, or
    one older than the command held, does not take over; ``takeover_after`` is a parameter
    (here 0.05 s)."""
    loop = build_device_loop(load_scenario('fig8'))
    loop = DeviceLoop(loop.backend, loop.limit, loop.watchdog, loop.period, takeover_after=0.05)
    for k in range(3):
        loop.tick(0.001 * k, 0.001)
    assert loop.on_command(2, PENALTY, np.zeros(3), 0.0, controller_id=A) == APPLIED
    assert loop.on_command(3, PENALTY, np.ones(3), 0.049, controller_id=B) == FOREIGN
    assert loop.on_command(9, PENALTY, np.ones(3), 0.05, controller_id=B) == 'unknown'
    assert loop.on_command(2, PENALTY, np.ones(3), 0.05, controller_id=B) == 'old'
    assert loop.controller_id == A and loop.takeovers == 0
    assert loop.on_command(3, PENALTY, np.ones(3), 0.05, controller_id=B) == APPLIED
    assert (loop.controller_id, loop.takeovers, loop.rejected_commands) == (B, 1, 2)


def test_device_report_levels_and_rejected_counts() -> None:
    """The driver's diagnostics: ERROR with a fault, WARN before configure, the loop's health
    after; malformed commands (refused by the node) add to the loop's own refusals."""
    from haptic_topology.device.loop import device_report
    assert device_report(None, 0.0, '', 2, {})[:2] == (1, 'not configured')
    assert device_report(None, 0.0, 'backend refused', 0, {})[:2] == (2,
                                                                      'fault: backend refused')
    loop, t = _engaged(A)
    assert loop.on_command(2, PENALTY, np.zeros(3), t, controller_id=B) == FOREIGN
    level, message, values = device_report(loop, t, '', 3, {'period_p99_ms': '1.000'})
    assert (level, message) == loop.health() == (0, 'ok')
    assert values['rejected_commands'] == '4'           # 3 malformed + 1 foreign
    assert values['period_p99_ms'] == '1.000' and values['seq'] == str(loop.seq)
    assert device_report(loop, t, 'backend lost', 0, {})[:2] == (2, 'fault: backend lost')
