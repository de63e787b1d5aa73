"""``run``, ``simulate`` and ``analyze`` name and show a run's figures alike: the loop-health
figures under one name each, in one order, with the same ``summary.json`` keys; the contact
figures of a run with obstacles; the obstacles in ``analyze``'s figure as in the run's own; the
linkage a run used in its plots' titles."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import pytest
from matplotlib.patches import Polygon

from haptic_topology.bag.analyze import (
    LOOP_COLUMNS,
    analyze,
    format_loop_health,
    load_run,
    run_figure,
)
from haptic_topology.bringup.analysis import AnalysisJob, analyse
from haptic_topology.cli import main as cli_main
from haptic_topology.sim.plots import trace_figure
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace_io import read_trace

REPO = Path(__file__).resolve().parents[3]
REFERENCE = REPO / 'bags' / 'reference_fig8'


def _legend(ax: plt.Axes) -> list[str]:
    return [str(h.get_label()) for h in ax.get_legend_handles_labels()[0]]


def _simulate(capsys: pytest.CaptureFixture[str], *args: str) -> list[str]:
    """``haptic-topology simulate ARGS``: its output lines."""
    assert cli_main(['simulate', *args]) == 0
    return capsys.readouterr().out.rstrip('\n').split('\n')


def test_run_and_analyze_give_a_bag_the_same_loop_figures_and_table(tmp_path: Path) -> None:
    """The end of ``run`` (its analysis process's function, on a copy of the reference bag)
    and ``analyze`` of the same bag: every figure of the loop table under the same
    ``summary.json`` key with the same value, and the same table."""
    bag = tmp_path / 'reference_fig8'
    shutil.copytree(REFERENCE, bag)
    (bag / 'logs').mkdir()
    result = analyse(AnalysisJob(bag, load_scenario('fig8'), 'penalty', 'hosted', False, False,
                                 bag / 'logs' / 'result.json'))
    run_summary = json.loads((bag / 'summary.json').read_text())
    [row] = analyze([bag], tmp_path / 'analysis', plots=False)
    for key, _, _, _ in LOOP_COLUMNS:
        assert key in run_summary and key in row, key
        assert run_summary[key] == row[key], key
        assert math.isfinite(row[key]), key
    # Every loop figure analyze writes, run writes under the same key with the same value.
    loop_keys = {k for k in row if k.startswith(('device_', 'bag_'))}
    assert {k: run_summary[k] for k in loop_keys} == {k: row[k] for k in loop_keys}
    # The table: run's rows (its loop figures) and analyze's, under one header.
    assert format_loop_health([('x', result['loop'])]) == format_loop_health([('x', row)])
    header = format_loop_health([]).split('\n')[0].split('  ')
    assert [h.strip() for h in header if h.strip()] == [
        'run', 'answered, device [%]', 'answered, bag [%]', 'rtt p50 [ms]', 'rtt p99 [ms]',
        'period p50 [ms]', 'period p99 [ms]', 'period std [ms]', 'missing states']


def test_contact_runs_print_penetration_and_contact_time(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``simulate wall`` and ``analyze`` of it print the deepest penetration and the time in
    contact; beside a run without obstacles those are ``-``; a table of runs without
    obstacles has no such columns."""
    wall = tmp_path / 'wall'
    head, rule, line = _simulate(capsys, 'wall', '--duration', '0.5', '--out', str(wall))[:3]
    summary = json.loads((wall / 'summary.json').read_text())
    assert summary['max_penetration_m'] > 0.0 and summary['contact_time_s'] > 0.0
    assert head.split()[-6:] == ['max', 'penetration', '[mm]', 'in', 'contact', '[s]']
    want = [f'{summary["max_penetration_m"] * 1e3:.3f}', f'{summary["contact_time_s"]:.3f}']
    assert line.split()[-2:] == want

    assert cli_main(['analyze', str(wall), str(REFERENCE), '--out', str(tmp_path / 'a'),
                     '--no-plot']) == 0
    out = capsys.readouterr().out.split('\n')
    assert out[0].endswith('max penetration [mm]  in contact [s]')
    assert out[2].split()[0] == 'wall' and out[2].split()[-2:] == want
    assert out[3].split()[0] == 'reference_fig8' and out[3].split()[-2:] == ['-', '-']

    head = _simulate(capsys, 'fig8', '--duration', '0.1', '--out', str(tmp_path / 'f'))[0]
    assert head.endswith('first at limit [s]')


def test_analyze_draws_the_obstacles_of_a_contact_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``analyze``'s figure of a ``simulate wall`` output has the wall on its linkage panel,
    as ``simulate``'s own figure has."""
    wall = tmp_path / 'wall'
    _simulate(capsys, 'wall', '--duration', '0.5', '--out', str(wall))
    fig = run_figure(load_run(wall))
    try:
        assert 'wall (half-plane)' in _legend(fig.axes[0])
        assert fig.axes[0].get_xlim()[1] > 108.0        # the wall at x = 108 mm
        assert any(isinstance(p, Polygon) and p.get_hatch() == '//'     # its side
                   for p in fig.axes[0].patches)
    finally:
        plt.close(fig)


def test_plot_titles_name_the_linkage_a_run_used(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``simulate fig8 --linkage my_arm.yaml``: its figure is titled ``fig8 on my_arm.yaml``,
    and ``analyze``'s figure of it names it too (and draws that linkage); a run on the
    scenario's own linkage is titled by the scenario alone."""
    mine = tmp_path / 'my_arm.yaml'
    shutil.copy(REPO / 'config' / 'linkages' / 'table1_planar3.yaml', mine)
    out = tmp_path / 'sim'
    _simulate(capsys, 'fig8', '--linkage', str(mine), '--duration', '0.1', '--out', str(out))
    trace = read_trace(out / 'trace.parquet')
    assert trace.meta['linkage_file'] == str(mine.resolve())
    fig = trace_figure(trace)
    try:
        assert fig._suptitle is not None
        assert fig._suptitle.get_text().startswith('fig8 on my_arm.yaml - penalty: final drift')
    finally:
        plt.close(fig)
    fig = run_figure(load_run(out))
    try:
        assert fig._suptitle is not None
        assert fig._suptitle.get_text().startswith('sim (fig8 on my_arm.yaml): final drift')
    finally:
        plt.close(fig)

    own = tmp_path / 'own'
    _simulate(capsys, 'fig8', '--duration', '0.1', '--out', str(own))
    trace = read_trace(own / 'trace.parquet')
    assert 'linkage_file' not in trace.meta
    fig = trace_figure(trace)
    try:
        assert fig._suptitle is not None
        assert fig._suptitle.get_text().startswith('fig8 - penalty: final drift')
    finally:
        plt.close(fig)
