"""The ``network`` device backend: a device controller on another computer, over UDP.

(One module of ~510 lines on purpose: the options, the lifecycle, the per-cycle path and the
counters of the client side share its state and are read together.)

:class:`NetworkBackend` is the client side of :mod:`haptic_topology.remote.protocol`, inside
``device_driver``: each :meth:`~NetworkBackend.write` sends one COMMAND datagram, each
:meth:`~NetworkBackend.read` takes the STATE datagrams that have arrived, without blocking,
and returns the newest valid one. The device (``haptic-topology device-server``, the
simulated maglev, or a real device's controller speaking the protocol) runs at its own clock:
a read returns the newest state the device sent, not one computed for ``dt``; ``dt`` is not
used. Wall clock only: a lock-step run needs a device that waits for the driver, which a
device on its own clock does not.

**Per cycle** (the driver's 1 kHz deadline path): ``write`` is one ``struct`` pack, one CRC32
(with a key: one keyed BLAKE2b) and one non-blocking ``sendto``; ``read`` drains the socket
with non-blocking ``recvfrom_into`` until it is empty (``wait_ms`` > 0: then waits at most
that long for the state that answers the command just written). Nothing else blocks.

**Never a bad value on.** A datagram that is not a valid STATE of the device's session
(:func:`~haptic_topology.remote.protocol.decode`: size, magic, version, type, task dimension,
CRC32, fields, NaN/inf), that comes from another address, or whose ``seq`` is not newer than
the newest taken (duplicate, late, reordered) is counted and dropped. A non-finite wrench
given to ``write`` is sent as 0 on that axis and counted (the driver clamps before, so this
does not happen through it).

**Faults** (the driver's fault machinery, :mod:`haptic_topology.device.backend`): a read
carries ``DeviceStatus.FAULT``, and the driver writes zero
from the next cycle until a read comes without it and then fades back in, while

* no valid STATE arrived within ``stale_ms`` (server stopped, network down, all lost): the
  reading repeats the newest valid state's values;
* the device reports ``COMMAND_TIMEOUT`` (it had no valid command within its timeout, so it
  output zero: the commands are lost on the way) or ``FAULT``.

:meth:`~NetworkBackend.fault_reason` says which. A restarted device server draws a new session
id: once the old session has been silent for ``stale_ms`` the new one is followed
(``server_sessions``), so the driver recovers by itself; a new session while the followed one
is alive is refused (``foreign_session``).

**Lifecycle.** ``configure`` checks the options and resolves the address; ``activate`` opens
the socket and sends idle commands (zero wrench, not engaged) until the first valid STATE
arrives, for at most ``connect_timeout_ms``, else it fails with a
:class:`~haptic_topology.errors.DeviceError` that says what was received; ``deactivate`` sends
a RELEASE command (the device zeroes its output at once and ends the session; the device's
command timeout does it anyway when the release is lost) and closes the socket. Each
activation is a new client session.

Options (``backend_options``; every one optional):

* ``host`` (``127.0.0.1``): address of the device (name or numeric, IPv4 or IPv6);
* ``port`` (47001): its UDP port;
* ``local_host`` (any: ``0.0.0.0`` / ``::``), ``local_port`` (0: any free one): the local
  address to bind;
* ``stale_ms`` (10, > 0): a newest valid state older than this is stale: FAULT;
* ``command_ttl_ms`` (20, >= 0.001): validity of each command at the device after it arrived;
* ``connect_timeout_ms`` (2000): how long ``activate`` waits for the first state;
* ``wait_ms`` (0, in [0, 1]): how long ``read`` may wait for the state answering the command
  just written (0: never waits);
* ``key_file`` (none): the link's pre-shared key (:mod:`haptic_topology.remote.auth`, the same
  key as the device server's ``--key-file``): every packet carries a MAC, and whatever fails
  it, is addressed to another client session or comes from a device session left behind is
  counted (``rejected_mac``, ``rejected_wrong_key``, ``rejected_unauthenticated``,
  ``rejected_replay``) and dropped. Each command is addressed to the device session of the
  newest state while that is not stale, else to none (the device then takes it as idle);
* ``trusted_network`` (false): allow a ``host`` other than loopback without ``key_file``.
  Without either, such a ``host`` is refused.

The diagnostics value ``network_link`` and ``hardware_id`` say which mode the link runs in.

Bad options are refused with a :class:`~haptic_topology.errors.DeviceError` naming the
option and what is expected (``network: backend_options.port: expected an integer port in
[1, 65535], got 0``).
"""

