"""The ``haply`` device backend: a Haply Inverse3 through the Haply Inverse Service's
WebSocket/JSON simulation channel, as Haply documents it for service version 3.5.x
(docs.haply.co, inverseSDK, "WebSocket Protocol" and "Control Commands"; the version this
module follows is :data:`SERVICE_VERSION`). The closed serial protocol between the service
and the device is not used.

(One module of ~650 lines on purpose: the options, the lifecycle, the per-cycle path, the
reconnection and the counters share the connection's state and are read together; its vendor
registry entry is at the end.)

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
  ones are counted, ``skipped``, and never used, valid or not) and returns it. A state is
  normally the answer to the previous cycle's command: one cycle old.

**Never force from bad or stale data.** A reading carries ``DeviceStatus.FAULT`` (the driver
then writes zero from the next cycle on and fades back in when it clears) while the newest
state is older than ``stale_ms``, the newest message is not a valid state of the device (not
JSON, fields missing, NaN/inf), the device is missing from it (unplugged), or the connection
has ended (service stopped); :meth:`HaplyBackend.fault_reason` says which, naming the
address. A faulted reading repeats the newest valid position with zero velocity.

**A lost connection** (the service stopped, crashed or restarted) is a FAULT that stands
until the user grasps again; meanwhile the backend reconnects:

1. the cycle that finds the connection ended reads FAULT (``the connection to ... ended
   (...); reconnecting``); the driver writes zero from the next cycle on;
2. each cycle then advances the reconnection without waiting
   (:class:`~haptic_topology.remote.redial.Redial`: to the address of the connection lost,
   attempts 50 ms after the loss and then after twice the previous delay, at most
   ``reconnect_max_ms`` apart, each abandoned after ``connect_timeout_ms``), FAULT all
   along with the newest attempt's failure in the reason;
3. once the service answers again with the same device in its inventory, the backend sends
   it a zero force (a new session), the link is up again (``haply_link``:
   ``up, waiting for a re-engage``; ``haply_reconnects`` counts it) and the reading is still
   FAULT, its reason saying what to do: the hand was let go
   (:meth:`~haptic_topology.device.vendor.VendorHand.release`), so no force resumes by
   itself;
4. the user grasps again deliberately, on the states that came after the reconnection: the
   engage button released and pressed again (or the clutch pressed and released); the
   reading is then no longer FAULT, the position goes on from where it stayed, the force
   fades in over ``grasp_ramp_ms`` (and the driver's watchdog ramp). With neither button
   configured the FAULT stands until the next activation.

``reconnect_max_ms: 0`` turns the reconnection off: the run goes on at zero force with the
fault, and the next activation connects again.

**Lifecycle.** ``configure`` checks the options (no I/O). ``preflight`` (``run``, before any
node starts) connects, takes the inventory and chooses the device, then closes without a
command. ``activate`` connects (at most ``connect_timeout_ms``; a refused connection fails at
once, naming the address), takes the inventory, chooses the device (``device_id``, or the
only Inverse3), sends a zero force and waits for its answer. ``deactivate`` sends a zero
force (always, whatever ``max_in_flight`` says), waits for its answer (at most 0.2 s) and
closes the connection; the service's device then returns to idle. The identity
(:class:`~haptic_topology.device.vendor.DeviceIdentity`: Haply, the model from the
inventory's ``config.type``, the device id as serial) is in :attr:`HaplyBackend.hardware_id`
and the diagnostics values.

**Frames and units.** Task vectors of a point grasp only (``planar_point``: x, y;
``spatial_point``: x, y, z): the Inverse3 senses and actuates three translations, no rotation
(:data:`~haptic_topology.device.backend.TRANSLATION_AXES`). The mapping, the grasp and clutch
buttons and the fade-in of the force at each grasp are the shared vendor layer's
(:class:`~haptic_topology.device.vendor.VendorHand`, options ``axes``, ``origin``, ``scale``,
``force_scale``, ``engage_button``, ``clutch_button``, ``grasp_ramp_ms``): by default the
handle's position at activation is the scenario's initial pose and the force fades in over
50 ms. Buttons: the service reports none for the Inverse3 itself; the handle's buttons are
those of a VerseGrip, a device of its own in the protocol (``verse_grip``: ``button``, bit 0;
``wireless_verse_grip``: ``buttons.a``, bit 0, ``buttons.b``, bit 1), read from the grip
``grip_id`` (default: the first one the service lists; none: no buttons held). The device
force is then clamped to ``max_force`` (norm). The Inverse3 has no force sensor: the hand
wrench is reported as zero and the controller sees the hand through the motion.

Options (``backend_options``; every one optional): the vendor layer's
(:data:`~haptic_topology.device.vendor.VENDOR_OPTIONS`) and ``host`` (127.0.0.1), ``port``
(10001), ``path`` (``/``), ``device_id`` (the only Inverse3), ``grip_id`` (the first
VerseGrip), ``max_force`` (N, norm; default 10), ``stale_ms`` (20), ``connect_timeout_ms``
(2000), ``max_in_flight`` (4), ``reconnect_max_ms`` (2000; 0: no reconnection), ``profile``
(the session profile name). A bad one is refused naming it.
"""

