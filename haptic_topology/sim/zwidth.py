"""Z-width maps: where in a plane of two gains a run stays passive and stable.

The Z-width of a haptic display (Colgate & Brown) is the range of impedances it renders
passively. :func:`sweep` runs the offline simulation (deterministic) of a scenario on a grid
of two gains (an **axis pair**) and classifies each run:

* ``penalty``: eq. 13's ``k_tc`` x ``b_tc`` (N/(m kg), N s/(m kg); scaled by ``M_d``),
  rendered by eq. 14;
* ``contacts``: the contact model's ``stiffness`` x ``damping`` (N/m, N s/m; eq. 1's
  ``F_env``, computed by the LMI every cycle, eq. 17), on a scenario with obstacles.

Each map holds one **variant**: the LMI updated every ``update_period`` device cycles, with
or without the passivity controller, on the scenario's device or a vendor device's
parameters (:data:`DEVICES`), with the VE or the device behind a link of the networking
page's one-way delays (whole cycles, no jitter or loss:
:func:`~haptic_topology.sim.lockstep.simulate`'s ``ve_delay`` and ``device_delay``). A run
is

* **passive**: the passivity observer (:mod:`haptic_topology.control.passivity`) never goes
  below ``-E_TOL`` (1 mJ) and the run is stable;
* **stable**: it never saturates the wrench limit and its largest drift is at most twice that
  of the same variant at the scenario's own gains without the passivity controller;
* **unstable**: neither.

The grid is the scenario's gains times :data:`X_FACTORS` and :data:`Y_FACTORS`, so the
defaults are a point of every map. Their **margin** along the first gain (at the default
second gain): the largest factor ``f`` of the grid such that every run from the default up to
``f`` times it is passive (``margin``) or stable (``stable_margin``), and the next factor of
the grid, the first that is not (``margin_next``, ``stable_next``; None: none within the
grid). ``haptic-topology zwidth`` (:mod:`haptic_topology.sim.zwidth_command`) writes the maps
and draws them; the shipped maps (``config/zwidth.json``) let ``lmi_controller`` warn at
configure about gains outside them (:func:`outside_map`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.device.maglev import DeviceParams, DeviceRealism, VelocitySource
from haptic_topology.errors import ConfigError
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import Scenario

#: The observer's lowest value (J) a passive run may reach (the issue's threshold).
E_TOL = 1e-3
#: Factors of the scenario's first gain the sweep runs (1: the default).
X_FACTORS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0)
#: Factors of the scenario's second gain the sweep runs (1: the default; 0: none).
Y_FACTORS = (0.0, 1.0, 4.0)
#: LMI update periods (device cycles) swept at 1 kHz: 100 Hz and 25 Hz.
UPDATE_PERIODS = (10, 40)
PASSIVE, STABLE, UNSTABLE = 'passive', 'stable', 'unstable'
#: The gain pairs a map sweeps: (first, second) gain names, as the warnings name them.
AXES = {'penalty': ('k_tc', 'b_tc'), 'contacts': ('contacts.stiffness', 'contacts.damping')}
#: Units of the gains.
UNITS = {'k_tc': 'N/(m kg)', 'b_tc': 'N s/(m kg)', 'contacts.stiffness': 'N/m',
         'contacts.damping': 'N s/m'}


@dataclass(frozen=True)
class DeviceModel:
    """A device's parameters for a map (per translation axis): ``mass`` (kg), viscous
    ``damping`` (N s/m, unknown to the controller: friction in eq. 9), ``max_force`` (N, the
    device's own limit), position ``quantization`` (m), ``velocity_cutoff_hz`` (Hz; 0: the
    exact velocity, else differenced positions through a first-order low-pass), and where
    the numbers come from (``source``)."""

    name: str
    label: str
    mass: float
    damping: float
    max_force: float
    quantization: float
    velocity_cutoff_hz: float
    source: str

    def params(self, sc: Scenario) -> DeviceParams:
        """The simulated device of scenario ``sc`` (a point grasp: force only) with these
        parameters; the scenario's hard stops, and its wrench limit where it is lower."""
        task = sc.linkage.task
        if not task.point:
            raise ConfigError(f'zwidth: device {self.name} renders a point grasp (force '
                              f'only); scenario {sc.name} is {task.value}')
        m = task.dim
        full = np.full(m, 1.0)
        diff = self.velocity_cutoff_hz > 0.0
        return replace(sc.device, mass=np.eye(m) * self.mass, christoffel=np.zeros((m, m)),
                       wrench_limit=np.minimum(sc.device.wrench_limit, self.max_force * full),
                       realism=DeviceRealism(
                           quantization=self.quantization * full,
                           velocity=VelocitySource.DIFFERENCE if diff else VelocitySource.MODEL,
                           velocity_cutoff_hz=self.velocity_cutoff_hz,
                           viscous=self.damping * full))


