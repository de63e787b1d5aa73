"""The passivity controller on the wall clock (issue 59): fig6 with an unstable penalty
(``k_tc`` 1e4 N/(m kg), ``b_tc`` 0, beyond the Colgate-Schenkel bound of the 1 kg maglev at
1 kHz) run on the real-time graph (``haptic-topology run``, hosted layout) with the passivity
controller enabled and disabled, one run at a time, and the same two runs offline
(``simulate``, exact).

Per run: the passivity observer's lowest and last value and the cycles the controller acted
(the graph's: the controller's last ``/diagnostics`` status in the bag, at most one status
period before the run's end; offline: the account's), the drift (max and final, mm) and, on
the wall clock, the fraction of states answered.

Run from the repository root::

    python bench/passivity_wall_clock.py [--duration 2] [--out bags/passivity_wall_clock]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bringup.options import param_overrides
from haptic_topology.bringup.run import run_graph
from haptic_topology.bringup.watch import CONTROLLER_STATUS
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario

K_TC, B_TC = 1e4, 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--duration', type=float, default=2.0, help='s of each run')
    ap.add_argument('--out', type=Path, default=Path('bags/passivity_wall_clock'))
    a = ap.parse_args()
    sc = replace(load_scenario('fig6'), duration=a.duration)
    gains = sc.gains.with_penalty(K_TC, B_TC)
    rows = []
    for on in (True, False):
        s = simulate(sc, gains=gains, passivity=PassivityConfig(enabled=on)).summary()
        acct = s['energy_account']
        rows.append(('simulate', on, 1e3 * acct['passivity_observer_min_j'],
                     1e3 * acct['passivity_observer_j'], acct['passivity_cycles'],
                     1e3 * s['max_distance_m'], 1e3 * s['final_distance_m'], 100.0))
    for on in (True, False):
        bag = a.out / ('enabled' if on else 'disabled')
        codes = run_graph('fig6', 'penalty', a.duration, bag, config_dir() /
                          'haptic_topology.yaml', 'hosted', startup_timeout=90.0,
                          overrides=param_overrides([
                              f'lmi_controller:k_tc:={K_TC}', f'lmi_controller:b_tc:={B_TC}',
                              f'lmi_controller:passivity:={"enabled" if on else "disabled"}']))
        if any(codes.values()):
            raise SystemExit(f'run {bag}: exit codes {codes}')
        graph = read_graph_bag(bag)
        st = graph.diagnostics.get(CONTROLLER_STATUS, {})    # its last status
        run = graph.trace.summary()
        answered = graph.loop.get('device_answered_fraction')
        rows.append(('run (wall clock)', on, 1e3 * float(st['passivity_observer_min_j']),
                     1e3 * float(st['passivity_observer_j']), int(st['passivity_cycles']),
                     1e3 * run['max_distance_m'], 1e3 * run['final_distance_m'],
                     float('nan') if answered is None else 100.0 * answered))
    print(f'fig6, k_tc {K_TC:g} N/(m kg), b_tc {B_TC:g}, {a.duration:g} s\n')
    print('| run | passivity ctrl | observer min [mJ] | observer end [mJ] | acted [cycles] '
          '| max drift [mm] | final drift [mm] | answered [%] |')
    print('|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(f'| {r[0]} | {"on" if r[1] else "off"} | {r[2]:.3f} | {r[3]:.3f} | {r[4]} | '
              f'{r[5]:.3f} | {r[6]:.3f} | {r[7]:.2f} |')


if __name__ == '__main__':
    main()
