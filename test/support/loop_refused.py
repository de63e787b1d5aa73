"""A loop process whose real-time options the OS refuses: run it where they are not
permitted (``unshare --user --map-root-user python loop_refused.py``: root of a user
namespace has no CAP_SYS_NICE or CAP_IPC_LOCK over the machine); it starts a wall-clock loop
process for fig8 with ``sched_priority`` 50 and ``lock_memory``, prints ``cycling`` and the
child's notices once it runs, one per line, then stops it."""

from __future__ import annotations

import sys

from loop_specs import spec_for

from haptic_topology.device.loop_process import LoopProcess

if __name__ == '__main__':
    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    spec.update(sched_priority=50, lock_memory=True)
    proc = LoopProcess(spec, dim, dof)
    proc.start()
    try:
        while not proc.status:
            proc.wait(0.01)
            proc.drain()
        print('cycling' if proc.status.get('device') else 'no status', flush=True)
        for line in proc.notices:
            print(line, flush=True)
    finally:
        proc.stop()
        proc.close()
    sys.exit(0)
