"""Bags split into several storage files (the recorder's ``max_bag_size`` and
``max_bag_duration``, as rosbag2's): every message read back in order, by this package's
reader and by rosbags; ``metadata.yaml`` lists each file with its counts; a recorder killed
while writing a later file leaves a bag that reads and repairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.errors import BagError
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

STATE = type_name('DeviceState')


def _state_bytes(seq: int) -> bytes:
    ts = typestore_with_haptic_msgs()
    header = ts.types['std_msgs/msg/Header'](ts.types['builtin_interfaces/msg/Time'](1, 2),
                                             'base')
    v = np.array([0.1, 0.2, 0.3]) * seq
    return bytes(ts.serialize_cdr(ts.types[STATE](header, seq, 3, v, v, v, v, 0, np.zeros(0), 0),
                                  STATE))


def _write(path: Path, n: int, flush_every: int = 200, **split: float) -> BagWriter:
    """``n`` states 1 ms apart, flushed every ``flush_every`` (the recorder flushes every
    0.2 s: the split happens at a flush)."""
    w = BagWriter(path, [TopicSpec('/haptic/device/state', STATE, (make_qos(False, 1),))],
                  typestore_with_haptic_msgs(), sources=message_definitions(),
                  compression='none', **split)  # type: ignore[arg-type]
    for i in range(1, n + 1):
        w.write(0, 1_000_000_000 + i * 1_000_000, _state_bytes(i))
        if i % flush_every == 0:
            w.flush()
    return w


def _meta(path: Path) -> dict:
    return yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


@pytest.mark.parametrize('split', [{'max_bag_size': 40_000}, {'max_bag_duration': 0.5}])
def test_a_split_bag_reads_back_whole_and_in_order(tmp_path: Path, split: dict) -> None:
    _write(tmp_path / 'b', 3000, **split).close()
    meta = _meta(tmp_path / 'b')
    names = meta['relative_file_paths']
    assert len(names) >= 3 and names == [f'b_{k}.mcap' for k in range(len(names))]
    assert sorted(p.name for p in (tmp_path / 'b').glob('*.mcap')) == sorted(names)
    assert [f['path'] for f in meta['files']] == names
    assert sum(f['message_count'] for f in meta['files']) == meta['message_count'] == 3000
    assert all(f['message_count'] > 0 for f in meta['files'])
    if 'max_bag_duration' in split:     # each file spans about the limit (split at flushes)
        spans = [f['duration']['nanoseconds'] for f in meta['files'][:-1]]
        assert all(0.5e9 <= s < 0.5e9 + 0.2e9 for s in spans), spans
    else:
        sizes = [(tmp_path / 'b' / n).stat().st_size for n in names[:-1]]
        assert all(s >= 40_000 for s in sizes), sizes
    decode = decoder()
    assert [decode(m).seq for m in iter_messages(open_bag(tmp_path / 'b'))] == list(
        range(1, 3001))
    with AnyReader([tmp_path / 'b']) as reader:      # rosbags, from metadata.yaml
        assert [reader.deserialize(raw, c.msgtype).seq
                for c, _, raw in reader.messages()] == list(range(1, 3001))


def test_a_recorder_killed_in_a_later_file_leaves_a_bag_that_reads_and_repairs(
        tmp_path: Path) -> None:
    w = _write(tmp_path / 'k', 2900, max_bag_size=40_000)
    w._file.flush()                 # killed: no close(); the files before are complete
    bag = open_bag(tmp_path / 'k')
    assert len(bag.files) >= 3
    seqs = [decoder()(m).seq for m in iter_messages(bag)]
    assert bag.truncated and seqs[:2800] == list(range(1, 2801))
    res = repair_bag(tmp_path / 'k')
    assert res.repaired and res.counts['/haptic/device/state'] == len(seqs)
    # The last file was opened at the split of the last flush and holds only its header
    # (the 100 messages since were not flushed): removed, the others listed.
    last = bag.files[-1].name
    assert res.removed == [last] and not (tmp_path / 'k' / last).exists()
    meta = _meta(tmp_path / 'k')
    assert [f['path'] for f in meta['files']] == [p.name for p in bag.files[:-1]]
    with AnyReader([tmp_path / 'k']) as reader:
        assert reader.message_count == len(seqs)


def test_split_limits_must_not_be_negative(tmp_path: Path) -> None:
    with pytest.raises(BagError, match='max_bag_size'):
        _write(tmp_path / 'n', 1, max_bag_size=-1)


def test_chunk_indexes_wait_on_disk_and_the_summary_indexes_every_chunk(
        tmp_path: Path) -> None:
    """The chunk indexes of the file being written are not kept as Python objects (1.1 kB
    each, one per 0.2 s flush, for as long as the file lasts): the summary written at the
    end still indexes every chunk, at the offsets where the chunks are, and readers that
    seek through it (mcap's, rosbags') read every message."""
    import tracemalloc

    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Chunk

    tracemalloc.start()
    w = _write(tmp_path / 'b', 500, flush_every=1)      # 500 chunks of one message each
    before = tracemalloc.take_snapshot()
    for i in range(501, 1501):
        w.write(0, 1_000_000_000 + i * 1_000_000, _state_bytes(i))
        w.flush()
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    w.close()
    # 1000 more chunks: mcap's own ChunkIndex objects would be thousands more live blocks
    # (> 500 kB), made in mcap's code or the writer's. Only those are counted: what the
    # interpreter and the standard library keep meanwhile depends on what ran before in the
    # process (the interned strings' dict grows by one block of several MB; pathlib's
    # interned parts, ~900 blocks in a fresh process).
    ours = [tracemalloc.Filter(True, '*/mcap/*'), tracemalloc.Filter(True, '*/bag/writer.py'),
            tracemalloc.Filter(True, '*/bag/metadata_text.py')]
    diff = after.filter_traces(ours).compare_to(before.filter_traces(ours), 'filename')
    blocks = sum(d.count_diff for d in diff)
    assert blocks < 300, [str(d) for d in diff[:5]]
    path = tmp_path / 'b' / 'b_0.mcap'
    with path.open('rb') as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        indexes = summary.chunk_indexes
        assert len(indexes) == 1500
        for ci in indexes:
            f.seek(ci.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(f))
            assert (chunk.message_start_time, chunk.message_end_time) == (
                ci.message_start_time, ci.message_end_time)
        f.seek(0)
        seqs = [int(m.log_time) for _, _, m in make_reader(f).iter_messages()]
    assert seqs == [1_000_000_000 + i * 1_000_000 for i in range(1, 1501)]
    with AnyReader([tmp_path / 'b'], default_typestore=typestore_with_haptic_msgs()) as r:
        assert sum(1 for _ in r.messages()) == 1500
