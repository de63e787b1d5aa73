"""Z-width maps (haptic_topology.sim.zwidth), the links and devices they sweep, and the warning
at configure about gains outside them (haptic_topology.config.resolve.zwidth_warning)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.config.resolve import (
    configure_hosted,
    resolve_lmi_controller,
    zwidth_warning,
)
from haptic_topology.config.settings import LmiControllerSettings
from haptic_topology.control.passivity import EnergyAccount, PassivityConfig
from haptic_topology.device.backend import create_backend
from haptic_topology.device.maglev import VelocitySource
from haptic_topology.errors import ConfigError
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import SimStep, simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.zwidth import (
    DEVICES,
    PASSIVE,
    STABLE,
    UNSTABLE,
    Variant,
    load_maps,
    margins,
    outside_map,
    run_point,
    sweep,
)


def _map(verdicts: dict[tuple[float, float], str], default: tuple[float, float] = (10.0, 7.0),
         scenario: str = 'fig6', update_period: int = 1, passivity: bool = False,
         axes: str = 'penalty') -> dict[str, Any]:
    x, y = ('k_tc', 'b_tc') if axes == 'penalty' else ('contacts.stiffness',
                                                       'contacts.damping')
    return {'scenario': scenario, 'axes': axes, 'x': x, 'y': y, 'device': 'scenario',
            'device_label': 'scenario', 'update_period': update_period, 'rate_hz': 1000.0,
            'passivity': passivity, 've_delay_ms': 0.0, 'device_delay_ms': 0.0,
            'default': list(default),
            'points': [{'x': k, 'y': b, 'verdict': v} for (k, b), v in verdicts.items()]}


MAP = _map({(10.0, 7.0): PASSIVE, (40.0, 7.0): PASSIVE, (160.0, 7.0): STABLE,
            (640.0, 7.0): PASSIVE, (2560.0, 7.0): UNSTABLE,
            (10.0, 0.0): PASSIVE, (40.0, 0.0): UNSTABLE, (160.0, 0.0): UNSTABLE,
            (640.0, 0.0): UNSTABLE, (2560.0, 0.0): UNSTABLE})


def test_margins() -> None:
    """The passive margin stops at the first run along k_tc that is not passive (a passive
    run beyond it does not count), the stable one at the first unstable run; each with the
    grid's next factor, the first outside; a map whose defaults are not passive has none."""
    assert margins(MAP) == {'margin': 4.0, 'margin_next': 16.0, 'stable_margin': 64.0,
                            'stable_next': 256.0}
    m = margins(_map({(10.0, 7.0): STABLE, (40.0, 7.0): PASSIVE}))
    assert m == {'margin': 0.0, 'margin_next': 1.0, 'stable_margin': 4.0, 'stable_next': None}


def test_outside_map_names_the_gain_and_the_bound() -> None:
    maps = [MAP]
    ok = {'k_tc': 40.0, 'b_tc': 7.0}
    assert outside_map(maps, 'fig6', 1, False, ok) == []
    assert outside_map(maps, 'fig6', 1, False, {'k_tc': 640.0, 'b_tc': 7.0}) == []
    assert outside_map(maps, 'fig6', 1, False, {'k_tc': 1000.0, 'b_tc': 7.0}) == [
        'k_tc = 1000 N/(m kg) is outside the Z-width map of scenario fig6 (scenario, b_tc = 7, '
        'LMI at 1000 Hz, passivity controller off): stable up to k_tc = 640, passive up to 40']
    # nearest b_tc of the grid: 1 -> 0, where only k_tc = 10 is stable (and passive)
    lines = outside_map(maps, 'fig6', 1, False, {'k_tc': 20.0, 'b_tc': 1.0})
    assert len(lines) == 1 and lines[0].endswith('stable up to k_tc = 10, passive up to 10')
    # the second gain: beyond the largest b_tc swept (all stable up to it at k_tc 10)
    assert outside_map(maps, 'fig6', 1, False, {'k_tc': 10.0, 'b_tc': 30.0}) == [
        'b_tc = 30 N s/(m kg) is outside the Z-width map of scenario fig6 (scenario, k_tc = '
        '10, LMI at 1000 Hz, passivity controller off): the map sweeps b_tc up to 7 N s/(m '
        'kg) (stable there, passive up to 7)']
    # another rate, controller, scenario or device: no map, no warning
    assert outside_map(maps, 'fig6', 10, False, {'k_tc': 1e5, 'b_tc': 7.0}) == []
    assert outside_map(maps, 'fig6', 1, True, {'k_tc': 1e5, 'b_tc': 7.0}) == []
    assert outside_map(maps, 'fig8', 1, False, {'k_tc': 1e5, 'b_tc': 7.0}) == []
    assert outside_map(maps, 'fig6', 1, False, {'k_tc': 1e5, 'b_tc': 7.0}, 'haply') == []


