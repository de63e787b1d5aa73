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
"""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

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


def main() -> int:
    clock, out = Clock.parse(sys.argv[1]), Path(sys.argv[2])
    rclpy.init()
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

    def send(topic: str, msg: Any) -> None:
        n[0] += 1
        msg.graph_id = OTHER_GRAPH if n[0] % 2 else 0
        pubs[topic].publish(msg)
        counts[topic] += 1

    def on_update(msg: LmiUpdate) -> None:
        if msg.graph_id in mine:
            return
        msg.seq = 0 if counts[TOPIC_LMI] % 25 == 24 else msg.seq + 1
        pose = list(msg.hand_pose)
        pose[0] += SHIFT
        msg.hand_pose = pose
        send(TOPIC_LMI, msg)

    def on_hand(msg: HandInputs) -> None:
        if msg.graph_id in mine:
            return
        m = int(msg.task_dim)
        pose = list(msg.pose)
        for i in range(0, len(pose), m):
            pose[i] += SHIFT
        msg.pose = pose
        send(TOPIC_HAND_INPUTS, msg)

    def on_state(msg: DeviceState) -> None:
        if msg.graph_id in mine:
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
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print('intruder ready', flush=True)
    take_errors = 0
    while rclpy.ok():
        try:
            executor.spin_once(timeout_sec=0.1)
        except (KeyboardInterrupt, ExternalShutdownException):
            break
        except RuntimeError as exc:
            # rclpy failed to take a sample (seen once in a full suite run: "Unable to
            # convert call argument '0' to Python object"): an intruder keeps going
            take_errors += 1
            print(f'take error: {exc}', flush=True)
    out.write_text(json.dumps({**counts, 'take_errors': take_errors}), encoding='utf-8')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
