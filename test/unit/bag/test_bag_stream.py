"""Reading a bag as a stream: memory that does not grow with the run's length, and the
figures, trace file and plot rows of the stream equal those of the whole trace.

The synthetic bags are written with the project's own writer from the messages of the
reference bag (its first running state, command, LMI update and VT path, renumbered and
re-stamped at 1 kHz, an update and a path every 10 cycles)."""

from __future__ import annotations

import json
import math
import tracemalloc
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.bag.analyze import analyze, reduce_bag
from haptic_topology.bag.graph_trace import read_graph_bag, stream_graph_bag
from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)
from haptic_topology.sim.trace import Trace
from haptic_topology.sim.trace_io import read_trace
from haptic_topology.sim.trace_stats import PeriodStats, PlotRows, Summary

REPO = Path(__file__).resolve().parents[3]
REFERENCE = REPO / 'bags' / 'reference_fig8'
TOPICS = {'/haptic/device/state': type_name('DeviceState'),
          '/haptic/device/command': type_name('DeviceCommand'),
          '/haptic/lmi/update': type_name('LmiUpdate'),
          '/haptic/ve/path': type_name('VtPath')}
#: Bytes a device cycle may cost at most in the stream's compact arrays (first pass under
#: 40, rows ~15, drift summary 16, periods 8; measured: ~60 at the peak).
BYTES_PER_CYCLE = 128


def _current(msg: Any, msgtype: str) -> Any:
    """``msg`` as an object of the current definition (fields it lacks: zero / empty, the
    controller id 7)."""
    ts = typestore_with_haptic_msgs()
    fields = ts.fielddefs[msgtype][1]
    if all(hasattr(msg, n) for n, _ in fields):
        return msg
    from haptic_topology.bag.reader import field_default

    return ts.types[msgtype](**{n: getattr(msg, n) if hasattr(msg, n) else 7
                                if n == 'controller_id' else field_default(t)[1]
                                for n, t in fields})


def _templates() -> dict[str, Any]:
    """The reference bag's first running state, its command, and an update and a VT path
    that consumed a hand input."""
    bag = open_bag(REFERENCE)
    decode = decoder(bag=bag)
    out: dict[str, Any] = {}
    for m in iter_messages(bag):
        kind = m.topic.rsplit('/', 1)[-1]
        if m.topic not in TOPICS or kind in out:
            continue
        msg = _current(decode(m), m.msgtype)
        if kind == 'state' and msg.status & 4:
            continue
        if kind == 'update' and int(msg.hand_input_seq) == 0:
            continue
        out[kind] = msg
    return out


