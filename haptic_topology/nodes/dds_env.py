"""The DDS environment of the graph's processes: discovery on this host by default."""

from __future__ import annotations

import os
from collections.abc import Mapping

from haptic_topology.paths import config_dir

DISCOVERY_ENV = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
#: Fast DDS's XML profile variable, and the project's profile for DDS on this host
#: (``config/fastdds_localhost.xml``: user data over UDP on the loopback, no shared memory).
FASTDDS_PROFILES_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
LOCALHOST_PROFILE = 'fastdds_localhost.xml'


def localhost_discovery_default(env: dict[str, str] | os._Environ[str]) -> str:
    """Keep DDS on this host unless the user chose otherwise; return the discovery range.

    Sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` in ``env`` when neither it nor the
    deprecated ``ROS_LOCALHOST_ONLY`` is set. With the range ``LOCALHOST`` and Fast DDS (the
    default RMW), also sets ``FASTRTPS_DEFAULT_PROFILES_FILE`` to :data:`LOCALHOST_PROFILE`
    unless it or ``ROS_STATIC_PEERS`` is set: user data then goes over UDP on the loopback
    instead of shared memory, where Fast DDS 2.14 can leave a killed and restarted process
    deaf (eProsima/Fast-DDS#5053). To run nodes on several machines set
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (or keep LOCALHOST and list the other hosts in
    ``ROS_STATIC_PEERS``) and the same ``ROS_DOMAIN_ID`` on every machine.
    """
    if DISCOVERY_ENV not in env and 'ROS_LOCALHOST_ONLY' not in env:
        env[DISCOVERY_ENV] = 'LOCALHOST'
    scope = env.get(DISCOVERY_ENV, 'LOCALHOST' if env.get('ROS_LOCALHOST_ONLY') == '1'
                    else 'SUBNET')
    if (scope == 'LOCALHOST' and FASTDDS_PROFILES_ENV not in env
            and not env.get('ROS_STATIC_PEERS')
            and env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') == 'rmw_fastrtps_cpp'):
        profile = config_dir() / LOCALHOST_PROFILE
        if profile.is_file():
            env[FASTDDS_PROFILES_ENV] = str(profile)
    return scope


def isolated_env(domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """An environment for ROS 2 processes that see only each other: ``base`` (default
    ``os.environ``) with ``ROS_DOMAIN_ID=domain_id``, discovery on this host only, Fast DDS,
    no static peers, and the nodes' DDS transport default (:func:`localhost_discovery_default`;
    a Fast DDS profile the user set is kept). The graph's tests, the benchmarks and the
    bringup's callers use it to keep their processes apart."""
    env = dict(os.environ if base is None else base)
    env.pop('ROS_LOCALHOST_ONLY', None)     # deprecated; conflicts with the discovery range
    env.pop('ROS_STATIC_PEERS', None)       # these processes are on this host only
    env.update(ROS_DOMAIN_ID=str(domain_id), RMW_IMPLEMENTATION='rmw_fastrtps_cpp')
    env[DISCOVERY_ENV] = 'LOCALHOST'
    localhost_discovery_default(env)
    return env
