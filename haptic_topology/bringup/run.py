"""``haptic-topology run SCENARIO --mode penalty|acceleration_only --duration S``: the bringup.

Starts the graph in one of four layouts (``--layout``): ``hosted`` (default): ``recorder``,
``ve_sim`` and ``device_driver``, which hosts ``lmi_controller`` (``device_driver.
host_controller``) and runs the 1 kHz cycle in its loop process, a child without rclpy
(``device_driver.loop_process``); ``thread``: the same with the cycle in a loop thread of the
driver's process (``loop_process: false``); ``separate``: the four nodes as four processes,
the state -> command hop over DDS; ``composed``: all four in one process on one executor
(``--composed`` is short for it; the driver hosts the controller). All with the params file
(default ``config/haptic_topology.yaml``) plus ``scenario``, ``clock`` (``wall`` or
``lockstep``), the controller's ``mode``, the recorder's ``output``,
``device_driver.min_subscribers = 2`` (controller and recorder must see the device before it
engages, so the bag holds the whole run) and ``device_driver.run_duration``. It waits on what
ROS tools see (:mod:`haptic_topology.bringup.watch`), never on log lines: the device driver
is started once the recorder's ``/diagnostics`` status says it is matched to the
controller's and the VE's publishers, and each publisher of a recorded topic (the device's
state publisher included) reports its readers matched
(:func:`~haptic_topology.bringup.watch.loop_readers`), and each subscription of the loop's
inputs its writers (:func:`~haptic_topology.bringup.watch.loop_writers`); the run is over
when the driver's lifecycle state is ``inactive`` (it deactivates itself after
``run_duration`` from engagement), or ends as soon as ``ve_sim`` reports a hand input batch it
rejected (one line with its reason: the VE did not take those inputs, so the run is not the
loop's from then on). Then it stops the device, controller, VE and the recorder
with SIGINT (SIGTERM, then SIGKILL, after a timeout each), reads the bag back as a stream in a
process of its own (:mod:`haptic_topology.bringup.analysis`) and writes ``trace.parquet``
(``--csv``: also ``trace.csv``), ``plot.png`` and ``summary.json`` next to the bag's files,
and prints the drift summary (as ``simulate``) and the loop figures. Several ``--mode``
options run one after the other. While the loop runs, ``--loop-cpu auto`` (the default for
the hosted layout on the wall clock) keeps a CPU for the loop process whenever other software
keeps the machine busy (:mod:`haptic_topology.bringup.partition`).

``--foxglove [PORT]`` also starts ``foxglove_bridge`` (first; the device starts once it
serves): the live topics on the Foxglove WebSocket protocol at ``ws://127.0.0.1:PORT``
(default 8765; ``--foxglove-host`` for another address), for Foxglove or Lichtblick without a
ROS install, under either subprotocol name (docs/foxglove.md; ``docs/foxglove_layout.json``).

The processes inherit the environment (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``).
Their logs are kept in ``<bag>/logs/``. One run at a time uses a ROS domain on one machine
(:func:`claim_domain`): a second run on the same domain refuses to start, in one line; two
graphs on one domain would share node names, lifecycle services and topics.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from haptic_topology.bringup.options import (
    CLOCKS,
    FOXGLOVE_NODE,
    LAYOUTS,
    loop_cpu_choice,
    loop_cpu_overrides,
    node_prefixes,
    param_overrides,
)
from haptic_topology.device.loop_process import CHILD_MODULE
from haptic_topology.errors import BringupError, ConfigError
from haptic_topology.paths import scenario_help
from haptic_topology.processes import STOP_TIMEOUT, RunUsage, terminate
from haptic_topology.vocabulary import LAW_MODES, STATUS_FOXGLOVE, TOPIC_STATE, Clock

if TYPE_CHECKING:
    from haptic_topology.sim.scenario import Scenario



#: Default port of ``--foxglove`` (the Foxglove app's default for a WebSocket connection).
FOXGLOVE_PORT = 8765
#: The bridge's ``/diagnostics`` status.
FOXGLOVE_STATUS = STATUS_FOXGLOVE


@dataclass
class _Proc:
    name: str
    popen: subprocess.Popen[bytes]
    log: Path
    handle: IO[bytes]


#: One lock file per ROS domain: held by the run that uses the domain (:func:`claim_domain`)
RUN_LOCKS = Path(tempfile.gettempdir()) / 'haptic_topology_runs'


def claim_domain(domain: int) -> int:
    """Claim ROS domain ``domain`` for this run on this machine; returns the descriptor of its
    lock (``flock``: released when closed, or when the process dies). Raises ConfigError,
    naming the other run's pid, while another run holds it."""
    RUN_LOCKS.mkdir(exist_ok=True)
    try:
        RUN_LOCKS.chmod(0o1777)     # any user's runs, as /tmp
    except OSError:
        pass                        # another user's directory: it is already so
    fd = os.open(RUN_LOCKS / f'domain_{domain}.lock', os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        other = os.pread(fd, 32, 0).decode(errors='replace').strip() or '?'
        os.close(fd)
        raise ConfigError(f'ROS domain {domain}: another haptic-topology run uses it on this '
                          f'machine (pid {other}); stop it, or give this run another domain, '
                          f'e.g. ROS_DOMAIN_ID={(domain + 1) % 102}') from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f'{os.getpid()}\n'.encode(), 0)
    return fd


