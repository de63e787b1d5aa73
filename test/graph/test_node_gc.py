"""A node process's objects are out of the garbage collector's reach once it spins
(``nodes.runtime.spin``: :func:`gc.freeze` after one collection), so a full collection walks
only what the node made since, not the ~100,000 objects of its modules and models."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.graph

WAIT = 60.0           # s: generous, a loaded machine is only slower

#: A real rclpy node spun by ``spin``; its first timer callback reports the collector's view
#: (frozen objects, objects still tracked) and stops the spin as SIGINT does.
PROBE = textwrap.dedent('''
    import gc, json, os, signal, sys
    import rclpy
    from rclpy.node import Node
    from haptic_topology.nodes.runtime import spin
    rclpy.init()
    node = Node('gc_probe')
    seen = []
    def tick():
        if not seen:
            seen.append({'frozen': gc.get_freeze_count(), 'tracked': len(gc.get_objects())})
            os.kill(os.getpid(), signal.SIGINT)
    node.create_timer(0.01, tick)
    before = {'frozen': gc.get_freeze_count(), 'tracked': len(gc.get_objects())}
    spin([node], 'events')
    print(json.dumps({'before': before, 'spinning': seen[0]}), flush=True)
    os._exit(0)
''')


def test_spin_freezes_what_the_process_built_before_it() -> None:
    out = subprocess.run([sys.executable, '-c', PROBE], capture_output=True, text=True,
                         timeout=WAIT, env=dict(os.environ, PYTHONUNBUFFERED='1'))
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    before, spinning = got['before'], got['spinning']
    assert before['frozen'] == 0, got
    # rclpy, numpy and the package's modules: tens of thousands of objects, now frozen
    assert spinning['frozen'] > 20_000, got
    assert spinning['frozen'] >= before['tracked'] // 2, got
    # what a full collection still walks: what the spin made since, a small fraction
    assert spinning['tracked'] < spinning['frozen'] // 20, got
