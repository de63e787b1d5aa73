"""Test helper (not collected): ``run_main`` with a node whose ``close`` raises before a real
``recorder``, as in the composed process (the device driver's close comes first there).

    python close_all_node.py --ros-args -p output:=BAG -r __ns:=NS

Prints ``recording to BAG`` (the recorder) and runs until SIGINT; then every node's close is
called whatever the others do (``haptic_topology.nodes.runtime.close_all``).
"""

from __future__ import annotations

from typing import Any

from rclpy.node import Node

from haptic_topology.config import node_params
from haptic_topology.nodes.recorder import Recorder
from haptic_topology.nodes.runtime import run_main


class FailingClose(Node):
    def __init__(self) -> None:
        super().__init__('failing_close')
        self.declare_parameter('executor', 'events')

    def close(self) -> None:
        raise RuntimeError('this close fails')


def build() -> list[Any]:
    return [FailingClose(), Recorder()]


if __name__ == '__main__':
    raise SystemExit(run_main('recorder', build, None, node_params.KNOWN,
                              exit_after_close=True))