_UNKNOWN = 'the real device\'s mass and damping are not known here: the emulator\'s are used'
#: The emulated vendor devices (their emulators' default parameters).
DEVICES = {
    'forcedimension': DeviceModel(
        'forcedimension', 'Force Dimension (emulator)', 0.2, 2.0, 12.0, 1e-5, 0.0,
        'emulators/forcedimension/fd_emulator.c: FDEMU_MASS 0.2 kg, FDEMU_DAMPING 2 N s/m, '
        f'FDEMU_MAX_FORCE 12 N, FDEMU_RESOLUTION 10 um; {_UNKNOWN}'),
    'openhaptics': DeviceModel(
        # The emulator filters the differenced velocity by v += 0.2 (raw - v) each 1 ms:
        # 1 - exp(-2 pi f dt) = 0.2, f = 35.5 Hz.
        'openhaptics', 'OpenHaptics Touch (emulator)', 0.1, 1.0, 3.3, 0.055e-3,
        -math.log(0.8) / (2.0 * math.pi * 1e-3),
        'emulators/openhaptics/hd.c: HD_EMU_MASS 0.1 kg, HD_EMU_DAMPING 1 N s/m, '
        'HD_EMU_MAX_FORCE 3.3 N (a Touch\'s nominal), 0.055 mm encoders, velocity '
        f'filtered 0.2 per ms (35.5 Hz); {_UNKNOWN}'),
    'haply': DeviceModel(
        'haply', 'Haply Inverse3 (emulator)', 0.2, 2.0, math.inf, 1e-5, 0.0,
        'haptic_topology/remote/haply_emulator.py: --mass 0.2 kg, --damping 2 N s/m, '
        f'--quantum 10 um, no force limit (the scenario\'s); {_UNKNOWN}'),
}


@dataclass(frozen=True)
class Variant:
    """What a map holds fixed: ``axes`` (:data:`AXES`), LMI ``update_period`` (device
    cycles), the passivity controller on or off, the ``device`` (``scenario``: the
    scenario's; else a key of :data:`DEVICES`), and one-way link delays (ms) of the VE
    (``ve_delay_ms``) and of the device (``device_delay_ms``)."""

    update_period: int
    passivity: bool
    axes: str = 'penalty'
    device: str = 'scenario'
    ve_delay_ms: float = 0.0
    device_delay_ms: float = 0.0


@dataclass(frozen=True)
class Point:
    """One run of a sweep: the gains, its class and figures."""

    x: float
    y: float
    verdict: str
    observer_min_j: float
    max_distance_m: float
    saturated: bool
    pc_cycles: int

    def to_dict(self) -> dict[str, Any]:
        return {'x': self.x, 'y': self.y, 'verdict': self.verdict,
                'observer_min_j': self.observer_min_j, 'max_distance_m': self.max_distance_m,
                'saturated': self.saturated, 'pc_cycles': self.pc_cycles}


def defaults(sc: Scenario, axes: str) -> tuple[float, float]:
    """The scenario's own gains of the axis pair ``axes``."""
    if axes == 'penalty':
        return float(sc.gains.k_tc), float(sc.gains.b_tc)
    if axes == 'contacts':
        if sc.contacts is None:
            raise ConfigError(f'zwidth: scenario {sc.name} has no contacts to sweep')
        return float(sc.contacts.params.stiffness), float(sc.contacts.params.damping)
    raise ConfigError(f'zwidth: axes: expected one of {", ".join(AXES)}, got {axes!r}')


