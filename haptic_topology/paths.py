"""Where the package's shipped configuration lives (share dir, or the source tree)."""

from __future__ import annotations

import importlib.metadata as md
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


def config_names(kind: str) -> list[str]:
    """The names of the shipped ``config/<kind>/*.yaml`` files (``kind``: ``scenarios`` or
    ``linkages``), sorted: what :func:`resolve_config` takes as a name."""
    return sorted(f.stem for f in (config_dir() / kind).glob('*.yaml'))


def scenario_help(what: str = 'a scenario YAML file') -> str:
    """The ``--help`` text of a scenario argument: every shipped scenario's name, or
    ``what``."""
    return f'scenario name ({", ".join(config_names("scenarios"))}) or {what}'


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
    known = config_names(kind)
    raise ConfigError(f'{name}: no such file, and no {kind[:-1]} of that name (known: '
                      f'{", ".join(known) or "none"})')


#: Prefix of a file inside an installed package, as in URDF mesh references.
PACKAGE_URI = 'package://'


def resolve_package_uri(uri: str, where: str, error: type[ConfigError] = ConfigError) -> Path:
    """The file ``package://NAME/REL``: ``REL`` under package NAME's share directory.

    NAME is looked up first in the ament index (a ROS install: ``share/NAME/REL``), then as an
    installed Python distribution whose files include ``.../share/NAME/REL`` (wheels such as
    ``example-robot-data`` install their share directory under ``cmeel.prefix/``), so the
    same reference works on any machine where the package is installed, wherever its
    site-packages is. ``where``: the field, for errors.
    """
    if not uri.startswith(PACKAGE_URI):
        raise error(f'{where}: expected package://NAME/PATH, got {uri!r}')
    name, _, rel = uri[len(PACKAGE_URI):].partition('/')
    if not name or not rel:
        raise error(f'{where}: expected package://NAME/PATH, got {uri!r}')
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )
        try:
            candidate = Path(get_package_share_directory(name)) / rel
            if candidate.is_file():
                return candidate
        except (PackageNotFoundError, KeyError, ValueError):
            pass
    except ImportError:
        pass
    try:
        dist = md.distribution(name)
    except md.PackageNotFoundError:
        raise error(f'{where}: package {name!r} is not installed (neither in the ament index '
                    f'nor as a Python distribution); install it, e.g. pip install {name}'
                    ) from None
    suffix = f'share/{name}/{rel}'
    for f in dist.files or ():
        if f.as_posix().endswith(suffix):
            return Path(str(dist.locate_file(f)))
    raise error(f'{where}: package {name!r} {dist.version} has no file share/{name}/{rel}')
