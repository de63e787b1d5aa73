"""Real-time settings of a process or of the loop thread: SCHED_FIFO, SCHED_BATCH or
SCHED_IDLE for the nodes off the deadline path, CPU affinity, ``mlockall``, the scheduler
slice, the timer slack, the thread's name, and the allocator's fixed mmap threshold of every
node process. No rclpy: the device loop calls these from its own thread."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import platform
import struct
import time
from collections.abc import Callable, Sequence


def _thread_ids() -> list[int]:
    """The ids of this process's threads (``[0]``, the caller, where /proc is not there)."""
    try:
        return [int(t) for t in os.listdir('/proc/self/task')]
    except OSError:
        return [0]


def _each_thread(apply: Callable[[int], object]) -> OSError | None:
    """``apply(tid)`` for every thread of this process; a thread that ended meanwhile is
    skipped. Returns the first error (the remaining threads are left as they are), or None."""
    for tid in _thread_ids():
        try:
            apply(tid)
        except ProcessLookupError:
            continue
        except OSError as exc:
            return exc
    return None


def _renice(tid: int, increment: int) -> None:
    """Raise thread ``tid``'s nice value by ``increment`` (at most to 19)."""
    os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + increment,
                                             19))


def set_realtime_priority(priority: int) -> str | None:
    """Put every thread of this process (DDS's receive threads included, which run the
    subscription callbacks' wake-ups) under SCHED_FIFO at ``priority``; threads started later
    inherit it. Returns None, or why it was not possible (the process then keeps normal
    scheduling).

    Why: on 2 cores the 1 kHz pair (device_driver, lmi_controller) shares the CPU with ve_sim's
    RK4 and the recorder; measured on the circle scenario, 10 s, separate processes: cycles
    answered in time 82 % -> 94 %, device period p99 1.76 -> 1.08 ms (docs/results.md, benchmarks).
    Linux throttles real-time threads to 95 % of each second (sched_rt_runtime_us), so a
    runaway loop cannot lock the machine.
    """
    try:
        for tid in _thread_ids():
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return (f'sched_priority {priority}: not permitted (needs CAP_SYS_NICE or an rtprio '
                'limit, e.g. in /etc/security/limits.conf); running with normal scheduling')
    except (OSError, AttributeError) as exc:
        return f'sched_priority {priority}: {exc}; running with normal scheduling'
    return None


#: The scheduling policies a node off the deadline path may run under (``sched_policy``):
#: ``other`` leaves the process as it started (normally ``SCHED_OTHER``).
NODE_POLICIES: dict[str, int] = {'other': os.SCHED_OTHER, 'batch': os.SCHED_BATCH,
                                 'idle': os.SCHED_IDLE}


def set_process_policy(policy: str) -> str | None:
    """Put every thread of this process under the :data:`NODE_POLICIES` policy ``policy``
    (threads and processes started later inherit it from their creator); nice values stay.
    ``'other'`` changes nothing. Returns None, or why it failed.

    Why ``batch``: a thread that wakes may preempt the one running on its core at once
    (EEVDF's wake-up preemption); a ``SCHED_BATCH`` thread never does, it waits for the
    running one to sleep or to use up its slice. A node off the deadline path (the VE, the
    recorder, the driver's ROS side beside its loop process) then does not cut into a loop
    cycle each time one of its threads (its executor, DDS's receive threads) wakes; its share
    of the CPU is the same. Traced on ``run circle`` (15 s, 2 cores): the loop process was
    preempted in 11 % of its cycles (321 times for more than 0.3 ms), nearly always by the
    other nodes' threads; with them under ``SCHED_BATCH``, in 4 % (79 times).

    Why ``idle``: a waking normal thread preempts a ``SCHED_IDLE`` thread at once, so the
    loop process does not wait behind the VE's computation for its core (traced under
    ``SCHED_BATCH`` with a busy process holding the other core: wake-ups that waited 1-1.8 ms
    behind ve_sim's main thread). The price: a ``SCHED_IDLE`` thread gets a core only when
    no normal thread wants it, so beside busy work on every core it stalls. Neither needs
    privilege (sched(7)), but an unprivileged process cannot leave ``SCHED_IDLE`` again, nor
    can the processes it starts: a node that starts the loop process must not use it."""
    if policy not in NODE_POLICIES:
        return (f'sched_policy: {policy!r} is not one of {", ".join(NODE_POLICIES)}; '
                'unchanged')
    if policy == 'other':
        return None
    cls = NODE_POLICIES[policy]
    exc = _each_thread(lambda tid: os.sched_setscheduler(tid, cls, os.sched_param(0)))
    return None if exc is None else f'sched_policy {policy}: {exc}; normal scheduling'


