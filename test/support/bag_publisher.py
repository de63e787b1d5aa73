"""Test helper (not collected): publish N messages of each haptic_topology_msgs type at 1 kHz.

    python bag_publisher.py N TIMEOUT_S [NAMESPACE [CLOCK]]

Publishes on the graph's topics with the graph's QoS under CLOCK (``wall`` default, or
``lockstep``: the loop topics reliable; see haptic_topology.nodes.publisher_qos):
DeviceState.seq, DeviceCommand.state_seq and LmiUpdate.seq run 1..N, one of each per
millisecond; HandInputs.seq runs 1..N too, in batches of BATCH samples (one message every
BATCH ms, as lmi_controller sends them; N must be a multiple of BATCH). Starts once every
topic has a subscriber (prints ``publishing``); prints ``sent N ...``. With RECORDED (the
5th argument, ``recorded``) it then stays up, so that its reliable writers can resend, until
the recorder's ``/diagnostics`` report every message received (``received <topic>``), prints
``recorded`` and exits; exit status 3 if that does not happen within TIMEOUT_S.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import rclpy
from builtin_interfaces.msg import Time

from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, publisher_qos
from haptic_topology.vocabulary import (
    TOPIC_COMMAND,
    TOPIC_DIAGNOSTICS,
    TOPIC_HAND_INPUTS,
    TOPIC_LMI,
    TOPIC_STATE,
    Clock,
)
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate

#: Samples per HandInputs message.
BATCH = 10


def main() -> int:
    n, timeout = int(sys.argv[1]), float(sys.argv[2])
    namespace = sys.argv[3] if len(sys.argv) > 3 else ''
    clock = Clock.parse(sys.argv[4] if len(sys.argv) > 4 else 'wall')
    rclpy.init()
    node = rclpy.create_node('bag_test_publisher', namespace=namespace)
    topics = ((DeviceState, TOPIC_STATE), (DeviceCommand, TOPIC_COMMAND),
              (HandInputs, TOPIC_HAND_INPUTS), (LmiUpdate, TOPIC_LMI))
    pubs = [node.create_publisher(t, name, publisher_qos(name, clock))
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
    cmd.controller_id = 1
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
    status = 0
    if len(sys.argv) > 5 and sys.argv[5] == 'recorded':
        status = _wait_recorded(node, n, timeout)
    else:
        time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return status


def _wait_recorded(node: Any, n: int, timeout: float) -> int:
    """Spin until the recorder reports all ``n`` messages of each topic received (hand
    inputs: n / BATCH messages); 0, or 3 on timeout. A reliable writer that exits earlier
    takes its unacknowledged samples with it: on a loaded machine the recorder can be more
    than a second behind."""
    from diagnostic_msgs.msg import DiagnosticArray

    want = {TOPIC_STATE: n, TOPIC_COMMAND: n, TOPIC_LMI: n,
            TOPIC_HAND_INPUTS: n // BATCH}
    got: dict[str, int] = {}

    def on_diagnostics(msg: Any) -> None:
        for st in msg.status:
            if st.name == 'recorder: bag':
                for kv in st.values:
                    for topic in want:
                        if kv.key == f'received {topic}':
                            got[topic] = int(kv.value)

    node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, on_diagnostics,
                             QOS_DIAGNOSTICS)
    deadline = time.monotonic() + timeout
    while any(got.get(t, 0) < k for t, k in want.items()):
        if time.monotonic() > deadline:
            print(f'recorder did not report all received within {timeout:g} s: {got}',
                  flush=True)
            return 3
        rclpy.spin_once(node, timeout_sec=0.05)
    print('recorded', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
