"""``device_driver`` with ``loop_process: true`` against real processes: either side of the
loop killed. The cycle runs in a child of the driver (no rclpy); killing the child is the
driver's fault (ERROR in ``/diagnostics``, its loop stops), killing the driver ends
the child (``PR_SET_PDEATHSIG``), which writes zero to the device first. Every wait is on
messages or processes, with a deadline; nothing is timed (``make bench`` measures how fast).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from procs import (
    describe,
    pidfd,
    stop_process,
    thread_affinities,
    thread_policies,
    wait_exit,
)

from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
WAIT = 60.0           # s: generous, a loaded machine is only slower


def _start(name: str, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', f'haptic_topology.nodes.{name}', '--ros-args', '--params-file',
         str(PARAMS), '-p', 'scenario:=circle', *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)


def _children(pid: int) -> list[int]:
    """The loop processes among ``pid``'s children (not, e.g., its resource tracker)."""
    out: list[int] = []
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            kids = [int(c) for c in (task / 'children').read_text().split()]
        except OSError:
            continue
        out += [k for k in kids if b'haptic_topology.device.loop_child' in _cmdline(k)]
    return out


def _cmdline(pid: int) -> bytes:
    """``pid``'s command line; empty once it has exited (a short-lived child of the driver
    can end between the listing of its parent's children and this read)."""
    try:
        return Path(f'/proc/{pid}/cmdline').read_bytes()
    except OSError:
        return b''


class _Watch:
    """Device states and the driver's diagnostics, on a node of this process."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, QOS_LOOP
        from haptic_topology.vocabulary import TOPIC_DIAGNOSTICS, TOPIC_STATE
        from haptic_topology_msgs.msg import DeviceState

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('loop_process_watch', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.running = 0
        self.driver: Any = None
        self.node.create_subscription(DeviceState, TOPIC_STATE, self._on_state, QOS_LOOP)
        self.node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diag,
                                      QOS_DIAGNOSTICS)
        self._idle = DeviceState.STATUS_IDLE

    def _on_state(self, msg: Any) -> None:
        if not msg.status & self._idle:
            self.running += 1

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == 'device_driver: loop':
                self.driver = st

    def wait(self, cond: Any, what: str, procs: list[subprocess.Popen[bytes]]) -> None:
        deadline = time.monotonic() + WAIT
        while not cond():
            for p in procs:
                assert p.poll() is None, f'{what}: a node died:\n{stop_process(p)[1][-3000:]}'
            assert time.monotonic() < deadline, f'{what}: not within {WAIT:g} s'
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def graph() -> Any:
    procs = [_start('ve_sim'), _start('device_driver', '-p', 'loop_process:=true')]
    watch = _Watch()
    try:
        watch.wait(lambda: watch.running >= 200, 'the loop process running', procs)
        yield procs, watch
    finally:
        watch.close()
        for p in procs:
            if p.poll() is None:
                stop_process(p)


def test_a_killed_loop_process_is_the_drivers_fault(graph: Any) -> None:
    procs, watch = graph
    driver = procs[1]
    child = _children(driver.pid)
    assert len(child) == 1, child
    os.kill(child[0], signal.SIGKILL)
    watch.wait(lambda: watch.driver is not None and watch.driver.level == b'\x02'
               and 'loop process' in watch.driver.message, 'the driver reporting the fault',
               procs)
    assert f'{child[0]} exited with code -9' in watch.driver.message
    watch.wait(lambda: watch.driver.values and any(
        kv.key == 'loop_running' and kv.value == 'false' for kv in watch.driver.values),
        'the driver inactive', procs)
    code, out = stop_process(driver)
    assert code == 0 and 'Traceback' not in out, out[-3000:]


def test_a_killed_driver_ends_its_loop_process(graph: Any) -> None:
    procs, watch = graph
    driver = procs[1]
    child = _children(driver.pid)
    assert len(child) == 1, child
    fd = pidfd(child[0])            # that process, whatever later takes its number
    driver.kill()
    driver.wait()
    assert wait_exit(fd, WAIT), f'the loop process outlived its driver: {describe(child[0])}'
    out = driver.stdout.read().decode(errors='replace') if driver.stdout else ''
    assert 'parent gone: output zeroed, device released' in out, out[-3000:]


def test_the_nodes_run_batch_and_the_loop_process_normal(graph: Any) -> None:
    """``sched_policy`` batch (default): every thread of ve_sim and of the driver's ROS side (its
    executor, DDS's threads, the publisher) is under SCHED_BATCH; the loop process, which
    the driver started, runs its cycle under normal scheduling."""
    procs, _ = graph
    ve, driver = procs
    child = _children(driver.pid)
    assert len(child) == 1, child
    for node in (ve.pid, driver.pid):
        policies = thread_policies(node)
        assert set().union(*policies.values()) == {os.SCHED_BATCH}, policies
        assert any(name.startswith('dds.') for name in policies), policies
    assert 'device_publish' in thread_policies(driver.pid)
    assert thread_policies(child[0])['device_loop'] == {os.SCHED_OTHER}


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='a partition needs two CPUs')
def test_a_cpu_partition_keeps_the_loops_core_for_the_loop_process() -> None:
    """``cpu_affinity`` (the loop process's core) with ``node_cpu_affinity`` and ve_sim's
    ``cpu_affinity`` on the other CPUs (what ``run --loop-cpu`` sets): every thread of the
    nodes, DDS's and the publisher included, stays off the loop's core, and the loop process
    runs its cycle there; the driver says so when it activates."""
    cpus = sorted(os.sched_getaffinity(0))
    loop, rest = cpus[-1], tuple(cpus[:-1])
    nodes = ','.join(map(str, rest))
    procs = [_start('ve_sim', '-p', f'cpu_affinity:=[{nodes}]'),
             _start('device_driver', '-p', 'loop_process:=true', '-p',
                    f'cpu_affinity:=[{loop}]', '-p', f'node_cpu_affinity:=[{nodes}]')]
    watch = _Watch()
    try:
        watch.wait(lambda: watch.running >= 200, 'the loop process running', procs)
        ve, driver = procs
        child = _children(driver.pid)
        assert len(child) == 1, child
        for node in (ve.pid, driver.pid):
            pinned = thread_affinities(node)
            assert set().union(*pinned.values()) == {rest}, pinned
            assert any(name.startswith('dds.') for name in pinned), pinned
        assert 'device_publish' in thread_affinities(driver.pid)
        assert thread_affinities(child[0])['device_loop'] == {(loop,)}
        _, out = stop_process(driver)
        assert (f'lmi_controller hosted (loop process {child[0]} on CPUs [{loop}], this node '
                f'on CPUs [{nodes.replace(",", ", ")}])') in out, out[-3000:]
    finally:
        watch.close()
        for p in procs:
            if p.poll() is None:
                stop_process(p)
