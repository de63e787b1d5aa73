"""Messages taken off the executor: in batches (the recorder's input side, :class:`BatchTaker`)
or the newest one on demand (``ve_sim``'s device state for the visualisation,
:class:`LatestTaker`).

A subscription spun by an executor costs one wake-up and one Python callback per message
(a subscriber taking 1,000 msg/s on the EventsExecutor used 0.08 core on the 2-core machine
this was measured on, ~80 us a message): at 30,000 msg/s that is more than two cores.
:class:`BatchTaker` instead subscribes from a hidden helper node
(``_<node>_reader``, left out of ``ros2 node list``) that no executor spins: DDS keeps the
samples in each reader's history (the recorder's deep queues, ``QOS_RECORD_*``), and one thread
takes everything there every few milliseconds with ``rcl_take_serialized_message``
(:mod:`haptic_topology.nodes.rcl_take`, ~3 us a message), with the time DDS received it and
the publisher's gid and sequence number.

Drops are counted per publisher, not guessed: a gap in a publisher's sequence numbers between
two of its samples taken is that many messages it sent and this reader never took, whatever
dropped them (the network or a full socket buffer for best effort, the reader's keep-last
history overflowing between two takes, the publisher's own history dropping samples a
reliable reader had not acknowledged). A topic's count is the larger of its publishers' gaps
summed and DDS's own count (the ``MESSAGE_LOST`` event, best-effort gaps, which DDS can
report before the publisher's next sample is taken but does not attribute to a publisher).
Messages a publisher sent before this reader matched it, and ones lost after its last sample
taken, are not gaps.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Sequence
from typing import Any

from rclpy.event_handler import QoSSubscriptionEventType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile

from haptic_topology.nodes.rcl_take import Gid, SerializedTaker, gid_bytes, gid_of

#: ``write([(topic_index, receive_time_ns, serialized), ...])``, oldest first
Write = Callable[[list[tuple[int, int, bytes]]], None]


def _receive_time(item: tuple[int, int, bytes]) -> int:
    return item[1]


def _never_called(_: Any) -> None:  # the reader node is never spun
    raise AssertionError('BatchTaker subscriptions are taken, not spun')


#: Receive buffer asked for the recorder's DDS sockets (bytes; Linux caps it at
#: ``net.core.rmem_max`` and doubles it for its bookkeeping)
RECEIVE_BUFFER = 4 << 20


def enlarge_udp_receive_buffers(size: int = RECEIVE_BUFFER) -> list[int]:
    """Ask for ``size``-byte receive buffers on every UDP socket of this process; return the
    sizes Linux granted.

    Over UDP (the nodes' DDS transport, ``config/fastdds_localhost.xml``) a burst larger than
    the socket's receive buffer is dropped by the kernel (``RcvbufErrors``; DDS then reports
    the best-effort samples lost). rmw_fastrtps's ``LOCALHOST`` setup builds its own UDP
    transport with the kernel's default buffer (``net.core.rmem_default``, 212,992 bytes
    here), which a recorder taking 30,000 msg/s overflows; the profile's socket sizes apply
    to Fast DDS's built-in transports only. Called once the participant exists.
    """
    granted = []
    for name in os.listdir('/proc/self/fd'):
        try:
            fd = int(name)
            if not os.readlink(f'/proc/self/fd/{name}').startswith('socket:'):
                continue
            sock = socket.socket(fileno=os.dup(fd))
        except (OSError, ValueError):
            continue
        with sock:
            if sock.type == socket.SOCK_DGRAM and sock.family in (socket.AF_INET,
                                                                   socket.AF_INET6):
                if sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) < size:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
                granted.append(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    return granted


class BatchTaker:
    """Subscriptions to ``topics`` (absolute names, ``(name, rclpy type, QoS)``) of the node
    ``owner``, taken in batches by :meth:`drain` from any one thread."""

    def __init__(self, owner: Node, topics: Sequence[tuple[str, Any, QoSProfile]]) -> None:
        self.node = Node(f'_{owner.get_name()}_reader', namespace=owner.get_namespace(),
                         context=owner.context, start_parameter_services=False,
                         enable_rosout=False)
        self.subscriptions = [self.node.create_subscription(t, name, _never_called, qos,
                                                            raw=True)
                              for name, t, qos in topics]
        self._takers = [SerializedTaker(sub) for sub in self.subscriptions]
        self._lost_events: list[Any] = []
        for sub in self.subscriptions:
            try:
                with sub.handle:
                    self._lost_events.append(_rclpy.EventHandle(
                        sub.handle, QoSSubscriptionEventType.RCL_SUBSCRIPTION_MESSAGE_LOST))
            except _rclpy.UnsupportedEventTypeError:
                self._lost_events.append(None)
        enlarge_udp_receive_buffers()
        n = len(topics)
        self.taken = [0] * n
        self.lost_dds = [0] * n
        #: per topic: publisher gid -> messages it sent that were never taken (gaps)
        self.lost_by_gid: list[dict[Gid, int]] = [{} for _ in range(n)]
        self._last_seq: list[dict[Gid, int]] = [{} for _ in range(n)]
        self._names: dict[Gid, str] = {}

    @property
    def lost_gaps(self) -> list[int]:
        """Messages per topic missing from its publishers' sequence numbers."""
        return [sum(d.copy().values()) for d in self.lost_by_gid]

    @property
    def lost(self) -> list[int]:
        """Messages per topic that were published but not taken (see module doc)."""
        # A sample lost on the way is both reported by DDS and a gap: count it once.
        return [max(a, b) for a, b in zip(self.lost_dds, self.lost_gaps, strict=True)]

    def lost_by_publisher(self) -> list[dict[str, int]]:
        """Per topic: publisher -> messages lost (only publishers that lost any). A publisher
        is named by its node (``/namespace/name``) as the ROS graph gives it, with its gid in
        hex where one node has several of the topic's publishers, or by ``gid <hex>`` alone
        if it left the graph before it could be named."""
        out = []
        for sub, lost_by_gid in zip(self.subscriptions, self.lost_by_gid, strict=True):
            lost = {g: n for g, n in lost_by_gid.copy().items() if n}
            if any(g not in self._names for g in lost):     # a graph query while one is unnamed
                for info in self.node.get_publishers_info_by_topic(sub.topic_name):
                    self._names[gid_of(bytes(info.endpoint_gid))] = \
                        f'{info.node_namespace.rstrip("/")}/{info.node_name}'
            names = [self._names.get(g, '') for g in lost]
            labels = [(name if names.count(name) == 1 else f'{name} {gid_bytes(g).hex()}')
                      if name else f'gid {gid_bytes(g).hex()}'
                      for g, name in zip(lost, names, strict=True)]
            out.append(dict(zip(labels, lost.values(), strict=True)))
        return out

    def publisher_counts(self) -> list[int]:
        return [sub.get_publisher_count() for sub in self.subscriptions]

    def drain(self, write: Write) -> int:
        """Take every sample waiting in every reader and hand them to ``write`` in one list,
        in the order DDS received them (across topics too, as a recorder taking each message
        on arrival would); return how many were taken."""
        items: list[tuple[int, int, bytes]] = []
        now = time.time_ns()        # for an rmw that gives no receive time
        for i, taker in enumerate(self._takers):
            self.taken[i] += taker.take_into(items, i, self._last_seq[i], self.lost_by_gid[i],
                                             now)
        items.sort(key=_receive_time)
        if items:
            write(items)
        for i, ev in enumerate(self._lost_events):
            if ev is not None:
                with ev:
                    self.lost_dds[i] = int(ev.take_event().total_count)
        return len(items)

    def destroy(self) -> None:
        for taker in self._takers:
            taker.destroy()
        for ev in self._lost_events:
            if ev is not None:
                ev.destroy_when_not_in_use()
        for sub in self.subscriptions:
            self.node.destroy_subscription(sub)
        self.node.destroy_node()


