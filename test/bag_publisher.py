"""Test helper (not collected): publish N messages of each haptic_topology_msgs type at 1 kHz.

    python bag_publisher.py N TIMEOUT_S [NAMESPACE [CLOCK]]

Publishes on the graph's topics with the graph's QoS under CLOCK (``wall`` default, or
``lockstep``: the loop topics reliable; see haptic_topology.nodes.common.publisher_qos):
DeviceState.seq, DeviceCommand.state_seq and LmiUpdate.seq run 1..N, one of each per
millisecond; HandInputs.seq runs 1..N too, in batches of BATCH samples (one message every
BATCH ms, as lmi_controller sends them; N must be a multiple of BATCH). Starts once every
topic has a subscriber (prints ``publishing``); prints ``sent N ...`` and exits.
"""

from __future__ import annotations

import sys
import time

import rclpy
from builtin_interfaces.msg import Time

from haptic_topology.nodes import common
from haptic_topology.settings import Clock
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate

#: Samples per HandInputs message.
BATCH = 10


def main() -> int:
    n, timeout = int(sys.argv[1]), float(sys.argv[2])
    namespace = sys.argv[3] if len(sys.argv) > 3 else ''
    clock = Clock.parse(sys.argv[4] if len(sys.argv) > 4 else 'wall')
    rclpy.init()
    node = rclpy.create_node('bag_test_publisher', namespace=namespace)
    topics = ((DeviceState, common.TOPIC_STATE), (DeviceCommand, common.TOPIC_COMMAND),
              (HandInputs, common.TOPIC_HAND_INPUTS), (LmiUpdate, common.TOPIC_LMI))
    pubs = [node.create_publisher(t, name, common.publisher_qos(name, clock))
            for t, name in topics]
    deadline = time.monotonic() + timeout
    while any(p.get_subscription_count() == 0 for p in pubs):
        if time.monotonic() > deadline:
            print('no subscriber', file=sys.stderr)
            return 2
        time.sleep(0.02)
    time.sleep(0.5)  # both directions of discovery
    state, cmd, hand, upd = DeviceState(), DeviceCommand(), HandInputs(), LmiUpdate()
    state.task_dim = cmd.task_dim = hand.task_dim = upd.task_dim = 3
    state.pose = state.twist = state.hand_wrench = state.applied_wrench = [0.1, 0.2, 0.3]
    cmd.wrench = cmd.vt_pose = cmd.vt_twist = [0.4, 0.5, 0.6]
    hand.pose = hand.twist = hand.hand_wrench = hand.coupling_wrench = [0.7, 0.8, 0.9] * BATCH
    stamps: list[Time] = []
    upd.dof = 3
    upd.q = upd.dq = upd.gravity = [0.0, 0.1, 0.2]
    upd.mass_matrix = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    print('publishing', flush=True)
    start = time.perf_counter()
    for i in range(1, n + 1):
        while (rem := start + i * 1e-3 - time.perf_counter()) > 0:
            time.sleep(rem)
        stamp = node.get_clock().now().to_msg()
        state.header.stamp = cmd.header.stamp = upd.header.stamp = stamp
        state.seq = i
        cmd.state_seq = i
        upd.seq = upd.hand_input_seq = i
        stamps.append(stamp)
        for pub, msg in zip(pubs, (state, cmd, hand, upd), strict=True):
            if msg is hand:
                if i % BATCH:
                    continue
                hand.header.stamp = stamp
                hand.seq = hand.state_seq = list(range(i - BATCH + 1, i + 1))
                hand.stamp, stamps = stamps, []
            pub.publish(msg)
    print(f'sent {n} in {time.perf_counter() - start:.2f} s', flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
