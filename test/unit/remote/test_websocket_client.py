"""The minimal WebSocket client of the ``haply`` backend (RFC 6455), frame by frame against a
socket pair (the other end plays the service, framing with the same module's ``frame`` and
parsing the client's frames with the ``websockets`` package's own parser), and its opening
handshake against the ``websockets`` package's server: masking, the newest of several
messages, fragments, ping -> pong, close, protocol errors, a frame that does not fit the
socket's buffer."""

from __future__ import annotations

import os
import select
import socket
import struct
import threading

import pytest
from websockets.frames import Frame, Opcode
from websockets.streams import StreamReader
from websockets.sync.server import ServerConnection, serve

from haptic_topology.errors import DeviceError
from haptic_topology.remote.websocket_client import WebSocketClient, connect, frame


def _pair() -> tuple[WebSocketClient, socket.socket]:
    a, b = socket.socketpair()
    a.setblocking(False)
    return WebSocketClient(a, b'', 'ws://pair/'), b


def _client_frames(sock: socket.socket) -> list[Frame]:
    """Every frame the client sent so far, parsed by ``websockets`` (mask required)."""
    sock.setblocking(False)
    data = b''
    while True:
        try:
            chunk = sock.recv(1 << 20)
        except BlockingIOError:
            break
        if not chunk:
            break
        data += chunk
    reader = StreamReader()
    reader.feed_data(data)
    frames = []
    while reader.buffer:
        parser = Frame.parse(reader.read_exact, mask=True, max_size=1 << 24)
        try:
            while True:
                next(parser)
        except StopIteration as stop:
            frames.append(stop.value)
    return frames


def test_text_frames_are_masked_and_parse_as_sent() -> None:
    ws, peer = _pair()
    for n in (0, 5, 125, 126, 65535, 65536):
        assert ws.send_text(b'x' * n)
    got = _client_frames(peer)
    assert [(f.opcode, len(f.data), f.fin) for f in got] == [
        (Opcode.TEXT, n, True) for n in (0, 5, 125, 126, 65535, 65536)]
    assert all(f.data == b'x' * len(f.data) for f in got)


def test_poll_returns_the_newest_of_several_and_never_waits() -> None:
    ws, peer = _pair()
    assert ws.poll() == (None, 0)
    third = frame(0x1, b'thr', None)
    peer.sendall(frame(0x1, b'one', None) + frame(0x1, b'two', None) + third[:3])
    assert ws.poll() == (b'two', 2)
    assert ws.skipped == 1
    peer.sendall(third[3:])
    assert ws.poll() == (b'thr', 1)


def test_fragments_are_joined_and_a_ping_is_answered() -> None:
    ws, peer = _pair()
    first = bytes([0x01, 3]) + b'abc'                  # text, not final
    ping = frame(0x9, b'hb', None)                     # a control frame in between
    last = bytes([0x80, 2]) + b'de'                    # continuation, final
    peer.sendall(first + ping + last)
    assert ws.poll() == (b'abcde', 1)
    pong = _client_frames(peer)
    assert [(f.opcode, f.data) for f in pong] == [(Opcode.PONG, b'hb')]


@pytest.mark.parametrize(('data', 'why'), [
    (frame(0x8, struct.pack('!H', 1001) + b'bye', None),
     'the service closed the connection (code 1001: bye)'),
    (bytes([0x81, 0x80 | 2]) + b'\0\0\0\0' + b'hi', 'protocol error: a masked frame from '
     'the service'),
    (bytes([0xC1, 2]) + b'hi', 'protocol error: reserved bits set'),
    (bytes([0x83, 2]) + b'hi', 'protocol error: opcode 0x3'),
    (bytes([0x80, 2]) + b'hi', 'protocol error: a continuation frame without a message')])
def test_a_close_or_a_broken_frame_ends_the_connection(data: bytes, why: str) -> None:
    ws, peer = _pair()
    peer.sendall(data)
    assert ws.poll() == (None, 0)
    assert ws.closed == why
    assert not ws.send_text(b'late')


