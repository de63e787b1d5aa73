"""The replays' plans scale with the bag: the controller check's plan
(:func:`~haptic_topology.bag.controller_check.controller_plan`) in time linear in the bag,
counted as the lines it runs (deterministic, unlike a wall-clock time), for a synthetic bag
of N and of 4N states; both plans and the check's comparison in memory flat in the bag's
length (tracemalloc's peak, deterministic for a given code); and the plans of the reference
bag and of synthetic ones stay what they were (the verdicts of the live check follow from
them, ``test/graph/test_replay.py``)."""

from __future__ import annotations

import hashlib
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.bag import controller_check
from haptic_topology.bag.controller_check import CommandCheck, ControllerPlan, controller_plan
from haptic_topology.bag.reader import iter_messages, open_bag
from haptic_topology.bag.replay import DEFAULT_TOLERANCE, ReplayStats, plan
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

REPO = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(REPO / 'test' / 'support'))
from synthetic_bag import write_bag  # noqa: E402

#: The Fig. 8 reference as first recorded (older message definitions; bags/reference_fig8 is
#: re-recorded with the current ones): the plans below are pinned to it.
REFERENCE = REPO / 'test' / 'fixtures' / 'old_messages' / 'reference_fig8'


def _check(bag: Path) -> tuple[ControllerPlan, CommandCheck]:
    """The controller check of ``bag`` without the live controller: the plan published
    through, each state answered with its recorded command as the controller answers it."""
    cp = controller_plan(open_bag(bag))
    check = CommandCheck(cp)
    for it in cp.items():
        ci = cp.command(it.seq) if it.seq >= 0 else -1
        if ci >= 0:
            check.answer(it.seq, int(cp.modes[ci]), cp.recorded_wrench(ci).copy())
    return cp, check


def _steps(bag: Path) -> int:
    """Lines run in :mod:`haptic_topology.bag.controller_check` (each turn of a loop or
    comprehension counts: :func:`sys.settrace` reports a backward jump as a line) by the
    plan of ``bag`` and its items: its work, without the reading and decoding below it."""
    count = 0

    def local(frame: Any, event: str, arg: Any) -> Any:
        nonlocal count
        if event == 'line':
            count += 1
        return local

    def trace(frame: Any, event: str, arg: Any) -> Any:
        return local if frame.f_code.co_filename == controller_check.__file__ else None

    sys.settrace(trace)
    try:
        for _ in controller_plan(open_bag(bag)).items():
            pass
    finally:
        sys.settrace(None)
    return count


def test_the_plan_grows_linearly_with_the_bag(tmp_path: Path) -> None:
    """4 times the states: about 4 times the steps (it was ~16 times and more: every
    command rebuilt the set of answered states, every state scanned the updates left)."""
    n = 1000
    write_bag(tmp_path / 'n', n)
    write_bag(tmp_path / 'n4', 4 * n)
    small, large = _steps(tmp_path / 'n'), _steps(tmp_path / 'n4')
    assert large < 4.5 * small, (small, large)


def _peak(run: Callable[[], object]) -> int:
    """tracemalloc's peak (bytes) while ``run`` runs."""
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


#: What the check may keep per recorded command, in its numpy arrays (it keeps ~75 bytes:
#: the state seq, mode, update_seq, a 3-component wrench, the difference, flags; a Python
#: object per message takes 100 bytes and more, besides the message's bytes).
ARRAY_BYTES_PER_STATE = 120


