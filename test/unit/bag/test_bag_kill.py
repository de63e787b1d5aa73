"""A recorder's bag writer killed with SIGKILL at any moment leaves a bag that every reader
opens and ``bag repair`` makes whole, with every message flushed before the kill.

Each trial runs ``support/bag_kill_child.py`` (the writer used as the recorder uses it, split
by size and/or duration) and kills it: either the moment it reports its k-th flush (it keeps
writing meanwhile, so the kill lands somewhere in the following writes), or while it waits
at a chosen file operation of the writer (creating a storage file, right after creating it,
writing or renaming ``metadata.yaml``, removing an empty last file in ``close``), the small
windows between the steps of a split, an open and a close. The trials are drawn from a
seeded RNG: a failure names its trial, and ``SEED`` reproduces it.
"""

from __future__ import annotations

import os
import random
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from rosbags.rosbag2 import Reader as Rosbag2Reader

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.cli import main as cli_main
from haptic_topology.errors import HapticTopologyError
from haptic_topology.messages.definitions import typestore_with_haptic_msgs

CHILD = Path(__file__).resolve().parents[2] / 'support' / 'bag_kill_child.py'
sys.path.insert(0, str(CHILD.parent))
from bag_kill_child import CUSTOM, STATE  # noqa: E402

SEED = 54
TRIALS = 40
#: The pause points: (phase, kind, occurrences to draw the N-th from).
#: With at least 1000 messages a trial flushes at least 5 times and has at least 3 files
#: (the first one, and a split every 400 messages or sooner): every pause point is reached.
WINDOWS = [('run', 'mkdir', 2), ('run', 'mcap_open', 3), ('run', 'spill_open', 3),
           ('run', 'meta_open', 6), ('run', 'rename', 6), ('close', 'meta_open', 1),
           ('close', 'rename', 1), ('close', 'remove', 1)]
DEADLINE = 30.0     # s, for a child to report what the test waits for


@dataclass(frozen=True)
class Trial:
    number: int
    total: int
    size: int
    duration: float
    end: str
    pause: str          # '-' or PHASE:KIND:N
    kill_at_flush: int  # with pause '-': kill when the child reports this flush (0: never)

    def argv(self, bag: Path) -> list[str]:
        return [sys.executable, str(CHILD), str(bag), str(self.total), str(self.size),
                str(self.duration), self.end, self.pause]


