"""What the documentation quotes a command as printing is what the command prints today.

Each test runs a documented command of the reference bag (``bags/reference_fig8``) or of the
installed package as the pages write it, and compares its output with the block the page
quotes: exactly where the output is deterministic (the controller check, ``analyze``'s tables
of a recorded bag and of ``simulate``, ``simulate`` of a contact scenario, an error line),
counts, names and files where it is not (how long a replay took), and the column names of
the tables a live run prints (``make demo`` in the README and getting_started.md). Together
about a minute.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from haptic_topology.bag.reader import open_bag

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / 'docs'
REFERENCE = REPO / 'bags' / 'reference_fig8'
CLI = Path(sys.executable).parent / 'haptic-topology'
_FENCE = re.compile(r'^```(?P<lang>[a-z]*)\n(?P<body>.*?)^```', re.S | re.M)


def quoted(page: str, marker: str, lang: str = '') -> list[str]:
    """The lines of the fenced block (of language ``lang``) on ``docs/<page>`` (the README:
    ``README.md``) that holds ``marker``; the test fails if there is none or more than one."""
    text = (REPO / page if page == 'README.md' else DOCS / page).read_text(encoding='utf-8')
    blocks = [m.group('body') for m in _FENCE.finditer(text)
              if m.group('lang') == lang and marker in m.group('body')]
    assert len(blocks) == 1, f'docs/{page}: {len(blocks)} ```{lang} blocks hold {marker!r}'
    return blocks[0].rstrip('\n').split('\n')


def command(line: str) -> list[str]:
    """A documented ``haptic-topology ...`` line (or ``.venv/bin/haptic-topology ...``;
    comment stripped) as arguments."""
    args = shlex.split(line.split('#', 1)[0])
    assert args[0] in ('haptic-topology', '.venv/bin/haptic-topology'), line
    return [str(CLI), *args[1:]]


def run(args: list[str], cwd: Path, expect: int = 0) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=240,
                          stdin=subprocess.DEVNULL)
    assert done.returncode == expect, (
        f'{shlex.join(args)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}')
    return done


def workdir(tmp_path: Path) -> Path:
    """A directory where ``bags/reference_fig8`` is the repository's reference bag, so the
    documented commands run as written and their output files stay out of the repository."""
    (tmp_path / 'bags').mkdir()
    (tmp_path / 'bags' / 'reference_fig8').symlink_to(REFERENCE)
    return tmp_path


@pytest.mark.graph
def test_the_controller_check_prints_what_the_replay_docs_quote(tmp_path: Path) -> None:
    line = next(c for c in quoted('recording.md', '--check-controller', 'sh')
                if '--check-controller' in c)
    want = quoted('recording.md', 'controller check (')
    got = run(command(line), workdir(tmp_path)).stdout.rstrip('\n').split('\n')
    # The replay's duration depends on the machine; the counts and the check do not.
    seconds = re.compile(r' in \d+\.\d+ s$')
    assert [seconds.sub(' in <t> s', g) for g in got] == [seconds.sub(' in <t> s', w)
                                                           for w in want]


@pytest.mark.parametrize('page', ['recording.md', 'results.md'])
def test_analyze_prints_the_tables_the_docs_quote(tmp_path: Path, page: str) -> None:
    """``simulate`` is deterministic and the bag is fixed: both tables equal, every figure."""
    cwd = workdir(tmp_path)
    for line in quoted(page, 'haptic-topology analyze bags/reference_fig8', 'sh'):
        done = run(command(line), cwd)
    want = quoted(page, 'simulate_fig8_penalty  penalty')
    assert done.stdout.rstrip('\n').split('\n')[:len(want)] == want
    # The files the page names.
    assert {'reference_fig8.png', 'simulate_fig8_penalty.png', 'comparison.png',
            'summary.json'} <= {p.name for p in (cwd / 'analysis').iterdir()}
    runs = json.loads((cwd / 'analysis' / 'summary.json').read_text())['runs']
    assert len(runs) == 2
    for key in ('final_distance_m', 'max_distance_m', 'rms_distance_m', 'constrained_time_s'):
        assert all(key in r for r in runs), key


def test_a_bag_of_other_topics_stops_analyze_with_the_quoted_line(tmp_path: Path) -> None:
    from haptic_topology.bag.writer import BagWriter, TopicSpec
    from haptic_topology.messages.definitions import typestore_with_haptic_msgs

    want = quoted('recording.md', 'not a bag of the haptic_topology graph')
    store = typestore_with_haptic_msgs()
    writer = BagWriter(tmp_path / 'bags' / 'chatter',
                       [TopicSpec('/chatter', 'std_msgs/msg/String')], store)
    text = store.types['std_msgs/msg/String']('hi')
    writer.write(0, time.time_ns(), bytes(store.serialize_cdr(text, 'std_msgs/msg/String')))
    writer.close()
    done = run(command('haptic-topology analyze bags/chatter --out analysis'), tmp_path,
               expect=1)
    assert done.stderr.rstrip('\n').split('\n') == want


def test_bag_info_prints_topics_types_counts_duration_and_size(tmp_path: Path) -> None:
    """``bag info`` (recording.md: "topics, types, counts, duration, size") of the reference:
    one line per topic of its ``metadata.yaml`` with type and count, their total."""
    comment = next(c for c in quoted('recording.md', 'haptic-topology bag info', 'sh')
                   if 'bag info' in c)
    assert comment.split('#', 1)[1].strip() == 'topics, types, counts, duration, size'
    done = run(command('haptic-topology bag info bags/reference_fig8'), workdir(tmp_path))
    head, *rows = done.stdout.rstrip('\n').split('\n')
    metadata = open_bag(REFERENCE).metadata_topics()
    counts = {topic: int(count) for topic, _, count in (r.split() for r in rows)}
    types = {topic: kind for topic, kind, _ in (r.split() for r in rows)}
    assert types == metadata
    total = re.fullmatch(r'bags/reference_fig8: (\d+) messages over \d+\.\d+ s, \d+\.\d+ MB',
                         head)
    assert total, head
    assert int(total.group(1)) == sum(counts.values())


def test_info_lists_the_message_types_the_docs_name(tmp_path: Path) -> None:
    """``haptic-topology info`` (README: "versions of rclpy/Pinocchio/numpy, share
    directories, message types"): the message types it lists are those nodes.md names."""
    readme = (REPO / 'README.md').read_text(encoding='utf-8')
    assert ('| `haptic-topology info` | versions of rclpy/Pinocchio/numpy, share directories, '
            'message types |') in readme
    out = run([str(CLI), 'info'], tmp_path).stdout
    for name in ('rclpy', 'pinocchio', 'numpy'):
        assert re.search(rf'^{name}\s+\d+\.\d+', out, re.M), f'info prints no {name} version'
    assert re.search(r'^share haptic_topology_msgs:\s+\S', out, re.M)
    listed = re.findall(r'^  haptic_topology_msgs/msg/(\w+)  ', out, re.M)
    nodes = (DOCS / 'nodes.md').read_text(encoding='utf-8')
    paragraph = re.search(r'is the ament_cmake package `haptic_topology_msgs`: (.*?)Offline tools',
                          nodes, re.S)
    assert paragraph, 'nodes.md lost its Messages paragraph'
    named = re.findall(r'`([A-Z]\w+)`', paragraph.group(1))
    assert len(set(listed)) == len(listed) and set(listed) == set(named)
    assert set(listed) == {p.stem for p in (REPO / 'msg_schemas' / 'msg').glob('*.msg')}


def columns(header: str) -> list[str]:
    """The column names of a table's header line (columns are two or more spaces apart)."""
    return [c for c in re.split(r'\s{2,}', header.strip()) if c]


def test_a_contact_scenario_prints_the_contact_columns_the_docs_quote(tmp_path: Path) -> None:
    """``simulate wall`` (configuration.md) is deterministic: its table, every figure, with
    the deepest penetration and the time in contact, and the files it names."""
    line = next(c for c in quoted('configuration.md', 'simulate wall', 'sh')
                if 'simulate wall' in c)
    want = quoted('configuration.md', 'max penetration [mm]')
    got = run(command(line), tmp_path).stdout.rstrip('\n').split('\n')
    assert got == want
    assert columns(want[0])[-2:] == ['max penetration [mm]', 'in contact [s]']


@pytest.mark.parametrize('page', ['README.md', 'getting_started.md'])
def test_the_run_tables_the_docs_quote_have_the_columns_run_prints(page: str) -> None:
    """A run's figures depend on the machine, its columns do not: the drift and loop-health
    tables the pages quote of ``make demo`` have the columns ``run`` prints, in its order."""
    from haptic_topology.bag.analyze import format_loop_health
    from haptic_topology.sim.trace import format_summary

    block = quoted(page, 'running fig8 (penalty)')
    drift = next(b for b in block if b.startswith('scenario '))
    loop = next(b for b in block if b.startswith('run '))
    assert columns(drift) == columns(format_summary([]).split('\n')[0])
    assert columns(loop) == columns(format_loop_health([]).split('\n')[0])
    rows = [b for b in block if b.startswith('fig8 ')]
    assert len(rows) == 4       # two runs in each table
    # A figure in each column; the loop table's run label ('fig8 penalty') is two words.
    assert [len(r.split()) for r in rows] == [len(columns(drift))] * 2 + [
        len(columns(loop)) + 1] * 2


def test_the_loop_columns_recording_md_lists_are_the_table_and_the_summary_keys() -> None:
    """recording.md's table of the loop-health columns: the names ``run`` and ``analyze``
    print, in order, with the ``summary.json`` key of each."""
    from haptic_topology.bag.analyze import LOOP_COLUMNS

    text = (DOCS / 'recording.md').read_text(encoding='utf-8')
    rows = re.findall(r'^\| ([^|`]+) \| `(\w+)` \| [^|]+ \|$', text, re.M)
    assert rows == [(name, key) for key, name, _, _ in LOOP_COLUMNS]
