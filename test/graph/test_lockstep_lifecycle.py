"""A lock-step run is one activation of the driver: activated again after a deactivate it
would start its device over at the scenario's initial pose and its simulated time at 0 while
the VE keeps the run's linkage, and wait for ever for an update. The driver refuses the
second activation with a fault that says why, and simulated time stays where the run ended.
Real processes; every wait is on messages, with a deadline."""

from __future__ import annotations

import signal
import subprocess
import sys
from typing import Any

import pytest

from haptic_topology.bringup.watch import GraphWatcher
from haptic_topology.device.runner import LOCKSTEP_RUNS_ONCE
from haptic_topology.errors import WaitTimeout
from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
WAIT = 120.0          # s: generous, a loaded machine is only slower


def _start(name: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', f'haptic_topology.nodes.{name}', '--ros-args', '--params-file',
         str(PARAMS), '-p', 'scenario:=circle', '-p', 'clock:=lockstep'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)


def test_a_lockstep_driver_refuses_a_second_activation() -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from rosgraph_msgs.msg import Clock as ClockMsg

    from haptic_topology.nodes.qos import QOS_CLOCK, QOS_DIAGNOSTICS
    from haptic_topology.vocabulary import TOPIC_CLOCK, TOPIC_DIAGNOSTICS

    procs = [_start('ve_sim'), _start('device_driver')]

    def alive() -> None:
        for p in procs:
            if p.poll() is not None:
                out = p.stdout.read().decode(errors='replace') if p.stdout else ''
                raise AssertionError(f'{p.args[2]} exited with {p.returncode}: {out[-3000:]}')

    now = [0.0]
    driver: list[Any] = [None]

    def on_clock(msg: Any) -> None:
        now[0] = msg.clock.sec + msg.clock.nanosec * 1e-9

    def on_diag(msg: Any) -> None:
        for st in msg.status:
            if st.name == 'device_driver: loop':
                driver[0] = st

    try:
        with GraphWatcher(alive=alive) as w:
            w.node.create_subscription(ClockMsg, TOPIC_CLOCK, on_clock, QOS_CLOCK)
            w.node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, on_diag,
                                       QOS_DIAGNOSTICS)
            w.wait(lambda: now[0] >= 0.2, WAIT, 'simulated time 0.2 s')
            w.change_state('device_driver', 'deactivate', WAIT)
            w.wait(lambda: w.lifecycle_state('device_driver') == 'inactive', WAIT, 'inactive')
            ended = now[0]
            with pytest.raises(WaitTimeout, match='transition activate failed'):
                w.change_state('device_driver', 'activate', WAIT)
            assert w.lifecycle_state('device_driver') == 'inactive'
            w.wait(lambda: driver[0] is not None and driver[0].level == b'\x02', WAIT,
                   "the driver's fault in /diagnostics")
            assert driver[0].message == f'fault: {LOCKSTEP_RUNS_ONCE}'
            w.spin(0.5)
            assert now[0] == ended          # no second run from 0: time stays where it ended
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
