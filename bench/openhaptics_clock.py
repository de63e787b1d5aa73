"""The cost of running the loop inside OpenHaptics' servo callback (``backend: openhaptics``),
against the emulator that ``scripts/setup.sh`` builds (``emulators/openhaptics/hd.c``).

* **In this process** (``--ticks`` servo ticks of the emulated scheduler thread, 1 kHz): per
  tick, the time from the tick's start in C (``hdEmuTickNs``: before the device's step and the
  callbacks) to the Python callback's first line (ctypes' entry and taking the GIL from a C
  thread) and to the cycle's start (after ``hdBeginFrame`` and the held force); from there to
  the frame's end with the cycle a backend's ``write`` and ``read`` inside the frame (the
  pyOpenHaptics calls, ``hdEndFrame``), and the same with an empty cycle; and the period
  between callbacks. p50 / p99 / max in microseconds.
* **The loop process** (``--seconds`` s): ``LoopProcess`` with the openhaptics backend, as
  ``device_driver`` runs it (fig8_point, not engaged: the device loop's idle cycles, no
  controller step): the period between cycles and the missed servo ticks, from the loop's own
  statistics (``DeadlinePacer.release``), p50 / p99 / max.
* ``--run``: also ``haptic-topology run fig8_point --params
  config/devices/openhaptics_emulator.yaml --duration 5`` (the whole graph, engaged), and its
  ``summary.json``'s device period and answered figures.

Run alone: ``.venv/bin/python bench/openhaptics_clock.py [--ticks 5000] [--seconds 5] [--run]``
(it sets ``HAPTIC_TOPOLOGY_LIBHD`` to the emulator).
Figures depend on the machine and its load; nothing here is a threshold.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test' / 'support'))

from loop_specs import spec_for  # noqa: E402

from haptic_topology.device.backend import BackendConfig  # noqa: E402
from haptic_topology.device.loop_process import LoopProcess  # noqa: E402
from haptic_topology.device.openhaptics import OpenHapticsBackend  # noqa: E402
from haptic_topology.device.openhaptics_hd import EMULATOR  # noqa: E402
from haptic_topology.sim.lockstep import initial_device_pose  # noqa: E402
from haptic_topology.sim.scenario import load_scenario  # noqa: E402

#: The hand always grasps (no buttons), no grasp fade.
OPTIONS = {'engage_button': None, 'clutch_button': None, 'grasp_ramp_ms': 0.0}


def _q(us: np.ndarray) -> str:
    p50, p99 = np.percentile(us, [50, 99])
    return f'p50 {p50:8.1f}  p99 {p99:8.1f}  max {us.max():8.1f}'


def in_process(ticks: int, with_cycle: bool) -> dict[str, np.ndarray]:
    """Per tick: entry latency, callback duration, period (us)."""
    sc = load_scenario('fig8_point')
    be = OpenHapticsBackend()
    be.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, dict(OPTIONS),
                               sc.source))
    be.activate()
    lib = ctypes.CDLL(str(EMULATOR))
    lib.hdEmuTickNs.restype = ctypes.c_longlong
    entry = np.zeros(ticks)
    python = np.zeros(ticks)
    spent = np.zeros(ticks)
    starts = np.zeros(ticks)
    u = np.array([0.1, 0.0])
    k = 0
    began = 0

    def cycle(now: float) -> None:
        nonlocal began
        began = time.monotonic_ns()
        tick = lib.hdEmuTickNs()
        python[k] = (now * 1e9 - tick) / 1e3        # now: the callback's first line
        entry[k] = (began - tick) / 1e3
        starts[k] = began / 1e3
        if with_cycle:
            be.write(u)
            be.read(1e-3)

    def between(now: float) -> bool:
        nonlocal k
        spent[k] = (time.monotonic_ns() - began) / 1e3     # frame ended, force committed
        k += 1
        return k < ticks

    try:
        be.run_clocked(1e-3, cycle, between, lambda: True)
    finally:
        be.write(np.zeros(2))
        be.deactivate()
    return {'python': python[:k], 'entry': entry[:k], 'cycle': spent[:k],
            'period': np.diff(starts[:k])}


def loop_process(seconds: float) -> dict[str, Any]:
    spec, dim, dof = spec_for('fig8_point', lockstep=False, duration=0.0)
    cfg: BackendConfig = spec['backend_config']
    spec['backend'] = 'openhaptics'
    spec['backend_config'] = replace(cfg, options=dict(OPTIONS))
    proc = LoopProcess(spec, dim, dof)
    try:
        proc.start()
        proc.wait_started()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            proc.wait(0.02)
            proc.drain()
        proc.stop()
        values = proc.device_values()       # the ended child's, sorted here once
    finally:
        proc.close()
    return {k: values.get(k) for k in ('cycles', 'period_p50_ms', 'period_p99_ms',
                                       'period_max_ms', 'loop_missed_deadlines',
                                       'loop_max_consecutive_missed_deadlines', 'rate_hz')}


def graph_run() -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'run'
        subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                        '--params', str(REPO / 'config' / 'devices' /
                                        'openhaptics_emulator.yaml'),
                        '--duration', '5', '--out', str(out)], check=True,
                       capture_output=True)
        s = json.loads((out / 'summary.json').read_text())
    return {k: s.get(k) for k in ('device_rate_hz', 'device_period_p99_ms', 'device_overruns',
                                  'max_consecutive_missed', 'device_answered_fraction',
                                  'bag_period_p50_ms', 'bag_period_p99_ms')}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--ticks', type=int, default=5000)
    ap.add_argument('--seconds', type=float, default=5.0)
    ap.add_argument('--run', action='store_true')
    args = ap.parse_args()
    if not EMULATOR.is_file():
        print(f'{EMULATOR}: not built; run scripts/setup.sh', file=sys.stderr)
        return 2
    os.environ['HAPTIC_TOPOLOGY_LIBHD'] = str(EMULATOR)     # this process, the loop's, run's
    print(f'host: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}')
    for with_cycle in (False, True):
        r = in_process(args.ticks, with_cycle)
        what = 'write + read in the frame' if with_cycle else 'empty frame'
        print(f'in process, {len(r["cycle"])} ticks, {what} (us):')
        print(f'  C tick -> Python callback  {_q(r["python"])}  (ctypes entry, the GIL)')
        print(f'  C tick -> cycle start      {_q(r["entry"])}  (and hdBeginFrame, the held '
              'force)')
        print(f'  cycle start -> frame end   {_q(r["cycle"])}  (the cycle, hdEndFrame)')
        print(f'  period between callbacks   {_q(r["period"])}')
    print(f'loop process, {args.seconds:g} s (idle cycles): {loop_process(args.seconds)}')
    if args.run:
        print(f'run fig8_point, 5 s: {graph_run()}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
