"""A graph run with the Foxglove bridge, watched by a ROS node of the test
(``test/graph/test_foxglove*.py``).

:class:`BridgeGraph` starts ``run_graph`` (recorder, ve_sim, device_driver and
foxglove_bridge as processes) in a thread and a node of its own context that keeps the
bridge's newest ``/diagnostics`` status values in :attr:`BridgeGraph.bridge`;
:meth:`BridgeGraph.spin_until` spins that node until a condition holds, failing with the run's
error or at the deadline; :meth:`BridgeGraph.join` waits for the run's end and checks that
every process exited with 0.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any


class BridgeGraph:
    """``run_graph(scenario, 'penalty', duration, bag, <shipped params>, foxglove=(host, 0))``
    beside a node called ``node_name``; ``wait`` (s): the deadline of every wait, from start."""

    def __init__(self, scenario: str, duration: float, bag: Path, node_name: str,
                 wait: float) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology import vocabulary as vocab
        from haptic_topology.bringup.run import FOXGLOVE_STATUS, run_graph
        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS
        from haptic_topology.paths import config_dir

        self.wait = wait
        self.deadline = time.monotonic() + wait
        self.outcome: dict[str, Any] = {}
        self.bridge: dict[str, str] = {}

        def graph() -> None:
            try:
                self.outcome['codes'] = run_graph(scenario, 'penalty', duration, bag,
                                                  config_dir() / 'haptic_topology.yaml',
                                                  foxglove=('127.0.0.1', 0))
            except BaseException as exc:    # reported by the test thread
                self.outcome['error'] = exc

        self.runner = threading.Thread(target=graph, daemon=True)
        self.runner.start()
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(node_name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

        def on_diagnostics(msg: Any) -> None:
            for st in msg.status:
                if st.name == FOXGLOVE_STATUS:
                    self.bridge.clear()         # the newest status: clients come and go
                    self.bridge.update({kv.key: kv.value for kv in st.values})

        self.node.create_subscription(DiagnosticArray, vocab.TOPIC_DIAGNOSTICS, on_diagnostics,
                                      QOS_DIAGNOSTICS)

    def spin_until(self, cond: Any, what: str) -> None:
        """Spin the node until ``cond()`` holds (``what``: the message of a failure)."""
        while not cond():
            assert 'error' not in self.outcome, (f'{what}: the run failed: '
                                                 f'{self.outcome.get("error")}')
            assert time.monotonic() < self.deadline, f'{what}: not within {self.wait:g} s'
            self.executor.spin_once(timeout_sec=0.1)

    def join(self) -> None:
        """Wait for the run's end; every process of it exited with 0, the bridge included."""
        from haptic_topology.bringup.run import FOXGLOVE_NODE

        self.runner.join(timeout=self.wait)
        assert not self.runner.is_alive(), 'the run did not end'
        assert 'error' not in self.outcome, self.outcome.get('error')
        assert self.outcome['codes'][FOXGLOVE_NODE] == 0
        assert set(self.outcome['codes'].values()) == {0}, self.outcome['codes']

    def close(self) -> None:
        """Shut the node down and let the run end."""
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.runner.join(timeout=self.wait)
