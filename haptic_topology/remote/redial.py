"""Reconnecting a WebSocket device link from inside a device cycle: attempts with a bounded
backoff, each one advanced a step per cycle, never waiting (the ``haply`` backend's link to
the Haply Inverse Service, :mod:`haptic_topology.remote.haply`).

:class:`Redial` makes attempts to the address of the connection that ended (no name lookup),
the first :data:`FIRST_DELAY_NS` after the loss, each next one after twice the previous delay,
at most ``max_delay_ns`` apart. An attempt is a non-blocking TCP connect, the opening
handshake (:class:`~haptic_topology.remote.websocket_client.Dialer`) and the service's first
message, all within ``attempt_ns``; one that fails or takes longer is abandoned and the next
one is scheduled. :meth:`Redial.step` costs a comparison while no attempt is under way and a
non-blocking ``select``/``send``/``recv`` while one is.

Example (``max_delay_ns`` 2 s, the service back after 1 s): attempts at 50, 150, 350 and
750 ms fail (refused), the one at 1550 ms succeeds and ``step`` returns the connection with
the service's first message.
"""

from __future__ import annotations

from typing import Any

from haptic_topology.errors import DeviceError
from haptic_topology.remote.websocket_client import Dialer, WebSocketClient

#: Delay (ns) from the loss to the first attempt, doubled after each failed attempt.
FIRST_DELAY_NS = 50_000_000


class Redial:
    """Reconnection attempts to ``address`` (``(family, sockaddr)``) as ``ws://host:port/path``
    (module doc); ``now_ns``: when the connection was lost (monotonic ns, the caller's
    clock)."""

    def __init__(self, address: tuple[int, Any], host: str, port: int, path: str,
                 max_delay_ns: int, attempt_ns: int, now_ns: int) -> None:
        self._target = (address, host, port, path)
        self.max_delay_ns = max_delay_ns
        self.attempt_ns = attempt_ns
        self._delay = min(FIRST_DELAY_NS, max_delay_ns)
        self._at = now_ns + self._delay
        self._until = 0
        self._dialer: Dialer | None = None
        self._client: WebSocketClient | None = None
        #: Attempts started so far.
        self.attempts = 0
        #: Why the newest attempt failed ('' before the first has failed).
        self.error = ''

    def step(self, now_ns: int) -> tuple[WebSocketClient, bytes] | None:
        """Advance without waiting: the open connection and the service's first message once
        an attempt has succeeded, else None."""
        if self._dialer is None and self._client is None:
            if now_ns < self._at:
                return None
            self.attempts += 1
            self._until = now_ns + self.attempt_ns
            address, host, port, path = self._target
            try:
                self._dialer = Dialer(address, host, port, path)
            except DeviceError as exc:
                self.retry_later(str(exc), now_ns)
                return None
        try:
            if self._client is None:
                assert self._dialer is not None
                self._client = self._dialer.step()
                if self._client is None:
                    self._expire(now_ns)
                    return None
                self._dialer = None
            first, _ = self._client.poll()
            if self._client.closed:
                raise DeviceError(f'{self._client.peer}: {self._client.closed} before its '
                                  'first message')
        except DeviceError as exc:
            self.retry_later(str(exc), now_ns)
            return None
        if first is None:
            self._expire(now_ns)
            return None
        client, self._client = self._client, None
        return client, first

    def _expire(self, now_ns: int) -> None:
        if now_ns > self._until:
            self.retry_later(f'no answer within {self.attempt_ns * 1e-6:g} ms', now_ns)

    def retry_later(self, why: str, now_ns: int) -> None:
        """The attempt under way (or the connection just returned, which the caller has
        closed) failed for ``why``: abandon it and schedule the next one (module doc)."""
        self.close()
        self.error = why
        self._delay = min(2 * self._delay, self.max_delay_ns)
        self._at = now_ns + self._delay

    def close(self) -> None:
        """Abandon the attempt under way, if any."""
        if self._dialer is not None:
            self._dialer.close()
            self._dialer = None
        if self._client is not None:
            self._client.close()
            self._client = None