from __future__ import annotations

import json
import math
import os
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
from haptic_topology.device.topic_mapping import option_error
from haptic_topology.device.vendor import (
    DeviceIdentity,
    VendorHand,
    VendorSupport,
    parse_vendor_options,
)
from haptic_topology.errors import DeviceError
from haptic_topology.remote.redial import Redial
from haptic_topology.remote.websocket_client import WebSocketClient, connect
from haptic_topology.vocabulary import DeviceStatus

#: The Haply Inverse Service version whose documented protocol this backend follows.
SERVICE_VERSION = '3.5.x'
#: The service's default simulation-channel port.
DEFAULT_PORT = 10001
#: Where ``haptic-topology devices`` looks for the service (``host:port``).
SERVICE_VARIABLE = 'HAPLY_INVERSE_SERVICE'
#: The backend's own options and their defaults (module doc); the vendor layer's come on top.
OWN_OPTIONS: dict[str, Any] = {
    'host': '127.0.0.1', 'port': DEFAULT_PORT, 'path': '/', 'device_id': '', 'grip_id': '',
    'max_force': 10.0, 'stale_ms': 20.0, 'connect_timeout_ms': 2000.0, 'max_in_flight': 4,
    'reconnect_max_ms': 2000.0, 'profile': 'haptic_topology',
}
NAME = 'haply'
_FAULT = DeviceStatus.FAULT
#: How long ``deactivate`` may wait for the answer to its zero force (s).
_RELEASE_WAIT = 0.2


def _number(opts: Mapping[str, Any], key: str, lo: float, hi: float) -> float:
    value = opts[key]
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not (math.isfinite(value) and lo < value <= hi)):
        raise option_error(key, f'a number in ({lo:g}, {hi:g}]', value, NAME)
    return float(value)


def _text(opts: Mapping[str, Any], key: str) -> str:
    value = opts[key]
    if not isinstance(value, str):
        raise option_error(key, 'text', value, NAME)
    return value


def _buttons(data: Mapping[str, Any], grip_id: str) -> int:
    """The button mask of the VerseGrip ``grip_id`` (''': the first listed) in a state
    message: wired ``button`` bit 0; wireless ``buttons.a`` bit 0, ``buttons.b`` bit 1."""
    for kind in ('wireless_verse_grip', 'verse_grip'):
        grips = data.get(kind)
        if not isinstance(grips, list):
            continue
        for g in grips:
            if not isinstance(g, dict) or (grip_id and str(g.get('device_id')) != grip_id):
                continue
            st = g.get('state')
            if not isinstance(st, dict):
                return 0
            b = st.get('buttons')
            if isinstance(b, dict):
                return int(bool(b.get('a'))) | int(bool(b.get('b'))) << 1
            return int(bool(st.get('button')))
    return 0


