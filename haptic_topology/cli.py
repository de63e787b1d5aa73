"""``haptic-topology``: the project's command line.

Subcommands are registered in :data:`COMMANDS`; each is a :class:`Command` with a function that
adds its arguments and a function that runs it and returns the exit status. ``kill -USR1`` of
a running command writes every thread's Python stack to its stderr
(:func:`haptic_topology.processes.stacks_on_signal`), as it does for the node processes.
"""

from __future__ import annotations

import argparse
import importlib.metadata as md
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from haptic_topology import MSGS_PACKAGE_NAME, PACKAGE_NAME, __version__
from haptic_topology.bag import analyze as analyze_command
from haptic_topology.bag import repair as bag_command
from haptic_topology.bag import replay as replay_plan
from haptic_topology.bringup import run as run_command
from haptic_topology.device import devices_command
from haptic_topology.errors import AxesError, HapticTopologyError, VendorLibraryMissing
from haptic_topology.processes import stacks_on_signal
from haptic_topology.remote import server_command as device_server_command
from haptic_topology.sim import command as simulate_command
from haptic_topology.sim import zwidth_command


def _replay(args: argparse.Namespace) -> int:
    """``replay``: the ROS side (:mod:`haptic_topology.nodes.replay`) is imported only when
    the subcommand runs, as the other ROS subcommands import rclpy only then."""
    from haptic_topology.nodes import replay

    return replay.run(args)


@dataclass(frozen=True)
class Command:
    """One subcommand: ``name``, one-line ``help``, argument setup and the function to run."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _dist_version(*names: str) -> str:
    """Version of the first installed distribution among ``names``, or ``'not installed'``."""
    for name in names:
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            continue
    return 'not installed'


def _share_dir(package: str) -> str:
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )
    except ImportError:
        return 'ament_index_python not installed'
    try:
        return str(get_package_share_directory(package))
    except PackageNotFoundError:
        return 'not found on AMENT_PREFIX_PATH'


def _info_arguments(parser: argparse.ArgumentParser) -> None:
    del parser  # no options


def _info(args: argparse.Namespace) -> int:
    """Print versions, share directories and message types; 0 if the messages are usable."""
    del args
    from haptic_topology.messages import definitions as msgdefs

    print(f'haptic_topology {__version__}')
    print(f'python          {sys.version.split()[0]} ({sys.prefix})')
    print(f'rclpy           {_dist_version("ros-jazzy-rclpy", "ros-rclpy", "rclpy")}')
    print(f'pinocchio       {_dist_version("pin", "pinocchio")}')
    print(f'numpy           {_dist_version("numpy")}')
    print(f'rosbags         {_dist_version("rosbags")}')
    print(f'share {PACKAGE_NAME}:      {_share_dir(PACKAGE_NAME)}')
    print(f'share {MSGS_PACKAGE_NAME}: {_share_dir(MSGS_PACKAGE_NAME)}')
    print(f'.msg definitions from: {msgdefs.msg_directory()}')
    try:
        import haptic_topology_msgs.msg as built
    except ImportError as exc:
        built = None
        print(f'built message package: not importable ({exc})')
    for full_name in msgdefs.message_definitions():
        short = full_name.rsplit('/', 1)[-1]
        status = 'built' if built is not None and hasattr(built, short) else 'definition only'
        print(f'  {full_name}  [{status}]')
    return 0


#: Registered subcommands, in the order ``--help`` lists them.
COMMANDS: tuple[Command, ...] = (
    Command('info', 'print versions, share directories and message types', _info_arguments,
            _info),
    Command('simulate', 'offline lock-step simulation of a scenario: trace, plot, summary',
            simulate_command.add_arguments, simulate_command.run),
    Command('zwidth', 'Z-width maps: k_tc x b_tc (and contact stiffness x damping) swept: '
            'passive / stable / unstable, with and without the passivity controller',
            zwidth_command.add_arguments, zwidth_command.run),
    Command('run', 'start the ROS 2 node graph (device, controller, VE, recorder): bag, '
            'summary, loop figures', run_command.add_arguments, run_command.run),
    Command('replay', "publish a bag's messages with their recorded timing; or check the "
            'controller against a recording', replay_plan.add_arguments, _replay),
    Command('analyze', 'drift and loop health of bags and simulate traces: table, plots, '
            'summary.json', analyze_command.add_arguments, analyze_command.run),
    Command('device-server', "serve the simulated maglev over UDP (the network backend's "
            'protocol) at its own clock, in this process', device_server_command.add_arguments,
            device_server_command.run),
    Command('device-key', 'write a new random pre-shared key for an authenticated device link '
            '(mode 0600)', device_server_command.add_key_arguments, device_server_command.run_key),
    Command('devices', 'list the device backends, whether each vendor library loads, and the '
            'devices connected', devices_command.add_arguments, devices_command.run),
    Command('bag', 'bag tools: info, repair (a bag whose recorder was killed)',
            bag_command.add_arguments, bag_command.run),
)


def build_parser(commands: Sequence[Command] = COMMANDS) -> argparse.ArgumentParser:
    """The argument parser with one subparser per entry of ``commands``."""
    parser = argparse.ArgumentParser(
        prog='haptic-topology',
        description='Haptic rendering of topological constraints of serial virtual linkages.',
    )
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for cmd in commands:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is, as Ctrl-C's KeyboardInterrupt."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise _Terminated


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``haptic-topology`` console script; returns the exit status.

    A scenario whose task the device cannot render (:class:`~haptic_topology.errors.AxesError`)
    and a vendor backend whose package or library is missing
    (:class:`~haptic_topology.errors.VendorLibraryMissing`) exit with status 2, any other
    error of the package with 1.
    SIGTERM ends a command as Ctrl-C does (status 143 instead of 130): ``run`` stops its
    nodes and every process deletes its DDS participant (nothing stays in ``/dev/shm``)."""
    args = build_parser().parse_args(argv)
    stacks_on_signal()
    run: Callable[[argparse.Namespace], int] = args._run
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    try:
        return run(args)
    except (AxesError, VendorLibraryMissing) as exc:    # a usage or installation error
        print(f'haptic-topology {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except HapticTopologyError as exc:
        print(f'haptic-topology {args.command}: error: {exc}', file=sys.stderr)
        return 1
    except _Terminated:
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        return 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


if __name__ == '__main__':
    sys.exit(main())
