"""Open and read rosbag2 (MCAP) bags, also truncated ones, with errors that name the file.

:func:`open_bag` accepts a rosbag2 directory (``metadata.yaml`` + ``.mcap`` files), a
directory holding ``.mcap`` files without metadata, or one ``.mcap`` file. It checks what can
be checked without reading every message (the path exists, the storage is MCAP, each file
starts with the MCAP magic) and raises :class:`~haptic_topology.errors.BagError` naming the
file and the problem. In a bag directory a storage file that is empty or holds only the start
of the magic (a recorder killed as it created the file) is skipped (:attr:`Bag.empty`), and
files found without ``metadata.yaml`` are taken in the order of their numbers.

:func:`iter_messages` reads the files front to back with ``mcap``'s non-seeking stream
reader, so it needs neither the summary nor the footer: a bag whose recorder was killed
reads up to the last complete chunk, and :attr:`Bag.truncated` tells that this happened
(:func:`haptic_topology.bag.repair.repair_bag` makes such a file whole for other readers).
Messages come in file order, which for our recorder is arrival order.

:func:`decoder` of a bag decodes each message with the definition the bag stores for its type
(MCAP ``ros2msg`` schema) where that differs from the current ``.msg`` text: a bag recorded
before a field was added (``DeviceCommand.controller_id``) reads as recorded, without the new
field (:func:`bag_typestore`).
"""

from __future__ import annotations

import functools
import re
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import Nodetype
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from zstandard import ZstdError

from haptic_topology import MSGS_PACKAGE_NAME
from haptic_topology.errors import BagError, TruncatedError
from haptic_topology.messages.definitions import typestore_with_haptic_msgs

MCAP_MAGIC = b'\x89MCAP0\r\n'
METADATA = 'metadata.yaml'

#: Called with the fraction (0..1) of the bag's bytes read so far.
Progress = Callable[[float], None]


@dataclass(frozen=True)
class BagMessage:
    """One message as stored: topic, full type name, receive time (ns), CDR bytes."""

    topic: str
    msgtype: str
    log_time: int
    data: bytes


@dataclass
class Bag:
    """An opened bag: its directory, MCAP files, parsed ``metadata.yaml`` (if any)."""

    path: Path
    files: list[Path]
    metadata: dict[str, Any] | None = None
    #: Set by :func:`iter_messages` when a file ended before its footer.
    truncated: list[Path] = field(default_factory=list)
    #: Topic -> type seen while reading (channels of the files).
    topics: dict[str, str] = field(default_factory=dict)
    #: Storage files left out of ``files``: empty, or only the start of the MCAP magic (a
    #: recorder killed as it created them; ``bag repair`` removes them).
    empty: list[Path] = field(default_factory=list)

    @property
    def size(self) -> int:
        return sum(f.stat().st_size for f in self.files)

    def metadata_topics(self) -> dict[str, str]:
        """Topic -> type as listed in ``metadata.yaml`` (empty without one)."""
        if not self.metadata:
            return {}
        out: dict[str, str] = {}
        for entry in self.metadata.get('topics_with_message_count') or []:
            meta = entry.get('topic_metadata', {}) if isinstance(entry, dict) else {}
            if 'name' in meta and 'type' in meta:
                out[str(meta['name'])] = str(meta['type'])
        return out


def _check_mcap(path: Path, in_bag: bool = False) -> bool:
    """True if ``path`` starts with the MCAP magic; False if it is empty or holds only the
    start of the magic and ``in_bag`` (a file of a bag directory whose writer was killed as
    it created the file: it holds no message); else raise."""
    try:
        with path.open('rb') as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise BagError(f'{path}: cannot read ({exc.strerror})') from None
    if head == MCAP_MAGIC:
        return True
    if in_bag and MCAP_MAGIC.startswith(head):
        return False
    if not head:
        raise BagError(f'{path}: empty file, not an MCAP bag')
    raise BagError(f'{path}: not an MCAP file (no MCAP magic at the start)')


