"""Test helpers of the device network protocol: the device server in a process of its own, a
fault-injecting UDP relay, a raw protocol client. Host and port are parameters everywhere, so
the same helpers can run across a network namespace pair.

:class:`ServerProcess` starts ``python -m haptic_topology.remote.server_command`` and waits for
its ready file (no log lines are parsed; the process handling is ``service_process.py``'s,
shared with the Haply emulator's harness); :meth:`ServerProcess.stop` sends SIGINT and reads
the counters (``--summary``) and the per-cycle applied-wrench log (``--log``).

:class:`Relay` sits between a client and the server and mutates the datagrams by their index
in each direction, deterministically (:data:`PATTERN`): drop, duplicate, reorder (hold until
the next one has gone), delay (3 ms), corrupt (one byte flipped), NaN with a valid CRC,
truncate. It records what it did, and the seq of every command it mutated or dropped.
"""

from __future__ import annotations

import json
import math
import select
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from service_process import MonitoredDevice, ServiceProcess

from haptic_topology.remote import protocol as P

#: Relay actions by datagram index modulo 50 (in each direction); the others pass unchanged.
PATTERN = {7: 'drop', 13: 'duplicate', 21: 'reorder', 29: 'delay', 37: 'corrupt', 43: 'nan',
           47: 'truncate'}
#: Actions after which the receiver must refuse the datagram as malformed.
MALFORMING = ('corrupt', 'nan', 'truncate')
DELAY = 0.003


def wait_for(cond: Callable[[], bool], timeout: float, what: str, poll: float = 0.002) -> None:
    """Wait until ``cond()`` holds, at most ``timeout`` s, else fail naming ``what``."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(poll)


# -- the server process -------------------------------------------------------------------------
@dataclass
class ServerResult:
    """What a stopped server left: exit status, output, counters and the applied log
    (``session``/``seq``: the command applied per cycle, 0 none; ``u``: applied wrench;
    ``status``)."""

    returncode: int | None
    output: str
    counters: dict[str, int]
    session: np.ndarray
    seq: np.ndarray
    u: np.ndarray
    status: np.ndarray


class ServerProcess(ServiceProcess):
    """``haptic-topology device-server`` in its own process (see module doc)."""

    def __init__(self, tmp: Path, scenario: str = 'fig8', port: int = 0,
                 host: str = '127.0.0.1', extra: tuple[str, ...] = (),
                 tag: str = 'server') -> None:
        self.dir = tmp
        self.summary = tmp / f'{tag}.summary.json'
        self.log = tmp / f'{tag}.log.csv'
        for p in (self.summary, self.log):
            p.unlink(missing_ok=True)
        super().__init__('haptic_topology.remote.server_command',
                         ['--scenario', scenario, '--host', host, '--port', str(port),
                          '--summary', str(self.summary), '--log', str(self.log), *extra],
                         tmp, tag, 'device server')
        self.host = str(self.info['host'])
        self.session = int(self.info['session'])
        self.pid = int(self.info['pid'])

    def stop(self, timeout: float = 20.0) -> ServerResult:  # type: ignore[override]
        """SIGINT, wait, read summary and log."""
        text = super().stop(timeout)
        counters = json.loads(self.summary.read_text())
        _, session, seq, u, status = read_log(self.log)
        return ServerResult(self.proc.returncode, text, counters, session, seq, u, status)


def read_log(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The server's ``--log``: per cycle its time (monotonic ns), the applied command's
    session and seq (0: none), the applied wrench (n x m), the status."""
    lines = path.read_text(encoding='utf-8').splitlines()
    head = lines[0].split(',')
    assert head[:3] == ['t_ns', 'applied_session', 'applied_seq'], head
    m = sum(1 for h in head if h.startswith('u'))
    rows = [line.split(',') for line in lines[1:]]
    col = [np.array([int(r[i]) for r in rows], dtype=np.int64) for i in range(3)]
    u = np.array([[float(v) for v in r[3:3 + m]] for r in rows]).reshape(len(rows), m)
    status = np.array([int(r[3 + m]) for r in rows], dtype=np.int64)
    return col[0], col[1], col[2], u, status


