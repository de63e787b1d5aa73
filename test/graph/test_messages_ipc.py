"""Every haptic_topology_msgs type crosses from a publisher process to a subscriber process.

Real rclpy, real Fast DDS, two OS processes; all fields carry non-default values.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from rosmsg_util import sample_values

from haptic_topology.messages.definitions import (
    MESSAGE_NAMES,
    type_name,
    typestore_with_haptic_msgs,
)

pytestmark = pytest.mark.graph

PEER = Path(__file__).resolve().parents[1] / 'support' / 'ipc_peer.py'
TIMEOUT_S = 30.0


def test_every_message_crosses_two_processes(
    ros_domain_env: dict[str, str], topic_prefix: str
) -> None:
    cmd = [sys.executable, str(PEER)]
    pub = subprocess.Popen([*cmd, 'pub', topic_prefix, str(TIMEOUT_S)], env=ros_domain_env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        sub = subprocess.run([*cmd, 'sub', topic_prefix, str(TIMEOUT_S)], env=ros_domain_env,
                             capture_output=True, text=True, timeout=TIMEOUT_S + 15)
    finally:
        pub.send_signal(signal.SIGINT)
        try:
            _, pub_err = pub.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            pub.kill()
            _, pub_err = pub.communicate()
    assert sub.returncode == 0, f'subscriber failed:\n{sub.stderr}\npublisher:\n{pub_err}'
    assert pub.pid != 0 and pub.returncode in (0, -signal.SIGINT), pub_err

    received = json.loads(sub.stdout)
    store = typestore_with_haptic_msgs()
    assert sorted(received) == sorted(MESSAGE_NAMES)
    for name in MESSAGE_NAMES:
        assert received[name] == sample_values(store, type_name(name)), name
