"""The recorder in a real process: nothing lost at 3 x 1 kHz + 100 Hz, readable by rosbags
and plain mcap, and readable after SIGKILL (as it is with our reader; after `bag repair` by
all).

A publisher process (``bag_publisher.py``) sends N messages of each haptic_topology_msgs
type but HandInputs, one of each per millisecond, with sequence numbers 1..N, and the N hand
inputs in batches of 10 (one HandInputs per 10 ms); the recorder must store exactly those.
Both run with the lock-step graph's QoS (``clock: lockstep``: the 1 kHz loop topics
reliable), so "nothing lost" is what the streams guarantee on any machine; in a wall-clock
graph the state and command topics are best effort and a starved recorder may miss some
(seen beside a busy process: 1528 of 3000 states), which says nothing about the recorder.
Every process runs in the session's random ROS_DOMAIN_ID, discovery on this host only
(``conftest.ros_domain_env``); every wait has a deadline.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader, AnyReaderError

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.messages.definitions import typestore_with_haptic_msgs

pytestmark = pytest.mark.graph

TEST_DIR = Path(__file__).resolve().parents[1] / 'support'
SEQ_FIELD = {'/haptic/device/state': 'seq', '/haptic/device/command': 'state_seq',
             '/haptic/hand_inputs': 'seq', '/haptic/lmi/update': 'seq'}
STATE_TOPIC = 'haptic/device/state'
#: Samples per message: HandInputs carries bag_publisher.BATCH sequence numbers.
PER_MESSAGE = {'/haptic/hand_inputs': 10}


def _wait_for_line(proc: subprocess.Popen[str], mark: str, timeout: float,
                   name: str = 'recorder') -> None:
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if mark in line:
            return
        if not line and proc.poll() is not None:
            raise AssertionError(f'{name} exited with {proc.returncode} before "{mark}"')
    raise AssertionError(f'no "{mark}" within {timeout} s')


def _start_recorder(bag: Path, namespace: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.recorder', '--ros-args', '-p',
         f'output:={bag}', '-p', 'clock:=lockstep', '-r', f'__ns:={namespace}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED='1'), start_new_session=True)
    _wait_for_line(proc, 'recording to', 40.0)
    return proc


def _start_publisher(n: int, namespace: str, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, str(TEST_DIR / 'bag_publisher.py'), str(n), '40',
                             namespace, 'lockstep', *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _seqs_by_topic(bag_path: Path, ns: str) -> tuple[dict[str, list[int]], bool]:
    bag = open_bag(bag_path)
    decode = decoder()
    out: dict[str, list[int]] = {t: [] for t in SEQ_FIELD}
    for msg in iter_messages(bag):
        topic = msg.topic.removeprefix(ns)
        if topic in SEQ_FIELD:
            value = getattr(decode(msg), SEQ_FIELD[topic])
            if topic in PER_MESSAGE:
                out[topic].extend(int(v) for v in value)
            else:
                out[topic].append(int(value))
    return out, bool(bag.truncated)


def test_recorder_loses_nothing_and_any_reader_decodes(tmp_path: Path,
                                                      topic_prefix: str) -> None:
    n = 3000
    bag = tmp_path / 'roundtrip'
    rec = _start_recorder(bag, topic_prefix)
    try:
        # The publisher stays up (its reliable writers resending) until the recorder
        # reports every message received; then the recorder is stopped.
        pub = _start_publisher(n, topic_prefix, 'recorded')
        out, _ = pub.communicate(timeout=120)
        assert pub.returncode == 0, out
    finally:
        rec.send_signal(signal.SIGINT)
        log, _ = rec.communicate(timeout=30)
    assert rec.returncode == 0, log
    assert 'received but not written: 0' in log

    # Our reader: every sequence number 1..N once, in order, on each topic.
    seqs, truncated = _seqs_by_topic(bag, topic_prefix)
    assert not truncated
    for topic, got in seqs.items():
        assert got == list(range(1, n + 1)), f'{topic}: {len(got)} of {n}'

    # rosbags: opens the rosbag2 directory, decodes every message with the schemas.
    store = typestore_with_haptic_msgs()
    with AnyReader([bag], default_typestore=store) as reader:
        counts = {c.topic.removeprefix(topic_prefix): c.msgcount for c in reader.connections}
        decoded = sum(1 for c, _, raw in reader.messages()
                      if reader.deserialize(raw, c.msgtype) is not None)
    for topic in SEQ_FIELD:
        assert counts[topic] == n // PER_MESSAGE.get(topic, 1)
    assert decoded == sum(counts.values()) >= 3 * n + n // 10

    # Plain mcap: summary with Statistics, ros2msg schemas with their dependencies, cdr.
    mcap_file = next(bag.glob('*.mcap'))
    with mcap_file.open('rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == sum(counts.values())
        for schema in summary.schemas.values():
            assert schema.encoding == 'ros2msg'
            if schema.name != 'std_msgs/msg/String':   # /robot_description: no header
                assert 'MSG: std_msgs/Header' in schema.data.decode(), schema.name
        plain = 0
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == 'cdr'
            assert 'offered_qos_profiles' in channel.metadata
            store.deserialize_cdr(message.data, schema.name)
            plain += 1
    assert plain == decoded


def test_sigkill_leaves_a_readable_bag(tmp_path: Path, topic_prefix: str) -> None:
    """Killed mid-run, the bag holds 1..K_topic of every sequence (K_topic: what was
    flushed of that topic; the topics' K differ by how far each stream's delivery was
    behind at the kill: a reliable stream can lag by a second on a loaded machine) and,
    after `bag repair`, opens in rosbags."""
    n = 4000
    bag = tmp_path / 'killed'
    rec = _start_recorder(bag, topic_prefix)
    pub = _start_publisher(n, topic_prefix)
    try:
        _wait_for_line(pub, 'publishing', 60.0, 'publisher')
        time.sleep(1.5)  # ~1500 of each sent, at least 7 flush periods
        os.killpg(rec.pid, signal.SIGKILL)
        rec.wait(timeout=10)
    finally:
        pub.kill()
        pub.wait(timeout=10)
    seqs, truncated = _seqs_by_topic(bag, topic_prefix)
    assert truncated
    k = len(seqs['/haptic/device/state'])
    assert k > 100, 'nothing flushed before the kill'
    for topic, got in seqs.items():
        assert got == list(range(1, len(got) + 1)), topic

    with pytest.raises(AnyReaderError):  # rosbags refuses a file without footer
        with AnyReader([bag]) as reader:
            list(reader.messages())
    result = repair_bag(bag)
    assert result.repaired
    assert result.counts[f'{topic_prefix}/haptic/device/state'] == k
    with AnyReader([bag], default_typestore=typestore_with_haptic_msgs()) as reader:
        states = [reader.deserialize(raw, c.msgtype).seq for c, _, raw in reader.messages()
                  if c.topic == f'{topic_prefix}/haptic/device/state']
    assert states == list(range(1, k + 1))


class _Graph:
    """This test's own rclpy node (its own context): publishes device states as the
    lock-step graph does and keeps the recorder's ``/diagnostics`` status of ``bag``."""

    def __init__(self, namespace: str, bag: Path) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from haptic_topology.nodes.qos import QOS_DIAGNOSTICS, publisher_qos
        from haptic_topology.vocabulary import TOPIC_DIAGNOSTICS, TOPIC_STATE, Clock
        from haptic_topology_msgs.msg import DeviceState

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('recorder_failure_test', namespace=namespace,
                                      context=self.context)
        self.pub = self.node.create_publisher(
            DeviceState, TOPIC_STATE.lstrip('/'), publisher_qos(TOPIC_STATE, Clock.LOCKSTEP))
        self.statuses: list[tuple[int, str, dict[str, str]]] = []

        def keep(arr: Any) -> None:
            for st in arr.status:
                values = {kv.key: kv.value for kv in st.values}
                if st.name == 'recorder: bag' and values.get('path') == str(bag):
                    self.statuses.append((st.level[0], st.message, values))

        self.node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, keep,
                                      QOS_DIAGNOSTICS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.msg = DeviceState(task_dim=3, pose=[0.0] * 3, twist=[0.0] * 3,
                               hand_wrench=[0.0] * 3, applied_wrench=[0.0] * 3)
        self.sent = 0

    def publish(self, n: int) -> None:
        for _ in range(n):
            self.sent += 1
            self.msg.seq = self.sent
            self.pub.publish(self.msg)

    def until(self, what: str, cond: Callable[[], bool], timeout: float = 30.0,
              publish: int = 0) -> None:
        """Spin (publishing ``publish`` states each turn) until ``cond`` holds."""
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, f'{what}: not within {timeout} s; ' \
                f'last status {self.statuses[-1:]}'
            self.publish(publish)
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def test_a_writer_failure_is_an_error_status_with_the_count_not_written(
        tmp_path: Path, topic_prefix: str) -> None:
    """The bag's directory is replaced by a regular file while the recorder runs (this fails
    for root too): the next split cannot create its file (BagError in the writer thread).
    The recorder's status turns ERROR, naming the exception, and counts the messages received
    since and not written; at the stop it reports that count and exits with 1. Every
    message received is either in the bag's files or counted as not written."""
    bag = tmp_path / 'failing'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.recorder', '--ros-args', '-p',
         f'output:={bag}', '-p', 'clock:=lockstep', '-p', 'max_bag_size:=1',
         '-p', f'topics:=[{STATE_TOPIC}]', '-r', f'__ns:={topic_prefix}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED='1'), start_new_session=True)
    graph = _Graph(topic_prefix, bag)
    try:
        _wait_for_line(proc, 'recording to', 40.0)
        graph.until('subscriber matched', lambda: graph.pub.get_subscription_count() > 0)
        graph.until('a split file written', lambda: (bag / 'failing_1.mcap').exists(),
                    publish=5)
        moved = tmp_path / 'moved'
        bag.rename(moved)
        bag.write_text('not a directory\n')
        graph.until('ERROR status', lambda: any(s[0] == 2 for s in graph.statuses),
                    publish=5)
        level, message, _ = next(s for s in graph.statuses if s[0] == 2)
        # (BagError: the split's next file; or OSError: the flush's metadata.yaml before it;
        # the path is gone for an instant before the file takes its place)
        assert message.startswith('writing the bag failed: ') and any(
            why in message for why in ('Not a directory', 'No such file or directory')), message
        graph.publish(50)           # after the failure: received, never written
        total = graph.sent
        graph.until('every state received and counted',
                    lambda: graph.statuses[-1][2].get(f'received {STATE_TOPIC}') == str(total))
        _, _, values = graph.statuses[-1]
        assert values['lost'] == '0'
        not_written = int(values['not written'])
    finally:
        graph.close()
        proc.send_signal(signal.SIGINT)
        log, _ = proc.communicate(timeout=30)
    # (a file just created when the writer failed is empty)
    in_files = sum(1 for f in sorted(moved.glob('*.mcap')) if f.stat().st_size
                   for _ in iter_messages(open_bag(f)))
    assert in_files + not_written == total >= 50 + in_files, (in_files, not_written, total)
    assert proc.returncode == 1, log
    assert f'{not_written} of {total} messages received were not written' in log, log


