"""What the nodes share: topic names, QoS, parameter declaration, loop health, ``main``.

QoS of the graph (why):

============================  ================================  ===================================
topic                         QoS                               why
============================  ================================  ===================================
``haptic/device/state``       best effort, keep last 1          1 kHz; the newest state counts
``haptic/device/command``     best effort, keep last 1          1 kHz; a late command is useless,
                                                                the device applies the newest
``haptic/hand_inputs``        reliable, keep last 500           ~100 Hz: one ``HandInputs`` per
                                                                VE update period with the 1 kHz
                                                                samples; the VE integrates every
                                                                one (zero-order hold between
                                                                them), a lost one would bend the
                                                                VT path. 500 batches: 5 s. Not on
                                                                the device's critical path, so a
                                                                retransmission costs nothing
``haptic/lmi/update``,        reliable, keep last 5000          ~100 Hz; each update re-syncs;
``haptic/ve/path``                                              the VT hand at every cycle
``/clock``                    best effort, keep last 1          lock-step only: simulated time
``haptic/joint_states``,      reliable, keep last 5             visualisation, ~30 Hz
``haptic/markers``,
``haptic/viz/...`` mirrors
``/tf``                       reliable, keep last 100           as tf2_ros broadcasts it
``/robot_description``        reliable, transient local,        once; a late subscriber gets it
                              keep last 1                       (as robot_state_publisher)
``/diagnostics``              reliable, keep last 10            1 Hz loop health
============================  ================================  ===================================

With ``clock: lockstep`` the state and command topics are reliable (keep last 10000): the
device steps only when the answer has come, so a lost message would stall the loop, and a bag
of the run must hold every state; the hand inputs keep 10000 batches too
(:func:`hand_inputs_qos`).

Why batches: a reliable 1 kHz stream with 5 s of history over UDP turned every gap (ve_sim
stopped for 1 s, or restarted) into a repair burst of hundreds of datagrams that overflowed
the socket buffer again, and the stream never recovered (fault test under load: 40697 inputs
lost against 11845 received). One message per VE update period carries the same samples in a
tenth of the messages, at the rate the VE consumes them anyway.

The recorder subscribes best effort with a deep queue (1000) to the best-effort topics and
reliable to the others, so it never slows a publisher down.

Executors: :class:`rclpy.experimental.EventsExecutor` by default (about 6 us per callback
against 130 us for the ``SingleThreadedExecutor``), spun with ``spin_once(timeout_sec=0.1)``
in a loop: in this rclpy build ``spin()`` and ``spin_once()`` without a timeout burn a core
and ignore SIGINT. ``executor: single_threaded`` is the fallback. The
``MultiThreadedExecutor`` is not offered (it collapses at 1 kHz in rclpy 7.1).
"""

from __future__ import annotations

import faulthandler
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
    ParameterUninitializedException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from haptic_topology.errors import ConfigError, HapticTopologyError
from haptic_topology.params import (
    NodeParams,
    ParamSpec,
    check_overrides,
    check_params_file,
    params_files,
)
from haptic_topology.settings import Clock, NodeSettings, param_specs

# -- topics ------------------------------------------------------------------------------------
TOPIC_STATE = 'haptic/device/state'
TOPIC_COMMAND = 'haptic/device/command'
TOPIC_LMI = 'haptic/lmi/update'
TOPIC_HAND_INPUTS = 'haptic/hand_inputs'
TOPIC_JOINTS = 'haptic/joint_states'
TOPIC_MARKERS = 'haptic/markers'
TOPIC_DIAGNOSTICS = '/diagnostics'
TOPIC_VT_PATH = 'haptic/ve/path'
TOPIC_LMI_ACK = 'haptic/lmi/ack'
TOPIC_CLOCK = '/clock'
# The linkage as a robot and standard mirrors, published by ve_sim (frames:
# haptic_topology.frames; messages: haptic_topology.nodes.viz).
TOPIC_ROBOT_DESCRIPTION = '/robot_description'
TOPIC_TF = '/tf'
TOPIC_DEVICE_POSE = 'haptic/viz/device/pose'
TOPIC_DEVICE_TWIST = 'haptic/viz/device/twist'
TOPIC_VT_POSE = 'haptic/viz/vt_hand/pose'
TOPIC_VT_TWIST = 'haptic/viz/vt_hand/twist'
TOPIC_WRENCH_APPLIED = 'haptic/viz/wrench/applied'
TOPIC_WRENCH_HAND = 'haptic/viz/wrench/hand'
TOPIC_WRENCH_COUPLING = 'haptic/viz/wrench/coupling'
#: The standard mirrors (geometry_msgs/*Stamped), at viz_rate_hz.
MIRROR_TOPICS = (TOPIC_DEVICE_POSE, TOPIC_DEVICE_TWIST, TOPIC_VT_POSE, TOPIC_VT_TWIST,
                 TOPIC_WRENCH_APPLIED, TOPIC_WRENCH_HAND, TOPIC_WRENCH_COUPLING)