def set_process_affinity(cpus: Sequence[int]) -> str | None:
    """Pin every thread of this process to ``cpus`` (``[-1]``: change nothing); threads and
    processes started later inherit the pinning from their creator. Returns None, or why it
    failed (the threads not reached stay as they were).

    Why: on 2 cores the loop process shares its core with the nodes' threads, and a thread of
    theirs that is in a system call (DDS sending or receiving) is not preempted before it
    returns (a kernel without full preemption), however short the loop's slice. Traced on
    ``run circle`` (30 s): 44 of the 58 cycles released more than 1.9 ms after the previous
    one waited behind the nodes' threads alone. With the nodes pinned to one core and the
    loop process to the other (``cpu_affinity``), what remains is other software on the
    loop's core; a busy process that computes in user space is preempted at once. Pinning
    one's own threads needs no privilege (sched_setaffinity(2))."""
    cpus = list(cpus)
    if cpus == [-1]:
        return None
    exc = _each_thread(lambda tid: os.sched_setaffinity(tid, cpus))
    return None if exc is None else f'cpu_affinity {cpus}: {exc}; not pinned'


#: The CPUs this process could run on when it imported this module: before any pinning of
#: its own (:func:`set_process_affinity`).
START_CPUS: tuple[int, ...] = tuple(sorted(os.sched_getaffinity(0)))


def loop_cpus(loop: Sequence[int], node: Sequence[int]) -> tuple[int, ...]:
    """The CPUs the loop process pins its thread to: ``loop`` (its node's ``cpu_affinity``);
    with ``[-1]`` there while the node's own threads are pinned to ``node``
    (``node_cpu_affinity``), the CPUs the node's process started with, which the loop
    process would otherwise inherit narrowed to the node's."""
    if list(loop) != [-1] or list(node) == [-1]:
        return tuple(loop)
    return START_CPUS


def normal_scheduling() -> str | None:
    """Put the calling thread back under normal scheduling (``SCHED_OTHER``) if it runs under
    ``SCHED_BATCH`` or ``SCHED_IDLE``, e.g. inherited from the node that started it
    (:func:`set_process_policy`); its nice value stays. None, or why it failed."""
    if os.sched_getscheduler(0) not in (os.SCHED_BATCH, os.SCHED_IDLE):
        return None
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError as exc:
        return f'normal scheduling: {exc}; the loop keeps SCHED_BATCH or SCHED_IDLE'
    return None


def renice_process(increment: int) -> str | None:
    """Raise the nice value of every thread of this process by ``increment`` (threads started
    later inherit their creator's), and of its autogroup if it leads its own session
    (:func:`raise_session_nice`). Linux keeps a nice value per thread, so ``os.nice`` alone
    would change only the calling one. Raising nice needs no privilege. Returns None, or why
    it failed."""
    exc = _each_thread(lambda tid: _renice(tid, increment))
    if exc is not None:
        return f'nice {increment}: {exc}; priority unchanged'
    return raise_session_nice(increment)


#: Set to ``0`` to keep every node's session at nice 0 (:func:`raise_session_nice` does
#: nothing): the nodes then yield to the loop only within their session, and never to
#: other programs. The tests set it: on a machine that also runs other busy work (a second
#: test worker) a session at nice 5 or 10 can be starved.
SESSION_NICE_ENV = 'HAPTIC_TOPOLOGY_SESSION_NICE'
#: This process's autogroup: ``"/autogroup-<id> nice <n>"``; write a number to set ``n``.
AUTOGROUP = '/proc/self/autogroup'


def _own_autogroup() -> bool:
    """This process leads its session, so the autogroup is its own, and the kernel has one."""
    return os.getsid(0) == os.getpid() and os.path.exists(AUTOGROUP)


def raise_session_nice(at_least: int) -> str | None:
    """Give this process's autogroup the nice value ``at_least`` (at most 19) unless it has
    a larger one, when the process leads its own session; else do nothing. Returns None, or
    why it failed.

    Why: with ``CONFIG_SCHED_AUTOGROUP`` (on by default in most distribution kernels; see
    sched(7)) the scheduler first shares the CPU among sessions, then among the threads of a
    session, and a thread's nice value ranks it only within its session. A node that leads
    its own session (started with ``setsid``; ``haptic-topology run`` starts the nodes and
    the loop process in run's session, which they do not lead) yields the CPU to the other
    sessions only through its autogroup's nice value, ``/proc/self/autogroup``. Raising it
    needs no privilege; the kernel accepts one such write per 100 ms from an unprivileged
    process, so a refused write is retried for a second.
    A process that does not lead its session (e.g. several nodes started from one shell)
    leaves the session's value alone: it is shared with the other processes of the session.
    With :data:`SESSION_NICE_ENV` set to ``0`` it does nothing.
    """
    if not _own_autogroup() or os.environ.get(SESSION_NICE_ENV) == '0':
        return None
    target = min(at_least, 19)
    for _ in range(11):
        try:
            with open(AUTOGROUP) as f:
                fields = f.read().split()
            if not fields:      # the kernel's default group (no setsid since boot): none
                return None
            if int(fields[-1]) >= target:
                return None
            with open(AUTOGROUP, 'w') as f:
                f.write(str(target))
            return None
        except BlockingIOError:         # EAGAIN: another process wrote in the last 100 ms
            time.sleep(0.1)
        except (OSError, ValueError) as exc:
            return f'session nice {target}: {exc}; unchanged'
    return f'session nice {target}: the kernel refused the write for 1 s; unchanged'


