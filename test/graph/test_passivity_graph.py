"""The passivity controller in the graph: fig6 with a penalty 1,000 times stiffer
and no damping (``k_tc`` 1e4 N/(m kg), ``b_tc`` 0: beyond the Colgate-Schenkel bound of a 1 kg
device at 1 kHz, unstable in ``simulate``), run with ``run_graph`` on the real-time graph
(hosted layout) with the controller enabled and disabled; and in lock-step, where the bag's
energy account (the controller's last ``/diagnostics`` status) is ``simulate``'s, exactly.

What holds on any machine is asserted, nothing about timing: the controller's last
``/diagnostics`` status in the bag says it was on and acted (cycles > 0) in the run with it,
off and never acting in the run without; the observer of the run without it went below zero
(the penalty without damping generates energy whatever the periods). The figures of both runs
(observer minimum and end, drift) are printed by ``bench/passivity_wall_clock.py``.

Every graph runs in a domain of its own (``spare_domains``); every wait has a deadline.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from haptic_topology.bag.analyze import reduce_bag
from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bringup.options import param_overrides
from haptic_topology.bringup.run import run_graph
from haptic_topology.bringup.watch import CONTROLLER_STATUS
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import format_energy

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
DURATION = 2.0          # s of wall clock from engagement: the VT reaches the constraint at ~0.9 s


def _last_controller_status(bag: Path) -> dict[str, str]:
    """The key/values of the controller's last ``/diagnostics`` status in ``bag``."""
    decode = decoder()
    last: dict[str, str] = {}
    for raw in iter_messages(open_bag(bag), ['/diagnostics']):
        for status in decode(raw).status:
            if status.name == CONTROLLER_STATUS:
                last = {kv.key: kv.value for kv in status.values}
    return last


def _run(tmp_path: Path, passivity: str, domain: int, clock: str = 'wall',
         duration: float = DURATION) -> Path:
    bag = tmp_path / f'fig6_stiff_{passivity}_{clock}'
    codes = run_graph('fig6', 'penalty', duration, bag, PARAMS, 'hosted',
                      startup_timeout=90.0, domain_id=domain, clock=clock,
                      overrides=param_overrides(['lmi_controller:k_tc:=10000.0',
                                                 'lmi_controller:b_tc:=0.0',
                                                 f'lmi_controller:passivity:={passivity}']))
    assert all(c == 0 for c in codes.values()), codes
    return bag


def test_wall_clock_graph_runs_the_passivity_controller_on_an_unstable_penalty(
        tmp_path: Path, spare_domains: list[int]) -> None:
    on = _last_controller_status(_run(tmp_path, 'enabled', spare_domains[0]))
    off = _last_controller_status(_run(tmp_path, 'disabled', spare_domains[1]))
    assert on['passivity_controller'] == 'on' and int(on['passivity_cycles']) > 0, on
    assert off['passivity_controller'] == 'off' and int(off['passivity_cycles']) == 0, off
    assert float(off['passivity_observer_min_j']) < 0.0, off


def test_lockstep_bag_has_the_energy_account_of_simulate(
        tmp_path: Path, spare_domains: list[int]) -> None:
    """Lock-step, the controller enabled: ``analyze``'s figures of the bag carry the
    controller's account at the last state, which is ``simulate``'s bit for bit (every figure:
    work per axis and part, the VT end's, observer, its minimum, the cycles the controller
    acted, when), and the energy table prints the same row."""
    duration = 0.3
    bag = _run(tmp_path, 'enabled', spare_domains[2], 'lockstep', duration)
    sc = replace(load_scenario('fig6'), duration=duration)
    offline = simulate(sc, gains=sc.gains.with_penalty(1e4, 0.0),
                       passivity=PassivityConfig(enabled=True)).summary()
    graph = reduce_bag(bag, 'fig6', plot=False).summary
    assert offline['energy_account']['passivity_cycles'] > 0
    assert graph['energy_account'] == offline['energy_account']
    assert format_energy([('fig6', graph)]) == format_energy([('fig6', offline)])
