"""What a test session leaves of Fast DDS in ``/dev/shm`` (``test/conftest.py`` runs it in the
session's controlling process: with pytest-xdist, once, after every worker has ended).

At the start the session removes the stale segments already there (those of ended
processes, :func:`~haptic_topology.nodes.dds_shm.remove_stale_segments`) and notes the Fast
DDS entries present; its processes (workers, nodes, peers) inherit :data:`SESSION_ENV`. At the
end it removes the stale segments again (the nodes its tests killed with SIGKILL left theirs)
and reports as left behind every Fast DDS entry not there at the start that is

- mapped by a running process of this session (one that carries its :data:`SESSION_ENV`), or
- in use by no running process: a port, mutex or data-sharing file of an ended process, which
  the removal leaves alone, or a segment it could not remove.

An entry another program on the machine holds (another test session, a run) is not counted:
its lock is held or it is mapped by that program."""

from __future__ import annotations

import os
import re
import secrets
from pathlib import Path

from haptic_topology.nodes.dds_shm import (
    SHM_DIR,
    fastdds_entries,
    lock_held,
    process_segments,
    remove_stale_segments,
)

#: Environment variable naming the session; its processes inherit it.
SESSION_ENV = 'HAPTIC_TEST_SESSION'
_BASE = re.compile(r'^(?:sem\.)?(.*?)(?:_el|_sl|_mutex)?$')


def begin() -> tuple[str, list[str], set[str]]:
    """Start of the session: its token (set in ``os.environ``), the stale segments removed
    and the Fast DDS entries present now."""
    token = secrets.token_hex(8)
    os.environ[SESSION_ENV] = token
    removed = remove_stale_segments()
    return token, removed, fastdds_entries()


def _session_processes(token: str) -> dict[int, str]:
    """Running processes carrying the session's token: pid -> command line."""
    out: dict[int, str] = {}
    marker = f'{SESSION_ENV}={token}'.encode()
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            environ = Path(f'/proc/{entry}/environ').read_bytes()
            command = Path(f'/proc/{entry}/cmdline').read_bytes()
        except OSError:
            continue
        if marker in environ.split(b'\0'):
            out[int(entry)] = command.replace(b'\0', b' ').decode(errors='replace')[:120]
    return out


def _mapped_by_anyone() -> set[str]:
    out: set[str] = set()
    for entry in os.listdir('/proc'):
        if entry.isdigit():
            out |= process_segments(int(entry))
    return out


def end(token: str, present: set[str]) -> tuple[list[str], dict[str, str]]:
    """End of the session: the stale segments removed now, and what the session leaves
    behind (entry -> why)."""
    removed = remove_stale_segments()
    uid = os.getuid()
    new: set[str] = set()
    for name in fastdds_entries() - present:
        try:
            if os.stat(SHM_DIR / name).st_uid == uid:     # another user's are theirs
                new.add(name)
        except OSError:
            continue                                    # gone meanwhile
    left: dict[str, str] = {}
    if not new:
        return removed, left
    ours = {s: f'mapped by {pid} {cmd}' for pid, cmd in _session_processes(token).items()
            for s in process_segments(pid)}
    mapped = _mapped_by_anyone()
    for name in sorted(new):
        match = _BASE.match(name)
        base = match.group(1) if match else name
        if base in ours:
            left[name] = f'a running process of this session: {ours[base]}'
        elif not (base in mapped or lock_held(SHM_DIR / f'{base}_el')
                  or lock_held(SHM_DIR / f'{base}_sl')):
            if (SHM_DIR / name).exists():
                left[name] = 'in use by no running process'
    return removed, left
