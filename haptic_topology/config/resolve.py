"""Settings + scenario -> each node's final configuration, resolved once (no rclpy).

A node declares its parameters (``haptic_topology.nodes.parameters.declare_settings``), loads
its scenario, and calls the ``resolve_*`` function of this module once; everything it needs
afterwards is in the returned frozen config, in final form (enums, arrays of the task's size,
periods in s and ns, "0 = the scenario's" replaced). Checks that need the scenario (array
sizes, lock-step rate) raise :class:`~haptic_topology.errors.ConfigError` naming the node,
the parameter and what was expected.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from haptic_topology.config.settings import (
    RATE_MAX,
    RATE_MIN,
    DeviceDriverSettings,
    LmiControllerSettings,
    RecorderSettings,
    VeSimSettings,
    parse_backend_options,
)
from haptic_topology.control.laws import ControlGains, check_gain
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.control.safety import SyncGuardConfig
from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.watchdog import WatchdogConfig, WatchdogFallback
from haptic_topology.errors import ConfigError
from haptic_topology.vocabulary import Clock, ControlMode

if TYPE_CHECKING:
    from haptic_topology.control.passivity import EnergyAccount
    from haptic_topology.device.backend import DeviceBackend
    from haptic_topology.sim.scenario import Scenario


# -- device_driver -----------------------------------------------------------------------------
@dataclass(frozen=True)
class DeviceDriverConfig:
    """What ``device_driver`` runs with. ``rate_hz`` (Hz), ``period`` (s) and ``period_ns``
    (ns) describe the same device cycle; ``wrench_limit`` (N, N m, task_dim values);
    ``watchdog`` with the damping expanded to task_dim values; ``takeover_after`` (s: silence
    of the followed controller before another may take over, ``device.loop``);
    ``run_duration`` (s, 0 = until stopped)."""

    settings: DeviceDriverSettings
    scenario: Scenario
    backend: str
    backend_options: dict[str, Any]
    clock: Clock
    rate_hz: float
    period: float
    period_ns: int
    wrench_limit: np.ndarray
    watchdog: WatchdogConfig
    takeover_after: float
    min_subscribers: int
    lockstep_warn_after: float
    run_duration: float
    executor: str
    sched_priority: int

    @property
    def task_dim(self) -> int:
        return self.scenario.linkage.task.dim

    def backend_config(self) -> BackendConfig:
        """The backend's configuration: the scenario's device, user and source, the device
        starting at the VT hand pose at ``q0`` plus the scenario's offset."""
        from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
        sc = self.scenario
        x0 = LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset
        return BackendConfig(sc.device, x0, dict(sc.user), dict(self.backend_options),
                             sc.source)


def _device_rate(s: DeviceDriverSettings, sc: Scenario, clock: Clock) -> tuple[float, float,
                                                                                  int]:
    """(rate_hz, period s, period ns) of the device cycle."""
    if s.rate_hz == 0.0 or clock is Clock.LOCKSTEP:
        rate = 1.0 / sc.dt
        if clock is Clock.LOCKSTEP and s.rate_hz != 0.0 and abs(s.rate_hz * sc.dt - 1.0) > 1e-9:
            raise ConfigError(f'device_driver: parameter rate_hz: clock lockstep needs 0.0 or '
                              f'1/dt = {rate:g} Hz (scenario {sc.name}, dt {sc.dt:g} s), got '
                              f'{s.rate_hz!r}')
        if not RATE_MIN <= rate <= RATE_MAX:
            raise ConfigError(f'device_driver: parameter rate_hz: 0.0 means 1/dt = {rate:g} Hz '
                              f'(scenario {sc.name}), outside [{RATE_MIN:g}, {RATE_MAX:g}]; '
                              'set rate_hz')
        return rate, sc.dt, round(sc.dt * 1e9)
    return s.rate_hz, 1.0 / s.rate_hz, round(1e9 / s.rate_hz)


