"""A second graph on the same ROS domain, as another lab's run or a replayed bag would be:
``python intruder.py CLOCK OUT_JSON``.

It echoes the run's own traffic back on the graph's topics as well-formed, consistent-looking
messages of another graph: for every ``LmiUpdate`` one numbered as the VE's next update with
the hand 2 cm away, and every 25th numbered 0 (a "restarted VE"); for every ``HandInputs``
batch a copy with the device 2 cm away; for every ``DeviceState`` a copy 2 cm away (the
controller's input in the separate layout) and a ``DeviceCommand`` of 5 N answering it
(the device's input). Half of them carry another graph's id, half the default graph's (0:
what a hand-started graph or an old bag sends). Runs until SIGINT/SIGTERM, then writes the
counts it published per topic (and ``take_errors``: samples rclpy failed to take) to
OUT_JSON.

``python intruder.py CLOCK OUT_JSON own-id``: a sender that copies the run's own graph id
(it is no secret) and echoes only what the graph takes by graph id alone: updates, in turn
numbered as the VE's next with the hand 2 cm away (not what the linkage has at that ``q``),
numbered 0 (a "restarted VE" with no new endpoint), or an old update numbered as the next
(a VE going back in time: the VE's first, which consumed no input, or the one of 20
before); and every hand-input batch 2 cm away, numbered and stamped as the original.
"""

from __future__ import annotations

import copy
import faulthandler
import json
import os
import signal
import sys
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from haptic_topology.messages.check import graph_wire
from haptic_topology.nodes.qos import QOS_LMI, hand_inputs_qos, loop_qos
from haptic_topology.vocabulary import (
    TOPIC_COMMAND,
    TOPIC_HAND_INPUTS,
    TOPIC_LMI,
    TOPIC_STATE,
    Clock,
)
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate

SHIFT = 0.02            # m, on the first pose coordinate
OTHER_GRAPH = graph_wire('another-lab')
MARK = 'intruder'       # own-id: the frame_id of what it sent, so it does not echo its echoes


def main() -> None:
    faulthandler.enable()     # a crash leaves its Python stack in the log the test shows
    clock, out = Clock.parse(sys.argv[1]), Path(sys.argv[2])
    own_id = sys.argv[3:] == ['own-id']
    # The stop signals are its own (a flag, as the nodes' spin): rclpy's handlers would shut
    # the context down under the executor.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('intruder')
    loop = loop_qos(clock)
    pubs = {TOPIC_LMI: node.create_publisher(LmiUpdate, TOPIC_LMI, QOS_LMI),
            TOPIC_HAND_INPUTS: node.create_publisher(HandInputs, TOPIC_HAND_INPUTS,
                                                     hand_inputs_qos(clock)),
            TOPIC_STATE: node.create_publisher(DeviceState, TOPIC_STATE, loop),
            TOPIC_COMMAND: node.create_publisher(DeviceCommand, TOPIC_COMMAND, loop)}
    counts = dict.fromkeys(pubs, 0)
    mine: set[int] = {0, OTHER_GRAPH}       # echoes of our own messages come back too
    n = [0]
    history: list[LmiUpdate] = []           # own-id: the run's updates so far

    def send(topic: str, msg: Any) -> None:
        n[0] += 1
        if own_id:
            msg.header.frame_id = MARK      # its own echoes come back with the run's id
        else:
            msg.graph_id = OTHER_GRAPH if n[0] % 2 else 0
        pubs[topic].publish(msg)
        counts[topic] += 1

    def the_runs(msg: Any) -> bool:
        """Whether ``msg`` is the run's (not one this intruder sent)."""
        return msg.header.frame_id != MARK if own_id else msg.graph_id not in mine

    def on_update(msg: LmiUpdate) -> None:
        if not the_runs(msg):
            return
        kind = counts[TOPIC_LMI] % 3 if own_id else 0
        if own_id:
            history.append(copy.deepcopy(msg))
        if kind == 2:                       # an old update, numbered as the next: the
            if len(history) <= 20:          # VE's first (it consumed no input yet) or
                return                      # the one of 20 before, in turn
            stale = history[0] if counts[TOPIC_LMI] % 6 == 2 else history[-21]
            stale.seq = msg.seq + 1
            send(TOPIC_LMI, stale)
            return
        if kind == 1 or (not own_id and counts[TOPIC_LMI] % 25 == 24):
            msg.seq = 0                     # "a restarted VE"
        else:
            msg.seq += 1
        pose = list(msg.hand_pose)
        pose[0] += SHIFT
        msg.hand_pose = pose
        send(TOPIC_LMI, msg)

    def on_hand(msg: HandInputs) -> None:
        if not the_runs(msg):
            return
        m = int(msg.task_dim)
        pose = list(msg.pose)
        for i in range(0, len(pose), m):
            pose[i] += SHIFT
        msg.pose = pose
        send(TOPIC_HAND_INPUTS, msg)

    def on_state(msg: DeviceState) -> None:
        if own_id or msg.graph_id in mine:
            return
        cmd = DeviceCommand(header=msg.header, state_seq=msg.seq, controller_id=1,
                            mode=DeviceCommand.MODE_PENALTY, task_dim=msg.task_dim,
                            wrench=[5.0] * int(msg.task_dim), vt_pose=msg.pose,
                            vt_twist=msg.twist, update_seq=-1)
        send(TOPIC_COMMAND, cmd)
        pose = list(msg.pose)
        pose[0] += SHIFT
        msg.pose = pose
        send(TOPIC_STATE, msg)

    node.create_subscription(LmiUpdate, TOPIC_LMI, on_update, QOS_LMI)
    node.create_subscription(HandInputs, TOPIC_HAND_INPUTS, on_hand, hand_inputs_qos(clock))
    node.create_subscription(DeviceState, TOPIC_STATE, on_state, loop)
    stop: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _: stop.append(signum))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print('intruder ready', flush=True)
    take_errors = 0
    while not stop:
        try:
            executor.spin_once(timeout_sec=0.1)
        except RuntimeError as exc:
            # rclpy failed to take a sample (seen once in a full suite run: "Unable to
            # convert call argument '0' to Python object"): an intruder keeps going
            take_errors += 1
            print(f'take error: {exc}', flush=True)
    out.write_text(json.dumps({**counts, 'take_errors': take_errors}), encoding='utf-8')
    # The node goes first: with it the process's DDS participant and its shared-memory
    # segment in /dev/shm, which would outlive the process.
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    # Ends here, as the node processes do (nodes.runtime): no rclpy teardown and no
    # interpreter finalization destroying rclpy's and Fast DDS's objects in whatever order
    # (a CI run had all three of test_foreign_graph's intruders exit with SIGSEGV, -11).
    sys.stdout.flush()
    os._exit(0)


if __name__ == '__main__':
    main()