def reset_session_nice() -> None:
    """Set this process's autogroup back to nice 0 if it leads its own session (a node that
    is stopping: its teardown, e.g. the recorder finishing its bag or Fast DDS deleting its
    readers, then runs at the weight of any other session instead of waiting behind busy
    ones). Lowering an autogroup's value to 0 needs no privilege. Errors are ignored: the
    process is ending anyway."""
    if not _own_autogroup():
        return
    try:
        with open(AUTOGROUP, 'w') as f:
            f.write('0')
    except OSError:
        pass


def renice_thread(increment: int) -> str | None:
    """Raise the calling thread's nice value by ``increment``; None, or why it failed."""
    try:
        _renice(0, increment)
    except OSError as exc:
        return f'nice {increment}: {exc}; priority unchanged'
    return None


def set_thread_realtime(priority: int, cpus: Sequence[int], lock_memory: bool,
                        slice_us: float = 0.0, timer_slack_ns: int = 0) -> list[str]:
    """Real-time settings of the calling thread (the loop process or the hosted loop thread):
    normal scheduling first (:func:`normal_scheduling`: not the ``SCHED_BATCH`` of the node
    that started it), then SCHED_FIFO at ``priority`` (0: keep normal scheduling), pinned to
    ``cpus`` (``[-1]``: no pinning), ``mlockall(MCL_CURRENT | MCL_FUTURE)`` for the process
    when ``lock_memory``, under normal scheduling a scheduler slice of ``slice_us``
    (:func:`set_sched_slice`; 0: the kernel's) and a timer slack of ``timer_slack_ns``
    (:func:`set_timer_slack`; 0: the kernel's). Returns one line per setting that was not
    permitted (the loop then runs without it)."""
    problems = list(filter(None, [normal_scheduling()]))
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # this thread
        except PermissionError:
            problems.append(f'sched_priority {priority}: not permitted (needs CAP_SYS_NICE or '
                            'an rtprio limit); normal scheduling')
        except OSError as exc:
            problems.append(f'sched_priority {priority}: {exc}; normal scheduling')
    if slice_us and os.sched_getscheduler(0) != os.SCHED_FIFO:
        problems.extend(filter(None, [set_sched_slice(slice_us)]))
    if timer_slack_ns:
        problems.extend(filter(None, [set_timer_slack(timer_slack_ns)]))
    if list(cpus) != [-1]:
        try:
            os.sched_setaffinity(0, set(cpus))
        except OSError as exc:
            problems.append(f'cpu_affinity {list(cpus)}: {exc}; not pinned')
    if lock_memory:
        problems.extend(filter(None, [lock_all_memory()]))
    return problems


#: ``sched_setattr`` / ``sched_getattr`` system call numbers (no wrapper in glibc or ``os``).
_SCHED_ATTR_SYSCALLS = {'x86_64': (314, 315), 'aarch64': (274, 275)}
#: ``struct sched_attr`` (SCHED_ATTR_SIZE_VER1, 56 bytes): size, policy, flags, nice,
#: priority, runtime, deadline, period, util_min, util_max.
_SCHED_ATTR = struct.Struct('IIQiIQQQII')
#: The slices (us) the kernel accepts for a task under normal scheduling.
SLICE_RANGE_US = (100.0, 100_000.0)


