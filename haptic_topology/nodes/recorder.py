"""``recorder``: writes the graph's topics to a rosbag2 directory (MCAP storage).

Subscribes with ``raw=True`` (the serialized CDR bytes are stored as received, nothing is
deserialised) and writes them with ``rosbags`` under ``output`` (default
``bags/<scenario>_<YYYYmmdd-HHMMSS>``), timestamped with the receive time. The bag is
finalised (``metadata.yaml``) on a clean shutdown (SIGINT/SIGTERM). QoS mirrors each
publisher's reliability with a deep queue (see :mod:`haptic_topology.nodes.common`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.writer import WriterError
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

from haptic_topology.errors import BagError
from haptic_topology.msgdefs import typestore_with_haptic_msgs
from haptic_topology.nodes import common
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInput, LmiUpdate

#: Topic -> (rclpy type, type name in the bag).
RECORDED: dict[str, tuple[Any, str]] = {
    common.TOPIC_STATE: (DeviceState, 'haptic_topology_msgs/msg/DeviceState'),
    common.TOPIC_COMMAND: (DeviceCommand, 'haptic_topology_msgs/msg/DeviceCommand'),
    common.TOPIC_HAND: (HandInput, 'haptic_topology_msgs/msg/HandInput'),
    common.TOPIC_LMI: (LmiUpdate, 'haptic_topology_msgs/msg/LmiUpdate'),
    common.TOPIC_JOINTS: (JointState, 'sensor_msgs/msg/JointState'),
    common.TOPIC_MARKERS: (MarkerArray, 'visualization_msgs/msg/MarkerArray'),
    common.TOPIC_DIAGNOSTICS: (DiagnosticArray, 'diagnostic_msgs/msg/DiagnosticArray'),
}

#: Topics whose publishers must be matched before the loop starts (see _check_connected).
CONNECT_TOPICS = (common.TOPIC_COMMAND, common.TOPIC_HAND, common.TOPIC_LMI)
CONNECTED_MARK = 'recorder connected'


def default_bag_dir(scenario: str, root: str | Path = 'bags') -> Path:
    return Path(root) / f'{scenario}_{time.strftime("%Y%m%d-%H%M%S")}'


class Recorder(Node):
    """Records the haptic topics and /diagnostics into one MCAP bag."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('recorder', **kwargs)
        d = common.declare
        scenario = d(self, 'scenario', 'fig8', 'scenario name, used in the default bag name')
        d(self, 'executor', 'events', 'executor of the process', choices=common.EXECUTORS)
        out = d(self, 'output', '', 'bag directory to create (must not exist); empty: '
                'bags/<scenario>_<timestamp>')
        name = Path(str(scenario)).stem
        self.path = Path(out) if out else default_bag_dir(name)
        if self.path.exists():
            raise BagError(f'recorder: output {self.path} already exists')
        self.path.parent.mkdir(parents=True, exist_ok=True)
        store = typestore_with_haptic_msgs()
        self.writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self.writer.open()
        except WriterError as exc:
            raise BagError(f'recorder: cannot open {self.path}: {exc}') from None
        self.counts: dict[str, int] = {}
        self.subscriptions_by_topic: dict[str, Any] = {}
        for topic, (msg_type, type_name) in RECORDED.items():
            conn = self.writer.add_connection(self._resolve(topic), type_name, typestore=store)
            qos = (common.QOS_RECORD_RELIABLE
                   if common.TOPIC_QOS[topic].reliability == common.QOS_LMI.reliability
                   else common.QOS_RECORD_BEST_EFFORT)
            self.counts[topic] = 0
            self.subscriptions_by_topic[topic] = self.create_subscription(
                msg_type, topic, self._writer_for(topic, conn), qos, raw=True)
        self._open = True
        self._connected = False
        self._connect_timer = self.create_timer(0.05, self._check_connected)
        self.get_logger().info(f'recording to {self.path}')
        print(f'recording to {self.path}', flush=True)

    def _check_connected(self) -> None:
        """Print ``connected`` once the controller's and the VE's topics have a publisher.

        The bringup starts the device driver (which starts the loop) only after this line, so
        no message of the run is sent before this recorder is matched to its publisher.
        """
        subs = self.subscriptions_by_topic
        if all(subs[t].get_publisher_count() > 0 for t in CONNECT_TOPICS):
            self._connect_timer.cancel()
            self._connected = True
            print(f'{CONNECTED_MARK} to {", ".join(CONNECT_TOPICS)}', flush=True)

    def _resolve(self, topic: str) -> str:
        return self.resolve_topic_name(topic)

    def _writer_for(self, topic: str, conn: Any) -> Any:
        def write(data: bytes) -> None:
            if self._open:
                self.writer.write(conn, time.time_ns(), data)
                self.counts[topic] += 1
        return write

    def close(self) -> None:
        """Finalise the bag (metadata.yaml); idempotent."""
        if self._open:
            self._open = False
            self.writer.close()
            summary = ', '.join(f'{t}: {n}' for t, n in self.counts.items())
            print(f'bag written: {self.path} ({summary})', flush=True)


def main(args: Sequence[str] | None = None) -> int:
    return common.run_main('recorder', lambda: [Recorder()], args)


if __name__ == '__main__':
    raise SystemExit(main())