class HaplyBackend(DeviceBackend):
    """A Haply Inverse3 through the Inverse Service (module doc). ``clock_ns``: monotonic
    clock (ns) for the staleness (tests inject one)."""

    name = NAME
    lockstep = False            # the device runs on its own clock

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock_ns = clock_ns
        self._m = 0
        self._ws: WebSocketClient | None = None
        self._hand: VendorHand | None = None
        self._first = True
        self._fresh_start = False
        self._pos = (0.0, 0.0, 0.0)
        self._vel = (0.0, 0.0, 0.0)
        self._buttons = 0
        self._state_ns = 0
        self._last: DeviceReading | None = None
        self._bad = ''
        self._reason = ''
        self.device_id = ''
        self.identity: DeviceIdentity | None = None
        self.session_id: Any = None
        self.peer = ''
        self._sent = 0
        self._answers = 0
        self._redial: Redial | None = None
        self._rejoin = False             # reconnected; the hand waits for a re-grasp
        self._rejoin_states = 0          # self.states at the reconnection
        self._lost = ''                  # why the newest connection ended
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
        self.reconnects = 0
        self.reconnect_attempts = 0      # of the reconnections finished

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        """The Inverse3 senses and actuates forces along x, y, z only: point tasks."""
        del options
        return TRANSLATION_AXES

    # -- configuration -----------------------------------------------------------------------
    def configure(self, config: BackendConfig) -> None:
        self._vendor, opts = parse_vendor_options(config.options, NAME, config.params.task,
                                                  OWN_OPTIONS)
        self.host = _text(opts, 'host')
        port = opts['port']
        if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
            raise option_error('port', 'an integer port in [1, 65535]', port, NAME)
        self.port = port
        self.path = _text(opts, 'path')
        if not self.path.startswith('/'):
            raise option_error('path', 'a path starting with /', self.path, NAME)
        self.wanted_id = _text(opts, 'device_id')
        self.grip_id = _text(opts, 'grip_id')
        self.profile = _text(opts, 'profile')
        self.max_force = _number(opts, 'max_force', 0.0, 1000.0)
        self.stale_ns = round(1e6 * _number(opts, 'stale_ms', 0.0, 10_000.0))
        self.connect_timeout = 1e-3 * _number(opts, 'connect_timeout_ms', 0.0, 600_000.0)
        n = opts['max_in_flight']
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 64:
            raise option_error('max_in_flight', 'an integer in [1, 64]', n, NAME)
        self.max_in_flight = n
        r = opts['reconnect_max_ms']
        if isinstance(r, bool) or r != 0:
            r = _number(opts, 'reconnect_max_ms', 0.0, 600_000.0)
        self.redial_max_ns = round(1e6 * r)
        self._m = self.keep_task(config).dim
        self._start_pose = np.asarray(config.initial_pose, dtype=float)[:self._m].copy()
        self.peer = f'ws://{self.host}:{self.port}{self.path}'

    @property
    def hardware_id(self) -> str:
        if not self._m:
            return self.name
        if self.identity is None:
            return f'{self.name} {self.peer}'
        return f'{self.identity.hardware_id(self.name)} via {self.peer}'

    def fault_reason(self) -> str:
        return self._reason or f'{self.name}: the device reports a fault'

    # -- lifecycle ---------------------------------------------------------------------------
    def preflight(self, config: BackendConfig) -> None:
        """Connect, take the inventory, choose the device; close without a command (the
        device's output is never touched)."""
        self.configure(config)
        start = time.monotonic()
        ws = self._connect()
        try:
            self._choose(ws, start)
        finally:
            ws.close()

    def _connect(self) -> WebSocketClient:
        try:
            return connect(self.host, self.port, self.path, self.connect_timeout)
        except DeviceError as exc:
            raise DeviceError(f'haply: {exc}: is the Haply Inverse Service (or '
                              '`python -m haptic_topology.remote.haply_emulator`) running '
                              'there?') from None

    def activate(self) -> None:
        self.task_dim()
        if self._ws is not None:
            return
        start = time.monotonic()
        self._ws = self._connect()
        try:
            self._start(self._ws, start)
        except DeviceError:
            self._close()
            raise

    def _left(self, start: float) -> float:
        return max(0.0, self.connect_timeout - (time.monotonic() - start))

    def _choose(self, ws: WebSocketClient, start: float) -> None:
        """Take the inventory and choose the device (module doc)."""
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
        elif ids:
            raise DeviceError(f'haply: {len(ids)} Inverse3 devices at {self.peer} '
                              f'({", ".join(ids)}): choose one with backend_options.device_id')
        else:
            raise DeviceError(f'haply: no Inverse3 at {self.peer}: is it plugged in and '
                              'powered?')
        self.device_id = chosen
        self.session_id = inventory.get('session_id')
        self.identity = identity(devices[ids.index(chosen)])

    def _start(self, ws: WebSocketClient, start: float) -> None:
        self._choose(ws, start)
        head = json.dumps({'device_id': self.device_id}, separators=(',', ':'))[:-1]
        self._prefix = ('{"inverse3":[' + head + ',"commands":{"set_cursor_force":{"vector":'
                        ).encode()
        self._suffix = b'}}}]}'
        self._session = (',"session":{"configure":{"profile":{"name":'
                         + json.dumps(self.profile) + '}}}').encode()
        self._first = True
        self._sent = self._answers = 0
        self._state_ns = 0
        self._bad = self._reason = ''
        self._hand = VendorHand(self._vendor, self._start_pose)
        self._last = None
        self._rejoin = False
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
        self._fresh_start = True

    def deactivate(self) -> None:
        ws = self._ws
        if ws is None:
            return
        if not ws.closed:
            # A zero force, and the service's answer to it (and to every command before it):
            # the service has applied it before the connection closes (a message still
            # queued at the service when it closes may never be read).
            self._send((0.0, 0.0, 0.0), force=True)
            deadline = time.monotonic() + _RELEASE_WAIT
            while not ws.closed:
                self._answers += ws.poll()[1]
                left = deadline - time.monotonic()
                if self._answers >= self._sent or left <= 0.0:
                    break
                ws.wait(left)
        self._close()

    def _close(self) -> None:
        if self._redial is not None:
            self.reconnect_attempts += self._redial.attempts
            self._redial.close()
            self._redial = None
        if self._ws is not None:
            self._ws.close()
            self._ws = None

    # -- cycle -------------------------------------------------------------------------------
    def _send(self, f_dev: Sequence[float], force: bool = False) -> None:
        ws = self._ws
        assert ws is not None
        if ws.closed:
            self.not_sent += 1
            return
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
        if self._ws is None or self._hand is None:
            raise DeviceError('haply: write() before activate()')
        w = np.asarray(wrench, dtype=float)
        if w.shape != (self._m,):
            raise DeviceError(f'haply: write(): expected {self._m} force values, got shape '
                              f'{w.shape}')
        if not np.all(np.isfinite(w)):
            self.nonfinite_writes += 1
            w = np.where(np.isfinite(w), w, 0.0)
        x, y, z = self._hand.force(w, self.max_force)
        if self._hand.clamped:
            self.force_clamped += 1
        self._send((x, y, z))

    def written(self, wrench: np.ndarray) -> np.ndarray:
        """What the newest ``write`` sent, in task terms (``VendorHand.sent``: zero while the
        hand does not grasp, faded, limited by ``max_force``): the trace's ``applied``."""
        return wrench if self._hand is None else self._hand.sent

    def read(self, dt: float) -> DeviceReading:
        ws = self._ws
        if ws is None or self._hand is None:
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
        return self._reading(now, ws, dt)

    def _take(self, msg: bytes, now: int) -> None:
        """Decode one state message; keep its position, velocity and buttons if valid."""
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
        self._pos, self._vel = pos, vel
        self._buttons = _buttons(data, self.grip_id)
        self._state_ns = now
        self._bad = ''
        self.states += 1

    def _reading(self, now: int, ws: WebSocketClient, dt: float) -> DeviceReading:
        hand = self._hand
        assert hand is not None
        age = now - self._state_ns
        if ws.closed:
            self._reason = self._reconnect(now, ws)
        elif self._bad:
            self._reason = f'haply: {self._bad}'
        elif age > self.stale_ns:
            self.stale_cycles += 1
            self._reason = (f'haply: no state from {self.peer} for {age * 1e-6:.1f} ms '
                            f'(stale_ms {self.stale_ns * 1e-6:g}): the service is stalled or '
                            'stopped')
        elif not self._rejoin:
            self._last = hand.reading(self._pos, self._vel, self._buttons, dt)
            return self._last
        elif self.states == self._rejoin_states:
            self._reason = (f'haply: reconnected to {self.peer} after {self._lost}: waiting '
                            'for its first state')
        else:
            # Reconnected: the buttons of the states since then decide (module doc, 4.).
            self._last = hand.reading(self._pos, self._vel, self._buttons, dt)
            if hand.grasping:
                self._rejoin = False
                return self._last
            self._reason = (f'haply: reconnected to {self.peer} after {self._lost}: '
                            f'{hand.regrasp_hint()}')
        self.fault_reads += 1
        m = self._m
        pose = self._last.pose if self._last is not None else self._start_pose.copy()
        return DeviceReading(pose, np.zeros(m), np.zeros(m), _FAULT)

    def _reconnect(self, now: int, ws: WebSocketClient) -> str:
        """The fault reason of a cycle with the connection ``ws`` ended, after advancing the
        reconnection (module doc, "A lost connection")."""
        ended = f'haply: the connection to {self.peer} ended ({ws.closed})'
        redial = self._redial
        if redial is None:
            self._lost = f'the connection ended ({ws.closed})'
            if not self.redial_max_ns or ws.address is None:
                return ended
            redial = self._redial = Redial(ws.address, self.host, self.port, self.path,
                                           self.redial_max_ns,
                                           round(1e9 * self.connect_timeout), now)
        got = redial.step(now)
        if got is not None:
            client, first = got
            try:
                ids = [str(d['device_id']) for d in json.loads(first)['inverse3']]
            except (ValueError, KeyError, TypeError):
                ids = None
            if ids is not None and self.device_id in ids:
                self._resume(client, now)
                return (f'haply: reconnected to {self.peer} after {self._lost}: waiting for '
                        'its first state')
            client.close()
            redial.retry_later(f'the Inverse3 {self.device_id} is not in the inventory '
                               f'(it has {", ".join(ids) or "none"})' if ids is not None
                               else f'no inventory: {first[:80]!r}', now)
        n = redial.attempts
        return f'{ended}; reconnecting' + (
            f' ({n} attempt{"s" * (n > 1)}, the newest: {redial.error})' if redial.error else '')

    def _resume(self, client: WebSocketClient, now: int) -> None:
        """Take the new connection ``client``: a new session, a zero force, the hand let go
        (module doc, "A lost connection", 3.)."""
        assert self._ws is not None and self._redial is not None and self._hand is not None
        self.reconnect_attempts += self._redial.attempts
        self._redial = None
        self._ws.close()
        self._ws = client
        self._first = True
        self._sent = self._answers = 0
        self._bad = ''
        self._state_ns = now                 # staleness counts from the reconnection
        self._hand.release()
        self._rejoin = True
        self._rejoin_states = self.states
        self.reconnects += 1
        self._send((0.0, 0.0, 0.0), force=True)

    # -- figures -----------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Counts so far (module doc)."""
        ws = self._ws
        return {'states': self.states, 'malformed': self.malformed,
                'nonfinite': self.nonfinite, 'device_missing': self.device_missing,
                'commands_sent': self._sent, 'throttled': self.throttled,
                'not_sent': self.not_sent, 'nonfinite_writes': self.nonfinite_writes,
                'force_clamped': self.force_clamped, 'stale_cycles': self.stale_cycles,
                'fault_reads': self.fault_reads, 'reconnects': self.reconnects,
                'reconnect_attempts': self.reconnect_attempts,
                'skipped': ws.skipped if ws is not None else 0,
                'partial_sends': ws.partial_sends if ws is not None else 0}

    def link(self) -> str:
        """The link to the service: ``up``, ``up, waiting for a re-engage`` (reconnected,
        module doc), ``down, reconnecting: <why the newest attempt failed>``, ``down`` (not
        reconnecting) or ``closed`` (not active)."""
        ws, redial = self._ws, self._redial
        if ws is None:
            return 'closed'
        if ws.closed:
            if redial is None:
                return 'down'
            return 'down, reconnecting' + (f': {redial.error}' if redial.error else '')
        return 'up, waiting for a re-engage' if self._rejoin else 'up'

    def values(self) -> dict[str, str]:
        """Counters, the device's identity, the grasp, the service session (diagnostics)."""
        out = {f'haply_{k}': str(v) for k, v in self.counters().items()}
        out['haply_session_id'] = str(self.session_id)
        out['haply_link'] = self.link()
        if self.identity is not None:
            out.update(self.identity.values())
        if self._hand is not None:
            out.update(self._hand.values())
        return out


