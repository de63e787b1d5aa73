"""``haptic-topology bag repair BAG``: make a bag whose recorder was killed whole again.

A recorder killed with SIGKILL (or a power cut) leaves its last MCAP file without summary and
footer, maybe a new storage file holding only the MCAP header (killed just after a split),
and a ``metadata.yaml`` with the counts of its last flush. Readers that seek to the footer
(``rosbags``, ``ros2 bag``, ``mcap.reader.make_reader``) refuse such a file. The repair reads
every storage file of the bag (those ``metadata.yaml`` lists and any other ``*.mcap`` beside
them, in the order of their numbers) up to its last good record: the end of a truncated
file, or the record before a corrupt chunk. A file that ends in its footer with every record
good is left as it is; another is rewritten (same schemas, channels and messages, plus
summary, Statistics and footer) into a temporary file beside it that then replaces it; a file
holding no message (created by a recorder killed before it wrote one) is removed, unless it is
the bag's only file. ``metadata.yaml`` is rewritten when a file was, or when its per-file
counts differ from what the files hold; it keeps the recorder's ``custom_data`` (graph id,
scenario) and ``ros_distro``. A bag that is already complete is left untouched.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.records import Channel, Message, Metadata, Schema
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos

from haptic_topology import __version__
from haptic_topology.bag.reader import (
    MCAP_MAGIC,
    METADATA,
    Bag,
    iter_records,
    open_bag,
    storage_order,
)
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
    """What the repair found: the bag, whether anything was rewritten, messages per topic,
    and per storage file name what was done (``rewritten``: file -> why; ``removed``)."""

    path: Path
    repaired: bool
    counts: dict[str, int]
    rewritten: dict[str, str] = field(default_factory=dict)
    removed: list[str] = field(default_factory=list)


@dataclass
class _Scan:
    """What one storage file holds up to its last good record."""

    path: Path
    topics: list[TopicSpec] = field(default_factory=list)
    hashes: dict[str, str] = field(default_factory=dict)
    counts: list[int] = field(default_factory=list)
    start_ns: int = 0
    end_ns: int = 0
    #: Why the file is not complete: '' (it ends in its footer, every record good), or what
    #: stopped the reading (no footer, a corrupt record).
    problem: str = ''
    corrupt: bool = False
    #: The ``rosbag2`` metadata record the recorder put into the file when it finished it.
    embedded: dict[str, Any] | None = None

    @property
    def messages(self) -> int:
        return sum(self.counts)

    def info(self) -> FileInfo:
        return FileInfo(self.path.name, self.start_ns, self.end_ns, self.messages)


def _copy(src: Path, writer: McapWriter | None = None) -> _Scan:
    """Read ``src`` up to its last good record; with ``writer``, copy the schemas, channels
    and messages read into it."""
    scan = _Scan(src)
    schemas: dict[int, Schema] = {}
    schema_map: dict[int, int] = {}
    channel_map: dict[int, int] = {}
    index_of: dict[int, int] = {}
    with src.open('rb') as stream:
        head = stream.read(len(MCAP_MAGIC))
        if len(head) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(head):
            scan.problem = 'no MCAP header (the recorder was stopped as it created the file)'
            return scan
        stream.seek(0)
        try:
            for rec in iter_records(src, stream):
                if isinstance(rec, Schema) and rec.id not in schemas:
                    schemas[rec.id] = rec
                    if writer is not None:
                        schema_map[rec.id] = writer.register_schema(rec.name, rec.encoding,
                                                                    rec.data)
                elif isinstance(rec, Channel) and rec.id not in index_of:
                    if writer is not None:
                        channel_map[rec.id] = writer.register_channel(
                            rec.topic, rec.message_encoding, schema_map.get(rec.schema_id, 0),
                            dict(rec.metadata))
                    msgtype = schemas[rec.schema_id].name if rec.schema_id in schemas else ''
                    index_of[rec.id] = len(scan.topics)
                    scan.topics.append(TopicSpec(rec.topic, msgtype,
                                                 _qos(rec.metadata.get('offered_qos_profiles'))))
                    scan.hashes[msgtype] = rec.metadata.get('topic_type_hash', '')
                    scan.counts.append(0)
                elif isinstance(rec, Message):
                    if rec.channel_id not in index_of:
                        raise BagError(f'{src}: message on unknown channel {rec.channel_id}')
                    if writer is not None:
                        writer.add_message(channel_map[rec.channel_id], rec.log_time, rec.data,
                                           rec.publish_time, rec.sequence)
                    if not scan.messages:
                        scan.start_ns = scan.end_ns = rec.log_time
                    scan.start_ns = min(scan.start_ns, rec.log_time)
                    scan.end_ns = max(scan.end_ns, rec.log_time)
                    scan.counts[index_of[rec.channel_id]] += 1
                elif isinstance(rec, Metadata) and rec.name == 'rosbag2':
                    scan.embedded = _embedded(rec.metadata.get('serialized_metadata', ''))
        except TruncatedError:
            scan.problem = 'no footer (the recorder was stopped before it finished the file)'
        except BagError as exc:
            scan.problem, scan.corrupt = str(exc).removeprefix(f'{src}: '), True
    return scan


def _qos(text: Any) -> tuple[Qos, ...]:
    try:
        return tuple(parse_qos(text or ''))
    except (ReaderError, KeyError, TypeError, AttributeError):
        return ()


def _embedded(text: str) -> dict[str, Any] | None:
    try:
        info = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    if isinstance(info, dict) and isinstance(info.get('rosbag2_bagfile_information'), dict):
        info = info['rosbag2_bagfile_information']
    return info if isinstance(info, dict) else None


def _storage_files(bag: Bag) -> list[Path]:
    """The bag's storage files: those ``metadata.yaml`` lists, in its order, then any other
    ``*.mcap`` of the directory by number (a file a killed recorder created but had not listed
    yet)."""
    listed = [*bag.files, *bag.empty]
    if bag.metadata is not None:
        names = [str(n) for n in bag.metadata.get('relative_file_paths') or []]
        listed = [bag.path / n for n in names]
    others = sorted((p for p in bag.path.glob('*.mcap') if p not in listed), key=storage_order)
    return [*listed, *others]


def _metadata_topics(metadata: dict[str, Any] | None) -> list[tuple[TopicSpec, str]]:
    """The topics ``metadata.yaml`` lists, with their type hashes."""
    out = []
    for entry in (metadata or {}).get('topics_with_message_count') or []:
        meta = entry.get('topic_metadata') if isinstance(entry, dict) else None
        if isinstance(meta, dict) and 'name' in meta and 'type' in meta:
            out.append((TopicSpec(str(meta['name']), str(meta['type']),
                                  _qos(meta.get('offered_qos_profiles'))),
                        str(meta.get('type_description_hash', ''))))
    return out


def _listed_counts(metadata: dict[str, Any] | None) -> list[tuple[str, int]] | None:
    try:
        return [(str(f['path']), int(f['message_count']))
                for f in (metadata or {}).get('files') or []]
    except (KeyError, TypeError, ValueError):
        return None


def _rewrite(src: Path, info: dict[str, Any]) -> None:
    """Replace ``src`` by a complete MCAP file of its good records (see module doc)."""
    tmp = src.with_name(f'.{src.name}.repair')
    try:
        with tmp.open('wb') as out:
            writer = McapWriter(out, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
            writer.start(profile='ros2', library=f'haptic_topology {__version__} (repaired)')
            _copy(src, writer)
            writer.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(info)})
            writer.finish()
            out.flush()
            os.fsync(out.fileno())
        tmp.replace(src)
    except OSError as exc:
        raise BagError(f'{src}: cannot repair ({exc.strerror or exc}); the file is left '
                       'as it was') from None
    finally:
        if tmp.exists():
            tmp.unlink()


def repair_bag(path: str | Path, force: bool = False) -> RepairResult:
    """Repair the bag directory at ``path`` (see module doc); ``force`` rewrites every file
    and ``metadata.yaml`` of a complete bag too."""
    bag = open_bag(path)
    if bag.path.is_file():
        raise BagError(f'{bag.path}: give the bag directory (repair rewrites metadata.yaml)')
    scans = [_copy(p) for p in _storage_files(bag)]
    empty = [s for s in scans if not s.messages and not s.corrupt]
    drop = {id(s) for s in (empty[1:] if len(empty) == len(scans) else empty)}
    kept = [s for s in scans if id(s) not in drop]
    # Topics: those metadata.yaml lists (in its order), then the others the files hold.
    topics = _metadata_topics(bag.metadata)
    for s in kept:
        known = {t.topic for t, _ in topics}
        topics += [(t, s.hashes.get(t.msgtype, '')) for t in s.topics if t.topic not in known]
    specs = [t for t, _ in topics]
    hashes = {t.msgtype: h for t, h in reversed(topics)}
    per_topic = dict.fromkeys((t.topic for t in specs), 0)
    for s in kept:
        for t, n in zip(s.topics, s.counts, strict=True):
            per_topic[t.topic] += n
    embedded = next((s.embedded for s in scans if s.embedded), None) or {}
    source = bag.metadata if bag.metadata is not None else embedded
    custom = source.get('custom_data') if isinstance(source.get('custom_data'), dict) else None
    files = [s.info() for s in kept]
    done = [f for f in files if f.messages]
    info = metadata_info(files, specs, hashes, list(per_topic.values()),
                         min((f.start_ns for f in done), default=0),
                         max((f.end_ns for f in done), default=0), custom,
                         str(source.get('ros_distro') or 'jazzy'))
    rewrite = [s for s in kept if s.problem or force]
    stale = (bag.metadata is None or force
             or _listed_counts(bag.metadata) != [(f.name, f.messages) for f in files]
             or bag.metadata.get('message_count') != sum(per_topic.values()))
    if not (rewrite or drop or stale):
        return RepairResult(bag.path, False, per_topic)
    for s in rewrite:
        _rewrite(s.path, info)
    for s in scans:
        if id(s) in drop:
            s.path.unlink()
    try:
        write_metadata(bag.path, info)
    except OSError as exc:
        raise BagError(f'{bag.path / METADATA}: cannot write ({exc.strerror or exc})') from None
    return RepairResult(bag.path, True, per_topic,
                        {s.path.name: s.problem or 'rewritten (--force)' for s in rewrite},
                        [s.path.name for s in scans if id(s) in drop])


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
        for name, why in res.rewritten.items():
            print(f'  {name}: rewritten up to its last good record: {why}')
        for name in res.removed:
            print(f'  {name}: removed (it held no message)')
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
