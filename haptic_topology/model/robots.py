"""Robots by name from ``example-robot-data``: ``linkage: {robot: panda, grasp: {link: ...}}``
in a linkage or scenario file, or ``robot:NAME`` where a linkage file is taken
(``--linkage robot:ur5``); and the collision pairs a robot's SRDF disables.

``example-robot-data`` (URDFs, SRDFs and meshes of many robots, one wheel of 131 MB) is an
optional extra, not part of the default setup: ``make robots`` (``scripts/setup.sh
--robots``) installs the pinned version into the venv; a ROS install's
``ros-jazzy-example-robot-data`` (the ament index) serves as well. When it is missing, naming a
robot is refused in one line saying how to install it. A robot named here is its URDF in that
package, referenced as ``package://example-robot-data/...`` and read unchanged, meshes included
(its collision meshes are the contact geometry: :mod:`haptic_topology.model.meshes`), with the
robot's SRDF where the package has one.

The Panda and the UR5 also ship with this package (``config/robots/``: URDF, SRDF, collision
meshes, licences), which the scenarios ``panda_link4``, ``panda_link4_point``, ``panda_table``
and ``ur5_table`` use, so they need no extra.

**SRDF.** A linkage's ``srdf:`` file (or a named robot's SRDF) is read for its
``<disable_collisions link1=... link2=.../>`` pairs (:func:`read_srdf`), kept as
``Linkage.disabled_collisions``: a scenario with ``contacts.self_collisions: true`` checks
every pair of non-adjacent links but these (:mod:`haptic_topology.dynamics.self_contacts`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from haptic_topology.errors import ConfigError, LinkageError
from haptic_topology.paths import resolve_package_uri

#: The distribution and the version this package is tested with (requirements-robots.in).
DISTRIBUTION = 'example-robot-data'
VERSION = '6.0.0'
#: How to install it, for the one-line refusal (the project's command first).
INSTALL = f"make robots (outside a checkout: pip install '{DISTRIBUTION}=={VERSION}')"
#: ``robot:NAME`` where a linkage file is taken.
ROBOT_PREFIX = 'robot:'

#: Name -> (URDF, SRDF or None) under ``share/example-robot-data/`` (serial arms this package
#: takes: revolute, prismatic and fixed joints).
ROBOTS: dict[str, tuple[str, str | None]] = {
    'panda': ('robots/panda_description/urdf/panda.urdf',
              'robots/panda_description/srdf/panda.srdf'),
    'ur3': ('robots/ur_description/urdf/ur3_robot.urdf', None),
    'ur5': ('robots/ur_description/urdf/ur5_robot.urdf', 'robots/ur_description/srdf/ur5.srdf'),
    'ur10': ('robots/ur_description/urdf/ur10_robot.urdf', None),
    'xarm7': ('robots/xarm_description/urdf/xarm7.urdf',
              'robots/xarm_description/srdf/xarm7.srdf'),
    'z1': ('robots/z1_description/urdf/z1.urdf', 'robots/z1_description/srdf/z1.srdf'),
    'so100': ('robots/so_arm_description/urdf/so100.urdf', None),
    'double_pendulum': ('robots/double_pendulum_description/urdf/double_pendulum.urdf', None),
}


def robot_files(name: str, where: str, distribution: str = DISTRIBUTION
                ) -> tuple[str, str | None]:
    """The ``package://`` URIs of robot ``name``'s URDF and SRDF (None: it has none). Raises
    LinkageError (one line, naming ``where``) for an unknown name, and when the URDF is not
    installed (``distribution``, example-robot-data, found neither in the ament index nor as
    a Python distribution: ``haptic_topology.paths.resolve_package_uri``), saying how to
    install it."""
    if name not in ROBOTS:
        raise LinkageError(f'{where}: unknown robot {name!r} (expected one of: '
                           f'{", ".join(sorted(ROBOTS))})')
    urdf_rel, srdf_rel = ROBOTS[name]
    urdf = f'package://{distribution}/{urdf_rel}'
    srdf = f'package://{distribution}/{srdf_rel}' if srdf_rel is not None else None
    try:
        resolve_package_uri(urdf, where)
    except ConfigError:
        raise LinkageError(f'{where}: robot {name!r} comes from {distribution}, an optional '
                           f'extra that is not installed (131 MB): {INSTALL}; the Panda and '
                           'the UR5 of config/robots/ need no extra (scenarios panda_table, '
                           'ur5_table)') from None
    return urdf, srdf


def read_srdf(path: Path, links: tuple[str, ...], where: str) -> tuple[tuple[str, str], ...]:
    """The ``<disable_collisions link1= link2=/>`` pairs of the SRDF at ``path``, each sorted,
    in file order without repeats. ``links``: the URDF's link names; a pair naming another
    link, and a file that is no SRDF, are refused (LinkageError, one line naming ``where``)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise LinkageError(f'{where}: cannot read the SRDF {path} ({exc})') from None
    if root.tag != 'robot':
        raise LinkageError(f'{where}: {path} is no SRDF (root element <{root.tag}>, expected '
                           '<robot>)')
    pairs: list[tuple[str, str]] = []
    for e in root.iter('disable_collisions'):
        a, b = e.get('link1', ''), e.get('link2', '')
        for link in (a, b):
            if link not in links:
                raise LinkageError(f'{where}: {path.name} disables collisions of link {link!r}, '
                                   'which the URDF does not have')
        pair = (min(a, b), max(a, b))
        if pair not in pairs:
            pairs.append(pair)
    return tuple(pairs)