from __future__ import annotations

import math
import select
import socket
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceBackend, DeviceReading
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.remote.auth import LinkKey, link_mode, load_key, require_key_off_loopback
from haptic_topology.remote.protocol import (
    DEFAULT_PORT,
    CommandFlags,
    Malformed,
    MalformedCounts,
    PacketType,
    ProtocolError,
    Rejected,
    ServerStatus,
    SessionFollower,
    SessionVerdict,
    State,
    decode,
    encode_command,
    new_session,
)
from haptic_topology.vocabulary import DeviceStatus

#: Options and their defaults (module doc).
DEFAULTS: dict[str, Any] = {
    'host': '127.0.0.1', 'port': DEFAULT_PORT, 'local_host': '', 'local_port': 0,
    'stale_ms': 10.0, 'command_ttl_ms': 20.0, 'connect_timeout_ms': 2000.0, 'wait_ms': 0.0,
    'key_file': '', 'trusted_network': False,
}
_FAULT = int(DeviceStatus.FAULT)
_PASS_BITS = int(DeviceStatus.WORKSPACE_LIMIT | DeviceStatus.SATURATED)
_TIMEOUT_BIT = int(ServerStatus.COMMAND_TIMEOUT)
#: Round-trip samples kept for the percentiles.
RTT_KEEP = 10_000
#: RELEASE copies sent by ``deactivate`` (one datagram may be lost; copies are duplicates).
_RELEASE_COPIES = 3


def _option_error(key: str, expected: str, value: Any) -> DeviceError:
    return DeviceError(f'network: backend_options.{key}: expected {expected}, got {value!r}')


def _number(options: Mapping[str, Any], key: str, lo: float, hi: float,
            lo_open: bool = False) -> float:
    value = options.get(key, DEFAULTS[key])
    bound = f'({lo:g}, {hi:g}]' if lo_open else f'[{lo:g}, {hi:g}]'
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _option_error(key, f'a number in {bound}', value)
    v = float(value)
    if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
        raise _option_error(key, f'a number in {bound}', value)
    return v


def _port(options: Mapping[str, Any], key: str, lo: int) -> int:
    value = options.get(key, DEFAULTS[key])
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= 65535:
        raise _option_error(key, f'an integer port in [{lo}, 65535]', value)
    return value


def _text(options: Mapping[str, Any], key: str) -> str:
    value = options.get(key, DEFAULTS[key])
    if not isinstance(value, str):
        raise _option_error(key, 'an address (text)', value)
    return value


