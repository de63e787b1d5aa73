"""How long a full garbage collection stops a node process, before and after the freeze its
spin does (``haptic_topology.nodes.runtime.freeze_startup_objects``).

Each node's process is built as its program builds it (``ve_sim``; ``device_driver`` with
the hosted ``lmi_controller``; ``recorder``), in a process of its own, without spinning;
then ``gc.collect()`` is timed (wall time, the median of ``--repeat``), the objects are
frozen as ``spin`` freezes them, and ``gc.collect()`` is timed again. Prints one JSON object:
per node, the objects the collector tracks and the pause (ms) before and after.

Run: ``.venv/bin/python bench/gc_pause.py`` (about 5 s).
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

NODES = ('ve_sim', 'device_driver', 'recorder')


def _pause(repeat: int) -> float:
    """Median wall time (ms) of a full collection."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        gc.collect()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times)


def _measure(node: str, repeat: int) -> dict[str, Any]:
    import rclpy

    from haptic_topology.nodes.runtime import freeze_startup_objects

    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        if node == 've_sim':
            from haptic_topology.nodes.ve_sim import VeSim
            nodes: list[Any] = [VeSim()]
        elif node == 'device_driver':
            from haptic_topology.nodes.device_driver import build
            nodes = build()
        else:
            from rclpy.parameter import Parameter

            from haptic_topology.nodes.recorder import Recorder
            nodes = [Recorder(parameter_overrides=[
                Parameter('output', value=f'{tmp}/bag')])]
        tracked = len(gc.get_objects())
        before = _pause(repeat)
        freeze_startup_objects()
        after = _pause(repeat)
        out = {'tracked_objects': tracked, 'frozen_objects': gc.get_freeze_count(),
               'full_collection_ms': round(before, 2),
               'full_collection_after_freeze_ms': round(after, 4)}
        for n in nodes:
            n.destroy_node()
    rclpy.try_shutdown()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--repeat', type=int, default=5, help='collections timed per figure')
    ap.add_argument('--node', choices=NODES, help=argparse.SUPPRESS)   # the child's part
    args = ap.parse_args()
    if args.node:
        print(json.dumps(_measure(args.node, args.repeat)), flush=True)
        return 0
    res = {}
    for node in NODES:
        out = subprocess.run([sys.executable, __file__, '--node', node, '--repeat',
                              str(args.repeat)], capture_output=True, text=True, check=True)
        res[node] = json.loads(out.stdout.strip().splitlines()[-1])
    print(json.dumps(res, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
