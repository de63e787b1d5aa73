"""``haptic-topology analyze INPUT... --out DIR``: drift and loop health of recorded runs.

Each INPUT is a bag of the node graph (a rosbag2 directory or ``.mcap`` file, read with
:func:`~haptic_topology.bag.graph_trace.stream_graph_bag`, truncated ones too), or a trace
(a ``trace.parquet`` or ``trace.csv`` of ``simulate`` or ``run``, or a ``simulate --out``
directory). For each it
prints one row of the drift table (the columns of ``simulate``: final, max and RMS distance
between the device and the VT grasp point, time constrained, time at the workspace limit)
with, when an input has obstacles, its deepest penetration and time in contact
(:func:`~haptic_topology.sim.trace.format_summary`), and one row of the loop-health table
``run`` prints too (:data:`LOOP_COLUMNS`: bags only but for the periods; fraction of states
answered before the next one, from the device driver's diagnostics and from the bag; round
trip p50/p99; the device's period p50/p99 and its standard deviation and the states missing,
from the state stamps). It writes into DIR:

* ``<label>.png``: the Fig. 6 / Fig. 8 style figure of each input (linkage, hand paths,
  drift, constraints, and for a run with obstacles the obstacles and the contact panel; the
  linkage and the obstacles come from the scenario named in the run, see :func:`run_figure`);
* ``comparison.png`` with two or more inputs only: the drift of each over time;
* ``summary.json``: ``{"runs": [...]}``, one object per input with the drift fields of
  ``simulate`` (``final_distance_m``, ``max_distance_m``, ``rms_distance_m``,
  ``constrained_time_s``, ...), ``label``, ``input``, ``source`` (graph/simulate) and, for
  bags, the loop figures and ``skipped_messages``: the foreign or malformed messages on the
  graph's topics that were left out, per ``<kind>_<reason>`` (see
  :mod:`haptic_topology.bag.graph_trace`); the trace, plot and summary are written anyway.
  A bag whose controller's last ``/diagnostics`` status was sent after the run's last state
  has the controller's energy account too (:func:`controller_account`): ``energy_account``
  as ``simulate`` writes it, and the observer's lowest and last value and the cycles the
  passivity controller acted in the energy table;
* ``<label>_energy.png`` for a bag (the figure ``simulate`` draws as ``energy.png``: the work
  at the device port per axis, the hand's, the passivity observer and the passivity
  controller's damping over time) when its energy account could be reconstructed row by row
  (:mod:`haptic_topology.bag.energy_series`: the controller replayed offline from the bag's
  states and updates, every command equal to the recorded one); the energy table and
  ``summary.json`` then take the observer's figures from that series, and
  ``energy_series`` says ``exact`` (``exact before state N (...)`` when the bag lacks
  an LMI update the commands from state N on name, as a cut bag may), or why there is none
  (``refused: state N: ...``, ``not reconstructed: ...``). By default bags of at most
  :data:`~haptic_topology.bag.energy_series.AUTO_STATES` device states are reconstructed;
  ``--energy`` reconstructs any bag, ``--no-energy`` none.

Reading a large bag shows a progress line on stderr (when stderr is a terminal, or the bag
is larger than 20 MB). Inputs are read as a stream, one after the other: the memory used
does not grow with a run's length but for about 60 bytes a device cycle (the figures that need
every row, such as the median period and the RMS drift, keep one float per row), and a plot
draws at most :data:`~haptic_topology.sim.trace_stats.PLOT_ROWS` buckets of a longer run
(:class:`~haptic_topology.sim.trace_stats.PlotRows`: the envelope of each curve, every step).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from haptic_topology.bag.graph_index import CONTROLLER_STATUS, DEVICE_STATUS
from haptic_topology.bag.graph_trace import stream_graph_bag
from haptic_topology.bag.reader import METADATA
from haptic_topology.device.vendor import IDENTITY_KEYS
from haptic_topology.errors import BagError, ConfigError
from haptic_topology.model.linkage import Linkage
from haptic_topology.sim.trace import Trace
from haptic_topology.sim.trace_io import (
    TraceWriter,
    empty_trace,
    iter_trace,
    read_trace,
    trace_meta,
)
from haptic_topology.sim.trace_stats import PeriodStats, PlotRows, Summary, feed

BIG_BAG_BYTES = 20_000_000
#: The names of a trace file in a ``simulate --out`` / ``run`` directory, by preference.
TRACE_NAMES = ('trace.parquet', 'trace.csv')


@dataclass
class Run:
    """One analysed input: its figures and the rows a plot of it draws (``plot``)."""

    label: str
    path: Path
    plot: Trace
    summary: dict[str, Any]
    loop: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    #: A bag's graph (its recorder's ``graph_id``) and the messages of other graphs per topic
    graph_id: str | None = None
    foreign_messages: dict[str, int] = field(default_factory=dict)
    foreign_publishers: dict[str, list[str]] = field(default_factory=dict)
    #: A bag's device, from the driver's newest ``/diagnostics`` status: ``hardware_id`` and
    #: what identifies a vendor's unit (``device_vendor``, ``device_model``, ...).
    device: dict[str, str] = field(default_factory=dict)
    #: A bag's energy account row by row (the rows its energy figure draws), when exact.
    energy_plot: Trace | None = None

    @property
    def meta(self) -> dict[str, Any]:
        return self.plot.meta


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


def _trace_file(p: Path) -> Path | None:
    """The trace file of ``p`` (itself, or the trace of a directory), None if it has none."""
    if p.is_dir():
        return next((p / n for n in TRACE_NAMES if (p / n).is_file()), None)
    return p if p.is_file() and not _is_bag(p) else None


def label_of(path: str | Path) -> str:
    """An input's label: a bag's directory name or file stem; a trace file's directory name
    when it is the trace of a directory (``trace.parquet``, ``trace.csv``), else its stem."""
    p = Path(path)
    if _is_bag(p):
        return p.name if p.is_dir() else p.stem
    f = _trace_file(p) or p
    return f.parent.name if f.name in TRACE_NAMES else f.stem


def _summary(sink: Summary, path: Path) -> dict[str, Any]:
    try:
        return sink.result()
    except ValueError as exc:
        raise BagError(f'{path}: {exc}') from None


def controller_account(diagnostics: dict[str, dict[str, str]]) -> dict[str, Any] | None:
    """The controller's energy account at the run's last state, from the last
    ``/diagnostics`` statuses of a bag (status name -> key/values): the controller's
    ``energy_account`` (:meth:`~haptic_topology.control.passivity.EnergyAccount.summary`,
    floats exact) when that status was sent after the controller had answered the device's
    last state (its ``last_state_seq`` is the driver's ``seq``); None otherwise (no such
    status, or one sent while the run went on: its figures would not be the run's)."""
    ctl = diagnostics.get(CONTROLLER_STATUS, {})
    dev = diagnostics.get(DEVICE_STATUS, {})
    raw, seq = ctl.get('energy_account'), ctl.get('last_state_seq')
    if raw is None or seq is None or seq != dev.get('seq') or dev.get('loop_running') != 'false':
        return None
    account: dict[str, Any] = json.loads(raw)
    return account


class _FirstRow:
    """The seq of a trace's first row (a sink)."""

    def __init__(self) -> None:
        self.seq: int | None = None

    def begin(self, template: Trace, rows: int) -> None:
        pass

    def add(self, chunk: Trace) -> None:
        if self.seq is None and len(chunk):
            self.seq = int(chunk.seq[0])

    def end(self) -> None:
        pass


def _energy(p: Path, energy: bool | None, rows: int, diagnostics: dict[str, dict[str, str]],
            first_seq: int | None, plot: bool, scenario: str
            ) -> tuple[dict[str, Any], Trace | None]:
    """The reconstructed energy series of bag ``p`` (module doc): the summary's figures and
    the rows of its figure (None: no figure)."""
    from haptic_topology.bag.energy_series import AUTO_STATES, energy_series

    if energy is False:
        return {'energy_series': 'not reconstructed: --no-energy'}, None
    if energy is None and rows > AUTO_STATES:
        return {'energy_series': f'not reconstructed: {rows} states, more than '
                                 f'{AUTO_STATES} (analyze --energy)'}, None
    series = energy_series(p, diagnostics.get(CONTROLLER_STATUS), first_seq, plot, scenario)
    if not series.exact:
        return {'energy_series': f'refused: {series.refused}'}, None
    exact = 'exact' if not series.unchecked else (
        f'exact before state {series.unchecked_from} ({series.unchecked} commands from it '
        f'on not reconstructed: LMI update {series.absent_update}, '
        'which the controller had taken, is not in the bag)')
    return dict(series.figures(), energy_series=exact), series.plot


def reduce_bag(path: str | Path, scenario: str = '', dof: int | None = None,
               task_dim: int | None = None, linkage: Linkage | None = None,
               traces: tuple[Path, ...] = (), periods: bool = False, plot: bool = True,
               progress: Any = None, energy: bool | None = None) -> Run:
    """Read the bag ``path`` once as a stream (:func:`~haptic_topology.bag.graph_trace.
    stream_graph_bag`; arguments as there) into its drift summary, loop figures (with the
    device period figures if ``periods``), the rows of its plot (if ``plot``) and the trace
    files ``traces`` (``.parquet``, ``.csv``), written as the rows come; then its energy
    account row by row (module doc; ``energy``: True always, False never, None for a bag
    of at most :data:`~haptic_topology.bag.energy_series.AUTO_STATES` states)."""
    p = Path(path)
    summary, period, rows, first = Summary(), PeriodStats(), PlotRows(), _FirstRow()
    sinks: list[Any] = [summary, first] + ([period] if periods else []) + (
        [rows] if plot else [])
    sinks += [TraceWriter(f) for f in traces]
    result = stream_graph_bag(p, sinks, scenario, dof, progress, task_dim, linkage)
    loop = dict(result.loop)
    if periods:
        loop.update(period.result())
    dev = result.diagnostics.get(DEVICE_STATUS, {})
    device = {k: dev[k] for k in ('hardware_id', *IDENTITY_KEYS) if dev.get(k)}
    figures = _summary(summary, p)
    account = controller_account(result.diagnostics)
    if account is not None:
        figures.update(energy_account=account,
                       passivity_observer_min_j=account['passivity_observer_min_j'],
                       passivity_observer_final_j=account['passivity_observer_j'],
                       passivity_rows=account['passivity_cycles'])
    series, energy_plot = _energy(p, energy, result.rows, result.diagnostics, first.seq,
                                  plot, scenario)
    figures.update(series)
    return Run(label_of(p), p, rows.trace or result.trace, figures, loop,
               dict(result.skipped), result.graph_id, dict(result.foreign_messages),
               dict(result.foreign_publishers), device, energy_plot)


def load_run(path: str | Path, plot: bool = True, energy: bool | None = None) -> Run:
    """Read one input (see module doc; ``energy``: :func:`reduce_bag`'s)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f'{p}: no such file or directory')
    if _is_bag(p):
        scenario = _scenario_of_bag(p)
        name = Path(scenario).stem if scenario else ''
        dof = task_dim = linkage = None
        if scenario:
            try:
                from haptic_topology.sim.scenario import load_scenario

                sc = load_scenario(scenario)
                dof, task_dim, name = sc.lmi_dof, sc.linkage.task.dim, sc.name
                linkage = sc.linkage
            except ConfigError:
                pass
        size = sum(f.stat().st_size for f in ([p] if p.is_file() else p.glob('*.mcap')))
        run = reduce_bag(p, name, dof, task_dim, linkage, periods=True, plot=plot,
                         progress=_ProgressLine(p.name, size), energy=energy)
        if scenario:
            run.plot.meta.setdefault('scenario_ref', scenario)
        return run
    f = _trace_file(p)
    if f is None:
        raise BagError(f'{p}: not a bag (no {METADATA} and no .mcap file) and no '
                       f'{" or ".join(TRACE_NAMES)}')
    if f.suffix == '.parquet':
        meta, n = trace_meta(f)
        head, chunks = empty_trace(meta), iter_trace(f)
    else:
        whole = read_trace(f)
        head, chunks, n = whole.take(slice(0, 0)), iter([whole]), len(whole)
    summary, period, rows = Summary(), PeriodStats(), PlotRows()
    feed(chunks, head, n, [summary, period] + ([rows] if plot else []))
    return Run(label_of(p), p, rows.trace or head, _summary(summary, p), period.result())


def run_figure(r: Run) -> Any:
    """The figure of ``r`` (``<label>.png``, module doc; the caller closes it): the linkage
    and obstacles of the scenario named in its metadata (a bag's ``custom_data.scenario``, a
    trace's ``scenario``; the linkage of a trace's ``linkage_file`` when it ran on another,
    also named in the title), none of those it cannot load."""
    from haptic_topology.model.linkage import load_linkage
    from haptic_topology.sim.plots import trace_figure
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.trace import run_name

    ref = str(r.meta.get('scenario_ref') or r.meta.get('scenario') or '')
    other = str(r.meta.get('linkage_file', ''))
    linkage: Linkage | None = None
    obstacles: tuple[Any, ...] = ()
    try:
        if ref:
            sc = load_scenario(ref)
            linkage = sc.linkage
            obstacles = tuple(sc.contacts.obstacles) if sc.contacts else ()
    except ConfigError:
        pass
    try:
        if other:
            linkage = load_linkage(other)
    except ConfigError:
        linkage = None
    name = f' ({run_name(str(r.meta.get("scenario", "")), other)})' if other else ''
    return trace_figure(r.plot, linkage, f'{r.label}{name}: final drift '
                        f'{r.summary["final_distance_m"] * 1e3:.2f} mm, max '
                        f'{r.summary["max_distance_m"] * 1e3:.2f} mm', obstacles)


#: The loop-health table of ``run`` and ``analyze`` (:func:`format_loop_health`), in order:
#: the ``summary.json`` key of each figure, its column, scale and format. The device
#: driver's own answered fraction and round trip (its last ``/diagnostics``), the bag's
#: answered fraction, and the device period from the states' stamps in the bag.
LOOP_COLUMNS = (('device_answered_fraction', 'answered, device [%]', 100.0, '{:.2f}'),
                ('bag_answered_fraction', 'answered, bag [%]', 100.0, '{:.2f}'),
                ('device_round_trip_p50_ms', 'rtt p50 [ms]', 1.0, '{:.3f}'),
                ('device_round_trip_p99_ms', 'rtt p99 [ms]', 1.0, '{:.3f}'),
                ('bag_period_p50_ms', 'period p50 [ms]', 1.0, '{:.3f}'),
                ('bag_period_p99_ms', 'period p99 [ms]', 1.0, '{:.3f}'),
                ('bag_period_std_ms', 'period std [ms]', 1.0, '{:.3f}'),
                ('bag_missing_states', 'missing states', 1.0, '{:.0f}'))


def format_loop_health(runs: list[tuple[str, dict[str, Any]]]) -> str:
    """The loop-health table (:data:`LOOP_COLUMNS`), one row per ``(label, figures)``; a
    figure missing or not finite is ``-`` (a trace of ``simulate`` has periods only)."""
    cells = [['run'] + [c[1] for c in LOOP_COLUMNS]]
    for label, figures in runs:
        row = [label]
        for key, _, scale, fmt in LOOP_COLUMNS:
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
    import matplotlib.pyplot as plt

    from haptic_topology.sim.plots import save_figure

    fig, ax = plt.subplots(figsize=(10, 5))
    for r in runs:
        ax.plot(r.plot.t, r.plot.distance() * 1000.0, lw=1.5,
                label=f'{r.label} ({r.meta.get("source", "simulate")})')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    ax.set_title('drift between the device and the VT grasp point')
    ax.grid(alpha=0.3)
    ax.legend(loc='best')
    fig.tight_layout()
    return save_figure(fig, path)


def _unique_labels(labels: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for label in labels:
        n = seen.get(label, 0)
        seen[label] = n + 1
        out.append(f'{label}_{n + 1}' if n else label)
    return out


def analyze(inputs: list[Path], out: Path, plots: bool = True,
            energy: bool | None = None) -> list[dict[str, Any]]:
    """Analyse ``inputs`` into ``out`` (see module doc), one after the other; return the
    summary rows. ``energy``: reconstruct bags' energy series (:func:`reduce_bag`)."""
    for p in inputs:
        if not Path(p).exists():
            raise BagError(f'{p}: no such file or directory')
    labels = _unique_labels([label_of(p) for p in inputs])
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    runs: list[Run] = []
    for p, label in zip(inputs, labels, strict=True):
        r = load_run(p, plots, energy)
        r.label = label
        summary = r.summary
        row: dict[str, Any] = {'label': r.label, 'input': str(r.path),
                               'source': r.meta.get('source', 'simulate'),
                               'truncated': bool(r.meta.get('truncated', False))}
        row.update(summary)
        row.update({k: (v if math.isfinite(v) else None) for k, v in r.loop.items()})
        if row['source'] == 'graph':
            row['skipped_messages'] = dict(r.skipped)
            row['graph_id'] = r.graph_id
            row['foreign_messages'] = dict(r.foreign_messages)
            row['foreign_publishers'] = dict(r.foreign_publishers)
        rows.append(row)
        if plots:
            from haptic_topology.sim.plots import save_figure
            save_figure(run_figure(r), out / f'{r.label}.png')
            if r.energy_plot is not None:
                from haptic_topology.sim.energy_plots import plot_energy
                plot_energy(r.energy_plot, out / f'{r.label}_energy.png', r.label)
            runs.append(r)
    if plots and len(runs) > 1:
        plot_comparison(runs, out / 'comparison.png')
    (out / 'summary.json').write_text(json.dumps({'runs': rows}, indent=2) + '\n',
                                      encoding='utf-8')
    return rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('inputs', nargs='+', type=Path, metavar='INPUT',
                        help='bag directory / .mcap file, trace.parquet / trace.csv, or a '
                        'simulate --out dir')
    parser.add_argument('--out', type=Path, required=True, metavar='DIR',
                        help='output directory (plots, summary.json)')
    parser.add_argument('--no-plot', action='store_true', help='summary only')
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--energy', action='store_true', default=None,
                       help="reconstruct a bag's energy account row by row whatever its "
                       'length (default: bags of at most 600,000 states)')
    group.add_argument('--no-energy', action='store_false', dest='energy',
                       help="do not reconstruct bags' energy accounts")


