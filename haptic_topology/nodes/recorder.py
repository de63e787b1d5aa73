"""``recorder``: writes the graph's topics to a rosbag2 directory (MCAP storage).

Subscribes with ``raw=True`` (the serialized CDR bytes are stored as received, nothing is
deserialised) to every topic of :data:`RECORDED`, or to those named in ``topics`` and/or
matching ``topic_regex``, and writes them with :class:`~haptic_topology.bag.writer.BagWriter`
under ``output`` (default ``bags/<scenario>_<YYYYmmdd-HHMMSS>``), timestamped with the
receive time. The haptic_topology_msgs schemas embedded in the bag are the .msg texts plus
their dependencies, so ``ros2 bag``, ``rosbags`` or any MCAP tool decodes them without our
package.

No executor callback runs per message: a writer thread takes what DDS holds for each topic
every 10 ms (:class:`~haptic_topology.nodes.take.BatchTaker`: serialized, with DDS's receive
time and the publisher's gid, about 3 us a message), writes it into the MCAP chunks in
receive order, closes a chunk every ``flush_period`` (0.2 s) and rewrites ``metadata.yaml``
with the running counts. So the recorder costs a fraction of a core at 30,000 msg/s, a clean
stop (SIGINT/SIGTERM) finalises the bag, and a SIGKILL leaves a file that reads back up to the
last flush (``haptic-topology bag repair`` completes it for other readers). Drops are counted
per publisher and reported in its status and its closing summary (``lost``: gaps in each
publisher's sequence numbers, whatever dropped the messages, or samples DDS never delivered;
see :mod:`haptic_topology.nodes.take`). A failure of the writing
(:class:`~haptic_topology.bag.writer_thread.WriterThread`) turns the status ERROR at its next
report, with the count of messages ``not written``. QoS mirrors each publisher's reliability
with a deep queue (see :mod:`haptic_topology.nodes.qos`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from haptic_topology.bag.graph_index import DEVICE_STATUS
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.bag.writer_thread import WriterThread
from haptic_topology.config import node_params, resolve
from haptic_topology.config.settings import RecorderSettings
from haptic_topology.device.vendor import IDENTITY_KEYS
from haptic_topology.errors import BagError
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs
from haptic_topology.nodes.diagnostics import diagnostics
from haptic_topology.nodes.parameters import declare_settings
from haptic_topology.nodes.qos import (
    QOS_DIAGNOSTICS,
    QOS_LATCHED,
    QOS_RECORD_BEST_EFFORT,
    QOS_RECORD_RELIABLE,
    TOPIC_QOS,
    publisher_qos,
)
from haptic_topology.nodes.runtime import EXECUTOR_SHUTDOWN, SPIN_PERIOD, run_main
from haptic_topology.nodes.take import BatchTaker
from haptic_topology.processes import STOP_TIMEOUT
from haptic_topology.vocabulary import (
    STATUS_RECORDER,
    TOPIC_COMMAND,
    TOPIC_DEVICE_POSE,
    TOPIC_DEVICE_TWIST,
    TOPIC_DIAGNOSTICS,
    TOPIC_HAND_INPUTS,
    TOPIC_JOINTS,
    TOPIC_LMI,
    TOPIC_MARKERS,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_STATE,
    TOPIC_TF,
    TOPIC_VT_PATH,
    TOPIC_VT_POSE,
    TOPIC_VT_TWIST,
    TOPIC_WRENCH_APPLIED,
    TOPIC_WRENCH_COUPLING,
    TOPIC_WRENCH_HAND,
    Clock,
)
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate, VtPath

#: Topic -> (rclpy type, type name in the bag).
RECORDED: dict[str, tuple[Any, str]] = {
    TOPIC_STATE: (DeviceState, 'haptic_topology_msgs/msg/DeviceState'),
    TOPIC_COMMAND: (DeviceCommand, 'haptic_topology_msgs/msg/DeviceCommand'),
    TOPIC_HAND_INPUTS: (HandInputs, 'haptic_topology_msgs/msg/HandInputs'),
    TOPIC_LMI: (LmiUpdate, 'haptic_topology_msgs/msg/LmiUpdate'),
    TOPIC_VT_PATH: (VtPath, 'haptic_topology_msgs/msg/VtPath'),
    TOPIC_JOINTS: (JointState, 'sensor_msgs/msg/JointState'),
    TOPIC_MARKERS: (MarkerArray, 'visualization_msgs/msg/MarkerArray'),
    TOPIC_DIAGNOSTICS: (DiagnosticArray, 'diagnostic_msgs/msg/DiagnosticArray'),
    TOPIC_ROBOT_DESCRIPTION: (String, 'std_msgs/msg/String'),
    TOPIC_TF: (TFMessage, 'tf2_msgs/msg/TFMessage'),
    TOPIC_DEVICE_POSE: (PoseStamped, 'geometry_msgs/msg/PoseStamped'),
    TOPIC_DEVICE_TWIST: (TwistStamped, 'geometry_msgs/msg/TwistStamped'),
    TOPIC_VT_POSE: (PoseStamped, 'geometry_msgs/msg/PoseStamped'),
    TOPIC_VT_TWIST: (TwistStamped, 'geometry_msgs/msg/TwistStamped'),
    TOPIC_WRENCH_APPLIED: (WrenchStamped, 'geometry_msgs/msg/WrenchStamped'),
    TOPIC_WRENCH_HAND: (WrenchStamped, 'geometry_msgs/msg/WrenchStamped'),
    TOPIC_WRENCH_COUPLING: (WrenchStamped, 'geometry_msgs/msg/WrenchStamped'),
}

#: Topics whose publishers must be matched before the loop starts (see _check_connected).
CONNECT_TOPICS = (TOPIC_COMMAND, TOPIC_HAND_INPUTS, TOPIC_LMI,
                  TOPIC_VT_PATH)
LOOP_TOPICS = (TOPIC_STATE, TOPIC_COMMAND)
#: s between two takes of everything DDS holds (the readers' histories hold 1,000-10,000
#: messages per topic: at the graph's rates at 10x, a second or more).
DRAIN_PERIOD = 0.01
#: s :meth:`Recorder.close` waits for the writer thread to finish the bag: what the bringup's
#: SIGINT-to-SIGTERM time (``STOP_TIMEOUT``) leaves after the spin loop's end and the
#: executor's shutdown, less a second for the rest of the teardown
CLOSE_TIMEOUT = STOP_TIMEOUT - SPIN_PERIOD - EXECUTOR_SHUTDOWN - 1.0


def select_topics(names: Sequence[str], regex: str) -> list[str]:
    """Topics of :data:`RECORDED` to record (see
    :func:`haptic_topology.config.resolve.select_topics`)."""
    return resolve.select_topics(names, regex, list(RECORDED))


def _latched(qos: QoSProfile) -> bool:
    return bool(qos.durability == DurabilityPolicy.TRANSIENT_LOCAL)


def _bag_qos(qos: QoSProfile) -> Any:
    return make_qos(qos.reliability == ReliabilityPolicy.RELIABLE, int(qos.depth),
                    _latched(qos))


def _record_qos(topic: str, clock: Clock) -> QoSProfile:
    """The recorder's deep queue with the reliability of ``topic``'s publisher; transient
    local for a transient-local publisher (``/robot_description``: published once, maybe
    before the recorder started)."""
    offered = publisher_qos(topic, clock)
    if _latched(offered):
        return QOS_LATCHED
    reliable = offered.reliability == ReliabilityPolicy.RELIABLE
    return QOS_RECORD_RELIABLE if reliable else QOS_RECORD_BEST_EFFORT


class Recorder(Node):
    """Records the haptic topics and /diagnostics into one MCAP bag (see module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('recorder', **kwargs)
        settings = declare_settings(self, RecorderSettings)
        self.config = config = resolve.resolve_recorder(settings, list(RECORDED))
        topics = list(config.topics)
        self.flush_period = config.flush_period
        self.path = config.path
        self.graph_id = settings.graph_id   # records every graph's messages; names its own
        specs = [TopicSpec(self.resolve_topic_name(t), RECORDED[t][1],
                           (_bag_qos(TOPIC_QOS[t]),)) for t in topics]
        self.writer = BagWriter(self.path, specs, typestore_with_haptic_msgs(),
                                sources=message_definitions(), chunk_size=config.chunk_size,
                                compression=config.compression,
                                custom={'recorded_by': 'haptic_topology recorder',
                                        'scenario': settings.scenario,
                                        'graph_id': settings.graph_id},
                                max_bag_size=config.max_bag_size,
                                max_bag_duration=config.max_bag_duration)
        self.taker = BatchTaker(self, [(self.resolve_topic_name(t), RECORDED[t][0],
                                        _record_qos(t, config.clock)) for t in topics])
        self.subscriptions_by_topic = dict(zip(topics, self.taker.subscriptions, strict=True))
        # One thread takes and writes (module doc; it alone touches the writer).
        self.writer_thread = WriterThread(self.writer, self.taker.drain, self.flush_period,
                                          DRAIN_PERIOD)
        self.writer_thread.start()
        self._open = True
        self._connect = [t for t in CONNECT_TOPICS if t in self.subscriptions_by_topic]
        self.connected = False
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS,
                                              QOS_DIAGNOSTICS)
        # The device's identity, from its driver's status, into the bag's custom_data.
        self.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._device_identity,
                                 QOS_DIAGNOSTICS)
        self._connect_timer = self.create_timer(0.05, self._check_connected)
        self.create_timer(0.25, self._publish_status)
        self.get_logger().info(f'recording to {self.path}')
        print(f'recording to {self.path}', flush=True)

    def _check_connected(self) -> None:
        """Report ``connected`` once the controller's and the VE's topics have a publisher
        matched to this recorder.

        The bringup starts the device driver (which starts the loop) only after that status,
        so no message of the run is sent before this recorder is matched to its publisher.
        """
        subs = self.subscriptions_by_topic
        if all(subs[t].get_publisher_count() > 0 for t in self._connect):
            self._connect_timer.cancel()
            self.connected = True
            self.get_logger().info(f'connected to {", ".join(self._connect) or "(none)"}')
        self._publish_status()

    def _device_identity(self, msg: DiagnosticArray) -> None:
        """Keep ``device`` (the driver's ``hardware_id``) and a vendor's identity values
        (``device_model``, ``device_serial``, ...) of this graph's device in the bag's
        ``custom_data`` (``metadata.yaml``, written at each flush and at the end)."""
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if (st.name != DEVICE_STATUS or not st.hardware_id
                    or values.get('graph_id', self.graph_id) != self.graph_id):
                continue
            found = {'device': st.hardware_id,
                     **{k: values[k] for k in IDENTITY_KEYS if values.get(k)}}
            if any(self.writer.custom.get(k) != v for k, v in found.items()):
                # a new dict, swapped whole: the writer thread reads it at its flushes
                self.writer.custom = {**self.writer.custom, **found}

    def _publish_status(self) -> None:
        """``/diagnostics`` status ``recorder: bag``: path, counts, ``connected``, and the
        publishers matched on the state and command topics (the bringup activates the device
        driver once its state publisher is matched here, so the bag holds the run's first
        state)."""
        lost = dict(zip(self.subscriptions_by_topic, self.taker.lost, strict=True))
        values = {'path': str(self.path), 'graph_id': self.graph_id,
                  'connected': str(self.connected).lower(),
                  **{f'received {t}': str(n) for t, n in self.counts.items()},
                  'lost': str(sum(lost.values())),
                  **{f'lost {t}': str(n) for t, n in lost.items() if n},
                  **{f'lost {t} from {p}': str(n) for t, p, n in self.lost_by_publisher()},
                  **{f'publishers {t}': str(sub.get_publisher_count())
                     for t, sub in self.subscriptions_by_topic.items()
                     if t in LOOP_TOPICS}}
        level, message = 0, 'recording'
        failed = self.writer_thread.error
        if failed is not None:      # within one status period of the failure
            level, message = 2, f'writing the bag failed: {_describe(failed)}'
            values['not written'] = str(self.writer_thread.unwritten(sum(self.taker.taken)))
        self.diag_pub.publish(diagnostics(self, STATUS_RECORDER, values, level, message))

    @property
    def counts(self) -> dict[str, int]:
        """Messages received so far, per topic."""
        return dict(zip(self.subscriptions_by_topic, self.taker.taken, strict=True))

    def lost_by_publisher(self) -> list[tuple[str, str, int]]:
        """``(topic, publisher, messages lost)`` for every publisher that lost any (see
        :meth:`BatchTaker.lost_by_publisher`)."""
        return [(t, p, n) for t, by in zip(self.subscriptions_by_topic,
                                           self.taker.lost_by_publisher(), strict=True)
                for p, n in by.items()]

    def close(self) -> None:
        """Stop the writer thread, which takes the rest and finalises the bag (summary,
        metadata.yaml), waiting at most ``CLOSE_TIMEOUT``; print what was written. Raises
        :class:`BagError` with the count of messages received but not written when the writer
        failed or had not finished by then. Idempotent."""
        if not self._open:
            return
        self._open = False
        thread = self.writer_thread
        ended = thread.stop(CLOSE_TIMEOUT)
        taken = sum(self.taker.taken)
        unwritten, lost = thread.unwritten(taken), sum(self.taker.lost)
        by_publisher = ', '.join(f'{t} from {p}: {n}' for t, p, n in self.lost_by_publisher())
        if ended:           # else the thread still takes from it
            self.taker.destroy()
        if thread.error is not None:
            raise BagError(f'{self.path}: writing the bag failed ({_describe(thread.error)}): '
                           f'{unwritten} of {taken} messages received were not written; what '
                           'was flushed before stays readable (`haptic-topology bag repair` '
                           'completes it)')
        if not ended:
            raise BagError(f'{self.path}: the bag was not finished within {CLOSE_TIMEOUT:g} s '
                           f'of the stop ({unwritten} of {taken} messages received not written '
                           'yet); `haptic-topology bag repair` completes what was flushed')
        summary = ', '.join(f'{t}: {n}' for t, n in self.writer.counts.items())
        print(f'bag written: {self.path} ({summary}; received but not written: {unwritten}; '
              f'lost before the recorder: {lost}{f" ({by_publisher})" if by_publisher else ""})',
              flush=True)


def _describe(exc: BaseException) -> str:
    return f'{type(exc).__name__}: {exc}'


def main(args: Sequence[str] | None = None) -> int:
    return run_main('recorder', lambda: [Recorder()], args, node_params.KNOWN,
                           exit_after_close=True)


if __name__ == '__main__':
    raise SystemExit(main())
