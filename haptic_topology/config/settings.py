"""Settings of each node: one frozen dataclass whose fields are the node's ROS parameters.

(One module of ~510 lines on purpose: every node's parameters, with their descriptions,
ranges and cross-checks, in one table that the nodes declare and that params files are
checked against; split by node, the shared parameter definitions would be imported back and
forth.)

Each field carries its parameter's description, range (``lo``/``hi``, inclusive), ``choices``
and ``read_only`` flag in ``field(metadata=...)`` (see :func:`param`); :func:`param_specs`
generates the :class:`~haptic_topology.config.params.ParamSpec` table from the fields (as
generate_parameter_library does from ``parameters.yaml``). That one table is what the node
declares (``haptic_topology.nodes.parameters.declare_settings``) and what params files and
``-p`` overrides are checked against before rclpy reads them
(:data:`haptic_topology.config.node_params.KNOWN`).

Constructing a settings object checks everything that needs only the values (ROS type,
range, choices, and relations such as ``degrade_after >= stale_after``) and raises
:class:`~haptic_topology.errors.ConfigError` naming the node, the parameter and what was
expected. What needs the scenario (sizes, ``0`` = "the scenario's") is resolved once by
:mod:`haptic_topology.config.resolve` into the node's final, frozen configuration.

No rclpy here.
"""

from __future__ import annotations

import array
import os
import re
from dataclasses import MISSING, dataclass, field, fields
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import yaml

from haptic_topology.config.params import ParamSpec, check_value
from haptic_topology.control.laws import GAIN_MAX, check_gain
from haptic_topology.device.realtime import NODE_POLICIES, SLICE_RANGE_US
from haptic_topology.device.watchdog import WatchdogFallback
from haptic_topology.errors import ConfigError
from haptic_topology.vocabulary import LAW_MODES, Clock

if TYPE_CHECKING:
    from haptic_topology.sim.scenario import Scenario

EXECUTORS = ('events', 'single_threaded')
MODES = LAW_MODES
FALLBACKS = tuple(f.value for f in WatchdogFallback)
COMPRESSIONS = ('zstd', 'lz4', 'none')
#: Device cycle rates a nonzero ``rate_hz`` may take (Hz).
RATE_MIN, RATE_MAX = 10.0, 10000.0


# -- fields -> parameter specs -----------------------------------------------------------------
_META = 'haptic_topology.param'


@dataclass(frozen=True)
class _ParamMeta:
    description: str
    read_only: bool
    lo: float | None
    hi: float | None
    choices: tuple[str, ...] | None
    ros_default: Any


def param(default: Any, description: str, *, lo: float | None = None, hi: float | None = None,
          choices: tuple[str, ...] | None = None, read_only: bool = True,
          ros_default: Any = MISSING) -> Any:
    """A settings field that is a ROS parameter.

    ``default`` gives the ROS type (``1.0`` double, ``1`` integer, ``[0.0]`` double array, ...;
    a list default is stored as a tuple). ``ros_default``: the default declared to ROS when it
    differs from the field's (the field's is then ``None``, meaning "the scenario's", see
    :func:`scenario_defaults`).
    """
    meta = _ParamMeta(description, read_only, lo, hi, choices,
                      default if ros_default is MISSING else ros_default)
    value = tuple(default) if isinstance(default, list) else default
    return field(default=value, metadata={_META: meta})


S = TypeVar('S', bound='NodeSettings')


def param_specs(cls: type[NodeSettings]) -> dict[str, ParamSpec]:
    """The parameter table of a settings class, by name, in field order."""
    out: dict[str, ParamSpec] = {}
    for f in fields(cls):
        meta = f.metadata.get(_META)
        if meta is None:
            continue
        default = meta.ros_default
        if isinstance(default, tuple):
            default = list(default)
        out[f.name] = ParamSpec(f.name, default, meta.description, read_only=meta.read_only,
                                lo=meta.lo, hi=meta.hi, choices=meta.choices)
    return out


