"""The authenticated device link (pre-shared key, BLAKE2b-128 MAC on every packet).

Checked without trusting the code under test:

* the MAC of a packet equals ``hashlib.blake2b`` called here directly over the documented
  bytes, and a packet built here from ``struct`` and ``hashlib`` alone is taken;
* a forger that has the protocol but not the key sends well-formed COMMANDs with the client's
  session and its next seq from another address, every cycle: the device applies none of
  them, and what the device applied and the client read are, cycle by cycle, the figures of
  the same run without the forger (server and client in this process on one injected
  clock); the forged ones are counted per reason;
* the same forger against the server process while the client's link goes through the
  lossy relay: nothing forged is ever applied;
* recorded packets replayed later (after the client released, and to a restarted device)
  are refused and counted as replays;
* a key file that others can read is refused at start (server process and backend); an
  unauthenticated link off loopback is refused unless the network is declared trusted.
"""

from __future__ import annotations

import hashlib
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from network_harness import Relay, ServerProcess, wait_for
from service_process import REPO

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.remote import protocol as P
from haptic_topology.remote.auth import LinkKey, load_key, write_key
from haptic_topology.remote.network import NetworkBackend
from haptic_topology.remote.server import DeviceServer, ServerConfig
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))
ENGAGED = P.CommandFlags.ENGAGED
LIMIT = np.array([20.0, 20.0, 2.0])       # fig8


def _key_file(tmp: Path, key: bytes = KEY, mode: int = 0o600, name: str = 'link.key') -> Path:
    p = tmp / name
    p.write_text(key.hex() + '\n', encoding='ascii')
    p.chmod(mode)
    return p


def _blake(data: bytes, key: bytes = KEY) -> bytes:
    return hashlib.blake2b(data, key=key, digest_size=16).digest()


def _key_id(key: bytes = KEY) -> int:
    return int.from_bytes(hashlib.blake2b(key, digest_size=4, person=b'HTDP key id').digest(),
                          'little')


# -- the packet ----------------------------------------------------------------------------------
@pytest.mark.parametrize('m', [3, 6])
def test_the_mac_is_blake2b_keyed_over_everything_before_it(m: int) -> None:
    key = LinkKey(KEY)
    cmd = P.encode_command(0x1234, 7, 99, 3, 98, ENGAGED, 500, [0.5] * m, key, 0xABCD)
    st = P.encode_state(0xABCD, 9, 100, 7, 99, 0, 7, [0.1] * m, [0.0] * m, [0.2] * m,
                        [0.5] * m, key, 0x1234)
    assert (len(cmd), len(st)) == ((104, 184) if m == 3 else (128, 280))
    for data, peer in ((cmd, 0xABCD), (st, 0x1234)):
        assert data[4] == 2                                             # version 2
        assert data[-16:] == _blake(data[:-16])
        assert struct.unpack_from('<II', data, len(data) - 24) == (peer, _key_id())
    got = P.decode(cmd, m, P.PacketType.COMMAND, key)
    assert isinstance(got, P.Command) and got.peer_session == 0xABCD and got.seq == 7
    # a COMMAND made here from the documented layout with struct and hashlib alone is taken
    body = struct.pack(f'<4sBBHB3xIQQQQI4x{m}d', b'HTDP', 2, 1, 1, m, 0x55, 3, 1, 0, 0, 900,
                       *([1.25] * m)) + struct.pack('<II', 0x77, _key_id())
    mine = P.decode(body + _blake(body), m, P.PacketType.COMMAND, key)
    assert isinstance(mine, P.Command)
    assert (mine.session, mine.seq, mine.ttl_us, mine.peer_session) == (0x55, 3, 900, 0x77)
    np.testing.assert_array_equal(mine.wrench, [1.25] * m)