def test_memory_is_flat_in_the_bag_s_length(tmp_path: Path) -> None:
    """4 times the states: the same peak of memory, but for the check's compact arrays
    (``ARRAY_BYTES_PER_STATE``). Plain replay's plan holds no message beyond the window of
    its reorder buffer (none here: written in time order), the check's plan and comparison
    none at all; a bag of a 15-minute run (900,000 states) was 2-3 GB when they held every
    message."""
    n = 1000
    write_bag(tmp_path / 'n', n)
    write_bag(tmp_path / 'n4', 4 * n)
    _check(tmp_path / 'n')                      # caches (typestores) filled before
    sum(1 for _ in plan(open_bag(tmp_path / 'n')))
    check = [_peak(lambda b=b: _check(tmp_path / b)[1].result(
        DEFAULT_TOLERANCE, 'fig8', ReplayStats())) for b in ('n', 'n4')]
    plain = [_peak(lambda b=b: sum(1 for _ in plan(open_bag(tmp_path / b))))
             for b in ('n', 'n4')]
    assert check[1] < 1.1 * check[0] + ARRAY_BYTES_PER_STATE * 4 * n, check
    assert plain[1] < 1.1 * plain[0], plain


def test_the_check_compares_each_answer_as_it_arrives(tmp_path: Path) -> None:
    """The verdict's figures from the answers: the first answer to a state counts, another
    mode or wrench is the difference, a state never answered is missing."""
    write_bag(tmp_path / 'b', 200)
    cp, _ = _check(tmp_path / 'b')
    check = CommandCheck(cp)
    for seq in range(1, 201):
        if seq == 7:
            continue                            # never answered
        ci = cp.command(seq)
        wrench = cp.recorded_wrench(ci) + (0.25 if seq == 9 else 0.0)
        check.answer(seq, 1 if seq == 11 else int(cp.modes[ci]), wrench)
        check.answer(seq, int(cp.modes[ci]), wrench + 5.0)   # a repeat: not counted
    assert 9 in check and 7 not in check
    res = check.result(DEFAULT_TOLERANCE, 'fig8', ReplayStats())
    assert (res.compared, res.recorded, res.replayed, res.missing) == (199, 200, 199, 1)
    assert res.missing_seqs.tolist() == [7] and res.max_abs_diff == np.inf
    assert res.diffs[res.seqs == 9].tolist() == [0.25] and not res.ok
    assert int(np.count_nonzero(res.diffs)) == 2


def test_commands_whose_update_the_bag_lacks_are_not_checked(tmp_path: Path) -> None:
    """A bag cut after the commands naming LMI update 20 and before that update (its recorder
    received it after them): the controller's inputs from state 191 on are not in the bag, so
    the plan ends before it and the verdict counts its 10 commands as not checked, naming the
    update, instead of comparing them with a controller that never had it."""
    write_bag(tmp_path / 'b', 200, without=frozenset({20}))
    cp, check = _check(tmp_path / 'b')
    states = [it.seq for it in cp.items() if it.seq >= 0]
    assert states == list(range(1, 191)), f'published states {states[0]}..{states[-1]}'
    res = check.result(DEFAULT_TOLERANCE, 'fig8', ReplayStats())
    assert (res.compared, res.recorded, res.missing, res.unchecked, res.unchecked_from,
            res.absent_update) == (190, 200, 0, 10, 191, 20) and res.ok
    assert ('190 commands compared of 200 recorded (0 not answered live, 10 not checked: '
            'from state 191 on, LMI update 20, which the controller had taken, is not in the '
            'bag)') in res.line()
    write_bag(tmp_path / 'whole', 200)
    _, whole = _check(tmp_path / 'whole')
    res = whole.result(DEFAULT_TOLERANCE, 'fig8', ReplayStats())
    assert (res.compared, res.unchecked, res.absent_update) == (200, 0, -1)
    assert 'not checked' not in res.line()


def _fingerprint(cp: ControllerPlan) -> tuple[int, int, int, int, str, str]:
    h = hashlib.sha256()
    n = 0
    for it in cp.items():
        h.update(repr((round(it.t, 12), it.topic, it.msgtype, it.seq)).encode())
        h.update(it.data)
        n += 1
    recorded = list(cp.recorded_commands())
    h.update(repr([(s, m, tuple(w)) for s, m, w in recorded]).encode())
    return (n, cp.matched_updates, cp.updates, len(recorded), cp.mode, h.hexdigest()[:16])


