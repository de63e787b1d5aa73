"""Shared fixtures: an isolated ROS 2 DDS domain for this test session.

Each session picks a random ROS_DOMAIN_ID and restricts discovery to this host, and every test
topic carries a random suffix, so parallel test runs (CI jobs, two developers on one machine)
never see each other's messages.
"""

from __future__ import annotations

import fcntl
import os
import random
import secrets
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parent.parent
#: The tests' helpers (harnesses, fake backends, peers run as processes), importable by name
#: from every test folder.
SUPPORT = Path(__file__).resolve().parent / 'support'
sys.path.insert(0, str(SUPPORT))


@pytest.fixture(scope='session')
def spare_domains(ros_domain_env: dict[str, str]) -> Iterator[list[int]]:
    """Twelve more domain ids held by this session, for graphs that run at the same time."""
    locks = [_lock_domain() for _ in range(12)]
    try:
        yield [d for d, _ in locks]
    finally:
        for _, fd in locks:
            os.close(fd)


def _lock_domain() -> tuple[int, int]:
    """A ROS domain id no other test session on this machine holds, and the descriptor of its
    lock file (flock, released when closed or when the process dies)."""
    ids = list(range(1, 101))
    random.SystemRandom().shuffle(ids)
    lock_dir = Path(tempfile.gettempdir()) / 'haptic_topology_domains'
    lock_dir.mkdir(exist_ok=True)
    for domain in ids:
        fd = os.open(lock_dir / f'{domain}.lock', os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return domain, fd
    raise RuntimeError(f'every ROS domain id 1-100 is held by a test session ({lock_dir})')


@pytest.fixture(scope='session', autouse=True)
def ros_domain_env() -> Iterator[dict[str, str]]:
    """Environment for ROS processes of this session; also applied to ``os.environ``.

    Domain ids 1-100 keep Fast DDS's ports below Linux's ephemeral range. DDS stays on this
    host with the nodes' default transport (``localhost_discovery_default``). The session holds
    an exclusive lock on its domain id for its lifetime, so two test sessions on one machine
    (CI and a developer, or parallel jobs) never share a domain and never see each other's
    nodes.
    """
    from haptic_topology.device.realtime import SESSION_NICE_ENV
    from haptic_topology.nodes.dds_env import isolated_env

    lock = _lock_domain()
    saved = dict(os.environ)
    # DDS on this host as the nodes run by default (the project's Fast DDS profile, user data
    # over UDP on the loopback), for the test processes too, unless the user set a profile.
    env = isolated_env(lock[0], saved)
    # Node sessions at nice 0: the tests check function, not priority, and two workers
    # running graphs would starve nodes whose session yields (test_realtime unsets it).
    env[SESSION_NICE_ENV] = '0'
    os.environ.clear()
    os.environ.update(env)
    try:
        yield dict(os.environ)
    finally:
        os.close(lock[1])
        os.environ.clear()
        os.environ.update(saved)


@pytest.fixture
def topic_prefix() -> str:
    """A topic namespace unique to one test."""
    return f'/test_{secrets.token_hex(4)}'


def pytest_configure(config: pytest.Config) -> None:
    """The session's controlling process (with pytest-xdist: before the workers start, which
    inherit its environment) removes stale Fast DDS segments and notes what is in /dev/shm
    (``support/shm_session.py``)."""
    if hasattr(config, 'workerinput'):
        return
    import shm_session

    config.stash[_SHM] = shm_session.begin()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Once every test (and every worker) has ended: what the session leaves of Fast DDS in
    /dev/shm fails it, exit status 1 (``support/shm_session.py``)."""
    if hasattr(session.config, 'workerinput') or _SHM not in session.config.stash:
        return
    import shm_session

    token, _, present = session.config.stash[_SHM]
    removed, left = shm_session.end(token, present)
    session.config.stash[_SHM_END] = (removed, left)
    if left and session.exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    if _SHM_END not in config.stash:
        return
    _, before, _ = config.stash[_SHM]
    removed, left = config.stash[_SHM_END]
    if before or removed:
        terminalreporter.write_line(
            f'/dev/shm: removed {len(before)} stale Fast DDS segments of ended processes at '
            f'the start, {len(removed)} at the end')
    if left:
        terminalreporter.write_line(
            f'/dev/shm: this session left {len(left)} Fast DDS entries behind:', red=True)
        for name, why in left.items():
            terminalreporter.write_line(f'  {name}: {why}', red=True)


_SHM = pytest.StashKey[tuple[str, list[str], set[str]]]()
_SHM_END = pytest.StashKey[tuple[list[str], dict[str, str]]]()


#: Test files that start node graphs, longest first (pytest --durations, 2 cores): with
#: ``-n 2 --dist loadfile`` (make test) each file runs in one worker, and starting the long
#: ones first keeps one of them from being the last thing the session waits for.
LONGEST_FIRST = ('test_node_graph.py', 'test_fault_injection.py', 'test_foreign_messages.py',
                 'test_replay.py', 'test_recorder.py', 'test_hosted_layout.py')


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run the files of :data:`LONGEST_FIRST` first, in that order; the rest keep theirs."""
    def key(item: pytest.Item) -> int:
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=key)


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Every test runs holding the machine's CPU lock shared, so a ``whole_machine`` test can
    hold it exclusive (``support/cpu_share.py``); outermost, so pytest-timeout's clock does
    not run while a test waits for it."""
    from cpu_share import cpu_share

    if item.get_closest_marker('whole_machine') is not None:
        yield
        return
    with cpu_share(exclusive=False):
        yield
