"""``haptic-topology replay BAG``: publish a bag's messages with their recorded timing.

Plain replay publishes every message (or those of ``--topics``) as the recorded CDR bytes
(``Publisher.publish(bytes)``, nothing is deserialised) on its recorded topic, at the
recorded receive times scaled by ``1 / --rate``, from ``--start-offset`` seconds into the
bag, once or ``--loop``. Each topic gets the QoS its publishers offered (the bag's
``offered_qos_profiles``), so e.g. recorded device states and LMI updates drive a live
``lmi_controller`` exactly as the device and the VE did. A topic whose type the bag holds in
an older definition than the installed one is re-serialised as the installed type when
fields were only appended since (``LmiUpdate`` and ``DeviceState`` before their contact
fields: the new fields empty or zero, :func:`~haptic_topology.bag.reader.upgraders`), and
left out, and named in the summary line, when the definition changed otherwise
(``DeviceCommand`` before ``controller_id``, a field inserted in the middle): its bytes would
be misread as the current type; naming it in ``--topics`` is an error.

``--check-controller`` is the controller's regression check: it starts ``lmi_controller``
itself (in its own namespace, with the bag's scenario and the recorded control law), feeds
it the recorded device states and LMI updates, records its commands and compares them with
the recorded ones state by state. What the controller needs to reproduce a command exactly:

* the same parameters (scenario, mode; the gains are the scenario's);
* the same states, in order, and only those it answered in the run: a state it skipped
  (late, overwritten in its depth-1 queue) changes the next cycle's ``dt``;
* each LMI update applied between the same two states as in the run. The recorder's
  receive order is not the controller's (under load the recorder got updates up to 8 ms
  after the controller), so the plan uses what every command carries: ``update_age``
  grows from command to command while the controller uses the same update, and
  ``header.stamp - update_age`` is when it received its newest one. Before the first state
  of each such group, every update the VE had published (its header stamp) by then is
  applied, at least the next one.

Only commands whose state is in the bag are compared (the recorder may have joined after
the device started).

The check runs in lock-step, not in recorded time: each state is published once the live
controller has answered the previous one (again if no answer comes within 0.3 s: the
controller ignores a state it has already answered), each update 2 ms before the next
state. The controller takes ``dt`` from the states' stamps, so the pace does not matter,
and its depth-1 best-effort state queue cannot drop a state (at recorded speed on 2 cores
it dropped 2-3 %, each drop changing the next ~8 commands by up to 0.1 N). Then the
controller computes bit for bit the same commands (measured: 0 difference over 1966
commands of a 2 s fig8 run); any difference means the control code changed.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import (
    Bag,
    BagMessage,
    decoder,
    iter_messages,
    open_bag,
    outdated_types,
    read_channels,
    require_types,
    upgraders,
)
from haptic_topology.errors import BagError, HapticTopologyError
from haptic_topology.msgdefs import type_name
from haptic_topology.vocabulary import TOPIC_LMI_ACK, ControlMode

STATE = vocab.TOPIC_STATE
COMMAND = vocab.TOPIC_COMMAND
UPDATE = vocab.TOPIC_LMI
HAND_INPUTS = vocab.TOPIC_HAND_INPUTS
#: One ``HandInput`` per cycle: bags recorded before the hand inputs were batched.
HAND = vocab.TOPIC_HAND_LEGACY
#: A recorded and a replayed command agree when no wrench component differs by more (N or
#: N m). The controller is deterministic given the same inputs in the same order, so the
#: expected difference is 0; 1e-9 leaves room for a different BLAS summation order only.
DEFAULT_TOLERANCE = 1e-9


class ReplayError(HapticTopologyError):
    """The replay could not run (no subscriber, controller failed to start, ...)."""


@dataclass(frozen=True)
class Item:
    """One message to publish ``t`` seconds (at rate 1) after the replay starts."""

    t: float
    topic: str
    msgtype: str
    data: bytes
    #: DeviceState.seq for states of a controller plan (lock-step replay), else -1.
    seq: int = -1


@dataclass
class ReplayStats:
    """What a replay did: messages published per topic, lateness of the publish times."""

    published: dict[str, int] = field(default_factory=dict)
    late_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    #: Topics left out: recorded with an older definition of their type (module doc).
    left_out: list[str] = field(default_factory=list)

    def line(self) -> str:
        text = (f'published {sum(self.published.values())} messages on '
                f'{len(self.published)} topics in {self.wall_s:.2f} s')
        if self.left_out:
            text += (f'; left out {", ".join(self.left_out)} (recorded with an older message '
                     'definition than the installed one)')
        if self.late_ms:
            late = np.array(self.late_ms)
            text += (f'; behind the recorded timing p50 {np.percentile(late, 50):.3f} ms, '
                     f'p99 {np.percentile(late, 99):.3f} ms')
        return text


def plan(bag: Bag, topics: Iterable[str] | None = None, start_offset: float = 0.0) -> list[Item]:
    """Messages of ``bag`` (``topics`` only if given) from ``start_offset`` s on, as items;
    without the topics of :func:`left_out` (an error if ``topics`` names one)."""
    wanted = None if topics is None else {'/' + t.lstrip('/') for t in topics}
    old = left_out(bag)
    if wanted is not None and wanted & set(old):
        raise BagError(f'{bag.path}: cannot replay {", ".join(sorted(wanted & set(old)))}: '
                       'recorded with an older definition of '
                       f'{", ".join(sorted({old[t] for t in wanted & set(old)}))} than the '
                       'installed one')
    msgs = [m for m in iter_messages(bag)
            if (wanted is None or m.topic in wanted) and m.topic not in old]
    if wanted is not None:
        missing = wanted - {m.topic for m in msgs}
        if missing:
            raise BagError(f'{bag.path}: no messages on {", ".join(sorted(missing))} (it has '
                           f'{", ".join(sorted(bag.topics))})')
    if not msgs:
        raise BagError(f'{bag.path}: no messages to replay')
    t0 = min(m.log_time for m in msgs) + int(start_offset * 1e9)
    upgrade = upgraders(bag)
    items = [Item((m.log_time - t0) * 1e-9, m.topic, m.msgtype,
                  upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data)
             for m in msgs if m.log_time >= t0]
    if not items:
        raise BagError(f'{bag.path}: --start-offset {start_offset:g} s is past the bag\'s end')
    items.sort(key=lambda it: it.t)  # stable: equal times keep file order
    return items


def left_out(bag: Bag) -> dict[str, str]:
    """Topic -> type of the topics plain replay leaves out: their type is recorded in an older
    definition than the installed one, changed other than by appended fields (module doc)."""
    old = outdated_types(bag) - set(upgraders(bag))
    return {t: ch['type'] for t, ch in read_channels(bag).items() if ch['type'] in old}


@dataclass
class ControllerPlan:
    """States and updates ordered as the recorded controller saw them (see module doc)."""

    items: list[Item]
    commands: dict[int, Any]
    scenario: str
    mode: str
    matched_updates: int
    updates: int


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def controller_plan(bag: Bag) -> ControllerPlan:
    """Build the regression replay of the recorded controller (see module doc)."""
    require_types(bag, {STATE: type_name('DeviceState'), COMMAND: type_name('DeviceCommand'),
                        UPDATE: type_name('LmiUpdate')})
    decode = decoder(bag=bag)
    states: list[tuple[BagMessage, Any]] = []
    commands: dict[int, Any] = {}
    updates: list[tuple[BagMessage, Any]] = []
    answered: set[int] = set()
    for m in iter_messages(bag):
        if m.topic.endswith(STATE):
            states.append((m, decode(m)))
        elif m.topic.endswith(COMMAND):
            c = decode(m)
            commands.setdefault(int(c.state_seq), c)
        elif m.topic.endswith(UPDATE):
            updates.append((m, decode(m)))
        elif m.topic.endswith(HAND_INPUTS):
            answered.update(int(s) for s in decode(m).state_seq)
        elif m.topic.endswith(HAND):
            answered.add(int(decode(m).state_seq))
    answered |= set(commands)
    if not commands:
        raise BagError(f'{bag.path}: no {COMMAND} messages: nothing to compare')
    scenario = str(((bag.metadata or {}).get('custom_data') or {}).get('scenario', ''))
    modes = [int(c.mode) for c in commands.values() if int(c.mode) != ControlMode.ZERO]
    mode = (ControlMode.ACCELERATION_ONLY.label
            if modes and max(set(modes), key=modes.count) == ControlMode.ACCELERATION_ONLY
            else ControlMode.PENALTY.label)
    updates.sort(key=lambda u: int(u[1].seq))
    published = np.array([_stamp(u[1].header) for u in updates])  # VE stamps at publish
    answered_states = [(m, st) for m, st in states if int(st.seq) in answered]
    # Group the commands by the update they used: the age grows from one command to the
    # next while the update is the same, and the controller's receive time of its newest
    # update (stamp - age, plus this cycle's compute time) jumps by ~1 update period.
    groups: dict[int, float] = {}  # seq of a group's first state -> update receive time
    prev_age = prev_got = math.inf
    first = -1
    for _, st in answered_states:
        cmd = commands.get(int(st.seq))
        if cmd is None or not math.isfinite(cmd.update_age):
            continue
        age = float(cmd.update_age)
        got = _stamp(cmd.header) - age
        # The age of one update only grows; it falls when a newer one was taken. A jump of
        # the receive time by more than 5 ms also marks a new update (after a gap in the
        # states the age may have grown anyway); compute times of up to 2 ms were seen.
        if first < 0 or age < prev_age or got > prev_got + 5e-3:
            first = int(st.seq)
            groups[first] = got
        groups[first] = min(groups[first], got)  # least compute time: closest to receipt
        prev_age, prev_got = age, got
    first_group = min(groups, default=-1)
    upgrade = upgraders(bag)

    def data(m: BagMessage) -> bytes:    # as the installed type (fields appended since)
        return upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data

    items: list[Item] = []
    applied = -1  # index of the last update placed so far
    t_first = states[0][0].log_time if states else 0
    for m, st in answered_states:
        seq = int(st.seq)
        t = (m.log_time - t_first) * 1e-9
        cmd = commands.get(seq)
        target = applied
        if seq in groups and published.size:
            # A new update was taken before this state (except for the first group, which
            # may go on with the update of the watchdog phase): every update the VE had
            # published by then (at least the next one), in order.
            newer = applied + (0 if seq == first_group else 1)
            target = max(newer, int(np.searchsorted(published, groups[seq], side='right')) - 1)
        elif cmd is not None and int(cmd.mode) != 2 and published.size and not math.isfinite(
                cmd.update_age) and applied < 0:
            # Answered by a synced controller without an age (a watchdog state before the
            # loop engaged): the updates published before the state was stamped.
            target = int(np.searchsorted(published, _stamp(st.header), side='right')) - 1
        target = min(target, len(updates) - 1)
        for j in range(applied + 1, target + 1):
            u = updates[j][0]
            items.append(Item(max(t - 2e-4, 0.0), u.topic, u.msgtype, data(u)))
        applied = max(applied, target)
        items.append(Item(t, m.topic, m.msgtype, data(m), seq))
    return ControllerPlan(items, {s: c for s, c in commands.items()
                                  if s in {int(st.seq) for _, st in answered_states}},
                          scenario, mode, len(groups), len(updates))


def _qos_profile(metadata: dict[str, str], topic: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliable, depth = True, 10
    try:
        offered = parse_qos(metadata.get('offered_qos_profiles', ''))
    except (ReaderError, KeyError, TypeError):
        offered = []
    if offered:
        reliable = all(q.reliability.name == 'RELIABLE' for q in offered)
        depth = max(1, max(q.depth for q in offered))
    elif topic.endswith((STATE, COMMAND)):
        reliable, depth = False, 1
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Type``."""
    pkg, _, name = msgtype.partition('/msg/')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise BagError(f'message type {msgtype}: no Python message package {pkg} installed '
                       'to publish it') from None