def _qos(reliable: bool, depth: int) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE)


QOS_LOOP = _qos(False, 1)         # state, command
#: Lock-step: the device steps only on the answer, so nothing may be lost (and nothing waits);
#: a deep history so that a recorder that falls behind a fast lock-step run loses nothing.
QOS_LOOP_LOCKSTEP = _qos(True, 10000)
QOS_CLOCK = _qos(False, 1)
#: Reliable topics keep 5 s of messages: a reader (the recorder) that falls behind by less
#: than that loses nothing (a keep-last writer overwrites what is not acknowledged).
QOS_HAND_INPUTS = _qos(True, 500)   # 100 Hz batches
#: Lock-step: as deep as the loop topics (a recorder behind a fast lock-step run).
QOS_HAND_INPUTS_LOCKSTEP = _qos(True, 10000)
QOS_LMI = _qos(True, 5000)
QOS_VIZ = _qos(True, 5)
#: /tf as tf2_ros's TransformBroadcaster offers it (reliable, volatile, keep last 100).
QOS_TF = _qos(True, 100)
#: /robot_description as robot_state_publisher offers it: a late subscriber (RViz started
#: later) still gets the one message (reliable, transient local, keep last 1).
QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
QOS_DIAGNOSTICS = _qos(True, 10)
#: The recorder's readers: what DDS holds between two of its takes (every 10 ms) and through
#: a stall of its writer thread; at the graph's rates at 14x (14,000 states/s) 10,000 is
#: 0.7 s (1,000 overflowed in a 20 s benchmark run: gaps of up to 2,500 states).
QOS_RECORD_BEST_EFFORT = _qos(False, 10000)
QOS_RECORD_RELIABLE = _qos(True, 10000)

#: Topic -> QoS of its publisher (the recorder mirrors the reliability).
TOPIC_QOS: dict[str, QoSProfile] = {
    TOPIC_STATE: QOS_LOOP, TOPIC_COMMAND: QOS_LOOP, TOPIC_HAND_INPUTS: QOS_HAND_INPUTS,
    TOPIC_LMI: QOS_LMI, TOPIC_VT_PATH: QOS_LMI,
    TOPIC_JOINTS: QOS_VIZ, TOPIC_MARKERS: QOS_VIZ, TOPIC_DIAGNOSTICS: QOS_DIAGNOSTICS,
    TOPIC_ROBOT_DESCRIPTION: QOS_LATCHED, TOPIC_TF: QOS_TF,
    **{t: QOS_VIZ for t in MIRROR_TOPICS},
}


#: Topic (a key of :data:`TOPIC_QOS`) -> full type name of its messages: what a tool that
#: subscribes by topic alone (``foxglove_bridge``) serves it as. Every topic of
#: :data:`TOPIC_QOS` has one (test/test_foxglove.py checks it).
TOPIC_TYPES: dict[str, str] = {
    TOPIC_STATE: 'haptic_topology_msgs/msg/DeviceState',
    TOPIC_COMMAND: 'haptic_topology_msgs/msg/DeviceCommand',
    TOPIC_HAND_INPUTS: 'haptic_topology_msgs/msg/HandInputs',
    TOPIC_LMI: 'haptic_topology_msgs/msg/LmiUpdate',
    TOPIC_VT_PATH: 'haptic_topology_msgs/msg/VtPath',
    TOPIC_JOINTS: 'sensor_msgs/msg/JointState',
    TOPIC_MARKERS: 'visualization_msgs/msg/MarkerArray',
    TOPIC_DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    TOPIC_ROBOT_DESCRIPTION: 'std_msgs/msg/String',
    TOPIC_TF: 'tf2_msgs/msg/TFMessage',
    TOPIC_DEVICE_POSE: 'geometry_msgs/msg/PoseStamped',
    TOPIC_DEVICE_TWIST: 'geometry_msgs/msg/TwistStamped',
    TOPIC_VT_POSE: 'geometry_msgs/msg/PoseStamped',
    TOPIC_VT_TWIST: 'geometry_msgs/msg/TwistStamped',
    TOPIC_WRENCH_APPLIED: 'geometry_msgs/msg/WrenchStamped',
    TOPIC_WRENCH_HAND: 'geometry_msgs/msg/WrenchStamped',
    TOPIC_WRENCH_COUPLING: 'geometry_msgs/msg/WrenchStamped',
}