CONTACT_MAP = _map({(2000.0, 60.0): PASSIVE, (8000.0, 60.0): STABLE,
                    (32000.0, 60.0): UNSTABLE, (2000.0, 0.0): PASSIVE,
                    (8000.0, 0.0): STABLE, (32000.0, 0.0): UNSTABLE,
                    (2000.0, 240.0): UNSTABLE, (8000.0, 240.0): UNSTABLE,
                    (32000.0, 240.0): UNSTABLE},
                   default=(2000.0, 60.0), scenario='wall', update_period=10,
                   axes='contacts')


def test_configure_warns_outside_the_map() -> None:
    """lmi_controller's configuration with k_tc beyond the shipped map's bound: a warning
    naming the gain and the bound; the configuration itself is accepted."""
    sc = load_scenario('fig6')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='fig6', k_tc=1000.0), sc)
    assert c.gains.k_tc == 1000.0
    warning = zwidth_warning(c, [MAP])
    assert len(warning) == 1 and warning[0].startswith('k_tc = 1000 N/(m kg) is outside')
    assert warning[0].endswith('stable up to k_tc = 640, passive up to 40')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='fig6'), sc)
    assert zwidth_warning(c, [MAP]) == []
    assert zwidth_warning(c, [MAP], passivity=True) == []      # no map with the PC on


def test_configure_warns_about_contact_stiffness_and_damping() -> None:
    """A scenario with obstacles: its contact stiffness and damping checked against its
    contact map, each named with its bound; inside the map, no line."""
    sc = load_scenario('wall')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='wall'), sc)
    assert zwidth_warning(c, [CONTACT_MAP]) == []
    stiff = replace(sc, contacts=replace(sc.contacts, params=replace(
        sc.contacts.params, stiffness=10000.0, damping=100.0)))
    c = resolve_lmi_controller(LmiControllerSettings(scenario='wall'), stiff)
    assert zwidth_warning(c, [CONTACT_MAP]) == [
        'contacts.stiffness = 10000 N/m is outside the Z-width map of scenario wall '
        '(scenario, contacts.damping = 100, LMI at 1000 Hz, passivity controller off): stable '
        'up to contacts.stiffness = 8000, passive up to 2000',
        'contacts.damping = 100 N s/m is outside the Z-width map of scenario wall (scenario, '
        'contacts.stiffness = 10000, LMI at 1000 Hz, passivity controller off): stable up to '
        'contacts.damping = 60, passive up to (none)']


def test_sweep_of_a_point_device() -> None:
    """fig8_point (a 1 kg point device without damping, 1 kHz, LMI at 100 Hz): its own
    gains are passive; 256 times the stiffness (K T / 2 = 25.6 N s/m on an undamped device,
    far beyond Colgate-Schenkel's bound) is not. Deterministic: simulate runs."""
    sc = load_scenario('fig8_point')           # 2 s: the penalty acts from about 1 s on
    m = sweep(sc, Variant(10, False), x_factors=(1.0, 256.0), y_factors=(1.0,))
    verdicts = [p['verdict'] for p in m['points']]
    assert verdicts[0] == PASSIVE and verdicts[1] != PASSIVE
    assert (m['margin'], m['margin_next']) == (1.0, 256.0) and m['rate_hz'] == 100.0
    assert m['points'][1]['observer_min_j'] < -1e-3
    assert (m['x'], m['y'], m['device'], m['ve_delay_ms']) == ('k_tc', 'b_tc', 'scenario', 0.0)


def test_sweep_of_the_contacts() -> None:
    """wall's contact stiffness x damping: the contact gains are what changes (the runs
    differ from the defaults' only where the contact gains do)."""
    sc = replace(load_scenario('wall'), duration=0.6)      # the tip touches at 0.26 s
    m = sweep(sc, Variant(10, False, 'contacts'), x_factors=(1.0, 4.0), y_factors=(1.0,))
    assert (m['x'], m['y'], m['default']) == ('contacts.stiffness', 'contacts.damping',
                                              [2000.0, 60.0])
    a, b = m['points']
    assert (a['x'], b['x']) == (2000.0, 8000.0)
    assert a['max_distance_m'] != b['max_distance_m']