def test_what_fails_the_mac_is_refused_with_its_reason() -> None:
    key = LinkKey(KEY)
    good = P.encode_command(5, 1, 1, 0, 0, ENGAGED, 500, [1.0, 0.0, 0.0], key, 9)
    flipped = bytearray(good)
    flipped[60] ^= 1
    forged_tag = good[:-16] + _blake(good[:-16], OTHER_KEY)        # right key id, wrong key
    other = P.encode_command(5, 1, 1, 0, 0, ENGAGED, 500, [1.0, 0.0, 0.0], LinkKey(OTHER_KEY), 9)
    plain = P.encode_command(5, 1, 1, 0, 0, ENGAGED, 500, [1.0, 0.0, 0.0])
    cases = [(bytes(flipped), P.Rejected.MAC, 'forged or corrupted'),
             (forged_tag, P.Rejected.MAC, 'forged or corrupted'),
             (other, P.Rejected.WRONG_KEY, f'key id {_key_id(OTHER_KEY):08x}'),
             (plain, P.Rejected.UNAUTHENTICATED, r'unauthenticated \(version 1\)')]
    for data, reason, text in cases:
        with pytest.raises(P.ProtocolError, match=text) as err:
            P.decode(data, 3, P.PacketType.COMMAND, key)
        assert err.value.reason is reason
    with pytest.raises(P.ProtocolError, match='this receiver has no key') as err:
        P.decode(good, 3, P.PacketType.COMMAND)
    assert err.value.reason is P.Malformed.VERSION


# -- the key file and the loopback rule ---------------------------------------------------------
def test_key_file_must_be_private_and_hex(tmp_path: Path) -> None:
    assert load_key(_key_file(tmp_path)).key == KEY
    assert load_key(_key_file(tmp_path, mode=0o400, name='ro.key')).key_id == _key_id()
    for mode in (0o644, 0o640, 0o604, 0o620):
        with pytest.raises(ConfigError, match=f'mode {mode:04o} lets others than its owner'):
            load_key(_key_file(tmp_path, mode=mode, name=f'{mode:o}.key'))
    with pytest.raises(ConfigError, match='must be 32 to 64 bytes'):
        load_key(_key_file(tmp_path, key=b'short', name='short.key'))
    bad = tmp_path / 'bad.key'
    bad.write_text('not hex\n')
    bad.chmod(0o600)
    with pytest.raises(ConfigError, match='expected the key as hexadecimal text'):
        load_key(bad)
    made = write_key(tmp_path / 'new.key')
    assert (tmp_path / 'new.key').stat().st_mode & 0o777 == 0o600
    assert load_key(tmp_path / 'new.key').key == made.key and len(made.key) == 32
    with pytest.raises(ConfigError, match='cannot create it'):
        write_key(tmp_path / 'new.key')


def test_device_key_command_writes_a_private_key(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    from haptic_topology import cli

    path = tmp_path / 'device.key'
    assert cli.main(['device-key', str(path)]) == 0
    key = load_key(path)
    assert path.stat().st_mode & 0o777 == 0o600
    assert f'key id {key.key_id:08x}' in capsys.readouterr().out
    assert cli.main(['device-key', str(path)]) != 0          # never overwrites a key
    assert load_key(path).key == key.key


def _config(options: dict[str, object]) -> BackendConfig:
    sc = load_scenario('fig8')
    return BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), options, sc.source)


def test_a_readable_key_file_stops_the_server_and_the_backend_at_start(tmp_path: Path) -> None:
    loose = _key_file(tmp_path, mode=0o644)
    be = NetworkBackend()
    with pytest.raises(DeviceError, match='backend_options.key_file: device link key file '
                       f'{loose}: mode 0644'):
        be.configure(_config({'key_file': str(loose)}))
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.remote.server_command',
                           '--scenario', 'fig8', '--port', '0', '--key-file', str(loose)],
                          capture_output=True, text=True, cwd=REPO, env=dict(os.environ),
                          timeout=120)
    assert proc.returncode == 1
    assert f'device link key file {loose}: mode 0644 lets others' in proc.stderr


