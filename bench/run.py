"""``make bench``: how fast the haptic loop really is, and how cost grows with the linkage.

Sections (each a measurement, printed and collected into ``bench/latest.json``; the same run is
appended to ``bench/RESULTS.md`` with the date, machine and versions):

1. The 1 kHz loop on the node graph (``haptic-topology run circle``), ``--loop-duration`` s
   each (default 30), in the default hosted layout (the controller hosted by the device
   driver, the cycle in its loop process), with the cycle in the driver's loop thread
   instead (``--layout thread``) and in the separate-process layout, each without
   SCHED_FIFO and, where the OS permits it, with it, the hosted and thread layouts beside
   a busy Python process pinned to CPU 0, and the hosted layout with the kernel's default
   scheduler slice, with the other nodes not under SCHED_BATCH, and with the VE and the
   recorder under SCHED_IDLE, alone and beside the busy process (:data:`RUN_PARAMS`), and
   with the loop process alone on a CPU (``run --loop-cpu``, :data:`RUN_LOOP_CPU`), alone
   and beside the busy process on the nodes' CPU or on the loop's, and beside the busy
   process without ``run``'s default ``--loop-cpu auto`` (``--loop-cpu off``):
   cycles answered in time, device period
   p50/p99/max, the longest
   run of consecutive missed cycles, round trip p50/p99 (separate layout), CPU per process
   and in total. A bare rclpy ping-pong of two processes with the same messages, QoS and
   executor (``bench/pingpong.py``) runs in the same session, with and without SCHED_FIFO,
   for the separate layout's round-trip ratio. The machine's floor (``bench/floor.c``: a
   compiled loop that only sleeps to the same 1 ms deadlines, with and without SCHED_FIFO)
   runs in the same session, before and after the graph's runs; each loop run is printed
   beside it and as a ratio to it (answered, longest missed run, period p99).
2. Controller compute per cycle without ROS (eq. 14 + LMI step, and eq. 10).
3. ``ve_sim`` cost per 100 Hz update for chains of 3-200 links, planar and spatial.
4. The recorder at the graph's rate and at ``RECORDER_HIGH`` x (over 30,000 msg/s) with a
   synthetic publisher
   (``bench/recorder_load.py``), ``--recorder-duration`` s each (default 60).
5. The live fig8 eq. 14 run against ``simulate`` (largest device-VT distance), and the
   offline ``simulate``'s speed (simulated s per wall s, the fastest of ``OFFLINE_RUNS`` runs).
6. The VE live with a ``CHAIN_LIVE``-link chain, planar and spatial
   (``bench/chain_scenario.py``), hosted, ``--loop-duration`` s each: its update rate
   beside the loop and the recorder.
7. Memory: one hosted run of ``--memory-duration`` s (default 150) and each process's
   resident set growth after its first minute (``run``'s ``rss_growth_kb_s_<process>``).
8. The authenticated device link (``bench/link_auth.py``): the MAC's cost per packet, and the
   ``network`` backend's loop against ``device-server`` without and with a key,
   ``LINK_DURATION`` s each (at most ``--loop-duration``), side by side.
9. The vendor backends on their emulators (``bench/vendor_loops.py``): ``run fig8_point``
   with ``sim_maglev``, ``forcedimension``, ``openhaptics`` and ``haply``, hosted,
   ``--loop-duration`` s each, and each one's figures as a ratio to ``sim_maglev``'s and to
   the floor. ``--vendors-only``: the floor and this section alone.
10. Mesh contacts (``bench/mesh_contacts.py``, run after section 2): the Panda's and the UR5's
    collision meshes against a mesh table and a box (``panda_table``, ``ur5_table``): one
    coal query p50/p99, one ``ContactModel.torques``, and one 100 Hz VE update with and
    without the contacts and with self-collisions. ``--meshes-only``: this section alone.

Then a table of every figure beside its goal (issues 11 and 26). Run: ``make bench`` (about
26 minutes), or ``.venv/bin/python bench/run.py --quick`` (short runs, for trying the script;
its figures are not written to RESULTS.md).
"""

from __future__ import annotations

import argparse
import importlib.metadata as md
import json
import math
import os
import platform
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

import core_costs  # noqa: E402
import floor  # noqa: E402
import link_auth  # noqa: E402
import mesh_contacts  # noqa: E402
import recorder_load  # noqa: E402
import vendor_loops  # noqa: E402
from chain_scenario import write_chain_scenario  # noqa: E402

from haptic_topology.vocabulary import TaskSpace  # noqa: E402

#: Seconds of each ``network`` backend loop run of section 8 (without and with the MAC).
LINK_DURATION = 10.0

#: Links of the chain whose VE runs live beside the loop and the recorder (issue 26, item 5).
CHAIN_LIVE = 100

#: SCHED_FIFO priorities of the benchmark's "fifo" runs: the device driver (in the hosted
#: layout its loop thread) / the separate lmi_controller; the bare ping-pong gets the same.
DEVICE_PRIORITY, CONTROLLER_PRIORITY = 50, 49


def _env() -> dict[str, str]:
    from haptic_topology.nodes.dds_env import isolated_env

    return isolated_env(random.randint(120, 200))