class Publishers:
    """One publisher per topic of the items (QoS from the bag), under ``namespace``."""

    def __init__(self, node: Any, bag: Bag, items: Sequence[Item], namespace: str = '') -> None:
        channels = read_channels(bag)
        self.pubs: dict[str, Any] = {}
        for topic, msgtype in {it.topic: it.msgtype for it in items}.items():
            name = topic if not namespace or topic == '/diagnostics' else (
                namespace.rstrip('/') + '/' + topic.lstrip('/'))
            qos = _qos_profile(channels.get(topic, {}).get('metadata', {}), topic)
            self.pubs[topic] = node.create_publisher(message_class(msgtype), name, qos)

    def wait_for_subscribers(self, topics: Iterable[str], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        pending = [t for t in topics if t in self.pubs]
        while pending and time.monotonic() < deadline:
            pending = [t for t in pending if self.pubs[t].get_subscription_count() == 0]
            time.sleep(0.02)
        if pending:
            raise ReplayError(f'no subscriber on {", ".join(pending)} within {timeout:g} s')
        # The publisher sees the subscriber first; a reliable message sent before the
        # subscriber has matched this publisher in turn would be lost.
        time.sleep(0.5)

    def publish(self, items: Sequence[Item], rate: float, loop: bool = False,
                stop: threading.Event | None = None) -> ReplayStats:
        """Publish ``items`` at their times / ``rate`` (again and again with ``loop``)."""
        stats = ReplayStats()
        start = time.perf_counter()
        span = items[-1].t if items else 0.0
        rounds = 0
        while True:
            base = start + rounds * (span / rate + 1e-3)
            for it in items:
                due = base + it.t / rate
                while (rem := due - time.perf_counter()) > 0:
                    time.sleep(rem)
                if stop is not None and stop.is_set():
                    break
                self.pubs[it.topic].publish(it.data)
                stats.late_ms.append(1e3 * (time.perf_counter() - due))
                stats.published[it.topic] = stats.published.get(it.topic, 0) + 1
            rounds += 1
            if not loop or (stop is not None and stop.is_set()):
                break
        stats.wall_s = time.perf_counter() - start
        return stats


    def publish_lockstep(self, items: Sequence[Item], answered: threading.Condition,
                         done: dict[int, Any], acked: dict[int, int], timeout: float = 0.3,
                         retries: int = 3) -> ReplayStats:
        """Publish ``items`` in order, each only once the previous one was taken: a state
        once it was answered (``done``), an update once the controller acknowledged it
        (``acked``: update seq -> count, on ``haptic/lmi/ack``), so the controller sees the
        recorded order whatever the machine's load.

        A message whose answer or acknowledgement does not come within ``timeout`` is
        published again (the controller ignores a state it has already answered; an update
        taken twice is the same re-sync), up to ``retries`` times.
        """
        stats = ReplayStats()
        start = time.perf_counter()
        for it in items:
            pub = self.pubs[it.topic]
            if it.seq < 0:
                useq = _update_seq(it.data)
                before = acked.get(useq, 0)

                def taken(useq: int = useq, before: int = before) -> bool:
                    return acked.get(useq, 0) > before

                with answered:
                    for _ in range(retries):
                        pub.publish(it.data)
                        if answered.wait_for(taken, timeout):
                            break
            else:
                seq = it.seq

                def seen(seq: int = seq) -> bool:
                    return seq in done

                with answered:
                    for _ in range(retries):
                        pub.publish(it.data)
                        if answered.wait_for(seen, timeout):
                            break
            stats.published[it.topic] = stats.published.get(it.topic, 0) + 1
        stats.wall_s = time.perf_counter() - start
        return stats


def _update_seq(data: Any) -> int:
    """``LmiUpdate.seq`` of a message as published (a message object or raw CDR)."""
    seq = getattr(data, 'seq', None)
    if seq is None:
        from rclpy.serialization import deserialize_message

        from haptic_topology_msgs.msg import LmiUpdate
        seq = deserialize_message(data, LmiUpdate).seq
    return int(seq)


class _Spinner:
    """rclpy init, one node, its executor spun in a thread (timeouts: see the notes)."""

    def __init__(self, name: str) -> None:
        import rclpy
        from rclpy.experimental import EventsExecutor

        from haptic_topology.nodes.dds_env import localhost_discovery_default

        self._rclpy = rclpy
        localhost_discovery_default(os.environ)     # the nodes' DDS setup (run_main)
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


def replay(bag_path: str | Path, rate: float = 1.0, topics: Sequence[str] | None = None,
           loop: bool = False, start_offset: float = 0.0, wait_subscribers: float = 0.0,
           stop: threading.Event | None = None, namespace: str = '') -> ReplayStats:
    """Plain replay (see module doc), topics under ``namespace`` (except /diagnostics);
    returns what was published."""
    bag = open_bag(bag_path)
    items = plan(bag, topics, start_offset)
    spinner = _Spinner('haptic_replay')
    try:
        pubs = Publishers(spinner.node, bag, items, namespace)
        if wait_subscribers > 0:
            pubs.wait_for_subscribers(pubs.pubs, wait_subscribers)
        stats = pubs.publish(items, rate, loop, stop)
        stats.left_out = [] if topics else sorted(left_out(bag))
        return stats
    finally:
        spinner.close()


@dataclass
class CheckResult:
    """Recorded vs replayed commands of the controller regression check."""

    compared: int
    recorded: int
    replayed: int
    missing: int
    max_abs_diff: float
    tolerance: float
    mode: str
    scenario: str
    stats: ReplayStats
    #: state seq -> largest |difference| of its command (inf: other mode or shape).
    diffs: dict[int, float] = field(default_factory=dict)
    missing_seqs: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.compared > 0 and self.max_abs_diff <= self.tolerance

    def line(self) -> str:
        return (f'controller check ({self.scenario}, {self.mode}): {self.compared} commands '
                f'compared of {self.recorded} recorded ({self.missing} not answered live); '
                f'max |difference| {self.max_abs_diff:.3g} (tolerance {self.tolerance:g}): '
                f'{"OK" if self.ok else "DIFFERENT"}')


def check_controller(bag_path: str | Path, params: Path,
                     scenario: str | None = None, tolerance: float = DEFAULT_TOLERANCE,
                     startup_timeout: float = 40.0, log_dir: Path | None = None) -> CheckResult:
    """The controller regression check (see module doc)."""
    from haptic_topology.nodes.qos import QOS_LMI
    bag = open_bag(bag_path)
    cp = controller_plan(bag)
    scenario = scenario or cp.scenario
    if not scenario:
        raise BagError(f'{bag.path}: no scenario in metadata.yaml custom_data; give '
                       '--scenario')
    ns = f'/replay_{os.getpid()}_{int(time.time() * 1e3) % 100000}'
    logs = Path(log_dir or tempfile.mkdtemp(prefix='haptic_replay_'))
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / 'lmi_controller.log'
    argv = [sys.executable, '-m', 'haptic_topology.nodes.lmi_controller', '--ros-args',
            '--params-file', str(params), '-p', f'scenario:={scenario}', '-p',
            f'mode:={cp.mode}', '-p', 'ack_updates:=true', '-r', f'__ns:={ns}']
    live: dict[int, Any] = {}
    spinner = _Spinner('haptic_replay_check')
    with log.open('wb') as handle:
        proc = subprocess.Popen(argv, stdout=handle, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONUNBUFFERED='1'),
                                start_new_session=True)
        try:
            from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

            from haptic_topology_msgs.msg import DeviceCommand

            answered = threading.Condition()

            def keep(msg: Any) -> None:
                with answered:
                    live.setdefault(int(msg.state_seq), (int(msg.mode), np.array(msg.wrench)))
                    answered.notify_all()

            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.BEST_EFFORT)
            sub = spinner.node.create_subscription(DeviceCommand, f'{ns}/{COMMAND}', keep,
                                                   qos)
            acked: dict[int, int] = {}

            def ack(msg: Any) -> None:
                with answered:
                    acked[int(msg.data)] = acked.get(int(msg.data), 0) + 1
                    answered.notify_all()

            from std_msgs.msg import UInt64

            spinner.node.create_subscription(UInt64, f'{ns}/{TOPIC_LMI_ACK}', ack, QOS_LMI)
            pubs = Publishers(spinner.node, bag, cp.items, ns)
            deadline = time.monotonic() + startup_timeout
            while sub.get_publisher_count() == 0 and time.monotonic() < deadline:
                if proc.poll() is not None:
                    raise ReplayError(f'lmi_controller exited with {proc.returncode}: '
                                      f'{log.read_text(errors="replace")[-800:]}')
                time.sleep(0.05)
            pubs.wait_for_subscribers(pubs.pubs, max(deadline - time.monotonic(), 0.1))
            stats = pubs.publish_lockstep(cp.items, answered, live, acked)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(10.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            spinner.close()
    diffs: dict[int, float] = {}
    missing: list[int] = []
    for seq, cmd in sorted(cp.commands.items()):
        got = live.get(seq)
        if got is None:
            missing.append(seq)
            continue
        rec = np.array(cmd.wrench, dtype=float)
        mode_diff = 0.0 if got[0] == int(cmd.mode) else math.inf
        diffs[seq] = max(float(np.max(np.abs(rec - got[1]), initial=0.0))
                         if rec.shape == got[1].shape else math.inf, mode_diff)
    return CheckResult(len(diffs), len(cp.commands), len(live), len(missing),
                       max(diffs.values(), default=math.inf), tolerance, cp.mode, scenario,
                       stats, diffs, missing)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', type=Path, help='bag directory (or .mcap file)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='time factor (2 = twice as fast; default 1); --check-controller '
                        'runs in lock-step instead')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', help='topics to publish '
                        '(default: all)')
    parser.add_argument('--loop', action='store_true', help='start again at the end, until '
                        'Ctrl-C')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                        help='skip the first S seconds of the bag')
    parser.add_argument('--namespace', default='', help='publish under this namespace '
                        '(e.g. /replay; /diagnostics stays)')
    parser.add_argument('--wait-subscribers', type=float, default=0.0, metavar='S',
                        help='wait up to S seconds for a subscriber on every topic')
    parser.add_argument('--check-controller', action='store_true',
                        help='start lmi_controller, feed it the recorded states and updates, '
                        'compare its commands with the recorded ones')
    parser.add_argument('--scenario', help='scenario for --check-controller (default: the '
                        "bag's)")
    parser.add_argument('--params', type=Path, help='params file for --check-controller '
                        '(default config/haptic_topology.yaml)')
    parser.add_argument('--tolerance', type=float, default=DEFAULT_TOLERANCE,
                        help=f'--check-controller: largest allowed wrench difference '
                        f'(default {DEFAULT_TOLERANCE:g})')


def run(args: argparse.Namespace) -> int:
    """The ``replay`` subcommand (see module doc)."""
    rate = float(args.rate)
    if not (rate > 0 and math.isfinite(rate)):
        raise BagError(f'--rate: expected a positive factor, got {rate}')
    if args.start_offset < 0:
        raise BagError(f'--start-offset: expected seconds >= 0, got {args.start_offset}')
    if args.check_controller:
        from haptic_topology.paths import config_dir

        params = args.params or config_dir() / 'haptic_topology.yaml'
        res = check_controller(args.bag, params, args.scenario, args.tolerance)
        print(res.stats.line())
        print(res.line())
        return 0 if res.ok else 1
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    stats = replay(args.bag, rate, args.topics, args.loop, args.start_offset,
                   args.wait_subscribers, stop, args.namespace)
    print(stats.line())
    return 0