def storage_order(path: Path) -> tuple[str, int, str]:
    """Sort key of a bag's storage files: by name, numbered files (``b_2.mcap``) by their
    number (``b_2`` before ``b_10``)."""
    m = re.fullmatch(r'(.*?)(\d+)\.mcap', path.name)
    return (m.group(1), int(m.group(2)), '') if m else (path.name, -1, path.name)


def _load_metadata(path: Path) -> dict[str, Any]:
    try:
        doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    except yaml.MarkedYAMLError as exc:
        where = f'line {exc.problem_mark.line + 1}: ' if exc.problem_mark else ''
        raise BagError(f'{path}: cannot read rosbag2 metadata (YAML error at {where}'
                       f'{exc.problem})') from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BagError(f'{path}: cannot read rosbag2 metadata ({first})') from None
    info = doc.get('rosbag2_bagfile_information') if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagError(f'{path}: not rosbag2 metadata (no rosbag2_bagfile_information)')
    return info


def open_bag(path: str | Path) -> Bag:
    """Locate and check the files of the bag at ``path`` (see module doc)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f'{p}: no such file or directory')
    if p.is_file() and p.name == METADATA:
        p = p.parent
    if p.is_file():
        _check_mcap(p)
        return Bag(p, [p])
    meta_path = p / METADATA
    metadata = _load_metadata(meta_path) if meta_path.is_file() else None
    if metadata is not None:
        storage = metadata.get('storage_identifier')
        if storage != 'mcap':
            raise BagError(f'{meta_path}: storage {storage!r} is not supported (only mcap; '
                           'convert with `rosbags-convert` or `ros2 bag convert`)')
        names = metadata.get('relative_file_paths') or []
        files = [p / str(n) for n in names]
        if not files:
            raise BagError(f'{meta_path}: lists no storage files (relative_file_paths)')
        for f in files:
            if not f.is_file():
                raise BagError(f'{f}: listed in {meta_path} but missing')
    else:
        files = sorted(p.glob('*.mcap'), key=storage_order)
        if not files:
            raise BagError(f'{p}: not a bag (no {METADATA} and no .mcap file)')
    readable = [f for f in files if _check_mcap(f, in_bag=True)]
    return Bag(p, readable, metadata, empty=[f for f in files if f not in readable])


def iter_records(path: Path, stream: IO[bytes]) -> Iterator[Any]:
    """MCAP records of ``stream``, chunks broken up; stops at a truncation (EOF mid-record).

    Yields the records; returns normally at the footer, or raises :class:`TruncatedError` when
    the file ends early.
    """
    reader = StreamReader(stream, emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk):
                try:
                    yield from breakup_chunk(record, validate_crc=True)
                except (EndOfFile, struct.error, ZstdError, RuntimeError) as exc:
                    # (zstd data corrupted; lz4 reports its errors as RuntimeError)
                    raise BagError(f'{path}: corrupt chunk at byte {stream.tell()} '
                                   f'({exc or type(exc).__name__})') from None
            else:
                yield record
            if isinstance(record, Footer):
                return
    except (EndOfFile, struct.error):
        raise TruncatedError() from None
    except (McapError, ValueError) as exc:  # CRCValidationError is a ValueError
        raise BagError(f'{path}: corrupt MCAP data near byte {stream.tell()} '
                       f'({exc or type(exc).__name__})') from None


def iter_messages(bag: Bag, topics: Iterable[str] | None = None,
                  progress: Progress | None = None) -> Iterator[BagMessage]:
    """Every message of ``bag`` (only ``topics`` if given), file by file (see module doc)."""
    wanted = None if topics is None else set(topics)
    total = max(bag.size, 1)
    done = 0
    bag.truncated.clear()
    for path in bag.files:
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        try:
            stream = path.open('rb')
        except OSError as exc:
            raise BagError(f'{path}: cannot read ({exc.strerror})') from None
        with stream:
            try:
                for record in iter_records(path, stream):
                    if isinstance(record, Message):
                        ch = channels.get(record.channel_id)
                        if ch is None:
                            raise BagError(f'{path}: message on unknown channel '
                                           f'{record.channel_id}')
                        if wanted is None or ch[0] in wanted:
                            yield BagMessage(ch[0], ch[1], record.log_time, record.data)
                    elif isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel):
                        msgtype = schemas.get(record.schema_id, '')
                        channels[record.id] = (record.topic, msgtype)
                        bag.topics[record.topic] = msgtype
                    elif isinstance(record, Chunk) and progress is not None:
                        progress((done + stream.tell()) / total)
            except TruncatedError:
                bag.truncated.append(path)
            done += path.stat().st_size
        if progress is not None:
            progress(done / total)


def read_channels(bag: Bag) -> dict[str, dict[str, Any]]:
    """Topic -> {type, schema (text), encoding, metadata} for every channel of the bag."""
    out: dict[str, dict[str, Any]] = {}
    for path in bag.files:
        schemas: dict[int, Schema] = {}
        with path.open('rb') as stream:
            try:
                for record in iter_records(path, stream):
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        sch = schemas.get(record.schema_id)
                        out[record.topic] = {
                            'type': sch.name if sch else '',
                            'schema': sch.data.decode(errors='replace') if sch else '',
                            'schema_encoding': sch.encoding if sch else '',
                            'encoding': record.message_encoding,
                            'metadata': dict(record.metadata)}
                    elif isinstance(record, (Message, Footer)):
                        # Our writer puts every schema and channel before the first message.
                        break
            except TruncatedError:
                pass
    return out


def bag_typestore(bag: Bag) -> Typestore:
    """The typestore to decode ``bag`` with: ours (:func:`typestore_with_haptic_msgs`), unless
    the bag stores another definition of one of our package's types (it was recorded with an
    older ``.msg``, see :func:`outdated_types`); then a store with the bag's definitions of
    those types and ours of the others."""
    return _store_with(_stored_definitions(bag))


def outdated_types(bag: Bag) -> set[str]:
    """Our package's types whose definition stored in ``bag`` has other fields than the
    current ``.msg`` (e.g. ``DeviceCommand`` of a bag recorded before ``controller_id``): their
    recorded bytes decode only with the stored definition. A stored schema that does not
    parse counts as current (ours is used)."""
    stored = _stored_definitions(bag)
    return set(_outdated(stored)) & {t for t, _ in stored}


#: Defaults of primitive fields appended to a message since a bag was recorded.
_BASE_DEFAULTS: dict[str, Any] = {'bool': False, 'string': '', 'float32': 0.0, 'float64': 0.0}


def field_default(fieldtype: Any) -> tuple[bool, Any]:
    """``(ok, value)``: the default of an appended field (0, 0.0, False, '', an empty
    sequence of a primitive); ok False for other types (nested messages, fixed arrays)."""
    node, detail = fieldtype
    if node == Nodetype.BASE:
        return True, _BASE_DEFAULTS.get(detail[0], 0)
    if node == Nodetype.SEQUENCE and detail[0][0] == Nodetype.BASE:
        base = detail[0][1][0]
        return True, [] if base in ('string', 'bool') else np.array([], dtype=np.dtype(base))
    return False, None


def upgraders(bag: Bag) -> dict[str, Callable[[bytes], bytes]]:
    """Type -> a function re-serialising a recorded message of that type as the installed
    definition, for the :func:`outdated_types` whose stored definition is a prefix of the
    installed one (fields only appended since, e.g. ``LmiUpdate`` before its contact fields):
    the recorded fields keep their values, the appended ones get their defaults (empty,
    zero, false). Types changed otherwise (a field inserted or retyped) have none."""
    stored = _stored_definitions(bag)
    old_store = _store_with(stored)
    ours = typestore_with_haptic_msgs()
    out: dict[str, Callable[[bytes], bytes]] = {}
    for msgtype in outdated_types(bag):
        old, new = _fields(old_store.fielddefs[msgtype]), _fields(ours.fielddefs[msgtype])
        if old is None or new is None or new[:len(old)] != old:
            continue
        extra = [field_default(t) for _, t in new[len(old):]]
        if not all(ok for ok, _ in extra):
            continue
        defaults = [v for _, v in extra]
        cls = ours.types[msgtype]

        def upgrade(data: bytes, msgtype: str = msgtype, n: int = len(old),
                    defaults: list[Any] = defaults, cls: Any = cls) -> bytes:
            msg = old_store.deserialize_cdr(data, msgtype)
            values = [getattr(msg, name) for name, _ in _fields(
                old_store.fielddefs[msgtype])[:n]]
            fresh = [np.array(v) if isinstance(v, np.ndarray) else
                     (list(v) if isinstance(v, list) else v) for v in defaults]
            return bytes(ours.serialize_cdr(cls(*values, *fresh), msgtype))

        out[msgtype] = upgrade
    return out


def _stored_definitions(bag: Bag) -> tuple[tuple[str, str], ...]:
    """(type, ros2msg schema text) of our package's types in the bag's channels."""
    stored: dict[str, str] = {}
    for ch in read_channels(bag).values():
        msgtype = ch['type']
        if (msgtype.startswith(f'{MSGS_PACKAGE_NAME}/') and ch['schema']
                and ch['schema_encoding'] == 'ros2msg'):
            stored.setdefault(msgtype, ch['schema'])
    return tuple(sorted(stored.items()))


@functools.cache
def _outdated(stored: tuple[tuple[str, str], ...]) -> dict[str, Any]:
    """The parsed stored definitions (with their dependencies) of the types of ``stored``
    whose fields differ from ours; empty when all are current (cached per bag kind)."""
    ours = typestore_with_haptic_msgs()
    older: dict[str, Any] = {}
    for msgtype, text in stored:
        try:
            types = get_types_from_msg(text, msgtype)
        except TypesysError:
            continue
        if msgtype in types and _fields(types[msgtype]) != _fields(ours.fielddefs.get(msgtype)):
            older.update(types)
    return older


@functools.cache
def _store_with(stored: tuple[tuple[str, str], ...]) -> Typestore:
    """Our typestore with the outdated types of ``stored`` replaced by their stored
    definitions (cached: the same store for bags of one kind)."""
    ours = typestore_with_haptic_msgs()
    older = _outdated(stored)
    if not older:
        return ours
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(older)
    store.register({k: v for k, v in ours.fielddefs.items()
                    if k.startswith(f'{MSGS_PACKAGE_NAME}/') and k not in older})
    return store


def _fields(fielddef: Any) -> Any:
    """The field names and types of a rosbags type definition (constants left out)."""
    return None if fielddef is None else [(f[0].lower(), f[1]) for f in fielddef[1]]


def decoder(typestore: Typestore | None = None, bag: Bag | None = None
            ) -> Callable[[BagMessage], Any]:
    """A function decoding a :class:`BagMessage` with ``typestore``; default: the store for
    ``bag`` (:func:`bag_typestore`), or ours without a bag."""
    if typestore is not None:
        store = typestore
    else:
        store = bag_typestore(bag) if bag is not None else typestore_with_haptic_msgs()

    def decode(msg: BagMessage) -> Any:
        try:
            return store.deserialize_cdr(msg.data, msg.msgtype)
        except KeyError:
            raise BagError(f'{msg.topic}: unknown message type {msg.msgtype!r}') from None
        except (ValueError, IndexError, struct.error, AssertionError, SerdeError) as exc:
            raise BagError(f'{msg.topic}: cannot decode {msg.msgtype} at t={msg.log_time} '
                           f'({exc})') from None
    return decode


def require_types(bag: Bag, expected: dict[str, str]) -> None:
    """Raise if a topic of ``expected`` (topic suffix -> type) has another type in the bag,
    or if the bag has none of the expected topics."""
    seen = bag.metadata_topics() or {t: d['type'] for t, d in read_channels(bag).items()}
    found = 0
    for topic, msgtype in seen.items():
        for suffix, want in expected.items():
            if topic.endswith(suffix):
                if msgtype != want:
                    raise BagError(f'{bag.path}: topic {topic} has type {msgtype}, '
                                   f'expected {want}')
                found += 1
    if not found:
        listing = ', '.join(f'{t} ({m})' for t, m in sorted(seen.items())) or 'no topics'
        raise BagError(f'{bag.path}: not a bag of the haptic_topology graph: none of '
                       f'{", ".join(sorted(expected))} (it has {listing})')
