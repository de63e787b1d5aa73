"""Bare rclpy ping-pong of two processes: the baseline for the haptic loop's figures.

``device`` process: a 1 kHz timer publishes ``DeviceState`` (seq, stamp) and receives
``DeviceCommand`` answers; ``echo`` process: answers each state with a command carrying its
``state_seq``, computing nothing. Same messages, QoS (best effort, keep last 1) and executor
(EventsExecutor, ``spin_once(timeout_sec=0.1)``) as the graph, so the ratio of the graph's
figures to these is the cost of our nodes.

Figures, with the device_driver's definitions: answered = the command for state k arrived
before tick k+1; round trip = arrival of that command - publication of state k; period =
time between ticks; CPU = user+system seconds of each process over the run / wall time.

Run: ``.venv/bin/python bench/pingpong.py --duration 30`` (prints one JSON object).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from typing import Any

import numpy as np

from haptic_topology.vocabulary import TOPIC_COMMAND, TOPIC_STATE


def _executor(node: Any, priority: int) -> Any:
    """The graph's executor for ``node``, after putting this process under SCHED_FIFO at
    ``priority`` (0: normal scheduling) as the graph's nodes do."""
    from haptic_topology.device.realtime import set_realtime_priority
    from haptic_topology.nodes.runtime import make_executor

    if priority:
        problem = set_realtime_priority(priority)
        if problem:
            print(problem, file=sys.stderr)
    executor = make_executor('events')
    executor.add_node(node)
    return executor


def _device(duration: float, rate_hz: float, priority: int) -> dict[str, Any]:
    import rclpy
    from rclpy.node import Node

    from haptic_topology.nodes.qos import QOS_LOOP
    from haptic_topology_msgs.msg import DeviceCommand, DeviceState

    rclpy.init()
    node = Node('bench_device')
    pub = node.create_publisher(DeviceState, TOPIC_STATE, QOS_LOOP)
    sent = np.zeros(1 << 20)
    rtt: list[float] = []
    periods: list[float] = []
    st: dict[str, Any] = {'seq': 0, 'answered_seq': 0, 'answered': 0, 'expected': 0,
                          'last': None, 'start': None}
    msg = DeviceState()
    msg.task_dim = 3

    def on_command(cmd: DeviceCommand) -> None:
        now = time.monotonic()
        k = int(cmd.state_seq)
        if 0 < k <= st['seq'] and k > st['answered_seq']:
            rtt.append(now - sent[k % sent.size])
            st['answered_seq'] = k

    def tick() -> None:
        now = time.monotonic()
        if st['last'] is not None:
            periods.append(now - st['last'])
        st['last'] = now
        if st['start'] is None and pub.get_subscription_count() > 0:
            st['start'] = now
        if st['start'] is None:
            return
        if st['seq']:
            st['expected'] += 1
            st['answered'] += int(st['answered_seq'] == st['seq'])
        st['seq'] += 1
        sent[st['seq'] % sent.size] = now
        msg.seq = st['seq']
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)

    node.create_subscription(DeviceCommand, TOPIC_COMMAND, on_command, QOS_LOOP)
    node.create_timer(1.0 / rate_hz, tick)
    executor = _executor(node, priority)
    cpu0 = os.times()
    wall0 = time.monotonic()
    deadline = None
    while rclpy.ok():
        executor.spin_once(timeout_sec=0.1)
        if st['start'] is not None and deadline is None:
            deadline = st['start'] + duration
            periods.clear()
            cpu0 = os.times()
            wall0 = time.monotonic()
        if deadline is not None and time.monotonic() >= deadline:
            break
    cpu1 = os.times()
    wall = time.monotonic() - wall0
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    rclpy.try_shutdown()
    r = np.asarray(rtt) * 1e6
    p = np.asarray(periods) * 1e6
    return {
        'answered_fraction': st['answered'] / max(st['expected'], 1),
        'states': st['seq'],
        'rtt_p50_us': float(np.percentile(r, 50)), 'rtt_p99_us': float(np.percentile(r, 99)),
        'rtt_max_us': float(r.max()),
        'period_p50_us': float(np.percentile(p, 50)),
        'period_p99_us': float(np.percentile(p, 99)), 'period_max_us': float(p.max()),
        'cpu_device': (cpu1.user - cpu0.user + cpu1.system - cpu0.system) / wall,
    }


def _echo(duration: float, priority: int) -> None:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node

    from haptic_topology.nodes.qos import QOS_LOOP
    from haptic_topology_msgs.msg import DeviceCommand, DeviceState

    rclpy.init()
    node = Node('bench_echo')
    pub = node.create_publisher(DeviceCommand, TOPIC_COMMAND, QOS_LOOP)
    cmd = DeviceCommand()
    cmd.task_dim = 3
    cmd.wrench = [0.0, 0.0, 0.0]

    def on_state(msg: DeviceState) -> None:
        cmd.state_seq = msg.seq
        cmd.header.stamp = msg.header.stamp
        pub.publish(cmd)

    node.create_subscription(DeviceState, TOPIC_STATE, on_state, QOS_LOOP)
    executor = _executor(node, priority)
    cpu0 = os.times()
    wall0 = time.monotonic()
    end = wall0 + duration
    try:
        while rclpy.ok() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # the device side is done
    cpu1 = os.times()
    print(json.dumps({'cpu_echo': (cpu1.user - cpu0.user + cpu1.system - cpu0.system)
                      / (time.monotonic() - wall0)}), flush=True)
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    rclpy.try_shutdown()


def run(duration: float = 30.0, rate_hz: float = 1000.0, priority: int = 0,
        echo_priority: int = 0) -> dict[str, Any]:
    """Start the echo process, run the device side here, return the figures.

    ``priority``/``echo_priority``: SCHED_FIFO priorities as the graph's device_driver and
    lmi_controller get them (0: normal scheduling).
    """
    from haptic_topology.nodes.dds_env import localhost_discovery_default

    localhost_discovery_default(os.environ)   # both sides on the nodes' DDS transport
    env = dict(os.environ)
    echo = subprocess.Popen([sys.executable, __file__, '--role', 'echo', '--duration',
                             str(duration + 8.0), '--sched-priority', str(echo_priority)],
                            env=env, stdout=subprocess.PIPE, text=True)
    try:
        figures = _device(duration, rate_hz, priority)
    finally:
        echo.send_signal(signal.SIGINT)
        out, _ = echo.communicate(timeout=20)
    for line in out.splitlines():
        if line.startswith('{'):
            figures.update(json.loads(line))
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--role', choices=('device', 'echo'), default='device')
    ap.add_argument('--duration', type=float, default=30.0)
    ap.add_argument('--rate', type=float, default=1000.0)
    ap.add_argument('--sched-priority', type=int, default=0,
                    help='SCHED_FIFO priority of this process (echo: its own)')
    ap.add_argument('--echo-sched-priority', type=int, default=0)
    a = ap.parse_args()
    if a.role == 'echo':
        _echo(a.duration, a.sched_priority)
    else:
        print(json.dumps(run(a.duration, a.rate, a.sched_priority, a.echo_sched_priority),
                         indent=2))


if __name__ == '__main__':
    main()