def run_point(sc: Scenario, v: Variant, x: float, y: float, drift_bound: float,
              passivity: bool | None = None) -> Point:
    """Simulate ``sc`` in variant ``v`` with the gains ``(x, y)`` of its axes and classify
    the run (module doc); ``drift_bound`` (m): the largest drift of a stable run;
    ``passivity``: default the variant's."""
    gains = sc.gains
    if v.axes == 'penalty':
        gains = sc.gains.with_penalty(x, y)
    else:
        assert sc.contacts is not None
        params = replace(sc.contacts.params, stiffness=x, damping=y)
        sc = replace(sc, contacts=replace(sc.contacts, params=params))
    device = None if v.device == 'scenario' else DEVICES[v.device].params(sc)
    trace = simulate(sc, gains=gains, device=device,
                     passivity=PassivityConfig(enabled=v.passivity if passivity is None
                                               else passivity),
                     ve_delay=cycles(v.ve_delay_ms, sc.dt),
                     device_delay=2 * cycles(v.device_delay_ms, sc.dt))
    s = trace.summary()
    limit = (sc.device if device is None else device).wrench_limit
    applied = np.abs(trace.columns['applied'])
    saturated = bool(np.any(applied[np.all(np.isfinite(applied), axis=1)]
                            >= limit * (1.0 - 1e-12)))
    e_min = float(np.nanmin(trace.columns['passivity_observer']))
    dist = float(s['max_distance_m'])
    stable = not saturated and math.isfinite(dist) and dist <= drift_bound
    verdict = (PASSIVE if stable and e_min >= -E_TOL else STABLE if stable else UNSTABLE)
    return Point(x, y, verdict, e_min, dist, saturated,
                 int(s['energy_account']['passivity_cycles']))


def cycles(ms: float, dt: float) -> int:
    """A delay of ``ms`` milliseconds in whole device cycles of ``dt`` s (nearest)."""
    return int(round(ms * 1e-3 / dt))


def sweep(sc: Scenario, v: Variant, duration: float | None = None,
          x_factors: tuple[float, ...] = X_FACTORS,
          y_factors: tuple[float, ...] = Y_FACTORS) -> dict[str, Any]:
    """The map of ``sc`` in variant ``v``, each run ``duration`` s long (None: the
    scenario's): the variant's fields, ``scenario``, ``task``, ``rate_hz``, ``x``/``y`` (the
    gains' names), ``default``, ``drift_bound_m``, ``points`` and the margins (module
    doc)."""
    sc = replace(sc, duration=sc.duration if duration is None else duration,
                 update_period=v.update_period)
    x0, y0 = defaults(sc, v.axes)
    bound = 2.0 * run_point(sc, v, x0, y0, math.inf, passivity=False).max_distance_m
    points = [run_point(sc, v, x0 * fx, y0 * fy, bound)
              for fy in y_factors for fx in x_factors]
    out: dict[str, Any] = {
        'scenario': sc.name, 'task': sc.linkage.task.value, 'axes': v.axes,
        'x': AXES[v.axes][0], 'y': AXES[v.axes][1], 'device': v.device,
        'device_label': 'scenario' if v.device == 'scenario' else DEVICES[v.device].label,
        'update_period': v.update_period, 'rate_hz': 1.0 / (sc.dt * v.update_period),
        'passivity': v.passivity, 've_delay_ms': v.ve_delay_ms,
        'device_delay_ms': v.device_delay_ms, 'default': [x0, y0], 'drift_bound_m': bound,
        'duration_s': sc.duration, 'points': [p.to_dict() for p in points]}
    out.update(margins(out))
    return out


def _row_bound(m: dict[str, Any], y: float, accept: tuple[str, ...], start: float
               ) -> tuple[float | None, float | None]:
    """Along the first gain at the grid's second gain ``y``, from ``start`` up: the largest
    value up to which every run's verdict is in ``accept``, and the next value of the grid
    (None: none)."""
    row = sorted((p for p in m['points'] if p['y'] == y and p['x'] >= start),
                 key=lambda p: p['x'])
    best = None
    for p in row:
        if p['verdict'] not in accept:
            return best, p['x']
        best = p['x']
    return best, None


def margins(m: dict[str, Any]) -> dict[str, float | None]:
    """The defaults' margins in map ``m`` (module doc): ``margin``, ``margin_next``,
    ``stable_margin``, ``stable_next`` as factors of the default first gain (``margin``
    0: the defaults themselves are not passive)."""
    x0, y0 = m['default']
    out: dict[str, float | None] = {}
    for name, accept in (('margin', (PASSIVE,)), ('stable_margin', (PASSIVE, STABLE))):
        best, nxt = _row_bound(m, y0, accept, x0)
        out[name] = 0.0 if best is None else best / x0
        out[name.replace('margin', 'next')] = None if nxt is None else nxt / x0
    return {'margin': out['margin'], 'margin_next': out['next'],
            'stable_margin': out['stable_margin'], 'stable_next': out['stable_next']}


