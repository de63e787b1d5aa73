"""Loop health as ``/diagnostics``: one-status arrays, matched endpoints, queued notices."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from haptic_topology.messages.check import RejectCounter, SourceGate


def diagnostics(node: Node, name: str, values: dict[str, str], level: int = 0,
                message: str = 'ok', hardware_id: str | None = None) -> DiagnosticArray:
    """A one-status :class:`DiagnosticArray` (level: DiagnosticStatus.OK/WARN/ERROR).

    ``hardware_id``: the hardware the status is about (the device driver: backend and device,
    :func:`haptic_topology.device.loop.hardware_id`); None for a node that drives no hardware,
    which reports its fully qualified node name. Every status carries ``pid``: the reporting
    process, so a tool that restarts a node can tell the new process's reports from late ones
    of the process it replaced."""
    values = {**values, 'pid': str(os.getpid())}
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    status = DiagnosticStatus(level=bytes([level]), name=name, message=message,
                              hardware_id=(node.get_fully_qualified_name() if hardware_id is None
                                           else hardware_id))
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    arr.status = [status]
    return arr


def matched(endpoints: Mapping[str, Any]) -> dict[str, str]:
    """Diagnostic values ``matched <topic>``: for each publisher the DDS readers matched to
    it, for each subscription the DDS writers matched to it (what the middleware actually
    connected, not the graph cache). A restarted node whose topic stays at 0 here is not
    connected, whatever the graph says."""
    out = {}
    for key, ep in endpoints.items():
        n = (ep.get_subscription_count() if hasattr(ep, 'get_subscription_count')
             else ep.get_publisher_count())
        out[f'matched {key}'] = str(n)
    return out


def log_notices(node: Node, notices: Any) -> None:
    """Log each text of ``notices`` (a list or deque another thread appends to: the loop
    thread's) as a warning of ``node``, oldest first, removing it."""
    while notices:
        try:
            text = notices.pop(0) if isinstance(notices, list) else notices.popleft()
        except IndexError:          # taken by another thread meanwhile
            break
        node.get_logger().warn(text)


def monotonic() -> float:
    return time.monotonic()


#: The name the graph cache gives an endpoint whose node it has not discovered yet
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'


#: Shortest interval (s) between two looks at the graph that a gate asks for.
REFRESH_PERIOD = 0.01


class PublisherWatch:
    """Publishers of a node's input topics that its graph does not expect.

    ``expected``: topic -> the node names that publish it in this graph (in this node's
    namespace). Every ``period`` s (steady clock) the node's graph cache is asked for the
    topic's publishers (``get_publishers_info_by_topic``); one of another name or another
    namespace is *foreign*: named in :meth:`values` and :meth:`problem` (the node reports
    ERROR while one is there) and logged once at ERROR the first time it appears; ``on_new``
    is called whenever one appears, so the node reports it at once rather than at its next
    diagnostics period.
    Messages are kept out by the graph identity (``graph_id``), not by this: DDS gives a
    message no publisher identity here, so this names who is there. What it sees feeds one
    :class:`~haptic_topology.messages.check.SourceGate` per topic (:attr:`gates`): whether a
    message that restarts its sender's numbering comes with a new own endpoint, and whether
    the graph can still tell its own messages from foreign ones.
    """

    def __init__(self, node: Node, expected: Mapping[str, tuple[str, ...]],
                 on_new: Any = None, period: float = 0.05) -> None:
        from rclpy.clock import Clock, ClockType

        self.node = node
        self.expected = {node.resolve_topic_name(t): (t, names) for t, names in expected.items()}
        self.foreign: dict[str, tuple[str, ...]] = {}     # topic -> 'namespace/name', sorted
        self.seen: set[str] = set()                       # every foreign publisher so far
        self.gates = {topic: SourceGate(topic, names[0], self._refresh)
                      for topic, names in expected.items()}
        self._on_new = on_new
        self._refreshed = -math.inf
        node.create_timer(period, self.check, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def check(self) -> None:
        ns = self.node.get_namespace()
        found: dict[str, tuple[str, ...]] = {}
        for resolved, (topic, names) in self.expected.items():
            others: set[str] = set()
            own: set[bytes] = set()
            for i in self.node.get_publishers_info_by_topic(resolved):
                if i.node_name == UNKNOWN_NODE:               # its name not discovered yet
                    continue
                if i.node_name in names and i.node_namespace == ns:
                    own.add(bytes(i.endpoint_gid))
                else:
                    others.add(f'{i.node_namespace.rstrip("/")}/{i.node_name}')
            if others:
                found[topic] = tuple(sorted(others))
            gate = self.gates[topic]
            told_apart = gate.distinct()
            gate.observe(frozenset(own), found.get(topic, ()))
            if told_apart and not gate.distinct():     # said once, when it happens
                self.node.get_logger().error(
                    f'{gate.lost()}; none is applied until {gate.owner} is back')
        before = {p for names in self.foreign.values() for p in names}
        now = {p for names in found.values() for p in names}
        self.foreign = found
        if now - self.seen:
            self.seen |= now
            self.node.get_logger().error(f'foreign publisher(s) on the graph\'s topics: '
                                         f'{self.describe()}; their messages are not applied '
                                         'unless they carry this graph\'s graph_id')
        if now - before and self._on_new is not None:
            self._on_new()          # reported at once, also when one comes back

    def admits(self, topic: str, rejected: RejectCounter) -> bool:
        """Whether a message of this graph on ``topic`` may be taken now (else it is counted
        in ``rejected``): not while no expected publisher of the graph is there and a
        foreign one is (:meth:`~haptic_topology.messages.check.SourceGate.refuse`)."""
        refusal = self.gates[topic].refuse()
        if refusal is not None:
            rejected.add(refusal)
        return refusal is None

    def _refresh(self) -> None:
        """A gate's look at the graph before it refuses; at most every
        :data:`REFRESH_PERIOD` s (a sender cannot make the node query the graph per
        message)."""
        now = time.monotonic()
        if now - self._refreshed >= REFRESH_PERIOD:
            self._refreshed = now
            self.check()

    def describe(self) -> str:
        return '; '.join(f'{t}: {", ".join(p)}' for t, p in sorted(self.foreign.items()))

    def problem(self) -> str | None:
        """The ERROR message while a foreign publisher is there (None: none)."""
        if not self.foreign:
            return None
        lost = [text for g in self.gates.values() if (text := g.lost()) is not None]
        return '; '.join([*lost, f'foreign publisher(s): {self.describe()}'])

    def values(self) -> dict[str, str]:
        """``foreign_publishers``: the foreign publishers now, ``topic: name, ...; ...``."""
        return {'foreign_publishers': self.describe()}

    def merge(self, values: dict[str, str], level: int, message: str) -> tuple[int, str]:
        """Add :meth:`values` to a node's ``values``; its ``(level, message)``, ERROR while a
        foreign publisher is there."""
        values.update(self.values())
        problem = self.problem()
        return (2, f'{problem}; {message}') if problem else (level, message)
