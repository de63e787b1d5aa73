"""One side of the two-process message test (run by test_messages_ipc.py, not collected).

    python ipc_peer.py pub <topic_prefix> <timeout_s>
        publish a sample of every haptic_topology_msgs type, repeatedly, until SIGINT/deadline
    python ipc_peer.py sub <topic_prefix> <timeout_s>
        print {type: fields} as JSON once one message of every type has arrived; exit 2 on
        deadline

Spins with spin_once(timeout_sec=...) under a deadline so neither side can hang.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosmsg_util import fill_rclpy, rclpy_to_dict, rclpy_type, sample_values

from haptic_topology.messages.definitions import (
    MESSAGE_NAMES,
    type_name,
    typestore_with_haptic_msgs,
)

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def publish(node: Any, prefix: str, deadline: float) -> int:
    store = typestore_with_haptic_msgs()
    pubs = []
    for name in MESSAGE_NAMES:
        msg = fill_rclpy(rclpy_type(name)(), sample_values(store, type_name(name)))
        pubs.append((node.create_publisher(rclpy_type(name), f'{prefix}/{name}', QOS), msg))
    while rclpy.ok() and time.monotonic() < deadline:
        for pub, msg in pubs:
            if pub.get_subscription_count() > 0:
                pub.publish(msg)
        rclpy.spin_once(node, timeout_sec=0.05)
    return 0


def subscribe(node: Any, prefix: str, deadline: float) -> int:
    received: dict[str, dict[str, Any]] = {}

    def keep(name: str) -> Any:
        return lambda msg: received.setdefault(name, rclpy_to_dict(msg))

    subs = [node.create_subscription(rclpy_type(n), f'{prefix}/{n}', keep(n), QOS)
            for n in MESSAGE_NAMES]
    while len(received) < len(MESSAGE_NAMES) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    del subs
    if len(received) < len(MESSAGE_NAMES):
        missing = sorted(set(MESSAGE_NAMES) - set(received))
        print(f'timed out; missing {missing}', file=sys.stderr)
        return 2
    print(json.dumps(received))
    return 0


def main(argv: list[str]) -> int:
    role, prefix, timeout = argv[1], argv[2], float(argv[3])
    deadline = time.monotonic() + timeout
    rclpy.init()
    node = rclpy.create_node(f'ipc_{role}')
    try:
        return (publish if role == 'pub' else subscribe)(node, prefix, deadline)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except RuntimeError:        # rclpy's RCLError
        if rclpy.ok():
            raise
        # The SIGINT that ends the publisher shut the context down in the middle of an rcl
        # call ("publisher's context is invalid"): the stop asked for, not a failure.
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main(sys.argv))