def loop_qos(clock: Clock) -> QoSProfile:
    """QoS of the 1 kHz state/command topics under ``clock`` (see the table above)."""
    return QOS_LOOP_LOCKSTEP if clock is Clock.LOCKSTEP else QOS_LOOP


def hand_inputs_qos(clock: Clock) -> QoSProfile:
    """QoS of ``haptic/hand_inputs`` under ``clock``: reliable either way (the VE must
    integrate every input); keep last 500 batches (5 s at 100 Hz), 10000 in lock-step."""
    return QOS_HAND_INPUTS_LOCKSTEP if clock is Clock.LOCKSTEP else QOS_HAND_INPUTS


def publisher_qos(topic: str, clock: Clock) -> QoSProfile:
    """QoS the graph's publisher of ``topic`` (a key of :data:`TOPIC_QOS`) offers under
    ``clock`` (what the recorder mirrors and writes into the bag)."""
    if topic in (TOPIC_STATE, TOPIC_COMMAND):
        return loop_qos(clock)
    if topic == TOPIC_HAND_INPUTS:
        return hand_inputs_qos(clock)
    return TOPIC_QOS[topic]


# -- parameters --------------------------------------------------------------------------------
def declare(node: Node, name: str, default: Any, description: str, *, read_only: bool = True,
            lo: float | None = None, hi: float | None = None,
            choices: Sequence[str] | None = None) -> Any:
    """Declare a parameter with description, range and read-only flag; return its value.

    Values from a params file are checked here: a wrong type or a value out of range raises
    :class:`ConfigError` naming the node and the parameter.
    """
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if choices is not None:
        desc.additional_constraints = 'one of: ' + ', '.join(choices)
    if lo is not None and hi is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f'range given for non-numeric parameter {name}')
        if isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    where = f'{node.get_name()}: parameter {name}'
    try:
        value = node.declare_parameter(name, default, desc).value
    except InvalidParameterTypeException as exc:
        raise ConfigError(f'{where}: expected {type(default).__name__}, got {exc}') from None
    except InvalidParameterValueException as exc:
        raise ConfigError(f'{where}: {exc}') from None
    except (ParameterException, ParameterUninitializedException) as exc:
        raise ConfigError(f'{where}: {exc}') from None
    if choices is not None and value not in choices:
        raise ConfigError(f'{where}: expected one of {", ".join(choices)}, got {value!r}')
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f'{where}: expected a finite number, got {value}')
    return value


def declare_spec(node: Node, spec: ParamSpec, default: Any = None) -> Any:
    """:func:`declare` from a :class:`ParamSpec` (``default`` overrides the spec's, e.g. a
    value taken from the scenario; it must have the spec's type)."""
    return declare(node, spec.name, spec.default if default is None else default,
                   spec.description, read_only=spec.read_only, lo=spec.lo, hi=spec.hi,
                   choices=spec.choices)


S = TypeVar('S', bound=NodeSettings)


def declare_settings(node: Node, cls: type[S],
                     scenario_defaults: Mapping[str, Any] | None = None) -> S:
    """Declare every parameter of the settings class ``cls`` on ``node`` (description, range,
    read-only flag from its fields) and return the frozen settings.

    ``scenario_defaults``: defaults to declare instead of the table's (see
    :func:`haptic_topology.settings.scenario_defaults`). Parameters the node has declared
    already (e.g. ``scenario``, read first to load the scenario the defaults come from) keep
    their value. A bad value raises :class:`ConfigError` naming the node and the parameter.
    """
    defaults = scenario_defaults or {}
    values: dict[str, Any] = {}
    for name, spec in param_specs(cls).items():
        if node.has_parameter(name):
            values[name] = node.get_parameter(name).value
        else:
            values[name] = declare_spec(node, spec, defaults.get(name))
    try:
        return cls.from_values(values)
    except ConfigError as exc:
        node_name = node.get_name()
        text = str(exc)
        if node_name != cls.NODE and text.startswith(f'{cls.NODE}: '):
            text = f'{node_name}: {text[len(cls.NODE) + 2:]}'
        raise ConfigError(text) from None


