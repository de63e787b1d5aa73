"""``haptic-topology simulate SCENARIO --mode penalty|acceleration_only --out DIR``.

Runs the offline lock-step simulation and writes ``trace.parquet`` (``--csv``: also
``trace.csv``), ``plot.png``, ``energy.png`` (:mod:`haptic_topology.sim.energy_plots`) and
``summary.json`` into DIR, and prints the summary and energy tables.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from haptic_topology.paths import scenario_help
from haptic_topology.vocabulary import LAW_MODES

if TYPE_CHECKING:
    import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('scenario', help=scenario_help())
    parser.add_argument('--mode', choices=LAW_MODES,
                        help='control law: eq. 14 (penalty) or eq. 10 (acceleration_only); '
                        "default: the scenario's")
    parser.add_argument('--out', required=True, type=Path,
                        help='output directory (created; trace.parquet, plot.png, '
                        'summary.json)')
    parser.add_argument('--csv', action='store_true',
                        help='also write the trace as trace.csv')
    parser.add_argument('--linkage', help='replace the scenario linkage (YAML or URDF file, '
                        'or robot:NAME, a robot of example-robot-data, e.g. robot:ur5: an '
                        'optional extra, make robots)')
    parser.add_argument('--q0', metavar='Q,Q,...',
                        help='initial joint positions (rad / m), comma-separated, e.g. '
                        "--q0=0,pi/6,-pi/3; needed with a --linkage of another number of joints")
    parser.add_argument('--duration', type=float, help='override the duration (s)')
    parser.add_argument('--blend', type=float,
                        help='continuous penalty weight near the rank threshold: 0 = hard '
                        'switching (the paper), e.g. 1 = ramp over [tol, 2 tol]')


def parse_q0(text: str, dof: int) -> np.ndarray:
    """``--q0``: ``dof`` comma-separated numbers or expressions like ``-pi/4``."""
    from haptic_topology.validate import as_angles

    def value(item: str) -> float | str:
        try:
            return float(item)
        except ValueError:
            return item.replace(' ', '')
    return as_angles([value(v) for v in text.split(',')], '--q0', dof)


def run(args: argparse.Namespace) -> int:
    """Simulate, write the outputs, print the table; errors surface as HapticTopologyError."""
    # Imported here so that `haptic-topology --help` does not load Pinocchio and matplotlib.
    from haptic_topology.model.linkage import load_linkage
    from haptic_topology.sim.energy_plots import plot_energy
    from haptic_topology.sim.lockstep import simulate
    from haptic_topology.sim.plots import plot_trace
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.trace import format_energy, format_summary
    from haptic_topology.sim.trace_io import write_trace
    from haptic_topology.vocabulary import ControlMode

    scenario = load_scenario(args.scenario)
    if args.linkage or args.q0 is not None:
        linkage = load_linkage(args.linkage) if args.linkage else scenario.linkage
        q0 = None if args.q0 is None else parse_q0(args.q0, linkage.dof)
        scenario = scenario.with_linkage(linkage, q0)
    for note in scenario.linkage.notes:
        print(note)
    if args.duration is not None:
        if not args.duration > 0.0:
            raise SystemExit(f'--duration: expected a positive number of seconds, got '
                             f'{args.duration}')
        scenario = replace(scenario, duration=args.duration)
    if args.blend is not None:
        if not args.blend >= 0.0:
            raise SystemExit(f'--blend: expected a number >= 0, got {args.blend}')
        lk = scenario.linkage
        scenario = replace(scenario, linkage=replace(
            lk, constraints=replace(lk.constraints, blend=args.blend)))
    mode = ControlMode.parse(args.mode) if args.mode else scenario.mode
    trace = simulate(scenario, mode)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    traces = [out / 'trace.parquet'] + ([out / 'trace.csv'] if args.csv else [])
    for path in traces:
        write_trace(trace, path)
    plot_trace(trace, out / 'plot.png', scenario.linkage,
               obstacles=scenario.contacts.obstacles if scenario.contacts else ())
    plot_energy(trace, out / 'energy.png')
    summary = trace.summary()
    summary['linkage'] = scenario.linkage.name
    (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n', encoding='utf-8')
    print(format_summary([summary]))
    print()
    print(format_energy([(scenario.name, summary)]))
    print(f'wrote {", ".join(str(p) for p in traces)}, {out / "plot.png"}, '
          f'{out / "energy.png"}, {out / "summary.json"}')
    return 0
