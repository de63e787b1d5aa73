"""``foxglove_bridge``: the graph's live topics on the Foxglove WebSocket protocol.

For a Foxglove app or Lichtblick without a ROS install (docs/foxglove.md): the node serves every
topic of the graph's vocabulary (:data:`~haptic_topology.nodes.TOPIC_QOS`, or those named in
``topics``) on ``ws://host:port`` (default ``127.0.0.1:8765``) under both names of the
protocol, ``foxglove.sdk.v1`` and ``foxglove.websocket.v1``. The channels are the Foxglove
SDK's (``foxglove-sdk``: its server listens on a free loopback port); the public port is
:class:`~haptic_topology.net.foxglove_front.FoxgloveFront`, which accepts either name, relays
the frames unchanged and bounds each client's outbox to ``message_backlog`` messages (the
oldest dropped and counted for that client only). ``docs/foxglove_layout.json`` is a layout.

Each topic is one channel: message encoding ``cdr``, schema encoding ``ros2msg``, schema name
the ROS type (:data:`~haptic_topology.nodes.TOPIC_TYPES`) and schema text the
concatenated .msg definitions rosbag2 writes into MCAP files (the ones the recorder's bags
carry, :func:`haptic_topology.bag.writer.schema_text`). The serialized CDR bytes are forwarded
as DDS delivered them, never deserialised: as the recorder, the node takes what DDS holds in
each reader every ``forward_period`` (:class:`~haptic_topology.nodes.take.BatchTaker`, one
thread, no executor callback per message) and logs it on the channel, timestamped with the
DDS receive time. A channel without a subscribed client costs the take only. A latched
topic (``/robot_description``) is logged again when a client subscribes to it, so an app that
connects after the VE started still gets the linkage's URDF.

Off the deadline path: its own process (``haptic-topology run ... --foxglove``), reading the
topics with the reliability and durability their publishers offer (best effort state and
command in real time; ``/robot_description`` transient local, so a late bridge still gets it).

Diagnostics (``foxglove_bridge: server``, 1 Hz): ``url``, ``port`` (the one taken: with
``port`` 0 the OS chooses), ``channels``, ``clients``, ``dropped`` (messages dropped for slow
clients since the start, all clients), per connected client ``client <address>``
(subprotocol, messages sent, dropped, waiting now, most ever waiting) and per topic
``forwarded <topic>`` and ``lost <topic>`` (see :class:`~haptic_topology.nodes.take.BatchTaker`).
"""

from __future__ import annotations

import importlib
import threading
from collections.abc import Sequence
from typing import Any

import foxglove
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile

from haptic_topology.bag.writer import schema_text
from haptic_topology.config import node_params
from haptic_topology.config.settings import FoxgloveBridgeSettings
from haptic_topology.errors import ConfigError
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs
from haptic_topology.net.foxglove_front import FoxgloveFront
from haptic_topology.nodes.diagnostics import diagnostics
from haptic_topology.nodes.parameters import declare_settings
from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, TOPIC_QOS, publisher_qos
from haptic_topology.nodes.runtime import run_main
from haptic_topology.nodes.take import BatchTaker
from haptic_topology.vocabulary import (
    STATUS_FOXGLOVE,
    TOPIC_DIAGNOSTICS,
    TOPIC_ROLES,
    TOPIC_TYPES,
    Clock,
)

#: Messages each reader holds between two takes (1 kHz topics: 20 per default period).
READER_DEPTH = 200
#: What ``ros2msg`` schemas and ``cdr`` messages are called in the Foxglove protocol.
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'


def served_topics(names: Sequence[str]) -> list[str]:
    """Topics of the vocabulary to serve: all if ``names`` is empty, else ``names`` (with or
    without the leading '/'), which must be in the vocabulary."""
    known = list(TOPIC_QOS)
    if not names:
        return known
    by_name = {t.lstrip('/'): t for t in known}
    unknown = [n for n in names if n.lstrip('/') not in by_name]
    if unknown:
        raise ConfigError(f'foxglove_bridge: parameter topics: unknown {", ".join(unknown)}; '
                          f'known: {", ".join(known)}')
    return [by_name[n.lstrip('/')] for n in names]