def _header(msg: Any, ns: int) -> Any:
    ts = typestore_with_haptic_msgs()
    stamp = ts.types['builtin_interfaces/msg/Time'](ns // 1_000_000_000, ns % 1_000_000_000)
    return replace(msg.header, stamp=stamp)


def write_synthetic_bag(path: Path, cycles: int) -> Path:
    """A bag of ``cycles`` device cycles (module doc)."""
    ts = typestore_with_haptic_msgs()
    tpl = _templates()
    names = list(TOPICS)
    custom = (open_bag(REFERENCE).metadata or {}).get('custom_data') or {}
    w = BagWriter(path, [TopicSpec(t, TOPICS[t], (make_qos(False, 1),)) for t in names], ts,
                  sources=message_definitions(), custom=custom)     # the messages' graph id
    angle = np.linspace(0.0, 2.0 * math.pi, cycles)
    for k in range(1, cycles + 1):
        ns = 1_000_000_000 + k * 1_000_000
        wiggle = np.array([0.01 * math.cos(angle[k - 1]), 0.01 * math.sin(angle[k - 1]), 0.0])
        state = replace(tpl['state'], header=_header(tpl['state'], ns), seq=k,
                        pose=tpl['state'].pose + wiggle, status=1 if k % 700 < 50 else 0)
        w.write(0, ns, bytes(ts.serialize_cdr(state, TOPICS[names[0]])))
        cmd = replace(tpl['command'], header=_header(tpl['command'], ns + 400_000),
                      state_seq=k, constraint_count=k // 1000 % 2)
        w.write(1, ns + 400_000, bytes(ts.serialize_cdr(cmd, TOPICS[names[1]])))
        if k % 10 == 0:
            upd = replace(tpl['update'], header=_header(tpl['update'], ns + 600_000),
                          seq=k // 10, hand_input_seq=k, constraint_count=k // 1500 % 2,
                          hand_pose=tpl['update'].hand_pose + wiggle)
            w.write(2, ns + 600_000, bytes(ts.serialize_cdr(upd, TOPICS[names[2]])))
            m = int(tpl['path'].task_dim)
            poses = np.tile(tpl['state'].pose[:m] + wiggle[:m], 10)
            vt = replace(tpl['path'], header=_header(tpl['path'], ns + 700_000),
                           update_seq=k // 10, hand_input_seqs=np.arange(k - 9, k + 1,
                                                                         dtype=np.uint64),
                           hand_pose=poses)
            w.write(3, ns + 700_000, bytes(ts.serialize_cdr(vt, TOPICS[names[3]])))
    w.close()
    return path


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    root = tmp_path_factory.mktemp('stream')
    return {n: write_synthetic_bag(root / f'cycles_{n}', n) for n in (3000, 12000)}


def _peak(bag: Path, out: Path) -> int:
    """Peak traced memory (bytes) of reading ``bag`` into everything analyze and run make
    of it (drift summary, periods, plot rows, the Parquet trace), in chunks of 1024 rows and
    with plots of at most 500 buckets (fewer than either bag has cycles)."""
    sinks: list[Any] = [Summary(), PeriodStats(), PlotRows(limit=500)]
    from haptic_topology.sim.trace_io import TraceWriter

    sinks.append(TraceWriter(out))
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        stream_graph_bag(bag, sinks, dof=3, task_dim=3, chunk_rows=1024)
        sinks[0].result()
        sinks[1].result()
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_runs_length(bags: dict[int, Path],
                                                   tmp_path: Path) -> None:
    """Four times the cycles: the peak grows by at most the compact per-cycle arrays
    (:data:`BYTES_PER_CYCLE`) plus 30 % (allocator slack), not by the decoded messages or
    the trace (several hundred bytes a cycle)."""
    _peak(bags[3000], tmp_path / 'warm.parquet')  # caches (typestores, imports) filled
    short = _peak(bags[3000], tmp_path / 'short.parquet')
    long = _peak(bags[12000], tmp_path / 'long.parquet')
    allowed = 1.3 * short + BYTES_PER_CYCLE * (12000 - 3000)
    assert long < allowed, (f'peak {long / 1e6:.2f} MB for 12000 cycles, '
                            f'{short / 1e6:.2f} MB for 3000: grows with the run '
                            f'(allowed {allowed / 1e6:.2f} MB)')


def test_stream_equals_the_whole_trace(bags: dict[int, Path], tmp_path: Path) -> None:
    """The summary, loop figures and trace file of the stream (small chunks: the rows of one
    chunk come from messages spread over two) equal those of the trace read whole."""
    bag = bags[3000]
    whole = read_graph_bag(bag, dof=3, task_dim=3)
    assert not whole.skipped and len(whole.trace) == 3000
    assert np.isfinite(whole.trace.columns['vt_pose']).all()
    summary, period = Summary(), PeriodStats()
    from haptic_topology.sim.trace_io import TraceWriter

    run = stream_graph_bag(bag, [summary, period, TraceWriter(tmp_path / 't.parquet')],
                           dof=3, task_dim=3, chunk_rows=97)
    assert run.rows == 3000 and run.loop == whole.loop
    assert json.dumps(summary.result()) == json.dumps(whole.trace.summary())
    back = read_trace(tmp_path / 't.parquet')
    for name, col in whole.trace.columns.items():
        np.testing.assert_array_equal(back.columns[name], col)
    np.testing.assert_array_equal(back.t, whole.trace.t)
    assert back.meta == whole.trace.meta


def test_plot_rows_keep_every_step_and_each_buckets_extremes(bags: dict[int, Path]) -> None:
    """A plot of a long run draws fewer rows, but each bucket's smallest and largest drift
    and every change of the step panels (constraint count, workspace limit)."""
    whole = read_graph_bag(bags[12000], dof=3, task_dim=3).trace
    rows = PlotRows(limit=1000)
    stream_graph_bag(bags[12000], [rows], dof=3, task_dim=3, chunk_rows=1000)
    drawn = rows.trace
    assert drawn is not None and 1000 <= len(drawn) < len(whole) // 2
    dist, kept = whole.distance(), np.searchsorted(whole.seq, drawn.seq)
    step = 12
    for b in range(0, len(whole), step):
        assert {b + int(np.argmin(dist[b:b + step])), b + int(np.argmax(dist[b:b + step]))} \
            <= set(kept.tolist())
    for col in ('constraint_count', 'status'):
        change = np.nonzero(np.diff(whole.columns[col]) != 0)[0] + 1
        assert set(change.tolist()) <= set(kept.tolist()), col
    assert kept[0] == 0 and kept[-1] == len(whole) - 1


def test_analyze_and_reduce_write_what_the_whole_trace_gives(bags: dict[int, Path],
                                                            tmp_path: Path) -> None:
    """``analyze`` of a bag and of the Parquet trace ``run`` writes give the drift summary of
    the whole trace."""
    bag = bags[3000]
    whole = read_graph_bag(bag, dof=3, task_dim=3).trace
    red = reduce_bag(bag, dof=3, task_dim=3, traces=(tmp_path / 'trace.parquet',
                                                     tmp_path / 'trace.csv'))
    # The synthetic commands are no controller's: its energy series is refused, at the first.
    series = red.summary.pop('energy_series')
    assert series.startswith('refused: state 1: the replayed command differs'), series
    assert red.energy_plot is None
    assert red.summary == whole.summary()
    csv, parquet = read_trace(tmp_path / 'trace.csv'), read_trace(tmp_path / 'trace.parquet')
    for name, col in whole.columns.items():
        np.testing.assert_array_equal(csv.columns[name], col)
        np.testing.assert_array_equal(parquet.columns[name], col)
    rows = analyze([tmp_path / 'trace.parquet', tmp_path / 'trace.csv'], tmp_path / 'out')
    for row in rows:
        for key, value in whole.summary().items():
            assert row[key] == value, key
    assert isinstance(Trace.concat([whole.take(slice(0, 5)), whole.take(slice(5, 9))]), Trace)


def test_energy_series_is_reconstructed_up_to_its_limit_or_on_request(
        bags: dict[int, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """``analyze`` reconstructs a bag's energy series by default up to
    ``energy_series.AUTO_STATES`` states, any bag with ``--energy``, none with
    ``--no-energy``; it says which in ``energy_series``."""
    import haptic_topology.bag.energy_series as es

    bag = bags[3000]
    off = reduce_bag(bag, dof=3, task_dim=3, plot=False, energy=False).summary
    assert off['energy_series'] == 'not reconstructed: --no-energy'
    monkeypatch.setattr(es, 'AUTO_STATES', 2999)
    auto = reduce_bag(bag, dof=3, task_dim=3, plot=False).summary
    assert auto['energy_series'] == ('not reconstructed: 3000 states, more than 2999 '
                                     '(analyze --energy)')
    forced = reduce_bag(bag, dof=3, task_dim=3, plot=False, energy=True).summary
    assert forced['energy_series'].startswith('refused: state 1: ')
