"""Stopping the node processes a test started (shared by the graph tests)."""

from __future__ import annotations

import signal
import subprocess


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