def fifo_permitted() -> bool:
    """Whether this machine lets a process use SCHED_FIFO (tried in a child process)."""
    code = ('import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))')
    return subprocess.run([sys.executable, '-c', code], capture_output=True,
                          check=False).returncode == 0


#: A busy process beside the graph (the "busy" runs): pure Python, pinned to CPU 0.
BUSY = 'import os\nos.sched_setaffinity(0, {0})\nwhile True:\n    pass\n'


def graph_loop(duration: float, layout: str, fifo: bool, scenario: str = 'circle',
               mode: str | None = None, busy: bool = False,
               startup_timeout: float = 30.0,
               nodes: dict[str, dict[str, Any]] | None = None,
               loop_cpu: str | None = None) -> dict[str, Any]:
    """One recorded run of ``scenario`` (a name or a file) on the graph in ``layout``
    (``busy``: beside :data:`BUSY`; ``nodes``: per node, parameters other than the config
    file's; ``loop_cpu``: ``run --loop-cpu``, None: its default); loop figures, the VE's
    update rate, CPU and memory, and when ``run`` pinned the loop (``loop_cpu_changes``)."""
    import yaml

    from haptic_topology.paths import config_dir
    from haptic_topology.sim.trace_io import read_trace

    with tempfile.TemporaryDirectory(prefix='bench_graph_') as tmp:
        bag = Path(tmp) / 'bag'
        params = yaml.safe_load((config_dir() / 'haptic_topology.yaml').read_text())
        if fifo:
            params['device_driver']['ros__parameters']['sched_priority'] = DEVICE_PRIORITY
            params['lmi_controller']['ros__parameters']['sched_priority'] = CONTROLLER_PRIORITY
        for node, values in (nodes or {}).items():
            params[node]['ros__parameters'].update(values)
        params_file = Path(tmp) / 'params.yaml'
        params_file.write_text(yaml.safe_dump(params), encoding='utf-8')
        cmd = [str(Path(sys.executable).with_name('haptic-topology')), 'run', scenario,
               '--duration', str(duration), '--out', str(bag), '--no-plot', '--params',
               str(params_file), '--layout', layout, '--startup-timeout', str(startup_timeout)]
        if mode:
            cmd += ['--mode', mode]
        if loop_cpu is not None:
            cmd += ['--loop-cpu', loop_cpu]
        hog = subprocess.Popen([sys.executable, '-c', BUSY]) if busy else None
        try:
            res = subprocess.run(cmd, env=_env(), capture_output=True, text=True,
                                 timeout=duration + 180 + 3 * startup_timeout, check=False)
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()
        if res.returncode != 0:
            raise RuntimeError(f'{" ".join(cmd)} failed:\n{res.stdout}\n{res.stderr}')
        s = json.loads((bag / 'summary.json').read_text())
        trace = read_trace(bag / 'trace.parquet')
    seq = trace.seq
    consecutive = np.diff(seq) == 1
    periods = np.diff(trace.t)[consecutive] * 1e6
    out = {
        'answered_fraction': s['device_answered_fraction'],
        'answered_or_previous_fraction': s.get('device_answered_or_previous_fraction'),
        'bag_answered_fraction': s['bag_answered_fraction'],
        'max_consecutive_missed': s.get('max_consecutive_missed'),
        'rtt_p50_us': 1e3 * s['device_round_trip_p50_ms'],
        'rtt_p99_us': 1e3 * s['device_round_trip_p99_ms'],
        'rtt_max_us': 1e3 * s.get('device_round_trip_max_ms', float('nan')),
        'period_p50_us': float(np.percentile(periods, 50)),
        'period_p99_us': float(np.percentile(periods, 99)),
        'period_max_us': float(periods.max()),
        'states': int(s['bag_states']),
        've_update_rate_hz': s['ve_update_rate_hz'],
        'max_distance_m': s['max_distance_m'],
        'final_distance_mm': 1e3 * s['final_distance_m'],
        'loop_cpu_changes': s.get('loop_cpu_changes'),
        # how late the loop woke after its deadlines (NaN: the separate layout's timers)
        'wake_late_p50_us': 1e3 * s.get('device_wake_late_p50_ms', float('nan')),
        'wake_late_p99_us': 1e3 * s.get('device_wake_late_p99_ms', float('nan')),
    }
    cpu = {k: v for k, v in s.items() if k.startswith('cpu_')}
    out.update(cpu)
    out['cpu_total'] = float(sum(cpu.values()))
    out.update({k: v for k, v in s.items() if k.startswith('rss_')})
    return out


#: ``simulate`` runs per speed figure: the fastest counts (as ``timeit`` reports), so that a
#: moment of another process's work on these 2 cores does not make the figure.
OFFLINE_RUNS = 3


def offline(scenario: str, mode: str) -> dict[str, float]:
    """``simulate`` of ``scenario``: its largest device-VT distance and its speed (the
    fastest of :data:`OFFLINE_RUNS` runs in this process; ``wall_s_runs``: each run's)."""
    from haptic_topology.sim.lockstep import simulate
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.vocabulary import ControlMode

    sc = load_scenario(scenario)
    walls = []
    for _ in range(OFFLINE_RUNS):
        t0 = time.perf_counter()
        tr = simulate(sc, ControlMode.parse(mode))
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    return {'max_distance_m': tr.summary()['max_distance_m'], 'duration_s': sc.duration,
            'wall_s': wall, 'wall_s_runs': walls, 'realtime_factor': sc.duration / wall}


