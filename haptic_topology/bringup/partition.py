"""``haptic-topology run --loop-cpu auto`` (the default): a core for the loop process only
while other software keeps the machine busy.

Why: on 2 cores a busy program pushes the graph's node threads onto the CPU the loop process
runs on, and one of theirs in a system call (DDS sending or receiving) is not preempted before
it returns (a kernel without full preemption): beside one busy process the loop answers
96-98 % of its cycles. With the loop process alone on one CPU and every other thread of the
graph on the others (``--loop-cpu N``) it answers 99.7-99.8 %; but on an otherwise idle
machine that pinning costs 0.1-0.2 % of the cycles, because the loop can no longer move away
from the system's own short bursts on its CPU. So :class:`Partitioner` watches the machine
and pins only while it is busy.

Every :data:`SAMPLE_PERIOD` s it reads the CPUs' busy time (``/proc/stat``) and the graph's
own CPU time (every process of the run, the loop process and ``run`` itself); the
difference is the load of other software, in cores. :class:`PartitionPolicy` decides from
those samples alone (no clock, no ``/proc``: its tests are exact): after
:data:`ENGAGE_SAMPLES` samples in a row with at least :data:`ENGAGE_LOAD` cores of other
load it keeps for the loop the CPU that was least busy in the last sample and puts every
other thread of the graph on the other CPUs; after :data:`RELEASE_SAMPLES` samples in a row
below :data:`RELEASE_LOAD` cores it gives every thread back all the CPUs ``run`` started
with. The pinning needs no privilege: the processes are this user's (sched_setaffinity(2));
threads that start later inherit their creator's CPUs, and a sample pins the threads that
are new since the last one.

Nothing here is on the loop's deadline path: the sampling (about 1 ms of CPU per sample
on a machine with 60 processes) runs in a thread of ``run`` at nice +10 under
``SCHED_BATCH``, as the nodes' threads.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from haptic_topology.processes import Periodic, children, stat_fields, thread_ids

#: Seconds between two samples.
SAMPLE_PERIOD = 0.5
#: Cores of other software's load at which the loop gets a CPU of its own...
ENGAGE_LOAD = 0.5
#: ... once that many samples in a row have at least it (1 s).
ENGAGE_SAMPLES = 2
#: Cores of other load below which the graph gets every CPU back...
RELEASE_LOAD = 0.25
#: ... once that many samples in a row are below it (5 s).
RELEASE_SAMPLES = 10


@dataclass(frozen=True)
class CpuSample:
    """One reading at ``t`` (s, monotonic): ``procs`` maps each process outside the graph to
    its CPU time (s: user + system, its ended children that it has waited for included) and
    the CPU it last ran on."""

    t: float
    procs: dict[int, tuple[float, int]]


@dataclass(frozen=True)
class Decision:
    """A change of the pinning: ``loop_cpu`` the CPU kept for the loop process (None: every
    thread on every CPU again), ``others`` the CPUs of every other thread of the graph,
    ``load`` the other software's load (cores) that made it, ``t`` (s) when."""

    t: float
    loop_cpu: int | None
    others: tuple[int, ...]
    load: float


@dataclass
class PartitionPolicy:
    """Decides when the loop gets a CPU of its own, from consecutive :class:`CpuSample` s
    (see module doc). ``cpus``: the CPUs the graph may use; with fewer than two it never
    pins."""

    cpus: tuple[int, ...]
    engage_load: float = ENGAGE_LOAD
    engage_samples: int = ENGAGE_SAMPLES
    release_load: float = RELEASE_LOAD
    release_samples: int = RELEASE_SAMPLES
    loop_cpu: int | None = None
    _run: int = 0
    _last: CpuSample | None = field(default=None, repr=False)

    def other_load(self, before: CpuSample, after: CpuSample) -> tuple[float, dict[int, float]]:
        """Cores of load outside the graph between two samples, in all and by the CPU each
        process last ran on (a process new since ``before`` counts all its CPU time; one
        gone counts nothing more)."""
        wall = after.t - before.t
        per_cpu = dict.fromkeys(self.cpus, 0.0)
        if wall <= 0.0:
            return 0.0, per_cpu
        for pid, (seconds, cpu) in after.procs.items():
            used = seconds - before.procs.get(pid, (0.0, cpu))[0]
            if used > 0.0 and cpu in per_cpu:
                per_cpu[cpu] += used / wall
        return sum(per_cpu.values()), per_cpu

    def step(self, sample: CpuSample) -> Decision | None:
        """Take the next sample; return the change of the pinning it makes, if any."""
        before, self._last = self._last, sample
        if before is None or len(self.cpus) < 2:
            return None
        load, per_cpu = self.other_load(before, sample)
        if self.loop_cpu is None:
            self._run = self._run + 1 if load >= self.engage_load else 0
            if self._run < self.engage_samples:
                return None
            # The CPU with the least of the other load (the highest-numbered of equals).
            self.loop_cpu = min(self.cpus, key=lambda c: (per_cpu[c], -c))
            self._run = 0
            return Decision(sample.t, self.loop_cpu,
                            tuple(c for c in self.cpus if c != self.loop_cpu), round(load, 3))
        self._run = self._run + 1 if load < self.release_load else 0
        if self._run < self.release_samples:
            return None
        self.loop_cpu, self._run = None, 0
        return Decision(sample.t, None, self.cpus, round(load, 3))