def scenario_defaults(cls: type[NodeSettings], scenario: Scenario) -> dict[str, Any]:
    """Defaults to declare instead of the table's, taken from ``scenario`` (lmi_controller:
    ``mode``, ``k_tc``, ``b_tc``; empty for the other nodes)."""
    return cls.defaults_from(scenario)


def _normalise(spec: ParamSpec, value: Any) -> Any:
    """A ROS / Python value in the field's form: tuples for arrays, float for an int given
    to a double."""
    kind = spec.kind()
    if isinstance(value, (list, array.array)):
        value = tuple(value)
    if (kind == 'double' and isinstance(value, int) and not isinstance(value, bool)):
        return float(value)
    if (kind == 'double array' and isinstance(value, tuple)
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        return tuple(float(v) for v in value)
    return value


@dataclass(frozen=True)
class NodeSettings:
    """Base of the per-node settings: checks every field against its parameter spec."""

    NODE: ClassVar[str] = ''

    def __post_init__(self) -> None:
        nullable = {f.name for f in fields(self) if f.default is None}
        for name, spec in param_specs(type(self)).items():
            value = _normalise(spec, getattr(self, name))
            object.__setattr__(self, name, value)
            if value is None and name in nullable:
                continue       # "the scenario's" (see scenario_defaults)
            if isinstance(value, tuple) and not value and not name.endswith('cpu_affinity'):
                continue       # an empty array has no ROS type; each node decides
            check_value(spec, list(value) if isinstance(value, tuple) else value,
                        f'{self.NODE}: parameter {name}')
            if name.endswith('cpu_affinity'):
                check_cpus(value, f'{self.NODE}: parameter {name}')
        self.check()

    def check(self) -> None:
        """Relations between fields (subclasses); raise
        :class:`~haptic_topology.errors.ConfigError`."""

    @classmethod
    def defaults_from(cls, scenario: Scenario) -> dict[str, Any]:
        """See :func:`scenario_defaults`."""
        return {}

    @classmethod
    def from_values(cls: type[S], values: dict[str, Any]) -> S:
        """Settings from parameter values by name (unknown names raise ConfigError)."""
        known = param_specs(cls)
        for name in values:
            if name not in known:
                raise ConfigError(f'{cls.NODE}: unknown parameter {name} (expected one of: '
                                  f'{", ".join(sorted(known))})')
        return cls(**values)


def _scenario(what: str) -> Any:
    return param('fig8', f'scenario name (config/scenarios) or YAML path: {what}')


def _executor() -> Any:
    return param('events', 'executor of the process', choices=EXECUTORS)


def _sched_priority() -> Any:
    return param(0, 'SCHED_FIFO priority 1-99 of the process (all its threads); 0 = normal '
                 'scheduling. Needs CAP_SYS_NICE (root or an rtprio limit): without it a '
                 'warning and normal scheduling', lo=0, hi=99)


def _graph_id() -> Any:
    return param('', "the graph this node belongs to: it publishes this identity in every "
                 "message on the graph's topics and applies only messages that carry it "
                 "(others are foreign: counted in /diagnostics, never applied). "
                 "haptic-topology run gives each run its own; empty: the default graph")


def check_cpus(cpus: tuple[int, ...], where: str) -> None:
    """A CPU affinity parameter: ``[-1]`` (no pinning) or CPU numbers of this machine."""
    n = os.cpu_count() or 1
    if cpus != (-1,) and not (cpus and all(0 <= c < n for c in cpus)):
        raise ConfigError(f'{where}: expected [-1] (no pinning) or CPU numbers in '
                          f'[0, {n - 1}], got {list(cpus)}')


def _cpu_affinity() -> Any:
    return param([-1], 'CPUs every thread of the process runs on from start-up (threads and '
                 'processes started later inherit them), e.g. [0] to keep the other core '
                 "for the loop process (device_driver's cpu_affinity); no privilege needed. "
                 '[-1] = no pinning')


def _nice(default: int) -> Any:
    return param(default, 'nice increment of the process (all its threads) at start-up: a '
                 'node off the 1 kHz deadline path yields the CPU to the loop when the cores '
                 'are busy; raising nice needs no privilege. 0 = unchanged', lo=0, hi=19)


def _sched_policy() -> Any:
    return param('batch', 'scheduling policy of every thread of this process from start-up, '
                 'so that it yields the CPU to the 1 kHz loop (no privilege needed). batch: '
                 'SCHED_BATCH, its threads never preempt the running loop when they wake, '
                 'their share of the CPU is unchanged; idle: SCHED_IDLE, the loop also '
                 'preempts them at once when it wakes (fewer missed cycles beside a busy '
                 'process), but they get a core only when no normal thread wants it, so they '
                 'stall while other work keeps every core busy; other: unchanged (normal '
                 'scheduling)', choices=tuple(NODE_POLICIES))


def _clock(lockstep: str) -> Any:
    return param('wall', f'wall: the graph runs in real time; {lockstep}',
                 choices=tuple(c.value for c in Clock))


# -- device_driver -----------------------------------------------------------------------------
def parse_backend_options(text: str) -> dict[str, Any]:
    """``backend_options`` (a YAML/JSON mapping, or empty) as a dict."""
    try:
        options = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as exc:
        raise ConfigError(f'device_driver: parameter backend_options: not YAML ({exc})'
                          ) from None
    if not isinstance(options, dict):
        raise ConfigError('device_driver: parameter backend_options: expected a mapping, '
                          f'got {text!r}')
    return options


@dataclass(frozen=True)
class DeviceDriverSettings(NodeSettings):
    """Parameters of ``device_driver`` (the device side of the haptic loop)."""

    NODE: ClassVar[str] = 'device_driver'

    scenario: str = _scenario('device model, limits, initial pose and simulated user')
    executor: str = _executor()
    graph_id: str = _graph_id()
    sched_priority: int = param(0, 'SCHED_FIFO priority 1-99 of the loop thread (with '
                                'host_controller; else of the process, all its threads); 0 = '
                                'normal scheduling. Needs CAP_SYS_NICE (root or an rtprio '
                                'limit): without it one warning and normal scheduling',
                                lo=0, hi=99)
    backend: str = param('sim_maglev', 'device backend: sim_maglev, ros_topics, network, a '
                         'vendor\'s (forcedimension; haptic-topology devices lists them), '
                         'module:Class, or an entry point of haptic_topology.device_backends')
    backend_options: str = param('', "backend settings as a YAML/JSON mapping (e.g. '{port: "
                                 "/dev/ttyUSB0}'); empty for none")
    rate_hz: float = param(0.0, 'device cycle rate (Hz); 0.0 = 1/scenario dt. A nonzero '
                           f'value must lie in [{RATE_MIN:g}, {RATE_MAX:g}]; with clock '
                           'lockstep it must equal 1/dt', lo=0.0, hi=RATE_MAX)
    watchdog_timeout: float = param(0.005, 'fade the output to the fallback when no fresh '
                                    'command came for this long (s): the oldest unanswered '
                                    'state is this old', lo=1e-4, hi=10.0)
    watchdog_ramp: float = param(0.05, 'time of a full fade between command and fallback, '
                                 'both ways (s)', lo=1e-3, hi=10.0)
    watchdog_fallback: str = param('zero', 'output the watchdog fades to: zero, or damping '
                                   '(-watchdog_damping * device twist)', choices=FALLBACKS)
    watchdog_damping: tuple[float, ...] = param(
        [0.0], 'damping of the damping fallback (N s/m, N m s/rad): one value for every axis '
        'or task_dim values')
    takeover_after: float = param(0.5, 'the device follows the controller whose command '
                                  'engaged it; another controller (another '
                                  'DeviceCommand.controller_id, e.g. a restarted one) may take '
                                  'over only once it has been silent this long (s)',
                                  lo=0.01, hi=3600.0)
    min_subscribers: int = param(1, 'ignore commands (device idle) until this many '
                                 'subscribers see the state topic (e.g. 2 with a recorder)',
                                 lo=0, hi=100)
    sampled_state_rate_hz: float = param(
        30.0, 'states a second (wall time, under either clock) also published on '
        'haptic/device/state_sampled (the same messages), for readers that want the newest '
        "state now and then (ve_sim's picture) without being sent all 1,000 (Hz); 0.0 = none",
        lo=0.0, hi=1000.0)
    wrench_limit: tuple[float, ...] = param(
        [0.0], "per-axis |u| limit (N, N m); [0.0] = the scenario's device.wrench_limit")
    clock: str = param('wall', 'wall: a 1 kHz wall timer paces the device; lockstep: '
                       'simulated time (/clock) advances one device period only when the '
                       'command answering the current state has arrived',
                       choices=tuple(c.value for c in Clock))
    lockstep_warn_after: float = param(2.0, 'lock-step: warn when the answer to a state has '
                                       'not come for this long (wall s)', lo=0.1, hi=600.0)
    autostart: bool = param(True, 'configure and activate the lifecycle node on start-up; '
                            'false: wait for lifecycle transitions (ros2 lifecycle set)')
    run_duration: float = param(0.0, 'deactivate after this long of engaged loop (s; '
                                'simulated s with clock lockstep); 0.0 = run until stopped',
                                lo=0.0, hi=1e6)
    host_controller: bool = param(True, 'run lmi_controller in this process: each cycle '
                                  '(read device -> controller -> write) in one loop thread, '
                                  'the state -> command hop a function call (ros2_control '
                                  'pattern); false: commands come over DDS from a separate '
                                  'lmi_controller process')
    loop_process: bool = param(True, 'with host_controller: run the loop (device backend, '
                               'controller, pacing) in a child process without rclpy, '
                               'exchanging records with this node through shared memory, so '
                               'the deadline never waits for a GIL that ROS threads hold '
                               '(backends that use rclpy themselves, ros_topics, keep the '
                               'loop thread); false: in a loop thread of this process')
    cpu_affinity: tuple[int, ...] = param(
        [-1], 'CPUs the loop runs on (the loop thread or loop process when hosting the '
        'controller, else the process), e.g. [1]; [-1] = no pinning')
    lock_memory: bool = param(False, 'mlockall(MCL_CURRENT | MCL_FUTURE) at activation, so '
                              'the loop never waits for a page fault; needs CAP_IPC_LOCK or '
                              'a memlock limit (else one warning)')
    sched_slice_us: float = param(
        100.0, 'under normal scheduling, the scheduler slice (us) the loop (process or thread; '
        'separate layout: the executor) asks for (Linux >= 6.12, EEVDF): a short one lets it '
        'preempt a busy task as soon as it wakes instead of after that task\'s slice (0.7-3 '
        'ms); its share of the CPU is unchanged, no privilege needed; 0 = the kernel\'s '
        'default; the kernel accepts 100-100000', lo=0.0, hi=100000.0)
    timer_slack_ns: int = param(
        0, 'timer slack of the loop (ns): how much later than its deadline the kernel may '
        'wake it to batch timers (prctl PR_SET_TIMERSLACK; 50000 by default; none under '
        'SCHED_FIFO), e.g. 1000; 0 = unchanged', lo=0, hi=10_000_000)
    publisher_nice: int = param(5, 'with the loop process: nice increment of the thread '
                                'that publishes its records (DeviceState, DeviceCommand, '
                                "hand inputs), and the nice value of this node's autogroup "
                                'when it leads its own session, so it yields the CPU to the '
                                'loop process when the cores are busy; 0 = unchanged. Not '
                                'applied to a loop thread layout, where it would hold the '
                                'GIL the loop waits for', lo=0, hi=19)
    sched_policy: str = param('batch', 'with the loop process: scheduling policy of every '
                              "thread of this node (its executor, DDS's threads, the "
                              'publisher). batch: SCHED_BATCH, they never preempt the running '
                              'loop process when they wake; the loop process keeps normal '
                              'scheduling (or SCHED_FIFO). No privilege needed; not applied '
                              'to a loop thread or the separate layout, where the loop runs '
                              'in this process. other = normal scheduling. (SCHED_IDLE is '
                              'not offered here: the loop process this node starts would '
                              'inherit it, and without privilege it could not leave it.)',
                              choices=('other', 'batch'))
    node_cpu_affinity: tuple[int, ...] = param(
        [-1], 'with the loop process: CPUs every thread of this node runs on (its executor, '
        "DDS's threads, the publisher), e.g. [0] with cpu_affinity [1]: the loop process then "
        "has a core that this node's threads never take. The loop process runs on "
        'cpu_affinity (with [-1] there: on the CPUs this process had before). No privilege '
        'needed; not applied to a loop thread or the separate layout. [-1] = no pinning')

    def check(self) -> None:
        if self.rate_hz != 0.0 and not RATE_MIN <= self.rate_hz <= RATE_MAX:
            raise ConfigError(f'device_driver: parameter rate_hz: expected 0.0 (1/scenario dt) '
                              f'or a value in [{RATE_MIN:g}, {RATE_MAX:g}] Hz, got '
                              f'{self.rate_hz!r}')
        parse_backend_options(self.backend_options)
        lo, hi = SLICE_RANGE_US
        if self.sched_slice_us != 0.0 and not lo <= self.sched_slice_us <= hi:
            raise ConfigError(f'device_driver: parameter sched_slice_us: expected 0.0 (the '
                              f"kernel's default) or a value in [{lo:g}, {hi:g}] us, got "
                              f'{self.sched_slice_us!r}')


@dataclass(frozen=True)
class LmiControllerSettings(NodeSettings):
    """Parameters of ``lmi_controller``. ``mode``/``k_tc``/``b_tc`` None: the scenario's."""

    NODE: ClassVar[str] = 'lmi_controller'

    scenario: str = _scenario('linkage, gains, device inertia, LMI model')
    executor: str = _executor()
    graph_id: str = _graph_id()
    sched_priority: int = _sched_priority()
    mode: str | None = param(None, 'control law: penalty (eq. 14) or acceleration_only '
                             "(eq. 10); live; default: the scenario's", read_only=False,
                             choices=MODES, ros_default='penalty')
    k_tc: float | None = param(None, 'penalty stiffness k_tc of eq. 13 (N/(m kg)); live; '
                               "default: the scenario's", read_only=False, lo=0.0,
                               hi=GAIN_MAX, ros_default=0.0)
    b_tc: float | None = param(None, 'penalty damping b_tc of eq. 13 (N s/(m kg)); live; '
                               "default: the scenario's", read_only=False, lo=0.0,
                               hi=GAIN_MAX, ros_default=0.0)
    max_dt: float = param(0.05, 'longest measured period used for one LMI step (s); longer '
                          'gaps (a paused device) are clipped', lo=1e-4, hi=1.0)
    stale_after: float = param(0.05, 'LMI update age (s) from which the model counts as stale '
                               '(warning; the last constraint set is kept)', lo=1e-3, hi=60.0)
    degrade_after: float = param(0.6, 'LMI update age (s) from which the force fades to zero',
                                 lo=1e-3, hi=60.0)
    resync_max_jump: float = param(
        1.0, 'largest estimated force step (N, N m) a re-sync may cause at once: |K_pc dx| + '
        "|B_pc dv| + |M_d P (k_tc dx + b_tc dv)| (eq. 13-16), the update's VT hand against "
        'ours at the same time; beyond it the re-sync is held until the force has faded out',
        lo=0.0, hi=1e6)
    resync_ramp: float = param(0.2, 'time (s) of a full force fade out before / in after a '
                               're-sync that may jump (stale model, restarted ve_sim or '
                               'device)', lo=1e-3, hi=10.0)
    clock: str = _clock('lockstep: simulated time (/clock from device_driver); a state is '
                        'answered only with the LMI update the offline simulation applies at '
                        'that step (see lockstep_wait)')
    lockstep_wait: float = param(60.0, 'lock-step: longest wait (wall s) for the LMI update the '
                                 'offline simulation applies at this step (a notice after '
                                 '5 s); then warn and answer with the local model',
                                 lo=0.01, hi=600.0)
    passivity: str = param(
        'auto', 'passivity controller of the law (time-domain passivity, Hannaford & Ryu; '
        "haptic_topology.control.passivity): enabled, disabled, or auto: the scenario's "
        'passivity block if it has one, else enabled when hosted by a device_driver whose '
        'backend is not a simulation, else disabled (not on/off: YAML reads those as '
        'booleans)', choices=('auto', 'enabled', 'disabled'))
    ack_updates: bool = param(False, 'publish the seq of every LMI update taken on '
                              'haptic/lmi/ack (std_msgs/UInt64), after it was taken: replay '
                              '--check-controller sends the next state only then')

    def check(self) -> None:
        for name in ('k_tc', 'b_tc'):
            value = getattr(self, name)
            reason = None if value is None else check_gain(name, value)
            if reason:
                raise ConfigError(f'lmi_controller: parameter {reason}')
        if self.degrade_after < self.stale_after:
            raise ConfigError(f'lmi_controller: parameters: degrade_after '
                              f'({self.degrade_after} s) must be >= stale_after '
                              f'({self.stale_after} s)')

    @classmethod
    def defaults_from(cls, scenario: Scenario) -> dict[str, Any]:
        return {'mode': scenario.mode.label, 'k_tc': float(scenario.gains.k_tc),
                'b_tc': float(scenario.gains.b_tc)}


# -- ve_sim ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VeSimSettings(NodeSettings):
    """Parameters of ``ve_sim``. ``update_period`` 0: the scenario's ``lmi.update_period``."""

    NODE: ClassVar[str] = 've_sim'

    scenario: str = _scenario('linkage, initial state, internal step, VT coupling')
    executor: str = _executor()
    graph_id: str = _graph_id()
    sched_priority: int = _sched_priority()
    nice: int = _nice(5)
    sched_policy: str = _sched_policy()
    cpu_affinity: tuple[int, ...] = _cpu_affinity()
    update_period: int = param(0, 'hand inputs per LMI update (10 at 1 kHz = 100 Hz); 0 = the '
                               "scenario's lmi.update_period", lo=0, hi=10000)
    idle_update_rate_hz: float = param(50.0, 'LMI updates per second while no hand input '
                                       'comes (start-up, controller stopped or restarting), '
                                       'so a controller can sync', lo=0.1, hi=1000.0)
    max_hand_wrench: float = param(1000.0, 'hand inputs with an entry beyond this (N, N m) '
                                   'in a wrench applied to the VT (the hand wrench; the '
                                   'coupling wrench with vt_coupling) are rejected', lo=1e-3,
                                   hi=1e9)
    viz_rate_hz: float = param(30.0, 'rate of /tf, joint states, markers and the Pose/Twist/'
                               'Wrench mirrors (Hz)', lo=0.1,
                               hi=200.0)
    frame_id: str = param('world', 'the world frame: root of /tf, frame of the markers, '
                          'the LMI updates, the VT path and the VT hand mirrors')
    clock: str = _clock('lockstep: simulated time (/clock from device_driver); no keep-alive '
                        'updates once hand inputs flow, so updates come at the offline '
                        "simulation's steps")


# -- recorder ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecorderSettings(NodeSettings):
    """Parameters of ``recorder``."""

    NODE: ClassVar[str] = 'recorder'

    scenario: str = param('fig8', 'scenario name, used in the default bag name')
    executor: str = _executor()
    graph_id: str = _graph_id()
    sched_priority: int = _sched_priority()
    nice: int = _nice(10)
    sched_policy: str = _sched_policy()
    cpu_affinity: tuple[int, ...] = _cpu_affinity()
    output: str = param('', 'bag directory to create (must not exist); empty: '
                        'bags/<scenario>_<timestamp>')
    topics: tuple[str, ...] = param([''], 'topics to record (empty: all of the graph)')
    topic_regex: str = param('', 'also record the graph topics matching this regular '
                             'expression (on the absolute name)')
    flush_period: float = param(0.2, 'close the current chunk and hand it to the OS at least '
                                'this often (s): what a SIGKILL can lose', lo=0.01, hi=10.0)
    chunk_kib: int = param(64, 'MCAP chunk size (KiB)', lo=4, hi=65536)
    compression: str = param('zstd', 'MCAP chunk compression', choices=COMPRESSIONS)
    max_bag_size: int = param(0, 'split the bag (as rosbag2 does): start a new storage file '
                              'once the current one holds this many bytes; 0 = no limit',
                              lo=0, hi=1 << 50)
    max_bag_duration: float = param(600.0, 'split the bag: start a new storage file once the '
                                    'current one spans this many seconds of messages (bounds '
                                    "the writer's index in memory over long sessions); 0.0 = "
                                    'no limit', lo=0.0, hi=1e7)
    clock: str = param('wall', "the graph's clock: with lockstep the state and command topics "
                       'are reliable and are recorded so', choices=tuple(c.value for c in Clock))

    def check(self) -> None:
        try:
            re.compile(self.topic_regex)
        except re.error as exc:
            raise ConfigError(f'recorder: parameter topic_regex: {exc}') from None


# -- foxglove_bridge ---------------------------------------------------------------------------
@dataclass(frozen=True)
class FoxgloveBridgeSettings(NodeSettings):
    """Parameters of ``foxglove_bridge`` (the graph's topics on the Foxglove WebSocket
    protocol, ``haptic_topology.nodes.foxglove_bridge``)."""

    NODE: ClassVar[str] = 'foxglove_bridge'

    scenario: str = param('fig8', 'scenario name (only named in the server name; accepted so '
                          "that the graph's common -p scenario:=... applies)")
    executor: str = _executor()
    graph_id: str = param('', "the graph served (named in /diagnostics; accepted so that the "
                          "graph's common -p graph_id:=... applies): the bridge serves what "
                          'is on the topics')
    nice: int = _nice(10)
    sched_policy: str = _sched_policy()
    cpu_affinity: tuple[int, ...] = _cpu_affinity()
    host: str = param('127.0.0.1', 'address the WebSocket server listens on (0.0.0.0: every '
                      'interface, for a Foxglove app on another machine)')
    port: int = param(8765, 'TCP port of the WebSocket server (0: any free port; the port '
                      'taken is in the /diagnostics status)', lo=0, hi=65535)
    topics: tuple[str, ...] = param([''], 'topics to serve (empty: every topic of the '
                                    'graph, haptic_topology.vocabulary.TOPIC_ROLES)')
    forward_period: float = param(0.02, 'the serialized messages DDS holds are taken and '
                                  'forwarded this often (s)', lo=0.001, hi=1.0)
    message_backlog: int = param(1024, 'messages that may wait for one client; beyond it the '
                                 'oldest is dropped and counted for that client only (a slow '
                                 'client holds at most this many)', lo=1, hi=1_000_000)
    clock: str = param('wall', "the graph's clock: with lockstep the state and command topics "
                       'are reliable, and are subscribed so',
                       choices=tuple(c.value for c in Clock))

    def check(self) -> None:
        if not self.host.strip():
            raise ConfigError('foxglove_bridge: parameter host: expected an address, got ""')
