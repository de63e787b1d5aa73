"""Where the package's shipped configuration lives (share dir, or the source tree)."""

from __future__ import annotations

from pathlib import Path

from haptic_topology.errors import ConfigError

PACKAGE = 'haptic_topology'


def config_dir() -> Path:
    """The repository's ``config/`` when run from a source checkout (editable install), else
    ``<share>/haptic_topology/config`` from the ament index (colcon or pip install)."""
    source = Path(__file__).resolve().parent.parent / 'config'
    if (source.parent / 'package.xml').is_file() and source.is_dir():
        return source
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )
        try:
            share = Path(get_package_share_directory(PACKAGE)) / 'config'
            if share.is_dir():
                return share
        except (PackageNotFoundError, KeyError, ValueError):
            pass
    except ImportError:
        pass
    return source


def resolve_config(name: str, kind: str) -> Path:
    """A config file given as a path, or by name from ``config/<kind>/<name>.yaml``.

    ``kind`` is ``scenarios`` or ``linkages``.
    """
    p = Path(name)
    if p.is_file():
        return p
    candidate = config_dir() / kind / f'{name}.yaml'
    if candidate.is_file():
        return candidate
    known = sorted(f.stem for f in (config_dir() / kind).glob('*.yaml'))
    raise ConfigError(f'{name}: no such file, and no {kind[:-1]} of that name (known: '
                      f'{", ".join(known) or "none"})')
