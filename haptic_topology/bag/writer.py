"""rosbag2 directories with MCAP storage, written so that a crash loses little.

A bag is a directory ``<name>/`` holding ``metadata.yaml`` and ``<name>_0.mcap``, the layout
``ros2 bag record -s mcap`` produces (metadata version 9, Jazzy). With ``max_bag_size``
(bytes) or ``max_bag_duration`` (s) the bag is split as rosbag2 splits it: at the first flush
after the current file has reached the size or spans the duration, the file is finished
(summary, footer) and ``<name>_1.mcap``, ``<name>_2.mcap``, ... follow; ``metadata.yaml``
lists them in order with their counts. The chunk indexes of the file being written wait in an
unnamed temporary file beside it (:class:`SpilledChunkIndexes`), not in memory, until the
file's summary takes them. The MCAP file has profile
``ros2``, one ``ros2msg`` schema per message type whose text is the .msg definition followed by
every dependency in rosbag2's concatenated form (``====...\\nMSG: std_msgs/Header\\n...``),
``cdr`` message encoding, and per channel the ``offered_qos_profiles`` (YAML) and
``topic_type_hash`` (RIHS01) metadata rosbag2 writes. On :meth:`BagWriter.close` the summary
(schemas, channels, chunk indexes, Statistics) and a ``rosbag2`` metadata record are added,
as rosbag2 does.

Crash tolerance: messages go into chunks of ``chunk_size`` bytes (64 KiB: ~0.1 s of the
1 kHz graph), and :meth:`BagWriter.flush` (called every ``flush_period``) closes the current
chunk early and puts it on disk (fsync), then rewrites ``metadata.yaml`` atomically
(temporary file, fsync, rename) with the running counts: the metadata never counts data the
disk lacks, and a new file's header is on disk before the metadata names it. The bag
directory appears (renamed from a hidden one) only with its first file and metadata. A
killed bag lacks the MCAP summary and footer: readers that seek to the footer (``rosbags``,
``mcap.reader.make_reader``) then need :func:`haptic_topology.bag.repair.repair_bag`;
:mod:`haptic_topology.bag.reader` reads such a file as it is. ``flush`` and ``close`` raise
:class:`~haptic_topology.errors.BagWriteError` (an ``OSError`` too) when the disk fails.
"""

from __future__ import annotations

import os
import secrets
import struct
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import ChunkIndex, MessageIndex
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys.store import Typestore

from haptic_topology import __version__
from haptic_topology.bag.metadata_text import MetadataText, dump_yaml
from haptic_topology.errors import BagError, BagWriteError

METADATA = 'metadata.yaml'
ROSBAG2_VERSION = 9
MSGDEF_SEPARATOR = '=' * 80 + '\n'
COMPRESSIONS = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
                'none': CompressionType.NONE}


@dataclass(frozen=True)
class TopicSpec:
    """A topic of a bag: name, full type name and the QoS its publishers offer."""

    topic: str
    msgtype: str
    qos: tuple[Qos, ...] = ()


def make_qos(reliable: bool, depth: int, transient_local: bool = False) -> Qos:
    """A rosbags :class:`Qos` (keep last ``depth``, volatile unless ``transient_local``) as
    our publishers offer it (``ros2 bag play`` offers a transient-local topic so again, e.g.
    ``/robot_description`` to a late RViz)."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def schema_text(typestore: Typestore, msgtype: str,
                sources: Mapping[str, str] | None = None) -> str:
    """The ``ros2msg`` schema of ``msgtype``: its definition, then each dependency.

    ``sources`` maps type names to original .msg texts (with their comments and units); the
    definition of a type found there replaces the one generated from the typestore.
    """
    generated, _ = typestore.generate_msgdef(msgtype, ros_version=2)
    if sources and msgtype in sources:
        parts = generated.split(MSGDEF_SEPARATOR)
        parts[0] = sources[msgtype].rstrip('\n') + '\n'
        generated = MSGDEF_SEPARATOR.join(parts)
    return generated


class SpilledChunkIndexes:
    """Stands in for the list of chunk indexes that mcap's ``Writer`` keeps until
    ``finish()`` writes them into the summary: each index is serialized as it comes (the
    summary record itself) into an unnamed temporary file in ``directory``, and read back
    once, when the summary is written. Kept as objects, an index is ~1.1 kB of Python
    (its per-channel offsets are a dict), and the recorder closes a chunk every flush
    (0.2 s): 5.5 kB/s of memory held until the file ends. The spill file takes ~0.2 kB per
    chunk of disk and none of memory beyond the OS's page cache."""

    def __init__(self, directory: Path) -> None:
        self._spill = tempfile.TemporaryFile(dir=directory)
        self._count = 0

    def append(self, index: ChunkIndex) -> None:
        record = RecordBuilder()
        index.write(record)
        self._spill.write(record.end())
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Any:
        """One item whose ``write`` puts every index record into the summary, in order."""
        self._spill.seek(0)
        yield _RawRecords(self._spill.read())
        self._spill.close()