def new_graph_id(scenario: str) -> str:
    """A graph identity for one run: ``<scenario>-<16 hex digits>`` (random)."""
    return f'{Path(scenario).stem}-{secrets.token_hex(8)}'


def environment_domain() -> int:
    """The ROS domain of this environment (``ROS_DOMAIN_ID``; 0 when unset)."""
    text = os.environ.get('ROS_DOMAIN_ID', '').strip()
    if not text:
        return 0
    try:
        return int(text)
    except ValueError:
        raise ConfigError(f'ROS_DOMAIN_ID: expected an integer 0-232, got {text!r}') from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('scenario', help=scenario_help())
    parser.add_argument('--mode', action='append', choices=LAW_MODES,
                        help="control law (repeat to run several); default: the scenario's")
    parser.add_argument('--duration', type=float,
                        help="run length (s) from the loop's first state; default: the "
                        "scenario's duration")
    parser.add_argument('--clock', choices=CLOCKS, default='wall',
                        help='wall: real time (default); lockstep: simulated time advancing '
                        'only when each state is answered, the result equals `simulate`')
    parser.add_argument('--layout', choices=tuple(LAYOUTS), default='hosted',
                        help='hosted (default): the controller in the device driver\'s '
                        'process and loop thread; separate: one process per node; composed: '
                        'all in one process')
    parser.add_argument('--composed', action='store_true', help='same as --layout composed')
    parser.add_argument('--out', type=Path, help='bag directory (one --mode only); default '
                        'bags/<scenario>_<mode>_<timestamp>')
    parser.add_argument('--params', type=Path, help='ROS 2 params file; default '
                        'config/haptic_topology.yaml')
    parser.add_argument('--backend', help='device_driver backend (default: the params file)')
    parser.add_argument('--startup-timeout', type=float, default=30.0,
                        help='seconds to wait for the loop to close (default 30)')
    parser.add_argument('--no-plot', action='store_true', help='skip plot.png')
    parser.add_argument('--csv', action='store_true',
                        help='also write the trace as trace.csv (trace.parquet is always written)')
    parser.add_argument('--node-prefix', action='append', default=[], metavar='NODE=COMMAND',
                        help='start process NODE of the layout with COMMAND before its command '
                        "line, e.g. 've_sim=ip netns exec ht_ve' (the VE on another network "
                        'namespace: scripts/two_hosts.sh); repeatable')
    parser.add_argument('--foxglove', type=int, nargs='?', const=FOXGLOVE_PORT, metavar='PORT',
                        help='also serve the live topics to Foxglove or Lichtblick on the '
                        'Foxglove WebSocket protocol (foxglove_bridge), on PORT (default '
                        f'{FOXGLOVE_PORT}); docs/foxglove.md')
    parser.add_argument('--foxglove-host', default='127.0.0.1', metavar='HOST',
                        help='address the Foxglove server listens on (default 127.0.0.1; '
                        '0.0.0.0 for an app on another machine)')
    parser.add_argument('--loop-cpu', metavar='CPU|auto|off',
                        help='keep CPU for the loop process: pin it there and every other '
                        'thread of the graph to the other CPUs (hosted layout; no privilege '
                        'needed); auto (the default with --layout hosted --clock wall): only '
                        'while other software keeps the machine busy; off: never '
                        '(docs/nodes.md, a core for the loop)')
    parser.add_argument('-p', '--param', action='append', default=[],
                        metavar='NODE:NAME:=VALUE',
                        help='a node parameter over the params file, e.g. '
                        "'device_driver:sched_priority:=50' or 've_sim:nice:=0'; the backend's "
                        "options as a mapping: 'device_driver:backend_options:={port: 10002}' "
                        '(it replaces the params file\'s backend_options whole); repeatable')


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding='utf-8', errors='replace')
    except OSError:
        return ''


