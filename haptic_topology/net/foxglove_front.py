"""The public face of the live view: one WebSocket port that speaks both names of the Foxglove
protocol, with a bounded outbox per client (no rclpy).

The Foxglove SDK's server (``foxglove-sdk``) accepts the subprotocol ``foxglove.sdk.v1`` only
and answers HTTP 400 to clients that offer ``foxglove.websocket.v1`` alone: Lichtblick,
older Foxglove Studio builds and every client built on ``@foxglove/ws-protocol``. Under
``foxglove.sdk.v1`` the SDK sends the frames of the ws-protocol specification
(foxglove/ws-protocol ``docs/spec.md``) unchanged: JSON ``serverInfo``, ``advertise``
(``id``, ``topic``, ``encoding``, ``schemaName``, ``schemaEncoding``, ``schema``),
``status``, ``unadvertise``; binary ``messageData`` (opcode 1, uint32 subscription id,
uint64 receive time in ns, payload) and ``time`` (opcode 2); it takes the client's
``subscribe``/``unsubscribe`` as the spec writes them. (``foxglove.sdk.v1.1`` differs: its
``advertise`` carries schemas by id. It is never asked for here.)

:class:`FoxgloveFront` listens on the public address with the ``websockets`` library and
accepts either name (``foxglove.sdk.v1`` preferred when a client offers both; a client that
offers neither gets HTTP 400 naming both). For each client it opens one connection to the
SDK's server on the loopback interface, offering ``foxglove.sdk.v1``, and relays every
frame in both directions unchanged.

Bounded per client: frames from the SDK are read as they come, whatever the client does,
into the client's :class:`Outbox`; a writer sends them on as fast as the client takes them.
When more than ``backlog`` ``messageData`` frames wait, the oldest is dropped and counted
(:attr:`ClientStats.dropped`); a client whose waiting control frames (JSON) exceed
``backlog`` is disconnected (close code 1008). A client that stops reading therefore holds at
most ``backlog`` frames, its socket's send buffer (:data:`SEND_BUFFER`) and the library's
write buffer (``write_limit``), and never slows the SDK's server or another client.
"""

from __future__ import annotations

import asyncio
import itertools
import socket
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, NegotiationError
from websockets.typing import Data, Subprotocol

from haptic_topology.errors import ConfigError

#: The Foxglove SDK's name of the protocol (what its server accepts).
SDK_SUBPROTOCOL = Subprotocol('foxglove.sdk.v1')
#: The ws-protocol specification's name (Lichtblick, @foxglove/ws-protocol clients).
WS_SUBPROTOCOL = Subprotocol('foxglove.websocket.v1')
#: Accepted on the public port, in order of preference.
SUBPROTOCOLS = (SDK_SUBPROTOCOL, WS_SUBPROTOCOL)
#: First byte of a binary ``messageData`` frame (server to client).
MESSAGE_DATA = 1
#: Close code for a client too slow to take even the control frames (policy violation).
CLOSE_TOO_SLOW = 1008
#: Seconds a closing handshake may take (a client that does not read never answers it).
CLOSE_TIMEOUT = 1.0
#: Kernel send buffer of each client's socket (bytes; the kernel doubles it). Without it the
#: kernel grows it up to ``net.ipv4.tcp_wmem`` (4 MB here): seconds of the whole stream held for
#: a client that does not read, before its outbox drops anything. 256 kB still carries the
#: stream (~1 MB/s with every topic) over a link with 100 ms round trip.
SEND_BUFFER = 256 * 1024


@dataclass
class ClientStats:
    """What one connected client got: ``sent`` frames handed to its connection, ``dropped``
    ``messageData`` frames it was too slow for, ``queued`` now waiting and ``peak_queued``."""

    address: str
    subprotocol: str
    sent: int = 0
    dropped: int = 0
    queued: int = 0
    peak_queued: int = 0


class OutboxOverflow(Exception):
    """More control frames wait for a client than its outbox holds."""


class Outbox:
    """A client's frames waiting to be written, in arrival order, at most ``backlog``
    ``messageData`` frames (the oldest dropped and counted) and ``backlog`` others.

    >>> box = Outbox(2, ClientStats('a', 'p'))
    >>> for frame in ('{"op":"advertise"}', b'\\x01a', b'\\x01b', b'\\x01c'):
    ...     box.put(frame)
    >>> [box.pop() for _ in range(3)], box.stats.dropped
    (['{"op":"advertise"}', b'\\x01b', b'\\x01c'], 1)
    """

    def __init__(self, backlog: int, stats: ClientStats) -> None:
        if backlog < 1:
            raise ConfigError(f'foxglove front: backlog must be >= 1, got {backlog}')
        self.backlog, self.stats = backlog, stats
        self._data: deque[tuple[int, Data]] = deque()
        self._control: deque[tuple[int, Data]] = deque()
        self._seq = itertools.count()
        self.ready = asyncio.Event()

    def put(self, frame: Data) -> None:
        """Queue ``frame``; drop the oldest ``messageData`` beyond the bound."""
        is_data = isinstance(frame, bytes) and frame[:1] == bytes((MESSAGE_DATA,))
        queue = self._data if is_data else self._control
        queue.append((next(self._seq), frame))
        if len(queue) > self.backlog:
            if not is_data:
                raise OutboxOverflow(f'{len(queue)} control frames waiting')
            queue.popleft()
            self.stats.dropped += 1
        queued = len(self._data) + len(self._control)
        self.stats.queued, self.stats.peak_queued = queued, max(queued, self.stats.peak_queued)
        self.ready.set()

    def pop(self) -> Data:
        """The oldest waiting frame (the outbox must not be empty)."""
        data, control = self._data, self._control
        queue = control if not data or (control and control[0][0] < data[0][0]) else data
        frame = queue.popleft()[1]
        self.stats.queued = len(data) + len(control)
        if not data and not control:
            self.ready.clear()
        return frame


