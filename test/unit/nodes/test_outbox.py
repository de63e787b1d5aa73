"""``nodes.outbox.until_batch``: how long the hosted publisher sleeps with the wall clock (until
just after the cycle that completes the next batch of hand inputs)."""

from __future__ import annotations

import doctest

import pytest

from haptic_topology.nodes import outbox
from haptic_topology.nodes.outbox import until_batch

MS = 1_000_000


def test_examples() -> None:
    assert doctest.testmod(outbox).failed == 0


@pytest.mark.parametrize(('hand_seq', 'left'), [(1, 9), (9, 1), (10, 10), (11, 9), (20, 10)])
def test_it_wakes_margin_after_the_cycle_that_ends_the_next_batch(hand_seq: int,
                                                                   left: int) -> None:
    got = until_batch(now_ns=1000 * MS, stamp_ns=1000 * MS, hand_seq=hand_seq, batch=10,
                      period_ns=MS, margin_ns=MS // 2, longest=1.0)
    assert got == pytest.approx((left + 0.5) * 1e-3, abs=1e-15)


def test_a_batch_of_one_input_per_cycle_wakes_it_at_most_every_shortest() -> None:
    assert until_batch(0, 0, 5, 1, MS, 0, 0.01, shortest=2e-3) == 2e-3


def test_without_inputs_or_with_stamps_of_another_clock_the_longest_wait() -> None:
    assert until_batch(0, 0, 0, 10, MS, MS // 2, 0.01) == 0.01          # not engaged
    # the record's stamp is simulated time (or the loop stalled): long past its batch
    assert until_batch(1_700_000_000 * 10**9, 5 * MS, 37, 10, MS, MS // 2, 0.01) == 0.01
    # a stamp ahead of this clock: at most the longest wait too
    assert until_batch(0, 10**12, 37, 10, MS, MS // 2, 0.01) == 0.01
