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
      gravity: [0, 0, 0]                         # m/s^2, world; default: the linkage's
      grasp: {link: link2, point: [0.02, 0, 0]}  # optional: held elsewhere than the linkage
                                                 # file says (point m, default the COM)
      task: planar_point                         # optional: held through a pin (planar_point)
                                                 # or ball joint (spatial_point), or rigidly
                                                 # (planar, spatial); default the linkage's
      device:
        offset: [0.005, 0.003, 0.0]              # initial device pose - VT hand pose
        mass: [1, 1, 1]                          # diagonal of M_d (eq. 9)
        christoffel: [0, 0, 0]                   # diagonal of C_d
        workspace: {lo: [...], hi: [...]}        # hard stops, absolute (m, rad); optional
        wrench_limit: [10, 10, 1]                # |u| per axis (N, N m)
      user: {type: constant_wrench, wrench: [0.4, 0, 0]}
      control: {k_pc: [...], b_pc: [...], k_tc: 10, b_tc: 7}
      passivity: {enabled: true, velocity_floor: 0.001, window: 1.0}  # optional: the
                                                 # passivity controller (default: off)
      lmi: {model: eq17, update_period: 1}       # device cycles per LMI update
      ve: {internal_step: 0.001, vt_coupling: true}      # RK4 step (s)
      contacts:                                  # optional: obstacles (eqs. 1, 17, F_env)
        stiffness: 2000                          # N/m; damping N s/m, friction, margin m
        link_radius: 0.004                       # m, every link's default capsule
        obstacles: [{type: half_plane, point: [0.1, 0], normal: [-1, 0]}]

