"""``device/realtime``'s nice increments: per thread on Linux, so the whole process means every
thread, and the autogroup of a process that leads its session. Run in a child interpreter: a
raised nice cannot be lowered again without privilege, and the pytest worker must keep its
own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_topology.device import realtime
from haptic_topology.device.realtime import (
    SESSION_NICE_ENV,
    START_CPUS,
    loop_cpus,
    set_process_affinity,
    set_process_policy,
)

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


SESSION = r"""
import json, os
from haptic_topology.device.realtime import raise_session_nice, renice_process, reset_session_nice

def group():
    return open('/proc/self/autogroup').read().split()
out = {'leader': os.getsid(0) == os.getpid(), 'start': group()}
out['raise'] = raise_session_nice(4)
out['after_raise'] = group()
out['lower'] = raise_session_nice(2)       # a smaller value leaves it as it is
out['after_lower'] = group()
out['process'] = renice_process(7)
out['after_process'] = group()
reset_session_nice()                     # a stopping node: back to 0, without privilege
out['after_reset'] = group()
print(json.dumps(out))
"""


def _session_child(own_session: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k != SESSION_NICE_ENV}  # the default
    proc = subprocess.run([sys.executable, '-c', SESSION], capture_output=True, text=True,
                          timeout=60, check=True, start_new_session=own_session, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not Path('/proc/self/autogroup').exists(),
                    reason='kernel without CONFIG_SCHED_AUTOGROUP')
def test_a_session_leader_raises_and_resets_its_autogroup_and_another_process_leaves_it(
        ) -> None:
    leader = _session_child(True)
    assert leader['leader'] and leader['start'][-1] == '0'        # a new session's group
    assert leader['raise'] is None and leader['after_raise'][-1] == '4'
    assert leader['lower'] is None and leader['after_lower'][-1] == '4'
    assert leader['process'] is None and leader['after_process'][-1] == '7'
    assert leader['after_reset'][-1] == '0'
    mine = open('/proc/self/autogroup').read().split()   # empty in the kernel's default group
    assert leader['after_process'][0] != (mine or [''])[0]
    member = _session_child(False)              # shares this session's group: untouched
    assert not member['leader'] and member['start'] == mine
    assert member['raise'] is None and member['after_process'] == mine
    assert member['after_reset'] == mine


def test_a_process_in_the_kernels_default_group_reads_an_empty_autogroup_and_leaves_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A process that never left the kernel's default group (e.g. a container's first process)
    reads ``/proc/self/autogroup`` as empty: there is no group of its own to renice."""
    empty = tmp_path / 'autogroup'
    empty.write_text('')
    monkeypatch.setattr(realtime, 'AUTOGROUP', str(empty))
    monkeypatch.setattr(realtime, '_own_autogroup', lambda: True)
    monkeypatch.delenv(SESSION_NICE_ENV, raising=False)
    assert realtime.raise_session_nice(5) is None
    assert empty.read_text() == ''


SLICE_CHILD = r'''
import json, os, sys
from haptic_topology.device.realtime import (sched_slice_ns, set_thread_realtime,
                                             timer_slack_ns)
out = {'default_slice': sched_slice_ns(), 'default_slack': timer_slack_ns()}
out['problems'] = set_thread_realtime(0, [-1], False, float(sys.argv[1]), int(sys.argv[2]))
out['slice'], out['slack'] = sched_slice_ns(), timer_slack_ns()
out['nice'] = os.getpriority(os.PRIO_PROCESS, 0)
print(json.dumps(out))
'''


def _kernel_keeps_slices() -> bool:
    """Linux >= 6.12 keeps a slice per task under normal scheduling (``sched_setattr``'s
    ``sched_runtime``)."""
    major, minor = (int(x) for x in os.uname().release.split('.')[:2])
    return (major, minor) >= (6, 12)


def _slice_child(slice_us: float, slack_ns: int, nice: int = 0) -> dict:
    res = subprocess.run(['nice', '-n', str(nice), sys.executable, '-c', SLICE_CHILD,
                          str(slice_us), str(slack_ns)],
                         capture_output=True, text=True, timeout=60, check=True)
    return dict(json.loads(res.stdout))


