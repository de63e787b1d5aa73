"""Consumers of a trace given chunk by chunk, so that a run of any length is reduced in
bounded memory: the trace's rows pass once, in order, and only compact per-row figures
(a float or two a row) are kept.

A :class:`TraceSink` gets ``begin`` with a row-less trace holding the metadata and the number
of rows to come, then ``add`` per chunk (a :class:`~haptic_topology.sim.trace.Trace` of
consecutive rows), then ``end``. The sinks here:

* :class:`Summary`: the drift figures (:class:`~haptic_topology.sim.trace.SummaryStats`,
  the figures of :meth:`~haptic_topology.sim.trace.Trace.summary` to the last bit);
* :class:`PeriodStats`: the device period p50/p99/std (ms) from the row times;
* :class:`PlotRows`: the rows a plot draws;
* :class:`~haptic_topology.sim.trace_io.TraceWriter`: the trace file.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, Protocol

import numpy as np

from haptic_topology.sim.trace import SummaryStats, Trace

#: A trace of at most this many rows is plotted whole; a longer one as :class:`PlotRows`
#: samples it.
PLOT_ROWS = 50_000


class TraceSink(Protocol):
    """Gets a trace chunk by chunk (module doc)."""

    def begin(self, template: Trace, rows: int) -> None: ...

    def add(self, chunk: Trace) -> None: ...

    def end(self) -> None: ...


def feed(chunks: Iterable[Trace], template: Trace, rows: int, sinks: list[Any]) -> None:
    """Give ``chunks`` (``rows`` rows in all, metadata of ``template``) to every sink."""
    for sink in sinks:
        sink.begin(template, rows)
    for chunk in chunks:
        for sink in sinks:
            sink.add(chunk)
    for sink in sinks:
        sink.end()


class Summary:
    """The drift figures of the trace (:meth:`~haptic_topology.sim.trace.Trace.summary`,
    :meth:`result`)."""

    def __init__(self) -> None:
        self.stats = SummaryStats()
        self.meta: dict[str, Any] = {}

    def begin(self, template: Trace, rows: int) -> None:
        self.meta = dict(template.meta)

    def add(self, chunk: Trace) -> None:
        self.stats.add(chunk)

    def end(self) -> None:
        pass

    def result(self) -> dict[str, Any]:
        """The figures; ValueError when no row has both a device and a VT hand pose."""
        return self.stats.result(self.meta)


class PeriodStats:
    """Device period p50/p99/std (ms) from the row times (the state stamps of a bag), over
    consecutive seqs only, and the states missing between the first and the last seq."""

    def __init__(self) -> None:
        self.periods: list[np.ndarray] = []
        self.rows = 0
        self.first_seq = self.last_seq = 0
        self.last_t = math.nan

    def begin(self, template: Trace, rows: int) -> None:
        pass

    def add(self, chunk: Trace) -> None:
        if not len(chunk):
            return
        seq = np.asarray(chunk.seq)
        t = chunk.t
        if self.rows:
            seq = np.concatenate([[self.last_seq], seq])
            t = np.concatenate([[self.last_t], t])
        else:
            self.first_seq = int(seq[0])
        self.periods.append(np.diff(t)[np.diff(seq) == 1] * 1e3)
        self.rows += len(chunk)
        self.last_seq, self.last_t = int(seq[-1]), float(t[-1])

    def end(self) -> None:
        pass

    def result(self) -> dict[str, float]:
        if self.rows < 3:
            return {}
        periods = np.concatenate(self.periods)
        if periods.size == 0:
            return {}
        return {'bag_period_p50_ms': float(np.percentile(periods, 50)),
                'bag_period_p99_ms': float(np.percentile(periods, 99)),
                'bag_period_std_ms': float(np.std(periods)),
                'bag_missing_states': float(self.last_seq - self.first_seq + 1 - self.rows)}


def _extremes(values: np.ndarray, start: int, step: int) -> np.ndarray:
    """Indices of the smallest and the largest finite value of ``values`` in each bucket of
    ``step`` rows (rows ``start + i``; bucket ``(start + i) // step``)."""
    if values.size == 0:
        return np.zeros(0, dtype=int)
    head = (-start) % step
    lo = np.where(np.isfinite(values), values, np.inf)
    hi = np.where(np.isfinite(values), values, -np.inf)
    out = []
    if head:
        out += [int(np.argmin(lo[:head])), int(np.argmax(hi[:head]))] if head <= values.size \
            else [int(np.argmin(lo)), int(np.argmax(hi))]
    body = max(0, (values.size - head) // step * step)
    if body:
        n = body // step
        base = head + np.arange(n) * step
        out += list(base + np.argmin(lo[head:head + body].reshape(n, step), axis=1))
        out += list(base + np.argmax(hi[head:head + body].reshape(n, step), axis=1))
    rest = head + body
    if rest < values.size:
        out += [rest + int(np.argmin(lo[rest:])), rest + int(np.argmax(hi[rest:]))]
    return np.asarray(out, dtype=int)


def _series(chunk: Trace) -> list[np.ndarray]:
    """The time series the plots draw whose extremes a bucket keeps."""
    out = [chunk.distance()]
    if chunk.has_contacts:
        rows = chunk.task.translation_rows
        env = chunk.columns['env_wrench']
        out += [env[:, i] for i in range(rows.stop)]
        out += [np.linalg.norm(chunk.columns[c][:, rows], axis=1)
                for c in ('env_wrench', 'applied', 'hand_wrench')]
        out.append(chunk.columns['penetration'])
    if chunk.has_energy:
        out += [chunk.columns[c] for c in ('passivity_observer', 'passivity_damping')]
    return out


def _levels(chunk: Trace) -> np.ndarray:
    """Per row, what the step panels show: constraint count, at the workspace limit, in
    contact (rows x 3)."""
    depth = (np.nan_to_num(chunk.columns['penetration'], nan=0.0) > 0.0
             if chunk.has_contacts else np.zeros(len(chunk), dtype=bool))
    return np.column_stack([chunk.columns['constraint_count'],
                            (chunk.columns['status'] & 1) > 0, depth]).astype(np.int64)


class PlotRows:
    """The rows a plot of the trace draws (``trace``, after ``end``): all of them when
    there are at most :data:`PLOT_ROWS`; else, in buckets of ``ceil(rows / PLOT_ROWS)`` rows,
    the first row of each bucket and the rows of the smallest and the largest value of each
    drawn time series (drift; with contacts, ``F_env``, the wrench norms and the penetration;
    with the energy account, the passivity observer and damping),
    every row where a step panel changes (constraint count, workspace limit, contact) and the
    last row. The time series keep their envelope at any zoom a figure can show, the step
    panels are exact, and the hand paths are sampled at 1 / bucket of the device's rate."""

    def __init__(self, limit: int = PLOT_ROWS) -> None:
        self.limit = limit
        self.step = 1
        self.start = 0
        self.parts: list[Trace] = []
        self.previous: np.ndarray | None = None
        self.trace: Trace | None = None
        self.template: Trace | None = None

    def begin(self, template: Trace, rows: int) -> None:
        self.template = template
        self.step = max(1, math.ceil(rows / self.limit))

    def add(self, chunk: Trace) -> None:
        n = len(chunk)
        if not n:
            return
        if self.step == 1:
            self.parts.append(chunk.take(slice(0, n)))
            self.start += n
            return
        rows = [np.nonzero((self.start + np.arange(n)) % self.step == 0)[0], [n - 1]]
        rows += [_extremes(v, self.start, self.step) for v in _series(chunk)]
        levels = _levels(chunk)
        before = levels[:1] if self.previous is None else self.previous
        changed = np.any(np.diff(np.vstack([before, levels]), axis=0) != 0, axis=1)
        rows.append(np.nonzero(changed)[0])
        self.previous = levels[-1:]
        keep = np.unique(np.concatenate([np.asarray(r, dtype=int) for r in rows]))
        self.parts.append(chunk.take(keep))
        self.start += n

    def end(self) -> None:
        if self.parts:
            self.trace = Trace.concat(self.parts)
        elif self.template is not None:
            self.trace = self.template
        self.parts = []