# -- loop health -------------------------------------------------------------------------------
def diagnostics(node: Node, name: str, values: dict[str, str], level: int = 0,
                message: str = 'ok', hardware_id: str | None = None) -> DiagnosticArray:
    """A one-status :class:`DiagnosticArray` (level: DiagnosticStatus.OK/WARN/ERROR).

    ``hardware_id``: the hardware the status is about (the device driver: backend and device,
    :func:`haptic_topology.device.loop.hardware_id`); None for a node that drives no hardware,
    which reports its fully qualified node name. Every status carries ``pid``: the reporting
    process, so a tool that restarts a node can tell the new process's reports from late ones
    of the process it replaced."""
    values = {**values, 'pid': str(os.getpid())}
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    status = DiagnosticStatus(level=bytes([level]), name=name, message=message,
                              hardware_id=(node.get_fully_qualified_name() if hardware_id is None
                                           else hardware_id))
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    arr.status = [status]
    return arr


def matched(endpoints: Mapping[str, Any]) -> dict[str, str]:
    """Diagnostic values ``matched <topic>``: for each publisher the DDS readers matched to
    it, for each subscription the DDS writers matched to it (what the middleware actually
    connected, not the graph cache). A restarted node whose topic stays at 0 here is not
    connected, whatever the graph says."""
    out = {}
    for key, ep in endpoints.items():
        n = (ep.get_subscription_count() if hasattr(ep, 'get_subscription_count')
             else ep.get_publisher_count())
        out[f'matched {key}'] = str(n)
    return out


def log_notices(node: Node, notices: Any) -> None:
    """Log each text of ``notices`` (a list or deque another thread appends to: the loop
    thread's) as a warning of ``node``, oldest first, removing it."""
    while notices:
        try:
            text = notices.pop(0) if isinstance(notices, list) else notices.popleft()
        except IndexError:          # taken by another thread meanwhile
            break
        node.get_logger().warn(text)


def monotonic() -> float:
    return time.monotonic()


# -- main ----------------------------------------------------------------------------------------
def make_executor(kind: str) -> Any:
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    return SingleThreadedExecutor()


#: Seconds after SIGINT/SIGTERM at which a node still running dumps its threads' stacks (the
#: bringup escalates to SIGTERM after 5 s).
STOP_DUMP_AFTER = 4.0


def spin(nodes: Sequence[Node], kind: str) -> None:
    """Spin ``nodes`` on one executor until SIGINT/SIGTERM (or rclpy's shutdown).

    The stop signals are this function's own (Python handlers installed after the executor
    exists, the previous ones restored when it returns): rclpy's ``EventsExecutor`` installs
    an asio handler for SIGINT and SIGTERM when it is created, and measured here a recorder
    idling on it ignored the SIGINT in 2 of 13 tries (it went on spinning normally, main
    thread in ``spin_once``'s timed wait, until SIGKILL): the bringup's "node did not exit"
    failures. A Python handler only sets a flag; ``spin_once`` returns every 0.1 s, so the
    loop ends within that after the signal, whatever the executor does with signals. The
    handlers stay for the rest of the process (see below).
    """
    executor = make_executor(kind)
    for n in nodes:
        executor.add_node(n)
    stop: list[int] = []

    def request_stop(signum: int, frame: Any) -> None:
        if not stop:
            # A node that has not ended STOP_DUMP_AFTER s after the signal writes every
            # thread's Python stack to stderr (its log): where a stop hangs, not a guess.
            faulthandler.dump_traceback_later(STOP_DUMP_AFTER, exit=False)
        stop.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        # Kept after the loop: a second signal must not raise KeyboardInterrupt in the
        # middle of the nodes' close (the recorder finalising its bag); a teardown that
        # hangs gets the bringup's SIGKILL.
        signal.signal(sig, request_stop)
    try:
        while rclpy.ok() and not stop:
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown(timeout_sec=1.0)


DISCOVERY_ENV = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
#: Fast DDS's XML profile variable, and the project's profile for DDS on this host
#: (``config/fastdds_localhost.xml``: user data over UDP on the loopback, no shared memory).
FASTDDS_PROFILES_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
LOCALHOST_PROFILE = 'fastdds_localhost.xml'