def set_sched_slice(slice_us: float) -> str | None:
    """Ask the fair scheduler (EEVDF, Linux >= 6.12) for a slice of ``slice_us`` for the
    calling thread: ``sched_setattr`` with ``SCHED_OTHER``, its nice value kept and
    ``sched_runtime`` = the slice. Returns None, or why it was not applied.

    Why: EEVDF runs the eligible task with the earliest virtual deadline, which is its
    virtual start plus its slice. With the default slice (0.7-3 ms, by the number of CPUs) a
    loop that wakes while a batch task (a node's executor, the recorder) runs on each core
    often waits out that task's slice; with a short one its deadline is earlier and it
    preempts at once. The slice does not change the thread's share of the CPU (its weight,
    i.e. nice, does), and needs no privilege. Older kernels ignore ``sched_runtime`` for
    normal tasks: the slice read back with ``sched_getattr`` tells, and then this says so.
    """
    lo, hi = SLICE_RANGE_US
    calls = _SCHED_ATTR_SYSCALLS.get(platform.machine())
    if calls is None:
        return f'sched_slice_us {slice_us:g}: sched_setattr unknown on {platform.machine()}'
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        return f'sched_slice_us {slice_us:g}: the thread is not under normal scheduling'
    libc = _libc()
    runtime = int(round(min(max(slice_us, lo), hi) * 1e3))
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    attr = ctypes.create_string_buffer(
        _SCHED_ATTR.pack(_SCHED_ATTR.size, os.SCHED_OTHER, 0, nice, 0, runtime, 0, 0, 0, 0))
    if libc.syscall(calls[0], 0, attr, 0) != 0:
        return f'sched_slice_us {slice_us:g}: {os.strerror(ctypes.get_errno())}; not applied'
    got = sched_slice_ns()
    if got != runtime:
        return (f'sched_slice_us {slice_us:g}: this kernel keeps no slice per task (Linux >= '
                '6.12 does); not applied')
    return None


def sched_slice_ns(tid: int = 0) -> int | None:
    """Thread ``tid``'s (0: the caller's) slice under normal scheduling (ns) as
    ``sched_getattr`` reads it; 0 where the kernel keeps none per task; None where the call
    is unknown or fails."""
    calls = _SCHED_ATTR_SYSCALLS.get(platform.machine())
    if calls is None:
        return None
    buf = ctypes.create_string_buffer(_SCHED_ATTR.size)
    if _libc().syscall(calls[1], tid, buf, _SCHED_ATTR.size, 0) != 0:
        return None
    return int(_SCHED_ATTR.unpack(buf.raw)[5])


_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30


def set_timer_slack(slack_ns: int) -> str | None:
    """The calling thread's timer slack (``prctl(PR_SET_TIMERSLACK)``, ns): how much later
    than asked the kernel may end its sleeps, to wake several timers at once (50 us by
    default for a normal thread; SCHED_FIFO threads have none). A smaller slack wakes the
    loop closer to its deadline. Needs no privilege. Returns None, or why it failed."""
    libc = _libc()
    if libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) != 0:
        return f'timer_slack_ns {slack_ns}: {os.strerror(ctypes.get_errno())}; unchanged'
    return None


def timer_slack_ns() -> int:
    """The calling thread's timer slack (ns)."""
    return int(_libc().prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))


@functools.cache
def _libc() -> ctypes.CDLL:
    # Once per process: ``find_library`` runs ``ldconfig -p`` in a child process each time.
    return ctypes.CDLL(ctypes.util.find_library('c'), use_errno=True)


def set_parent_death_signal(signum: int) -> None:
    """``prctl(PR_SET_PDEATHSIG)``: the kernel sends the calling process ``signum`` when the
    thread that started it ends (its parent dying, killed or not)."""
    pr_set_pdeathsig = 1
    _libc().prctl(pr_set_pdeathsig, signum, 0, 0, 0)


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` (at most 15 bytes) in /proc/<pid>/task/<tid>/comm,
    so ``top -H`` and the benchmark's CPU per thread can tell the loop thread apart."""
    pr_set_name = 15
    _libc().prctl(pr_set_name, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)


def lock_all_memory() -> str | None:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)``; None, or why it failed."""
    mcl_current, mcl_future = 1, 2
    if _libc().mlockall(mcl_current | mcl_future) != 0:
        err = ctypes.get_errno()
        return (f'lock_memory: mlockall failed: {os.strerror(err)} (needs CAP_IPC_LOCK or a '
                'memlock limit, e.g. ulimit -l unlimited); memory not locked')
    return None


#: Bytes from which glibc's ``malloc`` maps a block of its own (glibc's default, kept fixed).
MMAP_THRESHOLD = 128 * 1024
_M_MMAP_THRESHOLD = -3      # mallopt parameter (malloc.h)


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``nbytes`` for this process (``mallopt``); False where
    the C library has no ``mallopt`` (not glibc: nothing to fix).

    Why: by default glibc raises the threshold to the size of every mapped block that is
    freed (up to 32 MiB), and blocks below it come from the heap from then on. A node that
    handles blocks of varying size (batches of ring records, messages) then extends its heap
    while the bytes in use stay the same: measured on ``device_driver`` over a 2-minute
    ``run circle``, the heap's system bytes grew about 8 kB/s with the bytes in use flat
    (``malloc_stats``), and its RSS with them. A fixed threshold also turns the dynamic
    adjustment of the trim threshold off; with it the driver's RSS stayed flat.
    """
    libc = _libc()
    mallopt = getattr(libc, 'mallopt', None)
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, int(nbytes)))
