"""Fault injection on the real node graph (one shared run, ~40 s; see ``fault_harness.py``).

Each check asserts what the brief requires of every fault: the wrench applied to the device
(``DeviceState.applied_wrench`` as recorded, every cycle) stays finite and within the limit,
the bags are complete up to the fault (contiguous sequence numbers), the loop recovers by
itself, and a re-sync does not jump by more than the stated bound. Timing bounds are
generous (2-core machine, other test runs beside this one).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fault_harness as fh

pytestmark = pytest.mark.graph

#: Stated bound on the per-cycle change of the applied wrench after a fault (N, x and y): a
#: re-sync steps the force by at most resync_max_jump (1 N, estimated from the VT state; the
#: frozen matrices' change comes on top: ordinary re-syncs on a loaded 2-core machine were
#: measured up to 1.9 N), the fades add at most 0.1 N (controller: 20 N * 1 ms / 0.2 s) or
#: 0.8 N (device: 20 N * 2 ms / 50 ms) per cycle. Without the held re-sync a resumed or
#: restarted ve_sim gave 6-16 N in one cycle.
STEP_BOUND = 2.5
RESTART_BOUND = 20.0     # s: a node process starts in 2-3 s on an idle 2-core machine


@pytest.fixture(scope='module')
def run(tmp_path_factory: pytest.TempPathFactory) -> fh.FaultRun:
    return fh.run_faults(tmp_path_factory.mktemp('faults'))


def test_every_node_survived_and_stopped_cleanly(run: fh.FaultRun) -> None:
    assert run.exit_codes == dict.fromkeys(
        ('device_driver', 'lmi_controller', 've_sim', 'recorder'), 0), run.exit_codes
    for name, text in run.logs.items():
        assert 'Traceback' not in text, f'{name}:\n{text[-3000:]}'


def test_applied_wrench_finite_and_within_limits_at_every_cycle(run: fh.FaultRun) -> None:
    n = 0
    for bag in run.states:
        for s in fh.sessions(bag):
            assert np.all(np.isfinite(s.applied))
            assert np.all(np.abs(s.applied) <= fh.LIMIT + 1e-9), np.abs(s.applied).max(axis=0)
            n += len(s.seqs)
    assert n > 15000
    # The injected 1e9 N commands were clamped to the limit, not passed on.
    assert fh.figures(run, 'bad_messages')['max_ratio'] == pytest.approx(1.0)


def test_bags_complete_up_to_every_fault(run: fh.FaultRun) -> None:
    """Hand inputs (reliable) contiguous per controller in every bag; device states (best
    effort, 1 kHz) contiguous up to the first fault. Later, while a subscriber of the state
    topic is SIGSTOPped, the recorder was seen to miss best-effort states (up to 0.47 s in a
    row, in 2 of ~8 runs on a loaded machine; Fast DDS delivers a writer's samples to the
    readers in turn): at most 5 % is allowed and the README reports it. The killed
    recorder's bag holds everything up to ~its flush period."""
    assert len(run.bags) == 2
    sessions = [fh.sessions(b) for b in run.states]
    assert len(sessions[0]) == 2        # the device_driver was restarted within bag 1
    first_fault = run.events['watchdog'][0]
    missing = total = 0
    for per_bag in sessions:
        for s in per_bag:
            d = np.diff(s.seqs)
            assert np.all(d >= 1)
            early = s.t[1:] < first_fault
            assert np.all(d[early] == 1), s.seqs[1:][early & (d > 1)][:5]
            missing += int(np.sum(d - 1))
            total += int(s.seqs[-1] - s.seqs[0] + 1)
    assert missing <= 0.05 * total, (missing, total)
    # A restarted device_driver is a new DDS writer: the recorder records it once discovery
    # has matched it, which took up to ~2.8 s on a busy 2-core machine (seen in full-suite
    # runs), so the restarted session's first states (idle ones, and maybe the first engaged
    # ones) may be missing from the bag; every state that is there is in order (above).
    for bag_hands in run.hands:
        hands = [int(h.seq) for h in bag_hands if int(h.seq) != fh.INJECTED_SEQ]
        pieces = np.split(np.array(hands), np.flatnonzero(np.diff(hands) <= 0) + 1)
        for p in pieces:
            assert np.all(np.diff(p) == 1), p[np.flatnonzero(np.diff(p) != 1)[:5]]
    assert len(run.hands[0]) > 0
    f = fh.figures(run, 'kill_recorder')
    assert f['tail_s'] < 1.0            # lost at most the last flush period or so


def test_watchdog_fades_out_and_back_in(run: fh.FaultRun) -> None:
    """lmi_controller stopped 100 ms: the output is zero after timeout + ramp (55 ms) and the
    device fades back in by itself."""
    t0, t1 = run.events['watchdog']
    sess = [s for b in run.states for s in fh.sessions(b)]
    t, u, st = fh.window(sess, t0 + 0.08, t1)
    assert np.all(st & fh.WATCHDOG)     # (states the recorder kept; see the bag test)
    assert np.all(u == 0.0)
    assert run.diagnostics['device_driver: loop']['watchdog_trips'] >= 1
    f = fh.figures(run, 'watchdog')
    assert 0.0 < f['recovery_s'] < 2.0
    assert max(f['step_x'], f['step_y']) <= STEP_BOUND


def test_bad_messages_rejected_and_counted_per_reason(run: fh.FaultRun) -> None:
    dev = run.diagnostics['device_driver: loop']
    for reason in ('non_finite', 'size', 'task_dim', 'range'):
        assert dev[f'rejected_{reason}'] >= 1, (reason, dev)
    ctl = run.diagnostics['lmi_controller: loop']
    for reason in ('dof', 'non_finite', 'size', 'range', 'task_dim'):
        assert ctl[f'rejected_{reason}'] >= 1, (reason, ctl)
    ve = run.diagnostics['ve_sim: loop']
    for reason in ('non_finite', 'size', 'range'):
        assert ve[f'rejected_{reason}'] >= 1, (reason, ve)


@pytest.mark.parametrize('fault', ['ve_stop', 'kill_ve_sim', 'kill_lmi_controller',
                                   'kill_device_driver'])
def test_loop_recovers_without_a_jump(run: fh.FaultRun, fault: str) -> None:
    f = fh.figures(run, fault)
    assert f['finite'] == 1.0 and f['max_ratio'] <= 1.0 + 1e-9
    bound = 3.0 if fault == 've_stop' else RESTART_BOUND
    assert 0.0 < f['recovery_s'] < bound, f
    assert max(f['step_x'], f['step_y']) <= STEP_BOUND, f


def test_restarts_were_seen_by_the_others(run: fh.FaultRun) -> None:
    ctl = run.diagnostics['lmi_controller: loop']
    assert ctl['degradations'] >= 1         # ve_sim stopped: force faded out
    assert ctl['resyncs_held'] >= 1
    assert ctl['device_sessions'] >= 2      # the restarted device_driver's seq went back
    ve = run.diagnostics['ve_sim: loop']
    assert ve['controller_restarts'] >= 1
    assert 'VT placed at the device pose' in ''.join(
        t for n, t in run.logs.items() if n.startswith('ve_sim'))
    assert 've_sim restarted' in ''.join(
        t for n, t in run.logs.items() if n.startswith('lmi_controller'))
