"""Stopping the node processes a test started, and waiting for a process that is not a child
(shared by the graph tests)."""

from __future__ import annotations

import os
import select
import signal
import subprocess
from pathlib import Path


def stop_process(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> tuple[int | None, str]:
    """SIGINT ``proc`` (as Ctrl-C would), wait up to ``timeout`` s, else SIGKILL; return its
    exit status (None: it had ended before, so its status is not the stop's) and its output."""
    alive = proc.poll() is None
    if alive:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return (proc.returncode if alive else None), out.decode(errors='replace')


def pidfd(pid: int) -> int | None:
    """A descriptor of process ``pid`` itself (``os.pidfd_open``), to wait for its exit even
    once its number is reused; None when it is gone already."""
    try:
        return os.pidfd_open(pid)
    except ProcessLookupError:
        return None


def wait_exit(fd: int | None, timeout: float) -> bool:
    """Whether the process of ``fd`` (:func:`pidfd`; None: gone) exits within ``timeout``
    s (readable once it has ended, reaped or not). Closes ``fd``."""
    if fd is None:
        return True
    try:
        return bool(select.select([fd], [], [], timeout)[0])
    finally:
        os.close(fd)


def describe(pid: int) -> str:
    """``/proc`` state and command line of ``pid`` (for a failure message)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text().split(') ', 1)[-1][:40]
        cmd = Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode()[:200]
        wchan = Path(f'/proc/{pid}/wchan').read_text()
    except OSError:
        return f'{pid}: gone'
    return f'{pid}: state {stat!r}, wchan {wchan!r}, cmdline {cmd!r}'


def thread_policies(pid: int) -> dict[str, set[int]]:
    """The scheduling policies (``os.SCHED_*``) of process ``pid``'s threads, by thread name."""
    out: dict[str, set[int]] = {}
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            name = (task / 'comm').read_text().strip()
            out.setdefault(name, set()).add(os.sched_getscheduler(int(task.name)))
        except OSError:
            continue            # the thread ended meanwhile
    return out


def thread_affinities(pid: int) -> dict[str, set[tuple[int, ...]]]:
    """The CPUs (sorted) each thread of process ``pid`` may run on, by thread name."""
    out: dict[str, set[tuple[int, ...]]] = {}
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            name = (task / 'comm').read_text().strip()
            out.setdefault(name, set()).add(tuple(sorted(os.sched_getaffinity(int(task.name)))))
        except OSError:
            continue            # the thread ended meanwhile
    return out
