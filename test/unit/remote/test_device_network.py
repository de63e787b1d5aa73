"""The device network protocol, the ``network`` backend and the device server.

* protocol: round trip, sizes of the module doc, every malformed case refused with its reason,
  the sequence-number example of the module doc, sessions;
* the server in this process on an injected clock (exact counts, timeouts, release, takeover);
* the backend against a fake device socket in this process on an injected clock (exact
  counts, stale -> FAULT -> the driver's loop writes zero, a restarted server followed);
* the backend against the server in ANOTHER PROCESS (``python -m
  haptic_topology.remote.server_command``), directly and through a fault-injecting relay: what
  the server applied is, cycle by cycle, the clamped wrench the client sent with that seq or
  zero, never a corrupted, repeated or older one; commands stop -> zero; server killed and
  restarted -> the driver's loop recovers.

The shared backend conformance checks run on this backend in ``test_network_conformance.py``.

Wall-clock tests assert only what holds on any machine (finite, within limits, equal to what
was sent, recovers, counters consistent), never rates or latencies.
"""

from __future__ import annotations

import math
import re
import socket
import struct
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from network_harness import (
    MALFORMING,
    RawClient,
    Relay,
    ServerProcess,
    wait_for,
    with_nan,
)

from haptic_topology.config.settings import parse_backend_options
from haptic_topology.device.backend import (
    BackendConfig,
    DeviceBackend,
    backend_class,
    create_backend,
)
from haptic_topology.device.loop import DeviceLoop
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.remote import protocol as P
from haptic_topology.remote.network import NetworkBackend
from haptic_topology.remote.server import DeviceServer, ServerConfig
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode, DeviceStatus, TaskSpace

PENALTY = int(ControlMode.PENALTY)
FAULT = DeviceStatus.FAULT
LIMIT = np.array([20.0, 20.0, 2.0])       # fig8
ENGAGED = P.CommandFlags.ENGAGED


class FakeClock:
    """Monotonic ns, advanced by the test."""

    def __init__(self) -> None:
        self.ns = 10**12

    def __call__(self) -> int:
        return self.ns

    def advance(self, seconds: float) -> None:
        self.ns += round(seconds * 1e9)


def _config(options: dict[str, object] | None = None, scenario: str = 'fig8') -> BackendConfig:
    sc = load_scenario(scenario)
    return BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), options or {},
                         sc.source)


# -- protocol ------------------------------------------------------------------------------------
@pytest.mark.parametrize('m', [3, 6])
def test_round_trip_and_documented_sizes(m: int) -> None:
    w = np.linspace(-1.5, 2.5, m)
    data = P.encode_command(7, 42, 123, 41, 99, ENGAGED, 20_000, w)
    assert len(data) == P.command_size(m) == {3: 84, 6: 108}[m]
    c = P.decode(data, m, P.PacketType.COMMAND)
    assert isinstance(c, P.Command)
    assert (c.session, c.seq, c.stamp_ns, c.echo_seq, c.echo_stamp_ns, c.flags, c.ttl_us) == (
        7, 42, 123, 41, 99, ENGAGED, 20_000)
    np.testing.assert_array_equal(c.wrench, w)
    vec = [np.arange(m) + 10.0 * k + 0.125 for k in range(4)]
    status = int(DeviceStatus.WORKSPACE_LIMIT | P.ServerStatus.COMMAND_TIMEOUT)
    data = P.encode_state(9, 2**64 - 1, 5, 6, 7, status, 41, *vec)
    assert len(data) == P.state_size(m) == {3: 164, 6: 260}[m]
    s = P.decode(data)
    assert isinstance(s, P.State)
    assert (s.session, s.seq, s.stamp_ns, s.echo_seq, s.echo_stamp_ns, s.status,
            s.applied_seq) == (9, 2**64 - 1, 5, 6, 7, status, 41)
    for got, want in zip((s.pose, s.twist, s.hand_wrench, s.applied_wrench), vec, strict=True):
        np.testing.assert_array_equal(got, want)
    # the layout of the module doc, byte by byte
    assert data[:4] == b'HTDP' and data[4] == 1 and data[5] == 2 and data[8] == m
    assert struct.unpack_from('<IQ', data, 12) == (9, 2**64 - 1)
    assert struct.unpack_from('<IIQ', data, 48) == (status, 0, 41)
    assert struct.unpack_from(f'<{m}d', data, 64 + 24 * m) == tuple(vec[3])
    assert struct.unpack_from('<I', data, len(data) - 4)[0] == zlib.crc32(data[:-4])


def _cmd(m: int = 3, **kw: object) -> bytes:
    args: dict[str, object] = dict(session=1, seq=1, stamp_ns=0, echo_seq=0, echo_stamp_ns=0,
                                   flags=ENGAGED, ttl_us=1000, wrench=[1.0] * m)
    args.update(kw)
    return P.encode_command(**args)  # type: ignore[arg-type]


def _recrc(b: bytearray) -> bytes:
    struct.pack_into('<I', b, len(b) - 4, zlib.crc32(b[:-4]))
    return bytes(b)


def _patched(offset: int, fmt: str, value: object) -> bytes:
    b = bytearray(_cmd())
    struct.pack_into(fmt, b, offset, value)
    return _recrc(b)


def _flipped(offset: int) -> bytes:
    b = bytearray(_cmd())
    b[offset] ^= 0x01
    return bytes(b)