def test_the_slice_and_the_timer_slack_are_the_threads_own_and_keep_its_nice() -> None:
    """The loop asks for a 250 us slice and 1 us of timer slack: both read back from the
    kernel; the nice value the process started with stays (sched_setattr sets it too)."""
    out = _slice_child(250.0, 1000, nice=3)
    assert out['slack'] == 1000 and out['default_slack'] != 1000
    assert out['nice'] == 3
    if _kernel_keeps_slices():
        assert out['problems'] == []
        assert out['slice'] == 250_000 and out['default_slice'] != 250_000
    else:
        assert out['problems'] == ['sched_slice_us 250: this kernel keeps no slice per task '
                                   '(Linux >= 6.12 does); not applied']


def test_zero_leaves_the_kernels_slice_and_slack() -> None:
    out = _slice_child(0.0, 0)
    assert out['problems'] == []
    assert (out['slice'], out['slack']) == (out['default_slice'], out['default_slack'])


FIFO_CHILD = r'''
import os
from haptic_topology.device.realtime import set_thread_realtime
problems = set_thread_realtime(5, [-1], False, 100.0, 0)
print(problems, os.sched_getscheduler(0) == os.SCHED_FIFO)
'''


def test_a_sched_fifo_loop_keeps_sched_fifo_the_slice_is_for_normal_scheduling() -> None:
    """sched_setattr with SCHED_OTHER would undo SCHED_FIFO: with a priority the slice is not
    asked for (where SCHED_FIFO is refused, the loop gets the slice instead)."""
    res = subprocess.run([sys.executable, '-c', FIFO_CHILD], capture_output=True, text=True,
                         timeout=60, check=True)
    if 'sched_priority 5: not permitted' in res.stdout:
        assert res.stdout.strip().endswith(' False'), res.stdout
    else:
        assert res.stdout.strip() == '[] True', res.stdout


def test_a_slice_outside_the_kernels_range_is_refused_naming_the_parameter() -> None:
    from haptic_topology.config.settings import DeviceDriverSettings
    from haptic_topology.errors import ConfigError

    with pytest.raises(ConfigError, match=r"parameter sched_slice_us: expected 0.0 \(the "
                       r"kernel's default\) or a value in \[100, 100000\] us, got 50.0"):
        DeviceDriverSettings(sched_slice_us=50.0).check()
    DeviceDriverSettings(sched_slice_us=100.0).check()
    DeviceDriverSettings(sched_slice_us=0.0).check()


MMAP_CHILD = r'''
import ctypes, ctypes.util, json, sys
from haptic_topology.device.realtime import fix_mmap_threshold


class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        'arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks', 'fsmblks', 'uordblks',
        'fordblks', 'keepcost')]


libc = ctypes.CDLL(ctypes.util.find_library('c'))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
libc.mallinfo2.restype = MallInfo2
fixed = fix_mmap_threshold() if sys.argv[1] == 'fixed' else None
libc.free(libc.malloc(4 << 20))     # a mapped block freed: glibc's dynamic threshold rises
before = libc.mallinfo2().hblks
block = libc.malloc(512 << 10)      # above the fixed threshold, below the raised one
print(json.dumps({'fixed': fixed, 'mapped_blocks': libc.mallinfo2().hblks - before}))
libc.free(block)
'''


def _mmap_child(mode: str) -> dict:
    res = subprocess.run([sys.executable, '-c', MMAP_CHILD, mode], capture_output=True,
                         text=True, timeout=60, check=True)
    return dict(json.loads(res.stdout))


@pytest.mark.skipif(not hasattr(__import__('ctypes').CDLL(None), 'mallinfo2'),
                    reason='the C library is not glibc >= 2.33')
def test_the_mmap_threshold_stays_fixed_after_a_mapped_block_is_freed() -> None:
    """Every node process fixes glibc's mmap threshold (``run_main``): a 512 KiB block is
    still mapped after a 4 MiB one was freed, where glibc's dynamic threshold would have
    taken it from the heap (which then grows while the bytes in use stay the same)."""
    assert _mmap_child('fixed') == {'fixed': True, 'mapped_blocks': 1}
    assert _mmap_child('dynamic') == {'fixed': None, 'mapped_blocks': 0}


