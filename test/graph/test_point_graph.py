"""A point grasp through the ROS 2 node graph: ``haptic-topology run fig8_point --clock
lockstep`` (hosted layout: the loop in the device driver's loop process) records what
``simulate`` computes, bit for bit; its bag reads back as a ``planar_point`` run from its
metadata alone, ``analyze`` gives the same drift figures, and ``replay --check-controller``
reproduces every recorded command exactly.

Every process runs in the session's random ROS_DOMAIN_ID (``conftest.ros_domain_env``); every
wait has a deadline.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from offline_check import EXACT_COLUMNS

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace
from haptic_topology.vocabulary import TaskSpace

pytestmark = pytest.mark.graph

#: Simulated seconds of the run.
DURATION = 0.3
SUMMARY_KEYS = ('final_distance_m', 'max_distance_m', 'rms_distance_m', 'constrained_time_s',
                'workspace_limit_time_s', 'samples')


def _cli(*args: str, timeout: float) -> str:
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', *args],
                          capture_output=True, timeout=timeout, check=False)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 0, out
    return out


@pytest.fixture(scope='module')
def point_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The bag of ``run fig8_point --clock lockstep --duration 0.3`` and run's output."""
    bag = tmp_path_factory.mktemp('point') / 'fig8_point'
    out = _cli('run', 'fig8_point', '--clock', 'lockstep', '--duration', str(DURATION),
               '--out', str(bag), timeout=240)
    return bag, out


def test_lockstep_run_of_a_point_grasp_equals_simulate(point_bag: tuple[Path, str]) -> None:
    """Every exact column of the bag's trace (read with no scenario given: the task from the
    bag's metadata) and the VE's constraint counts equal ``simulate``'s bit for bit; the
    trace run wrote (trace.parquet) is the same, its task planar_point."""
    bag, out = point_bag
    assert '\ndevice: backend sim_maglev, sim_maglev planar_point\n' in out, out
    sc = load_scenario('fig8_point')
    offline = simulate(replace(sc, duration=DURATION))
    run = read_graph_bag(bag)
    graph = run.trace
    assert graph.task is TaskSpace.PLANAR_POINT and graph.task_dim == 2
    assert run.skipped == {}
    assert len(graph) == len(offline) == round(DURATION / sc.dt) + 1
    np.testing.assert_array_equal(graph.t, offline.t)
    for col in (*EXACT_COLUMNS, 'constraint_count', 'lmi_constraint_count', 'status'):
        np.testing.assert_array_equal(graph.columns[col], offline.columns[col], err_msg=col)
    g, o = graph.summary(), offline.summary()
    assert {k: g[k] for k in SUMMARY_KEYS} == {k: o[k] for k in SUMMARY_KEYS}
    assert run.loop['max_consecutive_missed'] == 0
    written = Trace.from_csv(bag / 'trace.parquet')
    assert written.meta['task'] == 'planar_point'
    for col in EXACT_COLUMNS:
        np.testing.assert_array_equal(written.columns[col], graph.columns[col], err_msg=col)


def test_analyze_reads_the_point_bag(point_bag: tuple[Path, str], tmp_path: Path) -> None:
    """``haptic-topology analyze`` of the bag: the drift figures of ``simulate`` and a plot."""
    bag, _ = point_bag
    _cli('analyze', str(bag), '--out', str(tmp_path / 'an'), timeout=120)
    summary = json.loads((tmp_path / 'an' / 'summary.json').read_text())
    (row,) = summary['runs']
    offline = simulate(replace(load_scenario('fig8_point'), duration=DURATION)).summary()
    assert {k: row[k] for k in SUMMARY_KEYS} == {k: offline[k] for k in SUMMARY_KEYS}
    assert (tmp_path / 'an' / 'fig8_point.png').is_file()


def test_replay_check_controller_of_the_point_bag(point_bag: tuple[Path, str]) -> None:
    """``haptic-topology replay BAG --check-controller``: a live controller fed the recorded
    states and updates answers every one with the recorded wrench, difference 0."""
    bag, _ = point_bag
    out = _cli('replay', str(bag), '--check-controller', timeout=180)
    n = round(DURATION / 0.001) + 2      # the engagement state's command too
    assert (f'controller check (fig8_point, penalty): {n} commands compared of {n} recorded '
            '(0 not answered live); max |difference| 0 (tolerance 1e-09): OK') in out, out