MALFORMED_CASES = [
    ('empty', b'', P.Malformed.SIZE, 'datagram of 0 bytes'),
    ('truncated', _cmd()[:-1], P.Malformed.SIZE, 'COMMAND of m = 3 must be 84 bytes, got 83'),
    ('too long', _cmd() + b'\0', P.Malformed.SIZE, 'must be 84 bytes, got 85'),
    ('header only', _cmd()[:52], P.Malformed.SIZE, 'must be 84 bytes, got 52'),
    ('bad magic', b'XTDP' + _cmd()[4:], P.Malformed.MAGIC, "magic b'XTDP'"),
    ('version 2', _patched(4, '<B', 2), P.Malformed.VERSION, 'protocol version 2'),
    ('type 9', _patched(5, '<B', 9), P.Malformed.TYPE, 'packet type 9'),
    ('m = 4', _patched(8, '<B', 4), P.Malformed.DIM, 'task dimension m = 4, expected 3'),
    ('m = 6 here', _cmd(6), P.Malformed.DIM, 'task dimension m = 6, expected 3'),
    ('flipped wrench bit', _flipped(60), P.Malformed.CRC, 'corrupted'),
    ('flipped reserved byte', _flipped(10), P.Malformed.CRC, 'corrupted'),
    ('flipped crc', _flipped(83), P.Malformed.CRC, 'corrupted'),
    ('seq 0', _patched(16, '<Q', 0), P.Malformed.FIELD, 'seq 0 must be >= 1'),
    ('session 0', _patched(12, '<I', 0), P.Malformed.FIELD, 'session 0'),
    ('unknown flag', _patched(6, '<H', 4), P.Malformed.FIELD, 'unknown command flags 0x4'),
    ('ttl 0', _patched(48, '<I', 0), P.Malformed.FIELD, 'ttl_us must be >= 1'),
    ('NaN wrench', with_nan(_cmd(), 56), P.Malformed.NON_FINITE, 'wrench[0] is nan'),
    ('inf wrench', _patched(64, '<d', -math.inf), P.Malformed.NON_FINITE, 'wrench[1] is -inf'),
]


@pytest.mark.parametrize(('data', 'reason', 'text'), [c[1:] for c in MALFORMED_CASES],
                         ids=[c[0] for c in MALFORMED_CASES])
def test_malformed_datagrams_are_refused_with_their_reason(data: bytes, reason: P.Malformed,
                                                           text: str) -> None:
    with pytest.raises(P.ProtocolError, match=re.escape(text)) as err:
        P.decode(data, 3, P.PacketType.COMMAND)
    assert err.value.reason is reason
    assert isinstance(err.value, DeviceError)


