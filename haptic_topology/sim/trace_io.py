"""Trace files: ``trace.parquet`` (the default) and ``trace.csv``, written as the rows come.

A trace file holds one row per device cycle, in the columns of
:meth:`~haptic_topology.sim.trace.Trace.header`
(``t``, ``seq``, ``device_pose_0``, ..., ``status``; floats as float64, ``seq`` and the counts
as int64) and the trace's metadata (``mode``, ``scenario``, ``task_dim``, ``task``, ``dof``, ...):

* Parquet: the metadata is the JSON text of the schema's key ``haptic_topology``; one row
  group per chunk written (:data:`CHUNK_ROWS` rows). Open it with
  ``pandas.read_parquet('trace.parquet')``, ``polars.read_parquet('trace.parquet')`` or
  ``pyarrow.parquet.read_table('trace.parquet')``; the metadata with
  ``json.loads(pyarrow.parquet.read_schema('trace.parquet').metadata[b'haptic_topology'])``.
* CSV: the metadata as a one-line JSON comment (``# {...}``), then the header row, then the
  rows (``repr`` of each float: exact).

:class:`TraceWriter` writes either, chunk by chunk (a
:class:`~haptic_topology.sim.trace_stats.TraceSink`), so a trace of any length is written in
bounded memory; :func:`iter_trace` reads a file back chunk by chunk and :func:`read_trace`
whole.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from haptic_topology.errors import ConfigError
from haptic_topology.sim.trace import CONTACT_FLOATS, ENERGY_FLOATS, SCALARS, VECTORS, Trace
from haptic_topology.vocabulary import TASK_NAMES, TaskSpace

#: Rows per chunk (Parquet row group) when a trace is written or read in pieces.
CHUNK_ROWS = 65_536
#: The schema metadata key of a Parquet trace holding its metadata (JSON).
META_KEY = b'haptic_topology'
FORMATS = ('parquet', 'csv')


def _blocks(trace: Trace) -> list[tuple[str, np.ndarray]]:
    """``(column name, 1-D values)`` in the order of :meth:`Trace.header`."""
    m, dof = trace.task_dim, int(trace.meta['dof'])
    out: list[tuple[str, np.ndarray]] = [('t', trace.t), ('seq', trace.seq)]
    for name in VECTORS:
        out += [(f'{name}_{i}', trace.columns[name][:, i]) for i in range(m)]
    out += [(f'q_{i}', trace.columns['q'][:, i]) for i in range(dof)]
    out += [(name, trace.columns[name]) for name in SCALARS]
    if trace.has_contacts:
        out += [(f'env_wrench_{i}', trace.columns['env_wrench'][:, i]) for i in range(m)]
        out += [(name, trace.columns[name]) for name in CONTACT_FLOATS]
    if trace.has_energy:
        out += [(name, trace.columns[name]) for name in ENERGY_FLOATS]
    return out


def _is_int(name: str) -> bool:
    return name == 'seq' or name in SCALARS


class TraceWriter:
    """Writes the chunks of one trace to ``path`` in the format ``fmt`` (``parquet`` or
    ``csv``; None: CSV if the name ends in ``.csv``, else Parquet; see module doc):
    :meth:`begin` with a row-less trace holding the metadata, :meth:`add` per chunk,
    :meth:`end` closes the file."""

    def __init__(self, path: str | os.PathLike[str], fmt: str | None = None) -> None:
        self.path = Path(path)
        self.fmt = fmt or ('csv' if self.path.suffix == '.csv' else 'parquet')
        if self.fmt not in FORMATS:
            raise ConfigError(f'{self.path}: trace format {self.fmt!r}: expected one of '
                              f'{", ".join(FORMATS)}')
        self._parquet: Any = None
        self._csv: IO[str] | None = None
        self._ints: list[bool] = []

    def begin(self, template: Trace, rows: int = 0) -> None:
        """Open the file: the columns and metadata of ``template`` (``rows``: unused)."""
        names = [name for name, _ in _blocks(template)]
        self._ints = [_is_int(n) for n in names]
        if self.fmt == 'csv':
            self._csv = self.path.open('w', newline='', encoding='utf-8')
            self._csv.write('# ' + json.dumps(template.meta) + '\n')
            csv.writer(self._csv).writerow(names)
            return
        import pyarrow as pa
        import pyarrow.parquet as pq

        schema = pa.schema([(n, pa.int64() if i else pa.float64())
                            for n, i in zip(names, self._ints, strict=True)],
                           metadata={META_KEY: json.dumps(template.meta).encode()})
        self._parquet = pq.ParquetWriter(str(self.path), schema)

    def add(self, chunk: Trace) -> None:
        """Write the next rows (Parquet: one row group)."""
        blocks = _blocks(chunk)
        if self._csv is not None:
            table = np.column_stack([b.astype(float) for _, b in blocks]) if blocks else None
            w = csv.writer(self._csv)
            for row in table if table is not None else []:
                w.writerow([int(v) if self._ints[i] else repr(float(v))
                            for i, v in enumerate(row)])
            return
        import pyarrow as pa

        arrays = [pa.array(np.asarray(b, dtype=np.int64 if i else np.float64))
                  for (_, b), i in zip(blocks, self._ints, strict=True)]
        self._parquet.write_table(pa.Table.from_arrays(arrays, schema=self._parquet.schema))

    def end(self) -> None:
        """Close the file."""
        if self._csv is not None:
            self._csv.close()
            self._csv = None
        if self._parquet is not None:
            self._parquet.close()
            self._parquet = None


def write_trace(trace: Trace, path: str | Path, fmt: str | None = None) -> None:
    """Write all of ``trace`` to ``path`` in ``fmt`` (``parquet`` or ``csv``; None: CSV if
    the name ends in ``.csv``, else Parquet)."""
    writer = TraceWriter(path, fmt)
    writer.begin(trace.take(np.arange(0)), len(trace))
    for start in range(0, len(trace), CHUNK_ROWS):
        writer.add(trace.take(np.arange(start, min(start + CHUNK_ROWS, len(trace)))))
    writer.end()


def empty_trace(meta: dict[str, Any], rows: int = 0) -> Trace:
    """A trace of ``rows`` rows (NaN / 0) with the metadata ``meta`` of a file."""
    meta = dict(meta)
    try:
        m, dof = int(meta.pop('task_dim')), int(meta.pop('dof'))
    except (KeyError, TypeError, ValueError):
        raise ConfigError('trace metadata: expected the integers task_dim and dof, got '
                          f'{meta!r}') from None
    contacts = bool(meta.pop('contacts', False))
    task = meta.get('task')
    if task is not None and (task not in TASK_NAMES or TaskSpace(task).dim != m):
        raise ConfigError(f'trace metadata: task must be a task of dimension task_dim = {m} '
                          f'({", ".join(t.value for t in TaskSpace if t.dim == m) or "none"}),'
                          f' got {task!r}')
    return Trace.empty(rows, m, dof, contacts, **meta)


def _from_table(meta: dict[str, Any], header: list[str], table: np.ndarray) -> Trace:
    """A trace from the metadata and the columns ``header`` of ``table`` (rows x columns)."""
    trace = empty_trace(meta, len(table))
    m, dof, contacts = trace.task_dim, int(trace.meta['dof']), trace.has_contacts
    col = {name: i for i, name in enumerate(header)}
    trace.t = table[:, col['t']]
    trace.seq = table[:, col['seq']].astype(int)
    for name in VECTORS:
        trace.columns[name] = table[:, [col[f'{name}_{i}'] for i in range(m)]]
    trace.columns['q'] = table[:, [col[f'q_{i}'] for i in range(dof)]]
    for name in SCALARS:
        trace.columns[name] = table[:, col[name]].astype(int)
    if contacts:
        trace.columns['env_wrench'] = table[:, [col[f'env_wrench_{i}'] for i in range(m)]]
        for name in CONTACT_FLOATS:
            trace.columns[name] = table[:, col[name]]
    if trace.has_energy:
        for name in ENERGY_FLOATS:
            trace.columns[name] = table[:, col[name]]
    return trace


def trace_meta(path: str | Path) -> tuple[dict[str, Any], int]:
    """The metadata and the number of rows of the trace file ``path`` (for a CSV the rows are
    counted by reading it)."""
    p = Path(path)
    if p.suffix == '.parquet':
        import pyarrow.parquet as pq

        try:
            md = pq.read_metadata(str(p))
            meta = (md.schema.to_arrow_schema().metadata or {}).get(META_KEY)
        except (OSError, ValueError) as exc:
            raise ConfigError(f'{p}: cannot read trace ({exc})') from None
        if meta is None:
            raise ConfigError(f'{p}: not a haptic_topology trace (no {META_KEY.decode()} '
                              'metadata)')
        return json.loads(meta), int(md.num_rows)
    trace = read_trace(p)
    return dict(trace.meta), len(trace)


def iter_trace(path: str | Path, rows: int = CHUNK_ROWS) -> Iterator[Trace]:
    """The trace file ``path`` in chunks of at most ``rows`` rows (a CSV: in one)."""
    p = Path(path)
    if p.suffix != '.parquet':
        yield read_trace(p)
        return
    import pyarrow.parquet as pq

    meta, _ = trace_meta(p)
    try:
        f = pq.ParquetFile(str(p))
        for batch in f.iter_batches(batch_size=rows):
            table = np.column_stack([batch.column(i).to_numpy(zero_copy_only=False).astype(float)
                                     for i in range(batch.num_columns)])
            yield _from_table(meta, batch.schema.names, table)
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError(f'{p}: cannot read trace ({exc})') from None


def read_trace(path: str | Path) -> Trace:
    """The whole trace file ``path`` (``.parquet`` or ``.csv``, see module doc)."""
    p = Path(path)
    if p.suffix == '.parquet':
        chunks = list(iter_trace(p))
        return Trace.concat(chunks) if chunks else empty_trace(trace_meta(p)[0])
    try:
        with p.open(encoding='utf-8') as f:
            first = f.readline()
            if not first.startswith('# {'):
                raise ConfigError(f'{p}: not a haptic_topology trace (no metadata line)')
            meta = json.loads(first[2:])
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f'{p}: cannot read trace ({exc})') from None
    if not rows:
        raise ConfigError(f'{p}: trace has no header row')
    header, body = rows[0], rows[1:]
    table = np.array(body, dtype=float) if body else np.zeros((0, len(header)))
    return _from_table(meta, header, table)
