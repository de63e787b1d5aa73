"""scripts/setup.sh: what ``make setup`` and ``make demo`` run needs no browser, no Node.js and no
root; ``--for-tests`` (``make test``) adds them and stops with a clear message where they are
missing.

Each test runs the real script against the venv the tests run in, on a ``PATH`` that mirrors
the current one without ``chromium``, ``node``, ``npm``, ``sudo`` and ``apt-get`` (the last two
replaced by scripts that log their call and fail). With nothing changed since the last setup
each step finds its stamp and the run takes seconds; it changes nothing that the same command
run by hand would not. The venv must be this checkout's (``make setup`` here): the script lays
the venv's share tree out pointing into the checkout it runs from.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SETUP = REPO / 'scripts' / 'setup.sh'
#: What the base setup must neither need nor call.
HIDDEN = ('chromium', 'chromium-browser', 'google-chrome', 'node', 'nodejs', 'npm', 'npx',
          'sudo', 'apt-get', 'apt')


def this_checkouts_venv() -> Path:
    venv = Path(sys.prefix)
    link = venv / 'share' / 'haptic_topology' / 'config'
    if not link.is_symlink() or link.resolve() != (REPO / 'config').resolve():
        pytest.fail(f'{venv} is not the venv of {REPO} (its share/haptic_topology/config is '
                    f'{os.readlink(link) if link.is_symlink() else "missing"}): this test runs '
                    f'scripts/setup.sh against the venv it runs in; run it with the venv of this '
                    f'checkout (make setup here)')
    return venv


def bare_path(tmp_path: Path, extra: dict[str, str] | None = None) -> tuple[str, Path]:
    """A ``PATH`` of one directory linking every program of the current ``PATH`` except
    :data:`HIDDEN`; ``sudo`` and ``apt-get`` are scripts that append their arguments to the
    returned log and fail. ``extra`` adds scripts by name and text."""
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    log = tmp_path / 'called.log'
    for entry in os.environ.get('PATH', '').split(os.pathsep):
        try:
            programs = sorted(Path(entry).iterdir()) if entry else []
        except OSError:     # missing or unreadable (another user's directory)
            continue
        for program in programs:
            link = bin_dir / program.name
            if program.name in HIDDEN or link.exists() or link.is_symlink():
                continue
            if program.is_file() and os.access(program, os.X_OK):
                link.symlink_to(program)
    traps = {name: f'#!/bin/sh\necho "{name} $*" >> {log}\nexit 1\n'
             for name in ('sudo', 'apt-get')}
    for name, text in {**traps, **(extra or {})}.items():
        script = bin_dir / name
        script.write_text(text)
        script.chmod(0o755)
    return str(bin_dir), log


def setup(path: str, venv: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, 'PATH': path, 'HAPTIC_VENV': str(venv)}
    return subprocess.run(['bash', str(SETUP), *args], env=env, capture_output=True, text=True,
                          timeout=600, cwd=REPO, stdin=subprocess.DEVNULL)


def test_the_demos_setup_needs_no_browser_no_node_and_no_root(tmp_path: Path) -> None:
    venv = this_checkouts_venv()
    path, log = bare_path(tmp_path)
    run = setup(path, venv)
    assert run.returncode == 0, f'setup.sh failed without chromium/node:\n{run.stdout}{run.stderr}'
    assert 'setup: ready:' in run.stdout
    assert not log.exists(), f'setup.sh tried to install something: {log.read_text()}'
    for word in ('chromium', 'npm', 'node'):
        assert word not in (run.stdout + run.stderr).lower(), (
            f'setup.sh mentions {word}:\n{run.stdout}{run.stderr}')


def test_the_tests_setup_stops_without_chromium_saying_so(tmp_path: Path) -> None:
    venv = this_checkouts_venv()
    path, _ = bare_path(tmp_path)
    run = setup(path, venv, '--for-tests')
    assert run.returncode == 1, run.stdout + run.stderr
    assert 'setup: ERROR: ' in run.stderr and 'chromium' in run.stderr, run.stderr


def test_the_tests_setup_stops_without_node_saying_so(tmp_path: Path) -> None:
    venv = this_checkouts_venv()
    path, log = bare_path(tmp_path, {'chromium': '#!/bin/sh\nexit 1\n'})
    run = setup(path, venv, '--for-tests')
    assert run.returncode == 1, run.stdout + run.stderr
    assert 'node/npm not found' in run.stderr and 'Node.js >= 20' in run.stderr, run.stderr
    assert not log.exists(), f'setup.sh tried to install something: {log.read_text()}'


def test_an_unknown_argument_is_refused() -> None:
    run = subprocess.run(['bash', str(SETUP), '--for-test'], capture_output=True, text=True,
                         timeout=60, stdin=subprocess.DEVNULL)
    assert run.returncode == 2
    assert 'unknown argument --for-test (expected --for-tests or --robots)' in run.stderr
