"""requirements.lock and the venv agree, and setup installs from the lock; the optional extra
"robots" (requirements-robots.lock) is installed whole or not at all, and only on request."""

from __future__ import annotations

import importlib.metadata as md
import re
from pathlib import Path

from conftest import REPO

LOCK = REPO / 'requirements.lock'
#: The optional extra's lock: only what it adds to LOCK (make robots installs it).
ROBOTS_LOCK = REPO / 'requirements-robots.lock'
#: Built by scripts/setup.sh, not installed from the lock: the two packages and the
#: interface packages of msg_schemas/third_party/ it builds where the wheels lack them.
BUILT_HERE = {'haptic-topology', 'haptic-topology-msgs'} | {
    p.name.replace('_', '-') for p in (REPO / 'msg_schemas' / 'third_party').iterdir()
    if (p / 'package.xml').is_file()}


def _normalize(name: str) -> str:
    return re.sub(r'[-_.]+', '-', name).lower()


def _pins(pattern: str, lock: Path = LOCK) -> dict[str, str]:
    pins = {}
    for line in lock.read_text().splitlines():
        m = re.fullmatch(pattern, line.strip())
        if m:
            pins[_normalize(m['name'])] = m['version']
    return pins


LOCKED = _pins(r'(?P<name>[A-Za-z0-9_.\-]+)==(?P<version>\S+)')
BUNDLED = _pins(r'# bundled: (?P<name>[A-Za-z0-9_.\-]+)==(?P<version>\S+)')
ROBOTS = _pins(r'(?P<name>[A-Za-z0-9_.\-]+)==(?P<version>\S+)', ROBOTS_LOCK)


def _installed() -> dict[str, str]:
    return {_normalize(d.metadata['Name']): d.version for d in md.distributions()}


def test_lock_pins_exact_versions_only() -> None:
    body = [ln for ln in LOCK.read_text().splitlines() if ln.strip() and not ln.startswith('#')]
    assert body and all(re.fullmatch(r'[A-Za-z0-9_.\-]+==\S+', ln) for ln in body)
    assert len(LOCKED) == len(body), 'duplicate pins in requirements.lock'


def test_every_pin_is_installed_at_its_version() -> None:
    installed = _installed()
    wrong = {n: (v, installed.get(n)) for n, v in (LOCKED | BUNDLED).items()
             if installed.get(n) != v}
    assert not wrong, f'lock vs venv (locked, installed): {wrong}; run `make setup`'


def test_every_installed_distribution_is_pinned() -> None:
    extra = sorted(set(_installed()) - set(LOCKED) - set(BUNDLED) - set(ROBOTS) - BUILT_HERE)
    assert not extra, (
        f'installed but not in requirements.lock: {extra}; add them to requirements.in and '
        'run scripts/lock.sh'
    )


def test_setup_installs_from_the_lock() -> None:
    setup = (REPO / 'scripts' / 'setup.sh').read_text()
    assert 'pip install -qq --no-deps -r "$root/requirements.lock"' in setup
    assert 'requirements.in' not in re.sub(r'#.*', '', setup)


def test_the_robots_extra_is_apart_from_the_lock_and_installed_whole_or_not() -> None:
    """example-robot-data (131 MB) is in the extra's lock only, never in requirements.lock or
    requirements.in; the extra adds exact pins that the lock does not have; in the venv it is
    either absent or present at exactly its pins (make robots), never half."""
    assert ROBOTS and 'example-robot-data' in ROBOTS
    assert not set(ROBOTS) & set(LOCKED), 'the extra pins what requirements.lock pins'
    assert not re.search(r'^example-robot-data', (REPO / 'requirements.in').read_text(), re.M)
    body = [ln for ln in ROBOTS_LOCK.read_text().splitlines() if ln.strip()
            and not ln.startswith('#')]
    assert all(re.fullmatch(r'[A-Za-z0-9_.\-]+==\S+', ln) for ln in body)
    assert re.findall(r'^example-robot-data==(\S+)$',
                      (REPO / 'requirements-robots.in').read_text(), re.M) == [
        ROBOTS['example-robot-data']]
    installed = _installed()
    present = {n: installed.get(n) for n in ROBOTS}
    assert present in ({n: None for n in ROBOTS}, ROBOTS), (
        f'the robots extra is half installed: {present} (locked {ROBOTS}); run `make robots`')


def test_only_the_robots_option_installs_the_extra() -> None:
    """scripts/setup.sh installs requirements-robots.lock under --robots only (make robots),
    not for make setup, make test or make demo."""
    setup = re.sub(r'#.*', '', (REPO / 'scripts' / 'setup.sh').read_text())
    install = 'pip install -qq --no-deps -r "$root/requirements-robots.lock"'
    start = setup.index('if ((robots)); then')
    block = setup[start:setup.index('\nfi\n', start)]
    assert install in block
    assert setup.count('requirements-robots') == block.count('requirements-robots')
    makefile = (REPO / 'Makefile').read_text()
    assert re.search(r'^robots:\n\t@bash scripts/setup.sh --robots$', makefile, re.M)
    assert makefile.count('--robots') == 1