# -- a raw client -------------------------------------------------------------------------------
class RawClient:
    """A protocol client made of one UDP socket (crafts any datagram)."""

    def __init__(self, host: str, port: int, m: int = 3) -> None:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        family, _, _, _, self.addr = infos[0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock.bind(('::' if family == socket.AF_INET6 else '0.0.0.0', 0))
        self.m = m
        self.session = P.new_session()
        self.seq = 0

    def command(self, wrench: list[float], flags: P.CommandFlags = P.CommandFlags.ENGAGED,
                seq: int | None = None, session: int | None = None,
                ttl_us: int = 1_000_000) -> bytes:
        if seq is None:
            self.seq += 1
            seq = self.seq
        return P.encode_command(session or self.session, seq, time.monotonic_ns(), 0, 0, flags,
                                ttl_us, wrench)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)

    def states(self, timeout: float) -> list[P.State]:
        """Valid states received within ``timeout`` s (at least one wait)."""
        out: list[P.State] = []
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if not select.select([self.sock], [], [], max(left, 0.0))[0]:
                return out
            data = self.sock.recv(4096)
            st = P.decode(data, self.m, P.PacketType.STATE)
            assert isinstance(st, P.State)
            out.append(st)
            if left <= 0:
                return out

    def wait_state(self, cond: Callable[[P.State], bool], timeout: float, what: str
                   ) -> P.State:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for st in self.states(0.01):
                if cond(st):
                    return st
        raise AssertionError(f'no state {what} within {timeout} s')

    def close(self) -> None:
        self.sock.close()


def with_nan(data: bytes, offset: int) -> bytes:
    """``data`` with a NaN float64 at ``offset`` and the CRC made valid again."""
    b = bytearray(data)
    struct.pack_into('<d', b, offset, math.nan)
    struct.pack_into('<I', b, len(b) - 4, zlib.crc32(b[:-4]))
    return bytes(b)


# -- the relay ----------------------------------------------------------------------------------
@dataclass
class Direction:
    """What the relay did in one direction."""

    index: int = 0
    forwarded: int = 0
    actions: dict[str, int] = field(default_factory=lambda: dict.fromkeys(PATTERN.values(), 0))
    #: (session, seq) of the original datagrams whose only copy was dropped or made
    #: malformed (a client's seqs start again at 1 in each session).
    spoiled: set[tuple[int, int]] = field(default_factory=set)
    #: (session, seq) of those that were duplicated, reordered or delayed.
    shuffled: set[tuple[int, int]] = field(default_factory=set)

    def spoiled_seqs(self, session: int) -> set[int]:
        """The spoiled seqs of one session."""
        return {q for s, q in self.spoiled if s == session}


