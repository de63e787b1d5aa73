"""``haptic-topology zwidth [SCENARIO ...] --out DIR``: Z-width maps of the penalty.

Sweeps ``k_tc`` x ``b_tc`` of eq. 13 under eq. 14 (:mod:`haptic_topology.sim.zwidth`) for each
scenario, with the LMI at each update rate, without and with the passivity controller, and
writes ``zwidth.json`` (every run's class and figures, the defaults' margin) and
``zwidth.png`` (one panel per scenario, rate and controller; the defaults marked; the
command, date and commit at the bottom), and prints a table of the margins.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from haptic_topology.paths import scenario_help

#: The device models of the shipped maps: planar and spatial maglev, planar and spatial
#: point devices.
DEFAULT_SCENARIOS = ('fig8', 'spatial_arm4', 'fig8_point', 'spatial_arm4_point')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('scenarios', nargs='*', metavar='SCENARIO',
                        help=f'{scenario_help()}; default: {", ".join(DEFAULT_SCENARIOS)}')
    parser.add_argument('--out', required=True, type=Path,
                        help='output directory (created; zwidth.json, zwidth.png)')
    parser.add_argument('--duration', type=float,
                        help="length of each run (s; default the scenario's)")
    parser.add_argument('--update-periods', default='10,40', metavar='N,N',
                        help='device cycles per LMI update (default 10,40: 100 and 25 Hz at '
                        '1 kHz)')


def _commit() -> str:
    """The source tree's commit (short hash; ``+`` when it has changes), or ``unknown``."""
    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=here, text=True,
                             capture_output=True, check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no'],
                               cwd=here, text=True, capture_output=True, check=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return 'unknown'
    return rev + ('+' if dirty else '')


def plot_maps(maps: list[dict[str, Any]], path: Path, footer: str) -> None:
    """One panel per map: ``k_tc`` x ``b_tc`` (factors of the defaults), each run coloured by
    its class, the defaults circled, the margin in the title."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from haptic_topology.sim.zwidth import PASSIVE, STABLE, UNSTABLE
    colors = {PASSIVE: 'tab:green', STABLE: 'tab:orange', UNSTABLE: 'tab:red'}
    names = list(dict.fromkeys(m['scenario'] for m in maps))
    cols = list(dict.fromkeys((m['update_period'], m['passivity']) for m in maps))
    fig, axes = plt.subplots(len(names), len(cols), figsize=(3.3 * len(cols), 2.6 * len(names)),
                             squeeze=False)
    for m in maps:
        ax = axes[names.index(m['scenario'])][cols.index((m['update_period'], m['passivity']))]
        k0, b0 = m['default']
        ks = sorted({p['k_tc'] for p in m['points']})
        bs = sorted({p['b_tc'] for p in m['points']})
        for p in m['points']:
            ax.scatter(ks.index(p['k_tc']), bs.index(p['b_tc']), s=140, marker='s',
                       color=colors[p['verdict']])
        ax.scatter(ks.index(k0), bs.index(b0), s=260, facecolors='none', edgecolors='black',
                   linewidths=2)
        ax.set_xticks(range(len(ks)), [f'{k:g}' for k in ks], fontsize=7)
        ax.set_yticks(range(len(bs)), [f'{b:g}' for b in bs], fontsize=7)
        ax.set_xlabel('k_tc [N/(m kg)]', fontsize=8)
        ax.set_ylabel('b_tc [N s/(m kg)]', fontsize=8)
        ax.set_title(f'{m["scenario"]}, LMI {m["rate_hz"]:g} Hz, PC '
                     f'{"on" if m["passivity"] else "off"}\nmargin x{m["margin"]:g}',
                     fontsize=8)
    handles = [plt.Line2D([], [], marker='s', ls='', color=c, label=v)
               for v, c in colors.items()]
    handles.append(plt.Line2D([], [], marker='o', ls='', mfc='none', mec='black',
                              label='scenario defaults'))
    fig.legend(handles=handles, loc='upper center', ncol=4, fontsize=8)
    fig.text(0.01, 0.005, footer, fontsize=7, family='monospace')
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """Sweep, write the outputs, print the margins."""
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.zwidth import sweep

    try:
        periods = [int(v) for v in str(args.update_periods).split(',')]
    except ValueError:
        raise SystemExit(f'--update-periods: expected integers like 10,40, got '
                         f'{args.update_periods!r}') from None
    if not periods or min(periods) < 1:
        raise SystemExit(f'--update-periods: expected integers >= 1, got {periods}')
    if args.duration is not None and not args.duration > 0.0:
        raise SystemExit(f'--duration: expected a positive number of seconds, got '
                         f'{args.duration}')
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    maps = []
    print(f'{"scenario":<20} {"LMI [Hz]":>8} {"PC":>3} {"k_tc":>8} {"b_tc":>7} '
          f'{"margin":>7}  passive/stable/unstable')
    for name in args.scenarios or DEFAULT_SCENARIOS:
        sc = load_scenario(name)
        for period in periods:
            for pc in (False, True):
                m = sweep(sc, period, pc, duration=args.duration)
                maps.append(m)
                counts = [sum(p['verdict'] == v for p in m['points'])
                          for v in ('passive', 'stable', 'unstable')]
                k0, b0 = m['default']
                print(f'{sc.name:<20} {m["rate_hz"]:>8g} {"on" if pc else "off":>3} '
                      f'{k0:>8g} {b0:>7g} {"x" + format(m["margin"], "g"):>7}  '
                      f'{"/".join(map(str, counts))}', flush=True)
    command = 'haptic-topology zwidth ' + ' '.join(sys.argv[2:])
    stamp = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
    footer = f'{command}\n{stamp}, commit {_commit()}'
    (out / 'zwidth.json').write_text(json.dumps({'command': command, 'date': stamp,
                                                 'commit': _commit(), 'maps': maps},
                                                indent=1) + '\n', encoding='utf-8')
    plot_maps(maps, out / 'zwidth.png', footer)
    print(f'wrote {out / "zwidth.json"}, {out / "zwidth.png"}')
    return 0