def test_state_checks_and_wrong_type() -> None:
    st = P.encode_state(1, 1, 0, 0, 0, 0, 0, [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3)
    with pytest.raises(P.ProtocolError, match='packet type STATE, expected COMMAND here'):
        P.decode(st, 3, P.PacketType.COMMAND)
    b = bytearray(st)
    struct.pack_into('<I', b, 48, 1 << 20)
    with pytest.raises(P.ProtocolError, match='unknown status bits 0x100000') as err:
        P.decode(_recrc(b))
    assert err.value.reason is P.Malformed.FIELD
    with pytest.raises(P.ProtocolError, match=re.escape('state values[7] is inf')) as err:
        P.decode(_recrc(_with_inf(st, 64 + 8 * 7)))
    assert err.value.reason is P.Malformed.NON_FINITE


def _with_inf(data: bytes, offset: int) -> bytearray:
    b = bytearray(data)
    struct.pack_into('<d', b, offset, math.inf)
    return b


@pytest.mark.parametrize(('kw', 'text'), [
    ({'wrench': [1.0, math.nan, 0.0]}, 'wrench[1] is nan: only finite numbers are sent'),
    ({'wrench': [1.0, 2.0]}, 'task dimension must be 3 or 6, got 2'),
    ({'seq': 0}, 'seq must be in [1, 2^64 - 1], got 0'),
    ({'session': 2**32}, 'session must be in [1, 2^32 - 1]'),
    ({'ttl_us': 0}, 'ttl_us must be in [1, 2^32 - 1], got 0'),
    ({'flags': 8}, 'unknown command flags 0x8'),
])
def test_encode_refuses_what_cannot_be_sent(kw: dict[str, object], text: str) -> None:
    with pytest.raises(P.ProtocolError, match=re.escape(text)):
        _cmd(**kw)
    with pytest.raises(P.ProtocolError, match=re.escape('pose[2] is inf')):
        P.encode_state(1, 1, 0, 0, 0, 0, 0, [0.0, 0.0, math.inf], [0.0] * 3, [0.0] * 3,
                       [0.0] * 3)


def test_seq_tracker_module_doc_example_and_window() -> None:
    t = P.SeqTracker()
    got = [t.arrive(s).value for s in (1, 2, 5, 3, 3, 2, 6)]
    assert got == ['new', 'new', 'new', 'late', 'duplicate', 'duplicate', 'new']
    assert (t.new, t.late, t.duplicate, t.lost, t.too_old) == (4, 1, 2, 1, 0)
    t.arrive(6 + 2000)                          # a jump beyond the window
    assert t.lost == 1 + 1999
    assert t.arrive(6) is P.Arrival.TOO_OLD     # too far back to tell duplicate from late
    assert t.arrive(2006 - 1023) is P.Arrival.LATE
    assert t.arrive(2006 - 1023) is P.Arrival.DUPLICATE
    assert t.lost == 1999


def test_session_follower_takeover_end_and_totals() -> None:
    f = P.SessionFollower(0.5)
    assert f.check(11, 0.0) is P.SessionVerdict.NEW
    f.tracker.arrive(1)
    f.heard_from(0.0)
    assert f.check(11, 0.1) is P.SessionVerdict.CURRENT
    assert f.check(22, 0.4) is P.SessionVerdict.FOREIGN        # 11 alive
    assert f.check(22, 0.5) is P.SessionVerdict.NEW            # 11 silent 0.5 s
    f.tracker.arrive(3)                                        # 2 lost in session 22
    f.end()
    assert f.check(22, 0.6) is P.SessionVerdict.ENDED
    assert f.check(33, 0.6) is P.SessionVerdict.NEW            # nothing followed: at once
    assert f.totals() == {'new': 2, 'duplicate': 0, 'late': 0, 'too_old': 0, 'lost': 2,
                          'foreign': 1, 'ended_session': 1}
    assert f.sessions == 3


# -- the server in this process, injected clock -------------------------------------------------
def _server(clock: FakeClock, **kw: object) -> DeviceServer:
    kw.setdefault('port', 0)
    cfg = ServerConfig(log_cycles=100_000, **kw)  # type: ignore[arg-type]
    return DeviceServer(load_scenario('fig8'), cfg, clock_ns=clock)


def _take(server: DeviceServer, datagrams: int) -> None:
    """Cycle the server until it has received ``datagrams`` in all (loopback delivers them
    in order; this waits for the kernel, not for time)."""
    deadline = time.monotonic() + 10.0
    while True:
        server.cycle(0.001)
        if server.datagrams >= datagrams:
            return
        assert time.monotonic() < deadline, f'server got {server.datagrams} of {datagrams}'


def _last(server: DeviceServer) -> tuple[int, np.ndarray, int]:
    k = server.log_n - 1
    return int(server.log_seq[k]), server.log_u[k].copy(), int(server.log_status[k])


def test_server_applies_only_valid_new_commands_clamped_and_counts_the_rest() -> None:
    clock = FakeClock()
    server = _server(clock)
    c = RawClient(server.host, server.port)
    try:
        sent = 0

        def send(data: bytes) -> None:
            nonlocal sent
            c.send(data)
            sent += 1
            _take(server, sent)

        send(c.command([0.0, 0.0, 0.0], flags=P.CommandFlags.NONE))     # idle: parked
        seq, u, status = _last(server)
        assert (seq, status & int(P.ServerStatus.PARKED)) == (0, int(P.ServerStatus.PARKED))
        np.testing.assert_array_equal(u, np.zeros(3))
        send(c.command([1.0, 2.0, 0.1]))                                  # seq 2, applied
        assert _last(server)[0] == 2
        np.testing.assert_array_equal(_last(server)[1], [1.0, 2.0, 0.1])
        send(c.command([100.0, -100.0, 50.0]))                            # seq 3, clamped
        seq, u, status = _last(server)
        assert seq == 3 and status & int(DeviceStatus.SATURATED)
        np.testing.assert_array_equal(u, [20.0, -20.0, 2.0])
        spoiled = [13.0, 13.0, 1.3]                   # a wrench that must never be applied
        bad = bytearray(c.command(spoiled))           # seq 4
        bad[60] ^= 0x10
        send(bytes(bad))                                                  # crc
        send(c.command(spoiled)[:-3])                                     # seq 5, size
        send(b'ABCD' + c.command(spoiled)[4:])                            # seq 6, magic
        send(with_nan(c.command(spoiled), 56))                            # seq 7, NaN
        send(c.command(spoiled, seq=3))                                   # duplicate of 3
        send(c.command([3.0, 3.0, 0.3], seq=10))                          # new (8, 9 lost)
        send(c.command(spoiled, seq=9))                                   # late
        send(c.command(spoiled, seq=12, session=c.session + 1))           # foreign session
        send(P.encode_state(c.session, 11, 0, 0, 0, 0, 0, *[[0.0] * 3] * 4))   # type
        send(c.command(spoiled + spoiled, seq=11))                        # m = 6: dim
        seq, u, _ = _last(server)
        assert seq == 10
        np.testing.assert_array_equal(u, [3.0, 3.0, 0.3])
        applied = {int(s) for s in server.log_seq[:server.log_n]}
        assert applied == {0, 2, 3, 10}
        assert not np.any(np.all(np.isclose(server.log_u[:server.log_n], [13.0, 13.0, 1.3]),
                                 axis=1))
        got = server.counters()
        want = {'datagrams': 13, 'commands': 4, 'malformed': 6, 'malformed_crc': 1,
                'malformed_size': 1, 'malformed_magic': 1, 'malformed_non_finite': 1,
                'malformed_type': 1, 'malformed_dim': 1, 'duplicate': 1, 'late': 1,
                'lost': 5, 'foreign': 1, 'client_sessions': 1, 'command_timeouts': 0}
        assert {k: got[k] for k in want} == want
        # lost: 4, 5, 6, 7 (their datagrams were refused) and 8; 9 came late
        assert np.all(np.abs(server.log_u[:server.log_n]) <= LIMIT)
    finally:
        c.close()
        server.close()


def test_server_zeroes_the_output_when_commands_stop_or_expire_and_on_release() -> None:
    clock = FakeClock()
    server = _server(clock, command_timeout=0.02, takeover_after=0.5)
    c = RawClient(server.host, server.port)
    try:
        c.send(c.command([1.0, 0.0, 0.0]))
        _take(server, 1)
        for dt, applied in ((0.019, True), (0.001, True), (0.0005, False), (0.01, False)):
            clock.advance(dt)
            server.cycle(0.001)
            seq, u, status = _last(server)
            assert (seq == 1) is applied
            np.testing.assert_array_equal(u, [1.0, 0.0, 0.0] if applied else np.zeros(3))
            assert bool(status & int(P.ServerStatus.COMMAND_TIMEOUT)) is not applied
        assert (server.command_timeouts, server.timeout_cycles) == (1, 2)
        # a command's own ttl: applied 5 ms only
        c.send(c.command([2.0, 0.0, 0.0], ttl_us=5000))
        _take(server, 2)
        assert _last(server)[0] == 2
        clock.advance(0.0051)
        server.cycle(0.001)
        assert _last(server)[0] == 0 and server.command_timeouts == 2
        # release: zero at once, the session ends, its packets are refused; a new one at once
        c.send(c.command([4.0, 0.0, 0.0]))
        _take(server, 3)
        assert _last(server)[0] == 3
        c.send(c.command([0.0, 0.0, 0.0], flags=P.CommandFlags.RELEASE))
        _take(server, 4)
        seq, u, status = _last(server)
        assert seq == 0 and not np.any(u) and not status & int(P.ServerStatus.COMMAND_TIMEOUT)
        c.send(c.command([5.0, 0.0, 0.0]))
        _take(server, 5)
        assert _last(server)[0] == 0 and server.follower.ended_packets == 1
        other = RawClient(server.host, server.port)
        other.send(other.command([6.0, 0.0, 0.0]))
        _take(server, 6)
        assert _last(server)[0] == 1 and server.follower.sessions == 2
        np.testing.assert_array_equal(_last(server)[1], [6.0, 0.0, 0.0])
        other.close()
        assert server.releases == 1
    finally:
        c.close()
        server.close()


def test_server_follows_one_client_until_it_is_silent_and_parks_until_engaged() -> None:
    clock = FakeClock()
    server = _server(clock, takeover_after=0.5)
    a, b = RawClient(server.host, server.port), RawClient(server.host, server.port)
    try:
        x0 = server.backend.idle(0.0).pose.copy()
        a.send(a.command([5.0, 0.0, 0.0], flags=P.CommandFlags.NONE))
        _take(server, 1)
        for _ in range(20):
            server.cycle(0.001)
        np.testing.assert_array_equal(server.backend.idle(0.0).pose, x0)   # parked
        a.send(a.command([1.0, 0.0, 0.0]))                   # seq 2, engaged
        _take(server, 2)
        assert _last(server)[0] == 2 and server.engaged
        b.send(b.command([9.0, 0.0, 0.0]))
        _take(server, 3)
        assert _last(server)[0] == 2 and server.follower.foreign == 1
        clock.advance(0.5)
        b.send(b.command([9.0, 0.0, 0.0]))
        _take(server, 4)
        np.testing.assert_array_equal(_last(server)[1], [9.0, 0.0, 0.0])
        assert server.follower.sessions == 2
    finally:
        a.close()
        b.close()
        server.close()


def test_server_config_is_checked() -> None:
    with pytest.raises(ConfigError, match='port must be in'):
        ServerConfig(port=70000)
    with pytest.raises(ConfigError, match='command_timeout must be in'):
        ServerConfig(command_timeout=0.0)
    with pytest.raises(ConfigError, match='rate_hz must be 0'):
        ServerConfig(rate_hz=5.0)
    with pytest.raises(DeviceError, match='cannot bind'):
        s = _server(FakeClock())
        try:
            _server(FakeClock(), port=s.port)
        finally:
            s.close()


# -- the backend against a fake device socket, injected clock -----------------------------------
class FakeDevice:
    """A UDP socket playing the device server for a :class:`NetworkBackend`."""

    def __init__(self, m: int = 3) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.sock.settimeout(10.0)
        self.port = self.sock.getsockname()[1]
        self.m = m
        self.session = P.new_session()
        self.seq = 0
        self.client: tuple[str, int] | None = None

    def state(self, pose: list[float], status: int = 0, seq: int | None = None,
              session: int | None = None, m: int | None = None) -> bytes:
        if seq is None:
            self.seq += 1
            seq = self.seq
        m = m or self.m
        pose = (pose * 2)[:m]
        return P.encode_state(session or self.session, seq, 1, 0, 0, status, 0, pose,
                              [0.0] * m, [0.4] + [0.0] * (m - 1), [0.0] * m)

    def recv_command(self) -> P.Command:
        data, addr = self.sock.recvfrom(4096)
        self.client = (addr[0], addr[1])
        c = P.decode(data, self.m, P.PacketType.COMMAND)
        assert isinstance(c, P.Command)
        return c

    def recv_seq(self, seq: int) -> P.Command:
        """The command with ``seq``, skipping the older ones still queued."""
        while True:
            c = self.recv_command()
            if c.seq >= seq:
                assert c.seq == seq, f'expected command {seq}, got {c.seq}'
                return c

    def send(self, data: bytes) -> None:
        assert self.client is not None
        self.sock.sendto(data, self.client)

    def close(self) -> None:
        self.sock.close()


def _activated(dev: FakeDevice, clock: FakeClock | None = None,
               options: dict[str, object] | None = None) -> NetworkBackend:
    """A backend activated against ``dev`` (which answers its first idle command)."""
    be = NetworkBackend(clock_ns=clock) if clock is not None else NetworkBackend()
    be.configure(_config({'port': dev.port, 'stale_ms': 10.0, **(options or {})}))
    err: list[BaseException] = []

    def activate() -> None:
        try:
            be.activate()
        except BaseException as exc:
            err.append(exc)

    t = threading.Thread(target=activate)
    t.start()
    c = dev.recv_command()
    assert c.flags == P.CommandFlags.NONE and not np.any(c.wrench)
    dev.send(dev.state([0.09, 0.01, 0.0]))
    t.join(10.0)
    assert not err, err
    return be


def _read_until(be: NetworkBackend, pose0: float, timeout: float = 10.0) -> DeviceStatus:
    """Read until the state whose pose[0] is ``pose0`` is the newest taken."""
    deadline = time.monotonic() + timeout
    while True:
        r = be.read(0.001)
        if r.pose[0] == pose0:
            return r.status
        assert time.monotonic() < deadline, f'no state with pose[0] = {pose0}'
        time.sleep(0.001)


@pytest.mark.parametrize(('options', 'text'), [
    ({'port': 0}, 'backend_options.port: expected an integer port in [1, 65535], got 0'),
    ({'port': '47001'}, "backend_options.port: expected an integer port in [1, 65535], got "
     "'47001'"),
    ({'local_port': 70000}, 'backend_options.local_port: expected an integer port in '
     '[0, 65535], got 70000'),
    ({'stale_ms': 0}, 'backend_options.stale_ms: expected a number in (0, 10000], got 0'),
    ({'stale_ms': math.nan}, 'backend_options.stale_ms: expected a number in (0, 10000]'),
    ({'wait_ms': 5}, 'backend_options.wait_ms: expected a number in [0, 1], got 5'),
    ({'command_ttl_ms': True}, 'backend_options.command_ttl_ms: expected a number'),
    ({'host': 5}, 'backend_options.host: expected an address (text), got 5'),
    ({'host': 'no-such-host.invalid'}, "backend_options.host: cannot resolve "
     "'no-such-host.invalid'"),
    ({'prot': 1}, "backend_options: unknown option 'prot' (expected some of: command_ttl_ms, "
     'connect_timeout_ms, host, key_file, local_host, local_port, port, stale_ms, '
     'trusted_network, wait_ms)'),
    ({'trusted_network': 'yes'}, "backend_options.trusted_network: expected true or false, "
     "got 'yes'"),
])
def test_backend_options_are_checked(options: dict[str, object], text: str) -> None:
    with pytest.raises(DeviceError, match=re.escape(text)):
        NetworkBackend().configure(_config(options))


def test_selected_by_module_class_and_configured_from_the_driver_parameter() -> None:
    """``backend:=network`` (built in) and ``module:Class`` resolve to it; ``backend_options``
    as the driver parses its YAML parameter configure it."""
    assert backend_class('network') is NetworkBackend
    assert backend_class('haptic_topology.remote.network:NetworkBackend') is NetworkBackend
    be = create_backend('haptic_topology.remote.network:NetworkBackend')
    opts = parse_backend_options('{host: 127.0.0.1, port: 47001, stale_ms: 20, '
                                 'command_ttl_ms: 15.5, wait_ms: 0.2}')
    be.configure(_config(opts))
    assert be.hardware_id == 'network 127.0.0.1:47001 planar, unauthenticated link'


def test_lifecycle_without_a_device_and_before_activate() -> None:
    be = NetworkBackend()
    with pytest.raises(DeviceError, match='used before configure'):
        be.task_dim()
    assert be.hardware_id == 'network'
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)     # bound, never answers
    silent.bind(('127.0.0.1', 0))
    port = silent.getsockname()[1]
    try:
        be.configure(_config({'port': port, 'connect_timeout_ms': 50}))
        assert be.hardware_id == f'network 127.0.0.1:{port} planar, unauthenticated link'
        for call in (lambda: be.read(0.001), lambda: be.write(np.zeros(3)),
                     lambda: be.idle(0.001)):
            with pytest.raises(DeviceError, match=r'before activate\(\)'):
                call()
        with pytest.raises(DeviceError, match=re.escape(
                f'network: no valid STATE from 127.0.0.1:{port} within 50 ms '
                '(connect_timeout_ms); received 0 datagrams: is `haptic-topology '
                'device-server` running there')):
            be.activate()
        be.deactivate()
        be.deactivate()                                             # safe, twice
    finally:
        silent.close()