def check_device_axes(sc: Scenario, backend: str, options: dict[str, Any]) -> None:
    """Refuse the scenario ``sc`` on the backend called ``backend`` (with its parsed
    ``options``) when its task needs an axis the device does not actuate or sense
    (:meth:`~haptic_topology.device.backend.DeviceBackend.axes`): one line naming both and,
    for a rigid grasp, the point-grasp scenario to use instead
    (:class:`~haptic_topology.errors.AxesError`)."""
    from haptic_topology.device.backend import backend_class, check_axes
    check_axes(sc.linkage.task, backend_class(backend).axes(options), sc.name, backend,
               None if sc.linkage.task.point else _point_alternative(sc))


def run_backend(params: Path, backend: str | None, items: Sequence[str]
                ) -> tuple[str, dict[str, Any]]:
    """The backend name and parsed ``backend_options`` a run's ``device_driver`` will have:
    ``backend`` (``run --backend``) or the last ``-p device_driver:backend:=...`` item, else
    the params file's ``device_driver`` section (default ``sim_maglev``); the options
    likewise. A ``-p`` value is read as ROS reads it (YAML: ``'{port: 10002}'`` is the text
    ``{port: 10002}``); an unquoted mapping (``{port: 10002}``) is taken as the options too
    (``run`` passes it on quoted: ``bringup.options.param_overrides``).
    For :func:`check_device_axes` before anything starts."""
    from haptic_topology.config.params import override_value
    from haptic_topology.validate import load_yaml
    found: dict[str, Any] = {}
    for section, body in load_yaml(params).items():
        if isinstance(section, str) and section.strip().rsplit('/', 1)[-1] == 'device_driver':
            values = body.get('ros__parameters') if isinstance(body, dict) else None
            if isinstance(values, dict):
                found.update({k: values[k] for k in ('backend', 'backend_options')
                              if k in values})
    for item in items:
        target, _, value = item.partition(':=')
        node, _, name = target.rpartition(':')
        if node == 'device_driver' and name in ('backend', 'backend_options'):
            found[name] = override_value(value)
    name = backend or str(found.get('backend', 'sim_maglev'))
    options = found.get('backend_options', '')
    if isinstance(options, dict):
        return name, options
    return name, parse_backend_options('' if options is None else str(options))


def _point_alternative(sc: Scenario) -> str:
    """``<name>_point`` when such a scenario exists, else how to write one."""
    from haptic_topology.paths import resolve_config
    try:
        resolve_config(f'{sc.name}_point', 'scenarios')
    except ConfigError:
        return f'a point grasp (scenario.task: {sc.linkage.task.point_grasp.value})'
    return f'{sc.name}_point'


def resolve_device_driver(s: DeviceDriverSettings, sc: Scenario) -> DeviceDriverConfig:
    """``device_driver``'s configuration: ``rate_hz`` 0.0 -> 1/dt (with ``clock: lockstep``
    any other value than 1/dt is refused), ``wrench_limit`` [0.0] -> the scenario's,
    ``watchdog_damping`` of one value -> every axis, ``backend_options`` parsed; a task the
    backend's device cannot render is refused (:func:`check_device_axes`)."""
    m = sc.linkage.task.dim
    clock = Clock.parse(s.clock)
    rate, period, period_ns = _device_rate(s, sc, clock)
    if list(s.wrench_limit) == [0.0]:
        limit = sc.device.wrench_limit.copy()
    else:
        limit = np.asarray(s.wrench_limit, dtype=float)
        if limit.shape != (m,) or not np.all(limit > 0.0) or not np.all(np.isfinite(limit)):
            raise ConfigError(f'device_driver: parameter wrench_limit: expected {m} '
                              f'positive numbers, got {list(s.wrench_limit)}')
    damping = np.asarray(s.watchdog_damping, dtype=float)
    if damping.size == 1:
        damping = np.full(m, float(damping[0]))
    if damping.shape != (m,) or not np.all(np.isfinite(damping)) or np.any(damping < 0.0):
        raise ConfigError(f'device_driver: parameter watchdog_damping: expected one or {m}'
                          f' numbers >= 0, got {list(s.watchdog_damping)}')
    watchdog = WatchdogConfig(s.watchdog_timeout, s.watchdog_ramp,
                              WatchdogFallback.parse(s.watchdog_fallback), damping)
    options = parse_backend_options(s.backend_options)
    check_device_axes(sc, s.backend, options)
    return DeviceDriverConfig(
        settings=s, scenario=sc, backend=s.backend,
        backend_options=options, clock=clock, rate_hz=rate,
        period=period, period_ns=period_ns, wrench_limit=limit, watchdog=watchdog,
        takeover_after=s.takeover_after, min_subscribers=s.min_subscribers,
        lockstep_warn_after=s.lockstep_warn_after,
        run_duration=s.run_duration, executor=s.executor, sched_priority=s.sched_priority)