def run(args: argparse.Namespace) -> int:
    """The ``analyze`` subcommand (see module doc)."""
    from haptic_topology.sim.trace import format_energy, format_summary

    rows = analyze(list(args.inputs), args.out, not args.no_plot, args.energy)
    # The first column shows the run's label (same width as the header 'scenario').
    print(format_summary([dict(r, scenario=r['label']) for r in rows]).replace(
        'scenario', 'run     ', 1))
    print()
    print(format_loop_health([(r['label'], r) for r in rows]))
    print()
    print(format_energy([(r['label'], r) for r in rows]))
    truncated = [r['label'] for r in rows if r['truncated']]
    if truncated:
        print(f'\nnote: {", ".join(truncated)} ended early (recorder killed?); read up to '
              'the last complete chunk')
    for r in rows:
        series = str(r.get('energy_series', ''))
        if series.startswith('refused'):
            print(f'\nnote: {r["label"]}: energy series {series}')
        skipped = r.get('skipped_messages') or {}
        if skipped:
            print(f'\nnote: {r["label"]}: skipped {sum(skipped.values())} foreign or '
                  f'malformed messages ({", ".join(f"{k} {v}" for k, v in skipped.items())})')
    print(f'\nwrote {args.out / "summary.json"}' + ('' if args.no_plot else ' and plots'))
    return 0
