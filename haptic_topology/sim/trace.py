"""Run traces (one row per device cycle) and the drift summary of a run.

A trace is what both the offline simulation and a recorded bag reduce to: device pose/twist,
hand wrench, command, the VT hand pose in the VE, the LMI's VT hand pose, joint positions and
constraint counts. It is written as CSV with a one-line JSON comment header (metadata). The
VE's constraint count ``constraint_count`` (``t`` of eq. 18) is the one its LMI updates report,
held until the next (:meth:`Trace.hold_constraint_counts`), in the offline simulation as in a
recorded run; ``lmi_constraint_count`` is the controller's at every cycle.

Drift (the paper's Fig. 6 / Fig. 8 measure): the translational distance (m) between the
device and the VT's grasp point in the VE at the same instant.

A run with obstacles (``meta['contacts']``) has three more columns: ``env_wrench`` (``F_env``
of eqs. 10 and 14 as the controller rendered it, m entries, every cycle), ``penetration`` (m,
the deepest contact of the VE's linkage, 0 when none) and ``contact_energy`` (J, the contacts'
work on the VT plus their elastic energy minus at the start, see
:mod:`haptic_topology.dynamics.contacts`). The last two are what the VE reports with each LMI
update (:func:`contact_depth`), held until the next one (:meth:`Trace.hold_contacts`), in the
offline simulation as in a recorded run, so both summaries sample contact alike.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.errors import ConfigError

_VECTORS = ('device_pose', 'device_twist', 'hand_wrench', 'command', 'applied', 'vt_pose',
            'lmi_pose')
_SCALARS = ('constraint_count', 'lmi_constraint_count', 'status')
_CONTACT_FLOATS = ('penetration', 'contact_energy')


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
        meta = dict(meta, task_dim=m, dof=dof)
        if contacts:
            meta['contacts'] = True
        return cls(np.zeros(n), np.arange(n), cols, meta)

    @property
    def has_contacts(self) -> bool:
        return bool(self.meta.get('contacts'))

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

    def distance(self) -> np.ndarray:
        """Device - VT hand distance, translational part (m), per row."""
        rows = slice(0, 2) if self.task_dim == 3 else slice(0, 3)
        diff = self.columns['device_pose'][:, rows] - self.columns['vt_pose'][:, rows]
        return np.linalg.norm(diff, axis=1)

    def summary(self) -> dict[str, Any]:
        """Drift figures of the run (the keys ``simulate`` and ``analyze`` both print)."""
        dist = self.distance()
        ok = np.isfinite(dist)
        dist = dist[ok]
        if dist.size == 0:
            raise ValueError('trace has no row with both a device and a VT hand pose')
        t = self.t[ok]
        dt = float(np.median(np.diff(t))) if t.size > 1 else float(self.meta.get('dt', 0.0))
        counts = self.columns['constraint_count'][ok]
        status = self.columns['status'][ok]
        applied = self.columns['applied'][ok]
        at_limit = np.nonzero(status & 1)[0]
        return {
            'scenario': self.meta.get('scenario', ''),
            'mode': self.meta.get('mode', ''),
            'duration_s': float(t[-1] - t[0]),
            'samples': int(dist.size),
            'final_distance_m': float(dist[-1]),
            'max_distance_m': float(dist.max()),
            'rms_distance_m': float(math.sqrt(float(np.mean(dist * dist)))),
            'constrained_time_s': float(np.count_nonzero(counts > 0) * dt),
            'workspace_limit_time_s': float(np.count_nonzero(status & 1) * dt),
            # When the device first reported a workspace stop (s from the first row), or None.
            'first_limit_s': float(t[at_limit[0]] - t[0]) if at_limit.size else None,
            'max_abs_wrench': float(np.nanmax(np.abs(applied))) if applied.size else 0.0,
            **self._contact_summary(ok, dt),
        }

    def _contact_summary(self, ok: np.ndarray, dt: float) -> dict[str, Any]:
        """Penetration max/RMS (over the rows in contact), time in contact and the energy the
        contact model injected (the largest positive contact energy balance; J); None for a
        run without obstacles."""
        keys = ('max_penetration_m', 'rms_penetration_m', 'contact_time_s',
                'energy_injected_j', 'energy_dissipated_j')
        if not self.has_contacts:
            return dict.fromkeys(keys)
        depth = self.columns['penetration'][ok]
        depth = depth[np.isfinite(depth)]
        inside = depth[depth > 0.0]
        energy = self.columns['contact_energy'][ok]
        energy = energy[np.isfinite(energy)]
        return dict(zip(keys, (
            float(depth.max()) if depth.size else 0.0,
            float(math.sqrt(float(np.mean(inside * inside)))) if inside.size else 0.0,
            float(inside.size * dt),
            max(0.0, float(energy.max())) if energy.size else 0.0,
            max(0.0, -float(energy[-1])) if energy.size else 0.0), strict=True))

    # -- CSV ---------------------------------------------------------------------------------
    def header(self) -> list[str]:
        m = self.task_dim
        names = ['t', 'seq']
        for name in _VECTORS:
            names += [f'{name}_{i}' for i in range(m)]
        names += [f'q_{i}' for i in range(int(self.meta['dof']))]
        names += list(_SCALARS)
        if self.has_contacts:
            names += [f'env_wrench_{i}' for i in range(m)] + list(_CONTACT_FLOATS)
        return names

    def to_csv(self, path: str | Path) -> None:
        with Path(path).open('w', newline='', encoding='utf-8') as f:
            f.write('# ' + json.dumps(self.meta) + '\n')
            w = csv.writer(f)
            w.writerow(self.header())
            blocks = [self.t[:, None], self.seq[:, None]]
            blocks += [self.columns[n] for n in _VECTORS]
            blocks += [self.columns['q']]
            blocks += [self.columns[n][:, None] for n in _SCALARS]
            first_scalar = sum(b.shape[1] for b in blocks) - len(_SCALARS)
            end_scalar = first_scalar + len(_SCALARS)
            if self.has_contacts:
                blocks += [self.columns['env_wrench']]
                blocks += [self.columns[n][:, None] for n in _CONTACT_FLOATS]
            table = np.hstack([b.astype(float) for b in blocks])
            for row in table:
                w.writerow([int(v) if (i == 1 or first_scalar <= i < end_scalar)
                            else repr(float(v)) for i, v in enumerate(row)])

    @classmethod
    def from_csv(cls, path: str | Path) -> Trace:
        p = Path(path)
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
        m, dof = int(meta.pop('task_dim')), int(meta.pop('dof'))
        contacts = bool(meta.pop('contacts', False))
        trace = cls.empty(len(body), m, dof, contacts, **meta)
        col = {name: i for i, name in enumerate(header)}
        trace.t = table[:, col['t']]
        trace.seq = table[:, col['seq']].astype(int)
        for name in _VECTORS:
            trace.columns[name] = table[:, [col[f'{name}_{i}'] for i in range(m)]]
        trace.columns['q'] = table[:, [col[f'q_{i}'] for i in range(dof)]]
        for name in _SCALARS:
            trace.columns[name] = table[:, col[name]].astype(int)
        if contacts:
            trace.columns['env_wrench'] = table[:, [col[f'env_wrench_{i}'] for i in range(m)]]
            for name in _CONTACT_FLOATS:
                trace.columns[name] = table[:, col[name]]
        return trace


def format_summary(rows: list[dict[str, Any]]) -> str:
    """A fixed-width table of summaries (one row per run)."""
    cols = [('scenario', 'scenario', '{}'), ('mode', 'mode', '{}'),
            ('final_distance_m', 'final [mm]', '{:.3f}'), ('max_distance_m', 'max [mm]',
                                                           '{:.3f}'),
            ('rms_distance_m', 'rms [mm]', '{:.3f}'),
            ('constrained_time_s', 'constrained [s]', '{:.3f}'),
            ('workspace_limit_time_s', 'at limit [s]', '{:.3f}'),
            ('first_limit_s', 'first at limit [s]', '{:.3f}')]
    cells = [[title for _, title, _ in cols]]
    for r in rows:
        line = []
        for key, _, fmt in cols:
            v = r.get(key, '')
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
