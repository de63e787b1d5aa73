"""A parent of a loop process, for the test that kills the parent: starts a wall-clock loop
process for scenario fig8 (``python loop_parent.py``), prints the child's pid and the ring
names once it runs, then takes its records until killed."""

from __future__ import annotations

import sys
import time

from loop_specs import spec_for

from haptic_topology.device.loop_process import LoopProcess

if __name__ == '__main__':
    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    proc = LoopProcess(spec, dim, dof)
    proc.start()
    while not proc.status:          # running: its first status record
        proc.wait(0.01)
        proc.drain()
    print(proc.pid, *proc.ring_names(), flush=True)
    while True:
        time.sleep(0.01)
        proc.drain()
        sys.stdout.flush()
