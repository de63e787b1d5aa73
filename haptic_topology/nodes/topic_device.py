"""``python -m haptic_topology.nodes.topic_device --scenario NAME --options YAML``: the
simulated maglev as a device with a ROS 2 driver (what the ``ros_topics`` backend talks to).

It plays a haptic device whose vendor driver publishes ``geometry_msgs/PoseStamped`` and
``TwistStamped`` (and, with ``wrench_topic``, the hand's force as a ``WrenchStamped``) and
takes ``WrenchStamped`` commands: the physics are the ``sim_maglev`` backend's (eq. 9 with the
scenario's device and simulated user, starting at the VT hand pose at ``q0`` plus the device
offset), run at its own clock (1 / scenario dt
unless ``--rate-hz``) by a :class:`~haptic_topology.device.pacing.DeadlinePacer` in a loop
thread. ``--options`` takes the same mapping as the driver's ``backend_options`` (topics,
``axes``, ``origin``, ``scale``, ``force_scale``, ``torque_scale``, ``qos``, ``command_qos``,
:mod:`haptic_topology.device.topic_mapping`): the player publishes in the device frame and
units those options describe, so the backend's mapping is exercised both ways.

The device is parked until a driver engages it. With ``wrench_topic`` that is the first
non-zero command (the controller sees the hand's wrench on that topic and answers it).
Without it the hand's wrench is never published, as on a device without a force sensor, so
a controller has nothing to answer before the device moves: the simulated hand then pushes
the device from the first command on (the driver commands zero while it idles), and the
controller answers the motion. It prints one line when it serves (what, where) and one
with its counters when it stops.

Per cycle it applies the newest command, mapped to the task, clamped to the scenario's
wrench limit (a real device saturates too), or zero when it is older than
``--command-timeout-ms`` (a device's own command timeout) or not finite. Every command
received is kept (arrival time, raw device values, task values) and written with
``--record PATH`` (``.npz``) at exit; its counters go to ``/diagnostics`` (status
``topic_device: device``) four times a second, so a test can wait on them. Ends on SIGINT or
SIGTERM. The tests (``test/graph/test_topic_backend.py``) run it in its own process; it is also a
way to try the ``ros_topics`` backend without a device (docs/devices.md).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.device.player import DevicePlayer
from haptic_topology.device.topic_mapping import TopicOptions, parse_topic_options
from haptic_topology.errors import HapticTopologyError
from haptic_topology.nodes.dds_env import localhost_discovery_default
from haptic_topology.nodes.device_messages import fill_pose, fill_twist, fill_wrench
from haptic_topology.nodes.diagnostics import diagnostics
from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, topic_qos
from haptic_topology.nodes.runtime import spin
from haptic_topology.vocabulary import STATUS_TOPIC_DEVICE, TOPIC_DIAGNOSTICS

#: ``/diagnostics`` status name of the player.
STATUS_NAME = STATUS_TOPIC_DEVICE
#: The counters of the line printed at the end.
STOP_COUNTERS = ('cycles', 'commands', 'nonzero_commands', 'nonfinite_commands',
                 'timeout_cycles', 'max_abs_command', 'engaged')
#: Frame of the player's messages when ``frame_id`` is not given.
DEVICE_FRAME = 'topic_device_base'


class TopicDevice:
    """The player (module doc) on ``node``: scenario name ``scenario``, options ``opts``,
    ``command_timeout`` (s), ``rate_hz`` (0: 1 / dt)."""

    def __init__(self, node: Node, scenario: str, opts: TopicOptions, command_timeout: float,
                 rate_hz: float = 0.0) -> None:
        from haptic_topology.sim.lockstep import initial_device_pose
        from haptic_topology.sim.scenario import load_scenario

        sc = load_scenario(scenario)
        if sc.linkage.task is not opts.mapping.task:
            raise HapticTopologyError(f'topic_device: scenario {scenario} is '
                                      f'{sc.linkage.task.value}, the options are not')
        self.node = node
        self.opts = opts
        self.mapping = opts.mapping
        self.player = DevicePlayer(BackendConfig(sc.device, initial_device_pose(sc),
                                                 dict(sc.user), {}, sc.source),
                                   round(1e9 * command_timeout), bool(opts.wrench_topic))
        self.limit = self.player.limit
        self.period = 1.0 / rate_hz if rate_hz else sc.dt
        self.frame = opts.frame_id or DEVICE_FRAME
        qos = topic_qos(opts.qos)
        self.pose_pub = node.create_publisher(PoseStamped, opts.pose_topic, qos)
        self.twist_pub = node.create_publisher(TwistStamped, opts.twist_topic, qos)
        self.wrench_pub = (node.create_publisher(WrenchStamped, opts.wrench_topic, qos)
                           if opts.wrench_topic else None)
        node.create_subscription(WrenchStamped, opts.command_topic, self._on_command,
                                 topic_qos(opts.command_qos))
        self.diag_pub = node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        node.create_timer(0.25, self._publish_status)
        self._pose, self._twist, self._wrench = PoseStamped(), TwistStamped(), WrenchStamped()
        for msg in (self._pose, self._twist, self._wrench):
            msg.header.frame_id = self.frame
        self.cmd_t: list[int] = []
        self.cmd_raw: list[list[float]] = []
        self.cmd_task: list[list[float]] = []
        self.frame_mismatches = 0
        self.name = f'{sc.name} ({sc.linkage.task.value})'
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='topic_device', daemon=True)

    def start(self) -> None:
        self._thread.start()

    # -- commands (executor thread) ----------------------------------------------------------
    def _on_command(self, msg: WrenchStamped) -> None:
        now = time.monotonic_ns()
        f, t = msg.wrench.force, msg.wrench.torque
        raw = [f.x, f.y, f.z, t.x, t.y, t.z]
        u = self.mapping.task_command((f.x, f.y, f.z), (t.x, t.y, t.z))
        if msg.header.frame_id != self.frame:
            self.frame_mismatches += 1
        self.cmd_t.append(now)
        self.cmd_raw.append(raw)
        self.cmd_task.append([math.nan] * self.limit.size if u is None else u.tolist())
        self.player.command(now, u)

    # -- the device's own loop (its thread) --------------------------------------------------
    def _run(self) -> None:
        pacer = DeadlinePacer(self.period)
        while not self._stop.is_set():
            tick = pacer.wait()
            reading = self.player.cycle(time.monotonic_ns(), min(tick.dt, 20.0 * self.period))
            self._publish(reading.pose, reading.twist, reading.hand_wrench)

    def _publish(self, pose: np.ndarray, twist: np.ndarray, hand: np.ndarray) -> None:
        ns = time.time_ns()
        self.pose_pub.publish(fill_pose(self._pose, self.mapping, pose, ns))
        self.twist_pub.publish(fill_twist(self._twist, self.mapping, twist, ns))
        if self.wrench_pub is not None:
            self.wrench_pub.publish(fill_wrench(self._wrench, self.mapping, hand, ns))

    # -- status, end -------------------------------------------------------------------------
    def values(self) -> dict[str, str]:
        """The counters (module doc); ``last_command``: the newest command received (task
        values, ``nan`` where not finite) and ``last_command_ns`` its arrival (monotonic ns,
        -1 before the first)."""
        p = self.player
        last = p.newest
        if last is None:
            text = ''
        elif last[1] is None:
            text = ' '.join(['nan'] * self.limit.size)
        else:
            text = ' '.join(repr(float(v)) for v in last[1])
        return {'commands': str(p.commands), 'last_command': text,
                'last_command_ns': str(-1 if last is None else last[0]),
                'nonfinite_commands': str(p.nonfinite_commands),
                'nonzero_commands': str(p.nonzero_commands),
                'frame_mismatches': str(self.frame_mismatches),
                'max_abs_command': ' '.join(f'{v:.6g}' for v in p.max_abs_command),
                'engaged': str(p.engaged).lower(), 'cycles': str(p.cycles),
                'timeout_cycles': str(p.timeout_cycles),
                'pose_subscribers': str(self.pose_pub.get_subscription_count()),
                'command_publishers': str(self.node.count_publishers(self.opts.command_topic))}

    def serving(self) -> str:
        """The line printed at the start: what it serves, on which topics."""
        o = self.opts
        return (f'topic_device: {self.name} at {1.0 / self.period:g} Hz: pose on {o.pose_topic}, '
                f'twist on {o.twist_topic}, commands from {o.command_topic}; ' + (
                    f'hand wrench on {o.wrench_topic}; parked until a non-zero command'
                    if o.wrench_topic else 'no wrench_topic: the hand wrench is not published; '
                    'the simulated hand pushes the device from the first command on'))

    def stopped(self) -> str:
        """The line printed at the end: the counters."""
        v = self.values()
        return 'topic_device: stopped: ' + ', '.join(f'{k} {v[k]}' for k in STOP_COUNTERS)

    def _publish_status(self) -> None:
        self.diag_pub.publish(diagnostics(self.node, STATUS_NAME, self.values(),
                                                 hardware_id='topic_device'))

    def close(self, record: Path | None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if record is not None:
            m = self.limit.size
            np.savez(record, cmd_t=np.array(self.cmd_t, dtype=np.int64),
                     cmd_raw=np.array(self.cmd_raw, dtype=float).reshape(-1, 6),
                     cmd_task=np.array(self.cmd_task, dtype=float).reshape(-1, m),
                     limit=self.limit, cycles=self.player.cycles,
                     timeout_cycles=self.player.timeout_cycles,
                     frame_mismatches=self.frame_mismatches, pid=os.getpid())


def _parse(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='topic_device', description='The simulated maglev as a '
                                     'device with a ROS 2 driver, for the ros_topics backend.')
    parser.add_argument('--scenario', required=True, help='scenario name or YAML file')
    parser.add_argument('--options', required=True,
                        help="the ros_topics backend_options (YAML mapping), e.g. '{pose_topic: "
                        "/dev/pose, twist_topic: /dev/twist, command_topic: /dev/command}'")
    parser.add_argument('--command-timeout-ms', type=float, default=20.0,
                        help='zero output when the newest command is older (ms, default 20)')
    parser.add_argument('--rate-hz', type=float, default=0.0,
                        help='device clock (Hz; default 1 / the scenario dt)')
    parser.add_argument('--record', type=Path, default=None,
                        help='write every command received to this .npz at exit')
    parser.add_argument('--node-name', default='topic_device',
                        help='ROS node name (default topic_device)')
    return parser.parse_args(list(argv))


def main(args: Sequence[str] | None = None) -> int:
    from haptic_topology.sim.scenario import load_scenario

    argv = list(sys.argv[1:] if args is None else args)
    ns = _parse(remove_ros_args(argv))
    try:
        raw = yaml.safe_load(ns.options) or {}
        task = load_scenario(ns.scenario).linkage.task
        opts = parse_topic_options(raw, task)
        if not (0.0 < ns.command_timeout_ms <= 3.6e6):
            raise HapticTopologyError(f'--command-timeout-ms: expected a number in (0, '
                                      f'3600000], got {ns.command_timeout_ms}')
    except (yaml.YAMLError, HapticTopologyError) as exc:
        print(f'topic_device: error: {exc}', file=sys.stderr)
        return 2
    localhost_discovery_default(os.environ)
    rclpy.init(args=argv)
    node = rclpy.create_node(ns.node_name)
    device = TopicDevice(node, ns.scenario, opts, 1e-3 * ns.command_timeout_ms, ns.rate_hz)
    device.start()
    print(device.serving(), flush=True)
    try:
        spin([node], 'events')
    finally:
        device.close(ns.record)
        print(device.stopped(), flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