# -- lmi_controller ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ControllerConfig:
    """What ``lmi_controller`` runs with. ``gains``: the scenario's with ``k_tc``/``b_tc``
    applied; ``cycle_time``: the scenario's dt (s); times in s; ``wrench_limit`` the
    scenario's device limit (N, N m)."""

    settings: LmiControllerSettings
    scenario: Scenario
    mode: ControlMode
    gains: ControlGains
    guard: SyncGuardConfig
    clock: Clock
    cycle_time: float
    max_dt: float
    resync_max_jump: float
    lockstep_wait: float
    wrench_limit: np.ndarray
    executor: str
    sched_priority: int
    #: The passivity controller's settings (``passivity`` on/off, or the scenario's block).
    passivity: PassivityConfig | None = None
    #: ``passivity: auto`` without a scenario block: on once hosted by a real device's
    #: driver (:meth:`~haptic_topology.control.passivity.EnergyAccount.enable`).
    passivity_auto: bool = False


def resolve_passivity(setting: str, sc: Scenario) -> tuple[PassivityConfig, bool]:
    """The passivity controller of ``lmi_controller``'s parameter ``passivity``
    (``enabled``, ``disabled``, ``auto``) and scenario ``sc``: its settings, and whether
    ``auto`` leaves the choice to the backend (no ``passivity`` block in the scenario)."""
    base = sc.passivity or PassivityConfig()
    if setting == 'auto':
        return base, sc.passivity is None
    return replace(base, enabled=setting == 'enabled'), False


def passivity_by_default(simulated: bool, velocity_filtered: bool = False) -> bool:
    """Whether ``passivity: auto`` (with no ``passivity`` block in the scenario) turns the
    passivity controller on: for every device that is not a simulation (``simulated``:
    :attr:`~haptic_topology.device.backend.DeviceBackend.simulated`), point and rigid grasps
    alike (the observer counts the energy the coupling takes in at the VT's end, so a rigid
    grasp's coordination is not damped: :mod:`haptic_topology.control.passivity`), except a
    device whose velocity is a low-pass filtered difference of its positions
    (``velocity_filtered``, OpenHaptics): the controller's damping then acts on a velocity
    that lags the motion and injects energy instead of dissipating it (fig8_point on the
    OpenHaptics emulator's parameters: observer minimum -0.49 J and 14 mm drift with it,
    -3 mJ and 1.1 mm without; :func:`AUTO_OFF_FILTERED` says so at configure)."""
    return not simulated and not velocity_filtered


#: What ``device_driver`` logs when ``passivity: auto`` leaves the controller off for a
#: device with a filtered velocity.
AUTO_OFF_FILTERED = ('passivity: auto: the passivity controller stays off on {backend}: its '
                     'velocity is a low-pass filtered difference of encoder positions, and '
                     'damping on a lagging velocity adds energy instead of removing it (the '
                     'parameter passivity:=enabled turns it on)')


