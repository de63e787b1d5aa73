"""The simulated maglev served over UDP at its own clock: the device side of the ``network``
backend (:mod:`haptic_topology.remote.protocol`), as the paper's maglev had its own
real-time controller.

:class:`DeviceServer` holds the same physics as the ``sim_maglev`` backend (a
:class:`~haptic_topology.device.backend.SimMaglevBackend` built from the scenario's device and
user blocks, starting at the VT hand pose at ``q0`` plus the device offset, as the driver
builds it) and one non-blocking UDP socket. ``haptic-topology device-server``
(:mod:`haptic_topology.remote.server_command`) runs it in a process of its own, paced by a
:class:`~haptic_topology.device.pacing.DeadlinePacer` (absolute deadlines, 1/dt of the
scenario unless ``rate_hz`` says otherwise).

Per cycle (:meth:`DeviceServer.cycle`):

1. take every datagram that arrived: a datagram that is not a valid COMMAND (size, magic,
   version, type, task dimension, CRC32, fields, NaN/inf) is counted per reason and dropped;
   a COMMAND of another client session while the followed one is alive (it sent a new
   command within ``takeover_after``) is counted ``foreign``; a duplicate, late or reordered
   one (its seq is not newer than the newest taken) is counted and dropped; the newest
   remaining command is held, with its arrival time. With a key (``ServerConfig.key``, an
   authenticated link) a datagram whose MAC does not verify is refused before it is read
   (``rejected_mac``, ``rejected_wrong_key``, ``rejected_unauthenticated``), and so is a
   command addressed to another device session or of a client session left behind
   (``rejected_replay``); a command addressed to no device session yet is taken as idle;
2. the output: the held command, clamped to the scenario's wrench limit, if it is *engaged*
   (flag ``ENGAGED``) and younger than ``command_timeout`` and than its own ``ttl_us``; else
   zero. Zero because the held command is too old is ``COMMAND_TIMEOUT`` (status bit, counted
   per cycle and per onset): when the commands stop, the output is zero ``command_timeout``
   later at the latest. A ``RELEASE`` command zeroes it at once and ends the session;
3. step the device by the measured period (clipped to 20 periods): parked at its initial pose
   (``PARKED``, no integration) until the first engaged command, as ``sim_maglev`` is;
4. send a STATE (pose, twist, hand wrench, applied wrench, status, the applied command's seq)
   to the address of the newest valid command, unless that client has been silent for
   ``forget_after``; and, with ``monitor`` set, a copy (a seq stream of its own, every cycle,
   client or not) to that address: an observer of what the device applies.

The cycle's time (the STATE's ``stamp_ns``, the log's ``t_ns``) is read after the datagrams
were taken: a command applied in a cycle arrived before that cycle's time.

So what the device applies is the clamped wrench of a valid command that was the newest when
it arrived, or zero: nothing malformed, repeated or out of order reaches it. The log
(``log_cycles`` > 0) keeps, per cycle, the time, the applied command's seq (0: none) and the
applied wrench, so a test can check each applied wrench against what the client sent.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from haptic_topology.device.backend import BackendConfig, SimMaglevBackend
from haptic_topology.device.maglev import saturate
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.errors import ConfigError, DeviceError
from haptic_topology.remote.auth import LinkKey, link_mode, require_key_off_loopback
from haptic_topology.remote.protocol import (
    DEFAULT_PORT,
    Command,
    CommandFlags,
    Malformed,
    MalformedCounts,
    PacketType,
    ProtocolError,
    Rejected,
    ServerStatus,
    SessionFollower,
    SessionVerdict,
    decode,
    encode_state,
    new_session,
)
from haptic_topology.vocabulary import DeviceStatus

if TYPE_CHECKING:
    from haptic_topology.sim.scenario import Scenario

_ENGAGED = int(CommandFlags.ENGAGED)
_RELEASE = int(CommandFlags.RELEASE)
_TIMEOUT = int(ServerStatus.COMMAND_TIMEOUT)
_PARKED = int(ServerStatus.PARKED)
_SATURATED = int(DeviceStatus.SATURATED)


@dataclass(frozen=True)
class ServerConfig:
    """``host``/``port``: the UDP address to serve on (port 0: any free one); ``rate_hz``
    (0: 1 / scenario dt); ``command_timeout`` (s): longest a command is applied after it
    arrived; ``takeover_after`` (s): silence of the followed client after which another
    session is followed; ``forget_after`` (s): silence after which no more states are sent
    to the client; ``duration`` (s, 0: until stopped); ``log_cycles``: cycles kept in the
    applied-wrench log (0: no log); ``monitor``: ``(host, port)`` that gets a copy of every
    cycle's STATE (None: none); ``key``: the link's pre-shared key (None: unauthenticated,
    only on a loopback address unless ``trusted_network``)."""

    host: str = '127.0.0.1'
    port: int = DEFAULT_PORT
    rate_hz: float = 0.0
    command_timeout: float = 0.02
    takeover_after: float = 0.5
    forget_after: float = 2.0
    duration: float = 0.0
    log_cycles: int = 0
    monitor: tuple[str, int] | None = None
    key: LinkKey | None = None
    trusted_network: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f'device-server: port must be in [0, 65535], got {self.port}')
        if not (math.isfinite(self.rate_hz) and (self.rate_hz == 0.0
                                                  or 10.0 <= self.rate_hz <= 10_000.0)):
            raise ConfigError(f'device-server: rate_hz must be 0 (1/dt) or in [10, 10000] Hz,'
                              f' got {self.rate_hz}')
        for name in ('command_timeout', 'takeover_after', 'forget_after'):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 < v <= 3600.0):
                raise ConfigError(f'device-server: {name} must be in (0, 3600] s, got {v}')
        if not (math.isfinite(self.duration) and self.duration >= 0.0):
            raise ConfigError(f'device-server: duration must be >= 0 s, got {self.duration}')
        if self.log_cycles < 0:
            raise ConfigError(f'device-server: log_cycles must be >= 0, got '
                              f'{self.log_cycles}')


class DeviceServer:
    """The simulated maglev of ``scenario`` behind a UDP socket (module doc). ``clock_ns``:
    monotonic clock (ns) for arrival times, stamps and the pacer (tests inject one)."""

    def __init__(self, scenario: Scenario, cfg: ServerConfig,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        from haptic_topology.sim.lockstep import initial_device_pose

        self.cfg = cfg
        self.scenario = scenario
        task = scenario.linkage.task
        if task.point:
            raise DeviceError(f'device-server: scenario {scenario.name} has task {task.value} '
                              f'(m = {task.dim}): the device protocol carries the rigid tasks '
                              'only (m = 3 planar, 6 spatial; its packets name m, not the task)')
        self.m = task.dim
        self.period = 1.0 / cfg.rate_hz if cfg.rate_hz else scenario.dt
        self.limit = np.asarray(scenario.device.wrench_limit, dtype=float)
        self._clock_ns = clock_ns
        self.backend = SimMaglevBackend()
        self.backend.configure(BackendConfig(scenario.device, initial_device_pose(scenario),
                                             dict(scenario.user), {}, scenario.source))
        self.backend.activate()
        try:
            infos = socket.getaddrinfo(cfg.host, cfg.port, type=socket.SOCK_DGRAM,
                                       flags=socket.AI_PASSIVE)
        except (socket.gaierror, UnicodeError) as exc:
            raise DeviceError(f'device-server: cannot resolve host {cfg.host!r} ({exc})'
                              ) from None
        family, _, _, _, sockaddr = infos[0]
        require_key_off_loopback(f'device-server: serving on {cfg.host}', str(sockaddr[0]),
                                 cfg.key, cfg.trusted_network, '--key-file PATH',
                                 '--trusted-network')
        self.key = cfg.key
        #: The link's mode in the summary: authenticated or not, and why not.
        self.link = link_mode(cfg.key, cfg.trusted_network)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind(sockaddr)
        except OSError as exc:
            sock.close()
            raise DeviceError(f'device-server: cannot bind {cfg.host}:{cfg.port}: '
                              f'{exc.strerror}') from None
        sock.setblocking(False)
        self.sock: socket.socket | None = sock
        bound = sock.getsockname()
        self.host, self.port = str(bound[0]), int(bound[1])
        self.session = new_session()
        self.follower = SessionFollower(cfg.takeover_after, remember_all=cfg.key is not None)
        self.malformed = MalformedCounts()
        self._buf = bytearray(2048)
        self._cmd: Command | None = None
        self._cmd_ns = 0
        self._client: tuple[object, ...] | None = None
        self._state_seq = 0
        self._monitor_seq = 0
        self._monitor_addr: tuple[object, ...] | None = None
        if cfg.monitor is not None:
            try:
                self._monitor_addr = socket.getaddrinfo(cfg.monitor[0], cfg.monitor[1], family,
                                                        socket.SOCK_DGRAM)[0][4]
            except (socket.gaierror, UnicodeError) as exc:
                sock.close()
                raise DeviceError(f'device-server: cannot resolve the monitor address '
                                  f'{cfg.monitor[0]!r} ({exc})') from None
        self.engaged = False
        self._timed_out = False
        self._t0_ns: int | None = None
        self.pacer = DeadlinePacer(self.period, clock=lambda: self._clock_ns() * 1e-9)
        # counters
        self.cycles = 0
        self.datagrams = 0
        self.commands = 0          # valid new commands taken
        self.applied_cycles = 0    # cycles that applied a command
        self.clamped_cycles = 0
        self.command_timeouts = 0  # onsets
        self.timeout_cycles = 0
        self.releases = 0
        self.states_sent = 0
        self.send_errors = 0
        self.encode_errors = 0
        self.last_error = ''
        n = cfg.log_cycles
        self.log_t = np.zeros(n, dtype=np.int64)
        self.log_seq = np.zeros(n, dtype=np.uint64)
        self.log_session = np.zeros(n, dtype=np.uint32)
        self.log_u = np.zeros((n, self.m))
        self.log_status = np.zeros(n, dtype=np.uint32)
        self.log_n = 0

    # -- one cycle ---------------------------------------------------------------------------
    def cycle(self, dt: float) -> None:
        """One device cycle ``dt`` s after the previous one (module doc)."""
        self._drain(self._clock_ns())
        now_ns = self._clock_ns()        # after the drain: what it took arrived before
        if self._t0_ns is None:
            self._t0_ns = now_ns
        cmd = self._cmd
        u = np.zeros(self.m)
        applied_seq = 0
        status = 0
        timed_out = False
        if cmd is not None:
            valid_ns = min(round(self.cfg.command_timeout * 1e9), cmd.ttl_us * 1000)
            if now_ns - self._cmd_ns <= valid_ns:
                if cmd.flags & _ENGAGED:
                    u, clamped = saturate(cmd.wrench, self.limit)
                    applied_seq = cmd.seq
                    self.engaged = True
                    self.applied_cycles += 1
                    if clamped:
                        status |= _SATURATED
                        self.clamped_cycles += 1
            else:
                timed_out = True
        if timed_out:
            status |= _TIMEOUT
            self.timeout_cycles += 1
            if not self._timed_out:
                self.command_timeouts += 1
        self._timed_out = timed_out
        if self.engaged:
            self.backend.write(u)
            reading = self.backend.read(dt)
        else:
            reading = self.backend.idle(dt)
            status |= _PARKED
        status |= int(reading.status)
        self.cycles += 1
        if self.log_n < self.log_t.size:
            k = self.log_n
            self.log_t[k] = now_ns
            self.log_seq[k] = applied_seq
            self.log_session[k] = self.follower.session if applied_seq else 0
            self.log_u[k] = u
            self.log_status[k] = status
            self.log_n += 1
        if self.sock is None:
            return
        echo_seq, echo_stamp = (cmd.seq, cmd.stamp_ns) if cmd is not None else (0, 0)
        values = (status, applied_seq, reading.pose, reading.twist, reading.hand_wrench, u)
        client = self._client
        if client is not None and now_ns * 1e-9 - self.follower.heard <= self.cfg.forget_after:
            self._state_seq += 1
            if self._send(client, self._state_seq, now_ns, echo_seq, echo_stamp, values,
                          self.follower.session):
                self.states_sent += 1
        if self._monitor_addr is not None:
            self._monitor_seq += 1
            self._send(self._monitor_addr, self._monitor_seq, now_ns, echo_seq, echo_stamp,
                       values, 0)

    def _send(self, addr: tuple[object, ...], seq: int, now_ns: int, echo_seq: int,
              echo_stamp: int, values: tuple[int, int, np.ndarray, np.ndarray, np.ndarray,
                                             np.ndarray], peer: int) -> bool:
        assert self.sock is not None
        try:
            data = encode_state(self.session, seq, now_ns, echo_seq, echo_stamp, *values,
                                key=self.key, peer_session=peer)
        except ProtocolError as err:     # a non-finite state is never sent: the client goes
            self.encode_errors += 1      # stale and its driver writes zero
            self.last_error = str(err)
            return False
        try:
            self.sock.sendto(data, addr)
        except OSError as exc:
            self.send_errors += 1
            self.last_error = exc.strerror or type(exc).__name__
            return False
        return True

    def _drain(self, now_ns: int) -> None:
        sock = self.sock
        if sock is None:
            return
        buf = self._buf
        view = memoryview(buf)
        now = now_ns * 1e-9
        follower = self.follower
        while True:
            try:
                n, addr = sock.recvfrom_into(buf)
            except BlockingIOError:
                return
            except InterruptedError:
                continue
            except OSError as exc:
                self.last_error = exc.strerror or type(exc).__name__
                return
            self.datagrams += 1
            try:
                got = decode(view[:n], self.m, PacketType.COMMAND, self.key)
            except ProtocolError as err:
                self.malformed.add(err)
                continue
            assert isinstance(got, Command)
            cmd = got if self.key is None else self._addressed(got)
            if cmd is None:
                continue
            verdict = follower.take(cmd.session, cmd.seq, now)
            if verdict is None:
                continue
            if verdict is SessionVerdict.NEW:
                self._cmd = None          # nothing of the previous client applies
            self._client = addr
            if cmd.flags & _RELEASE:
                self.releases += 1
                follower.end()
                self._cmd = None
                self._client = None
                continue
            self._cmd = cmd
            self._cmd_ns = now_ns
            self.commands += 1

    def _addressed(self, cmd: Command) -> Command | None:
        """An authenticated command, refused as a replay when addressed to another session of
        this device or of a client session left behind (not a copy of its release), and
        made idle when addressed to no session yet (module doc of the protocol)."""
        if cmd.peer_session not in (0, self.session):
            self.malformed.reject(Rejected.REPLAY, f'a command addressed to device session '
                                  f'{cmd.peer_session:08x}, this is {self.session:08x}: '
                                  'recorded before this device started')
            return None
        if cmd.session in self.follower.retired and not cmd.flags & _RELEASE:
            self.malformed.reject(Rejected.REPLAY, f'a command of client session '
                                  f'{cmd.session:08x}, which this device has left behind')
            return None
        if cmd.peer_session == 0 and cmd.flags & _ENGAGED:
            return replace(cmd, flags=cmd.flags & ~CommandFlags.ENGAGED)
        return cmd

    # -- running -----------------------------------------------------------------------------
    def serve(self, stop: Callable[[], bool]) -> None:
        """Run cycles at absolute deadlines until ``stop()`` or ``duration``."""
        end = math.inf if not self.cfg.duration else self.cfg.duration
        self.pacer.start()
        t0 = self.pacer.t0
        assert t0 is not None
        limit = 20.0 * self.period
        while not stop():
            tick = self.pacer.wait()
            if tick.now - t0 >= end:
                break
            self.cycle(min(max(tick.dt, 0.0), limit))

    def close(self) -> None:
        """Zero output (the device stops being driven) and close the socket."""
        self.backend.deactivate()
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    # -- figures -----------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Every count (module doc)."""
        f = self.follower.totals()
        out = {'cycles': self.cycles, 'missed_deadlines': self.pacer.missed,
               'datagrams': self.datagrams, 'commands': self.commands,
               'applied_cycles': self.applied_cycles, 'clamped_cycles': self.clamped_cycles,
               'duplicate': f['duplicate'], 'late': f['late'], 'too_old': f['too_old'],
               'lost': f['lost'], 'foreign': f['foreign'], 'ended_session': f['ended_session'],
               'malformed': self.malformed.total, 'client_sessions': self.follower.sessions,
               'releases': self.releases, 'command_timeouts': self.command_timeouts,
               'timeout_cycles': self.timeout_cycles, 'states_sent': self.states_sent,
               'send_errors': self.send_errors, 'encode_errors': self.encode_errors,
               'authenticated': int(self.key is not None),
               'rejected': self.malformed.rejected}
        out.update(self.malformed.values())
        return out

    def summary_line(self) -> str:
        """The counters in one line (printed at shutdown)."""
        c = self.counters()
        bad = ', '.join(f'{r.value} {n}' for r, n in self.malformed.counts.items()
                        if n and isinstance(r, Malformed))
        rej = ', '.join(f'{r.value} {n}' for r, n in self.malformed.counts.items()
                        if n and isinstance(r, Rejected))
        return (f'device-server {self.host}:{self.port}: {c["cycles"]} cycles '
                f'({c["missed_deadlines"]} missed deadlines); {c["commands"]} commands, applied '
                f'in {c["applied_cycles"]} cycles ({c["clamped_cycles"]} clamped); refused '
                f'{c["malformed"]} malformed{f" ({bad})" if bad else ""}, '
                f'{c["rejected"]} by the link{f" ({rej})" if rej else ""}, '
                f'{c["duplicate"]} duplicate, {c["late"]} late, {c["too_old"]} too old, '
                f'{c["foreign"]} foreign; {c["lost"]} lost; {c["command_timeouts"]} command '
                f'timeouts ({c["timeout_cycles"]} cycles at zero); {c["client_sessions"]} '
                f'client sessions, {c["releases"]} releases; {c["states_sent"]} states sent; '
                f'link {self.link}')

    def write_log(self, path: Path) -> None:
        """The applied-wrench log as CSV: ``t_ns`` (the cycle's monotonic time, ns: the
        system's ``CLOCK_MONOTONIC``, comparable with other processes' on this host),
        ``applied_session`` and ``applied_seq`` of the command applied (0: none), ``u0 ..
        u{m-1}`` (N, N m, repr of the float64: exact), ``status``."""
        n = self.log_n
        head = ','.join(['t_ns', 'applied_session', 'applied_seq',
                         *(f'u{i}' for i in range(self.m)), 'status'])
        lines = [head]
        for k in range(n):
            lines.append(','.join([str(int(self.log_t[k])), str(int(self.log_session[k])),
                                   str(int(self.log_seq[k])),
                                   *(repr(float(v)) for v in self.log_u[k]),
                                   str(int(self.log_status[k]))]))
        path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