def test_activate_names_a_device_of_another_task_dimension() -> None:
    dev = FakeDevice(m=3)
    be = NetworkBackend()
    be.configure(_config({'port': dev.port, 'connect_timeout_ms': 300}))
    err: list[BaseException] = []

    def activate() -> None:
        try:
            be.activate()
        except BaseException as exc:
            err.append(exc)

    t = threading.Thread(target=activate)
    t.start()
    dev.recv_command()
    dev.send(dev.state([0.1, 0.0, 0.0], m=6))
    t.join(10.0)
    dev.close()
    assert len(err) == 1 and isinstance(err[0], DeviceError)
    assert 'dim x1 (task dimension m = 6, expected 3)' in str(err[0])
    assert "another task dimension than this scenario's m = 3" in str(err[0])


def test_backend_takes_only_the_newest_valid_state_and_counts_the_rest() -> None:
    clock = FakeClock()
    dev = FakeDevice()
    be = _activated(dev, clock)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert be.hardware_id == (f'network 127.0.0.1:{dev.port} planar, unauthenticated '
                                  f'link, server session {dev.session:08x}')
        bad = bytearray(dev.state([0.5, 0.0, 0.0]))                 # seq 2, corrupted
        bad[70] ^= 0x20
        dev.send(bytes(bad))
        dev.send(with_nan(dev.state([0.5, 0.0, 0.0]), 64))           # seq 3, NaN pose
        dev.send(dev.state([0.2, 0.0, 0.0], seq=5))                  # new
        dev.send(dev.state([0.5, 0.0, 0.0], seq=4))                  # late
        dev.send(dev.state([0.5, 0.0, 0.0], seq=5))                  # duplicate
        stranger.sendto(dev.state([0.5, 0.0, 0.0], seq=6), be._sock.getsockname())  # type: ignore[union-attr]
        dev.send(dev.state([0.5, 0.0, 0.0], seq=7, session=dev.session ^ 0xFF))  # foreign
        dev.send(dev.state([0.5, 0.0, 0.0], seq=8, m=6))             # dim
        dev.send(dev.state([0.3, 0.0, 0.0], seq=9))                  # marker
        assert _read_until(be, 0.3) == DeviceStatus.OK
        got = be.counters()
        want = {'datagrams': 10, 'states': 3, 'malformed': 3, 'malformed_crc': 1,
                'malformed_non_finite': 1, 'malformed_dim': 1, 'late': 1, 'duplicate': 1,
                'lost': 5, 'foreign_source': 1, 'foreign_session': 1, 'server_sessions': 1,
                'stale_cycles': 0}
        assert {k: got[k] for k in want} == want
        # lost: 2, 3 (refused), 6 (another address), 7 (another session), 8 (refused)
    finally:
        stranger.close()
        be.deactivate()
        dev.close()