class NetworkBackend(DeviceBackend):
    """A device served over UDP (module doc). ``clock_ns``: monotonic clock (ns) for the
    staleness, the packet stamps and the round trip (tests inject one)."""

    name = 'network'
    lockstep = False          # the device server runs on its own clock

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock_ns = clock_ns
        self._m = 0
        self._sock: socket.socket | None = None
        self._buf = bytearray(2048)
        self._state: State | None = None
        self._state_ns = 0
        self._session = 0
        self._seq = 0
        self._reason = ''
        self._faulted = False
        self._stale = False
        self.peer = ''
        self.server_session = 0
        self.key: LinkKey | None = None
        self.link = ''
        self._follower = SessionFollower(1.0)
        self.malformed = MalformedCounts()
        self._rtt = np.zeros(RTT_KEEP)
        self._rtt_n = 0
        self._rtt_seq = 0
        # counters (module doc); read by any thread as they are
        self.datagrams = 0
        self.foreign_source = 0
        self.commands_sent = 0
        self.send_errors = 0
        self.recv_errors = 0
        self.nonfinite_writes = 0
        self.stale_cycles = 0
        self.stale_onsets = 0
        self.timeout_cycles = 0
        self.fault_reads = 0
        self.last_send_error = ''

    # -- configuration -----------------------------------------------------------------------
    def configure(self, config: BackendConfig) -> None:
        opts = config.options
        unknown = sorted(set(opts) - set(DEFAULTS))
        if unknown:
            raise DeviceError(f'network: backend_options: unknown option {unknown[0]!r} '
                              f'(expected some of: {", ".join(sorted(DEFAULTS))})')
        self.host = _text(opts, 'host')
        self.port = _port(opts, 'port', 1)
        self.local_host = _text(opts, 'local_host')
        self.local_port = _port(opts, 'local_port', 0)
        self.stale_ns = round(1e6 * _number(opts, 'stale_ms', 0.0, 10_000.0, lo_open=True))
        ttl_ms = _number(opts, 'command_ttl_ms', 0.001, 4_294_967.0)
        self.ttl_us = max(1, round(1e3 * ttl_ms))
        self.connect_timeout = 1e-3 * _number(opts, 'connect_timeout_ms', 1.0, 600_000.0)
        self.wait = 1e-3 * _number(opts, 'wait_ms', 0.0, 1.0)
        key_file = _text(opts, 'key_file')
        trusted = opts.get('trusted_network', False)
        if not isinstance(trusted, bool):
            raise _option_error('trusted_network', 'true or false', trusted)
        try:
            self.key = load_key(key_file) if key_file else None
        except ConfigError as exc:
            raise DeviceError(f'network: backend_options.key_file: {exc}') from None
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise DeviceError(f'network: backend_options.host: cannot resolve {self.host!r} '
                              f'({exc})') from None
        family, _, _, _, sockaddr = infos[0]
        self._family = family
        self._addr = sockaddr
        ip, port = str(sockaddr[0]), int(sockaddr[1])
        self._peer = (ip, port)
        self.peer = f'[{ip}]:{port}' if family == socket.AF_INET6 else f'{ip}:{port}'
        try:
            require_key_off_loopback(f'network: backend_options.host {self.host}', ip, self.key,
                                     trusted, 'backend_options key_file',
                                     'backend_options trusted_network: true')
        except ConfigError as exc:
            raise DeviceError(str(exc)) from None
        self.link = link_mode(self.key, trusted)
        task = config.params.task
        if task.point:
            raise DeviceError(f'network: scenario task {task.value} (m = {task.dim}): the '
                              'device protocol carries the rigid tasks only (m = 3 planar, 6 '
                              'spatial; its packets name m, not the task, so a device serving '
                              'another task of the same m could not be told apart)')
        self._m = self.keep_task(config).dim
        self._initial_pose = np.array(config.initial_pose, dtype=float)
        self._zero = np.zeros(self._m)
        self._follower = SessionFollower(self.stale_ns * 1e-9, remember_all=self.key is not None)
        self._state = None

    @property
    def hardware_id(self) -> str:
        if not self._m:
            return self.name
        dev = self._task.value if self._task is not None else f'{self._m}-dof'
        sess = f', server session {self.server_session:08x}' if self.server_session else ''
        auth = 'authenticated' if self.key is not None else 'unauthenticated'
        return f'{self.name} {self.peer} {dev}, {auth} link{sess}'

    def fault_reason(self) -> str:
        return self._reason or f'{self.name}: the device reports a fault'

    # -- lifecycle ---------------------------------------------------------------------------
    def preflight(self, config: BackendConfig) -> None:
        """The connection check of :meth:`activate` (idle commands, never engaged, until the
        first valid STATE or ``connect_timeout_ms``), then the release of :meth:`deactivate`:
        the server ends this session at once and follows the run's next one."""
        self.configure(config)
        try:
            self.activate()
        finally:
            self.deactivate()
            self.cleanup()

    def activate(self) -> None:
        m = self.task_dim()
        if self._sock is not None:
            return
        sock = socket.socket(self._family, socket.SOCK_DGRAM)
        local = self.local_host or ('::' if self._family == socket.AF_INET6 else '0.0.0.0')
        try:
            sock.bind((local, self.local_port))
        except OSError as exc:
            sock.close()
            raise DeviceError(f'network: cannot bind the local address {local}:'
                              f'{self.local_port} (backend_options local_host/local_port): '
                              f'{exc.strerror}') from None
        sock.setblocking(False)
        self._sock = sock
        self._session = new_session()
        self._seq = 0
        self._state = None
        self._faulted = self._stale = False
        start = time.monotonic()
        while self._state is None:
            self._send(self._zero, CommandFlags.NONE)
            select.select([sock], [], [], 0.002)
            self._drain()
            if self._state is None and time.monotonic() - start >= self.connect_timeout:
                self._close()
                raise DeviceError(self._no_state_message(m))

    def _no_state_message(self, m: int) -> str:
        got = f'{self.datagrams} datagrams'
        if self.malformed.total:
            got += ', refused: ' + '; '.join(
                f'{r.value} x{n} ({self.malformed.last[r]})'
                for r, n in self.malformed.counts.items() if n and isinstance(r, Malformed))
        if self.malformed.rejected:
            got += ', rejected by the link: ' + '; '.join(
                f'{r.value} x{n} ({self.malformed.last[r]})'
                for r, n in self.malformed.counts.items() if n and isinstance(r, Rejected))
        if self.foreign_source:
            got += f', {self.foreign_source} from other addresses'
        if self.send_errors:
            got += f', {self.send_errors} send errors ({self.last_send_error})'
        hint = ('is `haptic-topology device-server` running there with a scenario of the same '
                f'task dimension (m = {m}), and reachable?')
        if self.malformed.counts[Malformed.DIM]:
            hint = (f'the device serves another task dimension than this scenario\'s m = {m} '
                    '(planar 3, spatial 6)')
        return (f'network: no valid STATE from {self.peer} within '
                f'{1e3 * self.connect_timeout:g} ms (connect_timeout_ms); received {got}: '
                f'{hint}')

    def deactivate(self) -> None:
        if self._sock is None:
            return
        if self._m:
            self._seq += 1
            data = self._command(self._zero, CommandFlags.RELEASE)
            for _ in range(_RELEASE_COPIES):
                self._sendto(data)
        self._close()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # -- cycle -------------------------------------------------------------------------------
    def write(self, wrench: np.ndarray) -> None:
        if self._sock is None:
            raise DeviceError('network: write() before activate()')
        w = np.asarray(wrench, dtype=float)
        if w.shape != (self._m,):
            raise DeviceError(f'network: write(): expected {self._m} wrench values, got '
                              f'shape {w.shape}')
        if not np.all(np.isfinite(w)):
            self.nonfinite_writes += 1
            w = np.where(np.isfinite(w), w, 0.0)
        self._send(w, CommandFlags.ENGAGED)

    def idle(self, dt: float) -> DeviceReading:
        if self._sock is None:
            raise DeviceError('network: idle() before activate()')
        self._send(self._zero, CommandFlags.NONE)
        return self.read(dt)

    def read(self, dt: float) -> DeviceReading:
        del dt  # the device runs at its own clock (module doc)
        sock = self._sock
        if sock is None:
            raise DeviceError('network: read() before activate()')
        self._drain()
        if self.wait > 0.0:
            deadline = time.monotonic() + self.wait
            while self._state is None or self._state.echo_seq < self._seq:
                left = deadline - time.monotonic()
                if left <= 0.0 or not select.select([sock], [], [], left)[0]:
                    break
                self._drain()
        return self._reading(self._clock_ns())

    def _reading(self, now_ns: int) -> DeviceReading:
        st = self._state
        if st is None:       # only between activate's failure paths; never returned active
            self._reason = f'network: no STATE from {self.peer} yet'
            return DeviceReading(self._initial_pose.copy(), self._zero.copy(),
                                 self._zero.copy(), DeviceStatus.FAULT)
        age = now_ns - self._state_ns
        status = st.status
        stale = age > self.stale_ns
        if stale:
            self.stale_cycles += 1
            if not self._stale:
                self.stale_onsets += 1
            self._reason = (f'network: no valid STATE from {self.peer} for {age * 1e-6:.1f} ms '
                            f'(stale_ms {self.stale_ns * 1e-6:g}): device server stopped, '
                            'network down, or states lost')
        elif status & _TIMEOUT_BIT:
            self.timeout_cycles += 1
            self._reason = (f'network: the device at {self.peer} had no valid command within '
                            'its command timeout and outputs zero (commands lost or late on '
                            'the way)')
        elif status & _FAULT:
            self._reason = f'network: the device at {self.peer} reports a fault'
        self._stale = stale
        fault = stale or bool(status & (_TIMEOUT_BIT | _FAULT))
        if fault:
            self.fault_reads += 1
        self._faulted = fault
        bits = (status & _PASS_BITS) | (_FAULT if fault else 0)
        return DeviceReading(st.pose, st.twist, st.hand_wrench, DeviceStatus(bits))

    # -- datagrams ---------------------------------------------------------------------------
    def _command(self, wrench: np.ndarray, flags: CommandFlags) -> bytes:
        st = self._state
        echo_seq, echo_stamp = (st.seq, st.stamp_ns) if st is not None else (0, 0)
        now_ns = self._clock_ns()
        if self.key is None:
            return encode_command(self._session, self._seq, now_ns, echo_seq, echo_stamp,
                                  flags, self.ttl_us, wrench.tolist())
        # addressed to the device session of a fresh state only (module doc)
        peer = st.session if st is not None and now_ns - self._state_ns <= self.stale_ns else 0
        return encode_command(self._session, self._seq, now_ns, echo_seq, echo_stamp, flags,
                              self.ttl_us, wrench.tolist(), self.key, peer)

    def _send(self, wrench: np.ndarray, flags: CommandFlags) -> None:
        self._seq += 1
        self._sendto(self._command(wrench, flags))
        self.commands_sent += 1

    def _sendto(self, data: bytes) -> None:
        assert self._sock is not None
        try:
            self._sock.sendto(data, self._addr)
        except OSError as exc:    # full buffer, network unreachable, ...: the state goes stale
            self.send_errors += 1
            self.last_send_error = exc.strerror or type(exc).__name__

    @property
    def last_sent_seq(self) -> int:
        """``seq`` of the newest command sent in this session (0: none)."""
        return self._seq

    @property
    def session(self) -> int:
        """This activation's client session id (0 before the first)."""
        return self._session

    def _drain(self) -> None:
        sock = self._sock
        assert sock is not None
        buf = self._buf
        view = memoryview(buf)
        while True:
            try:
                n, addr = sock.recvfrom_into(buf)
            except BlockingIOError:
                return
            except InterruptedError:
                continue
            except OSError:
                self.recv_errors += 1
                return
            self.datagrams += 1
            if (addr[0], addr[1]) != self._peer:
                self.foreign_source += 1
                continue
            try:
                st = decode(view[:n], self._m, PacketType.STATE, self.key)
            except ProtocolError as err:
                self.malformed.add(err)
                continue
            assert isinstance(st, State)
            if self.key is not None and (st.peer_session != self._session
                                         or st.session in self._follower.retired):
                self.malformed.reject(Rejected.REPLAY, f'a state of device session '
                                      f'{st.session:08x} to client session '
                                      f'{st.peer_session:08x}, this is {self._session:08x}')
                continue
            now_ns = self._clock_ns()
            now = now_ns * 1e-9
            verdict = self._follower.take(st.session, st.seq, now)
            if verdict is None:
                continue
            if verdict is SessionVerdict.NEW:
                self.server_session = st.session
                self._rtt_seq = 0
            self._state = st
            self._state_ns = now_ns
            if st.echo_stamp_ns and st.echo_seq > self._rtt_seq:
                self._rtt_seq = st.echo_seq
                self._rtt[self._rtt_n % RTT_KEEP] = (now_ns - st.echo_stamp_ns) * 1e-9
                self._rtt_n += 1

    # -- figures -----------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Counts so far (states refused per reason; see module doc)."""
        f = self._follower.totals()
        out = {'datagrams': self.datagrams, 'states': f['new'], 'duplicate': f['duplicate'],
               'late': f['late'], 'too_old': f['too_old'], 'lost': f['lost'],
               'foreign_session': f['foreign'], 'foreign_source': self.foreign_source,
               'server_sessions': self._follower.sessions,
               'malformed': self.malformed.total, 'rejected': self.malformed.rejected,
               'commands_sent': self.commands_sent,
               'send_errors': self.send_errors, 'recv_errors': self.recv_errors,
               'nonfinite_writes': self.nonfinite_writes, 'stale_cycles': self.stale_cycles,
               'stale_onsets': self.stale_onsets, 'timeout_cycles': self.timeout_cycles,
               'fault_reads': self.fault_reads}
        out.update(self.malformed.values())
        return out

    def round_trip(self) -> dict[str, float]:
        """Command -> state round trip (s): p50, p99, max over the last samples (NaN: none)."""
        n = min(self._rtt_n, RTT_KEEP)
        if not n:
            return {'p50': math.nan, 'p99': math.nan, 'max': math.nan}
        r = self._rtt[:n]
        p50, p99 = np.percentile(r, [50, 99])
        return {'p50': float(p50), 'p99': float(p99), 'max': float(r.max())}

    def values(self) -> dict[str, str]:
        """Counters and round trip as diagnostics key/values."""
        out = {f'network_{k}': str(v) for k, v in self.counters().items()}
        out['network_link'] = self.link
        rtt = self.round_trip()
        out.update({f'network_round_trip_{k}_ms': f'{1e3 * v:.3f}' for k, v in rtt.items()})
        return out
