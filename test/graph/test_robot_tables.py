"""``haptic-topology run`` with a robot's own collision meshes: the Panda and the UR5
(``config/robots/``, their URDFs' STL meshes, no link replaced by a capsule) pushed onto a
table and into a box (``panda_table``, ``ur5_table``). In lock-step the graph records what
``simulate`` computes (the VE's coal queries on the meshes' hulls, the LMI's contact forces
every cycle), and the run's summary has the contact the offline run has. The offline
reference runs in this process, whatever ran in it before: a run depends only on its inputs
(``test_a_run_does_not_depend_on_what_ran_before_it_in_the_process``)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from offline_check import assert_equals_offline

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace

pytestmark = pytest.mark.graph

#: Simulated seconds: the hand reaches the table at about 0.24-0.30 s.
DURATION = 0.6


def _offline(scenario: str) -> Trace:
    return simulate(replace(load_scenario(scenario), duration=DURATION))


@pytest.mark.parametrize('scenario', ['panda_table', 'ur5_table'])
def test_a_robot_on_a_table_through_its_meshes_runs_as_simulate(scenario: str,
                                                                tmp_path: Path) -> None:
    bag = tmp_path / scenario
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', scenario, '--clock', 'lockstep',
         '--duration', f'{DURATION}', '--no-plot', '--out', str(bag)], capture_output=True,
        timeout=300)
    assert proc.returncode == 0, (proc.stdout + proc.stderr).decode(errors='replace')
    trace = _offline(scenario)
    assert_equals_offline(read_graph_bag(bag).trace, scenario, 'penalty', DURATION,
                          offline=trace)
    offline = trace.summary()
    summary = json.loads((bag / 'summary.json').read_text())
    assert offline['max_penetration_m'] > 0.0       # the meshes touched the table
    assert summary['max_penetration_m'] == pytest.approx(offline['max_penetration_m'],
                                                         rel=1e-9, abs=0.0)
    assert summary['contact_time_s'] == offline['contact_time_s']
