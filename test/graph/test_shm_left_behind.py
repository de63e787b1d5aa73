"""Nothing of Fast DDS stays in ``/dev/shm``: a node process stopped with SIGINT or SIGTERM
deletes its shared-memory segment itself; a graph killed with SIGKILL leaves its processes'
segments, and the next ``haptic-topology run`` removes them, and its own, while a running
process's segment stays (:mod:`haptic_topology.nodes.dds_shm`).

Only the segments of the processes a test starts are looked at (read from their
``/proc/<pid>/maps`` while they run), never a count of the folder: other programs on the
machine make and remove segments at the same time."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest
from procs import pidfd

from haptic_topology.nodes.dds_shm import SHM_DIR, cleaning, process_segments
from haptic_topology.paths import config_dir
from haptic_topology.processes import children, cmdline

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
#: Generous deadline for a node process to start (imports, discovery) on a loaded machine.
START = 90.0


def tree(pid: int) -> list[int]:
    """``pid`` and its running descendants."""
    out = [pid]
    for child in children(pid):
        out += tree(child)
    return out


class SegmentSampler:
    """The Fast DDS segments the processes of ``root``'s tree map, sampled every 50 ms in a
    thread while the tree runs: segment -> the command line of the process that mapped it."""

    def __init__(self, root: int) -> None:
        self.root = root
        self.seen: dict[str, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            for pid in tree(self.root):
                for segment in process_segments(pid):
                    self.seen.setdefault(segment, ' '.join(cmdline(pid)[:4]))

    def stop(self) -> dict[str, str]:
        self._stop.set()
        self._thread.join()
        return self.seen


def existing(segments: dict[str, str]) -> dict[str, str]:
    """Those of ``segments`` still in ``/dev/shm`` (segment or lock file)."""
    return {s: who for s, who in segments.items()
            if (SHM_DIR / s).exists() or (SHM_DIR / f'{s}_el').exists()}


def node_argv(module: str, bag: Path) -> list[str]:
    return [sys.executable, '-m', f'haptic_topology.nodes.{module}', '--ros-args',
            '--params-file', str(PARAMS), '-p', 'scenario:=circle',
            '-p', f'recorder:output:={bag}', '-p', 'device_driver:autostart:=false']


@contextmanager
def probe_node() -> Iterator[object]:
    """A node of this test process in a context of its own (a participant, so a segment of
    a process that keeps running); destroyed, and its context shut down, at the end."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node('shm_probe', context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def wait_spinning(node: object, name: str, timeout: float) -> None:
    """Wait until node ``name`` answers its ``list_parameters`` service: its process spins
    (its stop signals are handled from then on)."""
    from rcl_interfaces.srv import ListParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    assert isinstance(node, Node)
    client = node.create_client(ListParameters, f'/{name}/list_parameters')
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            if client.wait_for_service(timeout_sec=0.2):
                future = client.call_async(ListParameters.Request())
                while not future.done() and time.monotonic() < deadline:
                    executor.spin_once(timeout_sec=0.1)
                if future.done() and future.result() is not None:
                    return
        raise AssertionError(f'{name} did not answer list_parameters within {timeout} s')
    finally:
        executor.remove_node(node)
        executor.shutdown()
        node.destroy_client(client)


