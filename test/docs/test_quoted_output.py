"""What the documentation quotes a command as printing is what the command prints today.

Each test runs a documented command of the reference bag (``bags/reference_fig8``) or of the
installed package as the pages write it, and compares its output with the block the page
quotes: exactly where the output is deterministic (the controller check, ``analyze``'s tables
of a recorded bag and of ``simulate``, an error line), counts, names and files where it is
not (how long a replay took). Together well under a minute.
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
    """The lines of the fenced block (of language ``lang``) on ``docs/<page>`` that holds
    ``marker``; the test fails if there is none or more than one."""
    text = (DOCS / page).read_text(encoding='utf-8')
    blocks = [m.group('body') for m in _FENCE.finditer(text)
              if m.group('lang') == lang and marker in m.group('body')]
    assert len(blocks) == 1, f'docs/{page}: {len(blocks)} ```{lang} blocks hold {marker!r}'
    return blocks[0].rstrip('\n').split('\n')


def command(line: str) -> list[str]:
    """A documented ``haptic-topology ...`` line (comment stripped) as arguments."""
    args = shlex.split(line.split('#', 1)[0])
    assert args[0] == 'haptic-topology', line
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
