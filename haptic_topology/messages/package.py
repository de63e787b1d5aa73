"""Is the built message package ``haptic_topology_msgs`` importable? If not: what to run.

The repository holds two ROS packages: ``haptic_topology`` (ament_python, the repository root)
and ``haptic_topology_msgs`` (ament_cmake, ``msg_schemas/``). colcon's package discovery
(``colcon-recursive-crawl``) stops descending at the first directory it identifies as a
package, so a plain ``colcon build`` in a workspace holding the repository finds the root
package only: the nodes then have no messages. :func:`require_msgs_package` turns that into
one line naming the command that builds both (``scripts/colcon_check.sh`` runs that command
and checks the result).

No rclpy and no message import at module level (the core imports this module).

Example::

    >>> from pathlib import Path
    >>> colcon_command(Path('/ws/src/haptic_topology'))
    'colcon build --symlink-install --base-paths . /ws/src/haptic_topology/msg_schemas'
"""

from __future__ import annotations

import importlib.metadata as md
import importlib.util
import sysconfig
from pathlib import Path

from haptic_topology import MSGS_PACKAGE_NAME, PACKAGE_NAME

#: The repository this module was imported from (a source checkout, or a colcon
#: ``--symlink-install`` of one: its ``build/`` links back to the sources).
SOURCE_ROOT = Path(__file__).resolve().parents[2]
#: Directory of the message package inside the repository.
MSGS_DIR = 'msg_schemas'


def colcon_command(repo: Path | None) -> str:
    """The colcon command (run in the workspace root) that builds both packages: the default
    crawl (``.``) plus the message package inside the repository ``repo`` (None: unknown)."""
    base = str(repo) if repo is not None else f'<the {PACKAGE_NAME} repository>'
    where = f'{base}/{MSGS_DIR}'
    return f'colcon build --symlink-install --base-paths . {where}'


def _source_repo() -> Path | None:
    """The repository root, if this package runs from one (not from a copied install)."""
    return SOURCE_ROOT if (SOURCE_ROOT / MSGS_DIR / 'package.xml').is_file() else None


def _pip_installed() -> bool:
    """``haptic_topology`` was installed by pip into this interpreter's environment (the
    development venv of ``scripts/setup.sh``), not by colcon into a workspace."""
    try:
        dist = md.distribution(PACKAGE_NAME)
    except md.PackageNotFoundError:
        return False
    where = Path(str(dist.locate_file(''))).resolve()
    return where == Path(sysconfig.get_paths()['purelib']).resolve()


def missing_msgs_line(reason: str) -> str:
    """The one line printed when ``haptic_topology_msgs`` cannot be imported (``reason``:
    the import error's text)."""
    repo = _source_repo()
    head = f'{PACKAGE_NAME}: the message package {MSGS_PACKAGE_NAME} is not built ({reason})'
    if _pip_installed() and repo is not None:
        return f'{head}: run `make setup` in {repo}'
    return (f'{head}; a plain `colcon build` does not find {MSGS_DIR}/ inside the repository: '
            f'in the workspace root run `{colcon_command(repo)}`, '
            'then `source install/setup.bash`')


def require_msgs_package() -> None:
    """If ``haptic_topology_msgs`` is not installed, end the program with
    :func:`missing_msgs_line` on stderr and exit status 1 (``SystemExit``: no traceback).

    Only looks the package up (``importlib.util.find_spec``), imports nothing: a broken
    build (the package there, its typesupport libraries not) fails later, at the import,
    with its own error.
    """
    reason = f'No module named {MSGS_PACKAGE_NAME!r}'
    try:
        spec = importlib.util.find_spec(MSGS_PACKAGE_NAME)
    except ModuleNotFoundError as exc:     # a finder's own answer
        spec, reason = None, str(exc)
    if spec is None:
        raise SystemExit(missing_msgs_line(reason))
