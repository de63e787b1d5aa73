"""The Foxglove front (:mod:`haptic_topology.net.foxglove_front`) against the real Foxglove SDK
server in this process, no ROS.

* both subprotocol names are accepted on one port, ``foxglove.sdk.v1`` preferred; a client
  offering neither gets HTTP 400 naming both; the SDK's server itself refuses
  ``foxglove.websocket.v1`` (why the front exists: if an SDK version starts accepting it, this
  test says so);
* every frame a client gets through the front is, byte for byte, the frame the SDK's server
  sends a direct client (serverInfo, advertise, messageData), under either name;
* a client that never reads: the front drops for it only, counts what it dropped, holds at
  most ``backlog`` frames for it, while a client beside it receives every message;
* the outbox's rules (oldest messageData dropped, order kept, control overflow refused) and
  bad input (backlog, a port in use) with errors that name what is wrong.

Only what holds on any machine is asserted: counts, equality, bounds, never rates.
"""

from __future__ import annotations

import doctest
import gc
import json
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import foxglove
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from haptic_topology.errors import ConfigError
from haptic_topology.net import foxglove_front
from haptic_topology.net.foxglove_front import (
    SDK_SUBPROTOCOL,
    WS_SUBPROTOCOL,
    ClientStats,
    FoxgloveFront,
    Outbox,
    OutboxOverflow,
)

BACKLOG = 32
#: Messages the good client may be behind in the slow-client test.
WINDOW = 8
PAD = 4_000
SCHEMA = foxglove.Schema(name='std_msgs/msg/String', encoding='ros2msg', data=b'string data')


class Sdk:
    """The SDK's server with one ``cdr`` channel, and the front before it."""

    def __init__(self, backlog: int = BACKLOG) -> None:
        self.context = foxglove.Context()
        self.channel = foxglove.Channel('/chatter', schema=SCHEMA, message_encoding='cdr',
                                        context=self.context)
        self.server = foxglove.start_server(host='127.0.0.1', port=0, context=self.context,
                                            message_backlog_size=100_000)
        self.front = FoxgloveFront('127.0.0.1', 0, int(self.server.port), backlog)

    def stop(self) -> None:
        self.front.stop()
        self.server.stop()


@pytest.fixture
def sdk() -> Iterator[Sdk]:
    s = Sdk()
    try:
        yield s
    finally:
        s.stop()


def _cdr(i: int) -> bytes:
    """std_msgs/String 'm<i>' in CDR (little endian)."""
    text = f'm{i}'.encode() + b'\0'
    return b'\0\x01\0\0' + struct.pack('<I', len(text)) + text


def _subscribe(ws: ClientConnection, sub_id: int = 5) -> tuple[Any, Any]:
    info, advertise = ws.recv(timeout=10), ws.recv(timeout=10)
    channel = json.loads(advertise)['channels'][0]
    ws.send(json.dumps({'op': 'subscribe',
                        'subscriptions': [{'id': sub_id, 'channelId': channel['id']}]}))
    return info, advertise