def _versions() -> dict[str, str]:
    out = {'python': platform.python_version()}
    for name in ('ros-jazzy-rclpy', 'pin', 'numpy', 'mcap', 'rosbags'):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = 'missing'
    try:
        out['haptic_topology_commit'] = subprocess.run(
            ['git', 'rev-parse', '--short', 'HEAD'], cwd=BENCH.parent, capture_output=True,
            text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        out['haptic_topology_commit'] = 'unknown'
    return out


def _machine() -> dict[str, Any]:
    model = ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                model = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return {'cores': os.cpu_count(), 'cpu': model, 'kernel': platform.release()}


#: The loop runs: (key, layout, SCHED_FIFO, beside a busy process).
#: The recorder's high load: the graph's topics at 14x their rates, 30,842 msg/s nominal (the
#: goal's 30,000 msg/s; 10x was ~31,000 msg/s while hand inputs went at 1 kHz, 22,029 since
#: they go in batches).
RECORDER_HIGH = 14.0
RECORDER_HIGH_KEY = f'recorder_{RECORDER_HIGH:g}x'
LOOP_RUNS = (('hosted', 'hosted', False, False), ('separate', 'separate', False, False),
             ('thread', 'thread', False, False), ('hosted_busy', 'hosted', False, True),
             ('thread_busy', 'thread', False, True), ('hosted_fifo', 'hosted', True, False),
             ('separate_fifo', 'separate', True, False),
             ('thread_fifo', 'thread', True, False), ('hosted_slice0', 'hosted', False, False),
             ('hosted_nobatch', 'hosted', False, False), ('hosted_idle', 'hosted', False, False),
             ('hosted_busy_idle', 'hosted', False, True),
             ('hosted_partition', 'hosted', False, False),
             ('hosted_busy_partition', 'hosted', False, True),
             ('hosted_busy_partition_shared', 'hosted', False, True),
             ('hosted_busy_off', 'hosted', False, True),
             ('hosted_slack', 'hosted', False, False), ('hosted_mlock', 'hosted', False, False))
#: Node parameters of a run of :data:`LOOP_RUNS` other than the config file's: the loop
#: process with the kernel's default scheduler slice instead of ``sched_slice_us`` 100; the
#: other nodes under normal scheduling instead of SCHED_BATCH (``sched_policy`` other); the
#: VE and the recorder under SCHED_IDLE (``sched_policy`` idle; the driver keeps SCHED_BATCH);
#: the two real-time options that need no privilege and are off by default: a timer slack of
#: 1 us instead of the kernel's 50 us (``timer_slack_ns``), and the loop's memory locked
#: (``lock_memory``; where the OS refuses it the node warns and the run is without it).
_IDLE = {node: {'sched_policy': 'idle'} for node in ('ve_sim', 'recorder')}
RUN_PARAMS: dict[str, dict[str, dict[str, Any]]] = {
    'hosted_slice0': {'device_driver': {'sched_slice_us': 0.0}},
    'hosted_nobatch': {node: {'sched_policy': 'other'}
                       for node in ('device_driver', 've_sim', 'recorder')},
    'hosted_idle': _IDLE,
    'hosted_busy_idle': _IDLE,
    'hosted_slack': {'device_driver': {'timer_slack_ns': 1000}},
    'hosted_mlock': {'device_driver': {'lock_memory': True}},
}


#: ``run --loop-cpu`` of a run of :data:`LOOP_RUNS` (the others: ``run``'s default, ``auto``,
#: which pins as ``_partition`` while other software keeps the machine busy): the loop process
#: alone on the last CPU and every other thread of the graph on the others, the busy process
#: (pinned to CPU 0) among them; ``_shared``: the loop on CPU 0, beside the busy process, the
#: nodes on the others (those three run where there are CPU 0 and one more); ``_off``: never
#: pinned.
_CPUS = sorted(os.sched_getaffinity(0))
RUN_LOOP_CPU: dict[str, str] = {'hosted_busy_off': 'off', **(
    {'hosted_partition': str(_CPUS[-1]), 'hosted_busy_partition': str(_CPUS[-1]),
     'hosted_busy_partition_shared': '0'} if len(_CPUS) >= 2 and _CPUS[0] == 0 else {})}


def _pingpong(duration: float, fifo: bool) -> dict[str, Any]:
    # In a child process: its SCHED_FIFO priority must not stay on this process, or every
    # graph process started after it would inherit it (measured: 74 % answered instead of
    # 97 %, since ve_sim and the recorder then compete with the pair on equal terms).
    prio = ['--sched-priority', str(DEVICE_PRIORITY), '--echo-sched-priority',
            str(CONTROLLER_PRIORITY)] if fifo else []
    out = subprocess.run([sys.executable, str(BENCH / 'pingpong.py'), '--duration',
                          str(duration), *prio], env=_env(), capture_output=True, text=True,
                         timeout=duration + 60, check=True).stdout
    return dict(json.loads(out[out.index('{'):]))


def _floors(res: dict[str, Any], duration: float, fifo: bool, key: str) -> None:
    """The machine's floor (``floor.py``), without and (where permitted) with SCHED_FIFO, as
    ``res[key]`` and ``res[key + '_fifo']``."""
    for suffix, prio in (('', 0), ('_fifo', DEVICE_PRIORITY if fifo else 0)):
        if suffix and not prio:
            continue
        print(f'== machine floor{" (SCHED_FIFO)" if prio else ""}, {duration:g} s ...',
              flush=True)
        res[key + suffix] = floor.run(duration, prio)


#: The floor each loop run is read against: with SCHED_FIFO for the runs that use it.
def _floor_of(key: str) -> str:
    return 'floor_fifo' if key.endswith('_fifo') else 'floor'


def run(loop_duration: float, recorder_duration: float,
        memory_duration: float = 150.0) -> dict[str, Any]:
    res: dict[str, Any] = {'date': time.strftime('%Y-%m-%d %H:%M:%S %Z'),
                           'machine': _machine(), 'versions': _versions()}
    fifo = fifo_permitted()
    res['fifo_permitted'] = fifo
    print('== controller and VE compute (no ROS) ...', flush=True)
    res['core'] = core_costs.run()
    print('== mesh contacts: coal queries and VE updates with robot meshes (no ROS) ...',
          flush=True)
    res['meshes'] = mesh_contacts.section()
    _floors(res, loop_duration, fifo, 'floor')
    for key, layout, with_fifo, busy in LOOP_RUNS:
        if with_fifo and not fifo:
            print(f'== graph, {key}: skipped, SCHED_FIFO not permitted here', flush=True)
            continue
        if key.endswith(('_partition', '_partition_shared')) and key not in RUN_LOOP_CPU:
            print(f'== graph, {key}: skipped, needs CPU 0 and one more', flush=True)
            continue
        if layout == 'separate':
            base = 'baseline_fifo' if with_fifo else 'baseline'
            print(f'== bare ping-pong{" (SCHED_FIFO)" if with_fifo else ""}, '
                  f'{loop_duration:g} s ...', flush=True)
            res[base] = _pingpong(loop_duration, with_fifo)
        print(f'== graph, {key}, {loop_duration:g} s ...', flush=True)
        try:
            res[key] = graph_loop(loop_duration, layout, with_fifo, busy=busy,
                                  nodes=RUN_PARAMS.get(key), loop_cpu=RUN_LOOP_CPU.get(key))
        except RuntimeError as exc:
            if key in ('hosted', 'separate'):
                raise
            # A run whose settings starve a node on a slow machine fails to start or to
            # finish (SCHED_FIFO loops starving the normal-priority VE and recorder; the VE
            # under SCHED_IDLE beside a busy process never matching its readers): that is
            # its result, in the tables, and the other runs still count.
            res[f'{key}_failed'] = str(exc).strip().splitlines()[-1][:300]
            print(f'== graph, {key}: the run failed: {res[f"{key}_failed"]}', flush=True)
    _floors(res, loop_duration, fifo, 'floor_end')
    print('== live fig8 eq. 14 (hosted, wall clock) against simulate ...', flush=True)
    off = offline('fig8', 'penalty')
    live = graph_loop(off['duration_s'], 'hosted', False, 'fig8', 'penalty')
    res['fig8'] = {'live_max_distance_m': live['max_distance_m'],
                   'offline_max_distance_m': off['max_distance_m'],
                   'ratio': live['max_distance_m'] / off['max_distance_m']}
    res['simulate_speed'] = {name: offline(name, 'penalty')
                             for name in ('fig8', 'fig6')}
    with tempfile.TemporaryDirectory(prefix='bench_chain_') as tmp:
        for task in (TaskSpace.PLANAR, TaskSpace.SPATIAL):
            print(f'== graph, hosted, {CHAIN_LIVE}-link {task.value} chain, '
                  f'{loop_duration:g} s ...', flush=True)
            path = write_chain_scenario(CHAIN_LIVE, task, Path(tmp), loop_duration)
            try:
                res[f'chain_live_{task.value}'] = graph_loop(
                    loop_duration, 'hosted', False, str(path), startup_timeout=120.0)
            except RuntimeError as exc:     # reported in the goals table as not met
                res[f'chain_live_{task.value}_failed'] = \
                    str(exc).strip().splitlines()[-1][:300]
                print(f'== the run failed: {res[f"chain_live_{task.value}_failed"]}',
                      flush=True)
    print(f'== memory: graph, hosted, {memory_duration:g} s ...', flush=True)
    res['memory'] = graph_loop(memory_duration, 'hosted', False)
    res['memory_duration_s'] = memory_duration
    for factor in (1.0, RECORDER_HIGH):
        print(f'== recorder at {factor:g}x the graph rate, {recorder_duration:g} s ...',
              flush=True)
        res[f'recorder_{factor:g}x'] = recorder_load.run(recorder_duration, factor)
    duration = min(LINK_DURATION, loop_duration)
    print(f'== device link: MAC per packet; network backend loop without and with a key, '
          f'{duration:g} s each ...', flush=True)
    res['link_auth'] = link_auth.run(duration)
    res['vendors'] = vendor_loops.run(loop_duration, graph_loop)
    return res


def run_vendors(loop_duration: float) -> dict[str, Any]:
    """``--vendors-only``: the machine's floor, then section 9 (module doc)."""
    res: dict[str, Any] = {'date': time.strftime('%Y-%m-%d %H:%M:%S %Z'),
                           'machine': _machine(), 'versions': _versions()}
    _floors(res, loop_duration, False, 'floor')
    res['vendors'] = vendor_loops.run(loop_duration, graph_loop)
    _floors(res, loop_duration, False, 'floor_end')
    return res


def headline(res: dict[str, Any]) -> dict[str, Any]:
    """The figures of issue 11's goals table, flat (bench/latest.json 'headline')."""
    core = res['core']
    h, sep = res['hosted'], res['separate']
    out: dict[str, Any] = {
        'answered_fraction_hosted': h['answered_fraction'],
        'max_consecutive_missed_hosted': h['max_consecutive_missed'],
        'period_p99_us_hosted': h['period_p99_us'],
        'cpu_total_hosted': h['cpu_total'],
        'answered_fraction_separate': sep['answered_fraction'],
        'max_consecutive_missed_separate': sep['max_consecutive_missed'],
        'period_p99_us_separate': sep['period_p99_us'],
        'cpu_total_separate': sep['cpu_total'],
        'rtt_p99_us_separate': sep['rtt_p99_us'],
        'baseline_rtt_p99_us': res['baseline']['rtt_p99_us'],
        'rtt_p99_ratio_separate_to_baseline':
            sep['rtt_p99_us'] / res['baseline']['rtt_p99_us'],
        'rss_growth_kb_s': {k.removeprefix('rss_growth_kb_s_'): v
                            for k, v in res['memory'].items()
                            if k.startswith('rss_growth_kb_s_')},
        'rss_mb': {k.removeprefix('rss_mb_'): v for k, v in res['memory'].items()
                   if k.startswith('rss_mb_')},
        'memory_run_s': res['memory_duration_s'],
        **{f'{key}_chain_{task}': res.get(f'chain_live_{task}', {}).get(field, float('nan'))
           for task in ('planar', 'spatial')
           for key, field in (('ve_rate_hz', 've_update_rate_hz'),
                              ('answered_fraction', 'answered_fraction'))},
        'controller_step_p50_us': core['controller_step_p50_us'],
        'controller_step_p99_us': core['controller_step_p99_us'],
        'controller_step_eq10_p99_us': core['controller_step_eq10_p99_us'],
        'loop_step_p99_us_planar': core['loop_step_planar']['p99_us'],
        'loop_step_p99_us_spatial': core['loop_step_spatial']['p99_us'],
        **{f'loop_step_paced_{q}_us_{task}': core[f'loop_step_paced_{task}'][f'{q}_us']
           for q in ('p50', 'p99') for task in ('planar', 'spatial')
           if f'loop_step_paced_{task}' in core},
        've_update_p99_us_3_links': next(
            r['update_total_p99_us'] for r in core['ve_update']
            if r['links'] == 3 and r['task'] == 'planar'),
        'max_links_at_100hz_planar': core['max_links_at_100hz_planar'],
        'max_links_at_100hz_spatial': core['max_links_at_100hz_spatial'],
        'fig8_live_to_offline_max_distance': res['fig8']['ratio'],
        'simulate_realtime_factor_fig8': res['simulate_speed']['fig8']['realtime_factor'],
        've_update_p99_us_3_links_spatial': next(
            r['update_total_p99_us'] for r in core['ve_update']
            if r['links'] == 3 and r['task'] == 'spatial'),
        'max_links_within_30pct_planar': core['max_links_within_30pct_planar'],
        'max_links_within_30pct_spatial': core['max_links_within_30pct_spatial'],
    }
    for key in ('floor', 'floor_fifo', 'floor_end', 'floor_end_fifo'):
        if key in res:
            for fig in ('answered_fraction', 'max_consecutive_missed', 'period_p99_us',
                        'wake_late_p99_us'):
                out[f'{fig}_{key}'] = res[key][fig]
    if 'floor' in res:
        out['answered_ratio_hosted_to_floor'] = (h['answered_fraction']
                                                 / res['floor']['answered_fraction'])
        out['period_p99_ratio_hosted_to_floor'] = (h['period_p99_us']
                                                   / res['floor']['period_p99_us'])
    for key in (k for k, _, _, _ in LOOP_RUNS if k not in ('hosted', 'separate')):
        if f'{key}_failed' in res:
            out[f'failed_{key}'] = res[f'{key}_failed']
        if key in res:
            out[f'answered_fraction_{key}'] = res[key]['answered_fraction']
            out[f'max_consecutive_missed_{key}'] = res[key]['max_consecutive_missed']
            out[f'period_p99_us_{key}'] = res[key]['period_p99_us']
            out[f'cpu_total_{key}'] = res[key]['cpu_total']
    high = res.get(RECORDER_HIGH_KEY, {})
    out['recorder_high_published_msgs_per_s'] = high.get('published_msgs_per_s', 0.0)
    out['recorder_high_msgs_per_s'] = high.get('recorded_msgs_per_s', 0.0)
    out['recorder_high_lost'] = high.get('lost')
    out['recorder_high_cpu'] = high.get('cpu_fraction')
    lossless = [res[k]['recorded_msgs_per_s'] for k in ('recorder_1x', RECORDER_HIGH_KEY)
                if k in res and res[k].get('lossless')]
    out['recorder_lossless_msgs_per_s'] = max(lossless) if lossless else 0.0
    return out


def _answered_row(h: dict[str, Any], key: str, label: str, least: float) -> tuple[Any, ...]:
    """A goals row: cycles answered in time and the longest missed run of run ``key``."""
    if f'answered_fraction_{key}' not in h:
        got = 'the run failed' if f'failed_{key}' in h else 'not run'
        return (f'cycles answered in time ({label})', got, f'>= {100 * least:g} %', False)
    frac, miss = h[f'answered_fraction_{key}'], h[f'max_consecutive_missed_{key}']
    return (f'cycles answered in time ({label})',
            f'{100 * frac:.2f} %, max {miss:.0f} in a row missed',
            f'>= {100 * least:g} %, never 20 in a row', frac >= least and miss < 20)


def _memory_row(h: dict[str, Any]) -> tuple[str, str, str, bool]:
    growth = h['rss_growth_kb_s']
    worst = max(growth, key=lambda k: growth[k]) if growth else None
    got = ('no fit' if worst is None else
           ', '.join(f'{k} {v:.1f}' for k, v in growth.items()) + ' kB/s')
    return (f'resident set growth after the first minute ({h["memory_run_s"]:g} s run)', got,
            '< 1 kB/s, every process', worst is not None and growth[worst] < 1.0)


def goals(head: dict[str, Any]) -> str:
    """Every figure beside its goal (the loop's goals of issue 26 and the others of issue 11;
    no SCHED_FIFO but where a row says so, 30 s runs)."""
    h = head
    rows = [
        _answered_row(h, 'hosted_busy', 'loop process, beside a busy process (the default, '
                      'run --loop-cpu auto)', 0.995),
        _answered_row(h, 'hosted_busy_off', 'loop process, beside a busy process, never '
                      'pinned (run --loop-cpu off)', 0.995),
        _answered_row(h, 'hosted_fifo', 'loop process, SCHED_FIFO', 0.999),
        _answered_row(h, 'hosted_slice0', "loop process, the kernel's default slice", 0.999),
        _answered_row(h, 'hosted_slack', 'loop process, timer slack 1 us', 0.999),
        _answered_row(h, 'hosted_mlock', 'loop process, memory locked', 0.999),
        _answered_row(h, 'hosted_nobatch', 'loop process, the other nodes not SCHED_BATCH',
                      0.999),
        _answered_row(h, 'hosted_idle', 'loop process, VE and recorder SCHED_IDLE', 0.999),
        _answered_row(h, 'hosted_busy_idle',
                      'loop process, VE and recorder SCHED_IDLE, beside a busy process', 0.995),
        _answered_row(h, 'hosted_partition', 'loop process alone on a CPU (run --loop-cpu)',
                      0.999),
        _answered_row(h, 'hosted_busy_partition', 'loop process alone on a CPU, beside a busy '
                      "process on the nodes' CPU", 0.995),
        _answered_row(h, 'hosted_busy_partition_shared', 'loop process on a CPU without the '
                      "nodes, beside a busy process on the loop's CPU", 0.995),
        _answered_row(h, 'thread', 'loop thread', 0.999),
        _answered_row(h, 'thread_busy', 'loop thread, beside a busy process', 0.995),
        ('cycles answered in time (loop process, the default)',
         f'{100 * h["answered_fraction_hosted"]:.2f} %, '
         f'max {h["max_consecutive_missed_hosted"]:.0f} in a row missed',
         '>= 99.9 %, never 20 in a row', h['answered_fraction_hosted'] >= 0.999
         and h['max_consecutive_missed_hosted'] < 20),
        ('device period p99 (loop process)', f'{h["period_p99_us_hosted"] / 1e3:.3f} ms',
         '<= 1.1 ms', h['period_p99_us_hosted'] <= 1100.0),
        ('CPU of the whole graph with recorder (loop process)',
         f'{h["cpu_total_hosted"]:.2f} core', '<= 0.6 core', h['cpu_total_hosted'] <= 0.6),
        ('separate layout round trip p99 / bare ping-pong',
         f'{h["rtt_p99_ratio_separate_to_baseline"]:.2f}x ({h["rtt_p99_us_separate"]:.0f} / '
         f'{h["baseline_rtt_p99_us"]:.0f} us)', '<= 1.3x',
         h['rtt_p99_ratio_separate_to_baseline'] <= 1.3),
        ('VE update p99, 3 links / largest chain within 30 % of 10 ms',
         f'{h["ve_update_p99_us_3_links"] / 1e3:.2f} ms planar, '
         f'{h["ve_update_p99_us_3_links_spatial"] / 1e3:.2f} ms spatial / planar '
         f'{h["max_links_within_30pct_planar"]}, spatial {h["max_links_within_30pct_spatial"]}'
         f' links (at 100 Hz: {h["max_links_at_100hz_planar"]}, '
         f'{h["max_links_at_100hz_spatial"]})',
         '<= 0.3 ms / 100 links within 30 % of 10 ms',
         max(h['ve_update_p99_us_3_links'], h['ve_update_p99_us_3_links_spatial']) <= 300.0
         and min(h['max_links_within_30pct_planar'], h['max_links_within_30pct_spatial']) >= 100),
        (f'VE live, {CHAIN_LIVE}-link chain (loop and recorder running), planar / spatial',
         f'{h["ve_rate_hz_chain_planar"]:.1f} / {h["ve_rate_hz_chain_spatial"]:.1f} Hz (cycles '
         f'answered {100 * h["answered_fraction_chain_planar"]:.1f} / '
         f'{100 * h["answered_fraction_chain_spatial"]:.1f} %)', '>= 95 Hz',
         all(h[f've_rate_hz_chain_{t}'] >= 95.0 for t in ('planar', 'spatial'))),
        _memory_row(h),
        ('controller compute p99', f'{h["controller_step_p99_us"]:.0f} us', '<= 30 us',
         h['controller_step_p99_us'] <= 30.0),
        ('loop process cycle p99 (no ROS), planar / spatial',
         f'{h["loop_step_p99_us_planar"]:.0f} / {h["loop_step_p99_us_spatial"]:.0f} us',
         '<= 50 / 100 us', h['loop_step_p99_us_planar'] <= 50.0
         and h['loop_step_p99_us_spatial'] <= 100.0),
        (f'recorder at {RECORDER_HIGH:g}x', f'{h["recorder_high_msgs_per_s"]:.0f} of '
         f'{h["recorder_high_published_msgs_per_s"]:.0f} msg/s, lost '
         f'{h["recorder_high_lost"]}, {h["recorder_high_cpu"] or float("nan"):.2f} core',
         '30,000 msg/s lossless within 0.5 core',
         h['recorder_lossless_msgs_per_s'] >= 30000 and (h['recorder_high_cpu'] or 9) <= 0.5),
        ('live fig8 eq. 14 max distance / offline',
         f'{h["fig8_live_to_offline_max_distance"]:.3f}', 'within 10 % (0.9-1.1)',
         abs(h['fig8_live_to_offline_max_distance'] - 1.0) <= 0.1),
        ('offline simulate speed (fig8)', f'{h["simulate_realtime_factor_fig8"]:.1f}x real time',
         '>= 20x real time', h['simulate_realtime_factor_fig8'] >= 20.0),
    ]
    w = max(len(r[0]) for r in rows)
    lines = [f'{"figure":{w}s}  measured | goal | met']
    lines += [f'{name:{w}s}  {got} | {goal} | {"yes" if ok else "NO"}'
              for name, got, goal, ok in rows]
    return '\n'.join(lines)


def table(res: dict[str, Any]) -> str:
    lines = ['loop (1 kHz)          answered  ans.|prev  max miss  rtt p50/p99/max [us]      '
             'period p50/p99/max [us]   wake late p50/p99 [us]  CPU']
    for key in ('floor', 'floor_fifo', 'baseline', 'baseline_fifo',
                *(k for k, _, _, _ in LOOP_RUNS), 'floor_end', 'floor_end_fifo'):
        if key not in res:
            continue
        r = res[key]
        cpu = ', '.join(f'{k[4:]} {v:.2f}' for k, v in r.items() if k.startswith('cpu_'))
        prev = r.get('answered_or_previous_fraction')
        miss = r.get('max_consecutive_missed')
        lines.append(
            f'{key:20s}  {100 * r["answered_fraction"]:7.2f}%  '
            f'{(100 * prev if prev is not None else float("nan")):8.2f}%  '
            f'{(miss if miss is not None else float("nan")):8.0f}  '
            f'{r["rtt_p50_us"]:6.0f}/{r["rtt_p99_us"]:6.0f}/{r["rtt_max_us"]:7.0f}   '
            f'{r["period_p50_us"]:6.0f}/{r["period_p99_us"]:6.0f}/{r["period_max_us"]:7.0f}   '
            f'{r.get("wake_late_p50_us", math.nan):6.0f}/'
            f'{r.get("wake_late_p99_us", math.nan):6.0f}           {cpu}')
    lines.append('loop / machine floor  answered  missed in a row  period p99   (ratio of the '
                 'run to the floor measured before the runs: floor, or floor_fifo)')
    for key in (k for k, _, _, _ in LOOP_RUNS):
        fl = res.get(_floor_of(key))
        if key not in res or fl is None:
            continue
        r = res[key]
        miss = r.get('max_consecutive_missed') or math.nan
        lines.append(f'{key:20s}  {r["answered_fraction"] / fl["answered_fraction"]:8.4f}  '
                     f'{miss / max(fl["max_consecutive_missed"], 1):15.2f}  '
                     f'{r["period_p99_us"] / fl["period_p99_us"]:10.3f}')
    for key in (k for k, _, _, _ in LOOP_RUNS):
        changes = res.get(key, {}).get('loop_cpu_changes')
        if changes:     # run --loop-cpu auto pinned (or unpinned) the loop during the run
            lines.append(f'{key:20s}  loop CPU (auto): ' + '; '.join(
                f'at {c["t_s"]:g} s ' + ('unpinned' if c['loop_cpu'] is None
                                         else f'CPU {c["loop_cpu"]}')
                + f' ({c["other_load_cores"]:.2f} cores of other load)' for c in changes))
    for key in (k for k, _, _, _ in LOOP_RUNS):
        if f'{key}_failed' in res:
            lines.append(f'{key:20s}  failed: {res[f"{key}_failed"][:150]}')
    for key in ('recorder_1x', RECORDER_HIGH_KEY):
        if key in res:
            r = res[key]
            lines.append(f'{key}: {r["recorded_msgs_per_s"]:.0f} msg/s recorded of '
                         f'{r["published_msgs_per_s"]:.0f} published, lost {r["lost"]}, '
                         f'CPU {r["cpu_fraction"]:.2f}, {r["bytes_per_s"] / 1e3:.0f} kB/s')
    f8 = res['fig8']
    lines.append(f'fig8 eq. 14 max distance: live {1e3 * f8["live_max_distance_m"]:.3f} mm, '
                 f'offline {1e3 * f8["offline_max_distance_m"]:.3f} mm')
    for name, r in res['simulate_speed'].items():
        lines.append(f'simulate {name}: {r["duration_s"]:g} s simulated in {r["wall_s"]:.3f} '
                     f's, fastest of {OFFLINE_RUNS} ({r["realtime_factor"]:.1f}x real time)')
    if 'link_auth' in res:
        lines.extend(link_auth.table(res['link_auth']))
    if 'vendors' in res:
        lines.append(vendor_loops.table(res['vendors'], res.get('floor')))
    if 'meshes' in res:
        lines.extend(mesh_contacts.table(res['meshes']))
    return '\n'.join(lines)


def floor_line(res: dict[str, Any]) -> str:
    """The floor before and after the runs, one line each."""
    return '\n'.join(
        f'machine floor ({key}): {100 * res[key]["answered_fraction"]:.2f} % answered, '
        f'{res[key]["max_consecutive_missed"]:.0f} missed in a row, period p99 '
        f'{res[key]["period_p99_us"]:.0f} us' for key in ('floor', 'floor_end') if key in res)


def _append_results(res: dict[str, Any], how: str, text: str) -> None:
    """Append one partial run's ``text`` to RESULTS.md under its date, machine, the options
    it ran with (``how``) and the versions."""
    with (BENCH / 'RESULTS.md').open('a', encoding='utf-8') as f:
        f.write(f'\n## {res["date"]} - {res["machine"]["cores"]} cores, '
                f'{res["machine"]["cpu"]} ({how})\n\nversions: {json.dumps(res["versions"])}\n\n'
                f'```\n{text}\n```\n')
    print(f'appended {BENCH / "RESULTS.md"}')


def main() -> None:
    ap = argparse.ArgumentParser(description='haptic_topology benchmarks (make bench)')
    ap.add_argument('--loop-duration', type=float, default=30.0)
    ap.add_argument('--recorder-duration', type=float, default=60.0)
    ap.add_argument('--memory-duration', type=float, default=150.0,
                    help='s of the hosted run whose resident sets are fitted after its first '
                    'minute (shorter: after its first half)')
    ap.add_argument('--quick', action='store_true',
                    help='5 s runs to try the script; nothing is written to RESULTS.md')
    ap.add_argument('--meshes-only', action='store_true',
                    help='the mesh section only (section 10: coal queries and VE updates with '
                    'the robots\' meshes, with and without self-collisions; no ROS)')
    ap.add_argument('--vendors-only', action='store_true',
                    help='the machine floor and the vendor backends on their emulators only '
                    '(section 9)')
    a = ap.parse_args()
    if a.quick:
        a.loop_duration, a.recorder_duration, a.memory_duration = 5.0, 5.0, 10.0
    if a.meshes_only:
        res = {'date': time.strftime('%Y-%m-%d %H:%M:%S %Z'), 'machine': _machine(),
               'versions': _versions(), 'meshes': mesh_contacts.section()}
        text = '\n'.join(mesh_contacts.table(res['meshes']))
        print(text)
        _append_results(res, '--meshes-only', text)
        return
    if a.vendors_only:
        res = run_vendors(a.loop_duration)
        text = (vendor_loops.table(res['vendors'], res['floor']) + '\n'
                + floor_line(res))
        print(text)
        _append_results(res, f'--vendors-only, --loop-duration {a.loop_duration:g}', text)
        return
    res = run(a.loop_duration, a.recorder_duration, a.memory_duration)
    head = headline(res)
    res['headline'] = head
    print()
    core_costs.print_table(res['core'])
    print(table(res))
    print()
    print(goals(head))
    print(json.dumps(head, indent=2))
    if a.quick:
        return
    (BENCH / 'latest.json').write_text(json.dumps(res, indent=2) + '\n', encoding='utf-8')
    with (BENCH / 'RESULTS.md').open('a', encoding='utf-8') as f:
        f.write(f'\n## {res["date"]} - {res["machine"]["cores"]} cores, '
                f'{res["machine"]["cpu"]}\n\nversions: {json.dumps(res["versions"])}\n\n```\n')
        f.write(table(res) + '\n\n' + goals(head) + '\n```\n\n```json\n'
                + json.dumps(head, indent=2) + '\n```\n')
    print(f'wrote {BENCH / "latest.json"}, appended {BENCH / "RESULTS.md"}')


if __name__ == '__main__':
    main()
