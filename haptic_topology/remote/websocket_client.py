"""A minimal WebSocket client (RFC 6455) for a device cycle: text messages over a TCP socket
that never blocks once the connection is open.

Why not the ``websockets`` package's clients: its asyncio client needs an event loop turning
in the device's thread, and its sync client takes every frame in a thread of its own and hands
it over through a queue (a second thread competing with the 1 kHz loop for the interpreter
lock, and a lock per message). A device cycle needs neither: it sends one message and takes
whatever has arrived, so the framing is done here, inline, on a non-blocking socket.

* :func:`connect` (blocking, bounded by its ``timeout``): TCP connect, the opening handshake
  (``GET`` with ``Upgrade: websocket``, a random ``Sec-WebSocket-Key``; the answer must be
  ``101`` with the matching ``Sec-WebSocket-Accept``), then the socket is made non-blocking.
* :meth:`WebSocketClient.send_text`: one masked text frame (client frames are masked, RFC 6455
  5.3; the masking keys come from ``os.urandom``, drawn 1024 at a time). One ``send`` call; a
  frame the kernel took only in part is finished by the next calls before another is started,
  and while one is unfinished a new message is not sent (returns False): frames never
  interleave and nothing queues up behind a peer that does not read.
* :meth:`WebSocketClient.poll`: drains the socket (``recv_into`` until it would block) and
  returns the newest complete text message, and how many came (older ones are skipped
  unread: only the newest state matters to a device cycle). Pings are answered with pongs,
  fragmented messages are reassembled, a close frame or the end of the stream ends the
  connection (:attr:`WebSocketClient.closed` says why). A frame that breaks the protocol
  (masked by the server, reserved bits, unknown opcode, longer than :data:`MAX_MESSAGE`) ends
  it too.
* :meth:`WebSocketClient.wait_text` (blocking, bounded): the next text message, for the
  connection's start.
* :class:`Dialer`: the same opening as :func:`connect`, to an address resolved before (no
  name lookup), without ever waiting: a non-blocking TCP connect, then the handshake, one
  :meth:`Dialer.step` at a time (for a device cycle that reconnects; the caller bounds how
  long it lets an attempt take).
"""

from __future__ import annotations

import base64
import errno
import hashlib
import os
import select
import socket
import struct
import time
from typing import Any

from haptic_topology.errors import DeviceError

#: RFC 6455 1.3: appended to the key to compute ``Sec-WebSocket-Accept``.
_GUID = b'258EAFA5-E914-47DA-95CA-C5AB0DC85B11'
#: Longest message accepted (bytes); a longer one ends the connection.
MAX_MESSAGE = 1 << 20
_HEADER_MAX = 16384
_TEXT, _BINARY, _CONT, _CLOSE, _PING, _PONG = 0x1, 0x2, 0x0, 0x8, 0x9, 0xA
_RECV_CHUNK = 65536