def _wait(cond: Any, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f'{what}: not within {timeout:g} s'
        time.sleep(0.01)


def _receive(ws: ClientConnection, n: int) -> list[bytes]:
    frames: list[bytes] = []
    while len(frames) < n:
        frame = ws.recv(timeout=10)
        assert isinstance(frame, bytes), frame
        frames.append(frame)
    return frames


# -- the handshake -------------------------------------------------------------------------------
@pytest.mark.parametrize(('offered', 'chosen'), [
    ([WS_SUBPROTOCOL], WS_SUBPROTOCOL),
    ([SDK_SUBPROTOCOL], SDK_SUBPROTOCOL),
    ([WS_SUBPROTOCOL, SDK_SUBPROTOCOL], SDK_SUBPROTOCOL),
    (['foxglove.sdk.v1.1', WS_SUBPROTOCOL], WS_SUBPROTOCOL),
])
def test_either_name_is_accepted_on_one_port(sdk: Sdk, offered: list[Any],
                                             chosen: str) -> None:
    with connect(f'ws://127.0.0.1:{sdk.front.port}', subprotocols=offered) as ws:
        assert ws.subprotocol == chosen
        assert json.loads(ws.recv(timeout=10))['op'] == 'serverInfo'
        _wait(lambda: [c.subprotocol for c in sdk.front.stats()] == [chosen], 'stats')


@pytest.mark.parametrize('offered', [None, ['foxglove.sdk.v1.1'], ['chat']])
def test_a_client_offering_neither_name_gets_400_naming_both(sdk: Sdk,
                                                             offered: list[Any] | None) -> None:
    with pytest.raises(InvalidStatus) as err:
        connect(f'ws://127.0.0.1:{sdk.front.port}', subprotocols=offered)
    assert err.value.response.status_code == 400
    body = err.value.response.body.decode()
    assert SDK_SUBPROTOCOL in body and WS_SUBPROTOCOL in body, body


def test_the_sdk_server_alone_refuses_the_ws_protocol_name(sdk: Sdk) -> None:
    with pytest.raises(InvalidStatus) as err:
        connect(f'ws://127.0.0.1:{sdk.server.port}', subprotocols=[WS_SUBPROTOCOL])
    assert err.value.response.status_code == 400


# -- frames pass unchanged -----------------------------------------------------------------------
@pytest.mark.parametrize('name', [WS_SUBPROTOCOL, SDK_SUBPROTOCOL])
def test_frames_through_the_front_are_the_sdk_servers_frames(sdk: Sdk, name: Any) -> None:
    with connect(f'ws://127.0.0.1:{sdk.server.port}', subprotocols=[SDK_SUBPROTOCOL]) as direct, \
            connect(f'ws://127.0.0.1:{sdk.front.port}', subprotocols=[name]) as fronted:
        seen = [_subscribe(direct), _subscribe(fronted)]
        assert seen[0] == seen[1]
        advertised = json.loads(seen[0][1])['channels'][0]
        assert (advertised['encoding'], advertised['schemaEncoding'], advertised['schema']) == (
            'cdr', 'ros2msg', 'string data')
        _wait(lambda: sdk.channel.has_sinks() and len(sdk.front.stats()) == 1, 'subscribed')
        time.sleep(0.2)     # both subscriptions reach the SDK's server
        for i in range(50):
            sdk.channel.log(_cdr(i), log_time=1_000 + i)
        a, b = _receive(direct, 50), _receive(fronted, 50)
    assert a == b
    op, sub_id, stamp = struct.unpack_from('<BIQ', b[7])
    assert (op, sub_id, stamp, b[7][13:]) == (1, 5, 1_007, _cdr(7))


# -- a client that never reads -------------------------------------------------------------------
def _never_reading_client(port: int) -> ClientConnection:
    """A client that reads nothing once subscribed: a receive buffer of a few kB, a queue of
    one frame."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(('127.0.0.1', port))
    return connect(f'ws://127.0.0.1:{port}', sock=sock, subprotocols=[WS_SUBPROTOCOL],
                   max_queue=1, close_timeout=1, ping_interval=None)


def test_a_client_that_never_reads_is_dropped_for_alone_and_counted(sdk: Sdk) -> None:
    total = 6_000       # of PAD bytes: 24 MB, more than the kernel buffers of a socket hold
    got: list[bytes] = []
    with _never_reading_client(sdk.front.port) as slow_client, \
            connect(f'ws://127.0.0.1:{sdk.front.port}', subprotocols=[SDK_SUBPROTOCOL],
                    max_queue=None) as good:
        _subscribe(slow_client, sub_id=9)
        _subscribe(good)
        _wait(lambda: len(sdk.front.stats()) == 2, 'both clients connected')
        time.sleep(0.2)
        def read() -> None:
            while len(got) < total:
                frame = good.recv(timeout=30)
                assert isinstance(frame, bytes)
                got.append(frame)

        reader = threading.Thread(target=read)
        reader.start()
        for i in range(total):
            # Paced by the good client, whatever the machine's speed: it is never more than
            # WINDOW (< BACKLOG) messages behind, so nothing may be dropped for it.
            if i - len(got) >= WINDOW:
                _wait(lambda i=i: i - len(got) < WINDOW or not reader.is_alive(),
                      'the good client reads')
            sdk.channel.log(_cdr(i) + bytes(PAD), log_time=i)
        reader.join(timeout=60)

        def slow() -> ClientStats:
            return next(c for c in sdk.front.stats() if c.subprotocol == WS_SUBPROTOCOL)

        # Every message the SDK sent the slow client's relay is accounted for: handed to its
        # connection, dropped (counted) or waiting (serverInfo and advertise: 2 more frames).
        _wait(lambda: slow().sent + slow().dropped + slow().queued == total + 2,
              'the relay took every message for the slow client')
        stats = {c.subprotocol: c for c in sdk.front.stats()}
    # The good client got every message, in order; nothing was dropped for it.
    assert [struct.unpack_from('<Q', f, 5)[0] for f in got] == list(range(total))
    assert stats[SDK_SUBPROTOCOL].dropped == 0
    # The slow one: dropped and counted, never more than the backlog waiting for it.
    slow_stats = stats[WS_SUBPROTOCOL]
    assert slow_stats.dropped > 0
    assert slow_stats.peak_queued <= BACKLOG
    _wait(lambda: sdk.front.stats() == [], 'the slow client is gone')
    assert sdk.front.dropped_closed == slow_stats.dropped


def test_stop_is_prompt_with_a_client_that_never_reads(sdk: Sdk) -> None:
    with _never_reading_client(sdk.front.port) as slow_client:
        _subscribe(slow_client)
        _wait(lambda: sdk.channel.has_sinks(), 'subscribed')
        for i in range(2_000):      # 8 MB: the client's socket is full
            sdk.channel.log(_cdr(i) + bytes(PAD), log_time=i)
        _wait(lambda: sdk.front.stats()[0].dropped > 0, 'dropping')
        t0 = time.monotonic()
        sdk.front.stop()
        took = time.monotonic() - t0
    gc.collect()    # what the closed connections leave is finalised here, not in a later test
    assert took < 4 * foxglove_front.CLOSE_TIMEOUT + 5.0, took     # a bound, not a rate


# -- the outbox ----------------------------------------------------------------------------------
def test_outbox_doc_example() -> None:
    assert doctest.testmod(foxglove_front).failed == 0


def test_outbox_keeps_order_and_drops_the_oldest_message_data() -> None:
    box = Outbox(3, ClientStats('a', 'p'))
    frames: list[Any] = ['{"op":"serverInfo"}', b'\x01' + b'0', '{"op":"advertise"}',
                         b'\x02time', *(b'\x01' + bytes([48 + i]) for i in range(1, 5))]
    for f in frames:
        box.put(f)
    out = [box.pop() for _ in range(box.stats.queued)]
    assert out == ['{"op":"serverInfo"}', '{"op":"advertise"}', b'\x02time', b'\x012', b'\x013',
                   b'\x014']
    assert (box.stats.dropped, box.stats.queued, box.stats.peak_queued) == (2, 0, 6)
    assert not box.ready.is_set()


def test_outbox_refuses_more_control_frames_than_its_backlog() -> None:
    box = Outbox(2, ClientStats('a', 'p'))
    box.put('{"op":"status"}')
    box.put('{"op":"status"}')
    with pytest.raises(OutboxOverflow, match='3 control frames'):
        box.put('{"op":"status"}')


def test_bad_backlog_and_a_port_in_use_are_named() -> None:
    with pytest.raises(ConfigError, match='backlog must be >= 1, got 0'):
        Outbox(0, ClientStats('a', 'p'))
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f'cannot serve on 127.0.0.1:{port}'):
            FoxgloveFront('127.0.0.1', port, 1, BACKLOG)