def _tail(path: Path, lines: int = 8) -> str:
    return '\n'.join(_read(path).strip().splitlines()[-lines:])


def _start(name: str, argv: list[str], log_dir: Path,
           env_extra: dict[str, str] | None = None) -> _Proc:
    log = log_dir / f'{name}.log'
    handle = log.open('wb')
    env = dict(os.environ, PYTHONUNBUFFERED='1', **(env_extra or {}))
    # A process group of its own (the terminal's Ctrl-C reaches only this command, which
    # stops the nodes in order), in this command's session: under the kernel's autogroup
    # (sched(7)) the scheduler then weighs the graph's threads against each other, by their
    # nice value, SCHED_BATCH and the loop's slice, not each node's session as one whole.
    popen = subprocess.Popen(argv, stdout=handle, stderr=subprocess.STDOUT, env=env,
                             process_group=0)
    return _Proc(name, popen, log, handle)


def stop(procs: list[_Proc], timeout: float = STOP_TIMEOUT) -> dict[str, int]:
    """SIGINT each process in order, escalating to SIGTERM and SIGKILL; return exit codes."""
    codes: dict[str, int] = {}
    for p in procs:
        codes[p.name] = terminate(p.popen, timeout)
        p.handle.close()
    return codes


def remove_stale_shm(when: str) -> None:
    """Remove the Fast DDS shared-memory segments of ended processes from ``/dev/shm`` (a
    killed graph's, this machine's other programs' alike; a running process's stay:
    :mod:`haptic_topology.nodes.dds_shm`), with one line saying how many, ``when``."""
    from haptic_topology.nodes.dds_shm import remove_stale_segments

    removed = remove_stale_segments()
    if removed:
        print(f'removed {len(removed)} Fast DDS shared-memory segments of ended processes '
              f'from /dev/shm ({when})', flush=True)


