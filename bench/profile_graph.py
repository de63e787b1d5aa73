"""Where the graph's CPU goes: CPU per process and per thread, and Python stacks per thread.

Runs ``haptic-topology run SCENARIO --duration S --layout L`` with the sampling profiler on
(``haptic_topology.sampling``) and reads every node process's threads from
``/proc/<pid>/task/<tid>/{comm,stat}`` twice, ``--window`` seconds apart in the middle of the
run: the CPU (fraction of a core) of each thread (the hosted loop thread is ``device_loop``,
its publisher ``device_publish``; DDS's threads have their own names). Then prints, per
process, the innermost Python frames that took most samples, without the ones waiting
(sleep, wait, spin). ``python bench/profile_graph.py [--layout hosted] [--duration 12]
[--clock wall|lockstep]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from haptic_topology.processes import cpu_seconds

WAITING = ('wait (threading.py', 'sleep', 'spin_once', '_wait_for_ready_callbacks',
           'wait_offered', 'select', 'sample (sampling.py')


def _threads(pid: int) -> dict[str, float]:
    out: dict[str, float] = {}
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            comm = Path(f'/proc/{pid}/task/{tid}/comm').read_text().strip()
        except OSError:
            continue
        cpu = cpu_seconds(pid, int(tid))
        if cpu is not None:
            out[f'{comm}[{tid}]'] = cpu
    return out


def _node_pids() -> dict[str, int]:
    out = {}
    for pid in os.listdir('/proc'):
        if not pid.isdigit():
            continue
        try:
            cmd = Path(f'/proc/{pid}/cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        for part in cmd:
            if part.startswith(b'haptic_topology.nodes.'):
                out[part.decode().rsplit('.', 1)[1]] = int(pid)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scenario', default='circle')
    ap.add_argument('--layout', default='hosted', choices=('hosted', 'separate', 'composed'))
    ap.add_argument('--duration', type=float, default=12.0)
    ap.add_argument('--window', type=float, default=6.0)
    ap.add_argument('--top', type=int, default=12)
    ap.add_argument('--clock', default='wall', choices=('wall', 'lockstep'))
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix='haptic_profile_'))
    env = dict(os.environ, HAPTIC_TOPOLOGY_PROFILE=str(tmp / 'stacks'))
    run = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', args.scenario, '--duration',
         str(args.duration), '--layout', args.layout, '--clock', args.clock, '--no-plot',
         '--out', str(tmp / 'bag')],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 60.0
    pids: dict[str, int] = {}
    while time.monotonic() < deadline and 'device_driver' not in pids | (
            {'composed': 0} if args.layout == 'composed' else {}):
        pids = _node_pids()
        time.sleep(0.2)
    time.sleep(min(3.0, args.duration / 4))      # start-up and engagement
    pids = _node_pids()
    first = {name: _threads(pid) for name, pid in pids.items()}
    time.sleep(args.window)
    second = {name: _threads(pid) for name, pid in pids.items()}
    out, _ = run.communicate(timeout=args.duration + 120)
    print('\n'.join(out.strip().splitlines()[-4:]))
    total = 0.0
    for name, threads in second.items():
        cpu = {t: (v - first[name].get(t, 0.0)) / args.window for t, v in threads.items()}
        proc = sum(cpu.values())
        total += proc
        busy = ', '.join(f'{t} {c:.3f}' for t, c in sorted(cpu.items(), key=lambda x: -x[1])
                         if c >= 0.005)
        print(f'{name}: {proc:.3f} core ({busy})')
    print(f'total: {total:.3f} core')
    for name, pid in pids.items():
        f = tmp / f'stacks.{pid}'
        if not f.is_file():
            continue
        counts: Counter[str] = Counter()
        for line in f.read_text(encoding='utf-8').splitlines():
            stack, n = line.rsplit(' ', 1)
            frames = stack.split(';')
            inner = frames[-1]
            if any(w in inner for w in WAITING):
                continue
            counts[f'{frames[0]}: {inner}'] += int(n)
        print(f'\n{name}: top innermost frames (samples, 1 ms each; waits left out)')
        for frame, samples in counts.most_common(args.top):
            print(f'  {samples:6d}  {frame}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