def test_backend_never_sends_a_non_finite_wrench_and_releases_on_deactivate() -> None:
    dev = FakeDevice()
    be = _activated(dev)
    try:
        be.write(np.array([math.nan, math.inf, 1.5]))
        c = dev.recv_seq(be.last_sent_seq)
        assert c.flags == ENGAGED
        np.testing.assert_array_equal(c.wrench, [0.0, 0.0, 1.5])
        assert be.counters()['nonfinite_writes'] == 1
        with pytest.raises(DeviceError, match=re.escape('expected 3 wrench values, got shape '
                                                        '(6,)')):
            be.write(np.zeros(6))
        session = be.session
        be.deactivate()
        copies = [dev.recv_seq(c.seq + 1) for _ in range(3)]
        assert {(x.seq, x.flags) for x in copies} == {(c.seq + 1, P.CommandFlags.RELEASE)}
        be.deactivate()
        with pytest.raises(DeviceError, match=r'read\(\) before activate'):
            be.read(0.001)
        be2 = _activated(dev)                       # a new activation is a new session
        assert be2.session != session
        be2.deactivate()
    finally:
        dev.close()


def test_read_waits_at_most_wait_ms_for_the_answer() -> None:
    """``wait_ms``: ``read`` waits for the state that echoes the command just written, at
    most that long; with no answer it returns the newest state it has. An answer that came
    before the read is taken at once."""
    clock = FakeClock()
    dev = FakeDevice()
    be = _activated(dev, clock, {'wait_ms': 1.0})
    try:
        dev.send(dev.state([0.1, 0.0, 0.0]))
        assert _read_until(be, 0.1) == DeviceStatus.OK
        be.write(np.array([1.0, 0.0, 0.0]))
        c = dev.recv_seq(be.last_sent_seq)
        r = be.read(0.001)                          # nothing answers: the newest it has
        assert r.pose[0] == 0.1
        answer = bytearray(dev.state([0.2, 0.0, 0.0]))
        struct.pack_into('<Q', answer, 32, c.seq)   # echo_seq: the command just written
        dev.send(_recrc(answer))
        assert _read_until(be, 0.2) == DeviceStatus.OK
    finally:
        be.deactivate()
        dev.close()