def run_graph(scenario: str, mode: str, duration: float, bag: Path, params: Path,
              layout: str = 'hosted', backend: str | None = None,
              startup_timeout: float = 30.0, clock: str = 'wall',
              domain_id: int | None = None,
              foxglove: tuple[str, int] | None = None,
              node_prefix: dict[str, list[str]] | None = None,
              overrides: list[str] | None = None, claim: bool = True,
              graph_id: str | None = None, min_subscribers: int = 2,
              loop_cpu_auto: bool = False) -> dict[str, int]:
    """Run the graph once in ``layout`` (a key of :data:`LAYOUTS`), recording to ``bag``;
    return the processes' exit codes.

    ``device_driver`` runs the loop for ``duration`` s from engagement (simulated seconds with
    ``clock='lockstep'``) and then deactivates itself; the run is over when its lifecycle
    state is ``inactive``. ``domain_id``: run in this ROS domain instead of the
    environment's (several graphs at once on one machine). ``foxglove``: ``(host, port)``
    to also start ``foxglove_bridge`` there (first, so a connected app sees the whole run;
    the device starts once it serves).
    ``node_prefix``: process name -> argv put before its command (``--node-prefix``: e.g.
    ``ip netns exec ht_ve`` for ``ve_sim``, which then keeps its pid and gets the signals).
    ``overrides``: ROS ``-p`` arguments after the run's own (:func:`param_overrides`).
    ``claim``: claim the domain for the run (:func:`claim_domain`); False: the caller has.
    ``graph_id``: the nodes' ``graph_id`` (default: a new one, :func:`new_graph_id`), so a
    message of another graph on the domain (another run, a replayed bag) is never applied.
    ``min_subscribers``: the device's state readers it engages with (2: the controller and
    the recorder; a hosted controller counts as one); the bringup also waits for every
    reader of the states it sees, the graph's own among them
    (:meth:`~haptic_topology.bringup.watch.GraphWatcher.unmatched`), so another program's
    cannot stand in for the recorder. ``loop_cpu_auto``: a CPU for the loop process while
    other software keeps the machine busy (:mod:`haptic_topology.bringup.partition`; its changes in
    ``logs/loop_cpu.json``).
    """
    from haptic_topology.bringup.partition import Partitioner
    from haptic_topology.bringup.startup import FAULT_WAIT, device_line, start_driver
    from haptic_topology.bringup.watch import (
        DEVICE_STATUS,
        GraphWatcher,
        loop_readers,
        loop_writers,
    )
    from haptic_topology.errors import WaitTimeout
    if layout not in LAYOUTS:
        raise ConfigError(f'--layout: expected one of {", ".join(LAYOUTS)}, got {layout!r}')
    if bag.exists():
        raise ConfigError(f'--out: {bag} already exists')
    host = 'false' if layout == 'separate' else 'true'

    graph = graph_id or new_graph_id(scenario)
    ros = ['--ros-args', '--params-file', str(params), '-p', f'scenario:={scenario}',
           '-p', f'clock:={clock}', '-p', f'lmi_controller:mode:={mode}',
           '-p', f'recorder:output:={bag}',
           '-p', f'device_driver:min_subscribers:={min_subscribers}',
           '-p', f'device_driver:run_duration:={float(duration)!r}',
           '-p', f'device_driver:host_controller:={host}',
           '-p', f'graph_id:={graph}']
    if layout == 'thread':
        ros += ['-p', 'device_driver:loop_process:=false']
    if clock == 'lockstep':
        ros += ['-p', 'lmi_controller:use_sim_time:=true', '-p', 've_sim:use_sim_time:=true']
    if backend:
        ros += ['-p', f'device_driver:backend:={backend}']
    ros += overrides or []
    domain_lock = (claim_domain(environment_domain() if domain_id is None else domain_id)
                   if claim else None)
    remove_stale_shm('before the run')
    log_dir = Path(tempfile.mkdtemp(prefix='haptic_run_'))
    procs: list[_Proc] = []
    codes: dict[str, int] = {}
    cpu: dict[str, float] = {}
    memory: dict[str, dict[str, Any]] = {}
    partition: Partitioner | None = None
    watched: list[GraphWatcher] = []

    def alive() -> None:
        for p in procs:
            if p.name not in codes and p.popen.poll() is not None:
                raise BringupError(f'{p.name} exited with status {p.popen.returncode}:\n'
                                   f'{_tail(p.log)}')
        # The VE refused hand inputs: the run is not the loop's from then on (and the
        # end of the run would wait in vain for the VE to take them).
        for w in watched:
            if (reason := w.hand_inputs_rejected()) is not None:
                raise BringupError(f'{reason} (bag: {bag})')

    try:
        env = {} if domain_id is None else {'ROS_DOMAIN_ID': str(domain_id)}
        with GraphWatcher('haptic_bringup', alive, domain_id=domain_id,
                          graph_id=graph) as watch:
            watched.append(watch)
            py = [sys.executable, '-m']
            if foxglove is not None:
                host, port = foxglove
                procs.append(_start(FOXGLOVE_NODE, py + [f'haptic_topology.nodes.{FOXGLOVE_NODE}']
                                    + ros + ['-p', f'{FOXGLOVE_NODE}:host:={host}',
                                             '-p', f'{FOXGLOVE_NODE}:port:={int(port)}'],
                                    log_dir, env))
            for name in LAYOUTS[layout]:
                argv = py + [f'haptic_topology.nodes.{name}'] + ros
                if name in ('device_driver', 'composed'):     # the driver waits for us
                    argv += ['-p', 'device_driver:autostart:=false']
                argv = [*(node_prefix or {}).get(name, ()), *argv]   # --node-prefix
                procs.append(_start(name, argv, log_dir, env))
            if foxglove is not None:
                watch.wait(lambda: FOXGLOVE_STATUS in watch.status, startup_timeout,
                           'foxglove_bridge serving')
                print(f'foxglove: {watch.status[FOXGLOVE_STATUS].get("url")} (Foxglove or '
                      'Lichtblick: Open connection, Foxglove WebSocket)', flush=True)
            # As a lifecycle manager (every layout): the loop starts with the device, only
            # once the recorder is matched to the controller's and the VE's publishers
            # (discovery can take seconds) and to the device's own state publisher, so the
            # bag holds the run's first state, and the run's CPU window below is the run.
            watch.wait(watch.recorder_connected, startup_timeout,
                       'recorder connected to the loop topics')
            watch.wait(lambda: watch.recorder_sees(TOPIC_STATE), startup_timeout,
                       'recorder matched to the device state publisher')
            # The driver engages once its state publisher has min_subscribers readers (a
            # hosted controller counting as one): at least those, whoever they are.
            readers = loop_readers(layout)
            hosted_controller = 1 if host == 'true' else 0
            at_least = {(DEVICE_STATUS, TOPIC_STATE): min_subscribers - hosted_controller}
            loop_clock = Clock.parse(clock)
            watch.wait(lambda: watch.writers_matched(readers, loop_clock, at_least),
                       startup_timeout, lambda: 'publishers matched to their readers: '
                       + '; '.join(watch.unmatched(readers, loop_clock, at_least)))
            # ... and the loop's input subscriptions to their writers, on their own side
            writers = loop_writers(layout)
            watch.wait(lambda: watch.readers_matched(writers, loop_clock), startup_timeout,
                       lambda: 'subscriptions matched to their writers: '
                       + '; '.join(watch.unmatched_readers(writers, loop_clock)))
            start_driver(watch, startup_timeout, bag / 'logs')    # there after the stop
            started = watch.wait_lifecycle('device_driver', ('active', 'inactive'),
                                           startup_timeout, poll=0.2)
            # The loop process ends with the run: the driver has waited for it by then.
            drivers = [p.popen.pid for p in procs if p.name == 'device_driver']
            usage = RunUsage({p.name: p.popen.pid for p in procs},
                             drivers[0] if drivers else None, CHILD_MODULE, 'loop_process')
            usage.start()
            if loop_cpu_auto:
                partition = Partitioner(lambda: [p.popen.pid for p in procs], usage.child,
                                        lambda line: print(line, flush=True))
                partition.start()
            limit = startup_timeout + (duration + 10.0 if clock == 'wall'
                                       else max(60.0, 30.0 * duration))
            try:
                print(device_line(watch, FAULT_WAIT), flush=True)
                ended = watch.wait_lifecycle('device_driver', ('inactive',), limit)
            finally:
                usage.stop()
                if partition is not None:
                    partition.stop()
            cpu, memory = usage.cpu(ended - started), usage.rss.growth()
            # The loop has stopped; the recorder must take everything it sent while every
            # writer is still there to resend (checked on the nodes' own counts).
            try:
                watch.wait(lambda: watch.recorder_has_the_run(clock == 'lockstep'),
                           startup_timeout, 'recorder has every message of the run')
            except WaitTimeout as exc:
                raise WaitTimeout(f'{exc}; the nodes\' last reports: '
                                  f'{watch.run_counts()}') from None
            alive()     # a rejection first reported with the counts that ended the wait
    finally:
        # Device first, recorder last (it keeps every message until then).
        codes.update(stop([p for p in reversed(procs) if p.name not in codes]))
        remove_stale_shm('after the run')
        if bag.is_dir():
            shutil.copytree(log_dir, bag / 'logs', dirs_exist_ok=True)
            (bag / 'logs' / 'cpu.json').write_text(json.dumps(cpu) + '\n', encoding='utf-8')
            (bag / 'logs' / 'rss.json').write_text(json.dumps(memory) + '\n',
                                                   encoding='utf-8')
            if partition is not None:
                (bag / 'logs' / 'loop_cpu.json').write_text(
                    json.dumps(partition.report()) + '\n', encoding='utf-8')
        shutil.rmtree(log_dir, ignore_errors=True)
        if domain_lock is not None:
            os.close(domain_lock)
    bad = {n: c for n, c in codes.items() if c != 0}
    if bad:
        logs = bag / 'logs' if bag.is_dir() else log_dir
        raise BringupError(f'nodes exited with errors {bad}; logs in {logs}')
    return codes


