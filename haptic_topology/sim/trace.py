"""Run traces (one row per device cycle) and the drift summary of a run.

A trace is what both the offline simulation and a recorded bag reduce to: device pose/twist,
hand wrench, command, the VT hand pose in the VE, the LMI's VT hand pose, joint positions and
constraint counts. It is written as CSV with a one-line JSON comment header (metadata).

Drift (the paper's Fig. 6 / Fig. 8 measure): the translational distance (m) between the
device and the VT's grasp point in the VE at the same instant.
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


@dataclass
class Trace:
    """Columns of a run; ``meta`` holds mode, scenario, dt and task dimension."""

    t: np.ndarray
    seq: np.ndarray
    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def empty(cls, n: int, m: int, dof: int, **meta: Any) -> Trace:
        cols: dict[str, np.ndarray] = {name: np.full((n, m), np.nan) for name in _VECTORS}
        cols['q'] = np.full((n, dof), np.nan)
        for name in _SCALARS:
            cols[name] = np.zeros(n, dtype=int)
        meta = dict(meta, task_dim=m, dof=dof)
        return cls(np.zeros(n), np.arange(n), cols, meta)

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
        }

    # -- CSV ---------------------------------------------------------------------------------
    def header(self) -> list[str]:
        m = self.task_dim
        names = ['t', 'seq']
        for name in _VECTORS:
            names += [f'{name}_{i}' for i in range(m)]
        names += [f'q_{i}' for i in range(int(self.meta['dof']))]
        names += list(_SCALARS)
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
            table = np.hstack([b.astype(float) for b in blocks])
            ints = {0: False, 1: True}
            first_scalar = table.shape[1] - len(_SCALARS)
            for row in table:
                w.writerow([int(v) if (ints.get(i) or i >= first_scalar) else repr(float(v))
                            for i, v in enumerate(row)])

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
        trace = cls.empty(len(body), m, dof, **meta)
        col = {name: i for i, name in enumerate(header)}
        trace.t = table[:, col['t']]
        trace.seq = table[:, col['seq']].astype(int)
        for name in _VECTORS:
            trace.columns[name] = table[:, [col[f'{name}_{i}'] for i in range(m)]]
        trace.columns['q'] = table[:, [col[f'q_{i}'] for i in range(dof)]]
        for name in _SCALARS:
            trace.columns[name] = table[:, col[name]].astype(int)
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
