"""A prepared LMI update (:class:`~haptic_topology.control.controller.PreparedUpdate`) as
bytes and back: how ``device_driver`` hands updates to its loop process.

The loop process decodes an update at the start of a cycle, on the deadline path, so the
record is laid out for a cheap decode: an int64 header (the integers, the enums and each
array's shape and memory order), then every array's float64 entries in one block. Decoding
copies the block once and hands out views of it. Measured side by side on a 2-core machine
(the updates of ``circle`` and ``spatial_arm4``, 3,000 calls, three runs): decoding 36-77 us,
unpickling the same updates 114-220 us (one numpy reconstruction per array). Values come back
bit for bit, in the memory order they had.

An update with contacts (:class:`~haptic_topology.dynamics.contacts.LocalContacts`, whose
arrays change size with the contacts) is pickled inside the record instead: it is rarer and
carries objects of its own.
"""

from __future__ import annotations

import dataclasses
import pickle
from typing import Any

import numpy as np

from haptic_topology.control.controller import PreparedUpdate
from haptic_topology.control.lmi import LmiSnapshot, LmiSync
from haptic_topology.model.linkage import PenaltyDirection
from haptic_topology.vocabulary import TaskSpace

#: The record's first int64: how the rest is laid out.
FLAT, PICKLED = 1, 2

#: The arrays of an update, in record order: ``(object, field)``; ``contact_map`` is a pair.
_SNAP_ARRAYS = ('q', 'dq', 'mass_matrix', 'gravity', 'hand_jacobian', 'singular_values',
                'left_vectors', 'weights', 'hand_pose', 'hand_twist')
_SYNC_ARRAYS = ('accel_map', 'accel_bias', 'lambda_inv', 'projector', 'env_map')
#: Fields of each class that the record carries otherwise (scalars, enums, the objects that
#: are None in a flat record); checked against the dataclasses below.
_SNAP_OTHER = ('seq', 'hand_input_seq', 'task', 'constraint_count', 'characteristic_length',
               'penalty_direction', 'contacts', 'contact_energy')
_SYNC_OTHER = ('snapshot', 'contacts', 'contact_map', 'held_forces')
_PREP_FIELDS = ('sync', 'stable_dt', 'ml')

_N_ARRAYS = len(_SNAP_ARRAYS) + len(_SYNC_ARRAYS) + 2 + 1
#: Header ints: format, seq, hand_input_seq, constraint_count, task, penalty direction,
#: then (rows, columns or -1, Fortran order 0/1) per array.
_N_INTS = 6 + 3 * _N_ARRAYS
_TASKS = tuple(TaskSpace)
_DIRECTIONS = tuple(PenaltyDirection)


def _check_fields() -> None:
    """Every field of the three classes has its place in the record (a field added to one of
    them must be added here, or the record would silently drop it)."""
    for cls, names in ((LmiSnapshot, _SNAP_ARRAYS + _SNAP_OTHER),
                       (LmiSync, _SYNC_ARRAYS + _SYNC_OTHER),
                       (PreparedUpdate, _PREP_FIELDS)):
        fields = {f.name for f in dataclasses.fields(cls)}
        if fields != set(names):
            raise TypeError(f'update_record: {cls.__name__} has fields {sorted(fields)}, '
                            f'the record carries {sorted(names)}')


_check_fields()


def _arrays(p: PreparedUpdate) -> list[np.ndarray]:
    s, y = p.sync.snapshot, p.sync
    return ([getattr(s, n) for n in _SNAP_ARRAYS] + [getattr(y, n) for n in _SYNC_ARRAYS]
            + list(y.contact_map) + [p.ml])


def encode_update(p: PreparedUpdate) -> bytes:
    """``p`` as a record (module doc)."""
    s, y = p.sync.snapshot, p.sync
    if (s.contacts is not None or y.contacts is not None or y.held_forces is not None
            or len(y.contact_map) != 2):
        return np.int64(PICKLED).tobytes() + pickle.dumps(p, protocol=pickle.HIGHEST_PROTOCOL)
    arrays = _arrays(p)
    ints = [FLAT, s.seq, s.hand_input_seq, s.constraint_count, _TASKS.index(s.task),
            _DIRECTIONS.index(s.penalty_direction)]
    flat: list[np.ndarray] = [np.array([s.characteristic_length, s.contact_energy,
                                        p.stable_dt])]
    for a in arrays:
        if a.ndim not in (1, 2):
            raise ValueError(f'update_record: arrays of 1 or 2 dimensions, got {a.shape}')
        fortran = a.ndim == 2 and a.flags.f_contiguous and not a.flags.c_contiguous
        ints += [a.shape[0], a.shape[1] if a.ndim == 2 else -1, int(fortran)]
        flat.append(np.asarray(a, dtype=np.float64).ravel('F' if fortran else 'C'))
    return np.array(ints, dtype='<i8').tobytes() + np.concatenate(flat).astype('<f8').tobytes()


def decode_update(data: bytes | memoryview) -> PreparedUpdate:
    """The update of a record made by :func:`encode_update`."""
    kind = int(np.frombuffer(data, '<i8', count=1)[0])
    if kind == PICKLED:
        out = pickle.loads(memoryview(data)[8:])
        if not isinstance(out, PreparedUpdate):
            raise TypeError(f'update_record: a pickled {type(out).__name__}, expected '
                            'PreparedUpdate')
        return out
    if kind != FLAT:
        raise ValueError(f'update_record: format {kind}, expected {FLAT} or {PICKLED}')
    ints = np.frombuffer(data, '<i8', count=_N_INTS).tolist()
    f = np.frombuffer(data, '<f8', offset=8 * _N_INTS).copy()
    shapes = [ints[6 + 3 * k:9 + 3 * k] for k in range(_N_ARRAYS)]
    sizes = [rows * (cols if cols >= 0 else 1) for rows, cols, _ in shapes]
    if 3 + sum(sizes) != f.size:
        raise ValueError(f'update_record: {f.size} floats, the header describes '
                         f'{3 + sum(sizes)}')
    arrays: list[Any] = []
    at = 3
    for (rows, cols, fortran), n in zip(shapes, sizes, strict=True):
        block = f[at:at + n]
        arrays.append(block if cols < 0 else
                      block.reshape((rows, cols), order='F' if fortran else 'C'))
        at += n
    ns = len(_SNAP_ARRAYS)
    snap = LmiSnapshot(
        seq=ints[1], hand_input_seq=ints[2], task=_TASKS[ints[4]],
        constraint_count=ints[3], characteristic_length=float(f[0]),
        penalty_direction=_DIRECTIONS[ints[5]], contacts=None, contact_energy=float(f[1]),
        **dict(zip(_SNAP_ARRAYS, arrays[:ns], strict=True)))
    ny = ns + len(_SYNC_ARRAYS)
    sync = LmiSync(snapshot=snap, contacts=None, contact_map=(arrays[ny], arrays[ny + 1]),
                   held_forces=None, **dict(zip(_SYNC_ARRAYS, arrays[ns:ny], strict=True)))
    return PreparedUpdate(sync, float(f[2]), arrays[ny + 2])
