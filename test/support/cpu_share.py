"""Who may load the machine's cores while a wall-clock graph test runs.

A lock-step graph computes the same result on any machine however loaded (it waits for its
messages), so several can share the cores. A wall-clock graph whose assertions need the graph
to keep real time (the fault-injection run waits for the controller to be back on a *fresh*
model, which needs the VE to keep pace with the 1 kHz loop) cannot share them with a pool of
such graphs: on a slow 2-core machine four lock-step graphs beside it (about 16 node
processes) left its VE at 30 Hz and its loop at 530 Hz, and the controller never re-synced.

So they take one lock file per machine (``flock``): a pool of lock-step graphs holds it
*shared*, a wall-clock graph that needs real time holds it *exclusive*. The other pytest
worker's single-process tests still run beside either (the suite's busy-neighbour case).
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK_FILE = Path(tempfile.gettempdir()) / 'haptic_topology_cpu.lock'


@contextmanager
def cpu_share(exclusive: bool) -> Iterator[None]:
    """Hold the machine's CPU lock (see module doc) for the ``with`` body; waits for it."""
    fd = os.open(LOCK_FILE, os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)        # releases the lock (also if the process dies)
