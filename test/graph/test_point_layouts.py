"""A point grasp (fig8_point: planar_point, m = 2) in the graph's other layouts: separate
(one process per node, state -> command over DDS), composed (every node in one process) and
thread (the loop in a thread of the driver's process); test_point_graph runs the default,
hosted. In lock-step each records what ``simulate`` computes, bit for bit. On the wall clock
(how many states are answered depends on the machine) the run completes, its bag is a
planar_point run of task_dim 2, and every recorded command is what a live controller fed the
recorded states and updates answers, exactly.

Every graph runs in a domain of its own (``spare_domains``); every wait has a deadline.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from offline_check import EXACT_COLUMNS

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.replay import DEFAULT_TOLERANCE
from haptic_topology.bringup.run import run_graph
from haptic_topology.bringup.watch import VE_STATUS
from haptic_topology.nodes.replay import check_controller
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import TaskSpace

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
SCENARIO = 'fig8_point'
#: Simulated seconds of a lock-step run; wall-clock seconds of the other.
DURATION = 0.3
LAYOUTS = ('separate', 'composed', 'thread')


def _run(tmp_path: Path, layout: str, clock: str, domain: int) -> Path:
    bag = tmp_path / f'{SCENARIO}_{layout}_{clock}'
    codes = run_graph(SCENARIO, 'penalty', DURATION, bag, PARAMS, layout,
                      startup_timeout=90.0, clock=clock, domain_id=domain)
    assert all(c == 0 for c in codes.values()), codes
    return bag


def _ve_tasks(bag: Path) -> set[str]:
    """The values ``task`` of ve_sim's statuses recorded on /diagnostics."""
    decode = decoder()
    tasks = set()
    for raw in iter_messages(open_bag(bag), ['/diagnostics']):
        for status in decode(raw).status:
            if status.name == VE_STATUS:
                tasks |= {kv.value for kv in status.values if kv.key == 'task'}
    return tasks


@pytest.mark.parametrize('layout', LAYOUTS)
def test_lockstep_point_grasp_in_every_layout_equals_simulate(
        layout: str, tmp_path: Path, spare_domains: list[int]) -> None:
    bag = _run(tmp_path, layout, 'lockstep', spare_domains[LAYOUTS.index(layout)])
    sc = load_scenario(SCENARIO)
    offline = simulate(replace(sc, duration=DURATION))
    run = read_graph_bag(bag)
    graph = run.trace
    assert graph.task is TaskSpace.PLANAR_POINT and graph.task_dim == 2
    assert run.skipped == {}
    assert len(graph) == len(offline) == round(DURATION / sc.dt) + 1
    np.testing.assert_array_equal(graph.t, offline.t)
    for col in (*EXACT_COLUMNS, 'constraint_count', 'lmi_constraint_count', 'status'):
        np.testing.assert_array_equal(graph.columns[col], offline.columns[col], err_msg=col)
    assert run.loop['max_consecutive_missed'] == 0
    assert _ve_tasks(bag) == {'planar_point'}


def test_wall_clock_point_grasp_separate_layout(tmp_path: Path,
                                                spare_domains: list[int]) -> None:
    bag = _run(tmp_path, 'separate', 'wall', spare_domains[len(LAYOUTS)])
    run = read_graph_bag(bag)
    assert run.trace.task is TaskSpace.PLANAR_POINT and run.trace.task_dim == 2
    assert len(run.trace) >= 1
    decode = decoder()
    dims = {int(decode(raw).task_dim) for raw in
            iter_messages(open_bag(bag), ['/haptic/device/state', '/haptic/device/command'])}
    assert dims == {2}
    assert _ve_tasks(bag) == {'planar_point'}
    res = check_controller(bag, PARAMS, log_dir=tmp_path)
    assert res.scenario == SCENARIO and res.mode == 'penalty'
    assert res.missing == 0, res.missing_seqs[:20].tolist()
    assert res.compared == res.recorded >= 1
    assert res.max_abs_diff <= DEFAULT_TOLERANCE, res.line()