def _engaged_loop(be: DeviceBackend) -> DeviceLoop:
    loop = DeviceLoop(be, LIMIT, CommandWatchdog(WatchdogConfig(), 3), 0.001)
    tick = loop.tick(0.0, 0.001)
    loop.on_command(tick.seq, PENALTY, np.zeros(3), 0.0)
    loop.tick(0.001, 0.001)
    assert loop.engaged and loop.run_index == 0
    return loop


def test_stale_states_fault_the_device_and_the_loop_writes_zero_until_they_return() -> None:
    """No state for longer than ``stale_ms`` (injected clock): the reading carries FAULT with
    the reason, the driver's loop writes zero from the next cycle on; states back: the fault
    clears and the output fades back in at the watchdog's rate. The device's own
    COMMAND_TIMEOUT is a fault too."""
    clock = FakeClock()
    dev = FakeDevice()
    be = _activated(dev, clock, {'stale_ms': 10.0})
    u = np.array([1.0, -0.5, 0.05])
    try:
        dev.send(dev.state([0.1, 0.0, 0.0]))
        assert _read_until(be, 0.1) == DeviceStatus.OK
        loop = _engaged_loop(be)
        t = 0.001
        pose = 0.1

        def cycle(send: bool) -> tuple[np.ndarray, DeviceStatus]:
            """One driver cycle 1 ms later; ``send``: a new state is taken first."""
            nonlocal t, pose
            loop.on_command(loop.seq, PENALTY, u, t)
            clock.advance(0.001)
            t += 0.001
            if send:
                pose += 1e-6
                dev.send(dev.state([pose, 0.0, 0.0]))
                _read_until(be, pose)          # taken now (injected time), whatever the kernel
            tick = loop.tick(t, 0.001)
            cmd = dev.recv_seq(be.last_sent_seq)
            np.testing.assert_array_equal(cmd.wrench, tick.applied)
            return tick.applied, tick.status

        for _ in range(5):
            applied, status = cycle(True)
        assert not status & FAULT
        np.testing.assert_array_equal(applied, u)
        for _ in range(10):                              # 10 ms: not yet stale
            cycle(False)
        assert not loop.fault_active
        applied, status = cycle(False)                   # 11 ms: stale
        assert status & FAULT and loop.fault_active
        assert re.match(r'network: no valid STATE from 127\.0\.0\.1:\d+ for 11\.0 ms '
                        r'\(stale_ms 10\)', be.fault_reason())
        for _ in range(5):
            applied, status = cycle(False)
            np.testing.assert_array_equal(applied, np.zeros(3))
        # states return: the fault clears, the output fades back in
        dev.send(dev.state([0.2, 0.0, 0.0]))
        assert _read_until(be, 0.2) == DeviceStatus.OK
        applied, status = cycle(True)
        np.testing.assert_array_equal(applied, np.zeros(3))   # written after a FAULT read
        applied, status = cycle(True)
        np.testing.assert_allclose(applied, u * 0.001 / 0.05, rtol=1e-12)
        c = be.counters()
        assert c['stale_onsets'] == 1 and c['stale_cycles'] >= 6
        # the device reports that its commands timed out: a fault with its reason
        dev.send(dev.state([0.3, 0.0, 0.0], status=int(P.ServerStatus.COMMAND_TIMEOUT)))
        assert _read_until(be, 0.3) == FAULT
        assert 'had no valid command within its command timeout' in be.fault_reason()
    finally:
        be.deactivate()
        dev.close()


def test_a_restarted_device_server_is_followed_once_the_old_one_is_stale() -> None:
    clock = FakeClock()
    dev = FakeDevice()
    be = _activated(dev, clock)
    try:
        dev.send(dev.state([0.1, 0.0, 0.0]))
        assert _read_until(be, 0.1) == DeviceStatus.OK
        restarted = P.new_session()
        dev.send(dev.state([0.5, 0.0, 0.0], seq=1, session=restarted))
        dev.send(dev.state([0.11, 0.0, 0.0]))                  # the old one, alive
        assert _read_until(be, 0.11) == DeviceStatus.OK
        assert be.counters()['foreign_session'] == 1
        clock.advance(0.011)                                    # the old one went silent
        assert be.read(0.001).status == FAULT
        dev.send(dev.state([0.6, 0.0, 0.0], seq=1, session=restarted))
        assert _read_until(be, 0.6) == DeviceStatus.OK
        c = be.counters()
        assert (c['server_sessions'], c['foreign_session']) == (2, 1)
        assert be.server_session == restarted
    finally:
        be.deactivate()
        dev.close()


# -- the server in another process ----------------------------------------------------------------
@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., ServerProcess]]:
    """Starts device server processes (``ServerProcess`` arguments); kills those still
    running when the test ends, whatever happened in it."""
    made: list[ServerProcess] = []

    def make(**kw: Any) -> ServerProcess:
        kw.setdefault('tag', f'server{len(made)}')
        server = ServerProcess(tmp_path, **kw)
        made.append(server)
        return server

    yield make
    for server in made:
        server.kill()


def _run_loop(be: NetworkBackend, cycles: int, command: np.ndarray | None = None,
              seed: int = 2) -> tuple[DeviceLoop, dict[int, np.ndarray], list[DeviceStatus]]:
    """The driver's loop over ``be`` at 1 kHz for ``cycles`` engaged cycles, every state
    answered (``command``, or random in-range and out-of-range values); returns the loop, the
    wrench written per command seq, and the status of every state."""
    rng = np.random.default_rng(seed)
    loop = _engaged_loop(be)
    sent: dict[int, np.ndarray] = {}
    statuses = []
    pacer = DeadlinePacer(0.001)
    for _ in range(cycles):
        cmd = command if command is not None else rng.uniform(-1.5, 1.5, 3) * LIMIT
        tick = pacer.wait()
        loop.on_command(loop.seq, PENALTY, cmd, tick.now)
        t = loop.tick(tick.now, 0.001)
        sent[be.last_sent_seq] = t.applied
        statuses.append(t.status)
        r = t.reading
        assert np.all(np.isfinite(np.concatenate([r.pose, r.twist, r.hand_wrench])))
        assert np.all(np.isfinite(t.applied)) and np.all(np.abs(t.applied) <= LIMIT)
    return loop, sent, statuses