def test_the_end_of_the_stream_ends_the_connection() -> None:
    ws, peer = _pair()
    peer.close()
    ws.poll()
    assert ws.closed == 'the service closed the connection'


def test_a_service_gone_reads_the_same_from_a_send_as_from_a_receive() -> None:
    """The service's end is met by a send as often as by a receive (whichever comes first in
    the cycle): a closed stream and a reset give the receive's words, never 'send failed'."""
    ws, peer = _pair()
    peer.close()
    assert not ws.send_text(b'x')       # AF_UNIX: EPIPE
    assert ws.closed == 'the service closed the connection'
    srv = socket.socket()
    srv.bind(('127.0.0.1', 0))
    srv.listen()
    c = socket.create_connection(srv.getsockname())
    c.setblocking(False)
    s, _ = srv.accept()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
    s.close()                           # a reset (RST)
    srv.close()
    select.select([c], [], [], 10.0)    # the reset has arrived
    ws = WebSocketClient(c, b'', 'ws://reset/')
    assert not ws.send_text(b'x')
    assert ws.closed == 'the service reset the connection'
    c.close()


def test_a_frame_the_socket_cannot_take_is_finished_before_the_next() -> None:
    """A peer that does not read: the frame that does not fit is kept and finished by later
    calls; meanwhile new messages are refused (counted ``busy``), never interleaved."""
    ws, peer = _pair()
    big = os.urandom(1 << 22).hex().encode()          # 8 MB: more than the socket buffers
    assert ws.send_text(big)
    assert ws.sending and ws.partial_sends == 1
    assert not ws.send_text(b'next') and ws.busy == 1
    received = bytearray()
    while ws.sending:
        ws.poll()
        try:
            received += peer.recv(1 << 20)
        except BlockingIOError:
            pass
    assert ws.send_text(b'next')
    peer.setblocking(False)
    rest = bytearray()
    while True:
        try:
            chunk = peer.recv(1 << 20)
        except BlockingIOError:
            break
        rest += chunk
    reader = StreamReader()
    reader.feed_data(bytes(received + rest))
    frames = []
    for _ in range(2):
        parser = Frame.parse(reader.read_exact, mask=True, max_size=1 << 24)
        try:
            while True:
                next(parser)
        except StopIteration as stop:
            frames.append(stop.value)
    assert [f.data for f in frames] == [big, b'next']


def test_the_handshake_with_the_websockets_server() -> None:
    got: list[str] = []

    def handler(conn: ServerConnection) -> None:
        conn.send('hello')
        got.append(str(conn.recv()))

    with serve(handler, '127.0.0.1', 0, compression=None) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        port = server.socket.getsockname()[1]
        ws = connect('127.0.0.1', port, '/', 10.0)
        assert ws.wait_text(10.0) == b'hello'
        assert ws.send_text(b'back')
        ws.wait(10.0)
        ws.close()
        server.shutdown()
    assert got == ['back']


def test_nothing_listening_is_one_line_naming_the_address() -> None:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    with pytest.raises(DeviceError, match=rf'^cannot connect to ws://127\.0\.0\.1:{port}/x: '
                       'Connection refused$'):
        connect('127.0.0.1', port, '/x', 5.0)


def test_a_server_that_is_not_websocket_is_refused() -> None:
    srv = socket.create_server(('127.0.0.1', 0))
    port = srv.getsockname()[1]

    def answer() -> None:
        conn, _ = srv.accept()
        conn.recv(4096)
        conn.sendall(b'HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n')
        conn.close()

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    with pytest.raises(DeviceError, match=r"refused the WebSocket handshake: 'HTTP/1.1 404 "
                       r"Not Found'$"):
        connect('127.0.0.1', port, '/', 10.0)
    thread.join()
    srv.close()
