"""requirements.lock and the venv agree, and setup installs from the lock."""

from __future__ import annotations

import importlib.metadata as md
import re

from conftest import REPO

LOCK = REPO / 'requirements.lock'
#: Built by scripts/setup.sh, not installed from the lock: the two packages and the
#: interface packages of msg_schemas/third_party/ it builds where the wheels lack them.
BUILT_HERE = {'haptic-topology', 'haptic-topology-msgs'} | {
    p.name.replace('_', '-') for p in (REPO / 'msg_schemas' / 'third_party').iterdir()
    if (p / 'package.xml').is_file()}


def _normalize(name: str) -> str:
    return re.sub(r'[-_.]+', '-', name).lower()


def _pins(pattern: str) -> dict[str, str]:
    pins = {}
    for line in LOCK.read_text().splitlines():
        m = re.fullmatch(pattern, line.strip())
        if m:
            pins[_normalize(m['name'])] = m['version']
    return pins


LOCKED = _pins(r'(?P<name>[A-Za-z0-9_.\-]+)==(?P<version>\S+)')
BUNDLED = _pins(r'# bundled: (?P<name>[A-Za-z0-9_.\-]+)==(?P<version>\S+)')


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
    extra = sorted(set(_installed()) - set(LOCKED) - set(BUNDLED) - BUILT_HERE)
    assert not extra, (
        f'installed but not in requirements.lock: {extra}; add them to requirements.in and '
        'run scripts/lock.sh'
    )


def test_setup_installs_from_the_lock() -> None:
    setup = (REPO / 'scripts' / 'setup.sh').read_text()
    assert 'pip install -qq --no-deps -r "$root/requirements.lock"' in setup
    assert 'requirements.in' not in re.sub(r'#.*', '', setup)
