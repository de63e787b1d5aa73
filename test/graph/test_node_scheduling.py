"""The scheduling of the nodes off the deadline path (``nice``, ``sched_policy``), read back
from the kernel for every thread of a real ``recorder`` process: the node says in its log
how it runs, and its threads, DDS's included, run so."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from procs import thread_affinities, thread_policies

pytestmark = pytest.mark.graph

WAIT = 60.0           # s: generous, a loaded machine is only slower


def _normal() -> None:
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _recorder_scheduling(tmp_path: Path, *params: str,
                         read: Callable[[int], dict[str, set[Any]]] = thread_policies
                         ) -> tuple[str, dict[str, set[Any]]]:
    """Start a recorder with ``params``; its log line on scheduling and what ``read`` gives
    for its threads (their policies) once it has said it."""
    args = [f'output:={tmp_path / "bag"}', *params]
    proc = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.recorder', '--ros-args',
         *[x for a in args for x in ('-p', a)]],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED='1'), start_new_session=True,
        preexec_fn=_normal)     # whatever this test's own class is
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + WAIT
        seen: list[str] = []
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            seen.append(line)
            if 'nice +' in line:
                return line.strip(), read(proc.pid)
            assert line or proc.poll() is None, ''.join(seen)[-3000:]
        raise AssertionError(f'no scheduling line within {WAIT:g} s:\n{"".join(seen)[-3000:]}')
    finally:
        proc.terminate()
        proc.wait(WAIT)


def test_a_recorder_runs_every_thread_batch_and_at_its_nice(tmp_path: Path) -> None:
    line, policies = _recorder_scheduling(tmp_path)
    assert line.endswith('nice +10, SCHED_BATCH'), line
    assert any(name.startswith('dds.') for name in policies), policies
    assert set().union(*policies.values()) == {os.SCHED_BATCH}, policies


def test_sched_policy_idle_puts_every_thread_under_sched_idle(tmp_path: Path) -> None:
    line, policies = _recorder_scheduling(tmp_path, 'sched_policy:=idle')
    assert line.endswith('nice +10, SCHED_IDLE'), line
    assert set().union(*policies.values()) == {os.SCHED_IDLE}, policies


def test_sched_policy_other_keeps_normal_scheduling(tmp_path: Path) -> None:
    line, policies = _recorder_scheduling(tmp_path, 'sched_policy:=other', 'nice:=0')
    assert line.endswith('nice +0'), line
    assert set().union(*policies.values()) == {os.SCHED_OTHER}, policies


def test_cpu_affinity_pins_every_thread_and_the_log_says_so(tmp_path: Path) -> None:
    cpu = max(os.sched_getaffinity(0))
    line, pinned = _recorder_scheduling(tmp_path, f'cpu_affinity:=[{cpu}]',
                                        read=thread_affinities)
    assert line.endswith(f'nice +10, SCHED_BATCH, CPUs [{cpu}]'), line
    assert any(name.startswith('dds.') for name in pinned), pinned
    assert set().union(*pinned.values()) == {(cpu,)}, pinned
