"""``haptic-topology zwidth [SCENARIO ...] --out DIR``: Z-width maps of the penalty and of the
contacts.

Sweeps two gains (eq. 13's ``k_tc`` x ``b_tc``; a scenario with obstacles also the contact
``stiffness`` x ``damping``) for each scenario (:mod:`haptic_topology.sim.zwidth`), with the
LMI at each update rate, without and with the passivity controller; for a point grasp also on
each emulated vendor device's parameters (``--devices``); and with the VE or the device
behind a link (``--ve-delays-ms``, ``--device-delays-ms``, at the scenario's own update
rate). Without scenarios: the shipped set (:data:`DEFAULT_PLAN`). Writes ``zwidth.json``
(every run's class and figures, the defaults' margins), one figure per group of maps
(``zwidth.png``: the scenarios' devices; ``zwidth_vendors.png``, ``zwidth_delays.png``,
``zwidth_contacts.png``; each map's defaults circled; the command, date and commit at the
bottom) and ``zwidth.md`` (the table of margins the results page shows), and prints that
table.
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

#: The shipped maps: scenario -> (vendor devices, VE delays ms, device delays ms). Every
#: scenario's own device (planar and spatial maglev, planar and spatial point devices, the
#: contact scenario wall) at 100 and 25 Hz; the vendor devices on fig8_point (the scenario
#: their example runs); the networking page's delays (the VE 5, 20, 50 ms one way, the
#: device 1 ms) on fig8 and fig8_point.
DEFAULT_PLAN: dict[str, tuple[tuple[str, ...], tuple[float, ...], tuple[float, ...]]] = {
    'fig8': ((), (5.0, 20.0, 50.0), (1.0,)),
    'spatial_arm4': ((), (), ()),
    'fig8_point': (('forcedimension', 'openhaptics', 'haply'), (5.0, 20.0, 50.0), (1.0,)),
    'spatial_arm4_point': ((), (), ()),
    'wall': ((), (), ()),
}
#: The figure each group of maps goes to.
FIGURES = ('zwidth.png', 'zwidth_vendors.png', 'zwidth_delays.png', 'zwidth_contacts.png')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('scenarios', nargs='*', metavar='SCENARIO',
                        help=f'{scenario_help()}; default: {", ".join(DEFAULT_PLAN)} with '
                        'the shipped devices and delays')
    parser.add_argument('--out', required=True, type=Path,
                        help='output directory (created; zwidth.json, zwidth*.png, zwidth.md)')
    parser.add_argument('--duration', type=float,
                        help="length of each run (s; default the scenario's)")
    parser.add_argument('--update-periods', default='10,40', metavar='N,N',
                        help='device cycles per LMI update (default 10,40: 100 and 25 Hz at '
                        '1 kHz)')
    parser.add_argument('--devices', default='', metavar='NAME,NAME',
                        help='vendor devices whose (emulator\'s) parameters a point-grasp '
                        'scenario is also swept on: forcedimension, openhaptics, haply')
    parser.add_argument('--ve-delays-ms', default='', metavar='MS,MS',
                        help='one-way delays of a link between the VE and the rest (ms)')
    parser.add_argument('--device-delays-ms', default='', metavar='MS,MS',
                        help='one-way delays of a link between the device and the '
                        'controller (ms)')


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


def figure_of(m: dict[str, Any]) -> str:
    """The figure (:data:`FIGURES`) map ``m`` is drawn in."""
    if m['axes'] == 'contacts':
        return FIGURES[3]
    if m['ve_delay_ms'] or m['device_delay_ms']:
        return FIGURES[2]
    return FIGURES[0] if m['device'] == 'scenario' else FIGURES[1]


def row_label(m: dict[str, Any]) -> str:
    """The map's scenario, device and link, for titles and tables."""
    out = m['scenario']
    if m['device'] != 'scenario':
        out += f', {m["device_label"]}'
    if m['ve_delay_ms']:
        out += f', VE link {m["ve_delay_ms"]:g} ms'
    if m['device_delay_ms']:
        out += f', device link {m["device_delay_ms"]:g} ms'
    return out


