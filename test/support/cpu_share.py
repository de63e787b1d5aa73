"""Who may load the machine's cores while a wall-clock graph test runs.

A lock-step graph computes the same result on any machine however loaded (it waits for its
messages), so several can share the cores. A wall-clock graph whose assertions need the graph
to keep real time (the fault-injection run waits for the controller to be back on a *fresh*
model, which needs the VE to keep pace with the 1 kHz loop) cannot share them with anything
else of the suite: on a slow 2-core machine four lock-step graphs beside it left its VE at
30 Hz and its loop at 530 Hz, and wall-clock graphs of the other pytest worker beside it left
its VE at 29 Hz; either way the controller never re-synced.

So one lock file per machine (``flock``) says who runs: every test holds it *shared* while it
runs (``test/conftest.py``), a test marked ``whole_machine`` holds it *exclusive* for the part
that needs real time. The exclusive holder goes first: while it waits, no new shared holder
starts (a second lock file, the turnstile), so the other worker's tests pause until it is done.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK_FILE = Path(tempfile.gettempdir()) / 'haptic_topology_cpu.lock'
TURNSTILE_FILE = Path(tempfile.gettempdir()) / 'haptic_topology_cpu.turnstile'


@contextmanager
def cpu_share(exclusive: bool) -> Iterator[None]:
    """Hold the machine's CPU lock (see module doc) for the ``with`` body; waits for it."""
    fd = os.open(LOCK_FILE, os.O_CREAT | os.O_RDWR, 0o666)
    try:
        # An exclusive taker holds the turnstile until it has the lock, so shared takers
        # queue behind it instead of overtaking it for ever.
        gate = os.open(TURNSTILE_FILE, os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(gate, fcntl.LOCK_EX)
            if exclusive:
                fcntl.flock(fd, fcntl.LOCK_EX)
        finally:
            os.close(gate)
        if not exclusive:
            fcntl.flock(fd, fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)        # releases the lock (also if the process dies)
