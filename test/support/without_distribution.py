"""Run Python as if an installed distribution were not installed, without touching the venv.

``python test/support/without_distribution.py DIST -- ARGS...`` runs ``python ARGS...`` (e.g.
``-m pytest test/unit/model``) in a child whose ``site-packages`` is a temporary mirror of the
venv's: symlinks to every entry, except each file that ``DIST``'s RECORD lists (its
``*.dist-info`` and, for a cmeel wheel such as ``example-robot-data``, its share directory
and ament index marker under ``cmeel.prefix/``). Directories that hold such a file are real
directories in the mirror, their other entries symlinked. The child neither finds the
distribution (``importlib.metadata``) nor its files; everything else imports as before.

The mirror replaces the venv's ``site-packages`` entry of ``sys.path`` before anything else is
imported (``.pth`` files ran at start-up from the real directory; they only add paths or set
the environment). :func:`hidden_command` gives the command line for ``subprocess``.
"""

from __future__ import annotations

import importlib.metadata as md
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

SITE = Path(sysconfig.get_paths()['purelib'])

#: Run in the child before ARGS: swap the site-packages entry of sys.path for the mirror.
BOOT = ('import sys; sys.path[:] = [{mirror!r} if p == {site!r} else p for p in sys.path]; '
        'sys.argv = sys.argv[1:]; import runpy; a = sys.argv[0]; '
        'runpy.run_module(sys.argv.pop(1), run_name="__main__", alter_sys=True) if a == "-m" '
        'else runpy.run_path(a, run_name="__main__")')


def mirror_without(dist_name: str, into: Path) -> Path:
    """Build ``into``: a mirror of :data:`SITE` without the files of ``dist_name``."""
    dist = md.distribution(dist_name)
    hidden = {(SITE / str(f)).resolve() for f in dist.files or ()}
    hidden |= {Path(str(dist._path)).resolve()}  # type: ignore[attr-defined]
    keep_dirs = {p for h in hidden for p in h.parents}

    def fill(src: Path, dst: Path) -> None:
        dst.mkdir(parents=True, exist_ok=True)
        for entry in sorted(src.iterdir()):
            real = entry.resolve()
            if real in hidden:
                continue
            if entry.is_dir() and not entry.is_symlink() and real in keep_dirs:
                fill(entry, dst / entry.name)
            else:
                (dst / entry.name).symlink_to(entry)

    fill(SITE, into)
    return into


def hidden_command(dist_name: str, into: Path, args: list[str]) -> list[str]:
    """``[python, -c, BOOT, *args]`` run against a mirror at ``into`` without ``dist_name``;
    ``args`` as after ``python`` (``['-m', 'pytest', ...]`` or ``['script.py', ...]``)."""
    mirror = mirror_without(dist_name, into)
    return [sys.executable, '-c', BOOT.format(mirror=str(mirror), site=str(SITE)), *args]


def main(argv: list[str]) -> int:
    """``DIST -- ARGS...``: run ``python ARGS...`` without DIST; the child's exit status."""
    if len(argv) < 3 or argv[1] != '--':
        print('usage: without_distribution.py DIST -- ARGS...', file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix='without-') as tmp:
        cmd = hidden_command(argv[0], Path(tmp) / 'site-packages', argv[2:])
        return subprocess.run(cmd, check=False).returncode  # the mirror lives until it ends


if __name__ == '__main__':
    raise SystemExit(main(sys.argv[1:]))
