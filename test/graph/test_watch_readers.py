"""The bringup's "publishers matched to their readers" (``GraphWatcher.unmatched``) with another
program's reader on the topic, over DDS: a writer's matched count says how many readers it
matched, not which, so the watcher asks for as many as it sees readers the writer matches
(not those of another type or asking for a QoS it does not offer), and for the graph's own
readers to be there."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from haptic_topology.bringup.watch import CONTROLLER_STATUS, GraphWatcher
from haptic_topology.nodes.qos import hand_inputs_qos
from haptic_topology.vocabulary import TOPIC_HAND_INPUTS, Clock
from haptic_topology_msgs.msg import HandInputs

pytestmark = pytest.mark.graph

KEY = (CONTROLLER_STATUS, TOPIC_HAND_INPUTS)


@pytest.fixture()
def graph(spare_domains: list[int]) -> Iterator[tuple[GraphWatcher, Any]]:
    """A watcher and, in a context of their own: the controller's hand-input publisher; the
    VE's and the recorder's readers; an ``intruder``'s reader the publisher matches; a
    ``late_joiner``'s (transient local: not offered) and an ``other_type``'s, which it never
    matches (in a second context: one type per topic name in one)."""
    domain = spare_domains[0]
    watch = GraphWatcher('haptic_bringup', domain_id=domain)
    ctx, ctx_other = rclpy.Context(), rclpy.Context()   # one type per topic in a process
    rclpy.init(context=ctx, domain_id=domain)
    rclpy.init(context=ctx_other, domain_id=domain)
    nodes = []
    try:
        qos = hand_inputs_qos(Clock.WALL)
        for name in ('ve_sim', 'recorder', 'intruder'):
            node = rclpy.create_node(name, context=ctx)
            node.create_subscription(HandInputs, TOPIC_HAND_INPUTS, lambda _: None, qos)
            nodes.append(node)
        late = rclpy.create_node('late_joiner', context=ctx)
        late.create_subscription(HandInputs, TOPIC_HAND_INPUTS, lambda _: None,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        other = rclpy.create_node('other_type', context=ctx_other)
        other.create_subscription(String, TOPIC_HAND_INPUTS, lambda _: None, 10)
        ctl = rclpy.create_node('lmi_controller', context=ctx)
        pub = ctl.create_publisher(HandInputs, TOPIC_HAND_INPUTS, qos)
        nodes += [late, other, ctl]
        yield watch, pub
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        rclpy.try_shutdown(context=ctx_other)
        watch.close()


def test_a_foreign_reader_cannot_stand_in_for_one_of_the_graph(
        graph: tuple[GraphWatcher, Any]) -> None:
    watch, pub = graph
    deadline = time.monotonic() + 30.0
    # Discovery: the watcher sees the five readers, the publisher matches its three.
    while (len(watch.node.get_subscriptions_info_by_topic(f'/{TOPIC_HAND_INPUTS}')) < 5
           or pub.get_subscription_count() < 3):
        assert time.monotonic() < deadline, pub.get_subscription_count()
        watch.spin(0.05)
    time.sleep(0.5)
    matched = pub.get_subscription_count()
    assert matched == 3         # ve_sim, recorder, intruder; never late_joiner, other_type

    def ready(count: int, own: int = 2) -> bool:
        watch.status[CONTROLLER_STATUS] = {f'matched {TOPIC_HAND_INPUTS}': str(count)}
        return watch.writers_matched({KEY: own}, Clock.WALL)

    # What the publisher reports once it has matched every reader it will.
    assert ready(matched)
    # Two matched of the three: the recorder and the intruder may be the two, with the VE's
    # inputs lost; a count of 2 was what the graph expects, and it is not enough here.
    assert not ready(2)
    (line,) = watch.unmatched({KEY: 2}, Clock.WALL)
    assert 'matched to 2 readers of 3' in line and '/intruder' in line, line
    # Expecting a reader of the graph that the watcher does not see (a third node): not
    # matched, whatever the count.
    assert not ready(matched + 2, own=3)
