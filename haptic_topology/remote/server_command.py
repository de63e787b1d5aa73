"""``haptic-topology device-server --scenario NAME [--host H] [--port P] ...``.

Serves the scenario's simulated maglev over the device network protocol
(:mod:`haptic_topology.remote.protocol`) at its own clock, in this process, until SIGINT or
SIGTERM (or ``--duration``); then zeroes the output, closes the socket and prints one line
with its counters. Point ``device_driver`` at it with ``backend: network`` and
``backend_options: '{host: H, port: P}'``.

``--ready-file PATH``: once the socket is bound, a JSON object ``{host, port, pid, session,
task_dim, period}`` is written there (atomically: written beside it, then renamed), so a
program that started the server with ``--port 0`` learns the port without reading its output.
``--log PATH`` (CSV, one row per cycle: ``t_ns, applied_session, applied_seq, u0..,
status``) and ``--summary PATH`` (JSON of the counters) are written at shutdown.
``--monitor HOST:PORT``: a copy of every cycle's STATE goes there (an observer of what the
device applies, e.g. a test).

``--key-file PATH``: the link's pre-shared key (:mod:`haptic_topology.remote.auth`; the
driver's ``backend_options`` ``key_file`` names a copy of the same file): every packet is
authenticated and whatever fails the MAC is counted and dropped. Serving on an address other
than loopback without a key is refused unless ``--trusted-network`` is given. The ready file
and the output line say which (``link``).

``haptic-topology device-key PATH`` writes a new random key to ``PATH`` (mode 0600).

Also runnable as ``python -m haptic_topology.remote.server_command``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

from haptic_topology.errors import HapticTopologyError
from haptic_topology.paths import scenario_help
from haptic_topology.remote.protocol import DEFAULT_PORT

#: Cycles kept in the ``--log`` by default (10 min at 1 kHz).
DEFAULT_LOG_CYCLES = 600_000


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected an integer port in [0, 65535], got '
                                         f'{text!r}') from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f'expected an integer port in [0, 65535], got {value}')
    return value


def _positive_ms(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number of ms > 0, got {text!r}') from None
    if not 0.0 < value <= 3.6e6:
        raise argparse.ArgumentTypeError(f'expected a number of ms in (0, 3600000], got '
                                         f'{value}')
    return value


def _address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(':')
    if not sep or not host:
        raise argparse.ArgumentTypeError(f'expected HOST:PORT, got {text!r}')
    try:
        return host.strip('[]'), _port(port)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f'{text!r}: {exc}') from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--scenario', required=True,
                        help=scenario_help('a YAML file') + ': device model, limits, initial '
                        'pose and simulated user')
    parser.add_argument('--host', default='127.0.0.1',
                        help='address to serve on (default 127.0.0.1; 0.0.0.0: every IPv4 '
                        'interface)')
    parser.add_argument('--port', type=_port, default=DEFAULT_PORT,
                        help=f'UDP port (default {DEFAULT_PORT}; 0: any free one, see '
                        '--ready-file)')
    parser.add_argument('--rate-hz', type=float, default=0.0,
                        help='device clock (Hz); default 0 = 1 / the scenario dt')
    parser.add_argument('--command-timeout-ms', type=_positive_ms, default=20.0,
                        help='zero output when no valid command came for this long (ms, '
                        'default 20)')
    parser.add_argument('--takeover-after-ms', type=_positive_ms, default=500.0,
                        help='another client session is followed once the followed one has '
                        'been silent this long (ms, default 500)')
    parser.add_argument('--forget-after-ms', type=_positive_ms, default=2000.0,
                        help='stop sending states to a client silent this long (ms, default '
                        '2000)')
    parser.add_argument('--duration', type=float, default=0.0,
                        help='stop after this many seconds (default 0: until SIGINT/SIGTERM)')
    parser.add_argument('--ready-file', type=Path,
                        help='write {host, port, pid, session, task_dim, period} as JSON here '
                        'once serving')
    parser.add_argument('--log', type=Path,
                        help='write the applied wrench of every cycle here at shutdown (CSV)')
    parser.add_argument('--log-cycles', type=int, default=DEFAULT_LOG_CYCLES,
                        help=f'cycles kept for --log (default {DEFAULT_LOG_CYCLES})')
    parser.add_argument('--summary', type=Path,
                        help='write the counters here at shutdown (JSON)')
    parser.add_argument('--monitor', type=_address, metavar='HOST:PORT',
                        help='send a copy of every cycle\'s STATE here (an observer)')
    parser.add_argument('--key-file', type=Path, metavar='PATH',
                        help='pre-shared key of the link (hex, mode 0600; `haptic-topology '
                        'device-key PATH` makes one): every packet carries a MAC')
    parser.add_argument('--trusted-network', action='store_true',
                        help='serve without a key on an address other than loopback (anyone '
                        'who can reach the port can then move the device)')


def add_key_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('path', type=Path, help='file to create (refused if it exists)')


def run_key(args: argparse.Namespace) -> int:
    """``haptic-topology device-key PATH``: a new random key, mode 0600."""
    from haptic_topology.remote.auth import write_key

    key = write_key(args.path)
    print(f'device-key: wrote a new key to {args.path} (mode 0600, key id {key.key_id:08x}); '
          'copy it to the other computer with the same mode', flush=True)
    return 0


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    tmp.write_text(text, encoding='utf-8')
    os.replace(tmp, path)


def run(args: argparse.Namespace) -> int:
    """Serve until stopped; errors surface as HapticTopologyError."""
    from haptic_topology.remote.server import DeviceServer, ServerConfig
    from haptic_topology.sim.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    key = None
    if args.key_file is not None:
        from haptic_topology.remote.auth import load_key

        key = load_key(args.key_file)
    cfg = ServerConfig(host=args.host, port=args.port, rate_hz=args.rate_hz,
                       command_timeout=1e-3 * args.command_timeout_ms,
                       takeover_after=1e-3 * args.takeover_after_ms,
                       forget_after=1e-3 * args.forget_after_ms, duration=args.duration,
                       log_cycles=args.log_cycles if args.log else 0, monitor=args.monitor,
                       key=key, trusted_network=args.trusted_network)
    server = DeviceServer(scenario, cfg)
    stop = False

    def on_signal(signum: int, frame: FrameType | None) -> None:
        del signum, frame
        nonlocal stop
        stop = True

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        if args.ready_file:
            _write_atomic(args.ready_file, json.dumps({
                'host': server.host, 'port': server.port, 'pid': os.getpid(),
                'session': server.session, 'task_dim': server.m, 'period': server.period,
                'link': server.link}))
        print(f'device-server: serving {scenario.name} (m = {server.m}) on '
              f'{server.host}:{server.port} at {1.0 / server.period:g} Hz, link '
              f'{server.link}', flush=True)
        server.serve(lambda: stop)
    finally:
        server.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        if args.log:
            server.write_log(args.log)
        if args.summary:
            _write_atomic(args.summary, json.dumps(server.counters(), indent=1) + '\n')
        print(server.summary_line(), flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m haptic_topology.remote.server_command``: as the CLI subcommand."""
    parser = argparse.ArgumentParser(prog='haptic-topology device-server',
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except HapticTopologyError as exc:
        print(f'haptic-topology device-server: error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
