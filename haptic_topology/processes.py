"""Child processes and their CPU time, from ``/proc`` and signals (no ROS): what the bringup,
the benchmarks and the tests share."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path
from typing import Any


def _stat_fields(path: str) -> list[str] | None:
    try:
        return Path(path).read_text().rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return None


def running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting to be reaped does not)."""
    fields = _stat_fields(f'/proc/{pid}/stat')
    return fields is not None and fields[0] != 'Z'


def cpu_seconds(pid: int, tid: int | None = None) -> float | None:
    """User + system CPU time (s) of process ``pid`` (all its threads), or of its thread
    ``tid``, from ``/proc``; None once it is gone."""
    fields = _stat_fields(f'/proc/{pid}/stat' if tid is None else f'/proc/{pid}/task/{tid}/stat')
    if fields is None:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def reaped_children_cpu_seconds(pid: int) -> float | None:
    """User + system CPU time (s) of the children of ``pid`` that have ended and that it has
    waited for (e.g. ``device_driver``'s loop process after a run), from ``/proc``; None once
    ``pid`` is gone."""
    fields = _stat_fields(f'/proc/{pid}/stat')
    if fields is None:
        return None
    return (int(fields[13]) + int(fields[14])) / os.sysconf('SC_CLK_TCK')


def process_times(pid: int) -> dict[str, float] | None:
    """``cpu_s`` (user + system, s) and ``wall_s`` (age, s) of a running process; None once
    it is gone."""
    fields = _stat_fields(f'/proc/{pid}/stat')
    try:
        uptime = float(Path('/proc/uptime').read_text().split()[0])
    except OSError:
        return None
    if fields is None:
        return None
    hz = os.sysconf('SC_CLK_TCK')
    return {'cpu_s': (int(fields[11]) + int(fields[12])) / hz,
            'wall_s': uptime - int(fields[19]) / hz}


def terminate(popen: subprocess.Popen[Any], timeout: float = 5.0,
              escalate: float = 2.0) -> int:
    """SIGINT ``popen``, then SIGTERM and SIGKILL if it has not exited after ``timeout`` /
    ``escalate`` seconds; return its exit code."""
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, escalate),
                      (signal.SIGKILL, escalate)):
        if popen.poll() is not None:
            break
        popen.send_signal(sig)
        try:
            popen.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return popen.wait()