def _trials() -> list[Trial]:
    rng = random.Random(SEED)
    out = []
    for k in range(TRIALS):
        size, duration = rng.choice([(12_000, 0.0), (0, 0.2), (12_000, 0.2)])
        total = rng.randrange(1000, 2000, 20)
        end = rng.choice(['plain', 'split'])
        pause, at = '-', 0
        if k < 2 * len(WINDOWS):            # every window twice, then kills at flushes
            phase, kind, count = WINDOWS[k % len(WINDOWS)]
            pause = f'{phase}:{kind}:{rng.randrange(count)}'
            end = 'split' if kind == 'remove' else end
        else:
            at = rng.randrange(1, total // 200 + 1)
        out.append(Trial(k, total, size, duration, end, pause, at))
    return out


def _run_and_kill(trial: Trial, bag: Path) -> tuple[list[str], bool]:
    """Run the child, kill it at the trial's point; its report lines and whether it was
    killed (False: it ended first, e.g. its pause point never came)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(CHILD.parents[2]), os.environ.get('PYTHONPATH', '')]))
    proc = subprocess.Popen(trial.argv(bag), stdout=subprocess.PIPE, env=env)
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    text, killed = b'', False
    deadline = time.monotonic() + DEADLINE
    try:
        while True:
            lines = text.decode().splitlines()
            if (any(ln.startswith('paused') for ln in lines)
                    or sum(ln.startswith('flushed') for ln in lines) >= trial.kill_at_flush > 0):
                proc.send_signal(signal.SIGKILL)
                killed = True
                break
            left = deadline - time.monotonic()
            assert left > 0, f'trial {trial}: the child reported only {lines}'
            if select.select([fd], [], [], left)[0]:
                chunk = os.read(fd, 65536)
                if not chunk:
                    break
                text += chunk
    finally:
        if proc.poll() is None and not killed:
            proc.kill()
        proc.wait(DEADLINE)
        text += proc.stdout.read()
        proc.stdout.close()
    assert killed or proc.returncode == 0, f'trial {trial}: exit {proc.returncode}'
    return text.decode().splitlines(), killed


def _numbers(bag: Path) -> list[int]:
    """The message numbers of the bag read with this package's reader, checked against their
    content."""
    decode = decoder(typestore_with_haptic_msgs())
    out = []
    for m in iter_messages(open_bag(bag)):
        msg = decode(m)
        out.append(int(msg.seq) if m.msgtype == STATE else int(msg.data))
    return out


def _rosbags_numbers(bag: Path) -> list[int]:
    store = typestore_with_haptic_msgs()
    out = []
    with Rosbag2Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            msg = store.deserialize_cdr(raw, conn.msgtype)
            out.append(int(msg.seq) if conn.msgtype == STATE else int(msg.data))
        assert reader.message_count == len(out)
    return out


def _check(trial: Trial, bag: Path, lines: list[str]) -> None:
    flushed = max([int(ln.split()[1]) for ln in lines if ln.split()[0] in ('flushed', 'closed')],
                  default=0)
    closed = any(ln.startswith('closed') for ln in lines)
    if not bag.exists():        # killed before the constructor made the bag
        assert 'open' not in lines, trial
        return
    # This package's reader, before any repair (what `analyze` and `replay` do).
    before = _numbers(bag)
    assert before == list(range(1, len(before) + 1)), (trial, 'not a prefix, in order')
    assert len(before) >= flushed, (trial, f'{len(before)} read, {flushed} flushed')
    # `bag repair`, the command.
    assert cli_main(['bag', 'repair', str(bag)]) == 0, trial
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['custom_data'] == CUSTOM and meta['ros_distro'] == 'jazzy', (trial, meta)
    on_disk = sorted((p.name for p in bag.glob('*.mcap')),
                     key=lambda n: int(n.removesuffix('.mcap').rsplit('_', 1)[1]))
    assert meta['relative_file_paths'] == on_disk, trial
    assert sum(f['message_count'] for f in meta['files']) == meta['message_count'] == len(
        before), trial
    # Everything read before is there after, for this package's reader and for rosbags.
    assert _numbers(bag) == before, trial
    assert _rosbags_numbers(bag) == before, trial
    assert not repair_bag(bag).repaired, (trial, 'a repaired bag is complete')
    if closed:
        assert len(before) == flushed, trial


@pytest.mark.timeout(300)
def test_a_writer_killed_at_any_moment_leaves_a_bag_that_repairs_whole(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    failed, missed = [], []
    for trial in _trials():
        bag = tmp_path / f'k{trial.number}'
        lines, killed = _run_and_kill(trial, bag)
        try:
            _check(trial, bag, lines)
        except (AssertionError, HapticTopologyError) as exc:
            failed.append(f'{trial}: {type(exc).__name__}: {str(exc).splitlines()[0]}')
        capsys.readouterr()             # the repair command's lines
        # Every trial was killed where it was meant to be: at its pause point, or once it
        # had reported its k-th flush (at least as many as its messages need).
        if trial.pause != '-':
            if not (killed and f'paused {trial.pause.split(":")[1]}' in lines):
                missed.append(f'{trial}: {lines[-3:]}')
        elif sum(ln.startswith('flushed') for ln in lines) < trial.kill_at_flush:
            missed.append(f'{trial}: {lines[-3:]}')
    assert failed == [], '\n'.join(failed)
    assert missed == [], '\n'.join(missed)