def _select_subprotocol(_connection: ServerConnection,
                        offered: Sequence[Subprotocol]) -> Subprotocol:
    """The first of :data:`SUBPROTOCOLS` the client offers, else HTTP 400 naming both."""
    for name in SUBPROTOCOLS:
        if name in offered:
            return name
    raise NegotiationError(f'expected subprotocol {" or ".join(SUBPROTOCOLS)}, offered '
                           f'{", ".join(offered) or "none"}')


class FoxgloveFront:
    """Serves ``host:port`` (0: any free port, see :attr:`port`) to Foxglove clients of
    either subprotocol by relaying to the SDK server at ``ws://127.0.0.1:upstream_port``
    (see module doc). Runs an asyncio loop in a thread of its own; :meth:`stop` ends it."""

    def __init__(self, host: str, port: int, upstream_port: int, backlog: int) -> None:
        self.upstream = f'ws://127.0.0.1:{upstream_port}'
        self.backlog = backlog
        self.clients: dict[int, ClientStats] = {}
        #: Dropped frames of clients that have disconnected.
        self.dropped_closed = 0
        self._loop = asyncio.new_event_loop()
        self._server: Server | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, name='foxglove-front',
                                        daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(
                self._listen(host, port), self._loop).result(timeout=10.0)
        except OSError as exc:
            self.stop()
            raise ConfigError(f'foxglove_bridge: cannot serve on {host}:{port}: {exc}') from None
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _listen(self, host: str, port: int) -> Server:
        # compression=None: the SDK's server sends uncompressed frames too (no deflate cost);
        # ping_interval=None: a client on a saturated link is kept (and dropped for), as the
        # SDK's server keeps it; max_size=None: frames are the SDK's, relayed whole.
        return await serve(self._relay, host, port, subprotocols=list(SUBPROTOCOLS),
                           select_subprotocol=_select_subprotocol, compression=None,
                           ping_interval=None, max_size=None, close_timeout=CLOSE_TIMEOUT)

    def stats(self) -> list[ClientStats]:
        """A copy of the connected clients' counts."""
        return [ClientStats(**vars(s)) for s in list(self.clients.values())]

    async def _relay(self, client: ServerConnection) -> None:
        sock = client.transport.get_extra_info('socket')
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        peer = client.remote_address
        stats = ClientStats(f'{peer[0]}:{peer[1]}', str(client.subprotocol))
        key = id(client)
        self.clients[key] = stats
        try:
            async with connect(self.upstream, subprotocols=[SDK_SUBPROTOCOL], compression=None,
                               ping_interval=None, max_size=None, proxy=None,
                               close_timeout=CLOSE_TIMEOUT) as upstream:
                outbox = Outbox(self.backlog, stats)
                tasks = [asyncio.create_task(c) for c in (
                    self._take(upstream, outbox), self._write(client, outbox),
                    self._forward(client, upstream))]
                done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for task in pending:
                    task.cancel()
                await asyncio.gather(*pending, return_exceptions=True)
                for task in done:
                    exc = task.exception()
                    if isinstance(exc, OutboxOverflow):
                        await client.close(CLOSE_TOO_SLOW, f'too slow: {exc}')
                    elif exc is not None:
                        raise exc       # closed below; anything but a closed peer is logged
        except (OSError, ConnectionClosed):
            pass        # the SDK's server or the client went away: the client is closed below
        finally:
            del self.clients[key]
            self.dropped_closed += stats.dropped

    @staticmethod
    async def _take(upstream: ClientConnection, outbox: Outbox) -> None:
        half = outbox.backlog // 2
        async for frame in upstream:
            outbox.put(frame)
            if outbox.stats.queued > half:
                # A burst already read from the socket does not yield to the writer: let it
                # write what the client's socket takes before anything is dropped.
                await asyncio.sleep(0)

    @staticmethod
    async def _write(client: ServerConnection, outbox: Outbox) -> None:
        while True:
            await outbox.ready.wait()
            frame = outbox.pop()
            outbox.stats.sent += 1      # handed to the connection (it waits while it is full)
            await client.send(frame)

    @staticmethod
    async def _forward(client: ServerConnection, upstream: ClientConnection) -> None:
        async for frame in client:
            await upstream.send(frame)

    def stop(self) -> None:
        """Close every connection and the listening socket, end the thread; idempotent."""
        if not self._thread.is_alive():
            return

        async def close() -> None:
            if self._server is None:
                return
            self._server.close(close_connections=False)      # stop accepting
            connections = list(self._server.connections)
            if connections:
                # Going away (1001) for clients that read; a client that does not read never
                # completes the handshake (its socket is full): after CLOSE_TIMEOUT, cut.
                await asyncio.wait([asyncio.create_task(c.close(1001, 'server stopping'))
                                    for c in connections], timeout=CLOSE_TIMEOUT)
                for c in connections:
                    c.transport.abort()
            try:
                await asyncio.wait_for(self._server.wait_closed(), timeout=CLOSE_TIMEOUT)
            finally:
                # No task may outlive the loop: a pending task destroyed later by the garbage
                # collector runs Python code wherever that happens.
                rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
                for task in rest:
                    task.cancel()
                await asyncio.wait(rest, timeout=CLOSE_TIMEOUT) if rest else None

        try:
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(
                timeout=4 * CLOSE_TIMEOUT)
        except TimeoutError:
            pass        # the loop stops below all the same; the process is ending
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10.0)
        self._loop.close()

