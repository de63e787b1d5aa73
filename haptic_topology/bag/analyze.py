"""``haptic-topology analyze INPUT... --out DIR``: drift and loop health of recorded runs.

Each INPUT is a bag of the node graph (a rosbag2 directory or ``.mcap`` file, read with
:func:`~haptic_topology.bag.graph_trace.read_graph_bag`, truncated ones too), or a trace of
the offline simulation (a ``trace.csv`` or a ``simulate --out`` directory). For each it
prints one row of the drift table (the columns of ``simulate``: final, max and RMS distance
between the device and the VT grasp point, time constrained, time at the workspace limit)
and one row of loop health (bags only: fraction of states answered before the next one,
from the bag and from the device driver's diagnostics; round trip p50/p99; the device's
period p50/p99 and its standard deviation, from the state stamps). It writes into DIR:

* ``<label>.png``: the Fig. 6 / Fig. 8 style figure of each input (linkage, hand paths,
  drift, constraints; the linkage comes from the scenario named in the run);
* ``comparison.png`` with two or more inputs: the drift of each over time;
* ``summary.json``: ``{"runs": [...]}``, one object per input with the drift fields of
  ``simulate`` (``final_distance_m``, ``max_distance_m``, ``rms_distance_m``,
  ``constrained_time_s``, ...), ``label``, ``input``, ``source`` (graph/simulate) and, for
  bags, the loop figures and ``skipped_messages``: the foreign or malformed messages on the
  graph's topics that were left out, per ``<kind>_<reason>`` (see
  :mod:`haptic_topology.bag.graph_trace`); the trace, plot and summary are written anyway.

Reading a large bag shows a progress line on stderr (when stderr is a terminal, or the bag
is larger than 20 MB).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bag.reader import METADATA
from haptic_topology.errors import BagError, ConfigError
from haptic_topology.sim.trace import Trace

BIG_BAG_BYTES = 20_000_000


@dataclass
class Run:
    """One analysed input."""

    label: str
    path: Path
    trace: Trace
    loop: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    #: A bag's graph (its recorder's ``graph_id``) and the messages of other graphs per topic
    graph_id: str | None = None
    foreign_messages: dict[str, int] = field(default_factory=dict)
    foreign_publishers: dict[str, list[str]] = field(default_factory=dict)


class _ProgressLine:
    """``reading X: 40 %`` on stderr, rewritten in place on a terminal, every 10 %."""

    def __init__(self, name: str, size: int) -> None:
        self.name = name
        self.tty = sys.stderr.isatty()
        self.enabled = self.tty or size > BIG_BAG_BYTES
        self.last = -1

    def __call__(self, fraction: float) -> None:
        if not self.enabled:
            return
        step = int(min(max(fraction, 0.0), 1.0) * 10)
        if step == self.last:
            return
        self.last = step
        end = '\r' if self.tty and step < 10 else '\n'
        print(f'reading {self.name}: {step * 10:3d} %', end=end, file=sys.stderr, flush=True)


def _is_bag(p: Path) -> bool:
    return (p.is_file() and p.suffix == '.mcap') or (p.is_dir() and (
        (p / METADATA).is_file() or any(p.glob('*.mcap'))))


def _scenario_of_bag(p: Path) -> str:
    from haptic_topology.bag.reader import open_bag

    bag = open_bag(p)
    custom = (bag.metadata or {}).get('custom_data') or {}
    return str(custom.get('scenario', '')) if isinstance(custom, dict) else ''


def load_run(path: str | Path) -> Run:
    """Read one input (see module doc)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f'{p}: no such file or directory')
    if _is_bag(p):
        scenario = _scenario_of_bag(p)
        name = Path(scenario).stem if scenario else ''
        dof = task_dim = None
        if scenario:
            try:
                from haptic_topology.sim.scenario import load_scenario

                sc = load_scenario(scenario)
                dof, task_dim, name = sc.lmi_dof, sc.linkage.task.dim, sc.name
            except ConfigError:
                pass
        size = sum(f.stat().st_size for f in ([p] if p.is_file() else p.glob('*.mcap')))
        result = read_graph_bag(p, name, dof, progress=_ProgressLine(p.name, size),
                                task_dim=task_dim)
        loop = dict(result.loop)
        loop.update(_period_figures(result.trace))
        if scenario:
            result.trace.meta.setdefault('scenario_ref', scenario)
        return Run(p.name if p.is_dir() else p.stem, p, result.trace, loop,
                   dict(result.skipped), result.graph_id, dict(result.foreign_messages),
                   dict(result.foreign_publishers))
    csv_path = p / 'trace.csv' if p.is_dir() else p
    if not csv_path.is_file():
        raise BagError(f'{p}: not a bag (no {METADATA} and no .mcap file) and no trace.csv')
    trace = Trace.from_csv(csv_path)
    label = csv_path.parent.name if csv_path.name == 'trace.csv' else csv_path.stem
    return Run(label, p, trace, _period_figures(trace))


def _period_figures(trace: Trace) -> dict[str, float]:
    """Device period p50/p99/std (ms) from the row times (state stamps for a bag)."""
    if len(trace) < 3:
        return {}
    seq = np.asarray(trace.seq)
    consecutive = np.diff(seq) == 1
    periods = np.diff(trace.t)[consecutive] * 1e3
    if periods.size == 0:
        return {}
    return {'bag_period_p50_ms': float(np.percentile(periods, 50)),
            'bag_period_p99_ms': float(np.percentile(periods, 99)),
            'bag_period_std_ms': float(np.std(periods)),
            'bag_missing_states': float(int(seq[-1] - seq[0] + 1) - len(seq))}


