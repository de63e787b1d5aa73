"""A second graph on the graph's ROS domain (``support/intruder.py``: every update, hand-input
batch, state and command of the run echoed back well-formed, 2 cm off, numbered as the next
update or as a restarted VE's, half with another graph's id, half with the default graph's):
the run completes, computes exactly what it computes alone, applies nothing foreign, and
counts what it refused.

Lock-step runs, so "exactly what it computes alone" is ``simulate()`` to 1e-9 at every cycle;
hosted (loop process) and separate (the state -> command hop over DDS, so the intruder's
states and commands reach the controller and the device too). A third run (hosted) has an
intruder that copies the run's own graph id (``own-id``): the graph id cannot keep its
messages out, the checks of ``haptic_topology.control.admission`` do (model, session,
continuity), and the run still computes exactly what it computes alone.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from offline_check import assert_equals_offline

from haptic_topology.bag.graph_trace import GraphRun, read_graph_bag
from haptic_topology.bringup.run import run_graph
from haptic_topology.paths import config_dir
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import TOPIC_COMMAND, TOPIC_HAND_INPUTS, TOPIC_LMI, TOPIC_STATE

pytestmark = pytest.mark.graph

SUPPORT = Path(__file__).resolve().parents[1] / 'support'
PARAMS = config_dir() / 'haptic_topology.yaml'
SCENARIO, MODE, DURATION = 'fig8', 'penalty', 1.5
LAYOUTS = ('hosted', 'separate')
OWN_ID = 'hosted_own_id'        # the hosted run beside an intruder with the run's graph id


def _run(tmp: Path, name: str, domain: int) -> tuple[Path, dict[str, int]]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    layout = 'hosted' if name == OWN_ID else name
    counts_file, log = tmp / f'intruder_{name}.json', tmp / f'intruder_{name}.log'
    with log.open('wb') as out:
        intruder = subprocess.Popen([sys.executable, str(SUPPORT / 'intruder.py'), 'lockstep',
                                     str(counts_file), *(['own-id'] if name == OWN_ID else [])],
                                    env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60.0
        while b'intruder ready' not in log.read_bytes():
            assert intruder.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        bag = tmp / name
        codes = run_graph(SCENARIO, MODE, DURATION, bag, PARAMS, layout, startup_timeout=60.0,
                          clock='lockstep', domain_id=domain)
        assert all(c == 0 for c in codes.values()), codes
    finally:
        intruder.send_signal(signal.SIGINT)     # as Ctrl-C: it writes its counts
        try:
            code = intruder.wait(30.0)
        except subprocess.TimeoutExpired:
            intruder.kill()
            code = intruder.wait()
    assert code == 0, log.read_text()
    return bag, json.loads(counts_file.read_text(encoding='utf-8'))


@pytest.fixture(scope='module')
def runs(tmp_path_factory: pytest.TempPathFactory,
         spare_domains: list[int]) -> dict[str, tuple[GraphRun, dict[str, int]]]:
    tmp = tmp_path_factory.mktemp('foreign')
    names = (*LAYOUTS, OWN_ID)
    with ThreadPoolExecutor(len(names)) as pool:
        futures = {name: pool.submit(_run, tmp, name, domain)
                   for name, domain in zip(names, spare_domains, strict=False)}
        done = {}
        for name, f in futures.items():
            try:
                done[name] = f.result()
            except Exception as exc:        # name the run: the three share this fixture
                raise AssertionError(f'the {name} run: {exc}') from exc
    dof = load_scenario(SCENARIO).linkage.dof      # the bags read one after the other
    return {name: (read_graph_bag(bag, SCENARIO, dof), sent)
            for name, (bag, sent) in done.items()}


@pytest.mark.parametrize('layout', LAYOUTS)
def test_a_second_graph_changes_nothing_and_is_counted(
        runs: dict[str, tuple[GraphRun, dict[str, int]]], layout: str) -> None:
    run, sent = runs[layout]
    # It was there during the run: it echoed every kind of the run's messages (how many
    # depends on discovery and load, see below).
    for topic in (TOPIC_LMI, TOPIC_HAND_INPUTS, TOPIC_STATE, TOPIC_COMMAND):
        assert sent[topic] > 0, sent
    # Nothing of it was applied: the run computes what simulate() computes, cycle by cycle.
    assert_equals_offline(run.trace, SCENARIO, MODE, DURATION)
    # The bag holds it (the recorder records the domain), and the analysis read none of the
    # topics it reads (the trace: states, commands, updates).
    foreign = {t.lstrip('/'): n for t, n in run.foreign_messages.items()}
    for topic in (TOPIC_LMI, TOPIC_STATE, TOPIC_COMMAND):
        assert 0 < foreign[topic.lstrip('/')] <= sent[topic], (topic, foreign, sent)
    assert run.graph_id.startswith(f'{SCENARIO}-')
    # The nodes counted what reached them, by topic, and followed none of it: no restarted
    # VE (the updates numbered 0), no second controller.
    ctl = run.diagnostics['lmi_controller: loop']
    ve = run.diagnostics['ve_sim: loop']
    dev = run.diagnostics['device_driver: loop']
    assert int(ctl[f'foreign {TOPIC_LMI}']) > 0
    assert int(ve[f'foreign {TOPIC_HAND_INPUTS}']) > 0
    assert ctl['ve_restarts'] == '0'
    assert dev['controller_takeovers'] == '0'
    for status in (ctl, ve, dev):
        assert status['graph_id'] == run.graph_id
    # ... and named it (the nodes' /diagnostics at ERROR while it was there; summary.json).
    inputs = [TOPIC_LMI, TOPIC_HAND_INPUTS] + ([TOPIC_STATE, TOPIC_COMMAND]
                                                if layout == 'separate' else [])
    assert run.foreign_publishers == {'/intruder': sorted(inputs)}
    if layout == 'separate':
        assert int(ctl[f'foreign {TOPIC_STATE}']) > 0
        assert int(dev[f'foreign {TOPIC_COMMAND}']) > 0


def test_a_sender_with_the_graphs_own_id_is_refused_by_the_checks(
        runs: dict[str, tuple[GraphRun, dict[str, int]]]) -> None:
    run, sent = runs[OWN_ID]
    # How many of the run's messages it echoed depends on when it discovered the run and on
    # the load (one CI run: 158 updates, 95 batches of 150); that it echoed both does not.
    assert sent[TOPIC_LMI] > 0 and sent[TOPIC_HAND_INPUTS] > 0, sent
    # Nothing of it was applied.
    assert_equals_offline(run.trace, SCENARIO, MODE, DURATION)
    ctl = run.diagnostics['lmi_controller: loop']
    ve = run.diagnostics['ve_sim: loop']
    # Its messages carry the run's id: no foreign message by id, every one refused by a check.
    assert ctl['foreign_messages'] == ve['foreign_messages'] == '0'
    # Sent in turn: the hand 2 cm off, numbered 0, an old update (the VE's first, or the one
    # of 20 before). Which check refuses one depends on when it arrives (after the VE's next
    # update, one numbered as the next is already old: session), so the reasons are counted
    # together here; each check is tested exactly in test/unit/control/test_admission.py.
    checks = ('model', 'session', 'continuity')
    refused = sum(int(ctl[f'rejected_{r}']) for r in checks)
    assert 0 < refused <= sent[TOPIC_LMI], (ctl, sent)
    assert ctl['ve_restarts'] == '0'
    # every batch echoed: numbered and stamped as one taken already (session), or, if it
    # came first, as the next input 2 cm away (continuity)
    refused = sum(int(ve[f'rejected_{r}']) for r in checks)
    assert 0 < refused <= sent[TOPIC_HAND_INPUTS], (ve, sent)
    assert ve['controller_restarts'] == '0'
    assert run.foreign_publishers == {'/intruder': sorted([TOPIC_LMI, TOPIC_HAND_INPUTS])}
