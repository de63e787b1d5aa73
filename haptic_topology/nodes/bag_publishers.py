"""Publishing a bag's messages into a live graph: one publisher per topic with the QoS its
recorded publishers offered, plain or paced in lock-step, and the rclpy spinner the replay
and the controller check run in (see :mod:`haptic_topology.nodes.replay`)."""

from __future__ import annotations

import importlib
import threading
import time
from collections.abc import Container, Iterable, Mapping
from typing import Any

from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos

from haptic_topology.bag.reader import (
    Bag,
    read_channels,
)
from haptic_topology.bag.replay import (
    COMMAND,
    STATE,
    Item,
    ReplayStats,
)
from haptic_topology.errors import BagError, ReplayError
from haptic_topology.vocabulary import TOPIC_DIAGNOSTICS

#: How long (s) a replay waits at its end for its reliable messages to be acknowledged.
ACK_TIMEOUT = 10.0


def _qos_profile(metadata: dict[str, str], topic: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliable, depth = True, 10
    try:
        offered = parse_qos(metadata.get('offered_qos_profiles', ''))
    except (ReaderError, KeyError, TypeError):
        offered = []
    if offered:
        reliable = all(q.reliability.name == 'RELIABLE' for q in offered)
        depth = max(1, max(q.depth for q in offered))
    elif topic.endswith((STATE, COMMAND)):
        reliable, depth = False, 1
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Type``."""
    pkg, _, name = msgtype.partition('/msg/')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise BagError(f'message type {msgtype}: no Python message package {pkg} installed '
                       'to publish it') from None


def _update_seq(data: Any) -> int:
    """``LmiUpdate.seq`` of a message as published (a message object or raw CDR)."""
    seq = getattr(data, 'seq', None)
    if seq is None:
        from rclpy.serialization import deserialize_message

        from haptic_topology_msgs.msg import LmiUpdate
        seq = deserialize_message(data, LmiUpdate).seq
    return int(seq)


class Publishers:
    """One publisher per topic of ``topics`` (topic -> type; QoS from the bag), under
    ``namespace``, by ``node`` or, for a topic in ``nodes`` (name without the leading slash),
    by that node."""

    def __init__(self, node: Any, bag: Bag, topics: Mapping[str, str], namespace: str = '',
                 nodes: Mapping[str, Any] | None = None) -> None:
        channels = read_channels(bag)
        self.pubs: dict[str, Any] = {}
        for topic, msgtype in topics.items():
            name = topic if not namespace or topic == TOPIC_DIAGNOSTICS else (
                namespace.rstrip('/') + '/' + topic.lstrip('/'))
            qos = _qos_profile(channels.get(topic, {}).get('metadata', {}), topic)
            owner = (nodes or {}).get(topic.lstrip('/'), node)
            self.pubs[topic] = owner.create_publisher(message_class(msgtype), name, qos)

    def wait_for_subscribers(self, topics: Iterable[str], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        pending = [t for t in topics if t in self.pubs]
        while pending and time.monotonic() < deadline:
            pending = [t for t in pending if self.pubs[t].get_subscription_count() == 0]
            time.sleep(0.02)
        if pending:
            raise ReplayError(f'no subscriber on {", ".join(pending)} within {timeout:g} s')
        # The publisher sees the subscriber first; a reliable message sent before the
        # subscriber has matched this publisher in turn would be lost.
        time.sleep(0.5)

    def wait_acked(self, timeout: float = ACK_TIMEOUT) -> list[str]:
        """Wait until every matched subscriber of each reliable topic has acknowledged what
        was published (at most ``timeout`` s in all); return the topics still waiting. A
        publisher destroyed earlier drops what a slow subscriber has not taken yet."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout
        return sorted(t for t, pub in self.pubs.items() if not pub.wait_for_all_acked(
            Duration(seconds=max(deadline - time.monotonic(), 0.0))))

    def publish(self, items: Iterable[Item], span: float, rate: float, loop: bool = False,
                stop: threading.Event | None = None) -> ReplayStats:
        """Publish ``items`` at their times / ``rate`` (again and again with ``loop``: each
        round iterates ``items`` anew); ``span``: the last item's time (s)."""
        stats = ReplayStats()
        start = time.perf_counter()
        rounds = 0
        while True:
            base = start + rounds * (span / rate + 1e-3)
            for it in items:
                due = base + it.t / rate
                while (rem := due - time.perf_counter()) > 0:
                    time.sleep(rem)
                if stop is not None and stop.is_set():
                    break
                self.pubs[it.topic].publish(it.data)
                stats.late_ms.add(1e3 * (time.perf_counter() - due))
                stats.published[it.topic] = stats.published.get(it.topic, 0) + 1
            rounds += 1
            if not loop or (stop is not None and stop.is_set()):
                break
        stats.wall_s = time.perf_counter() - start
        return stats


    def publish_lockstep(self, items: Iterable[Item], answered: threading.Condition,
                         done: Container[int], acked: dict[int, int], timeout: float = 0.3,
                         retries: int = 3) -> ReplayStats:
        """Publish ``items`` in order, each only once the previous one was taken: a state
        once it was answered (``done``), an update once the controller acknowledged it
        (``acked``: update seq -> count, on ``haptic/lmi/ack``), so the controller sees the
        recorded order whatever the machine's load.

        A message whose answer or acknowledgement does not come within ``timeout`` is
        published again (the controller ignores a state it has already answered; an update
        taken twice is the same re-sync), up to ``retries`` times.
        """
        stats = ReplayStats()
        start = time.perf_counter()
        for it in items:
            pub = self.pubs[it.topic]
            if it.seq < 0:
                useq = _update_seq(it.data)
                before = acked.get(useq, 0)

                def taken(useq: int = useq, before: int = before) -> bool:
                    return acked.get(useq, 0) > before

                with answered:
                    for _ in range(retries):
                        pub.publish(it.data)
                        if answered.wait_for(taken, timeout):
                            break
                    acked.pop(useq, None)   # (kept small: one entry per update in flight)
            else:
                seq = it.seq

                def seen(seq: int = seq) -> bool:
                    return seq in done

                with answered:
                    for _ in range(retries):
                        pub.publish(it.data)
                        if answered.wait_for(seen, timeout):
                            break
            stats.published[it.topic] = stats.published.get(it.topic, 0) + 1
        stats.wall_s = time.perf_counter() - start
        return stats