def interval(m: dict[str, Any], gain: str, other: float, accept: tuple[str, ...] = (
        PASSIVE, STABLE)) -> tuple[float, float, bool, bool] | None:
    """Along ``gain`` (one of map ``m``'s two), at the grid's value of the other gain
    nearest ``other``: the run of grid values around the map's default of ``gain`` whose
    verdicts are all in ``accept``, as ``(lo, hi, lo is the grid's smallest, hi is the
    grid's largest)``; None when the default's own run is not."""
    first = gain == m['x']
    mine, theirs = ('x', 'y') if first else ('y', 'x')
    values = sorted({p[theirs] for p in m['points']})
    near = min(values, key=lambda v: abs(v - other))
    line = sorted((p for p in m['points'] if p[theirs] == near), key=lambda p: p[mine])
    at = [p[mine] for p in line]
    anchor = m['default'][0 if first else 1]
    if anchor not in at or line[at.index(anchor)]['verdict'] not in accept:
        return None
    i = j = at.index(anchor)
    while i > 0 and line[i - 1]['verdict'] in accept:
        i -= 1
    while j < len(line) - 1 and line[j + 1]['verdict'] in accept:
        j += 1
    return at[i], at[j], i == 0, j == len(line) - 1


def outside_map(maps: list[dict[str, Any]], scenario: str, update_period: int,
                passivity: bool, gains: dict[str, float], device: str = 'scenario'
                ) -> list[str]:
    """Why ``gains`` (name -> value, :data:`AXES`' names) lie outside the Z-width maps of
    ``scenario`` on ``device`` at ``update_period`` with the passivity controller on or off
    (without link delays), one line per gain: outside the run of stable grid values around
    the map's default (:func:`interval`, at the grid's value of the other gain nearest the
    configured one), or beyond the largest value the map swept. Names the gain and the
    bounds (stable, and passive). Empty: every gain inside, or no map fits."""
    lines = []
    for m in maps:
        if (m['scenario'], m['device'], m['update_period'], m['passivity'],
                m['ve_delay_ms'], m['device_delay_ms']) != (
                scenario, device, update_period, passivity, 0.0, 0.0):
            continue
        if m['x'] not in gains or m['y'] not in gains:
            continue
        for gain, other in ((m['x'], m['y']), (m['y'], m['x'])):
            value = gains[gain]
            stable = interval(m, gain, gains[other])
            if stable is not None and (stable[2] or value >= stable[0]) and value <= stable[1]:
                continue
            passive = interval(m, gain, gains[other], (PASSIVE,))
            unit = UNITS[gain]
            where = (f'{gain} = {value:g} {unit} is outside the Z-width map of scenario '
                     f'{scenario} ({m["device_label"]}, {other} = {gains[other]:g}, LMI at '
                     f'{m["rate_hz"]:g} Hz, passivity controller '
                     f'{"on" if passivity else "off"}): ')
            if stable is None:
                lines.append(where + f'not stable there even at the map\'s default {gain} = '
                             f'{m["default"][gain != m["x"]]:g}')
            elif value > stable[1] and stable[3]:
                lines.append(where + f'the map sweeps {gain} up to {stable[1]:g} {unit} '
                             f'(stable there, passive up to {_g(passive, 1)})')
            elif value > stable[1]:
                lines.append(where + f'stable up to {gain} = {stable[1]:g}, passive up to '
                             f'{_g(passive, 1)}')
            else:
                lines.append(where + f'stable from {gain} = {stable[0]:g} (not below), '
                             f'passive from {_g(passive, 0)}')
    return lines


def _g(v: tuple[float, float, bool, bool] | None, end: int) -> str:
    return '(none)' if v is None else format(v[end], 'g')


def load_maps(path: str | Path) -> list[dict[str, Any]]:
    """The maps of a ``zwidth.json`` (``{'maps': [...]}``); none if the file is missing."""
    p = Path(path)
    if not p.is_file():
        return []
    return list(json.loads(p.read_text(encoding='utf-8')).get('maps', []))