@pytest.mark.timeout(300)
@pytest.mark.parametrize(('module', 'name', 'sig'), [
    ('recorder', 'recorder', signal.SIGINT),
    ('device_driver', 'device_driver', signal.SIGINT),
    ('device_driver', 'device_driver', signal.SIGTERM),
    ('composed', 'recorder', signal.SIGINT),
], ids=['recorder-SIGINT', 'device_driver-SIGINT', 'device_driver-SIGTERM', 'composed-SIGINT'])
def test_a_stopped_node_process_deletes_its_segment(
        tmp_path: Path, module: str, name: str, sig: signal.Signals) -> None:
    """The recorder ended with ``os._exit`` before destroying its node, and the device
    driver's lifecycle state machine kept its rcl node (and the participant) alive."""
    proc = subprocess.Popen(node_argv(module, tmp_path / 'bag'), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    sampler = SegmentSampler(proc.pid)
    try:
        with probe_node() as probe:
            wait_spinning(probe, name, START)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        seen = sampler.stop()
    log = out.decode(errors='replace')[-2000:]
    assert proc.returncode == 0, log
    assert len(seen) == 1, (seen, log)           # one participant, one segment
    assert existing(seen) == {}, log


def ended_within(fd: int, timeout: float) -> bool:
    """Whether the process of pidfd ``fd`` ends within ``timeout`` s (``fd`` stays open)."""
    return bool(select.select([fd], [], [], timeout)[0])


def kill_all(fds: list[int]) -> None:
    """SIGKILL the processes of pidfds ``fds`` that still run (by descriptor: a number
    reused since is never hit), wait until they have ended, close the descriptors."""
    for fd in fds:
        try:
            signal.pidfd_send_signal(fd, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        assert all(ended_within(fd, 30.0) for fd in fds)
    finally:
        for fd in fds:
            os.close(fd)


def start_long_run(bag: Path) -> tuple[subprocess.Popen[bytes], SegmentSampler]:
    """``haptic-topology run circle`` for a minute, once the command and its three node
    processes each have their segment."""
    run = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', 'circle', '--duration', '60',
         '--no-plot', '--out', str(bag)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    sampler = SegmentSampler(run.pid)
    deadline = time.monotonic() + START
    while len(set(sampler.seen.values())) < 4 and time.monotonic() < deadline:
        time.sleep(0.1)
    return run, sampler


@pytest.mark.timeout(300)
def test_sigterm_of_run_stops_the_graph_and_leaves_nothing(tmp_path: Path) -> None:
    """SIGTERM ends ``run`` as Ctrl-C: it stops its nodes, each deletes its segment. (The
    command used to end at once, its nodes running on.)"""
    run, sampler = start_long_run(tmp_path / 'bag')
    fds = [fd for fd in map(pidfd, tree(run.pid)) if fd is not None]
    try:
        run.send_signal(signal.SIGTERM)
        out, _ = run.communicate(timeout=60)
        ended = [ended_within(fd, 30.0) for fd in fds]
    finally:
        kill_all(fds)
        seen = sampler.stop()
    log = out.decode(errors='replace')[-3000:]
    assert len(set(seen.values())) == 4, (seen, log)
    assert run.returncode == 128 + signal.SIGTERM, log
    assert all(ended), log                       # the nodes too
    assert existing(seen) == {}, log


@pytest.mark.timeout(300)
def test_a_killed_graphs_segments_are_removed_by_the_next_run(tmp_path: Path) -> None:
    killed, sampler = start_long_run(tmp_path / 'killed')
    # The folder's cleaner lock from before the kill to the check that the segments are
    # left: another test's run cleaning /dev/shm meanwhile would remove them first.
    with ExitStack() as stack:
        deadline = time.monotonic() + START
        while not stack.enter_context(cleaning()):
            assert time.monotonic() < deadline, 'another cleaner held /dev/shm throughout'
            time.sleep(0.05)
        try:
            fds = [fd for fd in map(pidfd, tree(killed.pid)) if fd is not None]
            kill_all(fds)
            killed.wait()
        finally:
            if killed.poll() is None:
                killed.kill()
            killed.communicate()
            left = sampler.stop()
        assert len(set(left.values())) == 4, left
        assert existing(left) == left            # SIGKILL: nothing deleted them
    with probe_node():
        live = process_segments(os.getpid())
        assert live and not live & set(left)
        run = subprocess.Popen(
            [sys.executable, '-m', 'haptic_topology.cli', 'run', 'circle', '--duration', '1',
             '--no-plot', '--out', str(tmp_path / 'next')],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        sampler = SegmentSampler(run.pid)
        try:
            out, _ = run.communicate(timeout=240)
        finally:
            if run.poll() is None:
                run.kill()
                run.communicate()
            seen = sampler.stop()
        log = out.decode(errors='replace')
        assert run.returncode == 0, log
        assert existing(left) == {}, log         # removed at the run's start
        assert existing(seen) == {}, log         # the run's own: deleted by its processes
        assert len(set(seen.values())) >= 4, seen
        assert all((SHM_DIR / s).exists() for s in live)    # a running process's stays
    assert existing(dict.fromkeys(live, 'probe')) == {}
