"""The passivity controller in the graph: fig6 with a penalty 1,000 times stiffer
and no damping (``k_tc`` 1e4 N/(m kg), ``b_tc`` 0: beyond the Colgate-Schenkel bound of a 1 kg
device at 1 kHz, unstable in ``simulate``), run with ``run_graph`` on the real-time graph
(hosted layout) with the controller enabled and disabled; and in lock-step, where the bag's
energy account (the controller's last ``/diagnostics`` status) is ``simulate``'s, exactly, and
so is the account reconstructed row by row from the bag
(:mod:`haptic_topology.bag.energy_series`), which a copy of the bag with one command changed
refuses.

What holds on any machine is asserted, nothing about timing: the controller's last
``/diagnostics`` status in the bag says it was on and acted (cycles > 0) in the run with it,
off and never acting in the run without; the observer of the run without it went below zero
(the penalty without damping generates energy whatever the periods). The figures of both runs
(observer minimum and end, drift) are printed by ``bench/passivity_wall_clock.py``.

Every graph runs in a domain of its own (``spare_domains``); every wait has a deadline.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from haptic_topology.bag.analyze import analyze, reduce_bag
from haptic_topology.bag.energy_series import energy_series
from haptic_topology.bag.reader import decoder, iter_messages, open_bag, read_channels
from haptic_topology.bag.writer import BagWriter, TopicSpec
from haptic_topology.bringup.analysis import AnalysisJob, analyse
from haptic_topology.bringup.options import param_overrides
from haptic_topology.bringup.run import run_graph
from haptic_topology.bringup.watch import CONTROLLER_STATUS
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs
from haptic_topology.paths import config_dir
from haptic_topology.sim.energy_plots import work_integrals
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import ENERGY_FLOATS, Trace, format_energy

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
DURATION = 2.0          # s of wall clock from engagement: the VT reaches the constraint at ~0.9 s


def _last_controller_status(bag: Path) -> dict[str, str]:
    """The key/values of the controller's last ``/diagnostics`` status in ``bag``."""
    decode = decoder()
    last: dict[str, str] = {}
    for raw in iter_messages(open_bag(bag), ['/diagnostics']):
        for status in decode(raw).status:
            if status.name == CONTROLLER_STATUS:
                last = {kv.key: kv.value for kv in status.values}
    return last


def _run(tmp_path: Path, passivity: str, domain: int, clock: str = 'wall',
         duration: float = DURATION) -> Path:
    bag = tmp_path / f'fig6_stiff_{passivity}_{clock}'
    codes = run_graph('fig6', 'penalty', duration, bag, PARAMS, 'hosted',
                      startup_timeout=90.0, domain_id=domain, clock=clock,
                      overrides=param_overrides(['lmi_controller:k_tc:=10000.0',
                                                 'lmi_controller:b_tc:=0.0',
                                                 f'lmi_controller:passivity:={passivity}']))
    assert all(c == 0 for c in codes.values()), codes
    return bag


def test_wall_clock_graph_runs_the_passivity_controller_on_an_unstable_penalty(
        tmp_path: Path, spare_domains: list[int]) -> None:
    on = _last_controller_status(_run(tmp_path, 'enabled', spare_domains[0]))
    off = _last_controller_status(_run(tmp_path, 'disabled', spare_domains[1]))
    assert on['passivity_controller'] == 'on' and int(on['passivity_cycles']) > 0, on
    assert off['passivity_controller'] == 'off' and int(off['passivity_cycles']) == 0, off
    assert float(off['passivity_observer_min_j']) < 0.0, off


#: Simulated seconds of the lock-step run (the passivity controller acts from 1 ms on).
LOCKSTEP_DURATION = 0.3


@pytest.fixture(scope='module')
def lockstep_bag(tmp_path_factory: pytest.TempPathFactory, spare_domains: list[int]) -> Path:
    """fig6, the unstable penalty, the passivity controller on, lock-step, 0.3 s."""
    return _run(tmp_path_factory.mktemp('lockstep'), 'enabled', spare_domains[2], 'lockstep',
                LOCKSTEP_DURATION)


@pytest.fixture(scope='module')
def offline() -> Trace:
    """``simulate`` of the same run."""
    sc = replace(load_scenario('fig6'), duration=LOCKSTEP_DURATION)
    return simulate(sc, gains=sc.gains.with_penalty(1e4, 0.0),
                    passivity=PassivityConfig(enabled=True))


