"""Run Python as if installed distributions were not installed, without touching the venv.

``python test/support/without_distribution.py DIST[,DIST...] -- ARGS...`` runs ``python
ARGS...`` (e.g. ``-m pytest test/unit/model``) in a child whose ``site-packages`` is a temporary
mirror of the venv's: symlinks to every entry, except each file that a DIST's RECORD lists (its
``*.dist-info`` and, for a cmeel wheel such as ``example-robot-data``, its share directory and
ament index marker under ``cmeel.prefix/``). Directories that hold such a file are real
directories in the mirror, their other entries symlinked. The child neither finds the
distributions (``importlib.metadata``) nor their files; everything else imports as before.

The mirror replaces the venv's ``site-packages`` entry of ``sys.path`` before anything else is
imported (``.pth`` files ran at start-up from the real directory; they only add paths or set
the environment), and ``WITHOUT_DISTRIBUTION_SITE`` names it, so that a child's own children
started through :func:`hidden_command` see the same mirror (a test run inside it that starts
Python again). :func:`hidden_command` gives the command line for ``subprocess``.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import subprocess
import sys
import sysconfig
import tempfile
from collections.abc import Sequence
from pathlib import Path

SITE = Path(sysconfig.get_paths()['purelib'])
#: The site-packages this process sees in place of SITE (a mirror), for its children.
ENV = 'WITHOUT_DISTRIBUTION_SITE'

#: Run in the child before ARGS: swap the site-packages entry of sys.path for the mirror.
BOOT = ('import os, sys; os.environ[{env!r}] = {mirror!r}; '
        'sys.path[:] = [{mirror!r} if p == {site!r} else p for p in sys.path]; '
        'sys.argv = sys.argv[1:]; import runpy; a = sys.argv[0]; '
        'runpy.run_module(sys.argv.pop(1), run_name="__main__", alter_sys=True) if a == "-m" '
        'else runpy.run_path(a, run_name="__main__")')


def mirror_without(base: Path, dists: Sequence[md.Distribution], into: Path) -> Path:
    """Build ``into``: a mirror of the site-packages ``base`` without the files of
    ``dists``."""
    hidden: set[Path] = set()
    for dist in dists:
        hidden |= {Path(str(dist.locate_file(f))).resolve() for f in dist.files or ()}
        hidden.add(Path(str(dist._path)).resolve())  # type: ignore[attr-defined]
    keep_dirs = {p for h in hidden for p in h.parents}

    def fill(src: Path, dst: Path) -> None:
        dst.mkdir(parents=True, exist_ok=True)
        for entry in sorted(src.iterdir()):
            real = entry.resolve()
            if real in hidden:
                continue
            if entry.is_dir() and real in keep_dirs:
                fill(entry, dst / entry.name)
            else:
                (dst / entry.name).symlink_to(real)

    fill(base, into)
    return into


def hidden_command(names: Sequence[str], into: Path, args: list[str]) -> list[str]:
    """``[python, -c, BOOT, *args]``: ``python ARGS`` against a mirror at ``into`` of the
    site-packages this process sees, without those of the distributions ``names`` it finds
    (none found: the same site-packages as this process); ``args`` as after ``python``
    (``['-m', 'pytest', ...]`` or ``['script.py', ...]``)."""
    base = Path(os.environ.get(ENV, str(SITE)))
    found = []
    for name in names:
        try:
            found.append(md.distribution(name))
        except md.PackageNotFoundError:
            pass
    mirror = mirror_without(base, found, into) if found else base
    return [sys.executable, '-c', BOOT.format(env=ENV, mirror=str(mirror), site=str(SITE)),
            *args]


def main(argv: list[str]) -> int:
    """``DIST[,DIST...] -- ARGS...``: run ``python ARGS...`` without the DISTs; the child's
    exit status."""
    if len(argv) < 3 or argv[1] != '--':
        print('usage: without_distribution.py DIST[,DIST...] -- ARGS...', file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix='without-') as tmp:
        cmd = hidden_command(argv[0].split(','), Path(tmp) / 'site-packages', argv[2:])
        return subprocess.run(cmd, check=False).returncode  # the mirror lives until it ends


if __name__ == '__main__':
    raise SystemExit(main(sys.argv[1:]))