POLICY_CHILD = r'''
import json, os, subprocess, sys, threading
from haptic_topology.device.realtime import set_process_policy, set_thread_realtime

def policies():
    return {int(t): os.sched_getscheduler(int(t)) for t in os.listdir('/proc/self/task')}

os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))    # whatever the runner's was
started = threading.Event()
def worker():
    out['worker_tid'] = threading.get_native_id()
    started.set()
    threading.Event().wait(5)   # stays alive until the process exits

out = {}
threading.Thread(target=worker, daemon=True).start()
started.wait()
out['start'] = policies()
out['problem'] = set_process_policy(sys.argv[1])
out['after'] = policies()
late = []
t = threading.Thread(target=lambda: late.append(os.sched_getscheduler(0)))
t.start(); t.join()
out['new_thread'] = late[0]
out['child_process'] = int(subprocess.run(
    [sys.executable, '-c', 'import os; print(os.sched_getscheduler(0))'],
    capture_output=True, text=True, check=True).stdout)
out['nice'] = os.getpriority(os.PRIO_PROCESS, 0)
out['loop_problems'] = set_thread_realtime(0, [-1], False, 0.0, 0)   # the loop's start
out['loop'] = policies()
out['loop_nice'] = os.getpriority(os.PRIO_PROCESS, 0)
out['main_tid'] = threading.get_native_id()
print(json.dumps(out))
'''


@pytest.mark.parametrize(('policy', 'cls'), [('batch', os.SCHED_BATCH),
                                             ('idle', os.SCHED_IDLE)])
def test_a_policy_covers_every_thread_and_what_they_start_and_the_loop_returns_to_normal(
        policy: str, cls: int) -> None:
    """A node off the deadline path puts all its threads under SCHED_BATCH or SCHED_IDLE
    (DDS's threads exist before it does): threads and processes it starts later inherit it,
    the loop process included, whose real-time settings put its own thread back under
    normal scheduling (this suite runs where that is permitted; without privilege only
    SCHED_BATCH can be left, which is why device_driver does not offer idle); nice values
    stay."""
    res = subprocess.run(['nice', '-n', '2', sys.executable, '-c', POLICY_CHILD, policy],
                         capture_output=True, text=True, timeout=60, check=True)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    start = {int(k): v for k, v in out['start'].items()}
    assert len(start) >= 2 and set(start.values()) == {os.SCHED_OTHER}
    assert out['problem'] is None
    assert {int(k): v for k, v in out['after'].items()} == dict.fromkeys(start, cls)
    assert out['new_thread'] == cls
    assert out['child_process'] == cls
    assert out['loop_problems'] == []
    loop = {int(k): v for k, v in out['loop'].items()}
    assert loop[out['main_tid']] == os.SCHED_OTHER              # the loop's thread only
    assert loop[out['worker_tid']] == cls
    assert out['nice'] == out['loop_nice'] == 2


def test_policy_other_changes_nothing_and_an_unknown_one_is_named() -> None:
    before = os.sched_getscheduler(0)
    assert set_process_policy('other') is None
    assert os.sched_getscheduler(0) == before
    assert set_process_policy('fifo') == ("sched_policy: 'fifo' is not one of other, batch, "
                                          'idle; unchanged')
    assert os.sched_getscheduler(0) == before


AFFINITY_CHILD = r'''
import json, os, subprocess, sys, threading
from haptic_topology.device.realtime import set_process_affinity, set_thread_realtime

def affinities():
    return {int(t): sorted(os.sched_getaffinity(int(t))) for t in os.listdir('/proc/self/task')}

node, loop = json.loads(sys.argv[1]), json.loads(sys.argv[2])
started = threading.Event()
def worker():
    out['worker_tid'] = threading.get_native_id()
    started.set()
    threading.Event().wait(5)

out = {'all': sorted(os.sched_getaffinity(0))}
threading.Thread(target=worker, daemon=True).start()
started.wait()
out['problem'] = set_process_affinity(node)
out['after'] = affinities()
late = []
t = threading.Thread(target=lambda: late.append(sorted(os.sched_getaffinity(0))))
t.start(); t.join()
out['new_thread'] = late[0]
out['child_process'] = json.loads(subprocess.run(
    [sys.executable, '-c', 'import os; print(sorted(os.sched_getaffinity(0)))'],
    capture_output=True, text=True, check=True).stdout)
out['loop_problems'] = set_thread_realtime(0, loop, False, 0.0, 0)   # the loop's start
out['loop'] = affinities()
out['main_tid'] = threading.get_native_id()
print(json.dumps(out))
'''