def run(args: argparse.Namespace) -> int:
    """The ``run`` subcommand (see module doc)."""
    from haptic_topology.messages.package import require_msgs_package

    require_msgs_package()      # before anything starts: one line if the messages are missing
    from haptic_topology.bringup.startup import preflight_device
    from haptic_topology.config.resolve import check_device_axes, run_backend
    from haptic_topology.device.vendor import require_library
    from haptic_topology.paths import config_dir
    from haptic_topology.sim.scenario import load_scenario

    sc = load_scenario(args.scenario)  # validate before starting anything
    for note in sc.linkage.notes:
        print(note)
    modes: list[str] = args.mode or [sc.mode.label]
    duration = sc.duration if args.duration is None else args.duration
    if not duration > 0.0:
        raise ConfigError(f'--duration: expected a positive number of seconds, got {duration}')
    if args.out is not None and len(modes) > 1:
        raise ConfigError('--out: give it with one --mode only')
    params = args.params or config_dir() / 'haptic_topology.yaml'
    if not params.is_file():
        raise ConfigError(f'--params: {params}: no such file')
    device, options = run_backend(params, args.backend, args.param)
    check_device_axes(sc, device, options)                      # one line, exit 2
    require_library(device)         # a vendor backend's SDK: one line, exit 2
    preflight_device(sc, device, options, args.clock)           # one line, exit 1
    scenario_ref = args.scenario if Path(args.scenario).suffix == '' else str(
        Path(args.scenario).resolve())
    layout = 'composed' if args.composed else args.layout
    loop_cpu = loop_cpu_choice(args.loop_cpu, layout, args.clock, params, args.param)
    fixed = loop_cpu if isinstance(loop_cpu, int) else None
    overrides = loop_cpu_overrides(fixed, layout) + param_overrides(args.param)
    if fixed is not None:   # this command's own threads (its graph watcher's) too
        os.sched_setaffinity(0, set(os.sched_getaffinity(0)) - {fixed})
    domain_lock = claim_domain(environment_domain())    # before any output: one line
    try:
        return _run_modes(args, sc, modes, duration, params, scenario_ref, layout, overrides,
                          loop_cpu == 'auto')
    finally:
        os.close(domain_lock)


