"""Serialize a message to CDR bytes in one ``struct`` call, for publishing at 1 kHz.

rclpy publishes a message object by converting every field to C (with the Python setters'
checks when the fields are filled) and then serializing it; a publisher also accepts the
serialized bytes (``Publisher.publish(bytes)``, ``rcl_publish_serialized_message``), which go
to the middleware as they are. :class:`CdrWriter` produces those bytes for a message type
whose sequences keep their lengths from one message to the next, as the device's state and
the controller's command do within a run: the layout of each combination of sequence
lengths is worked out once, and each message is then a single ``struct.pack``.

The bytes are what ``rclpy.serialization.serialize_message`` gives for the same message
(classic CDR, little endian, the encapsulation header ``00 01 00 00``; each primitive
aligned to its size from the end of that header), except that the alignment bytes are
zeros where ``serialize_message`` leaves whatever its buffer held, and that they end with
the last field: ``serialize_message`` may add slack after it (its size estimate counts
alignment for each empty sequence: 8 bytes for a ``DeviceCommand`` with its ``env_wrench``
empty), which no reader looks at. The tests check this byte for byte, and that rclpy
deserializes the bytes to the message. Supported: the primitive types, strings, unbounded
sequences of primitives or of messages of primitives (e.g. ``builtin_interfaces/Time[]``,
given as their fields' values one element after the other) and nested messages of these;
anything else is refused when the writer is made. No rclpy here: the message classes carry
their own field list.
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable, Mapping, Sequence
from operator import itemgetter
from typing import Any

#: CDR (XCDR1) little-endian encapsulation: representation id 0x0001, options 0.
ENCAPSULATION = b'\x00\x01\x00\x00'

#: Primitive type -> (struct code, size = alignment in bytes).
PRIMITIVES: dict[str, tuple[str, int]] = {
    'boolean': ('?', 1), 'octet': ('B', 1), 'char': ('B', 1), 'uint8': ('B', 1),
    'int8': ('b', 1), 'uint16': ('H', 2), 'int16': ('h', 2), 'uint32': ('I', 4),
    'int32': ('i', 4), 'uint64': ('Q', 8), 'int64': ('q', 8), 'float': ('f', 4),
    'double': ('d', 8),
}


def _leaves(msg_type: type, prefix: str = '') -> list[tuple[str, str]]:
    """``(dotted path, kind)`` of every leaf field in wire order; kind is a primitive type
    name, ``'string'`` or ``'sequence<primitive,...>'``: the primitives of one element (one
    for a sequence of primitives; those of a message of primitives, e.g. ``int32,uint32`` for
    ``builtin_interfaces/Time``)."""
    out: list[tuple[str, str]] = []
    probe = msg_type()
    fields: dict[str, str] = msg_type.get_fields_and_field_types()  # type: ignore[attr-defined]
    for name, kind in fields.items():
        path = prefix + name
        inner = kind[len('sequence<'):-1] if kind.startswith('sequence<') else None
        element = _element(inner) if inner is not None and '/' in inner else None
        if kind in PRIMITIVES or kind == 'string' or inner in PRIMITIVES:
            out.append((path, kind))
        elif element is not None:
            out.append((path, f'sequence<{element}>'))
        elif '/' in kind and '<' not in kind and '[' not in kind:
            out.extend(_leaves(type(getattr(probe, name)), path + '.'))
        else:
            raise ValueError(f'{msg_type.__name__}.{path}: type {kind!r} is not supported '
                             '(primitives, strings, unbounded sequences of primitives or of '
                             'messages of primitives, and nested messages of these)')
    return out


def _element(name: str) -> str | None:
    """The primitives of message type ``name`` (``pkg/Msg``) in wire order, comma-separated;
    None if it has any other field (or cannot be imported)."""
    pkg, _, msg = name.partition('/')
    try:
        kinds = [k for _, k in _leaves(getattr(importlib.import_module(f'{pkg}.msg'), msg))]
    except (ImportError, AttributeError, ValueError):
        return None
    return ','.join(kinds) if kinds and all(k in PRIMITIVES for k in kinds) else None


class _Layout:
    """The struct and the value slots of one combination of sequence and string lengths."""

    def __init__(self, leaves: list[tuple[str, str]], lengths: tuple[int, ...]) -> None:
        fmt, offset, slot = ['<'], 0, 0
        self.slots: dict[str, slice] = {}       # path -> its values in pack order
        self.counts: list[tuple[int, int]] = []  # (slot, value) of each length prefix
        self.lengths: dict[str, int] = {}       # path -> entries (bytes) of each sequence
        self.padding: list[int] = []            # offsets of the pad bytes in the message
        sizes = iter(lengths)

        def align(size: int) -> None:
            nonlocal offset
            pad = -offset % size
            if pad:
                fmt.append(f'{pad}x')
                self.padding.extend(range(len(ENCAPSULATION) + offset,
                                          len(ENCAPSULATION) + offset + pad))
            offset += pad

        for path, kind in leaves:
            if kind in PRIMITIVES:
                code, size = PRIMITIVES[kind]
                align(size)
                fmt.append(code)
                offset += size
                self.slots[path] = slice(slot, slot + 1)
                slot += 1
                continue
            n = self.lengths[path] = next(sizes)
            align(4)
            fmt.append('I')
            offset += 4
            if kind == 'string':        # length with the NUL, the bytes, the NUL
                self.counts.append((slot, n + 1))
                fmt.append(f'{n + 1}s')
                offset += n + 1
                self.slots[path] = slice(slot + 1, slot + 2)
                slot += 2
                continue
            element = [PRIMITIVES[k] for k in kind[len('sequence<'):-1].split(',')]
            if n % len(element):
                raise ValueError(f'{path}: {n} values are not whole elements of '
                                 f'{len(element)} ({kind})')
            self.counts.append((slot, n // len(element)))
            if len(element) > 1:            # field after field, element after element
                for _ in range(n // len(element)):
                    for code, size in element:
                        align(size)
                        fmt.append(code)
                        offset += size
            elif n:                         # an empty sequence is its length alone
                code, size = element[0]
                align(size)
                fmt.append(f'{n}{code}')
                offset += n * size
            self.slots[path] = slice(slot + 1, slot + 1 + n)
            slot += 1 + n
        self.struct = struct.Struct(''.join(fmt))
        self.size = slot


class CdrWriter:
    """CDR bytes of ``msg_type`` messages (module doc).

    ``fields``: the dotted paths (e.g. ``'header.stamp.sec'``, ``'pose'``) that
    :meth:`pack` takes, in its argument order: primitives as numbers, sequences as any sized
    iterable of numbers (numpy arrays of any shape: their entries row-major); strings only as
    constants. ``constants``:
    values of other fields that stay the same (e.g. ``{'header.frame_id': 'world'}``). A
    field in neither is the type's default. A message whose sequence lengths are new gets
    its layout worked out then (once).
    """

    def __init__(self, msg_type: type, fields: Sequence[str],
                 constants: Mapping[str, Any] | None = None) -> None:
        self.msg_type = msg_type
        self.fields = tuple(fields)
        self._leaves = _leaves(msg_type)
        kinds = dict(self._leaves)
        constants = dict(constants or {})
        unknown = sorted((set(self.fields) | set(constants)) - set(kinds))
        both = sorted(set(self.fields) & set(constants))
        strings = [f for f in self.fields if kinds.get(f) == 'string']
        if unknown or both or strings or len(set(self.fields)) != len(self.fields):
            raise ValueError(
                f'{msg_type.__name__}: ' + (f'no field {unknown} (fields: {sorted(kinds)})'
                                            if unknown else
                                            f'{both} both given per message and constant'
                                            if both else
                                            f'strings {strings} must be constants'
                                            if strings else 'a field named twice'))
        defaults: dict[str, Any] = {
            p: ([] if k.startswith('sequence<') else '' if k == 'string' else
                False if k == 'boolean' else 0.0 if k in ('float', 'double') else 0)
            for p, k in self._leaves if p not in self.fields}
        self._constants = {**defaults, **constants}
        self._varying = [p for p, k in self._leaves if k not in PRIMITIVES]
        self._sequences = [i for i, p in enumerate(self.fields) if p in self._varying]
        self._layouts: dict[tuple[int, ...], tuple[list[int | slice], list[Any], _Layout]] = {}

    def _layout(self, values: Sequence[Any]) -> tuple[list[int | slice], list[Any], _Layout]:
        lengths = tuple([len(values[n]) for n in self._sequences])
        hit = self._layouts.get(lengths)
        if hit is None:
            given = {self.fields[n]: m for n, m in zip(self._sequences, lengths, strict=True)}
            layout = _Layout(self._leaves, tuple(
                given[p] if p in given else _width(self._constants[p]) for p in self._varying))
            base: list[Any] = [0] * layout.size
            for slot, count in layout.counts:
                base[slot] = count
            for path, value in self._constants.items():
                where = layout.slots[path]
                if isinstance(value, str):
                    base[where] = [value.encode() + b'\x00']
                else:
                    base[where] = list(value) if hasattr(value, '__len__') else [value]
            wheres: list[int | slice] = [
                layout.slots[p].start if (layout.slots[p].stop - layout.slots[p].start == 1
                                          and p not in layout.lengths) else layout.slots[p]
                for p in self.fields]
            hit = self._layouts[lengths] = (wheres, base, layout)
        return hit

    def _given(self, values: tuple[Any, ...]) -> list[Any]:
        """``values`` with each sequence as a list (numpy arrays: their entries, at C
        speed)."""
        if len(values) != len(self.fields):
            raise ValueError(f'{self.msg_type.__name__}: {len(values)} values for the '
                             f'{len(self.fields)} fields {self.fields}')
        given = list(values)
        for n in self._sequences:
            v = given[n]
            if v.__class__ is not list:
                given[n] = v.ravel().tolist() if hasattr(v, 'ravel') else list(v)
        return given

    def gather(self, width: int, where: Mapping[str, int],
               lengths: Mapping[str, int]) -> Callable[[list[Any]], bytes]:
        """A packer of messages of one layout whose values all sit in one list: ``packer(src)``
        (``src`` a list of ``width`` values) is :meth:`pack` of field ``path`` =
        ``src[where[path]]`` for each primitive of the writer's ``fields``, and of the
        ``lengths[path]`` values from ``src[where[path]]`` on for each sequence (``lengths``
        gives every sequence field; one of length 0 needs no ``where``). No argument list is
        built per message: one ``itemgetter`` picks the struct's values from ``src``, e.g. a
        fixed-layout record's fields as ``tolist`` gives them."""
        seqs = {self.fields[n] for n in self._sequences}
        if set(lengths) != seqs:
            raise ValueError(f'{self.msg_type.__name__}: lengths must give the sequences '
                             f'{sorted(seqs)}, got {sorted(lengths)}')
        need = [p for p in self.fields if p not in seqs or lengths[p]]
        bad = [p for p in need if not 0 <= where.get(p, -1) <= width - lengths.get(p, 1)]
        if bad:
            raise ValueError(f'{self.msg_type.__name__}: fields {bad} need a position in '
                             f'0..{width - 1} with their values within the {width} of src')
        wheres, base, layout = self._layout([range(lengths[p]) if p in seqs else 0
                                             for p in self.fields])
        taken: dict[int, int] = {}      # struct value -> its position in src
        for path, at in zip(self.fields, wheres, strict=True):
            if isinstance(at, slice):
                first = where.get(path, 0)
                taken.update(zip(range(at.start, at.stop),
                                 range(first, first + lengths[path]), strict=True))
            else:
                taken[at] = where[path]
        consts = [base[s] for s in range(layout.size) if s not in taken]
        picks = iter(range(width, width + len(consts)))
        get = itemgetter(*[taken[s] if s in taken else next(picks)
                           for s in range(layout.size)])
        pack = layout.struct.pack

        def packer(src: list[Any]) -> bytes:
            return ENCAPSULATION + pack(*get(src + consts))
        return packer

    def padding(self, *values: Any) -> list[int]:
        """Offsets of the alignment bytes in :meth:`pack`'s result for ``values``: zeros
        here; CDR leaves them unspecified (``serialize_message`` leaves what its buffer
        held)."""
        return list(self._layout(self._given(values))[2].padding)

    def pack(self, *values: Any) -> bytes:
        """The CDR bytes, encapsulation header included, of the message with ``values`` (in
        the order of the ``fields`` the writer was made with) over the constants."""
        given = self._given(values)
        wheres, base, layout = self._layout(given)
        flat = base.copy()
        for where, value in zip(wheres, given, strict=True):
            flat[where] = value
        try:
            return ENCAPSULATION + layout.struct.pack(*flat)
        except struct.error as exc:
            raise ValueError(f'{self.msg_type.__name__}: a value does not fit its field '
                             f'({exc}); fields {self.fields}') from None


def _width(value: Any) -> int:
    """Entries of a sequence, bytes of a string (without the NUL)."""
    return len(value.encode()) if isinstance(value, str) else len(value)
