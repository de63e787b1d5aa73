"""A run's bag cut as a killed recorder leaves it, then `bag repair`ed: `analyze` and
`replay --check-controller` accept it as they accept the whole bag, with the run's graph id
and scenario (``custom_data``) that they read to tell the run's messages from another
graph's."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.bringup.run import run_graph
from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph


def _cli(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', 'haptic_topology.cli', *argv],
                          capture_output=True, text=True, timeout=240)


def test_a_repaired_cut_run_bag_is_analysed_and_checked(tmp_path: Path) -> None:
    params = config_dir() / 'haptic_topology.yaml'
    run = tmp_path / 'run'
    codes = run_graph('fig8', 'penalty', 1.0, run, params, 'hosted', startup_timeout=60.0,
                      clock='lockstep')
    assert all(c == 0 for c in codes.values()), codes
    custom = yaml.safe_load((run / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['custom_data']
    assert custom['scenario'] == 'fig8' and custom['graph_id']
    # The recorder killed at 70 % of its file: no summary, no footer, the last flush's
    # metadata.yaml.
    cut = tmp_path / 'cut'
    shutil.copytree(run, cut, ignore=shutil.ignore_patterns('logs'))
    (mcap,) = cut.glob('*.mcap')
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) * 7 // 10])
    before = read_graph_bag(cut, 'fig8')
    rows = len(before.trace.t)
    assert before.trace.meta['truncated'] and rows > 100 and before.skipped == {}

    assert repair_bag(cut).repaired
    after = read_graph_bag(cut, 'fig8')
    assert len(after.trace.t) == rows and after.graph_id == custom['graph_id']
    assert after.skipped == {} and after.foreign_messages == {}
    meta = yaml.safe_load((cut / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['custom_data'] == custom

    analysed = _cli('analyze', str(cut), '--out', str(tmp_path / 'analysis'))
    assert analysed.returncode == 0, analysed.stderr
    assert (tmp_path / 'analysis' / 'summary.json').is_file()
    checked = _cli('replay', str(cut), '--check-controller')
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert 'controller check (fig8, penalty)' in checked.stdout and ': OK' in checked.stdout