def test_off_loopback_needs_a_key_or_a_trusted_network(tmp_path: Path) -> None:
    sc = load_scenario('fig8')
    with pytest.raises(ConfigError, match=r'device-server: serving on 0\.0\.0\.0: 0\.0\.0\.0 is '
                       'not a loopback address and no key is configured.*--trusted-network'):
        DeviceServer(sc, ServerConfig(host='0.0.0.0', port=0))
    for cfg, link in ((ServerConfig(host='0.0.0.0', port=0, trusted_network=True),
                       'unauthenticated (trusted network)'),
                      (ServerConfig(host='0.0.0.0', port=0, key=LinkKey(KEY)),
                       f'authenticated (BLAKE2b-128, key id {_key_id():08x})'),
                      (ServerConfig(port=0), 'unauthenticated (loopback)')):
        server = DeviceServer(sc, cfg)
        try:
            assert server.link == link
        finally:
            server.close()
    be = NetworkBackend()
    with pytest.raises(DeviceError, match=r'10\.255\.0\.1 is not a loopback address and no '
                       'key is configured.*backend_options trusted_network: true'):
        be.configure(_config({'host': '10.255.0.1'}))
    be.configure(_config({'host': '10.255.0.1', 'trusted_network': True}))
    assert be.link == 'unauthenticated (trusted network)'
    be.configure(_config({'host': '10.255.0.1', 'key_file': str(_key_file(tmp_path))}))
    assert be.hardware_id == 'network 10.255.0.1:47001 planar, authenticated link'
    assert be.values()['network_link'] == f'authenticated (BLAKE2b-128, key id {_key_id():08x})'


# -- server and client in this process, one injected clock ---------------------------------------
class FakeClock:
    def __init__(self) -> None:
        self.ns = 10**12

    def __call__(self) -> int:
        return self.ns