class Relay:
    """A fault-injecting UDP relay (module doc). Clients send to ``(host, port)``; it forwards
    to ``server`` and the server's answers back to the newest client address."""

    def __init__(self, server: tuple[str, int], host: str = '127.0.0.1',
                 pattern: dict[int, str] | None = None) -> None:
        self.server = server
        self.pattern = PATTERN if pattern is None else pattern
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind((host, 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind((host, 0))
        self.host, self.port = self.front.getsockname()[:2]
        self.c2s = Direction()
        self.s2c = Direction()
        self._client: tuple[str, int] | None = None
        #: a reordered datagram held until the next one in its direction has gone (or for
        #: at most 20 ms), with the time it was held
        self._held: dict[str, tuple[bytes, float] | None] = {'c2s': None, 's2c': None}
        self._delayed: list[tuple[float, str, bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='relay', daemon=True)
        self.error: BaseException | None = None
        self._thread.start()

    @property
    def idle(self) -> bool:
        """Nothing held back."""
        return not self._delayed and self._held['c2s'] is None and self._held['s2c'] is None

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.front.close()
        self.back.close()
        if self.error is not None:
            raise self.error

    def _out(self, way: str, data: bytes) -> None:
        if way == 'c2s':
            self.back.sendto(data, self.server)
            self.c2s.forwarded += 1
        elif self._client is not None:
            self.front.sendto(data, self._client)
            self.s2c.forwarded += 1

    def _handle(self, way: str, data: bytes) -> None:
        d = self.c2s if way == 'c2s' else self.s2c
        k = d.index
        d.index += 1
        action = self.pattern.get(k % 50)
        seq = struct.unpack_from('<IQ', data, 12) if len(data) >= 24 else (-1, -1)
        held = self._held[way]
        self._held[way] = None
        if action is None:
            self._out(way, data)
        else:
            d.actions[action] += 1
            if action == 'drop':
                d.spoiled.add(seq)
            elif action == 'duplicate':
                d.shuffled.add(seq)
                self._out(way, data)
                self._out(way, data)
            elif action == 'reorder':
                d.shuffled.add(seq)
                self._held[way] = (data, time.monotonic())
            elif action == 'delay':
                d.shuffled.add(seq)
                self._delayed.append((time.monotonic() + DELAY, way, data))
            elif action == 'corrupt':
                d.spoiled.add(seq)
                b = bytearray(data)
                b[(k * 7) % len(b)] ^= 0x5A
                self._out(way, bytes(b))
            elif action == 'nan':
                d.spoiled.add(seq)
                self._out(way, with_nan(data, P.HEADER.size + 8 if way == 'c2s'
                                        else P.HEADER.size + 16))
            elif action == 'truncate':
                d.spoiled.add(seq)
                self._out(way, data[:-10])
        if held is not None:
            self._out(way, held[0])

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                ready = select.select([self.front, self.back], [], [], 0.0005)[0]
                for sock in ready:
                    data, addr = sock.recvfrom(4096)
                    if sock is self.front:
                        self._client = (addr[0], addr[1])
                        self._handle('c2s', data)
                    else:
                        self._handle('s2c', data)
                now = time.monotonic()
                due = [x for x in self._delayed if x[0] <= now]
                if due:
                    self._delayed = [x for x in self._delayed if x[0] > now]
                    for _, way, data in due:
                        self._out(way, data)
                for way in ('c2s', 's2c'):   # no successor within 20 ms: let it go
                    held = self._held[way]
                    if held is not None and now - held[1] > 0.02:
                        self._held[way] = None
                        self._out(way, held[0])
        except BaseException as exc:  # reported by stop()
            self.error = exc


# -- the server process as a conformance DeviceSide ----------------------------------------------
class ServerDevice(MonitoredDevice):
    """The device server process as a :class:`backend_conformance.DeviceSide`
    (:class:`service_process.MonitoredDevice`): its monitor stream (``--monitor``) is a copy of
    every cycle's STATE, stamped with the cycle's monotonic time, the wrench its
    ``applied_wrench``; ``log`` stops the process and reads its per-cycle log (``t_ns``,
    applied wrench)."""

    def __init__(self, tmp: Path, scenario: str = 'fig8', extra: tuple[str, ...] = ()) -> None:
        from haptic_topology.sim.scenario import load_scenario

        super().__init__()
        self.m = load_scenario(scenario).linkage.task.dim
        self.service = self.server = ServerProcess(tmp, scenario,
                                                   extra=(*self.monitor_arg, *extra),
                                                   tag='device')
        self.port = self.server.port
        self.result: ServerResult | None = None

    def take(self, data: bytes) -> tuple[int, np.ndarray]:
        st = P.decode(data, self.m, P.PacketType.STATE)
        assert isinstance(st, P.State)
        return st.stamp_ns, st.applied_wrench

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        if self.result is None:
            self.stopped = True
            self.result = self.server.stop()
        t, _, _, u, _ = read_log(self.server.log)
        return t, u