def test_vendor_devices_are_their_emulators_parameters() -> None:
    """The vendor devices' models carry their emulators' defaults (emulators/, the Haply
    emulator's options) and are refused for a rigid grasp (force-only devices)."""
    sc = load_scenario('fig8_point')
    fd = DEVICES['forcedimension'].params(sc)
    assert np.array_equal(fd.mass, np.eye(2) * 0.2)
    assert np.array_equal(fd.realism.viscous, [2.0, 2.0])
    assert np.array_equal(fd.wrench_limit, [12.0, 12.0])      # 12 N < the scenario's 20
    oh = DEVICES['openhaptics'].params(sc)
    assert np.array_equal(oh.wrench_limit, [3.3, 3.3])
    assert oh.realism.velocity is VelocitySource.DIFFERENCE
    assert np.array_equal(oh.realism.quantization, [0.055e-3, 0.055e-3])
    # the emulator's filter: v += 0.2 (raw - v) per 1 ms cycle
    assert 1.0 - np.exp(-2.0 * np.pi * oh.realism.velocity_cutoff_hz * 1e-3) == \
        pytest.approx(0.2, rel=1e-12)
    haply = DEVICES['haply'].params(sc)
    assert np.array_equal(haply.wrench_limit, sc.device.wrench_limit)
    emulator = (Path(__file__).parents[3] / 'emulators/forcedimension/fd_emulator.c').read_text()
    assert 'env_num("FDEMU_MASS", 0.2)' in emulator
    assert 'env_num("FDEMU_DAMPING", 2.0)' in emulator
    hd = (Path(__file__).parents[3] / 'emulators/openhaptics/hd.c').read_text()
    assert 'env_double("HD_EMU_MASS", 0.1)' in hd and 'env_double("HD_EMU_DAMPING", 1.0)' in hd
    with pytest.raises(ConfigError, match='renders a point grasp'):
        DEVICES['haply'].params(load_scenario('fig8'))


def _updates_taken(**kw: int) -> list[int]:
    seen: list[int] = []

    def obs(s: SimStep) -> None:
        seen.append(s.controller.updates)
    simulate(replace(load_scenario('fig8_point'), duration=0.3), observer=obs, **kw)
    return seen


def test_a_ve_behind_a_link_answers_late() -> None:
    """With the VE ``D`` cycles away each way, every LMI update is taken ``2 D`` cycles
    later than without the link (the hand input goes, the update comes back)."""
    near, far = _updates_taken(), _updates_taken(ve_delay=7)
    assert near[-1] > 20
    assert far[14:] == near[:-14]
    assert far[:14] == [1] * 14                  # only the initial state until then


def test_a_device_behind_a_link_takes_the_command_late() -> None:
    """With ``device_delay`` N the wrench the device applies in cycle k is the command
    answered in cycle k - 1 - N (hosted: k - 1)."""
    sc = replace(load_scenario('fig8_point'), duration=0.3)
    for n in (0, 2):
        tr = simulate(sc, device_delay=n)
        applied, command = tr.columns['applied'], tr.columns['command']
        assert np.abs(command).max() < 20.0              # within the limit: not clamped
        assert np.array_equal(applied[1 + n:], command[:-1 - n])


def test_links_are_deterministic() -> None:
    sc = replace(load_scenario('fig8'), duration=0.3)
    a = simulate(sc, ve_delay=5, device_delay=2).columns
    b = simulate(sc, ve_delay=5, device_delay=2).columns
    assert all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)


def _own(m: dict[str, Any]) -> bool:
    """A map of a scenario's own configuration: its device, no link, the passivity controller
    off (``passivity: auto`` on a simulated device)."""
    return (m['device'] == 'scenario' and not m['ve_delay_ms'] and not m['device_delay_ms']
            and not m['passivity'])