@pytest.mark.parametrize(('which', 'expected'), [
    ('reference', (2004, 161, 416, 1606, 'penalty', '990d579203419e82')),
    ('synthetic', (5500, 500, 500, 5000, 'penalty', '77282f572d104d6a')),
])
def test_the_plan_is_what_it_was(tmp_path: Path, which: str,
                                 expected: tuple[int, int, int, int, str, str]) -> None:
    """Items (times, topics, bytes, state seqs) and recorded commands as the plan gave them
    when it held them all in memory (the same fingerprints), read from the bag as they are
    taken; a second pass gives them again."""
    path = REFERENCE
    if which == 'synthetic':
        path = tmp_path / 'b'
        write_bag(path, 5000)
    cp = controller_plan(open_bag(path))
    assert _fingerprint(cp) == expected
    assert _fingerprint(cp) == expected
    assert cp.topics == {'/haptic/device/state': type_name('DeviceState'),
                         '/haptic/lmi/update': type_name('LmiUpdate')}


def _plain(items: Any) -> tuple[int, str]:
    h = hashlib.sha256()
    n = 0
    for it in items:
        h.update(repr((round(it.t, 12), it.topic, it.msgtype)).encode())
        h.update(it.data)
        n += 1
    return n, h.hexdigest()[:16]


@pytest.mark.parametrize(('which', 'kwargs', 'expected'), [
    ('reference', {}, (4945, '39a38e54c340dcf0')),
    ('reference', {'start_offset': 0.5}, (4891, 'b717fc74bd88e0a5')),
    ('reference', {'topics': ['haptic/lmi/update', '/haptic/device/state']},
     (2574, 'e6f238ccab1a2265')),
    ('synthetic', {}, (11000, 'dc16c56c0fbda92a')),
])
def test_plain_replay_plan_is_what_it_was(tmp_path: Path, which: str, kwargs: Any,
                                          expected: tuple[int, str]) -> None:
    """The plain plan as it was when it sorted a list of every message (the same
    fingerprints), read from the bag each time it is iterated (``--loop``)."""
    path = REFERENCE
    if which == 'synthetic':
        path = tmp_path / 'b'
        write_bag(path, 5000)
    items = plan(open_bag(path), **kwargs)
    assert _plain(items) == expected
    assert _plain(items) == expected


def test_plain_replay_orders_a_bag_written_out_of_time_order(tmp_path: Path) -> None:
    """Receive times out of file order (up to 3 ms back across topics, equal times too):
    the plan gives the messages sorted by time, equal times in file order, as sorting the
    whole bag does, through a window as deep as the bag's largest step back."""
    names = ['/haptic/device/state', '/haptic/device/command', '/haptic/lmi/update']
    w = BagWriter(tmp_path / 'b', [TopicSpec(t, type_name('DeviceState'),
                                             (make_qos(False, 1),)) for t in names],
                  typestore_with_haptic_msgs(), sources=message_definitions(),
                  chunk_size=20_000, compression='none')
    rng = np.random.default_rng(3)
    for i in range(3000):
        w.write(i % 3, 1_000_000_000 + (i // 4) * 1_000_000 - int(rng.integers(0, 3)) *
                1_000_000, i.to_bytes(4, 'little') * 8)
    w.close()
    bag = open_bag(tmp_path / 'b')
    items = plan(bag, start_offset=0.2)
    times = [m.log_time for m in iter_messages(bag)]
    t0 = min(times) + 200_000_000
    expected = sorted((((m.log_time - t0) * 1e-9, m.topic, m.data) for m in iter_messages(bag)
                       if m.log_time >= t0), key=lambda e: e[0])   # stable: file order kept
    got = [(it.t, it.topic, it.data) for it in items]
    back = max(max(times[:i]) - t for i, t in enumerate(times) if i)
    assert items.window == back == 2_000_000 and len(got) == len(expected) > 2000
    assert got == expected
    assert items.span == expected[-1][0]