def test_a_node_whose_close_raises_does_not_keep_the_recorder_from_its_bag(
        tmp_path: Path, topic_prefix: str) -> None:
    """Several nodes in one process (``composed``): the first node's close raises; the
    recorder's close still finalises the bag (summary and footer: not truncated), the failure
    is reported and the process exits with 1."""
    bag = tmp_path / 'closed'
    proc = subprocess.Popen(
        [sys.executable, str(TEST_DIR / 'close_all_node.py'), '--ros-args', '-p',
         f'output:={bag}', '-p', f'topics:=[{STATE_TOPIC}]', '-r', f'__ns:={topic_prefix}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED='1'), start_new_session=True)
    try:
        # Spinning (its first timer: no topic to wait for); a SIGINT before the spin would
        # end the start-up instead.
        _wait_for_line(proc, 'connected to (none)', 40.0)
    finally:
        proc.send_signal(signal.SIGINT)
        log, _ = proc.communicate(timeout=30)
    assert 'recorder: error: failing_close: closing failed: RuntimeError: this close fails' \
        in log, log
    assert 'bag written' in log, log
    assert proc.returncode == 1, log
    opened = open_bag(bag)
    list(iter_messages(opened))
    assert not opened.truncated


def test_messages_lost_are_counted_per_publisher(tmp_path: Path, topic_prefix: str) -> None:
    """Two reliable publishers of the state (nodes ``pub_a``, ``pub_b``; writer history 100)
    and a recorder that is stopped (SIGSTOP) while ``pub_a`` sends ``burst`` states and
    ``pub_b`` one: ``pub_a``'s writer keeps only its newest 100 unacknowledged and the
    recorder's socket buffer holds only some thousands of datagrams, so the recorder,
    continued, takes only part of the burst, and ``pub_a``'s sequence numbers skip the rest.
    Every state sent after the publishers matched is taken or counted lost, per publisher, in
    the status and in the summary printed at the stop. Exact whatever the timing: each
    publisher's last state is in its writer's history, so it is taken and closes every gap;
    how many of the burst are lost depends on the machine, the counts are checked against
    the bag."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from haptic_topology_msgs.msg import DeviceState

    bag = tmp_path / 'lossy'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.recorder', '--ros-args', '-p',
         f'output:={bag}', '-p', 'clock:=lockstep', '-p', f'topics:=[{STATE_TOPIC}]',
         '-r', f'__ns:={topic_prefix}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED='1'), start_new_session=True)
    graph = _Graph(topic_prefix, bag)
    burst, b_offset = 30000, 1_000_000          # B's states carry seq > b_offset
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    nodes = [graph.node.__class__(n, namespace=topic_prefix, context=graph.context)
             for n in ('pub_a', 'pub_b')]
    pub_a, pub_b = (n.create_publisher(DeviceState, STATE_TOPIC, reliable) for n in nodes)
    msg = DeviceState(task_dim=3, pose=[0.0] * 3, twist=[0.0] * 3, hand_wrench=[0.0] * 3,
                      applied_wrench=[0.0] * 3)

    def publish(pub: Any, seqs: range) -> None:
        for seq in seqs:
            msg.seq = seq
            pub.publish(msg)

    def status(key: str) -> int:
        return int(graph.statuses[-1][2].get(key, '0')) if graph.statuses else -1

    received, lost = f'received {STATE_TOPIC}', f'lost {STATE_TOPIC}'
    stopped = False
    try:
        _wait_for_line(proc, 'recording to', 40.0)
        graph.until('publishers matched', lambda: all(
            p.get_subscription_count() > 0 for p in (pub_a, pub_b)))
        publish(pub_a, range(1, 4))
        publish(pub_b, range(b_offset + 1, b_offset + 3))
        graph.until('5 states received', lambda: status(received) == 5)
        proc.send_signal(signal.SIGSTOP)
        stopped = True
        publish(pub_a, range(4, 4 + burst))
        publish(pub_b, range(b_offset + 3, b_offset + 4))
        proc.send_signal(signal.SIGCONT)
        stopped = False
        total = 3 + burst + 3
        graph.until('every state received or counted lost', timeout=60.0,
                    cond=lambda: status(received) + status(lost) == total)
        values = graph.statuses[-1][2]
    finally:
        if stopped:
            proc.send_signal(signal.SIGCONT)
        for node in nodes:
            node.destroy_node()
        graph.close()
        proc.send_signal(signal.SIGINT)
        log, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, log
    seqs, _ = _seqs_by_topic(bag, topic_prefix)
    states = seqs['/haptic/device/state']
    in_bag_a = sum(1 for s in states if s < b_offset)
    lost_a, lost_b = 3 + burst - in_bag_a, 3 - (len(states) - in_bag_a)
    # (each publisher's last state is taken: at most 101 states were received after it,
    # far fewer than the recorder's reader history holds)
    assert {3 + burst, b_offset + 3} <= set(states) and lost_a >= 1, (lost_a, states[-3:])
    assert int(values[lost]) == lost_a + lost_b == total - len(states)
    by_publisher = {k.removeprefix(f'{lost} from '): int(v) for k, v in values.items()
                    if k.startswith(f'{lost} from ')}
    expected = {p: n for p, n in ((f'{topic_prefix}/pub_a', lost_a),
                                  (f'{topic_prefix}/pub_b', lost_b)) if n}
    assert by_publisher == expected, values
    listed = ', '.join(f'{STATE_TOPIC} from {p}: {n}' for p, n in expected.items())
    assert f'lost before the recorder: {lost_a + lost_b} ({listed})' in log, log
