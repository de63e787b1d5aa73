"""Robots by name from ``example-robot-data``: ``linkage: {robot: panda, grasp: {link: ...}}``
in a linkage or scenario file, or ``robot:NAME`` where a linkage file is taken
(``--linkage robot:ur5``).

``example-robot-data`` (URDFs, SRDFs and meshes of many robots, one wheel of 131 MB) is only
needed for this: when it is not installed, naming a robot is refused in one line saying how to
install it (``pip install 'example-robot-data==6.0.0'``). A robot named here is its URDF in
that package, referenced as ``package://example-robot-data/...`` and read unchanged, meshes
included (its collision meshes are the contact geometry: :mod:`haptic_topology.model.meshes`).
"""

from __future__ import annotations

import importlib.metadata as md

from haptic_topology.errors import LinkageError

#: The distribution and the version this package is tested with (requirements.in).
DISTRIBUTION = 'example-robot-data'
VERSION = '6.0.0'
#: ``robot:NAME`` where a linkage file is taken.
ROBOT_PREFIX = 'robot:'

#: Name -> URDF under ``share/example-robot-data/`` (serial arms this package takes: revolute,
#: prismatic and fixed joints).
ROBOTS: dict[str, str] = {
    'panda': 'robots/panda_description/urdf/panda.urdf',
    'ur3': 'robots/ur_description/urdf/ur3_robot.urdf',
    'ur5': 'robots/ur_description/urdf/ur5_robot.urdf',
    'ur10': 'robots/ur_description/urdf/ur10_robot.urdf',
    'xarm7': 'robots/xarm_description/urdf/xarm7.urdf',
    'z1': 'robots/z1_description/urdf/z1.urdf',
    'so100': 'robots/so_arm_description/urdf/so100.urdf',
    'double_pendulum': 'robots/double_pendulum_description/urdf/double_pendulum.urdf',
}


def robot_urdf(name: str, where: str, distribution: str = DISTRIBUTION) -> str:
    """The ``package://`` URI of robot ``name``'s URDF. Raises LinkageError (one line, naming
    ``where``) for an unknown name, and when ``distribution`` (``example-robot-data``) is not
    installed, saying how to install it."""
    if name not in ROBOTS:
        raise LinkageError(f'{where}: unknown robot {name!r} (expected one of: '
                           f'{", ".join(sorted(ROBOTS))})')
    try:
        md.distribution(distribution)
    except md.PackageNotFoundError:
        raise LinkageError(f'{where}: robot {name!r} comes from {distribution}, which is not '
                           f"installed (131 MB): pip install '{distribution}=={VERSION}'"
                           ) from None
    return f'package://{DISTRIBUTION}/{ROBOTS[name]}'