def test_lockstep_bag_has_the_energy_account_of_simulate(lockstep_bag: Path,
                                                         offline: Trace) -> None:
    """Lock-step, the controller enabled: ``analyze``'s figures of the bag carry the
    controller's account at the last state, which is ``simulate``'s bit for bit (every figure:
    work per axis and part, the VT end's, observer, its minimum, the cycles the controller
    acted, when), and the energy table prints the same row."""
    graph = reduce_bag(lockstep_bag, 'fig6', plot=False).summary
    assert offline.meta['energy_account']['passivity_cycles'] > 0
    assert graph['energy_account'] == offline.meta['energy_account']
    assert format_energy([('fig6', graph)]) == format_energy([('fig6', offline.summary())])


def test_lockstep_bag_energy_series_equals_simulate_row_by_row(
        lockstep_bag: Path, offline: Trace, tmp_path: Path) -> None:
    """The bag's energy account reconstructed row by row (the controller replayed offline,
    every command equal to the recorded one) is ``simulate``'s trace columns bit for bit at
    every row: work at the port, observer, the passivity controller's damping, the times;
    ``analyze`` says so, takes the energy table's figures from it and draws
    ``<label>_energy.png``."""
    run = reduce_bag(lockstep_bag, 'fig6')
    assert run.summary['energy_series'] == 'exact'
    series = run.energy_plot
    assert series is not None and len(series) == len(offline)
    np.testing.assert_array_equal(series.t, offline.t)
    for col in ENERGY_FLOATS:
        np.testing.assert_array_equal(series.columns[col], offline.columns[col], err_msg=col)
    assert np.count_nonzero(offline.columns['passivity_damping']) > 0
    assert np.min(offline.columns['passivity_observer']) < 0.0
    port, hand = work_integrals(offline)
    np.testing.assert_array_equal(series.columns['work_integral'], port)
    np.testing.assert_array_equal(series.columns['hand_work_integral'], hand)
    summary = offline.summary()
    for key in ('passivity_observer_min_j', 'passivity_observer_final_j', 'passivity_rows',
                'passivity_first_s'):
        assert run.summary[key] == summary[key], key
    rows = analyze([lockstep_bag], tmp_path / 'out')
    assert rows[0]['energy_series'] == 'exact'
    assert (tmp_path / 'out' / f'{lockstep_bag.name}_energy.png').is_file()
    # run's analysis (beside a copy of the bag: it writes there)
    copy = tmp_path / 'run_bag'
    shutil.copytree(lockstep_bag, copy)
    out = analyse(AnalysisJob(copy, load_scenario('fig6'), 'penalty', 'hosted', False, True,
                              tmp_path / 'result.json'))
    assert out['summary']['energy_series'] == 'exact'
    assert (copy / 'energy.png').is_file()


def _tampered_copy(bag: Path, out: Path, nth: int) -> int:
    """A copy of ``bag`` written with the project's bag writer, the ``nth`` command's first
    wrench entry one float step larger; returns the state seq of that command."""
    source = open_bag(bag)
    store = typestore_with_haptic_msgs()
    topics = [(t, ch['type']) for t, ch in read_channels(source).items()]
    writer = BagWriter(out, [TopicSpec(t, ty) for t, ty in topics], store,
                       sources=message_definitions(),
                       custom=(source.metadata or {}).get('custom_data'))
    index = {t: i for i, (t, _) in enumerate(topics)}
    commands, seq = 0, -1
    for m in iter_messages(source):
        data = m.data
        if m.topic.endswith('haptic/device/command'):
            commands += 1
            if commands == nth:
                msg = store.deserialize_cdr(data, m.msgtype)
                wrench = np.array(msg.wrench, dtype=float)
                wrench[0] = np.nextafter(wrench[0], np.inf)
                data = bytes(store.serialize_cdr(replace(msg, wrench=wrench), m.msgtype))
                seq = int(msg.state_seq)
        writer.write(index[m.topic], m.log_time, data)
    writer.close()
    assert seq > 0
    return seq


def test_a_bag_with_a_tampered_command_has_its_energy_series_refused(
        lockstep_bag: Path, tmp_path: Path) -> None:
    """One command of the bag one float step off: the reconstruction stops there and the
    series is refused with one line naming that state; nothing is drawn."""
    copy = tmp_path / 'tampered'
    seq = _tampered_copy(lockstep_bag, copy, 100)
    series = energy_series(copy, _last_controller_status(copy))
    assert series.refused is not None and '\n' not in series.refused
    assert series.refused.startswith(f'state {seq}: the replayed command differs'), (
        series.refused)
    assert series.plot is None and not series.exact
    run = reduce_bag(copy, 'fig6')
    assert run.summary['energy_series'] == f'refused: {series.refused}'
    assert run.energy_plot is None
    assert reduce_bag(lockstep_bag, 'fig6', plot=False).summary['energy_series'] == 'exact'
