"""Scenario files: linkage, initial state, device, user, gains and LMI timing of one run.

Layout (``config/scenarios/fig6.yaml``)::

    scenario:
      name: fig6
      linkage: ../linkages/table1_planar3.yaml   # relative to this file, or a linkage name
      q0: [-pi/4, pi/6, -pi/6]                   # rad; 'pi' expressions are accepted
      dq0: [0, 0, 0]
      duration: 2.0                              # s
      dt: 0.001                                  # device period (s)
      mode: penalty                              # default control law (CLI --mode overrides)
      device:
        offset: [0.005, 0.003, 0.0]              # initial device pose - VT hand pose
        mass: [1, 1, 1]                          # diagonal of M_d (eq. 9)
        christoffel: [0, 0, 0]                   # diagonal of C_d
        workspace: {lo: [...], hi: [...]}        # hard stops, absolute (m, rad); optional
        wrench_limit: [10, 10, 1]                # |u| per axis (N, N m)
      user: {type: constant_wrench, wrench: [0.4, 0, 0]}
      control: {k_pc: [...], b_pc: [...], k_tc: 10, b_tc: 7}
      lmi: {model: eq17, update_period: 1}       # device cycles per LMI update
      ve: {internal_step: 0.001, vt_coupling: true}      # RK4 step (s)
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.control.laws import ControlGains, ControlMode
from haptic_topology.control.lmi import LmiModel
from haptic_topology.device.maglev import DeviceParams
from haptic_topology.device.users import user_from_config
from haptic_topology.errors import ConfigError
from haptic_topology.model.linkage import Linkage, load_linkage
from haptic_topology.paths import resolve_config
from haptic_topology.validate import (
    as_bool,
    as_float,
    as_int,
    as_str,
    as_vector,
    check_keys,
    load_yaml,
)

_PI_EXPR = re.compile(r'^\s*([+-])?\s*(\d+(?:\.\d*)?)?\s*\*?\s*pi\s*(?:/\s*(\d+(?:\.\d*)?))?\s*$')


def _angle_list(value: Any, where: str, size: int) -> np.ndarray:
    """A list of numbers or strings like ``-pi/4``, ``2*pi/3``."""
    if not isinstance(value, list):
        raise ConfigError(f'{where}: expected a list of {size} numbers, got {value!r}')
    out = []
    for i, v in enumerate(value):
        if isinstance(v, str):
            m = _PI_EXPR.match(v)
            if m is None:
                raise ConfigError(f'{where}[{i}]: expected a number or an expression like '
                                  f'-pi/4, got {v!r}')
            sign = -1.0 if m.group(1) == '-' else 1.0
            factor = float(m.group(2)) if m.group(2) else 1.0
            div = float(m.group(3)) if m.group(3) else 1.0
            if div == 0.0:
                raise ConfigError(f'{where}[{i}]: division by zero in {v!r}')
            out.append(sign * factor * math.pi / div)
        else:
            out.append(as_float(v, f'{where}[{i}]'))
    if len(out) != size:
        raise ConfigError(f'{where}: expected {size} numbers, got {len(out)}')
    return np.array(out)


@dataclass(frozen=True)
class Scenario:
    """A validated scenario (SI units)."""

    name: str
    linkage: Linkage
    q0: np.ndarray
    dq0: np.ndarray
    duration: float
    dt: float
    mode: ControlMode
    device: DeviceParams
    device_offset: np.ndarray
    user: dict[str, Any]
    gains: ControlGains
    lmi_model: LmiModel
    update_period: int
    internal_step: float
    vt_coupling: bool
    source: str

    def with_linkage(self, linkage: Linkage) -> Scenario:
        """Same scenario on another linkage (the initial state must fit its dof)."""
        if linkage.task is not self.linkage.task:
            raise ConfigError(f'{linkage.source}: linkage.task is {linkage.task.value}, the '
                              f'scenario {self.name} needs {self.linkage.task.value}')
        q0, dq0 = self.q0, self.dq0
        if linkage.dof != self.linkage.dof:
            q0, dq0 = np.zeros(linkage.dof), np.zeros(linkage.dof)
        return replace(self, linkage=linkage, q0=q0, dq0=dq0)


def _diag(raw: Any, where: str, m: int, positive: bool) -> np.ndarray:
    return np.diag(as_vector(raw, where, m, lo=0.0, lo_open=positive))


def load_scenario(name_or_path: str) -> Scenario:
    """Load ``config/scenarios/<name>.yaml`` or a scenario file; errors name file and key."""
    path = resolve_config(name_or_path, 'scenarios')
    doc = load_yaml(path)
    src = str(path)
    top = check_keys(doc, src, required=('scenario',))
    w = f'{src}: scenario'
    raw = check_keys(top['scenario'], w, required=('linkage', 'q0', 'duration'), optional=(
        'name', 'description', 'dq0', 'dt', 'mode', 'device', 'user', 'control', 'lmi', 've'))
    link_ref = as_str(raw['linkage'], f'{w}.linkage')
    link_path = Path(link_ref)
    if not link_path.is_absolute() and (path.parent / link_path).is_file():
        link_path = path.parent / link_path
    linkage = load_linkage(resolve_config(str(link_path), 'linkages'))
    d, m = linkage.dof, linkage.task.dim
    q0 = _angle_list(raw['q0'], f'{w}.q0', d)
    dq0 = _angle_list(raw.get('dq0', [0.0] * d), f'{w}.dq0', d)
    duration = as_float(raw['duration'], f'{w}.duration', lo=0.0, lo_open=True, hi=3600.0)
    dt = as_float(raw.get('dt', 0.001), f'{w}.dt', lo=0.0, lo_open=True, hi=0.1)
    mode = ControlMode.PENALTY
    if 'mode' in raw:
        try:
            mode = ControlMode.parse(as_str(raw['mode'], f'{w}.mode'))
        except ValueError as exc:
            raise ConfigError(f'{w}.{exc}') from None

    dev = check_keys(raw.get('device', {}), f'{w}.device', optional=(
        'offset', 'mass', 'christoffel', 'workspace', 'wrench_limit'))
    offset = as_vector(dev.get('offset', [0.0] * m), f'{w}.device.offset', m)
    mass = _diag(dev.get('mass', [1.0] * m), f'{w}.device.mass', m, positive=True)
    chris = _diag(dev.get('christoffel', [0.0] * m), f'{w}.device.christoffel', m, False)
    lo = np.full(m, -np.inf)
    hi = np.full(m, np.inf)
    if 'workspace' in dev:
        ws = check_keys(dev['workspace'], f'{w}.device.workspace', required=('lo', 'hi'))
        lo = _angle_list(ws['lo'], f'{w}.device.workspace.lo', m)
        hi = _angle_list(ws['hi'], f'{w}.device.workspace.hi', m)
        if np.any(lo >= hi):
            raise ConfigError(f'{w}.device.workspace: expected lo < hi on every axis, got lo='
                              f'{lo.tolist()} hi={hi.tolist()}')
    limit = as_vector(dev.get('wrench_limit', [1e9] * m), f'{w}.device.wrench_limit', m,
                      lo=0.0, lo_open=True)
    device = DeviceParams(linkage.task, mass, chris, lo, hi, limit)

    user = raw.get('user', {'type': 'constant_wrench', 'wrench': [0.0] * m})
    user_from_config(user, linkage.task, f'{w}.user', np.zeros(m))  # validate now

    ctl = check_keys(raw.get('control', {}), f'{w}.control', required=('k_pc', 'b_pc'),
                     optional=('k_tc', 'b_tc'))
    gains = ControlGains(
        k_pc=as_vector(ctl['k_pc'], f'{w}.control.k_pc', m, lo=0.0),
        b_pc=as_vector(ctl['b_pc'], f'{w}.control.b_pc', m, lo=0.0),
        k_tc=as_float(ctl.get('k_tc', 0.0), f'{w}.control.k_tc', lo=0.0),
        b_tc=as_float(ctl.get('b_tc', 0.0), f'{w}.control.b_tc', lo=0.0))

    lmi = check_keys(raw.get('lmi', {}), f'{w}.lmi', optional=('model', 'update_period'))
    lmi_model = LmiModel(as_str(lmi.get('model', 'eq17'), f'{w}.lmi.model', ('eq17', 'eq20')))
    update_period = as_int(lmi.get('update_period', 10), f'{w}.lmi.update_period', lo=1,
                           hi=10000)
    ve = check_keys(raw.get('ve', {}), f'{w}.ve', optional=('internal_step', 'vt_coupling'))
    internal_step = as_float(ve.get('internal_step', 2.5e-4), f'{w}.ve.internal_step',
                             lo=0.0, lo_open=True, hi=dt)
    coupling = as_bool(ve.get('vt_coupling', True), f'{w}.ve.vt_coupling')
    name = as_str(raw.get('name', path.stem), f'{w}.name')
    return Scenario(name, linkage, q0, dq0, duration, dt, mode, device, offset, dict(user),
                    gains, lmi_model, update_period, internal_step, coupling, src)
