"""Run traces (one row per device cycle) and the drift summary of a run.

A trace is what both the offline simulation and a recorded bag reduce to: device pose/twist,
hand wrench, command, the VT hand pose in the VE, the LMI's VT hand pose, joint positions and
constraint counts. It is written as CSV with a one-line JSON comment header (metadata). The
VE's constraint count ``constraint_count`` (``t`` of eq. 18) is the one its LMI updates report,
held until the next (:meth:`Trace.hold_constraint_counts`), in the offline simulation as in a
recorded run; ``lmi_constraint_count`` is the controller's at every cycle.

Drift (the paper's Fig. 6 / Fig. 8 measure): the translational distance (m) between the
device and the VT's grasp point in the VE at the same instant.

The task (``meta['task']``, a :class:`~haptic_topology.vocabulary.TaskSpace` value) says
which entries of the m-vectors are translations: x, y of ``planar`` (m = 3) and
``planar_point`` (m = 2), x, y, z of ``spatial`` (m = 6) and ``spatial_point`` (m = 3).
Traces written before point grasps existed carry no task: theirs is the rigid task of their
dimension (3 planar, 6 spatial).

A run with obstacles (``meta['contacts']``) has three more columns: ``env_wrench`` (``F_env``
of eqs. 10 and 14 as the controller rendered it, m entries, every cycle), ``penetration`` (m,
the deepest contact of the VE's linkage, 0 when none) and ``contact_energy`` (J, the contacts'
work on the VT plus their elastic energy minus at the start, see
:mod:`haptic_topology.dynamics.contacts`). The last two are what the VE reports with each LMI
update (:func:`contact_depth`), held until the next one (:meth:`Trace.hold_contacts`), in the
offline simulation as in a recorded run, so both summaries sample contact alike.

A run of a scenario on another linkage than its own (``simulate --linkage``) has the
linkage's file in ``meta['linkage_file']`` (absolute path; a linkage of no file: its name),
and its plots are titled ``<scenario> on <file name>`` (:func:`run_name`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.vocabulary import TaskSpace

#: Columns of m entries per row (m: the task dimension), of single integers, and of single
#: floats of a run with contacts; ``q`` has ``dof`` entries per row.
VECTORS = ('device_pose', 'device_twist', 'hand_wrench', 'command', 'applied', 'vt_pose',
           'lmi_pose')
SCALARS = ('constraint_count', 'lmi_constraint_count', 'status')
CONTACT_FLOATS = ('penetration', 'contact_energy')
#: Single floats of a run that carries its controller's energy account (``meta['energy']``,
#: :mod:`haptic_topology.control.passivity`): the work the controller put into the device
#: port (J), the passivity observer (J) and the passivity controller's damping (N s/m), each
#: after the row's state.
ENERGY_FLOATS = ('port_work', 'passivity_observer', 'passivity_damping')
_VECTORS, _SCALARS, _CONTACT_FLOATS = VECTORS, SCALARS, CONTACT_FLOATS


def run_name(scenario: str, linkage_file: str = '') -> str:
    """What a plot's title calls a run: the scenario's name, and ``on <file name>`` when it
    ran on the linkage ``linkage_file`` in place of its own (e.g. ``fig8 on my_arm.urdf``)."""
    return f'{scenario} on {Path(linkage_file).name}' if linkage_file else scenario


def contact_depth(gaps: np.ndarray) -> float:
    """The deepest penetration (m, >= 0) among contact ``gaps`` (m; none: 0)."""
    gaps = np.asarray(gaps, dtype=float)
    return max(0.0, -float(gaps.min())) if gaps.size else 0.0


@dataclass
class Trace:
    """Columns of a run; ``meta`` holds mode, scenario, dt and task dimension."""

    t: np.ndarray
    seq: np.ndarray
    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def empty(cls, n: int, m: int, dof: int, contacts: bool = False, **meta: Any) -> Trace:
        cols: dict[str, np.ndarray] = {name: np.full((n, m), np.nan) for name in _VECTORS}
        cols['q'] = np.full((n, dof), np.nan)
        for name in _SCALARS:
            cols[name] = np.zeros(n, dtype=int)
        if contacts:
            cols['env_wrench'] = np.full((n, m), np.nan)
            for name in _CONTACT_FLOATS:
                cols[name] = np.full(n, np.nan)
        if meta.get('energy'):
            for name in ENERGY_FLOATS:
                cols[name] = np.full(n, np.nan)
        meta = dict(meta, task_dim=m, dof=dof)
        if contacts:
            meta['contacts'] = True
        return cls(np.zeros(n), np.arange(n), cols, meta)

    @property
    def has_contacts(self) -> bool:
        return bool(self.meta.get('contacts'))

    @property
    def has_energy(self) -> bool:
        """Whether the trace carries the controller's energy account (:data:`ENERGY_FLOATS`)."""
        return bool(self.meta.get('energy'))

    def record_env_wrench(self, k: int, env_wrench: np.ndarray | None) -> None:
        """Row ``k``'s ``F_env`` as the controller rendered it (None: zero)."""
        self.columns['env_wrench'][k] = 0.0 if env_wrench is None else env_wrench

    def hold_contacts(self, rows: np.ndarray, depth: np.ndarray | list[float],
                      energy: np.ndarray | list[float]) -> None:
        """The VE's deepest contact (m) and contact energy balance (J) as its LMI updates
        report them: update ``i`` describes row ``rows[i]`` (ascending) and holds until the
        next one; NaN before the first and after the last. The offline simulation and a
        recorded run sample them alike, at the VE's update rate."""
        rows = np.asarray(rows, dtype=int)
        if rows.size == 0:
            self.columns['penetration'][:] = self.columns['contact_energy'][:] = np.nan
            return
        at, held = self._held_updates(rows)
        held &= np.arange(len(self)) <= rows[-1]
        self.columns['penetration'][:] = np.where(held, np.asarray(depth)[at], np.nan)
        self.columns['contact_energy'][:] = np.where(held, np.asarray(energy)[at], np.nan)

    def hold_constraint_counts(self, rows: np.ndarray | list[int],
                               counts: np.ndarray | list[int]) -> None:
        """The VE's constraint count as its LMI updates report it: update ``i`` describes
        row ``rows[i]`` (ascending) and holds until the next one (after the last too); 0
        before the first."""
        rows = np.asarray(rows, dtype=int)
        col = self.columns['constraint_count']
        if rows.size == 0:
            col[:] = 0
            return
        at, held = self._held_updates(rows)
        col[:] = np.where(held, np.asarray(counts)[at], 0)

    def _held_updates(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each row of the trace, the index of the newest update at or before it (update
        ``i`` describes row ``rows[i]``, ascending; 0 before the first) and whether there is
        one."""
        idx = np.searchsorted(rows, np.arange(len(self)), side='right') - 1
        return np.maximum(idx, 0), idx >= 0

    def record(self, k: int, t: float, **values: Any) -> None:
        self.t[k] = t
        self.seq[k] = k
        for name, value in values.items():
            self.columns[name][k] = value

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def task_dim(self) -> int:
        return int(self.meta['task_dim'])

    @property
    def task(self) -> TaskSpace:
        """The run's task (module doc): ``meta['task']``, else the rigid task of the trace's
        dimension (``planar_point`` for m = 2, the only task of that size)."""
        name = self.meta.get('task')
        if name is not None:
            return TaskSpace(name)
        m = self.task_dim
        return TaskSpace.PLANAR_POINT if m == TaskSpace.PLANAR_POINT.dim else TaskSpace.for_dim(m)

    def distance(self) -> np.ndarray:
        """Device - VT hand distance, translational part (m), per row."""
        rows = self.task.translation_rows
        diff = self.columns['device_pose'][:, rows] - self.columns['vt_pose'][:, rows]
        return np.linalg.norm(diff, axis=1)

    def summary(self) -> dict[str, Any]:
        """Drift figures of the run (the keys ``simulate`` and ``analyze`` both print; see
        :class:`SummaryStats`, which computes them chunk by chunk)."""
        stats = SummaryStats()
        stats.add(self)
        return stats.result(self.meta)

    def take(self, rows: np.ndarray | slice) -> Trace:
        """The rows ``rows`` (indices or a slice) as a trace of their own (same metadata)."""
        return Trace(self.t[rows], self.seq[rows],
                     {name: col[rows] for name, col in self.columns.items()}, dict(self.meta))

    @classmethod
    def concat(cls, chunks: list[Trace]) -> Trace:
        """The rows of ``chunks`` (same metadata and columns) one after the other."""
        first = chunks[0]
        return cls(np.concatenate([c.t for c in chunks]),
                   np.concatenate([c.seq for c in chunks]),
                   {name: np.concatenate([c.columns[name] for c in chunks])
                    for name in first.columns}, dict(first.meta))

    # -- files (haptic_topology.sim.trace_io) -------------------------------------------------
    def header(self) -> list[str]:
        """The column names of a trace file."""
        m = self.task_dim
        names = ['t', 'seq']
        for name in _VECTORS:
            names += [f'{name}_{i}' for i in range(m)]
        names += [f'q_{i}' for i in range(int(self.meta['dof']))]
        names += list(_SCALARS)
        if self.has_contacts:
            names += [f'env_wrench_{i}' for i in range(m)] + list(_CONTACT_FLOATS)
        if self.has_energy:
            names += list(ENERGY_FLOATS)
        return names

    def to_csv(self, path: str | Path) -> None:
        """Write the trace as CSV (:mod:`haptic_topology.sim.trace_io`)."""
        from haptic_topology.sim.trace_io import write_trace

        write_trace(self, path, 'csv')

    def to_parquet(self, path: str | Path) -> None:
        """Write the trace as Parquet (:mod:`haptic_topology.sim.trace_io`)."""
        from haptic_topology.sim.trace_io import write_trace

        write_trace(self, path, 'parquet')

    @classmethod
    def from_csv(cls, path: str | Path) -> Trace:
        """Read a trace file: Parquet if its name ends in ``.parquet``, else CSV
        (:func:`haptic_topology.sim.trace_io.read_trace`)."""
        from haptic_topology.sim.trace_io import read_trace

        return read_trace(path)


class SummaryStats:
    """The drift figures of :meth:`Trace.summary`, from the rows given chunk by chunk
    (:meth:`add`, in order): running counts and extremes, and the distances and times of the
    rows with both poses (16 bytes a row; the median period and the RMS need all of them),
    so that the figures are those of the whole trace, to the last bit.

    Rows counted: those with both a device and a VT hand pose (finite distance). ``dt`` is
    the median time step between them; the constrained time, the time at the workspace limit
    (status bit 0) and the contact time count rows times ``dt``."""

    def __init__(self) -> None:
        self.t: list[np.ndarray] = []
        self.dist: list[np.ndarray] = []
        self.constrained = 0
        self.at_limit = 0
        self.first_limit: float | None = None
        self.wrench_rows = 0
        self.max_wrench = math.nan
        self.contacts = False
        self.max_depth: float | None = None
        self.inside: list[np.ndarray] = []
        self.max_energy: float | None = None
        self.last_energy: float | None = None
        self._t_last = math.nan               # the previous chunk's last time (s)
        self.port_work: np.ndarray | None = None
        self.hand_work = 0.0
        self.observer_min = math.inf
        self.observer_last = math.nan
        self.pc_rows = 0
        self.pc_first: float | None = None

    def _add_energy(self, chunk: Trace) -> None:
        """The trace's work integral: row k's ``applied`` (held over the period that ends at
        row k) times its twist and period, ``sum u v dT`` (J), per axis; the hand's likewise;
        with the controller's account (``has_energy``) its observer and controller."""
        t = np.concatenate([[self._t_last], chunk.t])
        dt = np.diff(t)
        if chunk.t.size:
            self._t_last = float(chunk.t[-1])
        v = chunk.columns['device_twist']
        power = chunk.columns['applied'] * v
        ok = np.isfinite(dt) & np.all(np.isfinite(power), axis=1)
        work = (power[ok] * dt[ok, None]).sum(axis=0)
        self.port_work = work if self.port_work is None else self.port_work + work
        hand = chunk.columns['hand_wrench'] * v
        okh = np.isfinite(dt) & np.all(np.isfinite(hand), axis=1)
        self.hand_work += float((hand[okh] * dt[okh, None]).sum())
        if not chunk.has_energy:
            return
        obs = chunk.columns['passivity_observer']
        known = obs[np.isfinite(obs)]
        if known.size:
            self.observer_min = min(self.observer_min, float(known.min()))
            self.observer_last = float(known[-1])
        acted = np.nonzero(chunk.columns['passivity_damping'] > 0.0)[0]
        self.pc_rows += int(acted.size)
        if self.pc_first is None and acted.size:
            self.pc_first = float(chunk.t[acted[0]])

    def energy_result(self, t0: float) -> dict[str, Any]:
        """The energy figures (J; times s from ``t0``) of :meth:`result`."""
        axis = self.port_work if self.port_work is not None else np.zeros(0)
        out: dict[str, Any] = {'port_work_j': float(axis.sum()),
                               'port_work_axis_j': [float(w) for w in axis],
                               'hand_work_j': self.hand_work}
        if math.isfinite(self.observer_min):
            out.update({'passivity_observer_min_j': self.observer_min,
                        'passivity_observer_final_j': self.observer_last,
                        'passivity_rows': self.pc_rows,
                        'passivity_first_s': (None if self.pc_first is None
                                              else self.pc_first - t0)})
        return out

    def add(self, chunk: Trace) -> None:
        """The next rows of the trace."""
        self._add_energy(chunk)
        dist = chunk.distance()
        ok = np.isfinite(dist)
        self.dist.append(dist[ok])
        t = chunk.t[ok]
        self.t.append(t)
        self.constrained += int(np.count_nonzero(chunk.columns['constraint_count'][ok] > 0))
        limit = np.nonzero(chunk.columns['status'][ok] & 1)[0]
        self.at_limit += int(limit.size)
        if self.first_limit is None and limit.size:
            self.first_limit = float(t[limit[0]])
        applied = np.abs(chunk.columns['applied'][ok])
        self.wrench_rows += int(applied.size)
        known = applied[~np.isnan(applied)]
        if known.size:
            top = float(known.max())
            self.max_wrench = top if math.isnan(self.max_wrench) else max(self.max_wrench, top)
        if not chunk.has_contacts:
            return
        self.contacts = True
        depth = chunk.columns['penetration'][ok]
        depth = depth[np.isfinite(depth)]
        if depth.size:
            top = float(depth.max())
            self.max_depth = top if self.max_depth is None else max(self.max_depth, top)
        self.inside.append(depth[depth > 0.0])
        energy = chunk.columns['contact_energy'][ok]
        energy = energy[np.isfinite(energy)]
        if energy.size:
            top = float(energy.max())
            self.max_energy = top if self.max_energy is None else max(self.max_energy, top)
            self.last_energy = float(energy[-1])

    def result(self, meta: dict[str, Any]) -> dict[str, Any]:
        """The figures (keys of :meth:`Trace.summary`); ``meta``: the trace's metadata.
        Raises ValueError when no row has both poses."""
        dist = np.concatenate(self.dist) if self.dist else np.zeros(0)
        if dist.size == 0:
            raise ValueError('trace has no row with both a device and a VT hand pose')
        t = np.concatenate(self.t)
        dt = float(np.median(np.diff(t))) if t.size > 1 else float(meta.get('dt', 0.0))
        out = {
            'scenario': meta.get('scenario', ''),
            'mode': meta.get('mode', ''),
            'duration_s': float(t[-1] - t[0]),
            'samples': int(dist.size),
            'final_distance_m': float(dist[-1]),
            'max_distance_m': float(dist.max()),
            'rms_distance_m': float(math.sqrt(float(np.mean(dist * dist)))),
            'constrained_time_s': float(self.constrained * dt),
            'workspace_limit_time_s': float(self.at_limit * dt),
            # When the device first reported a workspace stop (s from the first row), or None.
            'first_limit_s': (float(self.first_limit - t[0]) if self.first_limit is not None
                              else None),
            'max_abs_wrench': self.max_wrench if self.wrench_rows else 0.0,
            **self.energy_result(float(t[0])),
        }
        if 'energy_account' in meta:        # the controller's own account (simulate)
            out['energy_account'] = meta['energy_account']
        keys = ('max_penetration_m', 'rms_penetration_m', 'contact_time_s',
                'energy_injected_j', 'energy_dissipated_j')
        if not (self.contacts or meta.get('contacts')):
            return dict(out, **dict.fromkeys(keys))
        # Penetration max/RMS (over the rows in contact), time in contact and the energy the
        # contact model injected (the largest positive contact energy balance; J).
        inside = np.concatenate(self.inside) if self.inside else np.zeros(0)
        return dict(out, **dict(zip(keys, (
            self.max_depth if self.max_depth is not None else 0.0,
            float(math.sqrt(float(np.mean(inside * inside)))) if inside.size else 0.0,
            float(inside.size * dt),
            max(0.0, self.max_energy) if self.max_energy is not None else 0.0,
            max(0.0, -self.last_energy) if self.last_energy is not None else 0.0),
            strict=True)))


#: The contact columns of :func:`format_summary`: in a table with a run with obstacles only.
CONTACT_COLUMNS = (('max_penetration_m', 'max penetration [mm]', '{:.3f}'),
                   ('contact_time_s', 'in contact [s]', '{:.3f}'))


def format_summary(rows: list[dict[str, Any]]) -> str:
    """A fixed-width table of summaries (one row per run): the drift columns, and when a
    run of the table has obstacles (its ``max_penetration_m`` is not None) the deepest
    penetration and the time in contact (:data:`CONTACT_COLUMNS`; ``-`` for a run without)."""
    cols = [('scenario', 'scenario', '{}'), ('mode', 'mode', '{}'),
            ('final_distance_m', 'final [mm]', '{:.3f}'), ('max_distance_m', 'max [mm]',
                                                           '{:.3f}'),
            ('rms_distance_m', 'rms [mm]', '{:.3f}'),
            ('constrained_time_s', 'constrained [s]', '{:.3f}'),
            ('workspace_limit_time_s', 'at limit [s]', '{:.3f}'),
            ('first_limit_s', 'first at limit [s]', '{:.3f}')]
    if any(r.get('max_penetration_m') is not None for r in rows):
        cols += CONTACT_COLUMNS
    cells = [[title for _, title, _ in cols]]
    contact = {key for key, _, _ in CONTACT_COLUMNS}
    for r in rows:
        line = []
        for key, _, fmt in cols:
            v = r.get(key, None if key in contact else '')
            if key.endswith('_m') and isinstance(v, float):
                v = v * 1000.0
            line.append('-' if v is None else fmt.format(v) if v != '' else '')
        cells.append(line)
    widths = [max(len(c[i]) for c in cells) for i in range(len(cols))]
    out = []
    for i, c in enumerate(cells):
        out.append('  '.join(s.rjust(widths[j]) if j > 1 else s.ljust(widths[j])
                             for j, s in enumerate(c)))
        if i == 0:
            out.append('  '.join('-' * wd for wd in widths))
    return '\n'.join(out)


#: The columns of :func:`format_energy`: summary key, title, scale, format.
ENERGY_COLUMNS = (('port_work_j', 'port work [mJ]', 1e3, '{:.3f}'),
                  ('hand_work_j', 'hand work [mJ]', 1e3, '{:.3f}'),
                  ('passivity_observer_min_j', 'observer min [mJ]', 1e3, '{:.3f}'),
                  ('passivity_observer_final_j', 'observer end [mJ]', 1e3, '{:.3f}'),
                  ('passivity_rows', 'passivity ctrl [cycles]', 1.0, '{:.0f}'))


def format_energy(rows: list[tuple[str, dict[str, Any]]]) -> str:
    """The energy table of summaries, one row per ``(label, summary)``: the trace's work
    integral at the device port and the hand's (J shown as mJ), and, for a run that carries
    its controller's account (``simulate``), the passivity observer's lowest and last value
    and the cycles the passivity controller acted (``-`` for a run without)."""
    cells = [['run'] + [c[1] for c in ENERGY_COLUMNS]]
    for label, r in rows:
        line = [label]
        for key, _, scale, fmt in ENERGY_COLUMNS:
            v = r.get(key)
            line.append('-' if v is None else fmt.format(scale * v))
        cells.append(line)
    widths = [max(len(c[i]) for c in cells) for i in range(len(cells[0]))]
    out = []
    for i, c in enumerate(cells):
        out.append('  '.join(s.ljust(widths[j]) if j == 0 else s.rjust(widths[j])
                             for j, s in enumerate(c)))
        if i == 0:
            out.append('  '.join('-' * w for w in widths))
    return '\n'.join(out)
