"""The bringup's "publishers matched to their readers" (``GraphWatcher.unmatched``) and
"subscriptions matched to their writers" (``unmatched_readers``) with another program's reader
or writer on the topic, over DDS: a matched count says how many peers an endpoint matched, not
which, so the watcher asks for as many as it sees peers the endpoint matches (not those of
another type or with a QoS that does not match), and for the graph's own to be there."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from haptic_topology.bringup.watch import CONTROLLER_STATUS, VE_STATUS, GraphWatcher
from haptic_topology.nodes.qos import hand_inputs_qos
from haptic_topology.vocabulary import TOPIC_HAND_INPUTS, Clock
from haptic_topology_msgs.msg import HandInputs

pytestmark = pytest.mark.graph

KEY = (CONTROLLER_STATUS, TOPIC_HAND_INPUTS)


@contextmanager
def _on_domain(domain: int, build: Callable[[Any, Any, list[Any]], Any]
               ) -> Iterator[tuple[GraphWatcher, Any]]:
    """A watcher on ``domain`` and what ``build(ctx, ctx_other, nodes)`` returns (the
    endpoint under test), its nodes created in two contexts of their own (one type per topic
    name in one) and appended to ``nodes``; all destroyed afterwards."""
    watch = GraphWatcher('haptic_bringup', domain_id=domain)
    ctx, ctx_other = rclpy.Context(), rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    rclpy.init(context=ctx_other, domain_id=domain)
    nodes: list[Any] = []
    try:
        yield watch, build(ctx, ctx_other, nodes)
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        rclpy.try_shutdown(context=ctx_other)
        watch.close()


def _discover(watch: GraphWatcher, seen: Callable[[], int], want_seen: int,
              matched: Callable[[], int], want_matched: int) -> int:
    """Spin until the watcher sees ``want_seen`` peers and the endpoint has matched
    ``want_matched``; then, half a second later, the endpoint's matched count."""
    deadline = time.monotonic() + 30.0
    while seen() < want_seen or matched() < want_matched:
        assert time.monotonic() < deadline, (seen(), matched())
        watch.spin(0.05)
    time.sleep(0.5)
    return matched()


@pytest.fixture()
def graph(spare_domains: list[int]) -> Iterator[tuple[GraphWatcher, Any]]:
    """A watcher and, in a context of their own: the controller's hand-input publisher; the
    VE's and the recorder's readers; an ``intruder``'s reader the publisher matches; a
    ``late_joiner``'s (transient local: not offered) and an ``other_type``'s, which it never
    matches (in a second context)."""
    def build(ctx: Any, ctx_other: Any, nodes: list[Any]) -> Any:
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
        nodes += [late, other, ctl]
        return ctl.create_publisher(HandInputs, TOPIC_HAND_INPUTS, qos)

    with _on_domain(spare_domains[0], build) as out:
        yield out


def test_a_foreign_reader_cannot_stand_in_for_one_of_the_graph(
        graph: tuple[GraphWatcher, Any]) -> None:
    watch, pub = graph
    # Discovery: the watcher sees the five readers, the publisher matches its three.
    matched = _discover(
        watch, lambda: len(watch.node.get_subscriptions_info_by_topic(f'/{TOPIC_HAND_INPUTS}')),
        5, pub.get_subscription_count, 3)
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


@pytest.fixture()
def inputs(spare_domains: list[int]) -> Iterator[tuple[GraphWatcher, Any]]:
    """A watcher and, in a context of their own: the VE's hand-input subscription; the
    controller's publisher and an ``intruder``'s, which it matches; a ``best_effort`` one
    (the subscription asks for reliable: never matched) and an ``other_type``'s (in a second
    context)."""
    def build(ctx: Any, ctx_other: Any, nodes: list[Any]) -> Any:
        qos = hand_inputs_qos(Clock.WALL)
        for name in ('lmi_controller', 'intruder'):
            node = rclpy.create_node(name, context=ctx)
            node.create_publisher(HandInputs, TOPIC_HAND_INPUTS, qos)
            nodes.append(node)
        loose = rclpy.create_node('best_effort', context=ctx)
        loose.create_publisher(HandInputs, TOPIC_HAND_INPUTS,
                               QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        other = rclpy.create_node('other_type', context=ctx_other)
        other.create_publisher(String, TOPIC_HAND_INPUTS, 10)
        ve = rclpy.create_node('ve_sim', context=ctx)
        nodes += [loose, other, ve]
        return ve.create_subscription(HandInputs, TOPIC_HAND_INPUTS, lambda _: None, qos)

    with _on_domain(spare_domains[0], build) as out:
        yield out


def test_a_foreign_writer_cannot_stand_in_for_the_graphs_on_the_readers_side(
        inputs: tuple[GraphWatcher, Any]) -> None:
    watch, sub = inputs
    key = (VE_STATUS, TOPIC_HAND_INPUTS)
    # Discovery: the watcher sees the four writers, the subscription matches its two.
    matched = _discover(
        watch, lambda: len(watch.node.get_publishers_info_by_topic(f'/{TOPIC_HAND_INPUTS}')),
        4, sub.get_publisher_count, 2)
    assert matched == 2         # lmi_controller, intruder; never best_effort, other_type

    def ready(count: int, own: int = 1) -> bool:
        watch.status[VE_STATUS] = {f'matched {TOPIC_HAND_INPUTS}': str(count)}
        return watch.readers_matched({key: own}, Clock.WALL)

    assert ready(matched)
    # One matched of the two: it may be the intruder's, with the controller's first inputs
    # still to come (and then taken as copies of the intruder's).
    assert not ready(1)
    (line,) = watch.unmatched_readers({key: 1}, Clock.WALL)
    assert 'matched to 1 writers of 2' in line and '/intruder' in line, line
    # A writer of the graph that the watcher does not see: not matched, whatever the count.
    assert not ready(matched + 2, own=2)