def plot_maps(maps: list[dict[str, Any]], path: Path, footer: str) -> None:
    """One panel per map: first x second gain, each run coloured by its class, the
    defaults circled, the margins in the title."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from haptic_topology.sim.plots import save_figure
    from haptic_topology.sim.zwidth import PASSIVE, STABLE, UNITS, UNSTABLE
    colors = {PASSIVE: 'tab:green', STABLE: 'tab:orange', UNSTABLE: 'tab:red'}
    rows = list(dict.fromkeys(row_label(m) for m in maps))
    cols = list(dict.fromkeys((m['update_period'], m['passivity']) for m in maps))
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(3.4 * len(cols), 2.7 * len(rows)),
                             squeeze=False)
    for m in maps:
        ax = axes[rows.index(row_label(m))][cols.index((m['update_period'], m['passivity']))]
        x0, y0 = m['default']
        xs = sorted({p['x'] for p in m['points']})
        ys = sorted({p['y'] for p in m['points']})
        for p in m['points']:
            ax.scatter(xs.index(p['x']), ys.index(p['y']), s=90, marker='s',
                       color=colors[p['verdict']])
        ax.scatter(xs.index(x0), ys.index(y0), s=200, facecolors='none', edgecolors='black',
                   linewidths=2)
        ax.set_xticks(range(len(xs)), [f'{x:g}' for x in xs], fontsize=6, rotation=60)
        ax.set_yticks(range(len(ys)), [f'{y:g}' for y in ys], fontsize=7)
        ax.set_xlabel(f'{m["x"]} [{UNITS[m["x"]]}]', fontsize=7)
        ax.set_ylabel(f'{m["y"]} [{UNITS[m["y"]]}]', fontsize=7)
        ax.set_title(f'{row_label(m)}\nLMI {m["rate_hz"]:g} Hz, PC '
                     f'{"on" if m["passivity"] else "off"}; margin '
                     f'{margin_text(m["margin"], m["margin_next"])}', fontsize=7)
    handles = [plt.Line2D([], [], marker='s', ls='', color=c, label=v)
               for v, c in colors.items()]
    handles.append(plt.Line2D([], [], marker='o', ls='', mfc='none', mec='black',
                              label='scenario defaults'))
    fig.legend(handles=handles, loc='upper center', ncol=4, fontsize=8)
    fig.text(0.01, 0.003, footer, fontsize=7, family='monospace')
    fig.tight_layout(rect=(0, 0.6 / len(rows) / 2.7 + 0.01, 1, 1 - 0.35 / len(rows) / 2.7))
    save_figure(fig, path)


def margin_text(margin: float, nxt: float | None, none: str = 'not passive') -> str:
    """``x16 (x32 not)``: the margin and the grid's next factor, which is outside;
    ``x256 (grid end)`` when nothing within the grid is; ``none`` for 0."""
    if margin == 0.0:
        return none
    return f'x{margin:g} ' + ('(grid end)' if nxt is None else f'(x{nxt:g} not)')


def table(maps: list[dict[str, Any]]) -> str:
    """The results page's table of the maps (markdown)."""
    head = ('| scenario, device, link | gains | LMI [Hz] | passivity controller | defaults | '
            'lowest observer at the defaults [mJ] | passive margin | stable margin |')
    lines = [head, '|' + '---|' * 8]
    for m in maps:
        x0, y0 = m['default']
        at = next(p for p in m['points'] if p['x'] == x0 and p['y'] == y0)
        lines.append(
            f'| {row_label(m)} | {m["x"]} {x0:g}, {m["y"]} {y0:g} | {m["rate_hz"]:g} | '
            f'{"on" if m["passivity"] else "off"} | {at["verdict"]} | '
            f'{1e3 * at["observer_min_j"]:.2f} | {margin_text(m["margin"], m["margin_next"])}'
            f' | {margin_text(m["stable_margin"], m["stable_next"], "not stable")} |')
    return '\n'.join(lines) + '\n'


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(',') if v.strip())
    except ValueError:
        raise SystemExit(f'{what}: expected numbers like 5,20, got {text!r}') from None
    if any(not v > 0.0 for v in values):
        raise SystemExit(f'{what}: expected positive numbers, got {text!r}')
    return values


def run(args: argparse.Namespace) -> int:
    """Sweep, write the outputs, print the margins."""
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.zwidth import DEVICES, Variant, sweep

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
    devices = tuple(d for d in str(args.devices).split(',') if d)
    for d in devices:
        if d not in DEVICES:
            raise SystemExit(f'--devices: expected names among {", ".join(DEVICES)}, got '
                             f'{d!r}')
    plan = ({name: (devices, _floats(args.ve_delays_ms, '--ve-delays-ms'),
                    _floats(args.device_delays_ms, '--device-delays-ms'))
             for name in args.scenarios} if args.scenarios else DEFAULT_PLAN)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    maps = []
    for name, (devs, ve_delays, device_delays) in plan.items():
        sc = load_scenario(name)
        variants = [Variant(p, pc, axes) for axes in (
            ('penalty', 'contacts') if sc.contacts is not None else ('penalty',))
            for p in periods for pc in (False, True)]
        variants += [Variant(p, pc, device=d) for d in (devs if sc.linkage.task.point else ())
                     for p in periods for pc in (False, True)]
        variants += [Variant(sc.update_period, pc, ve_delay_ms=d)
                     for d in ve_delays for pc in (False, True)]
        variants += [Variant(sc.update_period, pc, device_delay_ms=d)
                     for d in device_delays for pc in (False, True)]
        for v in variants:
            m = sweep(sc, v, duration=args.duration)
            maps.append(m)
            print(table([m]).splitlines()[-1], flush=True)
    command = 'haptic-topology zwidth ' + ' '.join(sys.argv[2:])
    stamp = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
    commit = _commit()
    footer = f'{command}\n{stamp}, commit {commit}'
    (out / 'zwidth.json').write_text(json.dumps({'command': command, 'date': stamp,
                                                 'commit': commit, 'maps': maps},
                                                indent=1) + '\n', encoding='utf-8')
    (out / 'zwidth.md').write_text(table(maps), encoding='utf-8')
    written = [out / 'zwidth.json', out / 'zwidth.md']
    for name in FIGURES:
        group = [m for m in maps if figure_of(m) == name]
        if group:
            plot_maps(group, out / name, footer)
            written.append(out / name)
    print(f'wrote {", ".join(map(str, written))}')
    return 0