def test_every_scenarios_defaults_sit_inside_their_shipped_map() -> None:
    """config/zwidth.json: each map's defaults are the scenario's current gains (else the
    maps are stale: regenerate them); in each map of a scenario's own configuration the
    defaults are passive or stable, no gain is warned about, and simulating them again gives
    the shipped run exactly (the maps are the code's)."""
    shipped = json.loads((config_dir() / 'zwidth.json').read_text())
    assert shipped['maps'] == load_maps(config_dir() / 'zwidth.json')
    own = [m for m in shipped['maps'] if _own(m)]
    assert {m['scenario'] for m in own} == {'fig8', 'spatial_arm4', 'fig8_point',
                                          'spatial_arm4_point', 'wall'}
    for m in shipped['maps']:
        sc = load_scenario(m['scenario'])
        now = ([float(sc.gains.k_tc), float(sc.gains.b_tc)] if m['axes'] == 'penalty' else
               [sc.contacts.params.stiffness, sc.contacts.params.damping])
        assert m['default'] == now, f'{m["scenario"]}: regenerate config/zwidth.json'
    for m in own:
        sc = load_scenario(m['scenario'])
        c = resolve_lmi_controller(LmiControllerSettings(scenario=sc.name), replace(
            sc, update_period=m['update_period']))
        assert zwidth_warning(c, own) == [], m['scenario']
        x0, y0 = m['default']
        at = next(p for p in m['points'] if (p['x'], p['y']) == (x0, y0))
        assert at['verdict'] in (PASSIVE, STABLE), (m['scenario'], m['update_period'])
        assert m['stable_margin'] >= 1.0
        again = run_point(replace(sc, duration=m['duration_s'],
                                  update_period=m['update_period']),
                          Variant(m['update_period'], False, m['axes']), x0, y0,
                          m['drift_bound_m'])
        assert again.to_dict() == at, (m['scenario'], m['axes'], m['update_period'])


def test_zwidth_command_writes_maps_figures_and_table(tmp_path: Path) -> None:
    """``haptic-topology zwidth wall --device-delays-ms 1``: the penalty and contact maps and
    the device link's, their figures stamped, the table of margins."""
    out = tmp_path / 'zw'
    subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'zwidth', 'wall', '--out',
                    str(out), '--duration', '0.3', '--update-periods', '10',
                    '--device-delays-ms', '1'], check=True, capture_output=True, text=True,
                   timeout=600)
    doc = json.loads((out / 'zwidth.json').read_text())
    assert doc['command'].startswith('haptic-topology zwidth wall --out ')
    keys = [(m['axes'], m['passivity'], m['device_delay_ms']) for m in doc['maps']]
    assert keys == [('penalty', False, 0.0), ('penalty', True, 0.0), ('contacts', False, 0.0),
                    ('contacts', True, 0.0), ('penalty', False, 1.0), ('penalty', True, 1.0)]
    assert (out / 'zwidth.png').is_file() and (out / 'zwidth_contacts.png').is_file()
    assert (out / 'zwidth_delays.png').is_file()
    table = (out / 'zwidth.md').read_text().splitlines()
    assert len(table) == 2 + 6 and table[-1].startswith('| wall, device link 1 ms | k_tc 200')


def test_the_driver_warns_for_its_own_device() -> None:
    """device_driver hosting lmi_controller (``configure_hosted``): ``passivity: auto`` turns
    the controller on for a vendor device rendering a point grasp, and the gains are checked
    against that device's shipped map (named in the line), not the scenario's device's
    (on the emulated Force Dimension device with the passivity controller on, no run of the
    map is stable, so b_tc is warned about too)."""
    sc = load_scenario('fig8_point')
    c = resolve_lmi_controller(LmiControllerSettings(scenario='fig8_point', k_tc=1e5), sc)
    assert c.passivity_auto
    for backend, label in (('forcedimension', 'Force Dimension (emulator)'),
                           ('sim_maglev', 'scenario')):
        energy = EnergyAccount(2, c.passivity or PassivityConfig(), sc.dt, np.eye(2))
        lines: list[str] = []
        configure_hosted(c, energy, create_backend(backend, False), lines.append)
        on = backend != 'sim_maglev'
        assert energy.params[0] == (1.0 if on else 0.0)
        if not on:          # the scenario's own device: lmi_controller warns itself
            assert lines == [] and zwidth_warning(c)[0].startswith(
                f'k_tc = 100000 N/(m kg) is outside the Z-width map of scenario fig8_point '
                f'({label}, b_tc = 50, LMI at 100 Hz, passivity controller off)')
            continue
        assert len(lines) == 2 and lines[0].startswith(
            f'k_tc = 100000 N/(m kg) is outside the Z-width map of scenario fig8_point '
            f'({label}, b_tc = 50, LMI at 100 Hz, passivity controller on)')
        assert lines[1].startswith('b_tc = 50 N s/(m kg) is outside') and lines[1].endswith(
            "not stable there even at the map's default b_tc = 50")
