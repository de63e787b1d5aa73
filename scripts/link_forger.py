"""A forger on the device link: has the protocol, sees the traffic, not the key.

``python scripts/link_forger.py --iface lab0 --device 10.77.0.2:47001 --out forger.json``
(root: it reads every frame of ``--iface`` with a packet socket). For every COMMAND the driver
sends to the device it sees, it sends to the device from its own socket, with the driver's
session and the NEXT seq, a COMMAND with the wrench :data:`WRENCH`:

* ``unauthenticated``: a version-1 packet (CRC32, no MAC);
* ``own_key``: an authenticated packet made with a key of its own;
* ``tampered``: the seen packet, seq and wrench changed, its MAC and key id kept;

and ``replayed``: every seen packet again, unchanged, 100 ms later. Its own packets (from
its socket's port) it does not take as seen. On SIGINT/SIGTERM (or
after ``--duration``) it writes ``{"seen", "sent": {kind: n}, "wrench"}`` to ``--out``. Used by
``scripts/two_hosts.sh run-device`` with ``HT_FORGER=1``; the device must apply none of it.
"""

from __future__ import annotations

import argparse
import collections
import json
import secrets
import select
import signal
import socket
import struct
import sys
import time
from types import FrameType

from haptic_topology.remote import protocol as P
from haptic_topology.remote.auth import LinkKey

#: The forged wrench (N, N, N m; within the fig8 limits, so clamping cannot hide it).
WRENCH = (7.654321, -6.543210, 0.4321)
ETH_P_IP = 0x0800
REPLAY_AFTER = 0.1


def _udp_payload(frame: bytes, port: int, own_port: int) -> bytes | None:
    """The UDP payload of an Ethernet/IPv4 frame sent to ``port`` from another port than
    ``own_port`` (not one of the forger's own), else None."""
    if len(frame) < 42 or struct.unpack_from('!H', frame, 12)[0] != ETH_P_IP:
        return None
    ihl = (frame[14] & 0x0F) * 4
    if frame[23] != socket.IPPROTO_UDP:
        return None
    udp = 14 + ihl
    src, dst = struct.unpack_from('!HH', frame, udp)
    if dst != port or src == own_port:
        return None
    return frame[udp + 8:]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument('--iface', required=True)
    ap.add_argument('--device', required=True, metavar='HOST:PORT')
    ap.add_argument('--out', required=True)
    ap.add_argument('--duration', type=float, default=3600.0)
    a = ap.parse_args()
    host, _, port_text = a.device.rpartition(':')
    port = int(port_text)
    sniff = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0003))
    sniff.bind((a.iface, 0))
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.bind(('0.0.0.0', 0))
    own_port = out.getsockname()[1]
    own = LinkKey(secrets.token_bytes(32))
    sent = dict.fromkeys(('unauthenticated', 'own_key', 'tampered', 'replayed'), 0)
    seen = 0
    later: collections.deque[tuple[float, bytes]] = collections.deque()
    stop = False

    def on_signal(signum: int, frame: FrameType | None) -> None:
        del signum, frame
        nonlocal stop
        stop = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    end = time.monotonic() + a.duration

    def send(kind: str, data: bytes) -> None:
        try:
            out.sendto(data, (host, port))
            sent[kind] += 1
        except OSError:
            pass

    while not stop and time.monotonic() < end:
        if select.select([sniff], [], [], 0.01)[0]:
            data = _udp_payload(sniff.recv(4096), port, own_port)
            if data is not None and len(data) >= P.HEADER.size and data[:4] == P.MAGIC \
                    and data[5] == int(P.PacketType.COMMAND) and data[8] == 3:
                seen += 1
                session, seq = struct.unpack_from('<IQ', data, 12)
                w = list(WRENCH)
                flags = P.CommandFlags.ENGAGED
                send('unauthenticated', P.encode_command(session, seq + 1, 1, 0, 0, flags,
                                                         10**6, w))
                send('own_key', P.encode_command(session, seq + 1, 1, 0, 0, flags, 10**6, w,
                                                 own, 0))
                if data[4] == P.VERSION_AUTH and len(data) == P.command_size(3, True):
                    t = bytearray(data)
                    struct.pack_into('<Q', t, 16, seq + 1)
                    struct.pack_into('<3d', t, 56, *w)
                    send('tampered', bytes(t))
                later.append((time.monotonic() + REPLAY_AFTER, data))
        now = time.monotonic()
        while later and later[0][0] <= now:
            send('replayed', later.popleft()[1])
    with open(a.out, 'w', encoding='utf-8') as f:
        json.dump({'seen': seen, 'sent': sent, 'wrench': list(WRENCH)}, f)
    return 0


if __name__ == '__main__':
    sys.exit(main())
