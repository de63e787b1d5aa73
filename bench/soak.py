"""``make soak``: a long ``haptic-topology run circle`` and the memory of every process.

Runs ``haptic-topology run circle --duration S`` (``--seconds``, default 3600; ``make soak
SOAK_SECONDS=600``), then ``haptic-topology analyze`` of its bag, and prints per process its
resident set at the start and the end and its peak (MiB), and its slope (kB/s, 1 kB = 1000
bytes; a least-squares fit after the first minute, or after half of a shorter run):

* the nodes, the loop process and the recorder: as ``run`` measured them while the loop ran
  (``<bag>/logs/rss.json``, :class:`haptic_topology.processes.RssSampler`);
* ``run`` itself, sampled here every second by the same sampler: while its graph ran (the
  slope; ``graph end``: its resident set when its nodes had ended) and over its whole life
  (the peak, its reading of the bag included);
* ``analyze`` of the bag: its peak (the kernel's high-water mark) and its wall time.

A line per process; the run's output directory is kept (``--out``, default a new directory
under ``bags/``) with ``soak.json`` (the figures). Exit status 1 if a process's peak is above
``--limit-mb`` (default 600 MB, 10^6 bytes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from haptic_topology.processes import RssSampler, children, rss_bytes


def _tool() -> str:
    return str(Path(sys.executable).with_name('haptic-topology'))


def _phase_growth(samples: list[tuple[float, int]]) -> dict[str, Any]:
    """start/end/peak/slope of one series (the sampler's fit)."""
    s = RssSampler(lambda: {})
    for t, rss in samples:
        s.add('p', t, rss)
    return s.growth()['p'] if samples else {}


def soak_run(seconds: float, out: Path, scenario: str) -> dict[str, dict[str, Any]]:
    """``run`` the scenario for ``seconds`` into ``out``; the memory figures per process."""
    cmd = [_tool(), 'run', scenario, '--duration', f'{seconds:g}', '--out', str(out)]
    print(' '.join(cmd), flush=True)
    started = time.monotonic()
    proc = subprocess.Popen(cmd)
    graph: list[tuple[float, int]] = []     # run's samples while its nodes run
    whole: list[tuple[float, int]] = []
    while proc.poll() is None:
        t = time.monotonic() - started
        rss = rss_bytes(proc.pid)
        if rss is not None:
            whole.append((t, rss))
            if children(proc.pid):      # (from its first node on: its start-up left out)
                graph.append((t, rss))
        time.sleep(1.0)
    if proc.wait() != 0:
        raise SystemExit(f'soak: {" ".join(cmd)} failed (exit {proc.returncode})')
    rss_file = out / 'logs' / 'rss.json'
    figures: dict[str, dict[str, Any]] = {}
    for name, m in json.loads(rss_file.read_text(encoding='utf-8')).items():
        figures[name] = {'start_mb': m.get('start_mb', m['series'][0][1]), 'end_mb': m['rss_mb'],
                         'peak_mb': m.get('peak_mb', max(r for _, r in m['series'])),
                         'slope_kb_s': m.get('growth_kb_s')}
    g = _phase_growth(graph)
    figures['run'] = {'start_mb': g.get('start_mb'), 'end_mb': round(whole[-1][1] / 2 ** 20, 2),
                      'peak_mb': round(max(r for _, r in whole) / 2 ** 20, 2),
                      'slope_kb_s': g.get('growth_kb_s'), 'graph_end_mb': g.get('rss_mb')}
    return figures


def soak_analyze(bag: Path) -> dict[str, Any]:
    """``analyze`` the bag: its peak resident set (MiB, the kernel's ``ru_maxrss``) and wall
    time (s)."""
    cmd = [_tool(), 'analyze', str(bag), '--out', str(bag / 'analysis')]
    print(' '.join(cmd), flush=True)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f'soak: {" ".join(cmd)} failed')
    return {'peak_mb': round(usage.ru_maxrss / 1024, 2), 'wall_s': round(wall, 1)}


def _cell(v: Any, fmt: str) -> str:
    return '-' if v is None else fmt.format(v)


def table(figures: dict[str, dict[str, Any]], analysis: dict[str, Any]) -> str:
    """One line per process, then the analysis."""
    head = f'{"process":<16} {"start [MiB]":>11} {"end [MiB]":>10} {"peak [MiB]":>10} ' \
           f'{"slope [kB/s]":>12}'
    lines = [head, '-' * len(head)]
    for name, f in figures.items():
        lines.append(f'{name:<16} {_cell(f["start_mb"], "{:.1f}"):>11} '
                     f'{_cell(f["end_mb"], "{:.1f}"):>10} {_cell(f["peak_mb"], "{:.1f}"):>10} '
                     f'{_cell(f["slope_kb_s"], "{:.3f}"):>12}')
    run = figures.get('run', {})
    if run.get('graph_end_mb') is not None:
        lines.append(f'run: {run["graph_end_mb"]:.1f} MiB when its graph ended, then the bag '
                     'read into trace, plot and summary')
    lines.append(f'analyze: peak {analysis["peak_mb"]:.1f} MiB, {analysis["wall_s"]:.1f} s')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float,
                        default=float(os.environ.get('SOAK_SECONDS', '3600')),
                        help='run duration (s; default $SOAK_SECONDS or 3600)')
    parser.add_argument('--scenario', default='circle')
    parser.add_argument('--out', type=Path, help='bag directory (default bags/soak_<time>)')
    parser.add_argument('--limit-mb', type=float, default=600.0,
                        help='peak resident set every process must stay under (MB)')
    args = parser.parse_args(argv)
    out = args.out or Path('bags') / f'soak_{time.strftime("%Y%m%d-%H%M%S")}'
    figures = soak_run(args.seconds, out, args.scenario)
    analysis = soak_analyze(out)
    print()
    print(table(figures, analysis))
    (out / 'soak.json').write_text(json.dumps({'seconds': args.seconds, 'processes': figures,
                                               'analyze': analysis}, indent=2) + '\n',
                                   encoding='utf-8')
    limit = args.limit_mb * 1e6 / 2 ** 20     # MiB
    over = [n for n, f in figures.items() if (f['peak_mb'] or 0.0) > limit]
    if analysis['peak_mb'] > limit:
        over.append('analyze')
    if over:
        print(f'over {args.limit_mb:g} MB at peak: {", ".join(over)}')
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