def _run_modes(args: argparse.Namespace, sc: Scenario, modes: list[str], duration: float,
               params: Path, scenario_ref: str, layout: str, overrides: list[str],
               loop_cpu_auto: bool) -> int:
    """:func:`run`'s runs, one per mode, on the domain it has claimed."""
    from haptic_topology.bag.analyze import format_loop_health
    from haptic_topology.bringup.analysis import AnalysisJob, analyse_in_child
    from haptic_topology.sim.trace import format_summary

    summaries = []
    loops = []
    for mode in modes:
        bag = args.out or Path('bags') / f'{sc.name}_{mode}_{time.strftime("%Y%m%d-%H%M%S")}'
        print(f'running {sc.name} ({mode}) for {duration:g} s, {layout} layout ...',
              flush=True)
        run_graph(scenario_ref, mode, duration, bag, params, layout, args.backend,
                  args.startup_timeout, args.clock,
                  foxglove=None if args.foxglove is None else (args.foxglove_host,
                                                               args.foxglove),
                  node_prefix=node_prefixes(args.node_prefix, layout),
                  overrides=overrides, claim=False, loop_cpu_auto=loop_cpu_auto)
        # The bag is read in a process of its own: this one has watched the graph.
        result = analyse_in_child(AnalysisJob(bag, sc, mode, layout, args.csv,
                                              not args.no_plot, bag / 'logs' / 'result.json'))
        print(f'bag: {bag}', flush=True)
        summaries.append(result['summary'])
        loops.append((f'{sc.name} {mode}', result['loop']))
    print()
    print(format_summary(summaries))
    print()
    print(format_loop_health(loops))
    return 0
