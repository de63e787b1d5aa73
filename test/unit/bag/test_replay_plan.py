"""The controller check's plan (:func:`~haptic_topology.bag.replay.controller_plan`) in time
linear in the bag: counted as the lines it runs (deterministic, unlike a wall-clock time),
for a synthetic bag of N and of 4N states; and the plans of the reference bag and of a
synthetic one stay what they were (the verdicts of the live check follow from them,
``test/graph/test_replay.py``)."""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import Any

import pytest

from haptic_topology.bag import replay
from haptic_topology.bag.reader import open_bag
from haptic_topology.bag.replay import ControllerPlan, controller_plan, plan

REPO = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(REPO / 'test' / 'support'))
from synthetic_bag import write_bag  # noqa: E402

#: The Fig. 8 reference as first recorded (older message definitions; bags/reference_fig8 is
#: re-recorded with the current ones): the plans below are pinned to it.
REFERENCE = REPO / 'test' / 'fixtures' / 'old_messages' / 'reference_fig8'


def _steps(bag: Path) -> int:
    """Lines run in :mod:`haptic_topology.bag.replay` (each turn of a loop or comprehension
    counts: :func:`sys.settrace` reports a backward jump as a line) by ``controller_plan`` of
    ``bag``: its work, without the reading and decoding below it."""
    opened = open_bag(bag)
    count = 0

    def local(frame: Any, event: str, arg: Any) -> Any:
        nonlocal count
        if event == 'line':
            count += 1
        return local

    def trace(frame: Any, event: str, arg: Any) -> Any:
        return local if frame.f_code.co_filename == replay.__file__ else None

    sys.settrace(trace)
    try:
        controller_plan(opened)
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


def _fingerprint(cp: ControllerPlan) -> tuple[int, int, int, int, str, str]:
    h = hashlib.sha256()
    for it in cp.items:
        h.update(repr((round(it.t, 12), it.topic, it.msgtype, it.seq)).encode())
        h.update(it.data)
    h.update(repr(sorted((s, int(c.mode), tuple(c.wrench))
                         for s, c in cp.commands.items())).encode())
    return (len(cp.items), cp.matched_updates, cp.updates, len(cp.commands), cp.mode,
            h.hexdigest()[:16])


@pytest.mark.parametrize(('which', 'expected'), [
    ('reference', (2004, 161, 416, 1606, 'penalty', '990d579203419e82')),
    ('synthetic', (5500, 500, 500, 5000, 'penalty', '77282f572d104d6a')),
])
def test_the_plan_is_what_it_was(tmp_path: Path, which: str,
                                 expected: tuple[int, int, int, int, str, str]) -> None:
    """Items (times, topics, bytes, state seqs) and recorded commands as the plan gave them
    before it was made linear."""
    path = REFERENCE
    if which == 'synthetic':
        path = tmp_path / 'b'
        write_bag(path, 5000)
    assert _fingerprint(controller_plan(open_bag(path))) == expected


def test_plain_replay_plan_of_the_reference_bag() -> None:
    items = plan(open_bag(REFERENCE))
    h = hashlib.sha256()
    for it in items:
        h.update(repr((round(it.t, 12), it.topic)).encode())
        h.update(it.data)
    assert (len(items), h.hexdigest()[:16]) == (4945, '0ae73848922c6f5f')