def identity(entry: Any) -> DeviceIdentity:
    """The :class:`~haptic_topology.device.vendor.DeviceIdentity` of an inventory entry: Haply,
    the model from ``config.type`` (``inverse3`` -> ``Inverse3``) with its device_info
    version and handedness, the device id as serial, the protocol as SDK."""
    cfg = entry.get('config') if isinstance(entry, dict) else None
    cfg = cfg if isinstance(cfg, dict) else {}
    raw = cfg.get('device_info')
    info: dict[str, Any] = raw if isinstance(raw, dict) else {}
    kind = str(cfg.get('type', 'inverse3'))
    model = {'inverse3': 'Inverse3', 'inverse3x': 'Inverse3x', 'minverse': 'Minverse'}.get(
        kind, kind)
    more = []
    if 'major_version' in info:
        more.append(f'version {info.get("major_version")}.{info.get("minor_version")}')
    if 'handedness' in cfg:
        more.append(f'{cfg["handedness"]}-handed')
    if 'port' in cfg:
        more.append(f'port {cfg["port"]}')
    if more:
        model += f' ({", ".join(more)})'
    return DeviceIdentity('Haply', model, str(entry.get('device_id', '')),
                          f'Inverse Service protocol {SERVICE_VERSION}')


def vendor_support() -> VendorSupport:
    """The ``haply`` entry of the vendor registry
    (:data:`~haptic_topology.device.vendor.VENDOR_BACKENDS`, for ``haptic-topology
    devices``): no vendor library to load (the protocol is built in); its devices are the
    Inverse3 devices in the inventory of the service at ``$HAPLY_INVERSE_SERVICE``
    (``host:port``, default ``127.0.0.1:10001``)."""
    def where() -> tuple[str, int]:
        text = os.environ.get(SERVICE_VARIABLE, '') or f'127.0.0.1:{DEFAULT_PORT}'
        host, _, port = text.rpartition(':')
        if not host or not port.isdigit():
            raise DeviceError(f'haply: {SERVICE_VARIABLE}: expected host:port, got {text!r}')
        return host, int(port)

    def load() -> str:
        host, port = where()
        return (f'no library needed: the Inverse Service protocol {SERVICE_VERSION} at '
                f'ws://{host}:{port}/')

    def devices() -> list[str]:
        host, port = where()
        ws = connect(host, port, '/', 2.0)
        try:
            first = ws.wait_text(2.0)
        finally:
            ws.close()
        try:
            entries = json.loads(first or b'')['inverse3']
            return [identity(e).hardware_id('Haply') for e in entries]
        except (ValueError, KeyError, TypeError):
            raise DeviceError(f'haply: no inventory from ws://{host}:{port}/') from None

    return VendorSupport(NAME, 'haptic_topology (built in)',
                         f'the Haply Inverse Service {SERVICE_VERSION}', SERVICE_VARIABLE,
                         load, devices)
