"""An emulator of the Haply Inverse Service's simulation channel (protocol 3.5.x, as the
``haply`` backend follows it: :mod:`haptic_topology.remote.haply`), with simulated Inverse3
devices, so that the backend can be tried and tested without a device:
``python -m haptic_topology.remote.haply_emulator``.

It speaks what Haply documents: a WebSocket server (port 10001 by default); on connection an
inventory (``session_id``, ``inverse3: [{device_id, config, state, status}]``); after that
one state message (``state`` and ``status`` of every device) per message received; the
``set_cursor_force`` command (``vector`` in N) of each message applied to the device it
names. Like the service's, a command lasts one message: the force returns to zero
``--command-timeout-ms`` after the newest command, and when the connection closes.

**The simulated device** (each ``--device``): a point mass ``--mass`` (kg) with viscous
``--damping`` (N s/m), integrated (semi-implicit Euler, 0.25 ms steps) from the previous
message's time to this one's on the monotonic clock, under the commanded force and the hand.
Positions are reported quantised to ``--quantum`` (m), in metres; velocities in m/s. The
device starts at rest at ``--start`` (m, the service's frame: x right, y forward, z up) and
its clock starts with the first command.

**The simulated hand**: a spring ``--hand-stiffness`` (N/m) with damping ``--hand-damping``
(N s/m) from the handle to a target that starts at ``--start`` plus ``--hand-offset`` (m) and
moves round a circle of radius ``--hand-radius`` (m) in the x-y plane at
``--hand-frequency`` (Hz). The defaults pull the handle 0.4 N along x at the start, as
``fig8_point``'s simulated user pushes, then the target circles slowly.

**Fault injection** (``--fault KIND@N``, repeatable; N counts the messages received, from 1,
over all connections): ``nan@N`` answers message N with a NaN position; ``malformed@N``
answers it with a truncated JSON text; ``unplug@N`` removes the device(s) from every state
from message N on; ``hang@N`` stops answering from message N on (the connection stays open);
``stop@N`` ends the service at message N (the connection drops without a close frame, as
when the service is stopped or crashes).

**The handle's buttons**: ``--grip ID`` adds a wireless VerseGrip (``wireless_verse_grip`` in
the inventory and the states, ``state.buttons.a`` / ``.b``); ``--press B@N-M`` holds its
button B from message N to M.

``--ready-file PATH`` writes ``{host, port, pid, devices}`` (JSON) once it serves (with
``--port 0``, how a program learns the port), ``--log PATH`` one line per command received
(CSV: monotonic ns, device id, fx, fy, fz; and a zero line when a connection closes),
``--monitor HOST:PORT`` a UDP copy of each of those lines as it happens. It prints one line
when it serves and one with its counters when it stops (SIGINT/SIGTERM).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

from websockets.exceptions import ConnectionClosed
from websockets.sync.server import ServerConnection, serve

from haptic_topology.remote.haply import DEFAULT_PORT, SERVICE_VERSION

#: Integration step of the simulated device (s).
STEP = 0.25e-3
#: Longest stretch integrated at one message (s); a longer gap is skipped (the device rests).
MAX_GAP = 1.0
FAULTS = ('nan', 'malformed', 'unplug', 'hang', 'stop')


@dataclass
class Hand:
    """The simulated hand (module doc)."""

    stiffness: float = 40.0
    damping: float = 2.0
    offset: tuple[float, float, float] = (0.01, 0.0, 0.0)
    radius: float = 0.005
    frequency: float = 0.25


@dataclass
class SimInverse3:
    """One simulated Inverse3 (module doc); ``t`` its clock (s, from the first command)."""

    device_id: str
    start: tuple[float, float, float]
    mass: float = 0.2
    damping: float = 2.0
    quantum: float = 1e-5
    hand: Hand = field(default_factory=Hand)
    x: list[float] = field(default_factory=list)
    v: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_until: float = 0.0
    t: float = 0.0
    last: float | None = None

    def __post_init__(self) -> None:
        self.x = list(self.start)

    def _target(self, t: float) -> tuple[float, float, float]:
        h = self.hand
        w = 2.0 * math.pi * h.frequency * t
        return (self.start[0] + h.offset[0] + h.radius * (math.cos(w) - 1.0),
                self.start[1] + h.offset[1] + h.radius * math.sin(w),
                self.start[2] + h.offset[2])

    def advance(self, now: float) -> None:
        """Integrate up to ``now`` (monotonic s) under the force that held meanwhile."""
        if self.last is None:
            return
        gap = min(now - self.last, MAX_GAP)
        n = int(gap / STEP)
        h, m, b = self.hand, self.mass, self.damping
        x, v = self.x, self.v
        for k in range(n):
            on = self.last + k * STEP < self.force_until
            tx, ty, tz = self._target(self.t)
            for i, target in enumerate((tx, ty, tz)):
                f = (self.force[i] if on else 0.0) + h.stiffness * (target - x[i]) \
                    - h.damping * v[i] - b * v[i]
                v[i] += STEP * f / m
                x[i] += STEP * v[i]
            self.t += STEP
        self.last = self.last + n * STEP if gap == now - self.last else now

    def command(self, force: tuple[float, float, float], now: float, lifetime: float) -> None:
        if self.last is None:
            self.last = now
        self.force = force
        self.force_until = now + lifetime

    def state(self, nan: bool = False) -> dict[str, Any]:
        q = self.quantum
        pos = [round(c / q) * q if q > 0 else c for c in self.x]
        if nan:
            pos[0] = math.nan
        on = self.last is not None and self.last < self.force_until
        f = self.force if on else (0.0, 0.0, 0.0)
        return {'cursor_position': _vec(pos), 'cursor_velocity': _vec(self.v),
                'current_cursor_force': _vec(f), 'control_domain': 'cartesian',
                'control_mode': 'force' if on else 'idle'}

    def config(self) -> dict[str, Any]:
        return {'type': 'inverse3', 'port': 'emulated',
                'device_info': {'major_version': 7, 'minor_version': 4,
                                'id': self.device_id, 'device_type': 4,
                                'uuid': f'EMULATED{self.device_id}'},
                'handedness': 'right', 'gravity_compensation': {'enabled': True,
                                                                'scaling_factor': 1.0}}


def _vec(c: Sequence[float]) -> dict[str, float]:
    return {'x': c[0], 'y': c[1], 'z': c[2]}


STATUS = {'calibrated': True, 'in_use': True, 'power_supply': True, 'ready': True,
          'started': True}


class Service:
    """The emulated service: devices, counters, faults, the log (module doc)."""

    def __init__(self, devices: list[SimInverse3], command_timeout: float,
                 faults: dict[str, int], log: TextIO | None,
                 monitor: tuple[str, int] | None, grip: str = '',
                 presses: Sequence[tuple[str, int, int]] = ()) -> None:
        self.devices = {d.device_id: d for d in devices}
        self.grip = grip
        self.presses = tuple(presses)
        self.lifetime = command_timeout
        self.faults = faults
        self.log = log
        self.monitor = monitor
        self._mon = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if monitor else None
        self.lock = threading.Lock()
        self.sessions = 0
        self.received = 0
        self.commands = 0
        self.unknown_device = 0
        self.bad_messages = 0
        self.stop_now = threading.Event()

    def _record(self, now_ns: int, device_id: str, f: tuple[float, float, float]) -> None:
        line = f'{now_ns},{device_id},{f[0]!r},{f[1]!r},{f[2]!r}'
        if self.log is not None:
            self.log.write(line + '\n')
        if self._mon is not None and self.monitor is not None:
            try:
                self._mon.sendto(line.encode(), self.monitor)
            except OSError:
                pass

    def _fault(self, kind: str, n: int) -> bool:
        at = self.faults.get(kind)
        if at is None:
            return False
        return n >= at if kind in ('unplug', 'hang') else n == at

    def _grips(self, n: int, config: bool = False) -> list[dict[str, Any]]:
        """The wireless VerseGrip (``--grip``) with its buttons at message ``n``."""
        if not self.grip:
            return []
        held = {b: any(b == k and n0 <= n <= n1 for k, n0, n1 in self.presses) for b in 'ab'}
        grip: dict[str, Any] = {
            'device_id': self.grip,
            'state': {'buttons': held, 'hall': 0, 'battery_level': 1.0,
                      'orientation': {'w': 1.0, 'x': 0.0, 'y': 0.0, 'z': 0.0}},
            'status': {'ready': True}}
        if config:
            grip['config'] = {'type': 'wireless_verse_grip'}
        return [grip]

    def inventory(self) -> str:
        with self.lock:
            self.sessions += 1
            return json.dumps({'session_id': self.sessions, 'inverse3': [
                {'device_id': d.device_id, 'config': d.config(), 'state': d.state(),
                 'status': STATUS} for d in self.devices.values()],
                'verse_grip': [], 'wireless_verse_grip': self._grips(self.received, True)})

    def answer(self, text: str | bytes) -> str | None:
        """Take one client message; the state message to answer with (None: no answer)."""
        now = time.monotonic()
        now_ns = time.monotonic_ns()
        with self.lock:
            self.received += 1
            n = self.received
            if self._fault('stop', n):
                self.stop_now.set()
                return None
            for d in self.devices.values():
                d.advance(now)
            try:
                msg = json.loads(text)
                entries = msg.get('inverse3', []) if isinstance(msg, dict) else None
                if not isinstance(entries, list):
                    raise ValueError('inverse3 is not a list')
                for e in entries:
                    dev = self.devices.get(str(e.get('device_id')))
                    if dev is None:
                        self.unknown_device += 1
                        continue
                    vec = e.get('commands', {}).get('set_cursor_force', {}).get('vector')
                    if vec is None:
                        continue
                    f = (float(vec['x']), float(vec['y']), float(vec['z']))
                    if not all(math.isfinite(c) for c in f):
                        raise ValueError('non-finite force')
                    dev.command(f, now, self.lifetime)
                    self.commands += 1
                    self._record(now_ns, dev.device_id, f)
            except (ValueError, KeyError, TypeError, AttributeError):
                self.bad_messages += 1
            if self._fault('hang', n):
                return None
            if self._fault('malformed', n):
                return '{"inverse3": [{"device_id": '
            gone = self._fault('unplug', n)
            return json.dumps({'inverse3': [] if gone else [
                {'device_id': d.device_id, 'state': d.state(self._fault('nan', n)),
                 'status': STATUS} for d in self.devices.values()],
                'wireless_verse_grip': self._grips(n)})

    def disconnected(self) -> None:
        """A connection closed: every device returns to idle (zero force)."""
        now_ns = time.monotonic_ns()
        with self.lock:
            for d in self.devices.values():
                d.force_until = 0.0
                self._record(now_ns, d.device_id, (0.0, 0.0, 0.0))

    def flush(self) -> None:
        if self.log is not None:
            self.log.flush()

    def counters(self) -> dict[str, int]:
        return {'sessions': self.sessions, 'received': self.received,
                'commands': self.commands, 'unknown_device': self.unknown_device,
                'bad_messages': self.bad_messages}


def _triple(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected x,y,z (three numbers), got {text!r}'
                                         ) from None
    return x, y, z


def _fault(text: str) -> tuple[str, int]:
    kind, _, at = text.partition('@')
    if kind not in FAULTS or not at.isdigit() or int(at) < 1:
        raise argparse.ArgumentTypeError(f'expected KIND@N with KIND one of '
                                         f'{", ".join(FAULTS)} and N >= 1, got {text!r}')
    return kind, int(at)


def _press(text: str) -> tuple[str, int, int]:
    button, _, span = text.partition('@')
    n0, _, n1 = span.partition('-')
    if button not in ('a', 'b') or not n0.isdigit() or not n1.isdigit() or int(n1) < int(n0):
        raise argparse.ArgumentTypeError(f'expected a@N-M or b@N-M (held from message N to M), '
                                         f'got {text!r}')
    return button, int(n0), int(n1)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m haptic_topology.remote.haply_emulator',
        description=f'An emulated Haply Inverse Service (simulation channel, protocol '
                    f'{SERVICE_VERSION}) with simulated Inverse3 devices.')
    p.add_argument('--host', default='127.0.0.1')
    p.add_argument('--port', type=int, default=DEFAULT_PORT, help='0: any free port')
    p.add_argument('--device', action='append', default=[], metavar='ID',
                   help='an Inverse3 device id (repeat for several; default 0E31)')
    p.add_argument('--start', type=_triple, default=(0.0, -0.12, 0.15), metavar='X,Y,Z')
    p.add_argument('--mass', type=float, default=0.2, help='kg')
    p.add_argument('--damping', type=float, default=2.0, help='N s/m')
    p.add_argument('--quantum', type=float, default=1e-5, help='position quantum (m)')
    p.add_argument('--hand-stiffness', type=float, default=40.0, help='N/m (0: no hand)')
    p.add_argument('--hand-damping', type=float, default=2.0, help='N s/m')
    p.add_argument('--hand-offset', type=_triple, default=(0.01, 0.0, 0.0), metavar='X,Y,Z')
    p.add_argument('--hand-radius', type=float, default=0.005, help='m')
    p.add_argument('--hand-frequency', type=float, default=0.25, help='Hz')
    p.add_argument('--command-timeout-ms', type=float, default=10.0)
    p.add_argument('--grip', default='', metavar='ID',
                   help='a wireless VerseGrip with this device id (its buttons a and b)')
    p.add_argument('--press', type=_press, action='append', default=[], metavar='B@N-M',
                   help='the grip\'s button B (a or b) held from message N to M; repeatable')
    p.add_argument('--fault', type=_fault, action='append', default=[], metavar='KIND@N')
    p.add_argument('--ready-file', default='')
    p.add_argument('--log', default='')
    p.add_argument('--monitor', default='', metavar='HOST:PORT')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    hand = Hand(args.hand_stiffness, args.hand_damping, args.hand_offset, args.hand_radius,
                args.hand_frequency)
    ids = args.device or ['0E31']
    devices = [SimInverse3(i, (args.start[0] + 0.05 * k, args.start[1], args.start[2]),
                           args.mass, args.damping, args.quantum, hand)
               for k, i in enumerate(ids)]
    monitor = None
    if args.monitor:
        host, _, port = args.monitor.rpartition(':')
        monitor = (host, int(port))
    log = open(args.log, 'w', encoding='utf-8') if args.log else None
    service = Service(devices, 1e-3 * args.command_timeout_ms, dict(args.fault), log, monitor,
                      args.grip, args.press)

    def handler(ws: ServerConnection) -> None:
        ws.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            ws.send(service.inventory())
            for message in ws:
                reply = service.answer(message)
                if service.stop_now.is_set():
                    break
                if reply is not None:
                    ws.send(reply)
        except ConnectionClosed:
            pass
        finally:
            service.disconnected()
        if service.stop_now.is_set():     # the service stops: no close frame, no goodbye
            service.flush()
            print(f'haply_emulator: stopped (fault stop@{service.faults["stop"]}): '
                  f'{service.counters()}', flush=True)
            os._exit(0)

    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    sock = socket.create_server((args.host, args.port))
    with serve(handler, sock=sock, compression=None, ping_interval=None) as server:
        port = sock.getsockname()[1]
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        if args.ready_file:
            tmp = args.ready_file + '.tmp'
            with open(tmp, 'w', encoding='utf-8') as f:
                json.dump({'host': args.host, 'port': port, 'pid': os.getpid(),
                           'devices': ids}, f)
            os.replace(tmp, args.ready_file)
        print(f'haply_emulator: Haply Inverse Service {SERVICE_VERSION} emulator on '
              f'ws://{args.host}:{port}: Inverse3 {", ".join(ids)}'
              + (f'; faults {", ".join(f"{k}@{n}" for k, n in args.fault)}' if args.fault
                 else ''), flush=True)
        while not stop.wait(0.2):
            pass
        server.shutdown()
    service.flush()
    if log is not None:
        log.close()
    print(f'haply_emulator: stopped: {json.dumps(service.counters())}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
