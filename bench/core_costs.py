"""Compute costs of the core, without ROS: controller cycle and VE update per chain size.

Measured as the calling thread's CPU time around each call (``time.thread_time_ns``: the
time another process holds the core does not count, so the figures are the code's cost on a
shared 2-core machine), after a warm-up; figures are percentiles over many calls. Used by
``bench/run.py`` (``make bench``); runnable alone: ``.venv/bin/python bench/core_costs.py``.
"""

from __future__ import annotations

import argparse
import gc
import json
import time
from typing import Any

import numpy as np

from haptic_topology.control import HapticController
from haptic_topology.control.update_record import decode_update, encode_update
from haptic_topology.device import MaglevModel, user_from_config
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop_process import GC_EVERY
from haptic_topology.device.records import CycleCodec
from haptic_topology.device.runner import Published
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model import serial_chain
from haptic_topology.sim import Scenario, VirtualEnvironment, load_scenario
from haptic_topology.sim.lockstep import (
    build_controller_loop,
    build_device_loop,
    virtual_environment,
)
from haptic_topology.vocabulary import ControlMode, TaskSpace

BUDGET_US = 10_000.0  # one update period of a 100 Hz VE
GOAL_FRACTION = 0.3   # issue 11: a 100-link chain within 30 % of the update period
GRAPH_SCENARIO = 'circle'  # what make bench runs on the node graph
CLOCK = time.thread_time_ns
#: The loop process's cycle is timed on these scenarios (planar: the graph's; spatial: 6-D).
LOOP_STEP_SCENARIOS = {'planar': GRAPH_SCENARIO, 'spatial': 'spatial_arm4'}
CHAIN_SIZES = (3, 10, 30, 100, 150, 200)


def _pct(samples_ns: list[int]) -> dict[str, float]:
    a = np.asarray(samples_ns, dtype=float) / 1000.0
    return {'p50_us': float(np.percentile(a, 50)), 'p99_us': float(np.percentile(a, 99)),
            'max_us': float(a.max()), 'n': int(a.size)}


def controller_step(mode: ControlMode, cycles: int = 20000) -> dict[str, float]:
    """Cost of HapticController.cycle (LMI step of eq. 20 + eq. 14 or eq. 10) on fig8.

    The LMI is re-synced every 10 cycles as in the graph; the re-sync is timed separately.
    """
    sc = load_scenario('fig8')
    dyn = LinkageDynamics(sc.linkage)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step)
    dev = MaglevModel(sc.device, dyn.hand_pose(sc.q0))
    user = user_from_config(sc.user, dyn.task, 'user', dev.pose)
    ctrl = HapticController(dyn.task, mode, sc.gains, sc.device.mass, sc.device.christoffel,
                            sc.lmi_model, sc.vt_coupling)
    ctrl.update(ve.snapshot(0))
    step_ns: list[int] = []
    sync_ns: list[int] = []
    u = np.zeros(3)
    f_h = np.zeros(3)
    for k in range(cycles + 500):
        if k:
            dev.step(u, f_h, sc.dt)
        f_h = user.wrench(k * sc.dt, dev.pose, dev.twist)
        t0 = CLOCK()
        out = ctrl.cycle(k, sc.dt, dev.pose, dev.twist, f_h)
        t1 = CLOCK()
        u = out.wrench
        ve.push_input(k, k * sc.dt, out.vt_wrench)
        if (k + 1) % 10 == 0:
            snap = ve.snapshot(k)
            t2 = CLOCK()
            ctrl.update(snap)
            t3 = CLOCK()
            if k >= 500:
                sync_ns.append(t3 - t2)
        if k >= 500:
            step_ns.append(t1 - t0)
        if k % 2000 == 1999:  # keep the VT in range over long runs: restart the scenario
            ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step)
            dev = MaglevModel(sc.device, dyn.hand_pose(sc.q0))
            ctrl = HapticController(dyn.task, mode, sc.gains, sc.device.mass,
                                    sc.device.christoffel, sc.lmi_model, sc.vt_coupling)
            ctrl.update(ve.snapshot(0))
    result = _pct(step_ns)
    result['resync_p50_us'] = _pct(sync_ns)['p50_us']
    result['resync_p99_us'] = _pct(sync_ns)['p99_us']
    return result


#: Cycles of the paced loop-cycle figure (:func:`loop_step` with ``paced``): 5 s at 1 kHz.
PACED_CYCLES = 5000


def _new_cycle(sc: Scenario) -> HostedCycle:
    """The loop's cycle for ``sc`` as ``simulate`` builds it."""
    return HostedCycle(build_device_loop(sc),
                       build_controller_loop(sc, sc.mode, update_period=sc.update_period))


