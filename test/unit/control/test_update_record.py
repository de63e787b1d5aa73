"""The update record the loop process decodes (haptic_topology.control.update_record): every
field of a prepared LMI update comes back bit for bit, in its memory order; contacts go
pickled inside the record; a record of another format is refused."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from haptic_topology.control.controller import PreparedUpdate
from haptic_topology.control.update_record import (
    FLAT,
    PICKLED,
    decode_update,
    encode_update,
)
from haptic_topology.sim.lockstep import build_controller_loop, virtual_environment
from haptic_topology.sim.scenario import load_scenario


def _prepared(scenario: str, inputs: int = 40) -> PreparedUpdate:
    sc = load_scenario(scenario)
    ve = virtual_environment(sc)
    rng = np.random.default_rng(11)
    for k in range(inputs):
        ve.push_input(k + 1, 1e-3 * (k + 1), rng.normal(0.0, 2.0, sc.linkage.task.dim))
    ctrl = build_controller_loop(sc, sc.mode, update_period=sc.update_period).ctrl
    return ctrl.prepare(ve.snapshot(seq=7))


def _same(a: Any, b: Any, where: str = 'update') -> None:
    """Equal field by field: arrays bit for bit with shape, dtype and memory order."""
    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f'{where}.{f.name}')
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f'{where}[{k}]')
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.dtype == b.dtype, where
        assert a.tobytes() == b.tobytes(), where
        assert a.flags.f_contiguous == b.flags.f_contiguous, where
        assert a.flags.c_contiguous == b.flags.c_contiguous, where
    elif isinstance(a, float):
        assert np.float64(a).tobytes() == np.float64(b).tobytes(), where
    else:
        assert a == b, where


@pytest.mark.parametrize('scenario', ['circle', 'fig8', 'spatial_arm4', 'panda_link4'])
def test_an_update_without_contacts_comes_back_bit_for_bit(scenario: str) -> None:
    p = _prepared(scenario)
    data = encode_update(p)
    assert int(np.frombuffer(data, '<i8', count=1)[0]) == FLAT
    _same(p, decode_update(data))
    _same(p, decode_update(memoryview(bytearray(data))))     # as the ring hands it over


def test_memory_order_is_kept() -> None:
    p = _prepared('spatial_arm4')
    s = p.sync.snapshot
    fortran = dataclasses.replace(
        p, sync=dataclasses.replace(p.sync, snapshot=dataclasses.replace(
            s, mass_matrix=np.asfortranarray(s.mass_matrix),
            hand_jacobian=np.asfortranarray(s.hand_jacobian))))
    back = decode_update(encode_update(fortran))
    assert back.sync.snapshot.hand_jacobian.flags.f_contiguous
    assert not back.sync.snapshot.hand_jacobian.flags.c_contiguous
    _same(fortran, back)


def test_an_update_with_contacts_is_pickled_inside_the_record() -> None:
    p = _prepared('wall', inputs=400)
    assert p.sync.snapshot.contacts is not None
    data = encode_update(p)
    assert int(np.frombuffer(data, '<i8', count=1)[0]) == PICKLED
    back = decode_update(data)
    _same(p.sync.snapshot.contacts.gaps, back.sync.snapshot.contacts.gaps)
    _same(p.ml, back.ml)
    assert back.sync.snapshot.seq == p.sync.snapshot.seq


def test_records_of_another_format_or_size_are_refused() -> None:
    data = bytearray(encode_update(_prepared('circle')))
    with pytest.raises(ValueError, match=r'update_record: \d+ floats, the header describes'):
        decode_update(bytes(data[:-8]))
    data[:8] = np.int64(9).tobytes()
    with pytest.raises(ValueError, match=r'update_record: format 9, expected 1 or 2'):
        decode_update(bytes(data))