def _mask(payload: bytes, key: bytes) -> bytes:
    """``payload`` XOR the repeated 4-byte ``key`` (RFC 6455 5.3), as one big-integer XOR."""
    n = len(payload)
    if not n:
        return b''
    stream = (key * (n // 4 + 1))[:n]
    return (int.from_bytes(payload, 'little') ^ int.from_bytes(stream, 'little')).to_bytes(
        n, 'little')


def frame(opcode: int, payload: bytes, key: bytes | None) -> bytes:
    """One final frame of ``opcode`` carrying ``payload``, masked with ``key`` (a client's
    frames) or not (``None``: a server's)."""
    n = len(payload)
    b0 = 0x80 | opcode
    mbit = 0x80 if key is not None else 0
    if n < 126:
        head = struct.pack('!BB', b0, mbit | n)
    elif n < 65536:
        head = struct.pack('!BBH', b0, mbit | 126, n)
    else:
        head = struct.pack('!BBQ', b0, mbit | 127, n)
    if key is None:
        return head + payload
    return head + key + _mask(payload, key)


class WebSocketClient:
    """An open connection (made by :func:`connect`); see the module doc."""

    def __init__(self, sock: socket.socket, rest: bytes, peer: str) -> None:
        self._sock = sock
        self.peer = peer
        self._in = bytearray(rest)
        self._chunk = bytearray(_RECV_CHUNK)
        self._out = b''
        self._keys = b''
        self._frag_op = 0
        self._frag = bytearray()
        #: Why the connection ended ('' while open).
        self.closed = ''
        #: ``(family, sockaddr)`` of the service (set by :func:`connect` and
        #: :class:`Dialer`): where a :class:`Dialer` reconnects to without a name lookup.
        self.address: tuple[int, Any] | None = None
        # counters
        self.frames_sent = 0
        self.partial_sends = 0
        self.busy = 0
        self.messages = 0
        self.skipped = 0
        self.pings = 0

    # -- sending -----------------------------------------------------------------------------
    @property
    def sending(self) -> bool:
        """A frame is still unfinished (part of it waits for the socket's buffer)."""
        return bool(self._out)

    def _key(self) -> bytes:
        if not self._keys:
            self._keys = os.urandom(4096)
        key, self._keys = self._keys[:4], self._keys[4:]
        return key

    def _flush(self) -> bool:
        """Send what is left of an unfinished frame; True when nothing is left."""
        if not self._out:
            return True
        try:
            n = self._sock.send(self._out)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            self._send_failed(exc)
            return False
        self._out = self._out[n:]
        return not self._out

    def _send_frame(self, opcode: int, payload: bytes) -> bool:
        if self.closed or not self._flush():
            if not self.closed:
                self.busy += 1
            return False
        data = frame(opcode, payload, self._key())
        try:
            n = self._sock.send(data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self._send_failed(exc)
            return False
        if n < len(data):
            self.partial_sends += 1
            self._out = data[n:]
        self.frames_sent += 1
        return True

    def send_text(self, text: bytes) -> bool:
        """Send one text message (UTF-8 bytes) without waiting; False when not sent (the
        connection has ended, or the previous frame is still unfinished: module doc)."""
        return self._send_frame(_TEXT, text)

    def _send_failed(self, exc: OSError) -> None:
        # A service that ends is seen by whichever call meets it first: a reset or a closed
        # stream reads the same from a send as from a receive (_drain).
        if isinstance(exc, ConnectionResetError):
            self._end('the service reset the connection')
        elif isinstance(exc, BrokenPipeError):
            self._end('the service closed the connection')
        else:
            self._end(f'send failed: {exc.strerror or type(exc).__name__}')

    # -- receiving ---------------------------------------------------------------------------
    def _end(self, why: str) -> None:
        if not self.closed:
            self.closed = why

    def _drain(self) -> None:
        sock, chunk = self._sock, self._chunk
        while not self.closed:
            try:
                n = sock.recv_into(chunk)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionResetError:
                self._end('the service reset the connection')
                return
            except OSError as exc:
                self._end(f'receive failed: {exc.strerror or type(exc).__name__}')
                return
            if n == 0:
                self._end('the service closed the connection')
                return
            self._in += chunk[:n]
            if n < len(chunk):
                return

    def _frames(self) -> tuple[bytes | None, int]:
        """Parse the complete frames received: the newest text message and the count."""
        buf = self._in
        pos, size = 0, len(buf)
        newest: bytes | None = None
        count = 0
        while size - pos >= 2 and not self.closed:
            b0, b1 = buf[pos], buf[pos + 1]
            n = b1 & 0x7F
            at = pos + 2
            if n == 126:
                if size - at < 2:
                    break
                n = int.from_bytes(buf[at:at + 2], 'big')
                at += 2
            elif n == 127:
                if size - at < 8:
                    break
                n = int.from_bytes(buf[at:at + 8], 'big')
                at += 8
            if b1 & 0x80 or b0 & 0x70 or n > MAX_MESSAGE:
                self._end('protocol error: ' + ('a masked frame from the service' if b1 & 0x80
                                                 else 'reserved bits set' if b0 & 0x70
                                                 else f'a frame of {n} bytes'))
                break
            if size - at < n:
                break
            payload = bytes(buf[at:at + n])
            pos = at + n
            op, fin = b0 & 0x0F, bool(b0 & 0x80)
            if op == _PING:
                self.pings += 1
                self._send_frame(_PONG, payload)
            elif op == _CLOSE:
                code = int.from_bytes(payload[:2], 'big') if len(payload) >= 2 else 1005
                reason = payload[2:].decode('utf-8', 'replace')
                self._end(f'the service closed the connection (code {code}'
                          + (f': {reason})' if reason else ')'))
            elif op == _PONG:
                pass
            elif op in (_TEXT, _BINARY, _CONT):
                if op != _CONT:
                    self._frag_op, self._frag = op, bytearray()
                elif not self._frag_op:
                    self._end('protocol error: a continuation frame without a message')
                    break
                self._frag += payload
                if len(self._frag) > MAX_MESSAGE:
                    self._end(f'protocol error: a message of more than {MAX_MESSAGE} bytes')
                    break
                if fin:
                    if self._frag_op == _TEXT:
                        newest = bytes(self._frag)
                        count += 1
                    self._frag_op, self._frag = 0, bytearray()
            else:
                self._end(f'protocol error: opcode {op:#x}')
        del buf[:pos]
        return newest, count

    def poll(self) -> tuple[bytes | None, int]:
        """Everything that has arrived, without waiting: (the newest complete text message or
        None, how many text messages came). Finishes an unfinished send first."""
        self._flush()
        self._drain()
        newest, count = self._frames()
        self.messages += count
        if count > 1:
            self.skipped += count - 1
        return newest, count

    def wait(self, timeout: float) -> None:
        """Wait at most ``timeout`` s for something to read (outside a device cycle)."""
        select.select([self._sock], [], [], timeout)

    def wait_text(self, timeout: float) -> bytes | None:
        """The next text message, waiting at most ``timeout`` s (None: none came, or the
        connection ended)."""
        deadline = time.monotonic() + timeout
        while not self.closed:
            newest, _ = self.poll()
            if newest is not None:
                return newest
            left = deadline - time.monotonic()
            if left <= 0.0:
                return None
            select.select([self._sock], [], [], left)
        return None

    def close(self) -> None:
        """Send a close frame (best effort: without waiting) and close the socket."""
        if not self.closed:
            self._send_frame(_CLOSE, struct.pack('!H', 1000))
            self._end('closed by this client')
        try:
            self._sock.close()
        except OSError:
            pass


def _request(host: str, port: int, path: str, origin: str) -> tuple[bytes, bytes]:
    """The opening handshake's request (RFC 6455 4.1) and its ``Sec-WebSocket-Key``."""
    key = base64.b64encode(os.urandom(16))
    request = (f'GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n'
               'Connection: Upgrade\r\nSec-WebSocket-Version: 13\r\n'
               f'Sec-WebSocket-Key: {key.decode()}\r\n'
               + (f'Origin: {origin}\r\n' if origin else '') + '\r\n')
    return request.encode(), key


def _answer(peer: str, key: bytes, data: bytes) -> bytes | None:
    """The bytes after the handshake's answer once ``data`` holds all of it (None: not yet);
    a :class:`~haptic_topology.errors.DeviceError` when it refuses or is not the right one."""
    if b'\r\n\r\n' not in data:
        if len(data) > _HEADER_MAX:
            raise DeviceError(f'{peer}: a handshake answer of more than {_HEADER_MAX} bytes')
        return None
    head, _, rest = data.partition(b'\r\n\r\n')
    lines = head.decode('latin-1').split('\r\n')
    status = lines[0].split(' ', 2)
    if len(status) < 2 or status[1] != '101':
        raise DeviceError(f'{peer}: the service refused the WebSocket handshake: '
                          f'{lines[0]!r}')
    fields = {k.strip().lower(): v.strip() for k, _, v in
              (line.partition(':') for line in lines[1:])}
    expect = base64.b64encode(hashlib.sha1(key + _GUID).digest()).decode()
    if fields.get('sec-websocket-accept') != expect:
        raise DeviceError(f'{peer}: a WebSocket handshake answer without the right '
                          'Sec-WebSocket-Accept')
    return rest


def connect(host: str, port: int, path: str, timeout: float, origin: str = '') -> WebSocketClient:
    """Open a connection to ``ws://host:port/path`` within ``timeout`` s (module doc); a
    :class:`~haptic_topology.errors.DeviceError` naming the address and why when it cannot."""
    peer = f'ws://{host}:{port}{path}'
    deadline = time.monotonic() + timeout
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise DeviceError(f'cannot connect to {peer}: {exc.strerror or exc}') from None
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        address = (sock.family, sock.getpeername())
        request, key = _request(host, port, path, origin)
        sock.sendall(request)
        data = b''
        while (rest := _answer(peer, key, data)) is None:
            left = deadline - time.monotonic()
            if left <= 0.0:
                raise DeviceError(f'{peer}: no answer to the WebSocket handshake within '
                                  f'{1e3 * timeout:g} ms')
            sock.settimeout(left)
            chunk = sock.recv(4096)
            if not chunk:
                raise DeviceError(f'{peer}: the connection closed during the WebSocket '
                                  'handshake')
            data += chunk
        sock.setblocking(False)
    except (DeviceError, OSError) as exc:
        sock.close()
        if isinstance(exc, DeviceError):
            raise
        raise DeviceError(f'{peer}: WebSocket handshake failed: {exc.strerror or exc}'
                          ) from None
    client = WebSocketClient(sock, rest, peer)
    client.address = address
    return client


class Dialer:
    """One attempt to open ``ws://host:port/path`` at ``address`` (``(family, sockaddr)``, e.g.
    :attr:`WebSocketClient.address` of an earlier connection), never waiting: the socket is
    non-blocking from the start, and each :meth:`step` does what can be done now. The caller
    bounds the attempt's duration (and :meth:`close` s it)."""

    def __init__(self, address: tuple[int, Any], host: str, port: int, path: str,
                 origin: str = '') -> None:
        self.peer = f'ws://{host}:{port}{path}'
        self._address = address
        self._request, self._key = _request(host, port, path, origin)
        self._data = b''
        self._sock: socket.socket | None = socket.socket(address[0], socket.SOCK_STREAM)
        self._sock.setblocking(False)
        err = self._sock.connect_ex(address[1])
        if err not in (0, errno.EINPROGRESS, errno.EAGAIN, errno.EALREADY):
            self.close()
            raise DeviceError(f'cannot connect to {self.peer}: {os.strerror(err)}')

    def step(self) -> WebSocketClient | None:
        """Advance the attempt without waiting: the open connection once the handshake is
        done (this dialer is then spent), None while it is under way; a
        :class:`~haptic_topology.errors.DeviceError` naming the address when it failed (the
        socket is closed then)."""
        sock = self._sock
        if sock is None:
            raise DeviceError(f'{self.peer}: this connection attempt is over')
        try:
            if self._request:
                if not select.select([], [sock], [], 0.0)[1]:
                    return None                     # the TCP connect is under way
                err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                if err:
                    raise DeviceError(f'cannot connect to {self.peer}: {os.strerror(err)}')
                n = sock.send(self._request)
                self._request = self._request[n:]
                return None
            try:
                chunk = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return None
            if not chunk:
                raise DeviceError(f'{self.peer}: the connection closed during the WebSocket '
                                  'handshake')
            self._data += chunk
            rest = _answer(self.peer, self._key, self._data)
            if rest is None:
                return None
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except (BlockingIOError, InterruptedError):
            return None
        except (DeviceError, OSError) as exc:
            self.close()
            if isinstance(exc, DeviceError):
                raise
            raise DeviceError(f'{self.peer}: WebSocket handshake failed: '
                              f'{exc.strerror or exc}') from None
        self._sock = None
        client = WebSocketClient(sock, rest, self.peer)
        client.address = self._address
        return client

    def close(self) -> None:
        """Abandon the attempt (harmless when it is over)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
