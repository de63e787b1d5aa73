"""Shared fixtures: an isolated ROS 2 DDS domain for this test session.

Each session picks a random ROS_DOMAIN_ID and restricts discovery to this host, and every test
topic carries a random suffix, so parallel test runs (CI jobs, two developers on one machine)
never see each other's messages.
"""

from __future__ import annotations

import os
import random
import secrets
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope='session', autouse=True)
def ros_domain_env() -> Iterator[dict[str, str]]:
    """Environment for ROS processes of this session; also applied to ``os.environ``.

    Domain ids 1-100 keep Fast DDS's ports below Linux's ephemeral range.
    """
    overrides = {
        'ROS_DOMAIN_ID': str(random.SystemRandom().randint(1, 100)),
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp',
    }
    saved = {k: os.environ.get(k) for k in [*overrides, 'ROS_LOCALHOST_ONLY']}
    os.environ.pop('ROS_LOCALHOST_ONLY', None)  # deprecated; conflicts with the range above
    os.environ.update(overrides)
    try:
        yield dict(os.environ)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture
def topic_prefix() -> str:
    """A topic namespace unique to one test."""
    return f'/test_{secrets.token_hex(4)}'
