"""The authenticated device link's cost (``make bench`` section 8).

* per packet, in this process: encoding a COMMAND and decoding a STATE (planar, m = 3) with
  and without a key, and the MAC alone (``hashlib.blake2b`` keyed, 16-byte tag), us per call
  (fastest of ``REPEATS`` runs of ``CALLS`` calls);
* the ``network`` backend's loop against ``haptic-topology device-server`` on loopback, without
  and with a key, ``duration`` s each at 1 kHz (absolute deadlines): the backend's work per
  cycle (``write`` + ``read``, us) p50/p99/max, the cycle period p50/p99/max, missed
  deadlines, the command -> state round trip p50/p99, and what either side refused.

Run alone: ``.venv/bin/python bench/link_auth.py --duration 3``.
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
from haptic_topology.remote import protocol as P
from haptic_topology.remote.auth import LinkKey, write_key
from haptic_topology.remote.network import NetworkBackend
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

CALLS, REPEATS = 20_000, 5


def _per_call_us(fn: Any) -> float:
    return 1e6 * min(timeit.repeat(fn, number=CALLS, repeat=REPEATS)) / CALLS


def packet_costs() -> dict[str, float]:
    """us per call: encode COMMAND / decode STATE without and with a key, the MAC alone."""
    key = LinkKey(bytes(range(32)))
    w = [1.0, -2.0, 0.5]
    v = [0.1, 0.2, 0.3]
    st_plain = P.encode_state(7, 5, 1, 4, 1, 0, 4, v, v, v, v)
    st_auth = P.encode_state(7, 5, 1, 4, 1, 0, 4, v, v, v, v, key, 9)
    body = st_auth[:-16]
    return {
        'encode_command_us': _per_call_us(
            lambda: P.encode_command(9, 5, 1, 4, 1, P.CommandFlags.ENGAGED, 20_000, w)),
        'encode_command_mac_us': _per_call_us(
            lambda: P.encode_command(9, 5, 1, 4, 1, P.CommandFlags.ENGAGED, 20_000, w, key, 7)),
        'decode_state_us': _per_call_us(lambda: P.decode(st_plain, 3, P.PacketType.STATE)),
        'decode_state_mac_us': _per_call_us(
            lambda: P.decode(st_auth, 3, P.PacketType.STATE, key)),
        'mac_only_us': _per_call_us(lambda: key.tag(body)),
    }


def _server(tmp: Path, key_file: Path | None) -> tuple[subprocess.Popen[bytes], int]:
    ready = tmp / f'ready_{bool(key_file)}.json'
    cmd = [sys.executable, '-m', 'haptic_topology.remote.server_command', '--scenario', 'fig8',
           '--port', '0', '--ready-file', str(ready)]
    if key_file is not None:
        cmd += ['--key-file', str(key_file)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60.0
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f'device-server did not start ({proc.returncode})')
        time.sleep(0.05)
    return proc, int(json.loads(ready.read_text())['port'])


def network_loop(duration: float, key_file: Path | None) -> dict[str, Any]:
    """The network backend's loop at 1 kHz for ``duration`` s (module doc)."""
    with tempfile.TemporaryDirectory(prefix='bench_link_') as d:
        proc, port = _server(Path(d), key_file)
        sc = load_scenario('fig8')
        opts: dict[str, object] = {'port': port, 'stale_ms': 50.0}
        if key_file is not None:
            opts['key_file'] = str(key_file)
        be = NetworkBackend()
        be.configure(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), opts,
                                   sc.source))
        n = max(1, round(duration * 1000))
        work = np.zeros(n)
        period = np.zeros(n)
        pacer = DeadlinePacer(0.001)
        w = np.zeros(3)
        try:
            be.activate()
            for k in range(n):
                tick = pacer.wait()
                period[k] = tick.dt
                t0 = time.perf_counter()
                be.write(w)
                be.read(0.001)
                work[k] = time.perf_counter() - t0
        finally:
            be.deactivate()
            proc.send_signal(signal.SIGINT)
            proc.wait(20)
        c, rtt = be.counters(), be.round_trip()
    us = 1e6
    return {'cycles': n, 'work_p50_us': us * float(np.percentile(work, 50)),
            'work_p99_us': us * float(np.percentile(work, 99)), 'work_max_us': us * work.max(),
            'period_p50_us': us * float(np.percentile(period[1:], 50)),
            'period_p99_us': us * float(np.percentile(period[1:], 99)),
            'period_max_us': us * float(period[1:].max()), 'missed': pacer.missed,
            'rtt_p50_us': us * rtt['p50'], 'rtt_p99_us': us * rtt['p99'],
            'refused': c['malformed'] + c['rejected'], 'link': be.link}


def run(duration: float) -> dict[str, Any]:
    """Both measurements (module doc)."""
    out: dict[str, Any] = {'packet': packet_costs()}
    with tempfile.TemporaryDirectory(prefix='bench_key_') as d:
        kf = Path(d) / 'link.key'
        write_key(kf)
        out['loop_plain'] = network_loop(duration, None)
        out['loop_mac'] = network_loop(duration, kf)
    return out


def table(res: dict[str, Any]) -> list[str]:
    p = res['packet']
    lines = [f'device link per packet [us]: encode COMMAND {p["encode_command_us"]:.2f}, with '
             f'MAC {p["encode_command_mac_us"]:.2f}; decode STATE {p["decode_state_us"]:.2f}, '
             f'with MAC {p["decode_state_mac_us"]:.2f}; MAC alone {p["mac_only_us"]:.2f}',
             'network backend loop   work p50/p99/max [us]   period p50/p99/max [us]   '
             'missed  rtt p50/p99 [us]  refused']
    for key, label in (('loop_plain', 'without key'), ('loop_mac', 'with key (MAC)')):
        r = res[key]
        lines.append(f'{label:20s}  {r["work_p50_us"]:6.0f}/{r["work_p99_us"]:6.0f}/'
                     f'{r["work_max_us"]:7.0f}   {r["period_p50_us"]:6.0f}/'
                     f'{r["period_p99_us"]:6.0f}/{r["period_max_us"]:7.0f}   '
                     f'{r["missed"]:6d}  {r["rtt_p50_us"]:6.0f}/{r["rtt_p99_us"]:6.0f}  '
                     f'{r["refused"]}')
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument('--duration', type=float, default=10.0, help='s of each loop run')
    res = run(ap.parse_args().duration)
    print('\n'.join(table(res)))
    print(json.dumps(res, indent=1))


if __name__ == '__main__':
    os.environ.setdefault('PYTHONUNBUFFERED', '1')
    main()
