"""Foreign and hostile messages on the graph's topics, against real node processes.

* extreme integers (``seq = 2**63 - 1``, ``2**64 - 1``, ``task_dim`` 255, ...) at a running
  ``lmi_controller`` and ``ve_sim``: rejected and counted per reason in ``/diagnostics`` (a
  hand input batch with one bad sample as a whole), and both nodes still answer afterwards
  (one message must never end a node);
* an impostor controller (another ``controller_id``, the graph's own ``graph_id``) answering
  every running device state of a lock-step graph with a well-formed command: none is
  applied (the run equals the offline simulation exactly), and the device driver counts
  them as ``foreign_commands``;

Every wait is on a message, with a deadline; nothing is timed.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from procs import stop_process

from haptic_topology.messages.check import MAX_SEQ
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TOPIC_COMMAND, TOPIC_DIAGNOSTICS, TOPIC_STATE

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
#: Longest wait (s) for a node to start or answer: generous, a loaded machine is only slower.
WAIT = 60.0
BIG = 2 ** 63 - 1
U64 = 2 ** 64 - 1
IDLE_WATCHDOG = 16 | 4


def _start(name: str, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', f'haptic_topology.nodes.{name}', '--ros-args', '--params-file',
         str(PARAMS), '-p', 'scenario:=fig8', *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)


class Probe:
    """A node of the test process (own rclpy context) on the graph's topics."""

    def __init__(self, procs: list[subprocess.Popen[bytes]]) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.qos import (
            QOS_DIAGNOSTICS,
            QOS_HAND_INPUTS,
            QOS_LMI,
            QOS_LOOP,
        )
        from haptic_topology.vocabulary import (
            TOPIC_COMMAND,
            TOPIC_DIAGNOSTICS,
            TOPIC_HAND_INPUTS,
            TOPIC_LMI,
            TOPIC_STATE,
        )
        from haptic_topology_msgs.msg import (
            DeviceCommand,
            DeviceState,
            HandInputs,
            LmiUpdate,
        )

        self.rclpy = rclpy
        self.procs = procs
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = n = rclpy.create_node('foreign_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self.state_pub = n.create_publisher(DeviceState, TOPIC_STATE, QOS_LOOP)
        self.hand_pub = n.create_publisher(HandInputs, TOPIC_HAND_INPUTS,
                                           QOS_HAND_INPUTS)
        self.lmi_pub = n.create_publisher(LmiUpdate, TOPIC_LMI, QOS_LMI)
        self.commands: list[Any] = []
        self.updates: list[Any] = []
        self.status: dict[str, dict[str, str]] = {}
        n.create_subscription(DeviceCommand, TOPIC_COMMAND, self.commands.append,
                              QOS_LOOP)
        n.create_subscription(LmiUpdate, TOPIC_LMI, self.updates.append, QOS_LMI)
        n.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diag,
                              QOS_DIAGNOSTICS)

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            self.status[st.name] = {kv.key: kv.value for kv in st.values}

    def value(self, status: str, key: str) -> int:
        return int(self.status.get(status, {}).get(key, '-1'))

    def wait(self, cond: Callable[[], bool], what: str, tick: Callable[[], None] | None = None,
             timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            for p in self.procs:
                assert p.poll() is None, f'{what}: a node died:\n{stop_process(p)[1][-3000:]}'
            assert time.monotonic() < deadline, f'{what}: not within {timeout:g} s'
            if tick is not None:
                tick()
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def _state(seq: int, status: int = IDLE_WATCHDOG, task_dim: int = 3) -> Any:
    from haptic_topology_msgs.msg import DeviceState

    v = [0.0] * task_dim
    return DeviceState(seq=seq, task_dim=task_dim, pose=v, twist=v, hand_wrench=v,
                       applied_wrench=v, status=status)


def _hand(seqs: list[int], state_seqs: list[int], task_dim: int = 3) -> Any:
    """A HandInputs batch of the samples ``seqs`` of states ``state_seqs``."""
    from builtin_interfaces.msg import Time

    from haptic_topology_msgs.msg import HandInputs

    v = [0.0] * (task_dim * len(seqs))
    stamps = [Time(sec=0, nanosec=1_000_000 * min(s, 999)) for s in state_seqs]
    msg = HandInputs(seq=seqs, state_seq=state_seqs, task_dim=task_dim, stamp=stamps,
                     pose=v, twist=v, hand_wrench=v, coupling_wrench=v)
    msg.header.stamp = stamps[-1]
    return msg


def _update(**ints: int) -> Any:
    from haptic_topology.control.lmi import LmiSnapshot
    from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
    from haptic_topology.nodes.convert import lmi_msg, seconds_to_stamp
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology_msgs.msg import LmiUpdate

    sc = load_scenario('fig8')
    snap = LmiSnapshot.from_dynamics(LinkageDynamics(sc.linkage).snapshot(sc.q0, sc.dq0),
                                     sc.linkage.task,
                                     sc.linkage.constraints.characteristic_length, 3, 7)
    msg = lmi_msg(LmiUpdate(), snap, seconds_to_stamp(1.0))
    for k, v in ints.items():
        setattr(msg, k, v)
    return msg


def test_extreme_integers_are_rejected_and_nodes_keep_answering() -> None:
    ctl, ve = 'lmi_controller: loop', 've_sim: loop'
    procs = [_start('lmi_controller'), _start('ve_sim')]
    probe: Probe | None = None
    try:
        probe = p = Probe(procs)

        def answered(seq: int) -> bool:
            return any(int(c.state_seq) == seq for c in p.commands)

        # Up: the controller answers an idle state; both report diagnostics.
        p.wait(lambda: answered(1), 'controller answers state 1',
               lambda: p.state_pub.publish(_state(1)))
        p.wait(lambda: p.value(ctl, 'rejected_range') == 0 and p.value(ve, 'rejected_range')
               == 0, 'diagnostics of both nodes')

        hostile_states = [_state(BIG), _state(U64), _state(MAX_SEQ + 1), _state(2, 255),
                          _state(2, 0, 255)]
        hostile_hands = [_hand([U64], [1]), _hand([1], [BIG]), _hand([BIG], [BIG]),
                         _hand([1], [0]), _hand([1, 2, U64], [1, 2, 3]),
                         _hand([1, 2], [2, 1])]
        hostile_updates = [_update(seq=U64), _update(hand_input_seq=BIG),
                           _update(constraint_count=255), _update(dof=2 ** 32 - 1),
                           _update(task_dim=255)]
        # Best-effort states: each one is sent until the controller has counted it.
        for msg, reason in zip(hostile_states, ['rejected_range'] * 4 + ['rejected_task_dim'],
                               strict=True):
            base = p.value(ctl, reason)
            p.wait(lambda r=reason, b=base: p.value(ctl, r) > b,
                   f'controller counts a hostile state ({reason})',
                   lambda m=msg: p.state_pub.publish(m))
        for msg in hostile_hands:
            p.hand_pub.publish(msg)
        for msg in hostile_updates:
            p.lmi_pub.publish(msg)
        # Reliable topics: every hostile message arrives and is counted.
        p.wait(lambda: p.value(ve, 'rejected_range') >= len(hostile_hands),
               've_sim counted the hostile hand inputs')
        # Nothing of a rejected batch was taken (not the good samples of the mixed ones).
        assert p.value(ve, 'hand_inputs') == 0 and p.value(ve, 'hand_batches') == 0
        p.wait(lambda: p.value(ctl, 'rejected_dof') >= 1 and p.value(ctl, 'rejected_task_dim')
               >= 2 and p.value(ctl, 'rejected_range') >= 4 + 3, 'controller counted updates')

        # The largest accepted seq (a plausible but false running state) does not end it.
        p.wait(lambda: answered(MAX_SEQ), 'controller answers state MAX_SEQ',
               lambda: p.state_pub.publish(_state(MAX_SEQ, status=0)))
        # Both still answer: the controller a new idle state, the VE a batch of ten hand
        # inputs with an update that consumed them.
        p.wait(lambda: answered(2), 'controller still answers',
               lambda: p.state_pub.publish(_state(2)))
        p.hand_pub.publish(_hand(list(range(1, 11)), list(range(1, 11))))
        p.wait(lambda: any(int(u.hand_input_seq) >= 9 for u in p.updates),
               've_sim still answers hand inputs')
    finally:
        if probe is not None:
            probe.close()
        results = [stop_process(proc) for proc in procs]
    for code, out in results:
        assert code == 0, out[-3000:]
        assert 'Traceback' not in out, out[-3000:]


# -- an impostor controller --------------------------------------------------------------------
#: The impostor's wrench (within fig8's limit of 20 N, 20 N, 2 N m: it would be applied as is)
#: and its id (any other than the controller's random one).
IMPOSTOR_WRENCH = [7.5, -7.5, 0.75]
IMPOSTOR_ID = 2 ** 62 + 12345
DURATION = 2.0


class Impostor:
    """Answers every running device state with a well-formed command of another controller
    id, on the lock-step graph's QoS, from its own rclpy context in this process."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, loop_qos
        from haptic_topology.vocabulary import Clock
        from haptic_topology_msgs.msg import DeviceCommand, DeviceState

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = n = rclpy.create_node('impostor', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        qos = loop_qos(Clock.LOCKSTEP)
        self.cmd_t = DeviceCommand
        self.pub = n.create_publisher(DeviceCommand, TOPIC_COMMAND, qos)
        n.create_subscription(DeviceState, TOPIC_STATE, self._on_state, qos)
        n.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diag,
                              QOS_DIAGNOSTICS)
        self.sent = 0
        self.foreign = 0          # the driver's foreign_commands, newest report

    def _on_state(self, msg: Any) -> None:
        if msg.status & 16:       # idle: only the controller's answer may engage the device
            return
        # With the graph's own id, read off its states (the id is no secret): so the
        # controller id is what keeps these out.
        cmd = self.cmd_t(state_seq=msg.seq, controller_id=IMPOSTOR_ID, mode=0, task_dim=3,
                         wrench=IMPOSTOR_WRENCH, vt_pose=list(msg.pose),
                         vt_twist=list(msg.twist), graph_id=msg.graph_id)
        cmd.header.stamp = msg.header.stamp
        self.pub.publish(cmd)
        self.sent += 1

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == 'device_driver: loop':
                values = {kv.key: kv.value for kv in st.values}
                self.foreign = max(self.foreign, int(values.get('foreign_commands', '0')))

    def spin_until(self, done: Callable[[], bool]) -> None:
        while not done():
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.mark.parametrize('layout', ['separate', 'hosted'])
def test_impostor_commands_answering_real_states_are_never_applied(tmp_path: Path,
                                                                    layout: str) -> None:
    """A lock-step fig8 run with an impostor answering every running state, often before the
    controller: the device applies only the controller's commands, so the run equals
    ``simulate()`` to 1e-9 at every cycle; the bag analysis keeps the controller's commands
    where both answered a state. Separate layout (four processes): the driver reports
    following the controller's id and counts the impostor's commands. Hosted layout: the
    driver takes no command from DDS at all, so it counts none."""
    from dataclasses import replace

    from haptic_topology.bag.graph_trace import read_graph_bag
    from haptic_topology.bag.reader import decoder, iter_messages, open_bag
    from haptic_topology.bringup.run import run_graph
    from haptic_topology.sim.lockstep import simulate
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.vocabulary import ControlMode

    bag = tmp_path / 'impostor'
    impostor = Impostor()
    try:
        with ThreadPoolExecutor(1) as pool:
            # The impostor reads the states too: one more reader, so that it cannot stand
            # in for the recorder when the driver starts and engages.
            job = pool.submit(run_graph, 'fig8', 'penalty', DURATION, bag, PARAMS, layout,
                              startup_timeout=60.0, clock='lockstep', min_subscribers=3)
            impostor.spin_until(job.done)
            codes = job.result()
        assert all(c == 0 for c in codes.values()), codes
    finally:
        impostor.close()
    sc = load_scenario('fig8')
    run = read_graph_bag(bag, 'fig8', sc.linkage.dof)
    offline = simulate(replace(sc, duration=DURATION), ControlMode.PENALTY)
    graph = run.trace
    assert len(graph) == len(offline) == round(DURATION / sc.dt) + 1
    for col in ('device_pose', 'device_twist', 'hand_wrench', 'applied', 'vt_pose', 'command',
                'lmi_pose'):
        np.testing.assert_allclose(graph.columns[col], offline.columns[col], rtol=0.0,
                                   atol=1e-9, err_msg=col)
    assert not np.any(np.all(graph.columns['applied'] == IMPOSTOR_WRENCH, axis=1))
    # What the nodes reported: the driver follows the controller's id, not the impostor's,
    # never let another take over, and counted the impostor's commands.
    decode = decoder(bag=open_bag(bag))
    reports: dict[str, dict[str, str]] = {}
    counts: list[tuple[str, str]] = []      # device reports: (foreign, rejected commands)
    for m in iter_messages(open_bag(bag), ['/diagnostics']):
        for st in decode(m).status:
            reports[st.name] = {kv.key: kv.value for kv in st.values}
            if st.name == 'device_driver: loop':
                d = reports[st.name]
                counts.append((d.get('foreign_commands', ''), d.get('rejected_commands', '')))
    dev, ctl = reports['device_driver: loop'], reports['lmi_controller: loop']
    assert dev['controller_id'] == ctl['controller_id'] != str(IMPOSTOR_ID)
    assert dev['controller_takeovers'] == '0'
    # The newest count the driver reported (in the bag or live), against what was sent: the
    # impostor's answers to the last states may come after the driver stopped.
    foreign = max([impostor.foreign] + [int(f) for f, _ in counts if f])
    if layout == 'hosted':
        assert foreign == 0 and impostor.sent > 1000, (impostor.sent, counts)
        return
    assert 0 < foreign <= impostor.sent, (impostor.sent, impostor.foreign, counts)
    assert int(dev['rejected_commands']) >= int(dev['foreign_commands'])
    assert run.skipped.get('command_duplicate', 0) > 0     # both answered those states
    print(f'impostor: sent {impostor.sent} commands, driver counted {foreign} foreign '
          f'(reports in the bag: {counts}; live: {impostor.foreign}), applied none; '
          f'{run.skipped.get("command_duplicate", 0)} states answered by both in the bag')