class LatestTaker:
    """The newest message of one topic, taken when asked (e.g. at a visualisation rate) instead
    of one executor callback per message.

    Like :class:`BatchTaker`, the subscription belongs to a hidden helper node
    (``_<node>_<suffix>``) that no executor spins; with a keep-last-1 QoS DDS holds only the
    newest sample, and :meth:`take` deserialises that one. ``topic`` is resolved by ``owner``
    (its namespace and remappings).
    """

    def __init__(self, owner: Node, topic: str, msg_type: Any, qos: QoSProfile,
                 suffix: str = 'latest') -> None:
        self.node = Node(f'_{owner.get_name()}_{suffix}', namespace=owner.get_namespace(),
                         context=owner.context, start_parameter_services=False,
                         enable_rosout=False)
        self.subscription = self.node.create_subscription(
            msg_type, owner.resolve_topic_name(topic), _never_called, qos)
        self._type = msg_type
        self.taken = 0

    def take(self) -> Any:
        """The newest message that came since the last call, or None."""
        newest = None
        handle = self.subscription.handle
        with handle:
            while (item := handle.take_message(self._type, False)) is not None:
                newest = item[0]
                self.taken += 1
        return newest

    def destroy(self) -> None:
        self.node.destroy_subscription(self.subscription)
        self.node.destroy_node()
