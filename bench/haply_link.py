"""The ``haply`` backend's exchange with the Haply Inverse Service, measured against the
emulator (``python -m haptic_topology.remote.haply_emulator``) on loopback.

* per message, in this process: formatting and framing one force command (``repr`` floats,
  masked frame), decoding one state message (``json.loads`` and the checks), us per call
  (fastest of ``REPEATS`` runs of ``CALLS`` calls);
* the backend in a 1 kHz loop (absolute deadlines, :class:`DeadlinePacer`) for ``duration`` s:
  the exchange's work per cycle (``write`` + ``read``, us) p50/p99/max, the cycle period
  p50/p99/max/std (ms), missed deadlines, the backend's counters (states taken, messages
  skipped unread, commands throttled by ``max_in_flight``, faulted readings);
* the same loop with the ``websockets`` package's sync client instead (``send`` of the same
  command + ``recv(timeout=0)`` until empty, newest decoded): its work per cycle and period.

Run: ``.venv/bin/python bench/haply_link.py --duration 5``. No figure is asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.remote.haply import HaplyBackend
from haptic_topology.remote.websocket_client import frame
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

CALLS, REPEATS = 20_000, 5
REPO = Path(__file__).resolve().parents[1]


def _per_call_us(fn: Any) -> float:
    return 1e6 * min(timeit.repeat(fn, number=CALLS, repeat=REPEATS)) / CALLS


def _emulator(tmp: Path) -> tuple[subprocess.Popen[bytes], int]:
    ready = tmp / 'ready.json'
    proc = subprocess.Popen([sys.executable, '-m', 'haptic_topology.remote.haply_emulator',
                             '--port', '0', '--ready-file', str(ready)],
                            stdout=subprocess.DEVNULL, cwd=REPO)
    deadline = time.monotonic() + 60.0
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise SystemExit('emulator did not start')
        time.sleep(0.02)
    return proc, int(json.loads(ready.read_text())['port'])


def _backend(port: int) -> HaplyBackend:
    sc = load_scenario('fig8_point')
    b = HaplyBackend()
    b.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, {'port': port},
                              sc.source))
    return b


def message_costs(port: int) -> dict[str, float]:
    """us per call: a command formatted and framed; a state message decoded."""
    b = _backend(port)
    b.activate()
    state = json.dumps({'inverse3': [{'device_id': b.device_id, 'state': {
        'cursor_position': {'x': 0.0123456789, 'y': -0.1198765, 'z': 0.150001},
        'cursor_velocity': {'x': 0.001, 'y': -0.002, 'z': 0.0003},
        'current_cursor_force': {'x': 0.1, 'y': 0.0, 'z': 0.0}, 'control_domain': 'cartesian',
        'control_mode': 'force'}, 'status': {'calibrated': True, 'in_use': True,
                                             'power_supply': True, 'ready': True,
                                             'started': True}}]}).encode()
    key = b'\x01\x02\x03\x04'

    def command() -> bytes:
        body = b'{"x":%r,"y":%r,"z":%r}' % (0.123456789, -1.5, 0.0)
        return frame(0x1, b._prefix + body + b._suffix, key)

    out = {'command_us': _per_call_us(command),
           'state_decode_us': _per_call_us(lambda: b._take(state, 0)),
           'state_bytes': float(len(state)), 'command_bytes': float(len(command()))}
    b.deactivate()
    return out


def _stats(work: list[float], periods: np.ndarray, missed: int) -> dict[str, float]:
    w = np.array(work) * 1e6
    p = periods * 1e3
    return {'work_p50_us': float(np.percentile(w, 50)), 'work_p99_us': float(np.percentile(w, 99)),
            'work_max_us': float(w.max()), 'period_p50_ms': float(np.percentile(p, 50)),
            'period_p99_ms': float(np.percentile(p, 99)), 'period_max_ms': float(p.max()),
            'period_std_ms': float(p.std()), 'missed': float(missed), 'cycles': float(len(w))}


def backend_loop(port: int, duration: float) -> dict[str, float]:
    b = _backend(port)
    b.activate()
    pacer = DeadlinePacer(0.001)
    n = int(duration / 0.001)
    work, stamps, missed = [], [], 0
    u = np.array([0.1, 0.0])
    clock = time.perf_counter
    faults = 0
    for _ in range(n):
        if not pacer.wait():
            missed += 1
        stamps.append(clock())
        t0 = clock()
        b.write(u)
        r = b.read(0.001)
        work.append(clock() - t0)
        faults += bool(r.status)
    b.write(np.zeros(2))
    b.deactivate()
    out = _stats(work, np.diff(stamps), missed)
    c = b.counters()
    out.update({f'backend_{k}': float(c[k]) for k in ('states', 'skipped', 'throttled',
                                                       'not_sent', 'malformed')})
    out['fault_readings'] = float(faults)
    return out


def websockets_loop(port: int, duration: float) -> dict[str, float]:
    """The same exchange through ``websockets.sync.client`` (its own reader thread)."""
    from websockets.sync.client import connect

    ws = connect(f'ws://127.0.0.1:{port}/', compression=None, ping_interval=None,
                 legacy=True)
    inventory = json.loads(ws.recv(timeout=5.0))
    dev = inventory['inverse3'][0]['device_id']
    prefix = '{"inverse3":[{"device_id":' + json.dumps(dev) + ',"commands":' \
        '{"set_cursor_force":{"vector":'
    suffix = '}}}]}'
    pacer = DeadlinePacer(0.001)
    n = int(duration / 0.001)
    work, stamps, missed = [], [], 0
    clock = time.perf_counter
    taken = 0
    for _ in range(n):
        if not pacer.wait():
            missed += 1
        stamps.append(clock())
        t0 = clock()
        ws.send(prefix + f'{{"x":{0.1!r},"y":{0.0!r},"z":{0.0!r}}}' + suffix)
        newest = None
        while True:
            try:
                newest = ws.recv(timeout=0)
            except TimeoutError:
                break
        if newest is not None:
            json.loads(newest)
            taken += 1
        work.append(clock() - t0)
    ws.close()
    out = _stats(work, np.diff(stamps), missed)
    out['states_taken'] = float(taken)
    return out


def run(duration: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        proc, port = _emulator(Path(tmp))
        try:
            res = {'messages': message_costs(port), 'backend': backend_loop(port, duration),
                   'websockets_sync': websockets_loop(port, duration)}
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=30)
    res['cpus'] = os.cpu_count()
    res['load'] = os.getloadavg()[0]
    return res


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--duration', type=float, default=5.0, help='s per loop (default 5)')
    args = p.parse_args()
    print(json.dumps(run(args.duration), indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