def zwidth_warning(c: ControllerConfig, maps: list[dict[str, Any]] | None = None,
                   device: str = 'scenario', passivity: bool | None = None) -> list[str]:
    """Why ``c``'s gains lie outside the Z-width maps of its scenario on ``device`` (the
    scenario's own, or a vendor device of :data:`haptic_topology.sim.zwidth.DEVICES`), at
    the scenario's LMI update period with the passivity controller as configured: one line
    per gain (eq. 13's ``k_tc``, ``b_tc``; a scenario with obstacles also
    ``contacts.stiffness``, ``contacts.damping``) naming the gain and the bound; empty
    inside, or without a map. ``maps``: default the shipped ones (``config/zwidth.json``,
    written by ``haptic-topology zwidth``). A warning, not a refusal: the edge of the map is
    for probing on purpose. ``passivity``: whether the passivity controller is on (default:
    as ``c`` configures it; ``passivity: auto`` is decided by the driver's backend)."""
    from haptic_topology.paths import config_dir
    from haptic_topology.sim.zwidth import load_maps, outside_map

    if maps is None:
        maps = load_maps(config_dir() / 'zwidth.json')
    on = (c.passivity is not None and c.passivity.enabled) if passivity is None else passivity
    gains = {'k_tc': float(c.gains.k_tc), 'b_tc': float(c.gains.b_tc)}
    contacts = c.scenario.contacts
    if contacts is not None:
        gains['contacts.stiffness'] = float(contacts.params.stiffness)
        gains['contacts.damping'] = float(contacts.params.damping)
    return outside_map(maps, c.scenario.name, c.scenario.update_period, on, gains, device)


def configure_hosted(c: ControllerConfig, energy: EnergyAccount, backend: DeviceBackend,
                     warn: Callable[[str], Any],
                     info: Callable[[str], Any] | None = None) -> None:
    """The hosted controller ``c`` on the driver's configured ``backend``: ``passivity:
    auto`` decided (:func:`passivity_by_default`) on ``c``'s ``energy`` account; for a vendor
    device with Z-width maps (:data:`haptic_topology.sim.zwidth.DEVICES`), every line of
    :func:`zwidth_warning` for that device and controller passed to ``warn`` (the
    scenario's own device: ``lmi_controller`` warns itself)."""
    from haptic_topology.sim.zwidth import DEVICES

    if c.passivity_auto:
        energy.enable(passivity_by_default(backend.simulated, backend.velocity_filtered))
        if info is not None and not backend.simulated and backend.velocity_filtered:
            info(AUTO_OFF_FILTERED.format(backend=backend.name))
    if backend.name in DEVICES:
        for line in zwidth_warning(c, device=backend.name, passivity=bool(energy.params[0])):
            warn(line)


def resolve_lmi_controller(s: LmiControllerSettings, sc: Scenario) -> ControllerConfig:
    """``lmi_controller``'s configuration: ``mode``/``k_tc``/``b_tc`` None -> the scenario's
    (a scenario built in code, not loaded, is checked here against the same range)."""
    mode = sc.mode if s.mode is None else ControlMode.parse(s.mode)
    k_tc = float(sc.gains.k_tc) if s.k_tc is None else s.k_tc
    b_tc = float(sc.gains.b_tc) if s.b_tc is None else s.b_tc
    for name, value in (('k_tc', k_tc), ('b_tc', b_tc)):
        reason = check_gain(name, value)
        if reason:
            raise ConfigError(f'lmi_controller: parameter {reason}')
    try:
        guard = SyncGuardConfig(s.stale_after, s.degrade_after, s.resync_ramp)
    except ConfigError as exc:
        raise ConfigError(f'lmi_controller: parameters: {exc}') from None
    passivity, auto = resolve_passivity(s.passivity, sc)
    return ControllerConfig(
        settings=s, scenario=sc, mode=mode, gains=sc.gains.with_penalty(k_tc, b_tc),
        guard=guard, clock=Clock.parse(s.clock), cycle_time=sc.dt, max_dt=s.max_dt,
        resync_max_jump=s.resync_max_jump, lockstep_wait=s.lockstep_wait,
        wrench_limit=sc.device.wrench_limit.copy(), executor=s.executor,
        sched_priority=s.sched_priority, passivity=passivity, passivity_auto=auto)


