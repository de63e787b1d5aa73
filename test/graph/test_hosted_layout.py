"""The hosted layout (device_driver runs lmi_controller in its loop thread) against real
processes: well-formed commands from another publisher on DDS never reach the device.

An impostor answers every running state of the hosted driver with a plausible command of
(1000, -1000, 1000) (N, N, N m; mode penalty, the state's own seq) as soon as it sees the
state. Had one been applied, the device would have clamped it to (+l_x, -l_y, +l_z) of its
limit l, faded by the watchdog at most, so the applied wrench would be s * (l_x, -l_y, l_z)
for some s > 0: a pattern the controller's own commands do not produce (they may saturate
one axis now and then on a loaded machine, the three in exactly that ratio never). In the
hosted layout the driver takes no commands from DDS, so no state shows it. Every wait is on
messages, with a deadline; nothing is timed.
"""

from __future__ import annotations

import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest
from procs import stop_process

from haptic_topology.paths import config_dir
from haptic_topology.sim.scenario import load_scenario

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
WAIT = 60.0           # s: generous, a loaded machine is only slower


def _start(name: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', f'haptic_topology.nodes.{name}', '--ros-args', '--params-file',
         str(PARAMS), '-p', 'scenario:=circle'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)


def test_commands_from_dds_never_reach_the_hosted_device() -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from haptic_topology.nodes.qos import QOS_LOOP
    from haptic_topology.vocabulary import TOPIC_COMMAND, TOPIC_STATE
    from haptic_topology_msgs.msg import DeviceCommand, DeviceState

    limit = load_scenario('circle').device.wrench_limit
    procs = [_start('ve_sim'), _start('device_driver')]
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('impostor', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    states: list[Any] = []
    sent: list[int] = []
    attack = [False]
    pub = node.create_publisher(DeviceCommand, TOPIC_COMMAND, QOS_LOOP)

    def on_state(msg: Any) -> None:
        states.append(msg)
        if attack[0] and not msg.status & DeviceState.STATUS_IDLE:
            cmd = DeviceCommand(state_seq=msg.seq, mode=DeviceCommand.MODE_PENALTY,
                                task_dim=3, wrench=[1e3, -1e3, 1e3], vt_pose=list(msg.pose),
                                vt_twist=[0.0] * 3, update_age=0.0)
            cmd.header.stamp = msg.header.stamp
            pub.publish(cmd)
            sent.append(msg.seq)

    node.create_subscription(DeviceState, TOPIC_STATE, on_state, QOS_LOOP)

    def running() -> list[Any]:
        return [s for s in states if not s.status & DeviceState.STATUS_IDLE]

    def wait(cond: Any, what: str) -> None:
        deadline = time.monotonic() + WAIT
        while not cond():
            for p in procs:
                assert p.poll() is None, f'{what}: a node died:\n{stop_process(p)[1][-3000:]}'
            assert time.monotonic() < deadline, f'{what}: not within {WAIT:g} s'
            executor.spin_once(timeout_sec=0.02)

    try:
        wait(lambda: len(running()) >= 200, 'the hosted loop running')
        attack[0] = True
        first = len(states)
        wait(lambda: len(sent) >= 1000, 'impostor answering 1000 running states')
        attack[0] = False
        after = [s for s in states[first:] if not s.status & DeviceState.STATUS_IDLE]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        outs = [stop_process(p)[1] for p in procs]
    assert all('Traceback' not in o for o in outs), outs
    assert len(after) >= 1000
    applied = np.array([s.applied_wrench for s in after])
    assert np.all(np.isfinite(applied)) and np.all(np.abs(applied) <= limit)
    ratio = applied / (limit * np.array([1.0, -1.0, 1.0]))       # s, s, s if applied
    impostor_like = (ratio[:, 0] > 0.0) & np.isclose(ratio[:, 1], ratio[:, 0], rtol=1e-9,
                                                     atol=0.0) & np.isclose(
        ratio[:, 2], ratio[:, 0], rtol=1e-9, atol=0.0)
    seqs = [s.seq for s, hit in zip(after, impostor_like, strict=True) if hit]
    assert seqs == [], f'impostor commands applied at states {seqs[:10]}'
    saturated = sum(1 for s in after if s.status & DeviceState.STATUS_SATURATED)
    print(f'impostor: {len(sent)} commands answering running states, none applied; '
          f'{saturated} of {len(after)} states saturated by the controller itself')