def _loop_updates(sc: Scenario, total: int, restart: int,
                  commands: np.ndarray) -> tuple[bytes, dict[int, bytes]]:
    """Pass 1 of :func:`loop_step`, untimed: ``total`` cycles of the loop with the VE, as
    ``simulate`` runs them (a new run every ``restart`` cycles); the update the VE offers at
    the start of each run, and by cycle index the update records that reach the loop before
    that cycle, prepared and encoded as the node does. Each cycle's command goes into row k
    of ``commands`` (NaN: no answer)."""
    def record(seq: int) -> bytes:      # the node's part: prepare and encode
        return encode_update(cycle.controller.ctrl.prepare(ve.snapshot(seq=seq)))

    first = b''
    offers: dict[int, bytes] = {}
    waiting: bytes | None = None
    for k in range(total):
        if k % restart == 0:
            ve = virtual_environment(sc)
            cycle = _new_cycle(sc)
            inputs = updates = 0
            first = record(0)
            cycle.offer_update(decode_update(first))
            waiting = None
        if waiting is not None:
            offers[k] = waiting
            cycle.offer_update(decode_update(waiting))
            cycle.apply_updates()
            waiting = None
        t = (k % restart) * sc.dt
        done = cycle.step(t, sc.dt, t)
        commands[k] = np.nan if done.answer is None else done.answer.out.wrench
        hand = done.answer.hand if done.answer is not None else None
        if hand is not None:
            ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
            inputs += 1
            if inputs % sc.update_period == 0:
                updates += 1
                waiting = record(updates)
    return first, offers


def loop_step(scenario: str, cycles: int = 20000, paced: bool = False) -> dict[str, float]:
    """Cost of one cycle of the loop process without ROS: :meth:`HostedCycle.step` (the
    device tick with the simulated maglev and user, the controller's answer: LMI step, eq. 14
    or the scenario's law, and at every ``update_period``-th cycle the LMI re-sync) plus the
    record it writes to the outbound ring (:meth:`CycleCodec.encode`), on ``scenario`` as
    ``simulate`` runs it, with the garbage collector as the loop process runs it.

    Two passes, as the graph splits the work: the VE runs in a process of its own, and the
    loop process receives its updates through a ring. Pass 1 (:func:`_loop_updates`, untimed)
    runs the loop with the VE and keeps the update records the node would put in the ring;
    pass 2 runs the loop alone on new objects and receives those records before the same
    cycles, decoded (:func:`decode_update`) and applied between two cycles as the loop process
    does; that is timed on its own (``update_*``: decode and re-sync), not in the step. Pass 2
    is the same run as pass 1 (its commands are checked equal), so each step is one the loop
    makes, and no VE computation runs in this thread between two steps.

    ``paced``: one cycle per millisecond of the monotonic clock, sleeping until the next
    (as the loop process does, whose core runs other threads or idles meanwhile) instead of
    back to back: the CPU time of a cycle that starts after a sleep, with its code and data
    no longer in the caches."""
    sc = load_scenario(scenario)
    dt = sc.dt
    warm = 500
    restart = int(round(sc.duration / dt))      # keep the run within the scenario's time
    expected = np.empty((cycles + warm, sc.linkage.task.dim))
    commands = np.empty_like(expected)
    first, offers = _loop_updates(sc, cycles + warm, restart, expected)
    step_ns: list[int] = []
    update_ns: list[int] = []
    # The garbage collector as the loop process runs it: frozen after start-up, automatic
    # collection off, a young-generation collection every GC_EVERY cycles (timed with them).
    gc.collect()
    gc.freeze()
    gc.disable()
    start = time.monotonic()
    for k in range(cycles + warm):
        if k % restart == 0:
            cycle = _new_cycle(sc)
            codec = CycleCodec(sc.linkage.task.dim)
            cycle.offer_update(decode_update(first))
            if k:
                start = time.monotonic() - k * 1e-3   # paced: the next cycle in 1 ms
        if paced:
            time.sleep(max(0.0, start + k * 1e-3 - time.monotonic()))
        t = (k % restart) * dt
        waiting = offers.get(k)
        if waiting is not None:
            t0 = CLOCK()
            cycle.offer_update(decode_update(waiting))
            cycle.apply_updates()
            update_ns.append(CLOCK() - t0)
        t0 = CLOCK()
        done = cycle.step(t, dt, t)
        codec.encode(Published(done, k))
        if k % GC_EVERY == GC_EVERY - 1:
            gc.collect(1)
        t1 = CLOCK()
        if k >= warm:
            step_ns.append(t1 - t0)
        commands[k] = np.nan if done.answer is None else done.answer.out.wrench
    gc.enable()
    gc.unfreeze()
    if not np.array_equal(commands, expected, equal_nan=True):
        raise RuntimeError(f'loop_step({scenario!r}): the timed pass answered differently '
                           'from the pass with the VE')
    out = _pct(step_ns)
    upd = _pct(update_ns)
    out.update(update_p50_us=upd['p50_us'], update_p99_us=upd['p99_us'])
    out['task'] = sc.linkage.task.value      # type: ignore[assignment]
    return out


