"""``nodes.wire.StateSampler``: which device states ``device_driver`` also publishes on
``haptic/device/state_sampled`` (the VE's picture reads them instead of all 1,000 a second),
by the times (ns) it is given."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_topology.nodes.wire import StateSampler

MS = 1_000_000


def _taken(sampler: StateSampler, times: list[int]) -> list[int]:
    return [ns for ns in times if sampler.due(ns)]


def test_thirty_a_second_of_a_1khz_stream_on_a_grid_not_one_every_34_ms() -> None:
    s = StateSampler(30.0)
    taken = _taken(s, [k * MS for k in range(10_000)])           # 10 s of states
    assert len(taken) == s.taken == 300
    # each is the first state at or after k / 30 s
    assert taken == [math.ceil(k * s.period_ns / MS) * MS for k in range(300)]
    assert set(np.diff(taken)) == {33 * MS, 34 * MS}


def test_late_states_keep_the_grid_and_a_gap_starts_it_again() -> None:
    s = StateSampler(10.0)                 # 100 ms periods
    # 0 taken; 150 is in the second period (100-200); 230 in the third
    assert _taken(s, [0, 50 * MS, 150 * MS, 199 * MS, 230 * MS]) == [0, 150 * MS, 230 * MS]
    # a gap of more than a period: taken at once, the grid starts at it
    assert _taken(s, [1000 * MS, 1099 * MS, 1100 * MS]) == [1000 * MS, 1100 * MS]


def test_a_clock_that_goes_back_takes_the_state_at_once() -> None:
    s = StateSampler(30.0)
    assert _taken(s, [5000 * MS, 5001 * MS, 0, 1 * MS, 34 * MS]) == [5000 * MS, 0, 34 * MS]


def test_rate_zero_takes_none_and_a_bad_rate_is_refused() -> None:
    s = StateSampler(0.0)
    assert _taken(s, [k * MS for k in range(100)]) == []
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='rate_hz must be a finite number >= 0'):
            StateSampler(bad)
