"""A run's bag cut as a killed recorder leaves it, then `bag repair`ed: `analyze` and
`replay --check-controller` accept it as they accept the whole bag, with the run's graph id
and scenario (``custom_data``) that they read to tell the run's messages from another
graph's. A bag cut after commands whose LMI update the recorder wrote after them is checked up
to those commands, which it names as not checked."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bag.reader import decoder, iter_messages, open_bag, read_channels
from haptic_topology.bag.repair import repair_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec
from haptic_topology.bringup.run import run_graph
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs
from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph


def _cli(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', 'haptic_topology.cli', *argv],
                          capture_output=True, text=True, timeout=240)


@pytest.fixture(scope='module')
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A lock-step fig8 run's bag (penalty, 1 s)."""
    out = tmp_path_factory.mktemp('repaired') / 'run'
    codes = run_graph('fig8', 'penalty', 1.0, out, config_dir() / 'haptic_topology.yaml',
                      'hosted', startup_timeout=60.0, clock='lockstep')
    assert all(c == 0 for c in codes.values()), codes
    return out


def test_a_repaired_cut_run_bag_is_analysed_and_checked(tmp_path: Path, run: Path) -> None:
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


def _cut_before_update(run: Path, out: Path) -> tuple[int, int, int, int]:
    """``run``'s bag as its recorder leaves it when it receives LMI update N after the commands
    that name it (a loaded machine) and is killed before writing it: every message up to the
    last command naming N, in the recorded order, but N. N is the update the command at 70 %
    of the run first names. Returns N, the state seq of the first command naming it, and how
    many states the written commands answer before it and from it on."""
    source = open_bag(run)
    decode = decoder(bag=source)
    topics = [(t, ch['type']) for t, ch in read_channels(source).items()]
    index = {t: i for i, (t, _) in enumerate(topics)}
    messages = list(iter_messages(source))
    commands = [(i, decode(m)) for i, m in enumerate(messages)
                if m.topic.endswith('haptic/device/command')]
    named = [int(c.update_seq) for _, c in commands]
    k = len(commands) * 7 // 10
    while named[k] == named[k - 1]:
        k += 1                                  # the first command naming a newer update
    update = named[k]
    naming = [(i, int(c.state_seq)) for i, c in commands if int(c.update_seq) == update]
    writer = BagWriter(out, [TopicSpec(t, ty) for t, ty in topics],
                       typestore_with_haptic_msgs(), sources=message_definitions(),
                       custom=(source.metadata or {}).get('custom_data'))
    for m in messages[:naming[-1][0] + 1]:
        if not (m.topic.endswith('haptic/lmi/update') and int(decode(m).seq) == update):
            writer.write(index[m.topic], m.log_time, m.data)
    writer.close()
    first = naming[0][1]
    answered = {int(c.state_seq) for i, c in commands if i <= naming[-1][0]}
    before = sum(s < first for s in answered)
    return update, first, before, len(answered) - before


def test_a_bag_cut_before_an_update_its_last_commands_name_is_checked_up_to_them(
        tmp_path: Path, run: Path) -> None:
    """The controller's inputs of the cut bag's last commands are not all in it: the check
    compares every command before them exactly and names them as not checked, and ``analyze``
    reconstructs the energy series up to them."""
    cut = tmp_path / 'cut'
    update, first, before, naming = _cut_before_update(run, cut)
    assert naming >= 1 and before > 100
    checked = _cli('replay', str(cut), '--check-controller')
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert (f'{before} commands compared of {before + naming} recorded (0 not answered '
            f'live, {naming} not checked: from state {first} on, LMI update {update}, which '
            'the controller had taken, is not in the bag); max |difference| 0 '
            '(tolerance 1e-09): OK') in checked.stdout, checked.stdout
    analysed = _cli('analyze', str(cut), '--out', str(tmp_path / 'analysis'))
    assert analysed.returncode == 0, analysed.stderr
    (summary,) = json.loads((tmp_path / 'analysis' / 'summary.json').read_text())['runs']
    assert summary['energy_series'] == (
        f'exact before state {first} ({naming} commands from it on not reconstructed: LMI '
        f'update {update}, which the controller had taken, is not in the bag)')
