"""Z-width maps of the penalty of eq. 13: where in ``k_tc`` x ``b_tc`` a run stays passive.

The Z-width of a haptic display (Colgate & Brown) is the range of impedances it renders
passively. Here the impedance is eq. 13's penalty, ``k_tc`` and ``b_tc`` (scaled by ``M_d``),
rendered by eq. 14 on a device model at the scenario's device period with the LMI updated
every ``update_period`` cycles. :func:`sweep` runs the offline simulation (deterministic) of a
scenario on a grid of gains and classifies each run:

* **passive**: the passivity observer (:mod:`haptic_topology.control.passivity`) never goes
  below ``-E_TOL`` (1 mJ) and the run is stable;
* **stable**: never saturates the wrench limit and its largest drift is at most twice that of
  the scenario's own gains at the same update rate, without the passivity controller;
* **unstable**: neither.

The grid is the scenario's gains times :data:`K_FACTORS` and :data:`B_FACTORS`, so the
defaults are a point of every map; their **margin** is the largest factor of ``k_tc`` (at the
default ``b_tc``) up to which every run of the map is passive. ``haptic-topology zwidth``
(:mod:`haptic_topology.sim.zwidth_command`) writes the maps as JSON and draws them; the
shipped maps (``config/zwidth.json``) let ``lmi_controller`` warn at configure about gains
outside them (:func:`outside_map`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import Scenario

#: The observer's lowest value (J) a passive run may reach (the issue's threshold).
E_TOL = 1e-3
#: Factors of the scenario's k_tc the sweep runs (1: the default).
K_FACTORS = (1.0, 4.0, 16.0, 64.0, 256.0)
#: Factors of the scenario's b_tc the sweep runs (1: the default; 0: no penalty damping).
B_FACTORS = (0.0, 1.0, 4.0)
#: LMI update periods (device cycles) swept at 1 kHz: 100 Hz and 25 Hz.
UPDATE_PERIODS = (10, 40)
PASSIVE, STABLE, UNSTABLE = 'passive', 'stable', 'unstable'


@dataclass(frozen=True)
class Point:
    """One run of a sweep: gains (N/(m kg), N s/(m kg)), its class and figures."""

    k_tc: float
    b_tc: float
    verdict: str
    observer_min_j: float
    max_distance_m: float
    saturated: bool
    pc_cycles: int

    def to_dict(self) -> dict[str, Any]:
        return {'k_tc': self.k_tc, 'b_tc': self.b_tc, 'verdict': self.verdict,
                'observer_min_j': self.observer_min_j, 'max_distance_m': self.max_distance_m,
                'saturated': self.saturated, 'pc_cycles': self.pc_cycles}


def run_point(sc: Scenario, k_tc: float, b_tc: float, passivity: bool,
              drift_bound: float) -> Point:
    """Simulate ``sc`` with the penalty gains and classify the run (module doc);
    ``drift_bound`` (m): the largest drift of a stable run."""
    trace = simulate(sc, gains=sc.gains.with_penalty(k_tc, b_tc),
                     passivity=PassivityConfig(enabled=passivity))
    s = trace.summary()
    limit = sc.device.wrench_limit
    applied = np.abs(trace.columns['applied'])
    saturated = bool(np.any(applied[np.all(np.isfinite(applied), axis=1)]
                            >= limit * (1.0 - 1e-12)))
    e_min = float(np.nanmin(trace.columns['passivity_observer']))
    dist = float(s['max_distance_m'])
    stable = not saturated and math.isfinite(dist) and dist <= drift_bound
    verdict = (PASSIVE if stable and e_min >= -E_TOL else STABLE if stable else UNSTABLE)
    return Point(k_tc, b_tc, verdict, e_min, dist, saturated,
                 int(s['energy_account']['passivity_cycles']))


def sweep(sc: Scenario, update_period: int, passivity: bool, duration: float | None = None,
          k_factors: tuple[float, ...] = K_FACTORS,
          b_factors: tuple[float, ...] = B_FACTORS) -> dict[str, Any]:
    """The map of ``sc`` at ``update_period`` cycles per LMI update, with or without the
    passivity controller, each run ``duration`` s long (None: the scenario's):
    ``{'scenario', 'update_period', 'rate_hz', 'passivity', 'default': [k, b],
    'drift_bound_m', 'margin', 'points': [...]}``."""
    sc = replace(sc, duration=sc.duration if duration is None else duration,
                 update_period=update_period)
    k0, b0 = float(sc.gains.k_tc), float(sc.gains.b_tc)
    ref = simulate(sc, passivity=PassivityConfig(enabled=False)).summary()
    bound = 2.0 * float(ref['max_distance_m'])
    points = [run_point(sc, k0 * fk, b0 * fb, passivity, bound)
              for fb in b_factors for fk in k_factors]
    out = {'scenario': sc.name, 'task': sc.linkage.task.value,
           'update_period': update_period, 'rate_hz': 1.0 / (sc.dt * update_period),
           'passivity': passivity, 'default': [k0, b0], 'drift_bound_m': bound,
           'duration_s': sc.duration, 'points': [p.to_dict() for p in points]}
    out['margin'] = margin(out)
    return out


def margin(m: dict[str, Any]) -> float:
    """The defaults' margin in a map: the largest factor ``f`` of ``k_tc`` such that every
    run at the default ``b_tc`` with ``k_tc <= f k_default`` is passive (0: the defaults are
    not)."""
    k0, b0 = m['default']
    row = sorted((p for p in m['points'] if p['b_tc'] == b0), key=lambda p: p['k_tc'])
    best = 0.0
    for p in row:
        if p['verdict'] != PASSIVE:
            break
        best = p['k_tc'] / k0 if k0 > 0.0 else math.inf
    return best


def passive_bound(m: dict[str, Any], b_tc: float, accept: tuple[str, ...] = (PASSIVE,)
                  ) -> float | None:
    """The largest ``k_tc`` of map ``m`` up to which every run is passive (``accept``: the
    verdicts that count), at the grid's ``b_tc`` nearest ``b_tc`` (None: not even the
    smallest)."""
    bs = sorted({p['b_tc'] for p in m['points']})
    b = min(bs, key=lambda v: abs(v - b_tc))
    best = None
    for p in sorted((p for p in m['points'] if p['b_tc'] == b), key=lambda p: p['k_tc']):
        if p['verdict'] not in accept:
            break
        best = p['k_tc']
    return best


def outside_map(maps: list[dict[str, Any]], scenario: str, update_period: int,
                passivity: bool, k_tc: float, b_tc: float) -> str | None:
    """Why ``k_tc`` lies outside the Z-width map of ``scenario`` (the map at the same update
    period and passivity controller, among ``maps``): beyond the largest ``k_tc`` up to which
    the map's runs are stable (passive or not) at the nearest ``b_tc``. Names the gain and
    the bounds (stable, and passive); None when it lies inside or no map fits."""
    for m in maps:
        if (m['scenario'], m['update_period'], m['passivity']) != (
                scenario, update_period, passivity):
            continue
        stable = passive_bound(m, b_tc, (PASSIVE, STABLE))
        if stable is not None and k_tc <= stable:
            return None
        passive = passive_bound(m, b_tc)
        return (f'k_tc = {k_tc:g} N/(m kg) is outside the Z-width map of scenario '
                f'{scenario} (b_tc = {b_tc:g}, LMI at {m["rate_hz"]:g} Hz, passivity '
                f'controller {"on" if passivity else "off"}): stable up to k_tc = '
                f'{"(none)" if stable is None else format(stable, "g")}, passive up to '
                f'{"(none)" if passive is None else format(passive, "g")}')
    return None


def load_maps(path: str | Path) -> list[dict[str, Any]]:
    """The maps of a ``zwidth.json`` (``{'maps': [...]}``); none if the file is missing."""
    p = Path(path)
    if not p.is_file():
        return []
    return list(json.loads(p.read_text(encoding='utf-8')).get('maps', []))