# -- ve_sim ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VeSimConfig:
    """What ``ve_sim`` runs with: ``update_period`` (hand inputs per LMI update) resolved;
    ``idle_period`` = 1/idle_update_rate_hz and ``viz_period`` = 1/viz_rate_hz (s)."""

    settings: VeSimSettings
    scenario: Scenario
    clock: Clock
    update_period: int
    idle_period: float
    max_hand_wrench: float
    viz_period: float
    frame_id: str
    executor: str
    sched_priority: int


def resolve_ve_sim(s: VeSimSettings, sc: Scenario) -> VeSimConfig:
    """``ve_sim``'s configuration: ``update_period`` 0 -> the scenario's lmi.update_period
    (with ``clock: lockstep`` no other value: the controller expects the scenario's)."""
    if (Clock.parse(s.clock) is Clock.LOCKSTEP and s.update_period
            and s.update_period != sc.update_period):
        raise ConfigError(f've_sim: parameter update_period: clock lockstep needs 0 or the '
                          f"scenario's lmi.update_period {sc.update_period}, got "
                          f'{s.update_period}')
    return VeSimConfig(
        settings=s, scenario=sc, clock=Clock.parse(s.clock),
        update_period=s.update_period if s.update_period else sc.update_period,
        idle_period=1.0 / s.idle_update_rate_hz, max_hand_wrench=s.max_hand_wrench,
        viz_period=1.0 / s.viz_rate_hz, frame_id=s.frame_id, executor=s.executor,
        sched_priority=s.sched_priority)


# -- recorder ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecorderConfig:
    """What ``recorder`` runs with: the bag directory, the topics (of those it can record),
    chunk size (bytes), flush period (s), split limits (bytes, s; 0: none)."""

    settings: RecorderSettings
    scenario_name: str
    path: Path
    topics: tuple[str, ...]
    flush_period: float
    chunk_size: int
    compression: str
    clock: Clock
    executor: str
    sched_priority: int
    max_bag_size: int = 0
    max_bag_duration: float = 0.0


def default_bag_dir(scenario: str, root: str | Path = 'bags') -> Path:
    """``<root>/<scenario>_<YYYYmmdd-HHMMSS>`` (local time now)."""
    return Path(root) / f'{scenario}_{time.strftime("%Y%m%d-%H%M%S")}'


def select_topics(names: Sequence[str], regex: str, recorded: Sequence[str]) -> list[str]:
    """Topics of ``recorded`` to record: all if neither ``names`` nor ``regex`` is given,
    else those in ``names`` (with or without the leading '/') or matching ``regex``."""
    if not names and not regex:
        return list(recorded)
    wanted = {n.lstrip('/') for n in names}
    unknown = wanted - {t.lstrip('/') for t in recorded}
    if unknown:
        raise ConfigError(f'recorder: parameter topics: unknown {", ".join(sorted(unknown))}; '
                          f'known: {", ".join(recorded)}')
    try:
        pattern = re.compile(regex) if regex else None
    except re.error as exc:
        raise ConfigError(f'recorder: parameter topic_regex: {exc}') from None
    out = [t for t in recorded if t.lstrip('/') in wanted
           or (pattern is not None and pattern.search('/' + t.lstrip('/')))]
    if not out:
        raise ConfigError(f'recorder: topic_regex {regex!r} matches none of '
                          f'{", ".join(recorded)}')
    return out


def resolve_recorder(s: RecorderSettings, recorded: Sequence[str]) -> RecorderConfig:
    """``recorder``'s configuration; ``recorded``: the topics it knows how to record. The
    scenario is only a name here (its file stem names the default bag directory)."""
    name = Path(s.scenario).stem
    topics = select_topics([n for n in s.topics if n], s.topic_regex, recorded)
    return RecorderConfig(
        settings=s, scenario_name=name,
        path=Path(s.output) if s.output else default_bag_dir(name), topics=tuple(topics),
        flush_period=s.flush_period, chunk_size=s.chunk_kib * 1024,
        compression=s.compression, clock=Clock.parse(s.clock), executor=s.executor,
        sched_priority=s.sched_priority, max_bag_size=s.max_bag_size,
        max_bag_duration=s.max_bag_duration)