def _coupling(task: TaskSpace) -> tuple[np.ndarray, np.ndarray]:
    """``(K_pc, B_pc)`` of the bench's graph scenario (circle), per task row: its
    translational gains on every translation row, its rotational gain on every rotation row."""
    gains = load_scenario(GRAPH_SCENARIO).gains
    rows = np.r_[[0] * (3 if task is TaskSpace.SPATIAL else 2),
                 [2] * (3 if task is TaskSpace.SPATIAL else 1)]
    return np.asarray(gains.k_pc)[rows], np.asarray(gains.b_pc)[rows]


def ve_update(n: int, task: TaskSpace, updates: int = 60,
              internal_step: float | None = None) -> dict[str, Any]:
    """Cost per 100 Hz VE update for an n-link chain, as ``ve_sim`` runs the bench's graph
    scenario (circle): RK4 at its ``internal_step`` (1 ms) unless one is given, with VT
    coupling (so each snapshot also pays the stable hold of the coordination spring).

    ``snapshot``: D, B, G, J_h, its SVD and the constraint directions (one LmiUpdate).
    ``integrate``: 10 ms of eq. 2 as ve_sim does it (10 hand inputs, each held 1 ms).
    """
    step = load_scenario(GRAPH_SCENARIO).internal_step if internal_step is None else internal_step
    dyn = LinkageDynamics(serial_chain(n, task))
    rng = np.random.default_rng(n)
    ve = VirtualEnvironment(dyn, rng.uniform(-0.5, 0.5, n), np.zeros(n), step,
                            coupling=_coupling(task))
    m = task.dim
    wrench = np.zeros(m)
    wrench[0] = 0.4
    snap_ns: list[int] = []
    step_ns: list[int] = []
    seq = 0
    for i in range(updates + 3):
        t0 = CLOCK()
        for _ in range(10):
            ve.push_input(seq, seq * 1e-3, wrench)
            seq += 1
        t1 = CLOCK()
        ve.snapshot(i)
        t2 = CLOCK()
        if i >= 3:
            step_ns.append(t1 - t0)
            snap_ns.append(t2 - t1)
    total = [a + b for a, b in zip(snap_ns, step_ns, strict=True)]
    s, st, tot = _pct(snap_ns), _pct(step_ns), _pct(total)
    return {'links': n, 'task': task.value, 'internal_step_s': step,
            'snapshot_p50_us': s['p50_us'], 'snapshot_p99_us': s['p99_us'],
            'integrate_10ms_p50_us': st['p50_us'], 'integrate_10ms_p99_us': st['p99_us'],
            'update_total_p50_us': tot['p50_us'], 'update_total_p99_us': tot['p99_us'],
            'fits_100hz': tot['p99_us'] < BUDGET_US,
            'within_goal': tot['p99_us'] <= GOAL_FRACTION * BUDGET_US}


def ve_costs(chain_sizes: tuple[int, ...] = CHAIN_SIZES) -> dict[str, Any]:
    """``ve_update`` for every chain size, planar and spatial, and the largest chains that
    keep 100 Hz and that stay within the goal."""
    out: dict[str, Any] = {}
    rows = []
    for task in (TaskSpace.PLANAR, TaskSpace.SPATIAL):
        best = best_goal = 0
        for n in chain_sizes:
            r = ve_update(n, task, updates=100 if n <= 30 else 40)
            rows.append(r)
            if r['fits_100hz']:
                best = max(best, n)
            if r['within_goal']:
                best_goal = max(best_goal, n)
        out[f'max_links_at_100hz_{task.value}'] = best
        out[f'max_links_within_30pct_{task.value}'] = best_goal
    out['ve_update'] = rows
    # The same at 0.25 ms, the step the bench used before the scenarios went to 1 ms: four
    # times the RK4 stages, for comparison with earlier results.
    out['ve_update_quarter_ms'] = [ve_update(n, task, updates=40 if n <= 30 else 20,
                                             internal_step=2.5e-4)
                                   for task in (TaskSpace.PLANAR, TaskSpace.SPATIAL)
                                   for n in chain_sizes]
    return out


def loop_steps() -> dict[str, Any]:
    """:func:`loop_step` of each of :data:`LOOP_STEP_SCENARIOS`, back to back and paced."""
    out: dict[str, Any] = {}
    for key, scenario in LOOP_STEP_SCENARIOS.items():
        out[f'loop_step_{key}'] = loop_step(scenario)
        out[f'loop_step_paced_{key}'] = loop_step(scenario, PACED_CYCLES, paced=True)
    return out


