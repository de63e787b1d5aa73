"""Reduce a bag recorded from the node graph to a :class:`~haptic_topology.sim.trace.Trace`.

Rows are the device states of the run (from the first state not flagged STATUS_WATCHDOG,
the state at which the controller engaged; ``t = 0`` there), in sequence order:

* device pose/twist, hand wrench, applied wrench and status from ``DeviceState``;
* command, LMI VT hand pose and LMI constraint count from the ``DeviceCommand`` with
  ``state_seq`` equal to the row's seq (NaN / 0 when it was lost);
* the VE's VT hand pose from ``VtPath`` (the VT after every consumed input s, i.e. at the
  time of state s + 1) where the bag has it, the initial one from the first ``LmiUpdate``
  (``hand_input_seq`` 0); bags without ``VtPath`` (older recordings): from ``LmiUpdate``
  (the VE after consuming input s), interpolated linearly in time between updates (100 Hz);
  joint positions from ``LmiUpdate``, interpolated the same way; after the last sample they
  are NaN; the constraint count is held from the last update.

Messages that do not belong to the run are skipped and counted per ``<kind>_<reason>`` in
:attr:`GraphRun.skipped` (``analyze`` writes them to ``summary.json`` as
``skipped_messages``): messages of another graph than the recorder's (``graph_id`` field
against the bag's ``custom_data.graph_id``: ``<kind>_foreign_graph``, also counted per topic
in :attr:`GraphRun.foreign_messages`; ``/diagnostics`` statuses of another graph are not
read), messages on the graph's topics that do not decode (``<kind>_decode``),
fail the nodes' own checks (:mod:`haptic_topology.messages.check`: task_dim, dof, sizes,
non-finite values, integer ranges; the run's task_dim is the scenario's, else the most common
one among the states, its dof the scenario's, else the most common among the updates), repeat
a sequence number already read (``state_duplicate``, ``command_duplicate``; of several
commands answering one state, the one from a controller the device driver reported following
(``controller_id`` in its ``/diagnostics``, any time in the bag) is kept, else the first one
read; of states, the first one read: a bag cannot tell which publisher sent which), or lie
far outside the run (``state_foreign_seq``: states are grouped where consecutive seqs are at
most :data:`MAX_SEQ_GAP` apart, and the largest group holding running states is the run).
Messages are decoded with the definitions stored in the bag where they differ from the
current ones (:func:`~haptic_topology.bag.reader.bag_typestore`): bags recorded before
``DeviceCommand.controller_id`` existed read as before.

The run's task (the trace's ``meta['task']``: which entries are translations, what the drift
measures) is the scenario's, given or named in the bag's metadata; of the task_dim alone only
where one task has it (:func:`~haptic_topology.bag.graph_index.bag_task`: 3 is ``planar`` or
``spatial_point``, and such a bag is refused rather than guessed).

Loop figures: the device driver's own counts from its last ``/diagnostics`` status
(answered fraction, round trip p50/p99), and an estimate from the bag alone: the fraction of
states k whose command was computed (``DeviceCommand.header.stamp``) before state k+1 was
stamped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.graph_index import (
    DEVICE_STATUS,
    KINDS,
    MAX_SEQ_GAP,
    PATH_TOPIC,
    BagIndex,
    index_bag,
    stamp,
)
from haptic_topology.bag.reader import Progress, decoder, iter_messages, open_bag, require_types
from haptic_topology.errors import BagError, MessageError
from haptic_topology.messages.check import (
    GraphFilter,
    check_command,
    check_state,
    check_vt_path,
    env_wrench,
)
from haptic_topology.messages.definitions import type_name
from haptic_topology.model.linkage import Linkage
from haptic_topology.sim.trace import Trace
from haptic_topology.sim.trace_io import CHUNK_ROWS
from haptic_topology.sim.trace_stats import TraceSink
from haptic_topology.vocabulary import ControlMode

__all__ = ['GRAPH_TYPES', 'MAX_SEQ_GAP', 'PATH_TOPIC', 'GraphRun', 'read_graph_bag',
           'stream_graph_bag']

_DEVICE_STATUS = DEVICE_STATUS
#: Topic suffix -> type the graph publishes on it (a bag without any of them is foreign);
#: ``haptic/hand`` (one ``HandInput`` per cycle): bags recorded before the hand inputs were
#: batched on ``haptic/hand_inputs``.
GRAPH_TYPES = {
    vocab.TOPIC_STATE: type_name('DeviceState'),
    vocab.TOPIC_COMMAND: type_name('DeviceCommand'),
    vocab.TOPIC_HAND_INPUTS: type_name('HandInputs'),
    vocab.TOPIC_HAND_LEGACY: type_name('HandInput'),
    vocab.TOPIC_LMI: type_name('LmiUpdate'),
}
_MODE_LABELS = {int(m): m.label for m in ControlMode}


@dataclass
class GraphRun:
    """A recorded run: its trace and loop figures (``loop`` keys are documented above).

    From :func:`stream_graph_bag` the trace has no rows (they went to the sinks): it holds
    the metadata and :attr:`rows` says how many there were."""

    trace: Trace
    loop: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    #: Skipped messages per ``<kind>_<reason>`` (module doc).
    skipped: dict[str, int] = field(default_factory=dict)
    #: The recorder's graph (``graph_id``; empty: the default graph) and the messages of
    #: other graphs on the loop topics, per topic (skipped: ``<kind>_foreign_graph``).
    graph_id: str = ''
    foreign_messages: dict[str, int] = field(default_factory=dict)
    #: Publishers of another node than the graph expects on its input topics, as the nodes
    #: reported them any time in the bag (``foreign_publishers``): name -> topics
    foreign_publishers: dict[str, list[str]] = field(default_factory=dict)
    rows: int = 0


class _Collect:
    """A sink keeping every chunk (:func:`read_graph_bag`)."""

    def __init__(self) -> None:
        self.chunks: list[Trace] = []

    def begin(self, template: Trace, rows: int) -> None:
        pass

    def add(self, chunk: Trace) -> None:
        self.chunks.append(chunk)

    def end(self) -> None:
        pass


def read_graph_bag(path: str | Path, scenario: str = '', dof: int | None = None,
                   progress: Progress | None = None, task_dim: int | None = None,
                   linkage: Linkage | None = None) -> GraphRun:
    """Read the bag ``path`` (see module doc) into a trace held whole in memory (a long run:
    :func:`stream_graph_bag`); ``progress`` gets the fraction read; ``dof``/``task_dim``:
    the scenario's linkage (None: from the bag's majority); ``linkage``: the scenario's
    linkage itself (None: loaded by the name ``scenario``; give it for a scenario file,
    whose name is not a known scenario).

    A truncated bag (recorder killed) is read up to its last complete chunk; the trace's
    ``meta['truncated']`` is then True. Foreign and malformed messages are skipped and
    counted (:attr:`GraphRun.skipped`).
    """
    sink = _Collect()
    run = stream_graph_bag(path, [sink], scenario, dof, progress, task_dim, linkage)
    run.trace = Trace.concat(sink.chunks)
    return run


def _scaled(progress: Progress | None, lo: float) -> Progress | None:
    return None if progress is None else (lambda f: progress(lo + 0.5 * f))


def stream_graph_bag(path: str | Path, sinks: list[TraceSink], scenario: str = '',
                     dof: int | None = None, progress: Progress | None = None,
                     task_dim: int | None = None, linkage: Linkage | None = None,
                     chunk_rows: int = CHUNK_ROWS) -> GraphRun:
    """Read the bag ``path`` (see module doc and :func:`read_graph_bag` for the arguments)
    in two passes, in memory that does not grow with the run's length but for a few bytes
    a cycle: the first (:func:`~haptic_topology.bag.graph_index.index_bag`) decides which
    message fills which row, the second decodes those and gives the trace to ``sinks``
    (:class:`~haptic_topology.sim.trace_stats.TraceSink`) in chunks of ``chunk_rows`` rows,
    in order. Returns the run with a row-less trace (its metadata)."""
    bag = open_bag(path)
    require_types(bag, GRAPH_TYPES)
    index = index_bag(bag, scenario, dof, task_dim, linkage, _scaled(progress, 0.0))
    template = Trace.empty(0, index.m, index.dof, index.contacts,
                           mode=_MODE_LABELS.get(index.mode, str(index.mode)),
                           scenario=scenario, dt=0.001, source='graph', bag=str(bag.path),
                           truncated=index.truncated, task=index.task.value)
    n = int(index.seqs.size)
    for sink in sinks:
        sink.begin(template, n)
    rows = _Rows(index, template, chunk_rows, sinks)
    decode = decoder(bag=bag)
    graph = GraphFilter(index.graph_id)
    checks = {'state': check_state, 'command': check_command, 'path': check_vt_path}
    for raw in iter_messages(bag, progress=_scaled(progress, 0.5)):
        for suffix, kind in KINDS:
            if raw.topic.endswith(suffix):
                if kind == 'update':
                    break
                # The first pass's checks again (their counts are the first pass's).
                try:
                    msg = decode(raw)
                    if graph.own(msg, suffix):
                        checks[kind](msg, index.m)
                        rows.fill(kind, msg)
                except (BagError, MessageError):
                    pass
                break
    rows.finish(bag.path)
    for sink in sinks:
        sink.end()
    figures = loop_figures(index, rows.in_time, rows.pairs)
    return GraphRun(template, figures, index.diagnostics, index.skipped, index.graph_id,
                    index.foreign_messages, index.foreign_publishers, n)


class _Chunk:
    """Rows ``start .. start + len`` of the trace while their messages come in."""

    def __init__(self, start: int, size: int, template: Trace, left: int) -> None:
        self.start = start
        self.trace = Trace.empty(size, template.task_dim, int(template.meta['dof']),
                                 template.has_contacts, **{
                                     k: v for k, v in template.meta.items()
                                     if k not in ('task_dim', 'dof', 'contacts')})
        self.path = np.full((size, template.task_dim), np.nan)
        self.state_stamp = np.full(size, np.nan)
        self.command_stamp = np.full(size, np.nan)
        self.left = left


class _Rows:
    """The second pass's rows: filled by message, handed on by chunk once complete."""

    def __init__(self, index: BagIndex, template: Trace, size: int,
                 sinks: list[TraceSink]) -> None:
        self.index, self.template, self.size, self.sinks = index, template, size, sinks
        self.n = int(index.seqs.size)
        #: Per row: its state not yet read; its command (0: none to come, 1: the first valid
        #: one, 2: a followed controller's, which replaces the first valid one, 3: the same
        #: once the first has come); VtPath poses to come.
        self.state = np.ones(self.n, dtype=bool)
        self.command = index.command.copy()
        self.paths = index.paths.copy()
        self.chunks: dict[int, _Chunk] = {}
        self.next = 0
        self.in_time = self.pairs = 0
        self.last_seq = -1
        self.last_command = math.nan

    def _chunk(self, row: int) -> tuple[_Chunk, int]:
        c = row // self.size
        chunk = self.chunks.get(c)
        if chunk is None:
            start = c * self.size
            end = min(start + self.size, self.n)
            index = self.index      # (what the rows take in all, not what is left)
            chunk = _Chunk(start, end - start, self.template,
                           int(end - start + np.count_nonzero(index.command[start:end])
                               + index.paths[start:end].astype(np.int64).sum()))
            self.chunks[c] = chunk
        return chunk, row - chunk.start

    def _row(self, seq: int) -> int:
        """The row of state ``seq``, -1 if none."""
        row = int(np.searchsorted(self.index.seqs, seq))
        return row if row < self.n and int(self.index.seqs[row]) == seq else -1

    def fill(self, kind: str, msg: Any) -> None:
        """A message that passed the first pass's checks: into its row if the row takes it
        (module doc: the first valid state of a seq, the chosen command, every VtPath pose
        of the previous seq, the last one read counting)."""
        index = self.index
        if kind == 'state':
            row = self._row(int(msg.seq))
            if row < 0 or not self.state[row]:
                return
            self.state[row] = False
            chunk, j = self._chunk(row)
            st = stamp(msg.header)
            chunk.trace.record(j, t=st - index.t0, device_pose=msg.pose,
                               device_twist=msg.twist, hand_wrench=msg.hand_wrench,
                               applied=msg.applied_wrench, status=int(msg.status))
            chunk.trace.seq[j] = int(msg.seq)
            chunk.state_stamp[j] = st
            self._done(chunk)
        elif kind == 'command':
            row = self._row(int(msg.state_seq))
            want = int(self.command[row]) if row >= 0 else 0
            followed = int(getattr(msg, 'controller_id', 0)) in index.followed
            if want == 0 or (want == 3 and not followed):
                return      # none wanted, or a duplicate that does not replace the first
            # 1: the first valid one; 2, 3: the first followed one (before it: the first)
            self.command[row] = 0 if want == 1 or followed else 3
            chunk, j = self._chunk(row)
            tr = chunk.trace
            tr.columns['command'][j] = msg.wrench
            tr.columns['lmi_pose'][j] = msg.vt_pose
            tr.columns['lmi_constraint_count'][j] = int(msg.constraint_count)
            if tr.has_contacts:
                env = env_wrench(msg, index.m)
                tr.columns['env_wrench'][j] = np.zeros(index.m) if env is None else env
            chunk.command_stamp[j] = stamp(msg.header)
            if self.command[row] == 0:
                self._done(chunk)
        elif kind == 'path' and index.vt_path:
            _, seqs, poses = check_vt_path(msg, index.m)
            for s, pose in zip(seqs, poses, strict=True):
                row = self._row(s + 1)
                if row >= 1 and self.paths[row] > 0:
                    self.paths[row] -= 1
                    chunk, j = self._chunk(row)
                    chunk.path[j] = pose
                    self._done(chunk)

    def _done(self, chunk: _Chunk) -> None:
        chunk.left -= 1
        while self.next in self.chunks and self.chunks[self.next].left == 0:
            self._flush(self.chunks.pop(self.next))
            self.next += 1

    def _flush(self, chunk: _Chunk) -> None:
        """Complete the chunk's rows (the VE's samples, held and interpolated) and hand it
        on."""
        index, tr = self.index, chunk.trace
        rows = chunk.start + np.arange(len(tr))
        known = index.known_rows
        if known.size:
            last = int(known[-1])
            span = rows <= last
            for j in range(index.m):
                tr.columns['vt_pose'][span, j] = np.interp(tr.t[span], index.known_t,
                                                           index.known_pose[:, j])
            for j in range(index.known_q.shape[1]):
                tr.columns['q'][span, j] = np.interp(tr.t[span], index.known_t,
                                                     index.known_q[:, j])
            if index.vt_path:
                later = rows >= 1
                tr.columns['vt_pose'][later] = chunk.path[later]
            at = np.searchsorted(known, rows, side='right') - 1
            held = at >= 0
            at = np.maximum(at, 0)
            tr.columns['constraint_count'][:] = np.where(held, index.known_count[at], 0)
            if tr.has_contacts:
                held &= rows <= last
                tr.columns['penetration'][:] = np.where(held, index.known_depth[at], np.nan)
                tr.columns['contact_energy'][:] = np.where(held, index.known_energy[at],
                                                           np.nan)
        # States answered in time: the command of state k computed before state k + 1.
        seq = np.concatenate([[self.last_seq], tr.seq])
        command = np.concatenate([[self.last_command], chunk.command_stamp])
        pairs = np.diff(seq) == 1
        if self.last_seq < 0:
            pairs[0] = False
        self.pairs += int(np.count_nonzero(pairs))
        self.in_time += int(np.count_nonzero(pairs & (command[:-1] < chunk.state_stamp)))
        self.last_seq, self.last_command = int(tr.seq[-1]), float(chunk.command_stamp[-1])
        for sink in self.sinks:
            sink.add(tr)

    def finish(self, path: Path) -> None:
        if self.chunks or self.next * self.size < self.n:
            raise BagError(f'{path}: the bag changed while it was read (rows '
                           f'{self.next * self.size} on lack their messages)')


