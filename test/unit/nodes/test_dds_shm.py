"""Fast DDS's shared-memory files: a segment is stale exactly when no process holds its lock
file, and only stale ones are removed (:mod:`haptic_topology.nodes.dds_shm`). The lock
holders are real processes (``flock``, as Fast DDS's ``RobustExclusiveLock``), in a folder of
the test's own instead of ``/dev/shm``."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from haptic_topology.nodes.dds_shm import (
    cleaner_lock,
    fastdds_entries,
    lock_held,
    process_segments,
    remove_stale_segments,
    stale_segments,
)

#: Locks (flock, exclusive) and maps each file named on its command line, prints "ready",
#: then waits until its stdin closes: a participant as Fast DDS makes one.
HOLDER = '''
import fcntl, mmap, os, sys
keep = []
for path in sys.argv[1:]:
    fd = os.open(path, os.O_RDWR)
    if path.endswith('_el'):
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    else:
        keep.append(mmap.mmap(fd, 4096))
    keep.append(fd)
print('ready', flush=True)
sys.stdin.read()
'''

LIVE = 'fastrtps_00000000000000aa'
DEAD = 'fastrtps_00000000000000bb'


def _segment(shm: Path, name: str) -> None:
    (shm / name).write_bytes(b'\0' * 4096)
    (shm / f'{name}_el').write_bytes(b'')


@pytest.fixture
def holder(tmp_path: Path) -> Iterator[subprocess.Popen[str]]:
    """A process holding segment :data:`LIVE`'s lock and mapping the segment."""
    _segment(tmp_path, LIVE)
    proc = subprocess.Popen([sys.executable, '-c', HOLDER, str(tmp_path / LIVE),
                             str(tmp_path / f'{LIVE}_el')], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline() == 'ready\n'
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def test_only_segments_of_ended_processes_are_removed(
        tmp_path: Path, holder: subprocess.Popen[str]) -> None:
    _segment(tmp_path, DEAD)
    others = {'fastrtps_port7411', 'fastrtps_port7411_el', 'sem.fastrtps_port7411_mutex',
              'fast_datasharing_01.0f.aa.bb_0.0.1.3', 'psm_1234abcd', 'lttng-ust-wait-6'}
    for name in others:
        (tmp_path / name).write_bytes(b'')
    assert lock_held(tmp_path / f'{LIVE}_el')
    assert not lock_held(tmp_path / f'{DEAD}_el')
    assert stale_segments(tmp_path) == {DEAD}
    assert remove_stale_segments(tmp_path) == [DEAD]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        others | {LIVE, f'{LIVE}_el'})
    assert fastdds_entries(tmp_path) == (others - {'psm_1234abcd', 'lttng-ust-wait-6'}
                                         | {LIVE, f'{LIVE}_el'})
    assert process_segments(holder.pid, tmp_path) == {LIVE}


def test_a_killed_holders_segment_becomes_stale(
        tmp_path: Path, holder: subprocess.Popen[str]) -> None:
    assert remove_stale_segments(tmp_path) == []
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert process_segments(holder.pid, tmp_path) == set()
    assert stale_segments(tmp_path) == {LIVE}
    assert remove_stale_segments(tmp_path) == [LIVE]
    assert list(tmp_path.iterdir()) == []


def test_a_lock_file_without_its_segment_is_removed(tmp_path: Path) -> None:
    """A process that ended between removing its segment and its lock file (the order of
    Fast DDS's teardown) leaves the lock file alone."""
    (tmp_path / f'{DEAD}_el').write_bytes(b'')
    assert remove_stale_segments(tmp_path) == [DEAD]
    assert list(tmp_path.iterdir()) == []


def test_nothing_to_do(tmp_path: Path) -> None:
    assert remove_stale_segments(tmp_path / 'absent') == []
    assert fastdds_entries(tmp_path / 'absent') == set()
    assert not lock_held(tmp_path / f'{DEAD}_el')


def test_while_another_process_holds_the_cleaner_lock_nothing_is_removed(
        tmp_path: Path) -> None:
    """One cleaner at a time: a process holding the folder's cleaner lock (here a child
    that takes it and waits) keeps every other cleaner out; once it lets go, the stale
    segment goes. Another folder's cleaner lock is another file."""
    _segment(tmp_path, DEAD)
    code = ('import sys, time\n'
            'from pathlib import Path\n'
            'from haptic_topology.nodes.dds_shm import cleaning\n'
            'with cleaning(Path(sys.argv[1])) as mine:\n'
            '    print(mine, flush=True)\n'
            '    sys.stdin.readline()\n')
    other = subprocess.Popen([sys.executable, '-c', code, str(tmp_path)], text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert other.stdout is not None and other.stdout.readline().strip() == 'True'
        assert remove_stale_segments(tmp_path) == []
        assert stale_segments(tmp_path) == {DEAD}
        assert cleaner_lock(tmp_path) != cleaner_lock(tmp_path / 'other')
    finally:
        other.communicate('\n', timeout=60)
    assert remove_stale_segments(tmp_path) == [DEAD]
