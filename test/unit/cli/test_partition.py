"""``run --loop-cpu auto``: when the loop gets a CPU of its own (the policy, from given
samples: exact), what counts as other software's load (real processes), and the pinning of
real processes' threads as the decisions say."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from procs import thread_affinities

from haptic_topology.bringup.options import loop_cpu_choice
from haptic_topology.bringup.partition import (
    ENGAGE_SAMPLES,
    RELEASE_SAMPLES,
    SAMPLE_PERIOD,
    CpuSample,
    Decision,
    Partitioner,
    PartitionPolicy,
    descendants,
    other_processes,
)
from haptic_topology.errors import ConfigError
from haptic_topology.paths import config_dir


class Machine:
    """Samples of a made-up machine: processes by pid with their CPU time and last CPU."""

    def __init__(self) -> None:
        self.t = 0.0
        self.procs: dict[int, tuple[float, int]] = {}

    def run(self, cores: dict[int, tuple[float, int]], seconds: float = SAMPLE_PERIOD
            ) -> CpuSample:
        """``seconds`` pass with process ``pid`` using ``cores`` on CPU ``cpu``."""
        self.t += seconds
        for pid, (load, cpu) in cores.items():
            self.procs[pid] = (self.procs.get(pid, (0.0, cpu))[0] + load * seconds, cpu)
        return CpuSample(self.t, dict(self.procs))


def test_the_loop_gets_the_idle_cpu_after_two_busy_samples_and_gives_it_back_after_ten_calm(
        ) -> None:
    policy, m = PartitionPolicy((0, 1)), Machine()
    assert policy.step(m.run({1: (0.02, 1)})) is None              # the first: nothing to diff
    assert [policy.step(m.run({1: (0.02, 1)})) for _ in range(20)] == [None] * 20   # idle
    assert policy.step(m.run({7: (1.0, 0)})) is None                # one busy sample
    assert policy.step(m.run({7: (0.1, 0)})) is None                # ... then calm: start over
    assert policy.step(m.run({7: (1.0, 0)})) is None
    assert policy.step(m.run({7: (1.0, 0)})) == Decision(m.t, 1, (0,), 1.0)
    assert policy.loop_cpu == 1
    # Busy goes on: nothing changes; calm for nine samples, one busy, then ten calm.
    assert [policy.step(m.run({7: (1.0, 0)})) for _ in range(5)] == [None] * 5
    assert [policy.step(m.run({7: (0.2, 0)})) for _ in range(RELEASE_SAMPLES - 1)] == \
        [None] * (RELEASE_SAMPLES - 1)
    assert policy.step(m.run({7: (0.3, 0)})) is None                # not below 0.25 cores
    calm = [policy.step(m.run({7: (0.2, 0)})) for _ in range(RELEASE_SAMPLES)]
    assert calm[:-1] == [None] * (RELEASE_SAMPLES - 1)
    assert calm[-1] == Decision(m.t, None, (0, 1), 0.2)
    assert policy.loop_cpu is None
    assert ENGAGE_SAMPLES == 2


def test_the_loop_cpu_is_the_one_with_least_of_the_other_load() -> None:
    policy, m = PartitionPolicy((0, 1, 2)), Machine()
    policy.step(m.run({5: (0.0, 0), 6: (0.0, 2)}))
    policy.step(m.run({5: (0.5, 0), 6: (0.25, 2), 8: (0.25, 1)}))
    assert policy.step(m.run({5: (0.5, 0), 6: (0.25, 2), 8: (0.125, 1)})) == \
        Decision(m.t, 1, (0, 2), 0.875)
    # Equal loads: the highest-numbered CPU.
    policy, m = PartitionPolicy((0, 1)), Machine()
    for _ in range(ENGAGE_SAMPLES):
        policy.step(m.run({5: (0.5, 0), 6: (0.5, 1)}))
    assert policy.step(m.run({5: (0.5, 0), 6: (0.5, 1)})) == Decision(m.t, 1, (0,), 1.0)


def test_what_counts_as_other_load() -> None:
    policy = PartitionPolicy((0, 1))
    before = CpuSample(1.0, {5: (2.0, 0), 6: (3.0, 1), 9: (1.0, 1)})
    # 5: 0.25 s more; 6: gone (nothing); 7: new, all its 0.1 s; 8: on a CPU the graph
    # cannot use (not counted); 9: unchanged.
    after = CpuSample(1.5, {5: (2.25, 0), 7: (0.1, 1), 8: (4.0, 3), 9: (1.0, 0)})
    assert policy.other_load(before, after) == (0.25 / 0.5 + 0.1 / 0.5,
                                                {0: 0.25 / 0.5, 1: 0.1 / 0.5})
    assert policy.other_load(after, after) == (0.0, {0: 0.0, 1: 0.0})


def test_one_cpu_is_never_partitioned() -> None:
    policy, m = PartitionPolicy((0,)), Machine()
    assert [policy.step(m.run({7: (1.0, 0)})) for _ in range(10)] == [None] * 10


_BURN = '''
import sys, time
while time.process_time() < float(sys.argv[1]):
    pass
print(time.process_time(), flush=True)
sys.stdin.read()
'''


def test_other_load_is_every_process_outside_the_graph_with_its_cpu_time() -> None:
    """A child of this process that used 0.2 s of CPU: outside the graph this process and
    its descendants make, it counts with at least that much (``/proc`` truncates user and
    system time to clock ticks each) on the CPU it last ran on; inside it, not at all."""
    child = subprocess.Popen([sys.executable, '-c', _BURN, '0.2'], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        used = child.stdout.readline()
        graph = descendants(os.getpid())
        assert {os.getpid(), child.pid} <= graph
        assert child.pid not in other_processes(graph)
        seconds, cpu = other_processes({os.getpid()})[child.pid]
        assert seconds >= float(used) - 2.0 / os.sysconf('SC_CLK_TCK')   # user, system
        assert cpu in os.sched_getaffinity(child.pid)
        assert os.getpid() not in other_processes({os.getpid()})
    finally:
        child.communicate('')


_THREADS = '''
import subprocess, sys, threading
for _ in range(3):
    threading.Thread(target=sys.stdin.read, daemon=True).start()
loop = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'],
                        stdin=subprocess.PIPE)
print(loop.pid, flush=True)
sys.stdin.read()
loop.communicate(b'')
'''


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='needs 2 CPUs to partition')
def test_the_decisions_pin_every_thread_of_real_processes_and_unpin_them() -> None:
    """Real processes stand in for ``run`` (``own``), a node with threads and its loop
    process; the samples are given (a busy machine, then a calm one)."""
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    own = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'],
                           stdin=subprocess.PIPE)
    node = subprocess.Popen([sys.executable, '-c', _THREADS], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE)
    try:
        assert node.stdout is not None
        loop = int(node.stdout.readline())
        m, said = Machine(), []
        busy = {99: (1.0, cpus[0])}
        samples = iter([m.run(busy) for _ in range(ENGAGE_SAMPLES + 1)]
                       + [m.run({99: (0.0, cpus[0])}) for _ in range(RELEASE_SAMPLES)])
        part = Partitioner(lambda: [node.pid], lambda: loop, said.append,
                           read=lambda: next(samples), own=own.pid)
        for _ in range(ENGAGE_SAMPLES + 1):
            part.sample()
        rest = tuple(c for c in cpus if c != cpus[-1])
        assert said == [f'loop CPU: other software keeps 1.00 cores busy; loop process alone '
                        f'on CPU {cpus[-1]}, every other thread of the graph on CPUs '
                        f'{list(rest)}']
        assert set().union(*thread_affinities(loop).values()) == {(cpus[-1],)}
        node_threads = thread_affinities(node.pid)
        assert sum(map(len, node_threads.values())) >= 1
        assert set().union(*node_threads.values()) == {rest}
        assert set().union(*thread_affinities(own.pid).values()) == {rest}
        for _ in range(RELEASE_SAMPLES):
            part.sample()
        assert said[1:] == [f'loop CPU: other software\'s load down to 0.00 cores; every '
                            f'thread of the graph on CPUs {list(cpus)} again']
        for pid in (loop, node.pid, own.pid):
            assert set().union(*thread_affinities(pid).values()) == {cpus}
        assert part.report() == [
            {'t_s': round(m.t - RELEASE_SAMPLES * SAMPLE_PERIOD, 2), 'loop_cpu': cpus[-1],
             'other_load_cores': 1.0},
            {'t_s': round(m.t, 2), 'loop_cpu': None, 'other_load_cores': 0.0}]
    finally:
        for p in (node, own):
            p.communicate(b'')


def test_loop_cpu_is_auto_where_the_loop_process_runs_on_the_wall_clock_and_nothing_pins(
        tmp_path: Path) -> None:
    params = config_dir() / 'haptic_topology.yaml'
    assert loop_cpu_choice(None, 'hosted', 'wall', params, []) == 'auto'
    assert loop_cpu_choice(None, 'hosted', 'wall', params,
                           ['ve_sim:cpu_affinity:=[-1]', 've_sim:nice:=0']) == 'auto'
    for layout, clock in (('separate', 'wall'), ('thread', 'wall'), ('composed', 'wall'),
                          ('hosted', 'lockstep')):
        assert loop_cpu_choice(None, layout, clock, params, []) is None
    assert loop_cpu_choice(None, 'hosted', 'wall', params, ['ve_sim:cpu_affinity:=[0]']) is None
    assert loop_cpu_choice(None, 'hosted', 'wall', params, ['recorder:sched_policy:=idle']) \
        is None
    assert loop_cpu_choice(None, 'hosted', 'wall', params,
                           ['recorder:sched_policy:=other']) == 'auto'
    for node, name, value in (('device_driver', 'cpu_affinity', [1]),
                              ('ve_sim', 'sched_policy', 'idle')):
        doc = yaml.safe_load(params.read_text())
        doc[node]['ros__parameters'][name] = value
        pinned = tmp_path / f'{name}.yaml'
        pinned.write_text(yaml.safe_dump(doc))
        assert loop_cpu_choice(None, 'hosted', 'wall', pinned, []) is None
    assert loop_cpu_choice('off', 'hosted', 'wall', params, []) is None
    assert loop_cpu_choice('auto', 'hosted', 'wall', pinned, []) == 'auto'
    assert loop_cpu_choice('1', 'hosted', 'wall', params, []) == 1
    with pytest.raises(ConfigError, match=r'^--loop-cpu: auto needs --layout hosted and '
                       r'--clock wall, got --layout separate --clock wall$'):
        loop_cpu_choice('auto', 'separate', 'wall', params, [])
    with pytest.raises(ConfigError, match=r"^--loop-cpu: expected a CPU number, auto or off, "
                       r"got 'one'$"):
        loop_cpu_choice('one', 'hosted', 'wall', params, [])