def _check_applied(seq: np.ndarray, u: np.ndarray, sent: dict[int, np.ndarray],
                   spoiled: frozenset[int] | set[int] = frozenset()) -> int:
    """Every cycle of the server applied zero, or exactly the wrench the client sent with
    that seq (never a spoiled one), and never went back to an older command."""
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= LIMIT)
    assert not np.any(u[seq == 0])
    applied = seq[seq > 0]
    assert np.all(np.diff(applied) >= 0), 'the server went back to an older command'
    for s in np.unique(applied):
        assert int(s) in sent, f'applied seq {s} was never sent as a wrench'
        assert int(s) not in spoiled, f'applied seq {s} was dropped or corrupted on the way'
        np.testing.assert_array_equal(u[seq == s], np.broadcast_to(sent[int(s)],
                                                                  u[seq == s].shape))
    return int(np.unique(applied).size)


def test_backend_and_server_process_closed_loop(spawn: Callable[..., ServerProcess]) -> None:
    """The driver's loop with the network backend against the server process: the server
    applied, per cycle, exactly the clamped wrench the client wrote with that seq or zero;
    nothing refused on the loopback; the release counted."""
    server = spawn()
    be = NetworkBackend()
    be.configure(_config({'port': server.port, 'stale_ms': 200.0}))
    try:
        be.activate()
        _, sent, _ = _run_loop(be, 1500)
    finally:
        be.deactivate()
    res = server.stop()
    assert res.returncode == 0, res.output
    assert _check_applied(res.seq, res.u, sent) > 0
    c = res.counters
    assert c['malformed'] == c['foreign'] == c['duplicate'] == c['late'] == 0
    assert c['client_sessions'] == 1
    assert c['commands'] <= be.counters()['commands_sent']
    assert be.counters()['malformed'] == 0
    assert re.search(r'device-server 127\.0\.0\.1:\d+: \d+ cycles', res.output)
    assert f'{c["commands"]} commands' in res.output


def test_preflight_reaches_the_server_releases_and_leaves_the_run_followed_at_once(
        spawn: Callable[..., ServerProcess]) -> None:
    """``run``'s preflight (:meth:`NetworkBackend.preflight`) against the server process: it
    returns once a STATE came, never engages (the server applies nothing for it), and
    releases, so the run's own session that follows at once is followed (not ``foreign``)
    and its commands are applied; without a server it fails within its connect timeout
    with the backend's line."""
    server = spawn()
    options = {'port': server.port, 'stale_ms': 200.0, 'connect_timeout_ms': 60_000}
    NetworkBackend().preflight(_config(options))
    be = NetworkBackend()
    be.configure(_config(options))
    try:
        be.activate()
        _, sent, _ = _run_loop(be, 300)
    finally:
        be.deactivate()
    res = server.stop()
    assert res.returncode == 0, res.output
    assert _check_applied(res.seq, res.u, sent) > 0
    assert set(np.unique(res.session[res.seq > 0]).tolist()) == {be.session}
    c = res.counters
    assert c['client_sessions'] == 2 and c['releases'] == 2, c
    assert c['foreign'] == c['malformed'] == 0, c
    # A port held by a socket that never answers (released after the check: no other
    # program can take it meanwhile and answer).
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(('127.0.0.1', 0))
        port = int(silent.getsockname()[1])
        with pytest.raises(DeviceError, match=rf'^network: no valid STATE from '
                           rf'127\.0\.0\.1:{port} within 300 ms \(connect_timeout_ms\); '
                           r'received 0 datagrams'):
            NetworkBackend().preflight(_config({'port': port, 'connect_timeout_ms': 300}))


def test_server_process_clamps_and_zeroes_output_when_commands_stop(
        spawn: Callable[..., ServerProcess]) -> None:
    """A raw client (no driver clamping) commands (30 N, -25 N, 0.5 N m) until the server
    process applies one, then stops: the server applied (20, -20, 0.5), the fig8 limit, then
    zero with COMMAND_TIMEOUT from 20 ms after the last command to the end."""
    server = spawn(extra=('--command-timeout-ms', '20'))
    c = RawClient(server.host, server.port)
    try:
        last = 0
        deadline = time.monotonic() + 30.0
        while True:                    # command until the server reports applying one
            c.send(c.command([30.0, -25.0, 0.5]))
            last = c.seq
            got = [s for s in c.states(0.002) if s.applied_seq == last]
            if got:
                break
            assert time.monotonic() < deadline
        st = c.wait_state(lambda s: bool(s.status & int(P.ServerStatus.COMMAND_TIMEOUT)),
                          10.0, 'with COMMAND_TIMEOUT')
        assert st.applied_seq == 0 and not np.any(st.applied_wrench)
    finally:
        c.close()
    res = server.stop()
    assert res.returncode == 0
    n = _check_applied(res.seq, res.u, {s: np.array([20.0, -20.0, 0.5])
                                         for s in range(1, c.seq + 1)})
    assert n >= 1
    last_applied = int(np.nonzero(res.seq)[0].max())
    assert np.all(res.seq[last_applied + 1:] == 0) and not np.any(res.u[last_applied + 1:])
    assert res.counters['command_timeouts'] >= 1 and res.counters['timeout_cycles'] >= 1
    timeout_bit = int(P.ServerStatus.COMMAND_TIMEOUT)
    assert np.all(res.status[last_applied + 1:][-5:] & timeout_bit)


