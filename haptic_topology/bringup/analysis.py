"""The end of ``haptic-topology run``: each run's bag read into its trace, plot and summary,
in a process of its own (``python -m haptic_topology.bringup.analysis``).

``run`` has watched the graph for the whole run (rclpy, the recorder's and the nodes'
reports, the resident-set sampler): reading an hour's bag in that process would add the
reading's memory to what the watching left behind. A fresh process starts from the package's
imports alone, and its memory is returned to the system when it ends. It takes an
:class:`AnalysisJob` (pickled, on its stdin), writes ``trace.parquet`` (and ``trace.csv``),
``summary.json``, ``plot.png`` and, when the bag's energy account was reconstructed row by row
(:mod:`haptic_topology.bag.energy_series`), ``energy.png`` beside the bag, prints what ``run``
prints of the bag (foreign publishers, skipped messages, the plots' paths, an energy series
refused) and writes the run's summary and loop
figures as JSON to ``job.result``, which ``run`` reads for its tables.
"""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from haptic_topology.errors import BringupError, HapticTopologyError
from haptic_topology.sim.scenario import Scenario


@dataclass(frozen=True)
class AnalysisJob:
    """One run to analyse: its ``bag``, scenario ``sc``, ``mode`` and ``layout`` (for the
    summary and the plot's title), ``csv`` (also ``trace.csv``), ``plot``, and where the
    result goes (``result``: JSON ``{"summary": ..., "loop": ...}``)."""

    bag: Path
    sc: Scenario
    mode: str
    layout: str
    csv: bool
    plot: bool
    result: Path


def analyse(job: AnalysisJob) -> dict[str, Any]:
    """Read ``job.bag`` (see module doc); returns and writes its summary and loop figures."""
    from haptic_topology.bag.analyze import reduce_bag

    bag, sc = job.bag, job.sc
    traces = (bag / 'trace.parquet',) + ((bag / 'trace.csv',) if job.csv else ())
    result = reduce_bag(bag, sc.name, sc.lmi_dof, sc.linkage.task.dim, sc.linkage,
                        traces, periods=True, plot=job.plot)
    summary = dict(result.summary, **{k: v for k, v in result.loop.items()})
    summary['layout'] = job.layout
    summary['skipped_messages'] = dict(result.skipped)
    summary['graph_id'] = result.graph_id
    summary['foreign_messages'] = result.foreign_messages
    summary['foreign_publishers'] = result.foreign_publishers
    summary.update({k if k.startswith('device_') else f'device_{k}': v
                    for k, v in result.device.items()})
    if result.foreign_publishers:
        print(f'foreign publishers on the graph\'s topics (nothing of theirs applied): '
              f'{", ".join(result.foreign_publishers)}', flush=True)
    if result.skipped:
        print(f'skipped {sum(result.skipped.values())} foreign or malformed messages in '
              f'the bag: {result.skipped}', flush=True)
    logs = bag / 'logs'
    for name, prefix in (('cpu.json', 'cpu_'),):
        f = logs / name
        if f.is_file():
            summary.update({f'{prefix}{k}': v
                            for k, v in json.loads(f.read_text(encoding='utf-8')).items()})
    auto_file = logs / 'loop_cpu.json'
    if auto_file.is_file():
        summary['loop_cpu_changes'] = json.loads(auto_file.read_text(encoding='utf-8'))
    rss_file = logs / 'rss.json'
    if rss_file.is_file():
        for name, m in json.loads(rss_file.read_text(encoding='utf-8')).items():
            summary[f'rss_mb_{name}'] = m['rss_mb']
            if 'growth_kb_s' in m:
                summary[f'rss_growth_kb_s_{name}'] = m['growth_kb_s']
    (bag / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n', encoding='utf-8')
    if job.plot:
        from haptic_topology.sim.plots import plot_trace

        plot_trace(result.plot, bag / 'plot.png', sc.linkage,
                   title=f'{sc.label} {job.mode} (ROS graph)',
                   obstacles=sc.contacts.obstacles if sc.contacts else ())
        print(f'plot: {bag / "plot.png"}', flush=True)
        if result.energy_plot is not None:
            from haptic_topology.sim.energy_plots import plot_energy

            plot_energy(result.energy_plot, bag / 'energy.png',
                        f'{sc.label} {job.mode} (ROS graph)')
            print(f'energy plot: {bag / "energy.png"}', flush=True)
    series = str(summary.get('energy_series', ''))
    if series.startswith('refused'):
        print(f'energy series {series}', flush=True)
    out = {'summary': summary, 'loop': result.loop}
    job.result.write_text(json.dumps(out) + '\n', encoding='utf-8')
    return out


def analyse_in_child(job: AnalysisJob) -> dict[str, Any]:
    """:func:`analyse` in a process of its own (see module doc); its one-line error (the
    process's last line on stderr) as a :class:`~haptic_topology.errors.BringupError`."""
    proc = subprocess.run([sys.executable, '-m', __name__], input=pickle.dumps(job),
                          stderr=subprocess.PIPE, check=False)
    if proc.returncode != 0:
        lines = proc.stderr.decode(errors='replace').strip().splitlines() or ['(no output)']
        raise BringupError(f'reading the bag failed: {lines[-1]}')
    sys.stderr.write(proc.stderr.decode(errors='replace'))
    out: dict[str, Any] = json.loads(job.result.read_text(encoding='utf-8'))
    job.result.unlink()
    return out


def main() -> int:
    try:
        analyse(pickle.loads(sys.stdin.buffer.read()))
    except HapticTopologyError as exc:        # one line, for run's error
        print(exc, file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