@dataclass(frozen=True)
class _RawRecords:
    data: bytes

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


def qos_yaml(qos: Sequence[Qos]) -> str:
    """``offered_qos_profiles`` as rosbag2 (metadata version 9) stores it in MCAP channels."""
    if not qos:
        return ''
    return dump_yaml(dump_qos_v9(list(qos))).strip()


def write_metadata(path: Path, info: dict[str, Any], text: str | None = None) -> None:
    """Write ``path/metadata.yaml`` atomically (temporary file, then rename); ``text``: the
    document already emitted (default: ``dump_yaml`` of ``info``)."""
    tmp = path / f'.{METADATA}.tmp'
    text = text or dump_yaml({'rosbag2_bagfile_information': info})
    with tmp.open('w', encoding='utf-8') as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path / METADATA)


@dataclass(frozen=True)
class FileInfo:
    """One storage file of a bag: its name, time range (ns) and message count."""

    name: str
    start_ns: int
    end_ns: int
    messages: int


def metadata_info(files: Sequence[FileInfo], topics: Sequence[TopicSpec],
                  hashes: Mapping[str, str], counts: Sequence[int], start_ns: int,
                  end_ns: int, custom: Mapping[str, str] | None = None,
                  ros_distro: str = 'jazzy') -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping (metadata version 9) of a bag whose
    storage ``files`` are in order; ``custom``: its ``custom_data`` (the recorder's graph id
    and scenario)."""
    total = int(sum(counts))
    start = start_ns if total else 0
    duration = max(0, end_ns - start_ns) if total else 0
    return {
        'version': ROSBAG2_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': total,
        'topics_with_message_count': [
            {'topic_metadata': {'name': t.topic, 'type': t.msgtype,
                                'serialization_format': 'cdr',
                                'offered_qos_profiles': dump_qos_v9(list(t.qos)),
                                'type_description_hash': hashes[t.msgtype]},
             'message_count': int(n)}
            for t, n in zip(topics, counts, strict=True)],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.name for f in files],
        'files': [{'path': f.name,
                   'starting_time': {'nanoseconds_since_epoch': f.start_ns if f.messages
                                     else 0},
                   'duration': {'nanoseconds': max(0, f.end_ns - f.start_ns)
                                if f.messages else 0},
                   'message_count': int(f.messages)} for f in files],
        'custom_data': dict(custom) if custom else None,
        'ros_distro': ros_distro,
    }


@dataclass
class _Counts:
    per_topic: list[int]
    start_ns: int = 0
    end_ns: int = 0
    flushed: list[int] = field(default_factory=list)


class BagWriter:
    """Writes one rosbag2 directory (see module doc). Not thread-safe: one writer thread.

    Example::

        w = BagWriter(Path('bags/x'), [TopicSpec('/a', 'std_msgs/msg/String')], store)
        w.write(0, time.time_ns(), cdr_bytes)  # topic index, receive time, CDR
        w.close()
    """

    def __init__(self, path: Path, topics: Sequence[TopicSpec], typestore: Typestore, *,
                 sources: Mapping[str, str] | None = None, chunk_size: int = 64 * 1024,
                 compression: str = 'zstd', custom: Mapping[str, str] | None = None,
                 max_bag_size: int = 0, max_bag_duration: float = 0.0) -> None:
        if compression not in COMPRESSIONS:
            raise BagError(f'{path}: compression must be one of {", ".join(COMPRESSIONS)}, '
                           f'got {compression!r}')
        if max_bag_size < 0 or not max_bag_duration >= 0.0:
            raise BagError(f'{path}: max_bag_size (bytes) and max_bag_duration (s) must be '
                           f'>= 0 (0: no split), got {max_bag_size} and {max_bag_duration}')
        if path.exists():
            raise BagError(f'{path}: already exists (a bag is never overwritten)')
        self.path = path
        self.topics = list(topics)
        self.custom = dict(custom or {})
        self.max_bag_size = int(max_bag_size)
        self.max_bag_duration_ns = round(max_bag_duration * 1e9)
        self._chunk_size, self._compression = chunk_size, COMPRESSIONS[compression]
        self.hashes: dict[str, str] = {}
        self._metadata_text = MetadataText()
        self._schemas: dict[str, bytes] = {}
        for spec in self.topics:
            if spec.msgtype not in self._schemas:
                try:
                    self._schemas[spec.msgtype] = schema_text(typestore, spec.msgtype,
                                                              sources).encode()
                    self.hashes[spec.msgtype] = typestore.hash_rihs01(spec.msgtype)
                except KeyError:
                    raise BagError(f'{path}: unknown message type {spec.msgtype} '
                                   f'(topic {spec.topic})') from None
        # The bag is made in a hidden directory beside ``path`` and renamed to ``path`` once
        # its first file has its header and metadata.yaml lists it: ``path`` never exists
        # without both (a kill before leaves ``.<name>.<hex>.part``).
        self._dir = path.parent / f'.{path.name}.{secrets.token_hex(4)}.part'
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._dir.mkdir()
        except OSError as exc:
            raise BagError(f'{path}: cannot create bag ({exc.strerror})') from None
        self._files: list[FileInfo] = []       # the closed storage files, in order
        self._counts = _Counts([0] * len(self.topics))
        self._counts.flushed = list(self._counts.per_topic)
        self._open_file()
        self._open = True
        self.flush(force=True)
        try:
            self._dir.rename(path)
        except OSError as exc:
            raise BagError(f'{path}: cannot create bag ({exc.strerror})') from None
        self._dir = path

    def _open_file(self) -> None:
        """Start storage file ``<name>_<k>.mcap`` (k: the files so far): schemas, channels."""
        self.mcap_name = f'{self.path.name}_{len(self._files)}.mcap'
        try:
            self._file: IO[bytes] = (self._dir / self.mcap_name).open('xb')
        except OSError as exc:
            raise BagError(f'{self.path}: cannot create {self.mcap_name} '
                           f'({exc.strerror})') from None
        self._mcap = McapWriter(self._file, chunk_size=self._chunk_size,
                                compression=self._compression)
        if hasattr(self._mcap, '_Writer__chunk_indices'):    # mcap 1.x (requirements.lock)
            self._mcap._Writer__chunk_indices = SpilledChunkIndexes(self._dir)
        self._mcap.start(profile='ros2', library=f'haptic_topology {__version__}')
        # The header on disk before metadata.yaml names the file: a bag killed after the
        # next metadata write never lists a file that no reader can open.
        self._sync()
        schema_ids = {t: self._mcap.register_schema(t, 'ros2msg', text)
                      for t, text in self._schemas.items()}
        self.channel_ids: list[int] = [
            self._mcap.register_channel(spec.topic, 'cdr', schema_ids[spec.msgtype],
                                        {'offered_qos_profiles': qos_yaml(spec.qos),
                                         'topic_type_hash': self.hashes[spec.msgtype]})
            for spec in self.topics]
        self._file_first = sum(self._counts.per_topic)     # messages before this file
        self._file_range: tuple[int, int] | None = None    # (first, last) log time (ns)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return {t.topic: n for t, n in zip(self.topics, self._counts.per_topic, strict=True)}

    def write(self, index: int, log_time_ns: int, data: bytes,
              publish_time_ns: int | None = None) -> None:
        """Append the serialized message ``data`` to topic ``self.topics[index]``."""
        c = self._counts
        seq = c.per_topic[index]
        self._mcap.add_message(self.channel_ids[index], log_time_ns, data,
                               log_time_ns if publish_time_ns is None else publish_time_ns,
                               seq)
        if not any(c.per_topic):
            c.start_ns = c.end_ns = log_time_ns
        c.start_ns = min(c.start_ns, log_time_ns)
        c.end_ns = max(c.end_ns, log_time_ns)
        c.per_topic[index] = seq + 1
        r = self._file_range
        self._file_range = ((log_time_ns, log_time_ns) if r is None else
                            (min(r[0], log_time_ns), max(r[1], log_time_ns)))

    def write_many(self, items: Sequence[tuple[int, int, bytes]]) -> None:
        """:meth:`write` for each ``(index, log_time_ns, data)`` of ``items``, in order.

        The same MCAP bytes as ``write`` one by one (tested), at a fifth of the cost: one
        ``struct.pack`` per message straight into mcap's chunk buffer instead of ~15 Python
        calls (mcap's ``add_message`` is ~15 us a message here, and the recorder takes up to
        30,000 a second). It updates the writer's statistics, the chunk's time range and
        message index as ``add_message`` does, through mcap 1.x's private attributes (the
        version is pinned in requirements.lock); without them it falls back to ``write``.
        """
        fast = _mcap_internals(self._mcap)
        if fast is None or not items:
            for index, log_time_ns, data in items:
                self.write(index, log_time_ns, data)
            return
        stats, chunk, chunk_size, finalize = fast
        c = self._counts
        per_topic, channel_ids = c.per_topic, self.channel_ids
        counts = stats.channel_message_counts
        first = not any(per_topic)
        # The three time ranges (file statistics, chunk, metadata.yaml counts) are widened
        # inline: a helper call each would cost more per message than the repetition.
        for index, ns, data in items:
            channel = channel_ids[index]
            seq = per_topic[index]
            if stats.message_count == 0:
                stats.message_start_time = ns
            elif ns < stats.message_start_time:
                stats.message_start_time = ns
            if ns > stats.message_end_time:
                stats.message_end_time = ns
            counts[channel] += 1
            stats.message_count += 1
            if chunk.num_messages == 0:
                chunk.message_start_time = ns
            elif ns < chunk.message_start_time:
                chunk.message_start_time = ns
            if ns > chunk.message_end_time:
                chunk.message_end_time = ns
            buffer = chunk.record_writer._buffer
            indices = chunk.message_indices.get(channel)
            if not indices:
                indices = chunk.message_indices[channel] = MessageIndex(channel_id=channel,
                                                                        records=[])
            indices.records.append((ns, buffer.tell()))
            chunk.num_messages += 1
            buffer.write(_MESSAGE_HEADER.pack(Opcode.MESSAGE, 22 + len(data), channel,
                                              seq & 0xFFFFFFFF, ns, ns))
            buffer.write(data)
            if buffer.tell() > chunk_size:
                finalize()
            if first:
                c.start_ns = c.end_ns = ns
                first = False
            if ns < c.start_ns:
                c.start_ns = ns
            if ns > c.end_ns:
                c.end_ns = ns
            per_topic[index] = seq + 1
        if stats.message_count:     # this file's range: mcap's statistics of it
            self._file_range = (stats.message_start_time, stats.message_end_time)

    def flush(self, force: bool = False) -> None:
        """Close the current chunk, hand the file to the OS, rewrite ``metadata.yaml``; a
        no-op when nothing was written since the last flush (an idle recorder flushes every
        0.2 s: the YAML dump and fsync were ~8 % of a core) unless ``force``."""
        if not self._open:
            return
        if not force and self._counts.flushed == self._counts.per_topic:
            return
        # mcap 1.6's Writer closes a chunk only when it is full; the early close keeps the
        # loss window of a crash at one flush period (mcap is pinned in requirements.lock).
        finalize = getattr(self._mcap, '_Writer__finalize_chunk', None)
        if finalize is not None:
            finalize()
        self._sync()        # the data on disk before the metadata that counts it
        if self._split_due():
            self._finish_file()
            self._open_file()
        self._counts.flushed = list(self._counts.per_topic)
        self._write_metadata(self._counts.flushed)

    def _split_due(self) -> bool:
        """The current file has reached ``max_bag_size`` bytes or spans
        ``max_bag_duration``: the next messages go into a new one (rosbag2's split)."""
        r = self._file_range
        if r is None:
            return False
        return ((self.max_bag_size > 0 and self._file.tell() >= self.max_bag_size)
                or (self.max_bag_duration_ns > 0 and r[1] - r[0] >= self.max_bag_duration_ns))

    def _current(self) -> FileInfo:
        r = self._file_range or (0, 0)
        return FileInfo(self.mcap_name, r[0], r[1],
                        sum(self._counts.per_topic) - self._file_first)

    def _finish_file(self) -> None:
        """Summary, footer and the ``rosbag2`` metadata record of the current file; closed."""
        c = self._counts
        info = metadata_info([*self._files, self._current()], self.topics, self.hashes,
                             c.per_topic, c.start_ns, c.end_ns, self.custom)
        self._mcap.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(info)})
        self._mcap.finish()
        self._sync()
        self._file.close()
        self._files.append(self._current())

    def _sync(self) -> None:
        """Hand the current file's bytes to the OS (a SIGKILL loses nothing of them) and to
        the disk (nor does a power cut)."""
        try:
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as exc:
            raise BagWriteError(f'{self.path / self.mcap_name}: cannot write '
                                f'({exc.strerror or exc})', exc.errno) from exc

    @property
    def files(self) -> list[str]:
        """The bag's storage files so far, in order."""
        return [f.name for f in self._files] + ([self.mcap_name] if self._open else [])

    def _write_metadata(self, counts: Sequence[int]) -> None:
        c = self._counts
        files = self._files + ([self._current()] if self._open else [])
        info = metadata_info(files, self.topics, self.hashes, counts, c.start_ns, c.end_ns,
                             self.custom)
        try:
            write_metadata(self._dir, info, self._metadata_text(info))
        except OSError as exc:
            raise BagWriteError(f'{self.path / METADATA}: cannot write '
                                f'({exc.strerror or exc})', exc.errno) from exc

    def close(self) -> None:
        """Write the summary and footer and the final ``metadata.yaml``; idempotent."""
        if not self._open:
            return
        if self._files and self._current().messages == 0:
            # Split at the last flush and nothing came since: no empty file at the end. The
            # metadata stops naming it before it goes (a kill in between leaves an unlisted
            # file without messages, which readers ignore and `bag repair` removes).
            self._mcap.finish()
            self._file.close()
            self._open = False
            self._write_metadata(self._counts.per_topic)
            (self._dir / self.mcap_name).unlink()
            return
        self._finish_file()
        self._open = False
        self._write_metadata(self._counts.per_topic)


#: An MCAP Message record's opcode, length and fixed fields (channel id, sequence, log and
#: publish time), little-endian, as mcap's ``Message.write`` lays them out.
_MESSAGE_HEADER = struct.Struct('<BQHIQQ')


def _mcap_internals(writer: Any) -> tuple[Any, Any, int, Any] | None:
    """mcap 1.x Writer's statistics, chunk builder, chunk size and chunk finalizer, or None
    (another mcap version, or a writer without chunks)."""
    try:
        chunk = writer._Writer__chunk_builder
        found = (writer._Writer__statistics, chunk, int(writer._Writer__chunk_size),
                 writer._Writer__finalize_chunk)
        chunk.record_writer._buffer.tell()
    except AttributeError:
        return None
    return found if chunk is not None else None