def _float(values: dict[str, str], key: str) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return math.nan


def loop_figures(index: BagIndex, in_time: int, pairs: int) -> dict[str, float]:
    """Loop figures from the device driver's diagnostics and from the bag's stamps
    (``in_time`` of ``pairs`` consecutive states answered before the next one)."""
    out: dict[str, float] = {}
    dev = index.diagnostics.get(_DEVICE_STATUS, {})
    for key in ('answered_fraction', 'answered_or_previous_fraction', 'round_trip_p50_ms',
                'round_trip_p99_ms', 'round_trip_max_ms', 'rate_hz', 'period_p99_ms',
                'overruns', 'max_consecutive_missed'):
        out[f'device_{key}'] = _float(dev, key)
    out['max_consecutive_missed'] = out.pop('device_max_consecutive_missed')
    # How late the loop woke after its deadlines: a loop paced by deadlines (the hosted
    # layouts) reports it; the separate layout's executor timers do not.
    for key in ('wake_late_p50_ms', 'wake_late_p99_ms', 'wake_late_max_ms'):
        if key in dev:
            out[f'device_{key}'] = _float(dev, key)
    out['bag_answered_fraction'] = in_time / pairs if pairs else math.nan
    # Every state and every command of the run in the bag (the idle ones before engagement
    # too), as a count of the bag's messages gives them; the trace's rows start at the first
    # running state.
    out['bag_states'] = float(index.bag_states)
    out['bag_commands'] = float(index.bag_commands)
    out['ve_update_rate_hz'] = index.update_rate_hz
    return out