def localhost_discovery_default(env: dict[str, str] | os._Environ[str]) -> str:
    """Keep DDS on this host unless the user chose otherwise; return the discovery range.

    Sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` in ``env`` when neither it nor the
    deprecated ``ROS_LOCALHOST_ONLY`` is set. With the range ``LOCALHOST`` and Fast DDS (the
    default RMW), also sets ``FASTRTPS_DEFAULT_PROFILES_FILE`` to :data:`LOCALHOST_PROFILE`
    unless it or ``ROS_STATIC_PEERS`` is set: user data then goes over UDP on the loopback
    instead of shared memory, where Fast DDS 2.14 can leave a killed and restarted process
    deaf (eProsima/Fast-DDS#5053). To run nodes on several machines set
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (or keep LOCALHOST and list the other hosts in
    ``ROS_STATIC_PEERS``) and the same ``ROS_DOMAIN_ID`` on every machine.
    """
    if DISCOVERY_ENV not in env and 'ROS_LOCALHOST_ONLY' not in env:
        env[DISCOVERY_ENV] = 'LOCALHOST'
    scope = env.get(DISCOVERY_ENV, 'LOCALHOST' if env.get('ROS_LOCALHOST_ONLY') == '1'
                    else 'SUBNET')
    if (scope == 'LOCALHOST' and FASTDDS_PROFILES_ENV not in env
            and not env.get('ROS_STATIC_PEERS')
            and env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') == 'rmw_fastrtps_cpp'):
        from haptic_topology.paths import config_dir
        profile = config_dir() / LOCALHOST_PROFILE
        if profile.is_file():
            env[FASTDDS_PROFILES_ENV] = str(profile)
    return scope


def check_config_args(argv: Sequence[str], known: Mapping[str, NodeParams | None],
                      node: str | None) -> None:
    """Check every ``--params-file`` and ``-p`` name of ``argv`` before rclpy parses them."""
    ros_args = _ros_args(argv)
    for path in params_files(ros_args):
        check_params_file(path, known, node)
    check_overrides(ros_args, known, node)


def _ros_args(argv: Sequence[str]) -> list[str]:
    out: list[str] = []
    inside = False
    for a in argv:
        if a == '--ros-args':
            inside = True
        elif a == '--':
            inside = False
        elif inside:
            out.append(a)
    return out


def run_main(prog: str, build: Callable[[], Sequence[Node]],
             args: Sequence[str] | None = None,
             params: Mapping[str, NodeParams | None] | None = None,
             exit_after_close: bool = False) -> int:
    """Init rclpy, build the node(s), spin, shut down cleanly; return the exit status.

    ``exit_after_close``: end the process with the status once the nodes' ``close`` has run,
    without rclpy's teardown (the recorder, see the comment at the end). Called as a
    program (``args`` None) the process always ends in this function, after rclpy's
    shutdown and without the interpreter's finalization (see the end).

    ``params``: node name -> its declared parameters (None: unknown here), used to check the
    params files and ``-p`` overrides before rclpy reads them; ``prog`` is the node checked
    (all of ``params`` for ``composed``). DDS discovery defaults to this host
    (:func:`localhost_discovery_default`).

    A configuration problem (params file, parameter, scenario) prints one line
    ``<prog>: error: ...`` and returns 2 without a traceback.
    """
    argv = list(sys.argv if args is None else args)
    localhost_discovery_default(os.environ)
    from haptic_topology.sampling import start_from_env
    start_from_env()
    if params is not None:
        try:
            check_config_args(argv, params, prog if prog in params else None)
        except ConfigError as exc:
            print(f'{prog}: error: {exc}', file=sys.stderr)
            return 2
    try:
        rclpy.init(args=argv)
    except (RuntimeError, ValueError) as exc:  # rclpy's RCLError is a RuntimeError
        print(f'{prog}: error: invalid ROS arguments or params file: {_first_line(exc)}',
              file=sys.stderr)
        return 2
    nodes: list[Node] = []
    status = 0
    try:
        nodes = list(build())
        kind = str(nodes[0].get_parameter('executor').value) if nodes else 'events'
        # A node that applies real-time settings to its own loop thread (the hosted
        # device_driver) sets ``process_sched_priority`` = 0: the rest of its process stays
        # under normal scheduling.
        priority = max((int(getattr(n, 'process_sched_priority',
                                    n.get_parameter('sched_priority').value))
                        for n in nodes if n.has_parameter('sched_priority')), default=0)
        if priority:
            problem = set_realtime_priority(priority)
            if problem:
                nodes[0].get_logger().warn(problem)
            else:
                nodes[0].get_logger().info(f'SCHED_FIFO priority {priority}')
        spin(nodes, kind)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except HapticTopologyError as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        status = 2
    except (ParameterException, RuntimeError) as exc:
        if not rclpy.ok():  # shutting down: a late rcl error is not a config problem
            pass
        else:
            print(f'{prog}: error: {_first_line(exc)}', file=sys.stderr)
            status = 2
    finally:
        for n in nodes:
            close = getattr(n, 'close', None)
            if close is not None:
                close()
        if exit_after_close:
            # Everything the nodes own is closed (the recorder's bag is complete): nothing
            # is left for rclpy's teardown to do. (Clean-clone CI runs had reported the
            # recorder "hung" here; the cause found later was the lost SIGINT, see spin().)
            _end_process(status)
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
    if args is None:
        # A node process (console script, python -m) ends here, without the interpreter's
        # finalization: everything ROS is shut down above, and finalization only destroys
        # rclpy's and Fast DDS's C++ objects once more. Measured: under load that took over
        # 4 s after run_main had returned (faulthandler: the main thread with no Python
        # frame), and the bringup's SIGTERM ended the process with -15.
        _end_process(status)
    return status


def _end_process(status: int) -> None:
    """``os._exit(status)`` after the sampling profiler's dump and the stdio buffers (no
    ``atexit`` function runs after it)."""
    from haptic_topology.sampling import dump_now

    dump_now()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def set_realtime_priority(priority: int) -> str | None:
    """Put every thread of this process (DDS's receive threads included, which run the
    subscription callbacks' wake-ups) under SCHED_FIFO at ``priority``; threads started later
    inherit it. Returns None, or why it was not possible (the process then keeps normal
    scheduling).

    Why: on 2 cores the 1 kHz pair (device_driver, lmi_controller) shares the CPU with ve_sim's
    RK4 and the recorder; measured on the circle scenario, 10 s, separate processes: cycles
    answered in time 82 % -> 94 %, device period p99 1.76 -> 1.08 ms (README, benchmarks).
    Linux throttles real-time threads to 95 % of each second (sched_rt_runtime_us), so a
    runaway loop cannot lock the machine.
    """
    try:
        tids = [int(t) for t in os.listdir('/proc/self/task')]
    except OSError:
        tids = [0]
    try:
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return (f'sched_priority {priority}: not permitted (needs CAP_SYS_NICE or an rtprio '
                'limit, e.g. in /etc/security/limits.conf); running with normal scheduling')
    except (OSError, AttributeError) as exc:
        return f'sched_priority {priority}: {exc}; running with normal scheduling'
    return None


def set_thread_realtime(priority: int, cpus: Sequence[int], lock_memory: bool) -> list[str]:
    """Real-time settings of the calling thread (the hosted device loop thread): SCHED_FIFO
    at ``priority`` (0: keep normal scheduling), pinned to ``cpus`` (``[-1]``: no pinning),
    and ``mlockall(MCL_CURRENT | MCL_FUTURE)`` for the process when ``lock_memory``. Returns
    one line per setting that was not permitted (the loop then runs without it)."""
    problems = []
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # this thread
        except PermissionError:
            problems.append(f'sched_priority {priority}: not permitted (needs CAP_SYS_NICE or '
                            'an rtprio limit); normal scheduling')
        except OSError as exc:
            problems.append(f'sched_priority {priority}: {exc}; normal scheduling')
    if list(cpus) != [-1]:
        try:
            os.sched_setaffinity(0, set(cpus))
        except OSError as exc:
            problems.append(f'cpu_affinity {list(cpus)}: {exc}; not pinned')
    if lock_memory:
        problems.extend(filter(None, [lock_all_memory()]))
    return problems


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` (at most 15 bytes) in /proc/<pid>/task/<tid>/comm,
    so ``top -H`` and the benchmark's CPU per thread can tell the loop thread apart."""
    import ctypes
    import ctypes.util

    pr_set_name = 15
    libc = ctypes.CDLL(ctypes.util.find_library('c'), use_errno=True)
    libc.prctl(pr_set_name, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)


def lock_all_memory() -> str | None:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)``; None, or why it failed."""
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library('c'), use_errno=True)
    mcl_current, mcl_future = 1, 2
    if libc.mlockall(mcl_current | mcl_future) != 0:
        err = ctypes.get_errno()
        return (f'lock_memory: mlockall failed: {os.strerror(err)} (needs CAP_IPC_LOCK or a '
                'memlock limit, e.g. ulimit -l unlimited); memory not locked')
    return None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