def test_fault_injection_through_a_relay(spawn: Callable[..., ServerProcess]) -> None:
    """Client -> relay -> server process and back; the relay drops, duplicates, reorders,
    delays, corrupts, NaNs and truncates datagrams by index, both ways. No spoiled command was
    ever applied, what was applied is what was sent for that seq, every reading finite; the
    refusals counted at both ends are at most what the relay did, and at least one of each
    kind reached the server."""
    server = spawn()
    relay = Relay(('127.0.0.1', server.port))
    try:
        be = NetworkBackend()
        be.configure(_config({'port': relay.port, 'stale_ms': 100.0}))
        try:
            be.activate()
            _, sent, _ = _run_loop(be, 1500, seed=5)
        finally:
            be.deactivate()
            wait_for(lambda: relay.idle, 5.0, 'the relay to flush what it held')
        res = server.stop()
    finally:
        relay.stop()
    assert res.returncode == 0, res.output
    assert set(res.session[res.seq > 0].tolist()) == {be.session}
    assert _check_applied(res.seq, res.u, sent, relay.c2s.spoiled_seqs(be.session)) > 0
    c, a = res.counters, relay.c2s.actions
    malformed_sent = sum(a[k] for k in MALFORMING)
    assert 1 <= c['malformed'] <= malformed_sent
    assert c['malformed_non_finite'] <= a['nan'] and c['malformed_size'] <= a['truncate']
    assert 1 <= c['duplicate'] <= a['duplicate']
    assert 1 <= c['late'] <= a['reorder'] + a['delay']
    assert c['lost'] >= 1 and c['foreign'] == 0
    b, s = be.counters(), relay.s2c.actions
    assert b['malformed'] <= sum(s[k] for k in MALFORMING)
    assert b['duplicate'] <= s['duplicate']
    assert b['late'] <= s['reorder'] + s['delay']
    assert b['states'] <= relay.s2c.forwarded


def test_server_process_restart_the_client_recovers(
        spawn: Callable[..., ServerProcess]) -> None:
    """SIGKILL the server while the driver's loop runs: the states go stale, the loop writes
    zero; a new server on the same port: its session is followed, the fault clears and the
    loop's output fades back to the command."""
    first = spawn(tag='first')
    port = first.port
    be = NetworkBackend()
    be.configure(_config({'port': port, 'stale_ms': 20.0, 'command_ttl_ms': 20.0}))
    u = np.array([0.5, 0.0, 0.0])
    be.activate()
    second: ServerProcess | None = None
    try:
        loop = _engaged_loop(be)
        pacer = DeadlinePacer(0.001)
        faulted_before = False
        phase = 'run'
        zero_after_fault = 0
        deadline = time.monotonic() + 90.0
        k = 0
        while True:
            tick = pacer.wait()
            loop.on_command(loop.seq, PENALTY, u, tick.now)
            t = loop.tick(tick.now, 0.001)
            if faulted_before:
                np.testing.assert_array_equal(t.applied, np.zeros(3))
                zero_after_fault += 1
            faulted_before = bool(t.status & FAULT)
            k += 1
            if phase == 'run' and k == 300:
                first.kill()
                phase = 'killed'
            elif phase == 'killed' and loop.fault_active:
                second = spawn(port=port, tag='second')
                pacer.start()             # the start-up took long: a fresh deadline grid
                phase = 'restarted'
            elif phase == 'restarted' and not loop.fault_active \
                    and np.array_equal(t.applied, u):
                break
            assert time.monotonic() < deadline, f'no recovery (phase {phase})'
    finally:
        be.deactivate()
    assert second is not None
    res = second.stop()
    c = be.counters()
    assert c['server_sessions'] == 2 and c['stale_onsets'] >= 1
    assert zero_after_fault >= 1 and loop.device_faults >= 1
    assert res.counters['client_sessions'] == 1 and res.counters['applied_cycles'] >= 1
    assert np.all(np.abs(res.u) <= LIMIT)


def test_server_command_line(spawn: Callable[..., ServerProcess]) -> None:
    import subprocess

    out = subprocess.run([sys.executable, '-m', 'haptic_topology.remote.server_command',
                          '--scenario', 'fig8', '--port', '70000'], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2
    assert 'expected an integer port in [0, 65535], got 70000' in out.stderr
    out = subprocess.run([sys.executable, '-m', 'haptic_topology.remote.server_command',
                          '--scenario', 'no_such_scenario', '--port', '0'],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    assert out.stderr.startswith('haptic-topology device-server: error: ')
    server = spawn(extra=('--duration', '0.2'))
    server.proc.wait(60)
    res = server.stop()
    assert res.returncode == 0 and res.counters['cycles'] >= 1
    assert res.counters['states_sent'] == 0            # no client: nothing sent


@pytest.mark.parametrize('scenario', ['fig8_point', 'spatial_arm4_point'])
def test_a_point_task_is_refused_its_packets_name_m_not_the_task(scenario: str) -> None:
    """spatial_point has m = 3 as planar does: a device serving fig8 would answer a
    spatial_arm4_point client with x, y, theta taken as x, y, z. The backend keeps the task
    the scenario declares and refuses a point task at configure, in one line; a rigid task is
    named by its declared task."""
    task = load_scenario(scenario).linkage.task
    be = NetworkBackend()
    with pytest.raises(DeviceError, match=re.escape(
            f'network: scenario task {task.value} (m = {task.dim}): the device protocol '
            'carries the rigid tasks only (m = 3 planar, 6 spatial; its packets name m, not '
            'the task, so a device serving another task of the same m could not be told '
            'apart)')):
        be.configure(_config({}, scenario))
    assert be.task() is None and be.hardware_id == 'network'
    be.configure(_config({}, 'spatial_arm4'))
    assert be.task() is TaskSpace.SPATIAL
    assert be.hardware_id == 'network 127.0.0.1:47001 spatial, unauthenticated link'


def test_the_device_server_refuses_a_point_task() -> None:
    """The server's side of the same rule: it would answer in packets of m = 3 that a planar
    client takes for x, y, theta."""
    with pytest.raises(DeviceError, match=re.escape(
            'device-server: scenario spatial_arm4_point has task spatial_point (m = 3): the '
            'device protocol carries the rigid tasks only (m = 3 planar, 6 spatial; its packets '
            'name m, not the task)')):
        DeviceServer(load_scenario('spatial_arm4_point'),
                     ServerConfig(port=0, log_cycles=100_000), clock_ns=FakeClock())
