"""The ``haply`` device backend: a Haply Inverse3 through the Haply Inverse Service's
WebSocket/JSON simulation channel, as Haply documents it for service version 3.5.x
(docs.haply.co, inverseSDK, "WebSocket Protocol" and "Control Commands"; the version this
module follows is :data:`SERVICE_VERSION`). The closed serial protocol between the service
and the device is not used.

**The protocol** (3.5.x). The service listens on ``ws://localhost:10001``. On connection it
sends an inventory: ``{"session_id": ..., "inverse3": [{"device_id", "config", "state",
"status"}, ...], ...}``; after that it sends exactly one state message (``state`` and
``status`` of every device) for each message it receives. A force command is
``{"inverse3": [{"device_id": ID, "commands": {"set_cursor_force": {"vector": {"x", "y",
"z"}}}}]}`` in newtons; ``state.cursor_position`` is in metres and ``cursor_velocity`` in
m/s, in the service's frame (right-handed, x right, y forward, z up). Commands are per
message: a device that receives none returns to idle (no force). The first message also
registers the session (``session.configure.profile.name``).

**Per cycle** (the driver's 1 kHz deadline path; nothing here waits):

* :meth:`HaplyBackend.write` maps the task force to the device frame, clamps its norm to
  ``max_force``, formats one command (``repr`` of each float: exact) and sends it as one
  WebSocket frame on a non-blocking socket
  (:class:`~haptic_topology.remote.websocket_client.WebSocketClient`). At most
  ``max_in_flight`` commands go unanswered: beyond that the cycle sends nothing
  (``throttled``), so a service that falls behind never accumulates a queue of old
  commands, and its states never lag behind by more than that many messages;
* :meth:`HaplyBackend.read` takes whatever has arrived, decodes only the newest state (older
  ones are counted and skipped) and returns it. A state is normally the answer to the
  previous cycle's command: one cycle old.

**Never force from bad or stale data.** A reading carries ``DeviceStatus.FAULT`` (the driver
then writes zero from the next cycle on and fades back in when it clears) while the newest
state is older than ``stale_ms``, the newest message is not a valid state of the device (not
JSON, fields missing, NaN/inf), the device is missing from it (unplugged), or the connection
has ended (service stopped); :meth:`HaplyBackend.fault_reason` says which, naming the
address. A faulted reading repeats the newest valid position with zero velocity. A closed
connection is not reopened: the run goes on at zero force with the fault, and the next
activation connects again.

**Lifecycle.** ``configure`` checks the options (no I/O). ``activate`` connects (at most
``connect_timeout_ms``; a refused connection fails at once, naming the address), takes the
inventory, chooses the device (``device_id``, or the only Inverse3), sends a zero force and
waits for its answer. ``deactivate`` sends a zero force (always, whatever ``max_in_flight``
says), closes the connection; the service's device then returns to idle. The identity
(device id, model, firmware, handedness) is :attr:`HaplyBackend.hardware_id`.

**Frames and units.** Task vectors of a point grasp only (``planar_point``: x, y;
``spatial_point``: x, y, z): the Inverse3 senses and actuates three translations, no rotation
(:data:`~haptic_topology.device.backend.TRANSLATION_AXES`). With ``A`` from ``axes`` (task
axis i = that signed device axis) and ``p_o`` from ``origin``: task position ``p = p_o + A
p_D`` (its first m rows), velocity ``v = A v_D``, command ``f_D = A^T f`` (the task force,
zero on a planar task's z row). ``origin: start`` (the default) puts the handle's position at
the first activation on the scenario's initial pose: wherever the handle is, it holds the
grasp point. The Inverse3 has no force sensor: the hand wrench is reported as zero and the
controller sees the hand through the motion.

Options (``backend_options``; every one optional): ``host`` (127.0.0.1), ``port`` (10001),
``path`` (``/``), ``device_id`` (the only Inverse3), ``axes`` ([x, y, z]), ``origin``
(``start``, or m numbers in metres), ``max_force`` (N, norm; default 10), ``stale_ms`` (20),
``connect_timeout_ms`` (2000), ``max_in_flight`` (4), ``profile`` (the session profile name).
A bad one is refused naming it.
"""

from __future__ import annotations

import json
import math
import pickle
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from haptic_topology.device.backend import (
    TRANSLATION_AXES,
    BackendConfig,
    DeviceAxes,
    DeviceBackend,
    DeviceReading,
)
from haptic_topology.errors import DeviceError
from haptic_topology.remote.websocket_client import WebSocketClient, connect
from haptic_topology.vocabulary import DeviceStatus