def _until(cond: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 10.0
    while not cond():
        assert time.monotonic() < deadline, f'timed out waiting for {what}'


class Forger:
    """Has the protocol, the client's session and seqs (seen on the wire), the device's
    session and the key id (sent in the clear), not the key. Sends from its own address."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.addr = ('127.0.0.1', port)
        self.sent = 0

    def forge(self, session: int, seq: int, device_session: int) -> list[bytes]:
        w = [19.0, -19.0, 1.9]
        plain = P.encode_command(session, seq, 1, 0, 0, ENGAGED, 10**6, w)
        own = P.encode_command(session, seq, 1, 0, 0, ENGAGED, 10**6, w, LinkKey(OTHER_KEY),
                               device_session)
        body = own[:-20] + struct.pack('<I', _key_id())                 # the right key id
        return [plain, own, body + _blake(body, OTHER_KEY)]

    def send(self, packets: list[bytes]) -> None:
        for data in packets:
            self.sock.sendto(data, self.addr)
            self.sent += 1

    def close(self) -> None:
        self.sock.close()


def _lockstep(tmp: Path, cycles: int, forger: bool) -> dict[str, Any]:
    """Client and device server in this process on one clock, one command and one state per
    cycle; with ``forger``, before each command the forger sends three forged copies of it
    (unauthenticated, another key, the right key id with another key's tag) and a genuine
    command of the previous cycle again. Returns what the device applied and the client
    read, per cycle of the engaged phase, and both sides' counters over it."""
    clock = FakeClock()
    key = LinkKey(KEY)
    server = DeviceServer(load_scenario('fig8'), ServerConfig(port=0, log_cycles=cycles + 1000,
                                                              key=key), clock_ns=clock)
    be = NetworkBackend(clock_ns=clock)
    be.configure(_config({'port': server.port, 'stale_ms': 50.0,
                          'key_file': str(_key_file(tmp))}))
    done = threading.Event()
    err: list[BaseException] = []

    def activate() -> None:
        try:
            be.activate()
        except BaseException as exc:
            err.append(exc)
        done.set()

    t = threading.Thread(target=activate)
    t.start()
    while not done.wait(0.001):
        server.cycle(0.001)
    t.join()
    assert not err, err
    evil = Forger(server.port)
    rng = np.random.default_rng(3)
    c0, s0 = be.counters(), server.counters()
    k0, base = server.log_n, be.last_sent_seq
    readings, recorded = [], b''
    try:
        for _ in range(cycles):
            clock.ns += 1_000_000
            w = rng.uniform(-1.0, 1.0, 3) * LIMIT
            expect = server.datagrams + 1
            if forger:
                packets = evil.forge(be.session, be.last_sent_seq + 1, server.session)
                if recorded:
                    packets.append(recorded)
                evil.send(packets)
                expect += len(packets)
            be.write(w)
            _until(lambda n=expect: (server._drain(clock()), server.datagrams)[1] >= n,
                   'the device to receive the cycle\'s datagrams')
            server.cycle(0.001)
            got = be.counters()['datagrams'] + 1
            _until(lambda n=got: (be._drain(), be.datagrams)[1] >= n, 'the state')
            r = be.read(0.001)
            readings.append(np.concatenate([r.pose, r.twist, r.hand_wrench, [int(r.status)]]))
            recorded = P.encode_command(be.session, be.last_sent_seq, 1, 0, 0, ENGAGED, 10**6,
                                        w, key, server.session)
    finally:
        evil.close()
        be.deactivate()
        server.close()
    c1, s1 = be.counters(), server.counters()
    seq = server.log_seq[k0:server.log_n].astype(np.int64)
    return {'seq': np.where(seq > 0, seq - base, 0), 'u': server.log_u[k0:server.log_n].copy(),
            'status': server.log_status[k0:server.log_n].copy(), 'read': np.array(readings),
            'client': {k: c1[k] - c0[k] for k in c1}, 'server': {k: s1[k] - s0[k] for k in s1},
            'forged': evil.sent}


def test_a_forger_without_the_key_moves_nothing_and_changes_no_figure(tmp_path: Path) -> None:
    clean = _lockstep(tmp_path, 300, forger=False)
    forged = _lockstep(tmp_path, 300, forger=True)
    assert np.count_nonzero(clean['seq']) > 250
    for name in ('seq', 'u', 'status', 'read'):
        np.testing.assert_array_equal(forged[name], clean[name], err_msg=name)
    assert not np.any(np.all(forged['u'] == [19.0, -19.0, 1.9], axis=1))
    n = 300
    extra = {'datagrams': 4 * n - 1, 'rejected': 3 * n, 'rejected_unauthenticated': n,
             'rejected_wrong_key': n, 'rejected_mac': n, 'duplicate': n - 1}
    assert forged['forged'] == 4 * n - 1
    assert {k: v - clean['server'][k] for k, v in forged['server'].items()
            if v != clean['server'][k]} == extra
    assert forged['client'] == clean['client']
    assert clean['server']['rejected'] == clean['client']['rejected'] == 0


def _hello_and_engage(server: DeviceServer, clock: FakeClock, key: LinkKey, n: int
                      ) -> tuple[list[bytes], bytes]:
    """A client made of the protocol functions: an idle hello (to no device session), then
    ``n`` engaged commands to the device session it learned, then a release. Returns every
    command it sent (its recording) and the first state it got (to its session)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(('127.0.0.1', 0))
    sock.settimeout(10.0)
    session, sent = P.new_session(), []
    try:
        def send(seq: int, flags: P.CommandFlags, peer: int) -> None:
            data = P.encode_command(session, seq, clock(), 0, 0, flags, 10**6,
                                    [1.0 + seq, -2.0, 0.25], key, peer)
            sent.append(data)
            sock.sendto(data, ('127.0.0.1', server.port))
            want = server.datagrams + 1
            _until(lambda: (server._drain(clock()), server.datagrams)[1] >= want, 'a command')
            server.cycle(0.001)

        send(1, P.CommandFlags.NONE, 0)
        state = sock.recv(4096)
        st = P.decode(state, 3, P.PacketType.STATE, key)
        assert isinstance(st, P.State) and st.peer_session == session
        for seq in range(2, n + 2):
            clock.ns += 1_000_000
            send(seq, ENGAGED, st.session)
        send(n + 2, P.CommandFlags.RELEASE, st.session)
    finally:
        sock.close()
    return sent, state


def test_recorded_packets_replayed_later_are_refused(tmp_path: Path) -> None:
    clock = FakeClock()
    key = LinkKey(KEY)
    cfg = ServerConfig(port=0, log_cycles=1000, key=key, takeover_after=0.001)
    server = DeviceServer(load_scenario('fig8'), cfg, clock_ns=clock)
    try:
        recording, state = _hello_and_engage(server, clock, key, 20)
        assert np.count_nonzero(server.log_seq[:server.log_n]) == 20     # applied live
        k = server.log_n
        replayer = Forger(server.port)
        clock.ns += 10**9                      # later: the client is long silent
        replayer.send(recording[:-1])          # all but the release
        _until(lambda: (server._drain(clock()), server.datagrams)[1] >= 22 + 21, 'the replay')
        for _ in range(5):
            server.cycle(0.001)
        assert server.counters()['rejected_replay'] == 21
        assert not np.any(server.log_seq[k:server.log_n])
        assert not np.any(server.log_u[k:server.log_n])
    finally:
        server.close()
    restarted = DeviceServer(load_scenario('fig8'), cfg, clock_ns=clock)
    try:
        replayer = Forger(restarted.port)
        replayer.send(recording)
        _until(lambda: (restarted._drain(clock()), restarted.datagrams)[1] >= 22, 'the replay')
        for _ in range(5):
            clock.ns += 1_000_000
            restarted.cycle(0.001)
        c = restarted.counters()
        assert c['rejected_replay'] == 21      # engaged and release: to the old device session
        assert c['commands'] == 1              # the hello, to no session: idle
        assert not np.any(restarted.log_seq[:restarted.log_n])
        assert not np.any(restarted.log_u[:restarted.log_n])
        assert not restarted.engaged
    finally:
        replayer.close()
        restarted.close()
    # a state recorded from a device to an earlier client session: refused by a new client
    dev = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    dev.bind(('127.0.0.1', 0))
    be = NetworkBackend()
    be.configure(_config({'port': dev.getsockname()[1], 'key_file': str(_key_file(tmp_path)),
                          'connect_timeout_ms': 300.0}))
    failed: list[BaseException] = []

    def activate() -> None:
        try:
            be.activate()
        except DeviceError as exc:
            failed.append(exc)

    try:
        t = threading.Thread(target=activate)
        t.start()
        _, addr = dev.recvfrom(4096)
        dev.sendto(state, addr)
        t.join(10.0)
        assert len(failed) == 1 and 'rejected by the link: replay x1' in str(failed[0])
        assert be.counters()['rejected_replay'] == 1 and be.counters()['states'] == 0
    finally:
        dev.close()


# -- the server process, the client through the lossy relay, a forger beside it ------------------
@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., ServerProcess]]:
    made: list[ServerProcess] = []

    def make(**kw: Any) -> ServerProcess:
        server = ServerProcess(tmp_path, **kw)
        made.append(server)
        return server

    yield make
    for server in made:
        server.kill()


def test_a_forger_beside_a_lossy_link_moves_nothing(tmp_path: Path,
                                                    spawn: Callable[..., ServerProcess]) -> None:
    kf = _key_file(tmp_path)
    server = spawn(extra=('--key-file', str(kf)))
    relay = Relay(('127.0.0.1', server.port))
    evil = Forger(server.port)
    be = NetworkBackend()
    be.configure(_config({'port': relay.port, 'stale_ms': 100.0, 'key_file': str(kf)}))
    sent: dict[int, np.ndarray] = {}
    rng = np.random.default_rng(5)
    pacer = DeadlinePacer(0.001)
    try:
        be.activate()
        for _ in range(1500):
            pacer.wait()
            evil.send(evil.forge(be.session, be.last_sent_seq + 1, server.session))
            w = rng.uniform(-1.0, 1.0, 3) * LIMIT
            be.write(w)
            sent[be.last_sent_seq] = w
            be.read(0.001)
    finally:
        be.deactivate()
        evil.close()
        wait_for(lambda: relay.idle, 5.0, 'the relay to flush what it held')
        res = server.stop()
        relay.stop()
    assert res.returncode == 0, res.output
    assert 'link authenticated (BLAKE2b-128' in res.output
    applied = res.seq > 0
    assert np.count_nonzero(applied) > 0
    assert set(res.session[applied].tolist()) == {be.session}
    spoiled = relay.c2s.spoiled_seqs(be.session)
    for s in np.unique(res.seq[applied]):
        assert int(s) not in spoiled
        np.testing.assert_array_equal(res.u[res.seq == s][0], sent[int(s)])
    assert not np.any(res.u[~applied])
    c = res.counters
    assert c['authenticated'] == 1 and c['client_sessions'] == 1
    assert 1 <= c['rejected_unauthenticated'] <= 1500
    assert c['rejected'] <= evil.sent + sum(relay.c2s.actions.values())
    assert be.values()['network_rejected_replay'] == '0'
