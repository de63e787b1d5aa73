"""``device/realtime``'s nice increments: per thread on Linux, so the whole process means every
thread. Run in a child interpreter: a raised nice cannot be lowered again without privilege,
and the pytest worker must keep its own."""

from __future__ import annotations

import json
import subprocess
import sys

CHILD = r'''
import json, os, threading
from haptic_topology.device.realtime import renice_process, renice_thread

def nices():
    return {int(t): os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir('/proc/self/task')}

go, done = threading.Event(), threading.Event()
out = {}
def worker():
    out['worker_tid'] = threading.get_native_id()
    go.wait()
    out['thread_problem'] = renice_thread(2)
    done.set()
    threading.Event().wait(5)   # stays alive until the process exits

threading.Thread(target=worker, daemon=True).start()
while 'worker_tid' not in out:
    pass
out['start'] = nices()
out['process_problem'] = renice_process(3)
out['after_process'] = nices()
go.set(); done.wait()
out['after_thread'] = nices()
out['main_tid'] = threading.get_native_id()
late = []
t = threading.Thread(target=lambda: late.append(os.getpriority(os.PRIO_PROCESS, 0)))
t.start(); t.join()
out['new_thread'] = late[0]
out['capped_problem'] = renice_process(40)
out['capped'] = os.getpriority(os.PRIO_PROCESS, 0)
print(json.dumps(out))
'''


def test_renice_process_raises_every_thread_and_renice_thread_only_its_own() -> None:
    proc = subprocess.run([sys.executable, '-c', CHILD], capture_output=True, text=True,
                          timeout=60, check=True)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    start = {int(k): v for k, v in out['start'].items()}
    after = {int(k): v for k, v in out['after_process'].items()}
    base = start[out['main_tid']]
    assert out['process_problem'] is None
    assert len(start) >= 2
    assert after == {tid: min(n + 3, 19) for tid, n in start.items()}
    after_thread = {int(k): v for k, v in out['after_thread'].items()}
    worker = out['worker_tid']
    assert out['thread_problem'] is None
    assert after_thread[worker] == min(base + 5, 19)
    assert after_thread[out['main_tid']] == min(base + 3, 19)
    assert out['new_thread'] == min(base + 3, 19)      # inherited from its creator
    assert out['capped_problem'] is None
    assert out['capped'] == 19                          # the largest nice value
