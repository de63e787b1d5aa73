"""Z-width maps (haptic_topology.sim.zwidth) and the warning at configure about gains outside
them (haptic_topology.config.resolve.zwidth_warning)."""

from __future__ import annotations

from typing import Any

from haptic_topology.config.resolve import resolve_lmi_controller, zwidth_warning
from haptic_topology.config.settings import LmiControllerSettings
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.zwidth import PASSIVE, STABLE, UNSTABLE, margin, outside_map, sweep


def _map(verdicts: dict[tuple[float, float], str], default: tuple[float, float] = (10.0, 7.0),
         scenario: str = 'fig6', update_period: int = 1, passivity: bool = False
         ) -> dict[str, Any]:
    return {'scenario': scenario, 'update_period': update_period, 'rate_hz': 1000.0,
            'passivity': passivity, 'default': list(default),
            'points': [{'k_tc': k, 'b_tc': b, 'verdict': v} for (k, b), v in verdicts.items()]}


MAP = _map({(10.0, 7.0): PASSIVE, (40.0, 7.0): PASSIVE, (160.0, 7.0): STABLE,
            (640.0, 7.0): PASSIVE, (10.0, 0.0): PASSIVE, (40.0, 0.0): UNSTABLE})


def test_margin_and_bound() -> None:
    """The margin stops at the first run along k_tc that is not passive (a passive run
    beyond it does not count); a map whose defaults are not passive has none."""
    assert margin(MAP) == 4.0
    assert margin(_map({(10.0, 7.0): STABLE, (40.0, 7.0): PASSIVE})) == 0.0


def test_outside_map_names_the_gain_and_the_bound() -> None:
    maps = [MAP]
    assert outside_map(maps, 'fig6', 1, False, 40.0, 7.0) is None
    assert outside_map(maps, 'fig6', 1, False, 640.0, 7.0) is None     # stable up to 640
    msg = outside_map(maps, 'fig6', 1, False, 1000.0, 7.0)
    assert msg == ('k_tc = 1000 N/(m kg) is outside the Z-width map of scenario fig6 '
                   '(b_tc = 7, LMI at 1000 Hz, passivity controller off): stable up to '
                   'k_tc = 640, passive up to 40')
    # nearest b_tc of the grid: 1 -> 0, where only k_tc = 10 is stable (and passive)
    assert str(outside_map(maps, 'fig6', 1, False, 20.0, 1.0)).endswith(
        'stable up to k_tc = 10, passive up to 10')
    # another rate, controller or scenario: no map, no warning
    assert outside_map(maps, 'fig6', 10, False, 1e5, 7.0) is None
    assert outside_map(maps, 'fig6', 1, True, 1e5, 7.0) is None
    assert outside_map(maps, 'fig8', 1, False, 1e5, 7.0) is None


def test_configure_warns_outside_the_map() -> None:
    """lmi_controller's configuration with k_tc beyond the shipped map's bound: a warning
    naming the gain and the bound; the configuration itself is accepted."""
    sc = load_scenario('fig6')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='fig6', k_tc=1000.0), sc)
    assert c.gains.k_tc == 1000.0
    warning = zwidth_warning(c, [MAP])
    assert warning is not None and warning.startswith('k_tc = 1000 N/(m kg) is outside')
    assert warning.endswith('stable up to k_tc = 640, passive up to 40')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='fig6'), sc)
    assert zwidth_warning(c, [MAP]) is None


def test_sweep_of_a_point_device() -> None:
    """fig8_point (a 1 kg point device without damping, 1 kHz, LMI at 100 Hz): its own
    gains are passive; 256 times the stiffness (K T / 2 = 25.6 N s/m on an undamped device,
    far beyond Colgate-Schenkel's bound) is not. Deterministic: simulate runs."""
    sc = load_scenario('fig8_point')           # 2 s: the penalty acts from about 1 s on
    m = sweep(sc, 10, False, k_factors=(1.0, 256.0), b_factors=(1.0,))
    verdicts = [p['verdict'] for p in m['points']]
    assert verdicts[0] == PASSIVE and verdicts[1] != PASSIVE
    assert m['margin'] == 1.0 and m['rate_hz'] == 100.0
    assert m['points'][1]['observer_min_j'] < -1e-3
