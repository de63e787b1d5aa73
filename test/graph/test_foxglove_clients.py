"""The live view with the clients labs use: a real graph (``run_graph`` with ``foxglove``:
recorder, ve_sim, device_driver and foxglove_bridge as processes) served to

* two Node clients built on ``@foxglove/ws-protocol``'s ``FoxgloveClient`` (what Lichtblick and
  older Foxglove Studio builds use; ``test/foxglove_client/``, installed by scripts/setup.sh
  with ``npm ci``), one offering only ``foxglove.websocket.v1``, one only
  ``foxglove.sdk.v1``, both at once: each must be given the name it offered, see every topic of
  the vocabulary advertised as ``cdr``/``ros2msg``, decode at least one message of every
  channel with ``@foxglove/rosmsg2-serialization`` and none fail;
* and beside them a client that subscribes to every channel and then never reads: the bridge
  drops for it alone and counts it (``/diagnostics``), holds at most ``message_backlog``
  messages for it, and the two good clients' DeviceState messages keep arriving (in the second
  half of their run too).

Only what holds on any machine is asserted (counts, equality, bounds); the loop's figures of
the run are printed (``-s``) for comparison with a run without clients, not asserted.
Without Node.js the test fails saying so (``make test`` sets up the client; ``make demo`` does
not need it).
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO

from haptic_topology import vocabulary as vocab

CLIENT_DIR = REPO / 'test' / 'foxglove_client'
SUBPROTOCOLS = ('foxglove.websocket.v1', 'foxglove.sdk.v1')
#: Seconds each Node client decodes after the first advertise.
CLIENT_SECONDS = 4.0
WAIT = 120.0
BACKLOG = 1024      # config/haptic_topology.yaml foxglove_bridge message_backlog
_CLIENT_STATUS = re.compile(r'(?P<proto>\S+) sent (?P<sent>\d+) dropped (?P<dropped>\d+) '
                            r'waiting (?P<waiting>\d+) peak (?P<peak>\d+)')


def _node() -> str:
    node = shutil.which('node')
    if node is None:
        pytest.fail('node not found: this test runs @foxglove/ws-protocol clients on Node.js '
                    '>= 20 (install Node.js and npm, then make setup-tests)')
    if not (CLIENT_DIR / 'node_modules' / '@foxglove' / 'ws-protocol').is_dir():
        pytest.fail(f'{CLIENT_DIR.relative_to(REPO)}/node_modules is missing: run '
                    'make setup-tests (it runs npm ci there)')
    return node


def _never_reading_client(port: int) -> Any:
    """A client offering foxglove.websocket.v1 that will read nothing once subscribed (a
    receive buffer of a few kB, a queue of one frame)."""
    from websockets.sync.client import connect

    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(('127.0.0.1', port))
    return connect(f'ws://127.0.0.1:{port}', sock=sock, subprotocols=['foxglove.websocket.v1'],
                   max_queue=1, close_timeout=1, ping_interval=None)


def _subscribe_all(ws: Any, deadline: float) -> None:
    """Subscribe ``ws`` to every channel of the vocabulary once advertised."""
    channels: dict[str, int] = {}
    while len(channels) < len(vocab.TOPIC_TYPES):
        assert time.monotonic() < deadline, f'advertised: {sorted(channels)}'
        msg = json.loads(ws.recv(timeout=30))
        if msg['op'] == 'advertise':
            channels.update({c['topic']: c['id'] for c in msg['channels']})
    ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
        {'id': i, 'channelId': cid} for i, cid in enumerate(channels.values())]}))


@pytest.mark.graph
@pytest.mark.timeout(300)
def test_ws_protocol_clients_of_both_names_decode_every_channel_beside_a_slow_client(
        tmp_path: Path) -> None:
    node_exe = _node()
    from bridge_graph import BridgeGraph

    from haptic_topology.bag.graph_trace import read_graph_bag

    bag = tmp_path / 'bag'
    run = BridgeGraph('fig8', 14.0, bag, 'foxglove_clients_test', WAIT)
    bridge, spin_until, deadline = run.bridge, run.spin_until, run.deadline
    stack = contextlib.ExitStack()
    try:
        spin_until(lambda: 'port' in bridge, 'the bridge reports its port')
        port = int(bridge['port'])
        _subscribe_all(stack.enter_context(_never_reading_client(port)), deadline)
        state_key = f'forwarded {vocab.TOPIC_STATE}'
        spin_until(lambda: int(bridge.get(state_key, 0)) > 0, 'the device state flows')
        clients = {p: subprocess.Popen([node_exe, 'client.mjs', f'ws://127.0.0.1:{port}', p,
                                        str(CLIENT_SECONDS)], cwd=CLIENT_DIR, text=True,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                   for p in SUBPROTOCOLS}
        spin_until(lambda: all(c.poll() is not None for c in clients.values()),
                   'the Node clients end')
        reports: dict[str, dict[str, Any]] = {}
        for p, c in clients.items():
            out, err = c.communicate()
            assert c.returncode == 0, f'{p}: node client exited {c.returncode}: {err}'
            reports[p] = json.loads(out)

        def slow_status() -> dict[str, int] | None:
            for key, value in bridge.items():
                m = _CLIENT_STATUS.fullmatch(value)
                if key.startswith('client ') and m and m['proto'] == 'foxglove.websocket.v1':
                    return {k: int(v) for k, v in m.groupdict().items() if k != 'proto'}
            return None

        spin_until(lambda: (slow_status() or {}).get('dropped', 0) > 0,
                   f'the bridge reports drops for the client that never reads ({bridge})')
        status = slow_status()
        assert status is not None
        print(f'\nslow client (never reads): {status}; bridge dropped {bridge["dropped"]}')
        assert status['peak'] <= BACKLOG and status['waiting'] <= BACKLOG
        assert int(bridge['dropped']) >= status['dropped'] > 0

        topics = {('/' + t.lstrip('/')): n for t, n in vocab.TOPIC_TYPES.items()}
        for p, report in reports.items():
            print(f'{p}: decoded {report["decoded"]}; DeviceState per 0.5 s '
                  f'{report["stateBins"]}')
            assert report['subprotocol'] == p
            assert report['errors'] == [], (p, report['errors'])
            assert {t: (c['encoding'], c['schemaEncoding'], c['schemaName'])
                    for t, c in report['channels'].items()} == {
                t: ('cdr', 'ros2msg', n) for t, n in topics.items()}, p
            assert {t: n for t, n in report['decoded'].items() if n < 1} == {}, p
            assert set(report['decodeErrors'].values()) == {0}, p
            assert {'seq', 'pose', 'applied_wrench'} <= set(
                report['firstFields']['/' + vocab.TOPIC_STATE.lstrip('/')]), p
            # DeviceState kept arriving while the slow client was dropped for: in the second
            # half of the client's run too.
            bins = report['stateBins']
            assert sum(bins[int(CLIENT_SECONDS):]) > 0, (p, bins)

        run.join()
        loop = read_graph_bag(bag, 'fig8').loop
        print('loop figures of the run:', {k: loop[k] for k in sorted(loop)})
    finally:
        stack.close()
        run.close()