#: The Haply Inverse Service version whose documented protocol this backend follows.
SERVICE_VERSION = '3.5.x'
#: The service's default simulation-channel port.
DEFAULT_PORT = 10001
#: Options and their defaults (module doc).
DEFAULTS: dict[str, Any] = {
    'host': '127.0.0.1', 'port': DEFAULT_PORT, 'path': '/', 'device_id': '',
    'axes': ['x', 'y', 'z'], 'origin': 'start', 'max_force': 10.0, 'stale_ms': 20.0,
    'connect_timeout_ms': 2000.0, 'max_in_flight': 4, 'profile': 'haptic_topology',
}
_AXES = {'x': 0, 'y': 1, 'z': 2}
_FAULT = DeviceStatus.FAULT
#: How long ``deactivate`` may wait for its zero force to leave (s).
_RELEASE_WAIT = 0.2


def _error(key: str, expected: str, value: Any) -> DeviceError:
    return DeviceError(f'haply: backend_options.{key}: expected {expected}, got {value!r}')


def _number(opts: Mapping[str, Any], key: str, lo: float, hi: float) -> float:
    value = opts.get(key, DEFAULTS[key])
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not (math.isfinite(value) and lo < value <= hi)):
        raise _error(key, f'a number in ({lo:g}, {hi:g}]', value)
    return float(value)


def _text(opts: Mapping[str, Any], key: str) -> str:
    value = opts.get(key, DEFAULTS[key])
    if not isinstance(value, str):
        raise _error(key, 'text', value)
    return value


def parse_axes(value: Any) -> np.ndarray:
    """``axes``: 3 signed device axis names (task x, y, z), right-handed -> ``A`` (3 x 3,
    device -> task)."""
    expected = '3 signed device axis names such as [x, -z, y] (task x, y, z), right-handed'
    if not (isinstance(value, list) and len(value) == 3
            and all(isinstance(v, str) for v in value)):
        raise _error('axes', expected, value)
    a = np.zeros((3, 3))
    for i, name in enumerate(value):
        text = name.strip().lower()
        axis = _AXES.get(text.lstrip('+-'))
        if axis is None:
            raise _error('axes', expected, value)
        a[i, axis] = -1.0 if text.startswith('-') else 1.0
    if abs(np.linalg.det(a) - 1.0) > 1e-9:
        raise _error('axes', expected, value)
    return a