def descendants(pid: int) -> set[int]:
    """Process ``pid`` and all its running descendants."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        if p not in out:
            out.add(p)
            todo += children(p)
    return out


def other_processes(graph: set[int]) -> dict[int, tuple[float, int]]:
    """Every process on the machine outside ``graph``: its CPU time (s, user + system of
    it and of its ended children it has waited for) and the CPU it last ran on."""
    hz = os.sysconf('SC_CLK_TCK')
    out: dict[int, tuple[float, int]] = {}
    for name in os.listdir('/proc'):
        if not name.isdigit() or int(name) in graph:
            continue
        f = stat_fields(f'/proc/{name}/stat')
        if f is not None and len(f) > 36:
            out[int(name)] = (sum(int(x) for x in f[11:15]) / hz, int(f[36]))
    return out


def pin_threads(pid: int, cpus: Sequence[int], done: set[int]) -> str | None:
    """Pin every thread of process ``pid`` not in ``done`` to ``cpus`` and add it to ``done``
    (which keeps only threads that still run); threads that end meanwhile are skipped.
    Returns None, or why a thread could not be pinned (e.g. another user's process)."""
    tids = thread_ids(pid)
    done.intersection_update(tids)
    for tid in tids:
        if tid in done:
            continue
        try:
            os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:
            continue
        except OSError as exc:
            return f'process {pid}: {exc.strerror}'
        done.add(tid)
    return None


class Partitioner(Periodic):
    """Samples the machine every :data:`SAMPLE_PERIOD` s in a thread of its own and pins the
    graph as :class:`PartitionPolicy` decides (see module doc).

    ``pids()``: the graph's node processes; ``loop_pid()``: the loop process (None while
    there is none); ``own``: the process that started them (default: this one, ``run``),
    pinned as a node; the graph is it and all its descendants. ``say``: prints each change;
    ``read``: the reading (default :meth:`machine`; tests give their own)."""

    name = 'loop_cpu_auto'

    def __init__(self, pids: Callable[[], list[int]], loop_pid: Callable[[], int | None],
                 say: Callable[[str], None] = print,
                 read: Callable[[], CpuSample] | None = None, own: int | None = None) -> None:
        super().__init__(SAMPLE_PERIOD)
        self._pids, self._loop_pid, self._say = pids, loop_pid, say
        self.own = os.getpid() if own is None else own
        self.cpus = tuple(sorted(os.sched_getaffinity(self.own)))
        self.policy = PartitionPolicy(self.cpus)
        self._read = read or self.machine
        self.decisions: list[Decision] = []
        self._pinned: dict[int, set[int]] = {}   # pid -> threads pinned under the decision
        self._refused: set[int] = set()          # processes said once not to be pinnable

    def machine(self) -> CpuSample:
        """The reading of this machine now (``/proc``)."""
        return CpuSample(time.monotonic() - self._t0,
                         other_processes(descendants(self.own)))

    def begin(self) -> None:
        """After the graph's own threads, as the nodes' (a thread's own values)."""
        try:
            os.setpriority(os.PRIO_PROCESS, 0, min(19, os.getpriority(os.PRIO_PROCESS, 0) + 10))
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
        except OSError:
            pass

    def sample(self) -> None:
        """One sample: decide, and pin the graph's threads as the decision in force says."""
        decision = self.policy.step(self._read())
        if decision is not None:
            self.decisions.append(decision)
            self._pinned.clear()
            if decision.loop_cpu is None:
                self._say(f'loop CPU: other software\'s load down to {decision.load:.2f} '
                          f'cores; every thread of the graph on CPUs {list(self.cpus)} again')
            else:
                self._say(f'loop CPU: other software keeps {decision.load:.2f} cores busy; '
                          f'loop process alone on CPU {decision.loop_cpu}, every other thread '
                          f'of the graph on CPUs {list(decision.others)}')
        self.apply()

    def apply(self) -> None:
        """Pin the threads new since the last call (all, after a decision)."""
        if not self.decisions:
            return
        last = self.decisions[-1]
        loop = self._loop_pid()
        pids = [self.own, *self._pids(), *([loop] if loop is not None else [])]
        self._pinned = {pid: self._pinned.get(pid, set()) for pid in pids}
        for pid in pids:
            if last.loop_cpu is None:
                cpus: Sequence[int] = self.cpus
            else:
                cpus = [last.loop_cpu] if pid == loop else last.others
            why = pin_threads(pid, cpus, self._pinned[pid])
            if why is not None and pid not in self._refused:
                self._refused.add(pid)
                self._say(f'loop CPU: cannot pin {why}')

    def report(self) -> list[dict[str, object]]:
        """The decisions, for ``summary.json``: ``t_s`` (from :meth:`start`), ``loop_cpu``
        (None: unpinned), ``other_load_cores``."""
        return [{'t_s': round(d.t, 2), 'loop_cpu': d.loop_cpu, 'other_load_cores': d.load}
                for d in self.decisions]
