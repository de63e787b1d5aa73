"""Compute costs of the core, without ROS: controller cycle and VE update per chain size.

Measured with ``time.perf_counter_ns`` around each call, after a warm-up; figures are
percentiles over many calls. Used by ``bench/run.py`` (``make bench``); runnable alone:
``.venv/bin/python bench/core_costs.py``.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

from haptic_topology.control import ControlMode, HapticController
from haptic_topology.device import MaglevModel, user_from_config
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model import TaskSpace, serial_chain
from haptic_topology.sim import VirtualEnvironment, load_scenario

BUDGET_US = 10_000.0  # one update period of a 100 Hz VE


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
        t0 = time.perf_counter_ns()
        out = ctrl.cycle(k, sc.dt, dev.pose, dev.twist, f_h)
        t1 = time.perf_counter_ns()
        u = out.wrench
        ve.push_input(k, k * sc.dt, out.vt_wrench)
        if (k + 1) % 10 == 0:
            snap = ve.snapshot(k)
            t2 = time.perf_counter_ns()
            ctrl.update(snap)
            t3 = time.perf_counter_ns()
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


def ve_update(n: int, task: TaskSpace, updates: int = 60) -> dict[str, Any]:
    """Cost per 100 Hz VE update for an n-link chain.

    ``snapshot``: D, B, G, J_h, its SVD and the constraint directions (one LmiUpdate).
    ``integrate``: 10 ms of eq. 2 as ve_sim does it (10 hand inputs, RK4 at 0.25 ms).
    """
    dyn = LinkageDynamics(serial_chain(n, task))
    rng = np.random.default_rng(n)
    ve = VirtualEnvironment(dyn, rng.uniform(-0.5, 0.5, n), np.zeros(n), 2.5e-4)
    m = task.dim
    wrench = np.zeros(m)
    wrench[0] = 0.4
    snap_ns: list[int] = []
    step_ns: list[int] = []
    seq = 0
    for i in range(updates + 3):
        t0 = time.perf_counter_ns()
        for _ in range(10):
            ve.push_input(seq, seq * 1e-3, wrench)
            seq += 1
        t1 = time.perf_counter_ns()
        ve.snapshot(i)
        t2 = time.perf_counter_ns()
        if i >= 3:
            step_ns.append(t1 - t0)
            snap_ns.append(t2 - t1)
    total = [a + b for a, b in zip(snap_ns, step_ns, strict=True)]
    s, st, tot = _pct(snap_ns), _pct(step_ns), _pct(total)
    return {'links': n, 'task': task.value, 'snapshot_p50_us': s['p50_us'],
            'snapshot_p99_us': s['p99_us'], 'integrate_10ms_p50_us': st['p50_us'],
            'integrate_10ms_p99_us': st['p99_us'], 'update_total_p99_us': tot['p99_us'],
            'fits_100hz': tot['p99_us'] < BUDGET_US}


def run(chain_sizes: tuple[int, ...] = (3, 10, 30, 100, 150, 200)) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for mode, key in ((ControlMode.PENALTY, 'eq14'), (ControlMode.ACCELERATION_ONLY, 'eq10')):
        r = controller_step(mode)
        out[f'controller_{key}'] = r
    out['controller_step_p50_us'] = out['controller_eq14']['p50_us']
    out['controller_step_p99_us'] = out['controller_eq14']['p99_us']
    out['controller_step_eq10_p99_us'] = out['controller_eq10']['p99_us']
    rows = []
    for task in (TaskSpace.PLANAR, TaskSpace.SPATIAL):
        best = 0
        for n in chain_sizes:
            r = ve_update(n, task, updates=60 if n <= 30 else 20)
            rows.append(r)
            if r['fits_100hz']:
                best = max(best, n)
        out[f'max_links_at_100hz_{task.value}'] = best
    out['ve_update'] = rows
    return out


def print_table(res: dict[str, Any]) -> None:
    print('controller cycle (eq. 14 / eq. 10 + LMI step, no ROS), microseconds')
    for key in ('controller_eq14', 'controller_eq10'):
        r = res[key]
        print(f'  {key:16s} p50 {r["p50_us"]:7.1f}  p99 {r["p99_us"]:7.1f}  max '
              f'{r["max_us"]:8.1f}  (LMI re-sync p50 {r["resync_p50_us"]:.1f}, p99 '
              f'{r["resync_p99_us"]:.1f})')
    print('ve_sim cost per 100 Hz update (budget 10000 us), microseconds')
    print('  task     links  snapshot p50/p99   integrate 10 ms p50/p99   total p99  100 Hz')
    for r in res['ve_update']:
        print(f'  {r["task"]:8s} {r["links"]:5d}  {r["snapshot_p50_us"]:7.1f}/'
              f'{r["snapshot_p99_us"]:7.1f}   {r["integrate_10ms_p50_us"]:9.1f}/'
              f'{r["integrate_10ms_p99_us"]:9.1f}   {r["update_total_p99_us"]:9.1f}  '
              f'{"yes" if r["fits_100hz"] else "no"}')
    print(f'  largest chain at 100 Hz: planar {res["max_links_at_100hz_planar"]}, spatial '
          f'{res["max_links_at_100hz_spatial"]}')


if __name__ == '__main__':
    results = run()
    print_table(results)
    print(json.dumps({k: v for k, v in results.items() if not isinstance(v, (dict, list))},
                     indent=2))