class HaplyBackend(DeviceBackend):
    """A Haply Inverse3 through the Inverse Service (module doc). ``clock_ns``: monotonic
    clock (ns) for the staleness (tests inject one)."""

    name = 'haply'
    lockstep = False            # the device runs on its own clock

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock_ns = clock_ns
        self._m = 0
        self._ws: WebSocketClient | None = None
        self._origin: np.ndarray | None = None
        self._first = True
        self._fresh_start = False
        self._pos = (0.0, 0.0, 0.0)
        self._vel = (0.0, 0.0, 0.0)
        self._origin_list = (0.0, 0.0, 0.0)
        self._state_ns = 0
        self._bad = ''
        self._reason = ''
        self.device_id = ''
        self.identity = ''
        self.session_id: Any = None
        self.peer = ''
        self._sent = 0
        self._answers = 0
        # counters (read by the diagnostics thread as they are)
        self.states = 0
        self.malformed = 0
        self.nonfinite = 0
        self.device_missing = 0
        self.throttled = 0
        self.not_sent = 0
        self.nonfinite_writes = 0
        self.force_clamped = 0
        self.stale_cycles = 0
        self.fault_reads = 0

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        """The Inverse3 senses and actuates forces along x, y, z only: point tasks."""
        del options
        return TRANSLATION_AXES

    # -- configuration -----------------------------------------------------------------------
    def configure(self, config: BackendConfig) -> None:
        opts = config.options
        unknown = sorted(set(opts) - set(DEFAULTS))
        if unknown:
            raise DeviceError(f'haply: backend_options: unknown option {unknown[0]!r} '
                              f'(expected some of: {", ".join(sorted(DEFAULTS))})')
        task = config.params.task
        if not task.point:
            raise DeviceError(f'haply: the Inverse3 renders point tasks only (planar_point, '
                              f'spatial_point), got {task.value}')
        self.host = _text(opts, 'host')
        port = opts.get('port', DEFAULTS['port'])
        if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
            raise _error('port', 'an integer port in [1, 65535]', port)
        self.port = port
        self.path = _text(opts, 'path')
        if not self.path.startswith('/'):
            raise _error('path', 'a path starting with /', self.path)
        self.wanted_id = _text(opts, 'device_id')
        self.profile = _text(opts, 'profile')
        self._a = parse_axes(opts.get('axes', DEFAULTS['axes']))
        self._a_rows = [[float(v) for v in row] for row in self._a]
        m = task.dim
        origin = opts.get('origin', DEFAULTS['origin'])
        if origin == 'start':
            self._fixed_origin: np.ndarray | None = None
        elif (isinstance(origin, list) and len(origin) == m
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) for v in origin)):
            self._fixed_origin = np.zeros(3)
            self._fixed_origin[:m] = origin
        else:
            raise _error('origin', f'start, or {m} numbers (m): the task position of the '
                         'device frame\'s origin', origin)
        self.max_force = _number(opts, 'max_force', 0.0, 1000.0)
        self.stale_ns = round(1e6 * _number(opts, 'stale_ms', 0.0, 10_000.0))
        self.connect_timeout = 1e-3 * _number(opts, 'connect_timeout_ms', 0.0, 600_000.0)
        n = opts.get('max_in_flight', DEFAULTS['max_in_flight'])
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 64:
            raise _error('max_in_flight', 'an integer in [1, 64]', n)
        self.max_in_flight = n
        self._m = m
        self._initial = np.zeros(3)
        self._initial[:m] = np.asarray(config.initial_pose, dtype=float)[:m]
        self.peer = f'ws://{self.host}:{self.port}{self.path}'
        self._origin = self._fixed_origin

    def task_dim(self) -> int:
        if not self._m:
            raise DeviceError('haply: used before configure()')
        return self._m

    @property
    def hardware_id(self) -> str:
        if not self._m:
            return self.name
        if not self.identity:
            return f'{self.name} {self.peer}'
        return f'{self.name} {self.identity} via {self.peer} (service protocol {SERVICE_VERSION})'

    def fault_reason(self) -> str:
        return self._reason or f'{self.name}: the device reports a fault'

    # -- lifecycle ---------------------------------------------------------------------------
    def activate(self) -> None:
        self.task_dim()
        if self._ws is not None:
            return
        start = time.monotonic()
        try:
            ws = connect(self.host, self.port, self.path, self.connect_timeout)
        except DeviceError as exc:
            raise DeviceError(f'haply: {exc}: is the Haply Inverse Service (or '
                              '`python -m haptic_topology.remote.haply_emulator`) running '
                              'there?') from None
        self._ws = ws
        try:
            self._start(ws, start)
        except DeviceError:
            self._close()
            raise

    def _left(self, start: float) -> float:
        return max(0.0, self.connect_timeout - (time.monotonic() - start))

    def _start(self, ws: WebSocketClient, start: float) -> None:
        first = ws.wait_text(self._left(start))
        if first is None:
            raise DeviceError(f'haply: no inventory from {self.peer} within '
                              f'{1e3 * self.connect_timeout:g} ms (connect_timeout_ms)'
                              + (f': {ws.closed}' if ws.closed else ''))
        try:
            inventory = json.loads(first)
            devices = inventory['inverse3']
            ids = [str(d['device_id']) for d in devices]
        except (ValueError, KeyError, TypeError):
            raise DeviceError(f'haply: the first message from {self.peer} is not an '
                              f'inventory of Inverse3 devices: {first[:120]!r}') from None
        if self.wanted_id:
            if self.wanted_id not in ids:
                raise DeviceError(f'haply: backend_options.device_id: no Inverse3 '
                                  f'{self.wanted_id!r} at {self.peer}; it has '
                                  f'{", ".join(ids) or "none"}')
            chosen = self.wanted_id
        elif len(ids) == 1:
            chosen = ids[0]
        else:
            raise DeviceError(f'haply: {len(ids)} Inverse3 devices at {self.peer} '
                              f'({", ".join(ids) or "none"}): choose one with '
                              'backend_options.device_id' if ids else
                              f'haply: no Inverse3 at {self.peer}: is it plugged in and '
                              'powered?')
        self.device_id = chosen
        self.session_id = inventory.get('session_id')
        self.identity = _identity(devices[ids.index(chosen)])
        head = json.dumps({'device_id': chosen}, separators=(',', ':'))[:-1]
        self._prefix = ('{"inverse3":[' + head + ',"commands":{"set_cursor_force":{"vector":'
                        ).encode()
        self._suffix = b'}}}]}'
        self._session = (',"session":{"configure":{"profile":{"name":'
                         + json.dumps(self.profile) + '}}}').encode()
        self._first = True
        self._sent = self._answers = 0
        self._state_ns = 0
        self._bad = self._reason = ''
        self._send((0.0, 0.0, 0.0), force=True)
        while not self._state_ns:
            msg = ws.wait_text(self._left(start))
            if msg is None:
                raise DeviceError(f'haply: no state from {self.peer} within '
                                  f'{1e3 * self.connect_timeout:g} ms of connecting '
                                  '(connect_timeout_ms)'
                                  + (f': {ws.closed}' if ws.closed else ''))
            self._answers += 1
            self._take(msg, self._clock_ns())
            if self._bad and not self._state_ns:
                raise DeviceError(f'haply: {self._bad}')
        if self._origin is None:
            self._origin = self._initial - self._a @ np.array(self._pos)
        ox, oy, oz = (float(v) for v in self._origin)
        self._origin_list = (ox, oy, oz)
        self._fresh_start = True

    def deactivate(self) -> None:
        ws = self._ws
        if ws is None:
            return
        if not ws.closed:
            self._send((0.0, 0.0, 0.0), force=True)
            deadline = time.monotonic() + _RELEASE_WAIT
            while ws._out and not ws.closed and time.monotonic() < deadline:
                ws.poll()
                time.sleep(0.001)
        self._close()

    def _close(self) -> None:
        if self._ws is not None:
            self._ws.close()
            self._ws = None

    def carry_over(self) -> bytes | None:
        """The task position of the device frame's origin, so that the next activation (a
        new instance) keeps the mapping of the first (``origin: start``)."""
        return None if self._origin is None else pickle.dumps(self._origin)

    def resume(self, carried: bytes) -> None:
        origin = pickle.loads(carried)
        if not (isinstance(origin, np.ndarray) and origin.shape == (3,)):
            raise DeviceError('haply: resume(): not a carried origin')
        if self._fixed_origin is None:
            self._origin = origin

    # -- cycle -------------------------------------------------------------------------------
    def _send(self, f_dev: Sequence[float], force: bool = False) -> None:
        ws = self._ws
        assert ws is not None
        if not force and self._sent - self._answers >= self.max_in_flight:
            self.throttled += 1
            return
        x, y, z = f_dev
        body = b'{"x":%r,"y":%r,"z":%r}' % (x, y, z)
        msg = self._prefix + body + self._suffix
        if self._first:
            msg = msg[:-1] + self._session + b'}'
            self._first = False
        if ws.send_text(msg):
            self._sent += 1
        else:
            self.not_sent += 1

    def write(self, wrench: np.ndarray) -> None:
        if self._ws is None:
            raise DeviceError('haply: write() before activate()')
        w = np.asarray(wrench, dtype=float)
        if w.shape != (self._m,):
            raise DeviceError(f'haply: write(): expected {self._m} force values, got shape '
                              f'{w.shape}')
        if not np.all(np.isfinite(w)):
            self.nonfinite_writes += 1
            w = np.where(np.isfinite(w), w, 0.0)
        # f_D = A^T f, on plain floats (for 3-vectors a fraction of numpy's calls)
        f = w.tolist() + [0.0] * (3 - self._m)
        a = self._a_rows
        f_dev = [a[0][i] * f[0] + a[1][i] * f[1] + a[2][i] * f[2] for i in range(3)]
        norm = math.sqrt(f_dev[0] * f_dev[0] + f_dev[1] * f_dev[1] + f_dev[2] * f_dev[2])
        if norm > self.max_force:
            self.force_clamped += 1
            k = self.max_force / norm
            f_dev = [k * c for c in f_dev]
        self._send(f_dev)

    def read(self, dt: float) -> DeviceReading:
        del dt  # the device runs at its own clock
        ws = self._ws
        if ws is None:
            raise DeviceError('haply: read() before activate()')
        newest, count = ws.poll()
        now = self._clock_ns()
        if self._fresh_start:
            # The first cycle comes some time after activate() took its state (the driver
            # starts its loop meanwhile) while the service was answering: that state is
            # the device's newest, not a stale one.
            self._fresh_start = False
            self._state_ns = max(self._state_ns, now)
        if count:
            self._answers += count
            assert newest is not None
            self._take(newest, now)
        return self._reading(now, ws)

    def _take(self, msg: bytes, now: int) -> None:
        """Decode one state message; keep its position and velocity if valid."""
        try:
            data = json.loads(msg)
            entry = None
            for d in data['inverse3']:
                if d['device_id'] == self.device_id:
                    entry = d
                    break
        except (ValueError, KeyError, TypeError, UnicodeDecodeError):
            self.malformed += 1
            self._bad = f'a malformed message from {self.peer}: {msg[:80]!r}'
            return
        if entry is None:
            self.device_missing += 1
            self._bad = f'the Inverse3 {self.device_id} is gone from {self.peer}\'s states ' \
                        '(unplugged or powered off?)'
            return
        try:
            st = entry['state']
            p, v = st['cursor_position'], st['cursor_velocity']
            pos = (float(p['x']), float(p['y']), float(p['z']))
            vel = (float(v['x']), float(v['y']), float(v['z']))
        except (KeyError, TypeError, ValueError):
            self.malformed += 1
            self._bad = (f'a state of {self.device_id} from {self.peer} without '
                         'cursor_position/cursor_velocity {x, y, z}')
            return
        if not all(math.isfinite(c) for c in pos + vel):
            self.nonfinite += 1
            self._bad = (f'a non-finite state of {self.device_id} from {self.peer}: '
                         f'position {pos}, velocity {vel}')
            return
        self._pos = pos
        self._vel = vel
        self._state_ns = now
        self._bad = ''
        self.states += 1

    def _task(self, d: tuple[float, float, float], origin: bool) -> np.ndarray:
        """``(p_o +) A d``, its first m rows."""
        a, o = self._a_rows, self._origin_list if origin else (0.0, 0.0, 0.0)
        return np.array([o[i] + a[i][0] * d[0] + a[i][1] * d[1] + a[i][2] * d[2]
                         for i in range(self._m)])

    def _reading(self, now: int, ws: WebSocketClient) -> DeviceReading:
        m = self._m
        pose = self._task(self._pos, True)
        age = now - self._state_ns
        if ws.closed:
            self._reason = f'haply: the connection to {self.peer} ended ({ws.closed})'
        elif self._bad:
            self._reason = f'haply: {self._bad}'
        elif age > self.stale_ns:
            self.stale_cycles += 1
            self._reason = (f'haply: no state from {self.peer} for {age * 1e-6:.1f} ms '
                            f'(stale_ms {self.stale_ns * 1e-6:g}): the service is stalled or '
                            'stopped')
        else:
            return DeviceReading(pose, self._task(self._vel, False), np.zeros(m))
        self.fault_reads += 1
        return DeviceReading(pose, np.zeros(m), np.zeros(m), _FAULT)

    # -- figures -----------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Counts so far (module doc)."""
        ws = self._ws
        return {'states': self.states, 'malformed': self.malformed,
                'nonfinite': self.nonfinite, 'device_missing': self.device_missing,
                'commands_sent': self._sent, 'throttled': self.throttled,
                'not_sent': self.not_sent, 'nonfinite_writes': self.nonfinite_writes,
                'force_clamped': self.force_clamped, 'stale_cycles': self.stale_cycles,
                'fault_reads': self.fault_reads,
                'skipped': ws.skipped if ws is not None else 0,
                'partial_sends': ws.partial_sends if ws is not None else 0}

    def values(self) -> dict[str, str]:
        """Counters as diagnostics key/values, with the device and the service session."""
        out = {f'haply_{k}': str(v) for k, v in self.counters().items()}
        out['haply_device_id'] = self.device_id
        out['haply_session_id'] = str(self.session_id)
        return out


def _identity(entry: Any) -> str:
    """``Inverse3 <id> (<type>, hardware 7, firmware 4, right-handed)`` from an inventory
    entry (what of it is there)."""
    cfg = entry.get('config') if isinstance(entry, dict) else None
    cfg = cfg if isinstance(cfg, dict) else {}
    raw = cfg.get('device_info')
    info: dict[str, Any] = raw if isinstance(raw, dict) else {}
    parts = [str(cfg.get('type', 'inverse3'))]
    if 'major_version' in info:
        parts.append(f'version {info.get("major_version")}.{info.get("minor_version")}')
    if 'handedness' in cfg:
        parts.append(f'{cfg["handedness"]}-handed')
    if 'port' in cfg:
        parts.append(f'port {cfg["port"]}')
    return f'Inverse3 {entry.get("device_id")} ({", ".join(parts)})'