def _linkage_of(run: Run) -> Any:
    ref = run.trace.meta.get('scenario_ref') or run.trace.meta.get('scenario')
    if not ref:
        return None
    try:
        from haptic_topology.sim.scenario import load_scenario

        return load_scenario(str(ref)).linkage
    except ConfigError:
        return None


def format_loop_health(runs: list[tuple[str, dict[str, Any]]]) -> str:
    """Loop health table, one row per ``(label, figures)`` (a trace of ``simulate`` has
    periods only)."""
    cols = [('bag_answered_fraction', 'answered, bag [%]', 100.0, '{:.2f}'),
            ('device_answered_fraction', 'answered, device [%]', 100.0, '{:.2f}'),
            ('device_round_trip_p50_ms', 'rtt p50 [ms]', 1.0, '{:.3f}'),
            ('device_round_trip_p99_ms', 'rtt p99 [ms]', 1.0, '{:.3f}'),
            ('bag_period_p50_ms', 'period p50 [ms]', 1.0, '{:.3f}'),
            ('bag_period_p99_ms', 'period p99 [ms]', 1.0, '{:.3f}'),
            ('bag_period_std_ms', 'period std [ms]', 1.0, '{:.3f}'),
            ('bag_missing_states', 'missing states', 1.0, '{:.0f}')]
    cells = [['run'] + [c[1] for c in cols]]
    for label, figures in runs:
        row = [label]
        for key, _, scale, fmt in cols:
            v = figures.get(key)
            ok = isinstance(v, (int, float)) and math.isfinite(v)
            row.append(fmt.format(float(v) * scale) if ok else '-')  # type: ignore[arg-type]
        cells.append(row)
    widths = [max(len(c[i]) for c in cells) for i in range(len(cells[0]))]
    lines = ['  '.join(c.ljust(widths[i]) if i == 0 else c.rjust(widths[i])
                       for i, c in enumerate(row)) for row in cells]
    lines.insert(1, '  '.join('-' * w for w in widths))
    return '\n'.join(lines)


def plot_comparison(runs: list[Run], path: Path) -> Path:
    """Drift over time of each run in one figure (PNG)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 5))
    for r in runs:
        ax.plot(r.trace.t, r.trace.distance() * 1000.0, lw=1.5,
                label=f'{r.label} ({r.trace.meta.get("source", "simulate")})')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    ax.set_title('drift between the device and the VT grasp point')
    ax.grid(alpha=0.3)
    ax.legend(loc='best')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _unique_labels(runs: list[Run]) -> None:
    seen: dict[str, int] = {}
    for r in runs:
        n = seen.get(r.label, 0)
        seen[r.label] = n + 1
        if n:
            r.label = f'{r.label}_{n + 1}'


def analyze(inputs: list[Path], out: Path, plots: bool = True) -> list[dict[str, Any]]:
    """Analyse ``inputs`` into ``out`` (see module doc); return the summary rows."""
    runs = [load_run(p) for p in inputs]
    _unique_labels(runs)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    for r in runs:
        try:
            summary = r.trace.summary()
        except ValueError as exc:
            raise BagError(f'{r.path}: {exc}') from None
        row: dict[str, Any] = {'label': r.label, 'input': str(r.path),
                               'source': r.trace.meta.get('source', 'simulate'),
                               'truncated': bool(r.trace.meta.get('truncated', False))}
        row.update(summary)
        row.update({k: (v if math.isfinite(v) else None) for k, v in r.loop.items()})
        if row['source'] == 'graph':
            row['skipped_messages'] = dict(r.skipped)
            row['graph_id'] = r.graph_id
            row['foreign_messages'] = dict(r.foreign_messages)
            row['foreign_publishers'] = dict(r.foreign_publishers)
        rows.append(row)
        if plots:
            from haptic_topology.sim.plots import plot_trace

            plot_trace(r.trace, out / f'{r.label}.png', _linkage_of(r),
                       title=f'{r.label}: final drift {summary["final_distance_m"] * 1e3:.2f} '
                       f'mm, max {summary["max_distance_m"] * 1e3:.2f} mm')
    if plots and len(runs) > 1:
        plot_comparison(runs, out / 'comparison.png')
    (out / 'summary.json').write_text(json.dumps({'runs': rows}, indent=2) + '\n',
                                      encoding='utf-8')
    return rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('inputs', nargs='+', type=Path, metavar='INPUT',
                        help='bag directory / .mcap file, trace.csv, or simulate --out dir')
    parser.add_argument('--out', type=Path, required=True, metavar='DIR',
                        help='output directory (plots, summary.json)')
    parser.add_argument('--no-plot', action='store_true', help='summary only')


def run(args: argparse.Namespace) -> int:
    """The ``analyze`` subcommand (see module doc)."""
    from haptic_topology.sim.trace import format_summary

    rows = analyze(list(args.inputs), args.out, not args.no_plot)
    # The first column shows the run's label (same width as the header 'scenario').
    print(format_summary([dict(r, scenario=r['label']) for r in rows]).replace(
        'scenario', 'run     ', 1))
    print()
    print(format_loop_health([(r['label'], r) for r in rows]))
    truncated = [r['label'] for r in rows if r['truncated']]
    if truncated:
        print(f'\nnote: {", ".join(truncated)} ended early (recorder killed?); read up to '
              'the last complete chunk')
    for r in rows:
        skipped = r.get('skipped_messages') or {}
        if skipped:
            print(f'\nnote: {r["label"]}: skipped {sum(skipped.values())} foreign or '
                  f'malformed messages ({", ".join(f"{k} {v}" for k, v in skipped.items())})')
    print(f'\nwrote {args.out / "summary.json"}' + ('' if args.no_plot else ' and plots'))
    return 0
