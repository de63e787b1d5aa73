"""``haptic-topology bag repair BAG``: make a bag whose recorder was killed whole again.

A recorder killed with SIGKILL (or a power cut) leaves an MCAP file without summary and
footer, and a ``metadata.yaml`` with the counts of its last flush. Readers that seek to the
footer (``rosbags``, ``ros2 bag``, ``mcap.reader.make_reader``) refuse such a file. The
repair reads every complete record (up to the last complete chunk), writes a new MCAP file
with the same schemas, channels and messages plus summary, Statistics and footer next to
it, renames it over the old one, and rewrites ``metadata.yaml`` with the true counts. A bag
that is already complete is left untouched.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos

from haptic_topology import __version__
from haptic_topology.bag.reader import iter_records, open_bag
from haptic_topology.bag.writer import (
    FileInfo,
    TopicSpec,
    dump_yaml,
    metadata_info,
    write_metadata,
)
from haptic_topology.errors import BagError, TruncatedError


@dataclass(frozen=True)
class RepairResult:
    """What the repair found: the bag, whether it was rewritten, messages per topic."""

    path: Path
    repaired: bool
    counts: dict[str, int]


def _rewrite(src: Path, dst: Path) -> tuple[list[TopicSpec], dict[str, str], list[int], int,
                                              int, bool]:
    """Copy every complete record of ``src`` into a complete MCAP file ``dst``."""
    topics: list[TopicSpec] = []
    hashes: dict[str, str] = {}
    counts: list[int] = []
    start = end = 0
    schema_map: dict[int, int] = {}
    channel_map: dict[int, int] = {}
    index_of: dict[int, int] = {}
    schemas: dict[int, Schema] = {}
    truncated = False
    with src.open('rb') as stream, dst.open('wb') as out:
        writer = McapWriter(out, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
        writer.start(profile='ros2', library=f'haptic_topology {__version__} (repaired)')
        try:
            for rec in iter_records(src, stream):
                if isinstance(rec, Schema) and rec.id not in schema_map:
                    schemas[rec.id] = rec
                    schema_map[rec.id] = writer.register_schema(rec.name, rec.encoding,
                                                                rec.data)
                elif isinstance(rec, Channel) and rec.id not in channel_map:
                    channel_map[rec.id] = writer.register_channel(
                        rec.topic, rec.message_encoding, schema_map.get(rec.schema_id, 0),
                        dict(rec.metadata))
                    msgtype = schemas[rec.schema_id].name if rec.schema_id in schemas else ''
                    try:
                        qos = tuple(parse_qos(rec.metadata.get('offered_qos_profiles', '')))
                    except (ReaderError, KeyError, TypeError):
                        qos = ()
                    index_of[rec.id] = len(topics)
                    topics.append(TopicSpec(rec.topic, msgtype, qos))
                    hashes[msgtype] = rec.metadata.get('topic_type_hash', '')
                    counts.append(0)
                elif isinstance(rec, Message):
                    if rec.channel_id not in channel_map:
                        raise BagError(f'{src}: message on unknown channel {rec.channel_id}')
                    writer.add_message(channel_map[rec.channel_id], rec.log_time, rec.data,
                                       rec.publish_time, rec.sequence)
                    if not any(counts):
                        start = end = rec.log_time
                    start, end = min(start, rec.log_time), max(end, rec.log_time)
                    counts[index_of[rec.channel_id]] += 1
        except TruncatedError:
            truncated = True
        info = metadata_info([FileInfo(dst.name, start, end, sum(counts))], topics, hashes,
                             counts, start, end)
        writer.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(info)})
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    return topics, hashes, counts, start, end, truncated


def repair_bag(path: str | Path, force: bool = False) -> RepairResult:
    """Repair the bag at ``path`` (see module doc); ``force`` rewrites a complete bag too. A
    bag split into several files (the recorder's ``max_bag_size``/``max_bag_duration``) has
    each file checked; the truncated ones (a killed recorder leaves the last) are rewritten,
    and ``metadata.yaml`` lists them all with their counts."""
    bag = open_bag(path)
    if bag.path.is_file():
        raise BagError(f'{bag.path}: give the bag directory (repair rewrites metadata.yaml)')
    files: list[FileInfo] = []
    topics: list[TopicSpec] = []
    hashes: dict[str, str] = {}
    counts: list[int] = []
    repaired = force or bag.metadata is None
    for src in bag.files:
        tmp = src.with_name(f'.{src.name}.repair')
        try:
            file_topics, file_hashes, file_counts, start, end, truncated = _rewrite(src, tmp)
            if truncated or force or bag.metadata is None:
                tmp.replace(src)
                repaired = True
        finally:
            if tmp.exists():
                tmp.unlink()
        files.append(FileInfo(src.name, start, end, sum(file_counts)))
        hashes.update(file_hashes)
        for spec, n in zip(file_topics, file_counts, strict=True):
            known = [t.topic for t in topics]
            if spec.topic in known:
                counts[known.index(spec.topic)] += n
            else:
                topics.append(spec)
                counts.append(n)
    per_topic = {t.topic: n for t, n in zip(topics, counts, strict=True)}
    if not repaired:
        return RepairResult(bag.path, False, per_topic)
    done = [f for f in files if f.messages]
    write_metadata(bag.path, metadata_info(
        files, topics, hashes, counts, min((f.start_ns for f in done), default=0),
        max((f.end_ns for f in done), default=0)))
    return RepairResult(bag.path, True, per_topic)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest='bag_command', metavar='ACTION', required=True)
    rep = sub.add_parser('repair', help='rewrite a truncated bag (recorder killed) whole',
                         description=__doc__.split('\n\n')[0] if __doc__ else None)
    rep.add_argument('bag', type=Path, help='bag directory')
    rep.add_argument('--force', action='store_true', help='rewrite a complete bag too')
    info = sub.add_parser('info', help='topics, types and counts of a bag')
    info.add_argument('bag', type=Path, help='bag directory or .mcap file')


def run(args: argparse.Namespace) -> int:
    """The ``bag`` subcommand: ``repair`` or ``info``."""
    if args.bag_command == 'repair':
        res = repair_bag(args.bag, args.force)
        total = sum(res.counts.values())
        verb = 'repaired' if res.repaired else 'complete, left as it is'
        print(f'{res.path}: {verb}: {total} messages')
        for topic, n in res.counts.items():
            print(f'  {topic}: {n}')
        return 0
    from haptic_topology.bag.reader import iter_messages

    bag = open_bag(args.bag)
    counts: dict[str, int] = {}
    first = last = None
    for msg in iter_messages(bag):
        counts[msg.topic] = counts.get(msg.topic, 0) + 1
        first = msg.log_time if first is None else min(first, msg.log_time)
        last = msg.log_time if last is None else max(last, msg.log_time)
    span = (last - first) * 1e-9 if first is not None and last is not None else 0.0
    print(f'{bag.path}: {sum(counts.values())} messages over {span:.3f} s, '
          f'{bag.size / 1e6:.2f} MB' + (' (TRUNCATED: run `haptic-topology bag repair`)'
                                         if bag.truncated else ''))
    for topic, n in counts.items():
        print(f'  {topic}  {bag.topics.get(topic, "?")}  {n}')
    return 0
