"""Fast DDS's files in ``/dev/shm``: which there are, and removing those of ended processes.

Every ROS 2 process on Fast DDS with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (the graph's
default, :mod:`haptic_topology.nodes.dds_env`) opens a shared-memory transport: rmw_fastrtps
adds it to the participant whatever the XML profile says. The transport creates one segment
per participant, ``fastrtps_<16 hex digits>`` (about 549 kB), and a lock file beside it,
``fastrtps_<16 hex digits>_el``, which the creating process holds locked (``flock``,
exclusive) for as long as the segment lives: it locks the file first, then creates the
segment. The participant removes both when it is deleted (all nodes of its rclpy context
destroyed). A process that ends without that (SIGKILL, a crash, ``os._exit`` with a node
alive) leaves both behind, and nothing else removes them: they hold memory until reboot.

A segment is stale when its lock file is not locked: its creator has ended (the kernel
releases an ``flock`` with the last descriptor). That is the rule of Fast DDS's own
``fastdds shm clean`` and of its transport, which removes a peer's segment it had opened once
the peer's lock is free. :func:`remove_stale_segments` applies it while holding the lock
itself, so a process that happens to create a segment of the same name at that moment fails
to lock it and picks another name (as Fast DDS does on a collision); a segment whose lock is
held, by whatever process on the machine, is never touched.

One cleaner at a time per folder: :func:`remove_stale_segments` runs only while it holds the
folder's cleaner lock (:func:`cleaning`, a file in the temporary directory); another cleaner
that finds it held leaves the folder to the holder. A program that must see a killed
process's segments before they are removed (a test of this cleanup) holds that lock meanwhile.

No ROS import here: the bringup and the test session use it before and after any node runs.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: Where Fast DDS keeps its shared memory and lock files on Linux.
SHM_DIR = Path('/dev/shm')
#: The lock file of a participant's segment (Fast DDS 2.x, ``SharedMemManager``).
SEGMENT_LOCK = re.compile(r'^fastrtps_[0-9a-z]{16}_el$')
#: Every kind of entry Fast DDS makes there: segments and their locks, port segments
#: (``fastrtps_port<N>``) and their locks, port mutexes (``sem.fastrtps_port<N>_mutex``)
#: and data-sharing segments.
FASTDDS_ENTRY = re.compile(r'^(fastrtps_|sem\.fastrtps_|fast_datasharing_)')


def fastdds_entries(shm_dir: Path = SHM_DIR) -> set[str]:
    """The names of Fast DDS's entries in ``shm_dir`` (:data:`FASTDDS_ENTRY`)."""
    try:
        return {n for n in os.listdir(shm_dir) if FASTDDS_ENTRY.match(n)}
    except FileNotFoundError:
        return set()


def lock_held(path: Path) -> bool:
    """Whether a process holds ``path`` locked (``flock``); False when the file is gone. The
    test takes the lock for an instant and releases it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def stale_segments(shm_dir: Path = SHM_DIR) -> set[str]:
    """The segments in ``shm_dir`` whose creator has ended (their lock file is not locked),
    by segment name; a segment of a running process is never among them."""
    return {lock[:-3] for lock in fastdds_entries(shm_dir)
            if SEGMENT_LOCK.match(lock) and not lock_held(shm_dir / lock)}


def cleaner_lock(shm_dir: Path = SHM_DIR) -> Path:
    """The cleaner lock file of ``shm_dir`` (module doc), in the temporary directory."""
    key = hashlib.blake2b(str(shm_dir.resolve()).encode(), digest_size=8).hexdigest()
    return Path(tempfile.gettempdir()) / f'haptic_topology_shm_cleaner_{key}.lock'


@contextmanager
def cleaning(shm_dir: Path = SHM_DIR) -> Iterator[bool]:
    """Hold the cleaner lock of ``shm_dir`` while the block runs, if no other process holds
    it: yields whether this process does (it never waits)."""
    fd = os.open(cleaner_lock(shm_dir), os.O_CREAT | os.O_RDWR, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True
    finally:
        os.close(fd)


def remove_stale_segments(shm_dir: Path = SHM_DIR) -> list[str]:
    """Remove every stale segment of ``shm_dir`` and its lock file; return the segments'
    names (sorted). Each is removed while this process holds its lock; an entry locked by
    another process, or that this user may not remove, stays. Nothing is removed while
    another process holds the folder's cleaner lock (:func:`cleaning`)."""
    with cleaning(shm_dir) as mine:
        return _remove_stale(shm_dir) if mine else []


def _remove_stale(shm_dir: Path) -> list[str]:
    removed: list[str] = []
    for lock in sorted(fastdds_entries(shm_dir)):
        if not SEGMENT_LOCK.match(lock):
            continue
        try:
            fd = os.open(shm_dir / lock, os.O_RDONLY)
        except OSError:
            continue            # gone meanwhile: its owner (or another cleaner) removed it
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            segment = lock[:-3]
            try:
                (shm_dir / segment).unlink(missing_ok=True)
                (shm_dir / lock).unlink()
            except OSError:
                continue        # another user's (/dev/shm is sticky): theirs to remove
            removed.append(segment)
        except OSError:
            continue            # locked: its process runs
        finally:
            os.close(fd)
    return removed


def process_segments(pid: int, shm_dir: Path = SHM_DIR) -> set[str]:
    """The Fast DDS segments that process ``pid`` has mapped, by name: the one of each of
    its rclpy contexts, and those of the peers it reads over shared memory (none with the
    graph's default profile, user data over UDP); empty once it has ended."""
    prefix = f'{shm_dir}/'
    try:
        with open(f'/proc/{pid}/maps', encoding='utf-8', errors='replace') as maps:
            paths = {line.split(maxsplit=5)[-1].strip() for line in maps if prefix in line}
    except OSError:
        return set()
    names = {p[len(prefix):] for p in paths
             if p.startswith(prefix) and not p.endswith(' (deleted)')}
    return {n for n in names if FASTDDS_ENTRY.match(n)}