def run(chain_sizes: tuple[int, ...] = CHAIN_SIZES) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for mode, key in ((ControlMode.PENALTY, 'eq14'), (ControlMode.ACCELERATION_ONLY, 'eq10')):
        r = controller_step(mode)
        out[f'controller_{key}'] = r
    out['controller_step_p50_us'] = out['controller_eq14']['p50_us']
    out['controller_step_p99_us'] = out['controller_eq14']['p99_us']
    out['controller_step_eq10_p99_us'] = out['controller_eq10']['p99_us']
    out.update(loop_steps())
    out.update(ve_costs(chain_sizes))
    return out


def _print_ve_rows(rows: list[dict[str, Any]]) -> None:
    print('  task     links  snapshot p50/p99   integrate 10 ms p50/p99   total p50/p99'
          '        100 Hz  <=30 %')
    for r in rows:
        print(f'  {r["task"]:8s} {r["links"]:5d}  {r["snapshot_p50_us"]:7.1f}/'
              f'{r["snapshot_p99_us"]:7.1f}   {r["integrate_10ms_p50_us"]:9.1f}/'
              f'{r["integrate_10ms_p99_us"]:9.1f}   {r["update_total_p50_us"]:8.1f}/'
              f'{r["update_total_p99_us"]:8.1f}   {"yes" if r["fits_100hz"] else "no ":3s}'
              f'     {"yes" if r["within_goal"] else "no"}')


def print_table(res: dict[str, Any]) -> None:
    for key in ('controller_eq14', 'controller_eq10'):
        if key not in res:
            continue
        if key == 'controller_eq14':
            print('controller cycle (eq. 14 / eq. 10 + LMI step, no ROS), microseconds')
        r = res[key]
        print(f'  {key:16s} p50 {r["p50_us"]:7.1f}  p99 {r["p99_us"]:7.1f}  max '
              f'{r["max_us"]:8.1f}  (LMI re-sync p50 {r["resync_p50_us"]:.1f}, p99 '
              f'{r["resync_p99_us"]:.1f})')
    if 'loop_step_planar' in res:
        print('loop process cycle (HostedCycle.step + ring record, no ROS; LMI re-sync '
              'matrices prepared by the node, the update decoded and applied between '
              'cycles), microseconds')
        for key, scenario in LOOP_STEP_SCENARIOS.items():
            r = res[f'loop_step_{key}']
            print(f'  {key:8s} {scenario:14s} p50 {r["p50_us"]:7.1f}  p99 {r["p99_us"]:7.1f}  '
                  f'max {r["max_us"]:8.1f}  (update between cycles p50 '
                  f'{r["update_p50_us"]:.1f}, p99 {r["update_p99_us"]:.1f})')
            paced = res.get(f'loop_step_paced_{key}')
            if paced is not None:
                print(f'  {key:8s} paced at 1 kHz   p50 {paced["p50_us"]:7.1f}  p99 '
                      f'{paced["p99_us"]:7.1f}  max {paced["max_us"]:8.1f}  (one cycle per ms, '
                      'sleeping between)')
    if 've_update' not in res:
        return
    step_ms = 1e3 * res['ve_update'][0]['internal_step_s']
    print(f've_sim cost per 100 Hz update (budget 10000 us, goal <= 30 %), RK4 at {step_ms:g} ms '
          f'as ve_sim runs {GRAPH_SCENARIO}, with VT coupling, microseconds')
    _print_ve_rows(res['ve_update'])
    print(f'  largest chain at 100 Hz: planar {res["max_links_at_100hz_planar"]}, spatial '
          f'{res["max_links_at_100hz_spatial"]}; within 30 %: planar '
          f'{res["max_links_within_30pct_planar"]}, spatial '
          f'{res["max_links_within_30pct_spatial"]}')
    if res.get('ve_update_quarter_ms'):
        print('the same with RK4 at 0.25 ms (4x the stages; the step of the bench before 1 ms)')
        _print_ve_rows(res['ve_update_quarter_ms'])


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--ve-only', action='store_true', help='only the VE update costs')
    ap.add_argument('--loop-only', action='store_true',
                    help="only the loop process's cycle (planar and spatial)")
    ap.add_argument('--sizes', default=','.join(map(str, CHAIN_SIZES)),
                    help='chain sizes, comma-separated (default %(default)s)')
    a = ap.parse_args()
    sizes = tuple(int(x) for x in a.sizes.split(','))
    results = (ve_costs(sizes) if a.ve_only else
               loop_steps() if a.loop_only else run(sizes))
    print_table(results)
    print(json.dumps({k: v for k, v in results.items() if not isinstance(v, (dict, list))},
                     indent=2))
