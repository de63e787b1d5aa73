"""``bag repair`` and the writer's order of writes at the edges: the metadata the analysis
needs survives a repair, a kill just after a split leaves a bag that reads, stale metadata is
rewritten, a corrupt chunk costs only the rest of its file, complete files are not copied,
files without metadata are taken in the order of their numbers, and the data reaches the
disk before the metadata that counts it."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader as Rosbag2Reader

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.errors import BagError, BagWriteError
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

STATE = type_name('DeviceState')
CUSTOM = {'recorded_by': 'haptic_topology recorder', 'scenario': 'fig8', 'graph_id': 'g54'}


def _state_bytes(seq: int) -> bytes:
    ts = typestore_with_haptic_msgs()
    header = ts.types['std_msgs/msg/Header'](ts.types['builtin_interfaces/msg/Time'](1, 2),
                                             'base')
    v = np.array([0.1, 0.2, 0.3]) * seq
    return bytes(ts.serialize_cdr(ts.types[STATE](header, seq, 3, v, v, v, v, 0, np.zeros(0), 0),
                                  STATE))


def _writer(path: Path, **split: float) -> BagWriter:
    return BagWriter(path, [TopicSpec('/haptic/device/state', STATE, (make_qos(False, 1),))],
                     typestore_with_haptic_msgs(), sources=message_definitions(),
                     compression='none', custom=CUSTOM, **split)  # type: ignore[arg-type]


def _write(w: BagWriter, first: int, last: int, flush_every: int = 200) -> None:
    """States ``first``..``last`` 1 ms apart, flushed every ``flush_every`` (as the
    recorder's 0.2 s)."""
    for i in range(first, last + 1):
        w.write(0, 1_000_000_000 + i * 1_000_000, _state_bytes(i))
        if i % flush_every == 0:
            w.flush()


def _seqs(path: Path) -> list[int]:
    decode = decoder()
    return [decode(m).seq for m in iter_messages(open_bag(path))]


def _rosbags_seqs(path: Path) -> list[int]:
    ts = typestore_with_haptic_msgs()
    with Rosbag2Reader(path) as reader:
        return [ts.deserialize_cdr(raw, STATE).seq for _, _, raw in reader.messages()]


def _meta(path: Path) -> dict:
    return yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


# -- 1: what the analysis needs survives -----------------------------------------------------
def test_repair_keeps_custom_data_and_ros_distro_and_names_the_real_file(
        tmp_path: Path) -> None:
    """The recorder's ``custom_data`` (graph id, scenario: ``analyze`` and ``replay
    --check-controller`` read them) and ``ros_distro`` stay in the repaired metadata.yaml,
    and the ``rosbag2`` record embedded in the repaired file names that file."""
    w = _writer(tmp_path / 'k')
    _write(w, 1, 700)               # killed: no close(); 600 flushed
    meta_path = tmp_path / 'k' / 'metadata.yaml'
    meta_path.write_text(meta_path.read_text().replace('ros_distro: jazzy',
                                                       'ros_distro: kilted'))
    res = repair_bag(tmp_path / 'k')
    meta = _meta(tmp_path / 'k')
    assert meta['custom_data'] == CUSTOM
    assert meta['ros_distro'] == 'kilted'
    assert res.repaired and res.rewritten.keys() == {'k_0.mcap'}
    with (tmp_path / 'k' / 'k_0.mcap').open('rb') as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    embedded = yaml.safe_load(records['rosbag2']['serialized_metadata'])
    assert embedded['relative_file_paths'] == ['k_0.mcap']
    assert embedded['custom_data'] == CUSTOM
    assert _seqs(tmp_path / 'k') == list(range(1, 601))


# -- 3: killed just after a split ------------------------------------------------------------
def test_a_new_storage_file_has_its_header_on_disk_when_the_metadata_lists_it(
        tmp_path: Path) -> None:
    """Right after the flush that split the bag, before anything else is written, the file
    the metadata names last starts with the MCAP magic and header on disk (not only in the
    writer's buffer)."""
    w = _writer(tmp_path / 's', max_bag_size=20_000)
    _write(w, 1, 200)
    w.flush()
    n = 200
    while len(w.files) < 2:
        _write(w, n + 1, n + 200)
        n += 200
    newest = tmp_path / 's' / _meta(tmp_path / 's')['relative_file_paths'][-1]
    data = newest.read_bytes()
    assert data[:8] == b'\x89MCAP0\r\n' and data[8:9] == b'\x01', data[:16]   # Header op
    # Killed now: every reader opens the bag, with every flushed message.
    assert _seqs(tmp_path / 's') == list(range(1, n + 1))
    assert repair_bag(tmp_path / 's').repaired
    assert _rosbags_seqs(tmp_path / 's') == list(range(1, n + 1))


@pytest.mark.parametrize('left', [0, 5, 8 + 4])
def test_an_empty_or_header_only_storage_file_is_skipped_and_removed(
        tmp_path: Path, left: int) -> None:
    """A bag whose last listed file holds nothing, the start of the magic or a cut header
    (a recorder killed as it created the file): the reader reads the files before it, and
    `bag repair` removes it; rosbags then reads every message."""
    w = _writer(tmp_path / 'e', max_bag_size=20_000)
    _write(w, 1, 1000)
    w.close()
    names = _meta(tmp_path / 'e')['relative_file_paths']
    last = tmp_path / 'e' / names[-1]
    kept = _meta(tmp_path / 'e')['message_count'] - _meta(tmp_path / 'e')['files'][-1][
        'message_count']
    last.write_bytes(last.read_bytes()[:left])
    bag = open_bag(tmp_path / 'e')
    assert _seqs(tmp_path / 'e') == list(range(1, kept + 1))
    assert (bag.empty == [last]) == (left < 8)
    res = repair_bag(tmp_path / 'e')
    assert res.repaired and res.removed == [last.name] and not last.exists()
    assert _meta(tmp_path / 'e')['relative_file_paths'] == names[:-1]
    assert _rosbags_seqs(tmp_path / 'e') == list(range(1, kept + 1))


# -- 4: stale metadata -----------------------------------------------------------------------
def test_metadata_older_than_the_files_is_rewritten(tmp_path: Path) -> None:
    """Killed after a file was finished (at a split) but before metadata.yaml was
    rewritten: the metadata says 900 messages where the files hold 1200; the repair sees it
    from the per-file counts and writes the true ones."""
    w = _writer(tmp_path / 'm', max_bag_duration=1.0)
    _write(w, 1, 900, flush_every=300)
    older = (tmp_path / 'm' / 'metadata.yaml').read_text()
    _write(w, 901, 1200, flush_every=300)      # the flush at 1200 splits the bag
    assert len(w.files) == 2
    (tmp_path / 'm' / 'metadata.yaml').write_text(older)    # its rewrite never happened
    assert _meta(tmp_path / 'm')['message_count'] == 900
    res = repair_bag(tmp_path / 'm')
    assert res.repaired and res.counts == {'/haptic/device/state': 1200}
    assert res.rewritten == {} and res.removed == ['m_1.mcap']   # header only
    meta = _meta(tmp_path / 'm')
    assert meta['message_count'] == 1200 and meta['custom_data'] == CUSTOM
    assert [(f['path'], f['message_count']) for f in meta['files']] == [('m_0.mcap', 1200)]
    assert _rosbags_seqs(tmp_path / 'm') == list(range(1, 1201))
    assert not repair_bag(tmp_path / 'm').repaired


# -- 5: not all or nothing -------------------------------------------------------------------
def test_a_corrupt_chunk_costs_the_rest_of_its_file_only(tmp_path: Path) -> None:
    """A CRC error in the second chunk of the middle file: the files before and after are
    left as they are (same inode), the middle one keeps its first chunk."""
    w = _writer(tmp_path / 'c', max_bag_size=30_000)
    _write(w, 1, 2000, flush_every=100)         # two chunks a file
    w.close()
    meta = _meta(tmp_path / 'c')
    names = meta['relative_file_paths']
    assert len(names) >= 3
    middle = tmp_path / 'c' / names[1]
    with middle.open('rb') as f:
        chunks = []
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                chunks.append((rec.message_end_time, f.tell()))
    assert len(chunks) >= 2
    data = bytearray(middle.read_bytes())
    data[chunks[1][1] - 100] ^= 0xFF        # in the second chunk's (uncompressed) records
    middle.write_bytes(bytes(data))
    inodes = {n: (tmp_path / 'c' / n).stat().st_ino for n in names}
    res = repair_bag(tmp_path / 'c')
    assert res.repaired and list(res.rewritten) == [names[1]]
    assert 'crc validation failed in Chunk' in res.rewritten[names[1]]
    assert {n: (tmp_path / 'c' / n).stat().st_ino for n in names[::2]} == {
        n: inodes[n] for n in names[::2]}
    last_kept = (chunks[0][0] - 1_000_000_000) // 1_000_000    # the first chunk's last seq
    after = meta['files'][0]['message_count'] + meta['files'][1]['message_count']
    expected = [*range(1, last_kept + 1), *range(after + 1, 2001)]
    assert _rosbags_seqs(tmp_path / 'c') == expected
    assert _seqs(tmp_path / 'c') == expected
    counts = [f['message_count'] for f in _meta(tmp_path / 'c')['files']]
    assert counts[0] == meta['files'][0]['message_count'] and sum(counts) == len(expected)


def test_complete_files_are_not_copied(tmp_path: Path) -> None:
    """The repair of a bag whose last file was cut writes a copy of that file only: with
    room for no other file of the bag's size (the process's file size limit, as a full disk
    would), it succeeds."""
    w = _writer(tmp_path / 'f', max_bag_size=390_000)
    _write(w, 1, 2000)                       # killed: f_0 complete, 200 messages in f_1
    assert [f['message_count'] for f in _meta(tmp_path / 'f')['files']] == [1800, 200]
    # The size of each file's repaired copy (zstd): the limit lets the small one be written.
    shutil.copytree(tmp_path / 'f', tmp_path / 'g')
    repair_bag(tmp_path / 'g', force=True)
    small, large = ((tmp_path / 'g' / f'f_{k}.mcap').stat().st_size for k in (1, 0))
    assert small * 4 < large
    limit = small * 2
    code = ('import resource, signal, sys\n'
            'signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n'
            f'resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n'
            'from haptic_topology.cli import main\n'
            'sys.exit(main(["bag", "repair", sys.argv[1]]))\n')
    proc = subprocess.run([sys.executable, '-c', code, str(tmp_path / 'f')],
                          capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 0, proc.stderr
    assert _rosbags_seqs(tmp_path / 'f') == list(range(1, 2001))


def test_storage_files_without_metadata_are_taken_in_the_order_of_their_numbers(
        tmp_path: Path) -> None:
    w = _writer(tmp_path / 'n', max_bag_size=10_000)
    _write(w, 1, 3000)
    w.close()
    names = _meta(tmp_path / 'n')['relative_file_paths']
    assert len(names) > 11
    (tmp_path / 'n' / 'metadata.yaml').unlink()
    assert _seqs(tmp_path / 'n') == list(range(1, 3001))
    assert repair_bag(tmp_path / 'n').repaired
    assert _meta(tmp_path / 'n')['relative_file_paths'] == names
    assert _meta(tmp_path / 'n')['custom_data'] == CUSTOM    # from the files' own records
    assert _rosbags_seqs(tmp_path / 'n') == list(range(1, 3001))


# -- 6: data before metadata -----------------------------------------------------------------
def test_the_data_is_on_disk_before_the_metadata_that_counts_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each time metadata.yaml goes to disk (its fsync), every storage file it lists has been
    synced as it is: a power cut cannot leave metadata counting data the disk lacks."""
    synced: dict[str, int] = {}
    unsynced: list[tuple[str, int, int]] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        real_fsync(fd)
        name = os.readlink(f'/proc/self/fd/{fd}')
        if name.endswith('.mcap'):
            synced[os.path.basename(name)] = os.fstat(fd).st_size
        elif name.endswith('.metadata.yaml.tmp'):
            listed = yaml.safe_load(Path(name).read_text())[
                'rosbag2_bagfile_information']['relative_file_paths']
            for n in listed:
                size = (Path(name).parent / n).stat().st_size
                if synced.get(n) != size:
                    unsynced.append((n, size, synced.get(n, -1)))

    monkeypatch.setattr(os, 'fsync', fsync)
    w = _writer(tmp_path / 'd', max_bag_size=20_000)
    _write(w, 1, 1500)
    w.close()
    assert len(synced) >= 3
    assert unsynced == []


def test_a_failing_disk_raises_a_bag_write_error_naming_the_file(tmp_path: Path) -> None:
    """The recorder catches ``OSError`` around its writer; the writer's error is one, and a
    ``BagError`` naming the file it could not write."""
    w = _writer(tmp_path / 'x')
    _write(w, 1, 100)
    shutil.rmtree(tmp_path / 'x')           # the bag's directory is gone
    with pytest.raises(BagWriteError) as err:
        w.flush()
    assert isinstance(err.value, OSError) and isinstance(err.value, BagError)
    assert err.value.errno == errno.ENOENT
    assert str(err.value).startswith(f'{tmp_path / "x" / "metadata.yaml"}: cannot write')
