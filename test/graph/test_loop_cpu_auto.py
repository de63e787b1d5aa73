"""``haptic-topology run`` with its default ``--loop-cpu auto``, beside two busy programs
pinned to one CPU: the loop process gets a CPU of its own while they run, and the run says so
and lists it in ``summary.json``. Nothing is timed: two busy programs keep at least half a
core busy on any machine, whichever CPU the run then keeps for the loop."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_topology.bringup.partition import ENGAGE_LOAD

pytestmark = pytest.mark.graph

_BUSY = 'import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\nwhile True:\n    pass\n'


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='a partition needs two CPUs')
@pytest.mark.timeout(240)
def test_run_keeps_a_cpu_for_the_loop_while_other_programs_keep_the_machine_busy(
        tmp_path: Path) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    bag = tmp_path / 'bag'
    busy = [subprocess.Popen([sys.executable, '-c', _BUSY, str(cpus[0])]) for _ in range(2)]
    try:
        proc = subprocess.run(
            [sys.executable, '-m', 'haptic_topology.cli', 'run', 'circle', '--duration', '4',
             '--no-plot', '--out', str(bag)], capture_output=True, text=True, timeout=200)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    changes = json.loads((bag / 'summary.json').read_text())['loop_cpu_changes']
    assert changes, proc.stdout
    first = changes[0]
    assert first['loop_cpu'] in cpus and first['other_load_cores'] >= ENGAGE_LOAD, changes
    others = [c for c in cpus if c != first['loop_cpu']]
    assert (f'loop CPU: other software keeps {first["other_load_cores"]:.2f} cores busy; '
            f'loop process alone on CPU {first["loop_cpu"]}, every other thread of the graph '
            f'on CPUs {others}') in proc.stdout