def test_a_pinned_node_pins_every_thread_and_what_it_starts_and_the_loop_pins_its_own() -> None:
    """A node pinned to a core pins every thread it has (DDS's exist before it does) and the
    threads and processes it starts later inherit the pinning; the loop process, started by
    such a node, pins its own thread to its own core."""
    cpus = sorted(os.sched_getaffinity(0))
    node, loop = [cpus[0]], [cpus[-1]]      # two different cores where there are two
    res = subprocess.run([sys.executable, '-c', AFFINITY_CHILD, json.dumps(node),
                          json.dumps(loop)], capture_output=True, text=True, timeout=60,
                         check=True)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    after = {int(k): v for k, v in out['after'].items()}
    assert out['problem'] is None
    assert len(after) >= 2 and set(map(tuple, after.values())) == {tuple(node)}
    assert out['new_thread'] == out['child_process'] == node
    assert out['loop_problems'] == []
    pinned = {int(k): v for k, v in out['loop'].items()}
    assert pinned[out['main_tid']] == loop                       # the loop's thread only
    assert pinned[out['worker_tid']] == node


def test_the_loop_keeps_its_own_cpus_or_the_ones_its_pinned_node_started_with() -> None:
    assert loop_cpus([1], [0]) == (1,)
    assert loop_cpus([-1], [-1]) == (-1,)            # nothing pinned: nothing to undo
    assert loop_cpus([-1], [0]) == START_CPUS        # not narrowed to the node's CPUs
    assert START_CPUS == tuple(sorted(os.sched_getaffinity(0)))


def test_no_pinning_changes_nothing_and_a_cpu_not_there_is_named() -> None:
    before = os.sched_getaffinity(0)
    assert set_process_affinity([-1]) is None
    assert os.sched_getaffinity(0) == before
    n = os.cpu_count() or 1
    problem = set_process_affinity([n + 7])
    assert problem is not None and problem.startswith(f'cpu_affinity [{n + 7}]: ')
    assert problem.endswith('; not pinned')
    assert os.sched_getaffinity(0) == before


SLICE_AFTER_BATCH = r'''
import os
from haptic_topology.device.realtime import set_process_policy, set_thread_realtime, sched_slice_ns
set_process_policy('batch')
problems = set_thread_realtime(0, [-1], False, 250.0, 0)
print(problems, os.sched_getscheduler(0) == os.SCHED_OTHER, sched_slice_ns())
'''


def test_a_loop_started_under_batch_gets_its_slice() -> None:
    """The slice is asked for under normal scheduling: a loop process that inherited
    SCHED_BATCH from its node gets it all the same."""
    res = subprocess.run([sys.executable, '-c', SLICE_AFTER_BATCH], capture_output=True,
                         text=True, timeout=60, check=True)
    if _kernel_keeps_slices():
        assert res.stdout.strip() == '[] True 250000', res.stdout
    else:
        assert res.stdout.strip().startswith("['sched_slice_us 250: this kernel keeps no "
                                             "slice per task"), res.stdout


def test_parent_death_signal_is_set_for_the_calling_process() -> None:
    """``set_parent_death_signal`` sets what ``prctl(PR_GET_PDEATHSIG)`` reads back (in a
    child interpreter: the pytest worker must not die with its parent's end)."""
    code = ('import ctypes, signal\n'
            'from haptic_topology.device import realtime\n'
            'got = ctypes.c_int(-1)\n'
            'before = realtime._libc().prctl(2, ctypes.byref(got), 0, 0, 0), got.value\n'
            'realtime.set_parent_death_signal(signal.SIGTERM)\n'
            'after = realtime._libc().prctl(2, ctypes.byref(got), 0, 0, 0), got.value\n'
            'print(before, after, realtime._libc() is realtime._libc())\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split('\n')[0]
    assert out == '(0, 0) (0, 15) True'