This module reads the top level; each block is parsed by its owner:
:func:`~haptic_topology.device.maglev.device_from_config` (``device``),
:func:`~haptic_topology.device.users.user_from_config` (``user``),
:meth:`ControlGains.from_config <haptic_topology.control.laws.ControlGains.from_config>`
(``control``), :meth:`PassivityConfig.from_config
<haptic_topology.control.passivity.PassivityConfig.from_config>` (``passivity``),
:class:`~haptic_topology.control.lmi.LmiSettings` (``lmi``),
:class:`VeSettings` (``ve``),
:class:`~haptic_topology.dynamics.contacts.ContactSettings` (``contacts``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.control.laws import ControlGains
from haptic_topology.control.lmi import LmiModel, LmiSettings
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.device.maglev import DeviceParams, device_from_config
from haptic_topology.device.users import user_from_config
from haptic_topology.dynamics.contacts import ContactSettings
from haptic_topology.dynamics.loops import LoopClosures, check_assembled
from haptic_topology.errors import ConfigError
from haptic_topology.model.linkage import Linkage, linkage_from_dict, load_linkage
from haptic_topology.model.robots import ROBOT_PREFIX
from haptic_topology.paths import resolve_config
from haptic_topology.sim.trace import run_name
from haptic_topology.validate import (
    as_angles,
    as_bool,
    as_float,
    as_str,
    as_vector,
    check_keys,
    load_yaml,
)
from haptic_topology.vocabulary import TASK_NAMES, ControlMode, TaskSpace


@dataclass(frozen=True)
class VeSettings:
    """The ``ve:`` block of a scenario: RK4 ``internal_step`` (s, in (0, dt]) and whether the
    coordination wrench acts on the VT (``vt_coupling``: ``F_vt = F_h - F_pc``, else ``F_h``)."""

    internal_step: float = 2.5e-4
    vt_coupling: bool = True

    @classmethod
    def from_config(cls, raw: Any, where: str, dt: float) -> VeSettings:
        """Parse the block (``where``: its path); ``dt``: the scenario's device period (s)."""
        ve = check_keys(raw, where, optional=('internal_step', 'vt_coupling'))
        step = as_float(ve.get('internal_step', 2.5e-4), f'{where}.internal_step', lo=0.0,
                        lo_open=True, hi=dt)
        return cls(step, as_bool(ve.get('vt_coupling', True), f'{where}.vt_coupling'))



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
    #: Obstacles and contact model; None: a VE without objects (F_env = 0).
    contacts: ContactSettings | None = None
    #: The linkage file :meth:`with_linkage` put in place of the scenario's own linkage
    #: (absolute; a linkage of no file: its name); empty: the scenario's own.
    linkage_file: str = ''
    #: The passivity controller's settings (``passivity``); None: none in the file (off in
    #: ``simulate``, the backend's default in the graph).
    passivity: PassivityConfig | None = None

    @property
    def label(self) -> str:
        """The run's name in plot titles (:func:`~haptic_topology.sim.trace.run_name`):
        ``fig8``, or ``fig8 on my_arm.urdf`` on another linkage."""
        return run_name(self.name, self.linkage_file)

    def with_linkage(self, linkage: Linkage, q0: np.ndarray | None = None) -> Scenario:
        """Same scenario on another linkage, starting at ``q0`` (rad / m, one per joint;
        default the scenario's; a point-grasp scenario holds a rigid linkage of its space at
        the point too); another linkage than the scenario's is named in :attr:`linkage_file`.
        Refused (:class:`~haptic_topology.errors.ConfigError`) when
        the scenario's ``q0`` or a nonzero ``dq0`` does not fit the linkage's joints and no
        ``q0`` is given: a state made up for it would start the hand anywhere."""
        linkage_file = self.linkage_file
        if linkage is not self.linkage:
            source = Path(linkage.source)
            linkage_file = str(source.resolve()) if source.is_file() else linkage.name
        if (self.linkage.task.point and not linkage.task.point
                and linkage.task.rigid is self.linkage.task.rigid):
            linkage = replace(linkage, task=self.linkage.task)  # held as the scenario holds it
        if linkage.task is not self.linkage.task:
            raise ConfigError(f'{linkage.source}: linkage.task is {linkage.task.value}, the '
                              f'scenario {self.name} needs {self.linkage.task.value}')
        dq0 = self.dq0
        if linkage.dof != self.dq0.size:
            if np.any(self.dq0):
                raise ConfigError(f'{self.source}: scenario.dq0 has {self.dq0.size} entries, '
                                  f'the linkage {linkage.name} {linkage.dof} joints: give a '
                                  'scenario for it')
            dq0 = np.zeros(linkage.dof)
        if q0 is None:
            if linkage.dof != self.q0.size:
                raise ConfigError(f'{self.source}: scenario.q0 has {self.q0.size} entries, the '
                                  f'linkage {linkage.name} {linkage.dof} joints: give q0 '
                                  '(simulate --q0) or a scenario for it')
            q0 = self.q0
        elif np.shape(q0) != (linkage.dof,):
            raise ConfigError(f'q0: expected {linkage.dof} numbers (the joints of '
                              f'{linkage.name}), got {np.size(q0)}')
        if self.contacts is not None:
            self.contacts.shapes(linkage)       # the per-link choices must fit it
        check_start(linkage, np.asarray(q0, dtype=float), dq0, 'scenario')
        return replace(self, linkage=linkage, q0=np.array(q0, dtype=float), dq0=dq0,
                       linkage_file=linkage_file)

    @property
    def lmi_dof(self) -> int:
        """The joints the LMI integrates (the size of its updates): the linkage's ``d``, or a
        closed chain's mobility ``f`` at ``q0`` (its updates are in the independent
        velocities, see
        :meth:`~haptic_topology.dynamics.linkage_dynamics.LinkageDynamics.snapshot`)."""
        if not self.linkage.loops:
            return self.linkage.dof
        return LoopClosures(self.linkage).mobility(self.q0)

    @property
    def lmi(self) -> LmiSettings:
        """The ``lmi:`` block (model, update_period)."""
        return LmiSettings(self.lmi_model, self.update_period)

    @property
    def ve(self) -> VeSettings:
        """The ``ve:`` block (internal_step, vt_coupling)."""
        return VeSettings(self.internal_step, self.vt_coupling)

    def coupling_gains(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(K_pc, B_pc)`` when the VE's hand input carries the coordination wrench (VT
        coupling), else None."""
        return (self.gains.k_pc, self.gains.b_pc) if self.vt_coupling else None


def _scenario_linkage(ref: Any, path: Path, w: str) -> Linkage:
    """``scenario.linkage``: a linkage file (a path relative to the scenario, or a name in
    ``config/linkages``), ``robot:NAME``, or the linkage document inline (a mapping, as under
    a linkage file's ``linkage:``, e.g. ``{robot: panda, grasp: {link: panda_link4}}``)."""
    if isinstance(ref, Mapping):
        return linkage_from_dict({'linkage': dict(ref)}, str(path))
    link_ref = as_str(ref, f'{w}.linkage')
    if link_ref.startswith(ROBOT_PREFIX):
        return load_linkage(link_ref)
    link_path = Path(link_ref)
    if not link_path.is_absolute() and (path.parent / link_path).is_file():
        link_path = path.parent / link_path
    return load_linkage(resolve_config(str(link_path), 'linkages'))


def load_scenario(name_or_path: str) -> Scenario:
    """Load ``config/scenarios/<name>.yaml`` or a scenario file; errors name file and key."""
    path = resolve_config(name_or_path, 'scenarios')
    doc = load_yaml(path)
    src = str(path)
    top = check_keys(doc, src, required=('scenario',))
    w = f'{src}: scenario'
    raw = check_keys(top['scenario'], w, required=('linkage', 'q0', 'duration'), optional=(
        'name', 'description', 'dq0', 'dt', 'mode', 'gravity', 'grasp', 'task', 'device',
        'user', 'control', 'lmi', 've', 'contacts', 'passivity'))
    linkage = _scenario_linkage(raw['linkage'], path, w)
    if 'gravity' in raw:
        linkage = replace(linkage, gravity=as_vector(raw['gravity'], f'{w}.gravity', 3))
    if 'grasp' in raw:      # the linkage held elsewhere than its file says
        grasp = check_keys(raw['grasp'], f'{w}.grasp', required=('link',), optional=('point',))
        point = as_vector(grasp['point'], f'{w}.grasp.point', 3) if 'point' in grasp else None
        if point is not None and linkage.task.planar and point[2] != 0.0:
            raise ConfigError(f'{w}.grasp.point: z must be 0 for a planar linkage')
        link = as_str(grasp['link'], f'{w}.grasp.link', linkage.link_names)
        linkage = linkage.with_grasp(link, point)
    if 'task' in raw:       # the linkage held rigidly or at a point (a pin or ball joint)
        task = TaskSpace(as_str(raw['task'], f'{w}.task', TASK_NAMES))
        if task.rigid is not linkage.task.rigid:
            allowed = (linkage.task.rigid.value, linkage.task.point_grasp.value)
            raise ConfigError(f'{w}.task: linkage {linkage.name} is {linkage.task.value}, so '
                              f'expected {" or ".join(allowed)}, got {task.value!r}')
        linkage = replace(linkage, task=task)
    d, m = linkage.dof, linkage.task.dim
    q0 = as_angles(raw['q0'], f'{w}.q0', d)
    dq0 = as_angles(raw.get('dq0', [0.0] * d), f'{w}.dq0', d)
    duration = as_float(raw['duration'], f'{w}.duration', lo=0.0, lo_open=True, hi=3600.0)
    dt = as_float(raw.get('dt', 0.001), f'{w}.dt', lo=0.0, lo_open=True, hi=0.1)
    mode = ControlMode.PENALTY
    if 'mode' in raw:
        try:
            mode = ControlMode.parse(as_str(raw['mode'], f'{w}.mode'))
        except ValueError as exc:
            raise ConfigError(f'{w}.{exc}') from None

    device, offset = device_from_config(raw.get('device', {}), f'{w}.device', linkage.task)
    user = raw.get('user', {'type': 'constant_wrench', 'wrench': [0.0] * m})
    user_from_config(user, linkage.task, f'{w}.user', np.zeros(m), compile=False)  # check
    gains = ControlGains.from_config(raw.get('control', {}), f'{w}.control', m)
    lmi = LmiSettings.from_config(raw.get('lmi', {}), f'{w}.lmi')
    if lmi.model is LmiModel.EQ20 and np.any(linkage.gravity != 0.0):
        raise ConfigError(f'{w}.lmi.model: eq20 (D qdd = J_h^T F_vt) neglects the gravity '
                          f'{linkage.gravity.tolist()} m/s^2 of linkage {linkage.name} that the '
                          'VE integrates; expected eq17, or scenario.gravity: [0, 0, 0]')
    ve = VeSettings.from_config(raw.get('ve', {}), f'{w}.ve', dt)
    name = as_str(raw.get('name', path.stem), f'{w}.name')
    contacts = (ContactSettings.from_config(raw['contacts'], f'{w}.contacts', linkage,
                                            path.parent)
                if 'contacts' in raw else None)
    passivity = (PassivityConfig.from_config(raw['passivity'], f'{w}.passivity')
                 if 'passivity' in raw else None)
    check_start(linkage, q0, dq0, w)
    return Scenario(name, linkage, q0, dq0, duration, dt, mode, device, offset, dict(user),
                    gains, lmi.model, lmi.update_period, ve.internal_step, ve.vt_coupling, src,
                    contacts, passivity=passivity)


def check_start(linkage: Linkage, q0: np.ndarray, dq0: np.ndarray, where: str) -> None:
    """A closed-chain linkage (``linkage.loops``) must start assembled and mobile
    (:func:`~haptic_topology.dynamics.loops.check_assembled`)."""
    if linkage.loops:
        check_assembled(linkage, q0, dq0, where)
