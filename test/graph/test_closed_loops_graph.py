"""Closed-loop linkages through the node graph: the lock-step graph equals ``simulate`` to
1e-9 at every cycle (the four-bar, hosted and in the separate layout; the five-bar held at
its distal joint and at a proximal link; the Bennett linkage with the 6-DOF device; the
four-bar on a floor, contacts included), and wall-clock runs render the four-bar, the
five-bar and the Bennett linkage."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from offline_check import assert_equals_offline

from haptic_topology.bag.graph_trace import GraphRun, read_graph_bag
from haptic_topology.bringup.run import run_graph
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
#: (scenario, mode, layout, clock, duration s)
RUNS = (('fourbar', 'penalty', 'hosted', 'lockstep', 2.0),
        ('fourbar', 'acceleration_only', 'separate', 'lockstep', 2.0),
        ('bennett', 'penalty', 'hosted', 'lockstep', 1.0),
        ('fourbar_floor', 'penalty', 'hosted', 'lockstep', 1.5),
        ('fivebar_distal', 'penalty', 'hosted', 'lockstep', 2.0),
        ('fivebar_proximal', 'acceleration_only', 'hosted', 'lockstep', 1.0),
        ('fourbar', 'penalty', 'hosted', 'wall', 1.0),
        ('fivebar_distal', 'penalty', 'hosted', 'wall', 1.0),
        ('bennett', 'penalty', 'hosted', 'wall', 1.0))


def _run(tmp: Path, key: tuple[str, str, str, str, float], domain: int) -> GraphRun:
    scenario, mode, layout, clock, duration = key
    bag = tmp / '_'.join(map(str, key))
    codes = run_graph(scenario, mode, duration, bag, PARAMS, layout, startup_timeout=60.0,
                      clock=clock, domain_id=domain)
    assert all(c == 0 for c in codes.values()), codes
    return read_graph_bag(bag, scenario, load_scenario(scenario).lmi_dof)


@pytest.fixture(scope='module')
def runs(tmp_path_factory: pytest.TempPathFactory,
         spare_domains: list[int]) -> dict[tuple[str, str, str, str, float], GraphRun]:
    """The runs, two at a time (lock-step results do not depend on the load; the wall-clock
    run's checks hold on any machine)."""
    tmp = tmp_path_factory.mktemp('closed_loops')
    with ThreadPoolExecutor(2) as pool:
        futures = {key: pool.submit(_run, tmp, key, domain)
                   for key, domain in zip(RUNS, spare_domains, strict=False)}
        return {key: f.result() for key, f in futures.items()}


@pytest.mark.parametrize('key', [k for k in RUNS if k[3] == 'lockstep'],
                         ids=lambda k: '-'.join(map(str, k[:3])))
def test_lockstep_graph_equals_simulate_on_closed_loops(
        runs: dict[tuple[str, str, str, str, float], GraphRun],
        key: tuple[str, str, str, str, float]) -> None:
    scenario, mode, _, _, duration = key
    assert_equals_offline(runs[key].trace, scenario, mode, duration)
    assert runs[key].loop['max_consecutive_missed'] == 0


@pytest.mark.parametrize('key', [k for k in RUNS if k[3] == 'wall'],
                         ids=lambda k: '-'.join(map(str, k[:3])))
def test_a_wall_clock_run_renders_the_closed_loop(
        runs: dict[tuple[str, str, str, str, float], GraphRun],
        key: tuple[str, str, str, str, float]) -> None:
    """What holds on any machine: the loop ran, the controller took the reduced LMI updates
    (constraint counts among those simulate's run of the whole scenario has: 2 for the
    four-bar, 1-2 for the five-bar at its distal joint, 5 for the Bennett linkage), its
    commands stayed finite and what the device applied stayed within its limits (a command
    may ask for more: the device clamps it, status SATURATED; how often depends on the
    machine's timing)."""
    scenario, mode, _, _, _ = key
    sc = load_scenario(scenario)
    trace = runs[key].trace
    assert len(trace) > 100
    assert np.all(np.isfinite(trace.columns['command']))
    applied = trace.columns['applied']
    assert np.all(np.isfinite(applied))
    assert np.all(np.abs(applied) <= sc.device.wrench_limit + 1e-12)
    counts = trace.columns['lmi_constraint_count']
    offline = simulate(sc, ControlMode.parse(mode)).columns['lmi_constraint_count']
    assert set(counts[~np.isnan(counts)]) <= set(offline[~np.isnan(offline)])