def message_class(type_name: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name``."""
    pkg, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def reader_qos(topic: str, clock: Clock) -> QoSProfile:
    """The bridge's reader of ``topic``: reliability and durability as the graph's publisher
    offers them under ``clock``, keep last :data:`READER_DEPTH`."""
    pub = publisher_qos(topic, clock)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=READER_DEPTH,
                      reliability=pub.reliability, durability=pub.durability)


class _Relatch(foxglove.websocket.ServerListener):
    """Logs a latched topic's last message again when a client subscribes to its channel."""

    def __init__(self) -> None:
        self.last: dict[int, tuple[foxglove.Channel, bytes, int]] = {}   # channel id ->

    def on_subscribe(self, client: Any, channel: Any) -> None:
        held = self.last.get(channel.id)
        if held is not None:
            held[0].log(held[1], log_time=held[2])


class FoxgloveBridge(Node):
    """Serves the graph's topics to Foxglove clients (see module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('foxglove_bridge', **kwargs)
        self.settings = s = declare_settings(self, FoxgloveBridgeSettings)
        clock = Clock.parse(s.clock)
        topics = served_topics([n for n in s.topics if n])
        store = typestore_with_haptic_msgs()
        sources = message_definitions()
        self.context_fg = foxglove.Context()
        self.channels: list[foxglove.Channel] = []
        self.topics: list[str] = []
        readers = []
        for topic in topics:
            type_name = TOPIC_TYPES[topic]
            try:
                cls = message_class(type_name)
            except (ImportError, AttributeError) as exc:
                self.get_logger().warn(f'{topic}: {type_name} not importable ({exc}); '
                                       'not served')
                continue
            name = self.resolve_topic_name(topic)
            schema = foxglove.Schema(name=type_name, encoding=SCHEMA_ENCODING,
                                     data=schema_text(store, type_name, sources).encode())
            self.channels.append(foxglove.Channel(name, schema=schema,
                                                  message_encoding=MESSAGE_ENCODING,
                                                  context=self.context_fg))
            self.topics.append(topic)
            readers.append((name, cls, reader_qos(topic, clock)))
        self.latched = {i for i, t in enumerate(self.topics) if TOPIC_ROLES[t].transient_local}
        self.relatch = _Relatch()
        # The SDK's server, reached through the front only: loopback, any free port.
        self.server = foxglove.start_server(name=f'haptic_topology ({s.scenario})',
                                            host='127.0.0.1', port=0, context=self.context_fg,
                                            server_listener=self.relatch,
                                            message_backlog_size=s.message_backlog)
        try:
            self.front = FoxgloveFront(s.host, s.port, int(self.server.port), s.message_backlog)
        except ConfigError:
            self.server.stop()
            raise
        self.port = self.front.port
        self.url = f'ws://{s.host}:{self.port}'
        self.taker = BatchTaker(self, readers)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._forward_loop, name='foxglove-forward',
                                        daemon=True)
        self._thread.start()
        self._open = True
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        self.create_timer(1.0, self._publish_status)
        self.get_logger().info(f'serving {len(self.channels)} topics on {self.url}')

    def _forward(self, items: list[tuple[int, int, bytes]]) -> None:
        channels = self.channels
        wanted = [c.has_sinks() for c in channels]
        for i, t_ns, data in items:
            if i in self.latched:
                self.relatch.last[channels[i].id()] = (channels[i], data, t_ns)
            if wanted[i]:
                channels[i].log(data, log_time=t_ns)

    def _forward_loop(self) -> None:
        """Thread: every ``forward_period`` take what DDS holds and log it on the channels."""
        period = self.settings.forward_period
        while not self._stop.wait(period):
            self.taker.drain(self._forward)

    def _publish_status(self) -> None:
        clients = self.front.stats()
        dropped = self.front.dropped_closed + sum(c.dropped for c in clients)
        values = {'url': self.url, 'port': str(self.port), 'channels': str(len(self.channels)),
                  'clients': str(len(clients)), 'dropped': str(dropped),
                  **{f'client {c.address}': f'{c.subprotocol} sent {c.sent} dropped '
                     f'{c.dropped} waiting {c.queued} peak {c.peak_queued}' for c in clients},
                  **{f'forwarded {t}': str(n) for t, n in zip(self.topics, self.taker.taken,
                                                               strict=True)},
                  **{f'lost {t}': str(n) for t, n in zip(self.topics, self.taker.lost,
                                                          strict=True) if n}}
        self.diag_pub.publish(diagnostics(self, STATUS_FOXGLOVE, values, 0,
                                                 f'serving on {self.url}'))

    def close(self) -> None:
        """Stop forwarding and the server; idempotent."""
        if not getattr(self, '_open', False):
            return
        self._open = False
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.taker.destroy()
        self.front.stop()
        self.server.stop()


def main(args: Sequence[str] | None = None) -> int:
    return run_main('foxglove_bridge', lambda: [FoxgloveBridge()], args,
                           node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
