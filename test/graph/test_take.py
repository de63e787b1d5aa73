"""The recorder's input side (:class:`~haptic_topology.nodes.take.BatchTaker`) over real DDS,
in this process: every message taken once, in order, with DDS's receive time, and a reader
history that overflowed between two drains counted as lost, exactly, per publisher."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from haptic_topology.nodes.take import BatchTaker

pytestmark = pytest.mark.graph

DEPTH = 10


@pytest.fixture
def pair(topic_prefix: str) -> Iterator[tuple[Any, BatchTaker, Any]]:
    """A publisher of DeviceState (best effort, depth 1) and a BatchTaker with a reader
    history of ``DEPTH``, both matched."""
    import rclpy

    from haptic_topology_msgs.msg import DeviceState

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        owner = rclpy.create_node('take_test', context=context)
        topic = f'{topic_prefix}/state'
        pub = owner.create_publisher(DeviceState, topic, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        taker = BatchTaker(owner, [(topic, DeviceState, QoSProfile(
            depth=DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT))])
        deadline = time.monotonic() + 20.0
        while pub.get_subscription_count() < 1 or taker.publisher_counts() != [1]:
            assert time.monotonic() < deadline, 'publisher and reader never matched'
            time.sleep(0.01)
        yield owner, taker, pub
        taker.destroy()
        owner.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def _publish(pub: Any, seqs: range | list[int]) -> None:
    from haptic_topology_msgs.msg import DeviceState

    msg = DeviceState(task_dim=3, pose=[0.0] * 3, twist=[0.0] * 3, hand_wrench=[0.0] * 3,
                      applied_wrench=[0.0] * 3)
    for seq in seqs:
        msg.seq = seq
        pub.publish(msg)


def _drain_until(taker: BatchTaker, count: int) -> list[tuple[int, int, bytes]]:
    """Drain until ``count`` messages were taken in total (delivery is asynchronous)."""
    out: list[tuple[int, int, bytes]] = []
    deadline = time.monotonic() + 20.0
    while sum(taker.taken) < count:
        assert time.monotonic() < deadline, f'took {taker.taken}, expected {count}'
        taker.drain(out.extend)
        time.sleep(0.01)
    return out


def test_messages_taken_in_order_and_overflow_counted_as_lost(pair: Any) -> None:
    from rclpy.serialization import deserialize_message

    from haptic_topology_msgs.msg import DeviceState

    _, taker, pub = pair
    before = time.time_ns()
    _publish(pub, range(1, 6))
    first = _drain_until(taker, 5)
    seqs = [deserialize_message(d, DeviceState).seq for _, _, d in first]
    assert seqs == [1, 2, 3, 4, 5]
    assert all(before <= ns <= time.time_ns() for _, ns, _ in first)
    assert taker.lost == [0]

    # 30 more with nobody taking: the reader's history keeps the newest DEPTH of them, the
    # ones before are gone, and the gap in the publisher's sequence numbers says how many.
    # (Publisher and reader share a participant, so delivery is in publish() and the
    # history holds exactly 26-35; the assertions hold for any delivery timing.)
    _publish(pub, range(6, 36))
    second: list[tuple[int, int, bytes]] = []
    deadline = time.monotonic() + 20.0
    while not second or deserialize_message(second[-1][2], DeviceState).seq != 35:
        assert time.monotonic() < deadline, f'took {taker.taken}, lost {taker.lost}'
        taker.drain(second.extend)
        time.sleep(0.01)
    seqs = [deserialize_message(d, DeviceState).seq for _, _, d in second]
    assert seqs == sorted(seqs) and len(seqs) >= DEPTH
    assert taker.taken[0] + taker.lost[0] == 35        # every message taken or counted lost
    assert taker.lost[0] == 35 - 5 - len(seqs) >= 1, (seqs, taker.lost)


def test_overflow_with_two_publishers_is_counted_per_publisher(topic_prefix: str) -> None:
    """Two publishers (nodes ``pub_a`` and ``pub_b``) on one topic, a reader history of
    ``DEPTH``: a burst of one publisher pushes both publishers' older samples out before the
    next drain (keep-last: DDS reports nothing lost). Each publisher's gap in its sequence
    numbers is counted against it. Publishers and reader share one participant, so Fast DDS
    delivers in ``publish()`` and the history holds exactly the newest ``DEPTH`` samples."""
    import rclpy
    from rclpy.serialization import deserialize_message

    from haptic_topology_msgs.msg import DeviceState

    best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        owner = rclpy.create_node('take_test', context=context)
        a, b = (rclpy.create_node(name, namespace=topic_prefix, context=context)
                for name in ('pub_a', 'pub_b'))
        topic = f'{topic_prefix}/state'
        pub_a, pub_b = (n.create_publisher(DeviceState, topic, best_effort) for n in (a, b))
        taker = BatchTaker(owner, [(topic, DeviceState, QoSProfile(
            depth=DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT))])
        deadline = time.monotonic() + 20.0
        while taker.publisher_counts() != [2] or not all(
                p.get_subscription_count() for p in (pub_a, pub_b)):
            assert time.monotonic() < deadline, 'publishers and reader never matched'
            time.sleep(0.01)
        _publish(pub_a, range(1, 4))            # A: 1-3, B: 1001-1002, all taken
        _publish(pub_b, range(1001, 1003))
        _drain_until(taker, 5)
        assert taker.lost == [0]

        # B sends 1003, A 4-33, B 1004, nobody taking: the history keeps A's 25-33 and B's
        # 1004; A's 4-24 (21) and B's 1003 (1) are gone.
        _publish(pub_b, [1003])
        _publish(pub_a, range(4, 34))
        _publish(pub_b, [1004])
        taken: list[tuple[int, int, bytes]] = []
        while not {33, 1004} <= {deserialize_message(d, DeviceState).seq for _, _, d in taken}:
            assert time.monotonic() < deadline, f'took {taker.taken}, lost {taker.lost}'
            taker.drain(taken.extend)
            time.sleep(0.01)
        seqs = [deserialize_message(d, DeviceState).seq for _, _, d in taken]
        assert seqs == [*range(25, 34), 1004]
        assert taker.lost == [22]
        assert taker.lost_by_publisher() == [{f'{topic_prefix}/pub_a': 21,
                                              f'{topic_prefix}/pub_b': 1}]
        assert taker.taken[0] + taker.lost[0] == 3 + 2 + 32  # each taken or counted lost
        taker.destroy()
        for node in (a, b, owner):
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_udp_receive_buffers_are_enlarged_up_to_the_kernel_limit() -> None:
    """Every UDP socket of the process gets the asked receive buffer (Linux doubles the value
    and caps it at ``net.core.rmem_max``); other sockets are left alone."""
    import socket
    from pathlib import Path

    from haptic_topology.nodes.take import enlarge_udp_receive_buffers

    rmem_max = int(Path('/proc/sys/net/core/rmem_max').read_text())
    size = 1 << 20
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp, \
            socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
        tcp_before = tcp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        granted = enlarge_udp_receive_buffers(size)
        assert udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) == 2 * min(size, rmem_max)
        assert udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) in granted
        assert tcp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) == tcp_before


def test_the_recorders_history_holds_its_whole_depth(topic_prefix: str) -> None:
    """A burst of the recorder's history depth (``RECORD_BEST_EFFORT``, 10,000) between two
    drains is taken whole: Fast DDS's default of 5,000 samples per reader (max_samples) would
    keep only the newest 5,000 (the package's profile raises it)."""
    import rclpy
    from rclpy.serialization import deserialize_message

    from haptic_topology.vocabulary import RECORD_BEST_EFFORT
    from haptic_topology_msgs.msg import DeviceState

    depth = RECORD_BEST_EFFORT.depth
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        owner = rclpy.create_node('take_depth_test', context=context)
        pub_node = rclpy.create_node('pub', namespace=topic_prefix, context=context)
        topic = f'{topic_prefix}/state'
        pub = pub_node.create_publisher(DeviceState, topic, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        taker = BatchTaker(owner, [(topic, DeviceState, QoSProfile(
            depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT))])
        deadline = time.monotonic() + 20.0
        while not pub.get_subscription_count():
            assert time.monotonic() < deadline, 'publisher and reader never matched'
            time.sleep(0.01)
        _publish(pub, range(1, depth + 1))      # in one participant: delivered in publish()
        taken: list[tuple[int, int, bytes]] = []
        while len(taken) < depth and time.monotonic() < deadline:
            taker.drain(taken.extend)
            time.sleep(0.01)
        seqs = [deserialize_message(d, DeviceState).seq for _, _, d in taken]
        assert seqs == list(range(1, depth + 1)), (len(seqs), seqs[:3])
        taker.destroy()
        for node in (pub_node, owner):
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
