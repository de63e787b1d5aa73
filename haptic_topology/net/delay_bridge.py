"""``python -m haptic_topology.net.delay_bridge --a IF --b IF --delay-ms D``: a delaying L2 bridge.

Every Ethernet frame that arrives on interface ``a`` leaves on ``b`` (and the other way)
``d * (1 + u)`` seconds later, ``u`` uniform in ``[-jitter, +jitter]`` and drawn per frame,
or is dropped with probability ``loss`` (a seeded :class:`random.Random`): what the kernel's
``netem`` qdisc does with ``delay D J loss L`` (uniform jitter; with jitter frames may
overtake each other, as they do under netem). It is for kernels without netem (these
machines: ``tc qdisc add ... netem`` fails with "Specified qdisc kind is unknown"):
``scripts/two_hosts.sh`` runs it in the middle one of three network namespaces, between the
veth ends that lead to the other two. Being layer 2, it passes ARP and the multicast of DDS
discovery unchanged; it needs no IP address and makes no routing decision.

How it works:

* one ``AF_PACKET``/``SOCK_RAW`` socket per interface, bound to it for every protocol; what
  a socket sees leaving its interface (``PACKET_OUTGOING``: the bridge's own sends) is
  skipped;
* ``PACKET_VNET_HDR``: each frame is read with its ``virtio_net_hdr`` and sent with it. A
  veth offers checksum offload, so a UDP datagram sent into one usually still has an
  incomplete checksum (``CHECKSUM_PARTIAL``); read from a packet socket and sent out as plain
  bytes, the receiver would drop it as corrupt. The header tells the kernel to complete it;
* arrival time: the kernel's receive stamp (``SO_TIMESTAMPNS``), so a frame's delay counts
  from when it reached the bridge's interface, including any time the bridge waited for a
  CPU;
* one thread: ``select`` on both sockets with the next due time as its timeout, and a heap of
  pending frames ordered by due time.

Counters (``--stats FILE``, JSON: written once the sockets are bound, every second, and at
exit; also printed as one JSON line at exit): per direction the frames received, forwarded,
dropped, overtaken (sent after a frame that arrived later), send errors and still pending
at exit; at exit also the delay drawn and the delay achieved (send time minus kernel
arrival), each mean/min/p50/p99/max in ms; the achieved one exceeds the drawn one by the
bridge's own scheduling latency.

``--rt-priority N`` runs the bridge under SCHED_FIFO: on a busy 2-core machine its own
scheduling latency otherwise shows in the delay's tail (the graph beside it takes over a core).

Needs CAP_NET_RAW (root). Stops on SIGINT/SIGTERM; frames still pending then are not sent
(counted as ``pending``).
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import os
import random
import select
import signal
import socket
import struct
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from haptic_topology.errors import ConfigError, HapticTopologyError, LinkError

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
PACKET_OUTGOING = 4
SO_TIMESTAMPNS = 35       # = SCM_TIMESTAMPNS on Linux
SO_RCVBUFFORCE = 33
#: ``struct virtio_net_hdr``: flags, gso_type (u8), hdr_len, gso_size, csum_start,
#: csum_offset (u16).
VNET_HDR_LEN = 10
VNET_HDR_F_DATA_VALID = 2
#: Largest frame read (a veth's 1500-byte MTU leaves a wide margin; GSO frames are bigger).
MAX_FRAME = 65536 + VNET_HDR_LEN
RECEIVE_BUFFER = 4 * 1024 * 1024
#: Frames taken from one socket before the other gets its turn (and due frames are sent).
BURST = 64
STATS_EVERY = 1.0         # s
DIRECTIONS = ('a_to_b', 'b_to_a')


@dataclass(frozen=True)
class LinkSettings:
    """The link one direction of the bridge emulates.

    ``delay``: mean one-way delay (s); ``jitter``: half-width of the uniform spread as a
    fraction of ``delay`` (0.2: each frame's delay is in ``[0.8 d, 1.2 d]``); ``loss``:
    probability that a frame is dropped; ``seed``: of the random draws.
    """

    delay: float
    jitter: float = 0.2
    loss: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.delay) and 0.0 <= self.delay <= 10.0):
            raise ConfigError(f'delay must be in [0, 10] s, got {self.delay}')
        if not (math.isfinite(self.jitter) and 0.0 <= self.jitter < 1.0):
            raise ConfigError(f'jitter must be a fraction in [0, 1), got {self.jitter}')
        if not (math.isfinite(self.loss) and 0.0 <= self.loss < 1.0):
            raise ConfigError(f'loss must be a probability in [0, 1), got {self.loss}')


class DelayLine:
    """Draws each frame's fate: dropped (None) or its delay (s).

    >>> line = DelayLine(LinkSettings(delay=0.020, jitter=0.2, loss=0.0, seed=1))
    >>> all(0.016 <= line.draw() <= 0.024 for _ in range(1000))
    True
    """

    def __init__(self, settings: LinkSettings) -> None:
        self.settings = settings
        self._rng = random.Random(settings.seed)

    def draw(self) -> float | None:
        s = self.settings
        if s.loss > 0.0 and self._rng.random() < s.loss:
            return None
        if s.jitter == 0.0 or s.delay == 0.0:
            return s.delay
        return s.delay * (1.0 + self._rng.uniform(-s.jitter, s.jitter))


def figures(values: Sequence[float], scale: float = 1e3) -> dict[str, float | None]:
    """``mean``/``min``/``p50``/``p99``/``max`` of ``values`` times ``scale`` (None each when
    empty), rounded to 4 decimals.

    >>> figures([0.001, 0.002, 0.003])['p50']
    2.0
    """
    if not values:
        return dict.fromkeys(('mean', 'min', 'p50', 'p99', 'max'))
    v = sorted(values)

    def q(p: float) -> float:
        return v[min(len(v) - 1, max(0, math.ceil(p * len(v)) - 1))]

    return {k: round(x * scale, 4) for k, x in (
        ('mean', math.fsum(v) / len(v)), ('min', v[0]), ('p50', q(0.5)), ('p99', q(0.99)),
        ('max', v[-1]))}


@dataclass
class DirectionStats:
    """Counters of one direction of the bridge."""

    received: int = 0
    forwarded: int = 0
    dropped: int = 0
    overtaken: int = 0
    send_errors: int = 0
    truncated: int = 0
    pending: int = 0
    drawn: list[float] = field(default_factory=list)
    achieved: list[float] = field(default_factory=list)
    _latest_sent_arrival: float = -math.inf

    def sent(self, arrival: float, drawn: float, now: float) -> None:
        self.forwarded += 1
        self.drawn.append(drawn)
        self.achieved.append(now - arrival)
        if arrival < self._latest_sent_arrival:
            self.overtaken += 1
        else:
            self._latest_sent_arrival = arrival

    def to_dict(self, delays: bool = True) -> dict[str, Any]:
        """Counters, and with ``delays`` the delay figures (sorting every delay so far: at
        exit only, a periodic sort of 10^5 delays would itself delay frames)."""
        d: dict[str, Any] = {k: getattr(self, k) for k in (
            'received', 'forwarded', 'dropped', 'overtaken', 'send_errors', 'truncated',
            'pending')}
        if delays:
            d['drawn_delay_ms'] = figures(self.drawn)
            d['achieved_delay_ms'] = figures(self.achieved)
        return d


def summary(settings: LinkSettings, interfaces: tuple[str, str],
            stats: dict[str, DirectionStats], state: str) -> dict[str, Any]:
    """The stats file's content: settings, per-direction counters and both directions; the
    delay figures only once ``state`` is ``stopped``."""
    both = DirectionStats()
    for s in stats.values():
        for k in ('received', 'forwarded', 'dropped', 'overtaken', 'send_errors', 'truncated',
                  'pending'):
            setattr(both, k, getattr(both, k) + getattr(s, k))
        both.drawn += s.drawn
        both.achieved += s.achieved
    return {'stage': 'delay_bridge', 'state': state, 'pid': os.getpid(),
            'interfaces': list(interfaces), 'delay_ms': settings.delay * 1e3,
            'jitter': settings.jitter, 'loss': settings.loss, 'seed': settings.seed,
            'directions': {k: v.to_dict(state == 'stopped') for k, v in stats.items()},
            'total': both.to_dict(state == 'stopped')}


def _open(ifname: str) -> socket.socket:
    try:
        socket.if_nametoindex(ifname)
    except OSError:
        raise LinkError(f'interface {ifname!r}: no such interface in this network '
                        'namespace') from None
    try:
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)
    except PermissionError:
        raise LinkError('a packet socket needs CAP_NET_RAW (run as root)') from None
    try:
        sock.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RECEIVE_BUFFER)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        sock.bind((ifname, ETH_P_ALL))
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        raise LinkError(f'interface {ifname!r}: {exc}') from None
    return sock


def _arrival(ancdata: list[tuple[int, int, bytes]]) -> float:
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = struct.unpack('qq', data[:16])
            return float(sec) + nsec * 1e-9
    return time.time()


class Bridge:
    """The two sockets, the pending frames and the counters (see module doc)."""

    def __init__(self, a: str, b: str, line: DelayLine,
                 stats_path: Path | None = None) -> None:
        self.interfaces = (a, b)
        self.line = line
        self.stats_path = stats_path
        self.stats = {d: DirectionStats() for d in DIRECTIONS}
        self._socks: list[socket.socket] = []
        self._pending: list[tuple[float, int, int, float, float, bytes]] = []
        self._count = 0
        #: SCHED_FIFO priority the bridge runs at (0: normal scheduling), for the stats.
        self.priority = 0

    def open(self) -> None:
        for name in self.interfaces:
            self._socks.append(_open(name))
        self.write_stats('running')

    def close(self) -> None:
        for i, d in enumerate(DIRECTIONS):
            self.stats[d].pending = sum(1 for p in self._pending if p[2] == i)
        self._pending.clear()
        for s in self._socks:
            s.close()
        self._socks.clear()

    def write_stats(self, state: str) -> dict[str, Any]:
        out = summary(self.line.settings, self.interfaces, self.stats, state)
        out['rt_priority'] = self.priority
        if self.stats_path is not None:
            tmp = self.stats_path.with_name(self.stats_path.name + '.tmp')
            tmp.write_text(json.dumps(out, indent=1) + '\n', encoding='utf-8')
            os.replace(tmp, self.stats_path)
        return out

    def _take(self, i: int) -> None:
        """Read up to :data:`BURST` frames from socket ``i`` and schedule or drop each."""
        sock, st = self._socks[i], self.stats[DIRECTIONS[i]]
        for _ in range(BURST):
            try:
                data, anc, flags, addr = sock.recvmsg(MAX_FRAME, 64)
            except (BlockingIOError, InterruptedError):
                return
            if addr[2] == PACKET_OUTGOING:
                continue
            st.received += 1
            if flags & socket.MSG_TRUNC:
                st.truncated += 1
                continue
            delay = self.line.draw()
            if delay is None:
                st.dropped += 1
                continue
            if data[0] & VNET_HDR_F_DATA_VALID:     # a receive-side flag; not for sending
                data = bytes([data[0] & ~VNET_HDR_F_DATA_VALID]) + data[1:]
            arrival = _arrival(anc)
            self._count += 1
            heapq.heappush(self._pending, (arrival + delay, self._count, i, arrival, delay,
                                           data))

    def _send_due(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            _, _, i, arrival, delay, data = heapq.heappop(self._pending)
            st = self.stats[DIRECTIONS[i]]
            try:
                self._socks[1 - i].send(data)
            except OSError:          # ENOBUFS and the like: a lost frame, as on a wire
                st.send_errors += 1
                continue
            st.sent(arrival, delay, time.time())

    def run(self, stopped: Callable[[], bool]) -> None:
        """Forward until ``stopped()`` (checked at least every 0.1 s)."""
        next_stats = time.monotonic() + STATS_EVERY
        while not stopped():
            now = time.time()
            self._send_due(now)
            timeout = 0.1
            if self._pending:
                timeout = min(timeout, max(0.0, self._pending[0][0] - time.time()))
            try:
                ready, _, _ = select.select(self._socks, [], [], timeout)
            except InterruptedError:
                continue
            for sock in ready:
                self._take(self._socks.index(sock))
            if time.monotonic() >= next_stats:
                self.write_stats('running')
                next_stats = time.monotonic() + STATS_EVERY


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='delay_bridge', description='Layer-2 bridge between two interfaces with delay, '
        'uniform jitter and random loss (a user-space stand-in for netem).')
    p.add_argument('--a', required=True, help='first interface')
    p.add_argument('--b', required=True, help='second interface')
    p.add_argument('--delay-ms', type=float, required=True, help='mean one-way delay (ms)')
    p.add_argument('--jitter', type=float, default=0.2,
                   help='uniform spread as a fraction of the delay (default 0.2: +-20 %%)')
    p.add_argument('--loss', type=float, default=0.01,
                   help='drop probability per frame (default 0.01)')
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument('--stats', type=Path, help='JSON counters, rewritten every second')
    p.add_argument('--rt-priority', type=int, default=0,
                   help='SCHED_FIFO priority 1-99 of the bridge (0: normal scheduling, the '
                   'default); keeps its own latency out of the delay on a busy machine')
    return p


def set_priority(priority: int) -> str | None:
    """SCHED_FIFO at ``priority`` for this process (0: leave it); None, or why not."""
    if not priority:
        return None
    if not 1 <= priority <= 99:
        return f'--rt-priority must be in 1..99, got {priority}; normal scheduling'
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return f'--rt-priority {priority}: {exc}; normal scheduling'
    return None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        settings = LinkSettings(args.delay_ms * 1e-3, args.jitter, args.loss, args.seed)
        bridge = Bridge(args.a, args.b, DelayLine(settings), args.stats)
        bridge.open()
    except HapticTopologyError as exc:
        print(f'delay_bridge: error: {exc}', file=sys.stderr)
        return 2
    problem = set_priority(args.rt_priority)
    if problem:
        print(f'delay_bridge: warning: {problem}', file=sys.stderr)
    bridge.priority = 0 if problem else args.rt_priority
    stop: list[int] = []

    def request_stop(signum: int, frame: Any) -> None:
        stop.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, request_stop)
    try:
        bridge.run(lambda: bool(stop))
    finally:
        bridge.close()
        out = bridge.write_stats('stopped')
        print(json.dumps(out), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
