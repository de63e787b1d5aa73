"""What a replay of a bag publishes, offline: the plan of a plain replay (messages, times,
topics left out) and the plan of the controller check (which states, which updates between
them), and the check's result. The publishing side (rclpy) is
:mod:`haptic_topology.nodes.replay`, which documents ``haptic-topology replay``.
"""

from __future__ import annotations

import argparse
import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import (
    Bag,
    BagMessage,
    decoder,
    iter_messages,
    outdated_types,
    read_channels,
    require_types,
    upgraders,
)
from haptic_topology.errors import BagError
from haptic_topology.messages.check import GraphFilter
from haptic_topology.messages.definitions import type_name
from haptic_topology.vocabulary import ControlMode

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
    #: Reliable topics whose last messages a subscriber had not acknowledged when the replay
    #: stopped waiting for it (10 s at the end of the replay).
    unacknowledged: list[str] = field(default_factory=list)

    def line(self) -> str:
        text = (f'published {sum(self.published.values())} messages on '
                f'{len(self.published)} topics in {self.wall_s:.2f} s')
        if self.left_out:
            text += (f'; left out {", ".join(self.left_out)} (recorded with an older message '
                     'definition than the installed one)')
        if self.unacknowledged:
            text += (f'; not acknowledged by every subscriber: {", ".join(self.unacknowledged)} '
                     '(a subscriber too slow or gone: it may have missed the last messages)')
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

    def wanted_messages() -> Iterable[BagMessage]:
        return (m for m in iter_messages(bag)
                if (wanted is None or m.topic in wanted) and m.topic not in old)

    # A first pass finds the start and the topics without keeping a message, so the
    # messages are held once, as the items.
    first, seen = None, set()
    for m in wanted_messages():
        first = m.log_time if first is None else min(first, m.log_time)
        seen.add(m.topic)
    if wanted is not None:
        missing = wanted - seen
        if missing:
            raise BagError(f'{bag.path}: no messages on {", ".join(sorted(missing))} (it has '
                           f'{", ".join(sorted(bag.topics))})')
    if first is None:
        raise BagError(f'{bag.path}: no messages to replay')
    t0 = first + int(start_offset * 1e9)
    upgrade = upgraders(bag)
    items = [Item((m.log_time - t0) * 1e-9, m.topic, m.msgtype,
                  upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data)
             for m in wanted_messages() if m.log_time >= t0]
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
    #: The recorder's graph: the replayed controller is of it (its messages only are read)
    graph_id: str = ''


@dataclass(frozen=True)
class _Seq:
    """What the plan keeps of a state or an update besides its bytes: seq and header (the
    decoded arrays are left to the garbage collector: a 15-minute bag holds ~900,000
    states)."""

    seq: int
    header: Any


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
    graph = GraphFilter(str(((bag.metadata or {}).get('custom_data') or {}).get('graph_id')
                            or ''))
    for m in iter_messages(bag):
        if not m.topic.endswith((STATE, COMMAND, UPDATE, HAND_INPUTS)):
            if m.topic.endswith(HAND):
                answered.add(int(decode(m).state_seq))
            continue
        msg = decode(m)
        if not graph.own(msg, m.topic):
            continue            # another graph's (module doc)
        if m.topic.endswith(STATE):
            states.append((m, _Seq(int(msg.seq), msg.header)))
        elif m.topic.endswith(COMMAND):
            commands.setdefault(int(msg.state_seq), msg)
        elif m.topic.endswith(UPDATE):
            updates.append((m, _Seq(int(msg.seq), msg.header)))
        elif m.topic.endswith(HAND_INPUTS):
            answered.update(int(s) for s in msg.state_seq)
    answered |= set(commands)
    if not commands:
        raise BagError(f'{bag.path}: no {COMMAND} messages: nothing to compare')
    scenario = str(((bag.metadata or {}).get('custom_data') or {}).get('scenario', ''))
    modes = [int(c.mode) for c in commands.values() if int(c.mode) != ControlMode.ZERO]
    mode = (ControlMode.ACCELERATION_ONLY.label
            if modes and max(set(modes), key=modes.count) == ControlMode.ACCELERATION_ONLY
            else ControlMode.PENALTY.label)
    answered_states = [(m, st) for m, st in states if int(st.seq) in answered]
    upgrade = upgraders(bag)

    def data(m: BagMessage) -> bytes:    # as the installed type (fields appended since)
        return upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data

    if type_name('DeviceCommand') in outdated_types(bag):
        # Recorded before DeviceCommand.update_seq: reconstructed from the update ages.
        items, groups = _items_from_ages(answered_states, commands, updates, data)
    else:
        items, groups = _items_from_update_seqs(answered_states, commands, updates, data)
    replayed = {int(st.seq) for _, st in answered_states}
    return ControllerPlan(items, {s: c for s, c in commands.items() if s in replayed},
                          scenario, mode, groups, len(updates), graph.graph_id)


def _items_from_update_seqs(answered_states: list[tuple[BagMessage, Any]],
                            commands: dict[int, Any], updates: list[tuple[BagMessage, Any]],
                            data: Any) -> tuple[list[Item], int]:
    """The plan's items from what each command says: before each state, the updates (in the
    recorded order, the VE's publishing order) up to the one its command names as the newest
    the controller had taken (``update_seq``). Returns the items and how many states had
    updates placed before them."""
    items: list[Item] = []
    fed = 0                                 # updates placed so far (recorded order)
    groups = 0
    t_first = answered_states[0][0].log_time if answered_states else 0
    where: dict[int, list[int]] = {}        # update seq -> its indexes, ascending
    for j, (_, u) in enumerate(updates):
        where.setdefault(int(u.seq), []).append(j)
    for m, st in answered_states:
        seq = int(st.seq)
        t = (m.log_time - t_first) * 1e-9
        cmd = commands.get(seq)
        newest = -1 if cmd is None else int(cmd.update_seq)
        at = where.get(newest, []) if newest >= 0 else []
        k = bisect.bisect_left(at, fed)     # the first update named so, not placed yet
        if k < len(at):
            for u, _ in updates[fed:at[k] + 1]:
                items.append(Item(max(t - 2e-4, 0.0), u.topic, u.msgtype, data(u)))
            fed = at[k] + 1
            groups += 1
        items.append(Item(t, m.topic, m.msgtype, data(m), seq))
    return items, groups


def _items_from_ages(answered_states: list[tuple[BagMessage, Any]], commands: dict[int, Any],
                     updates: list[tuple[BagMessage, Any]], data: Any
                     ) -> tuple[list[Item], int]:
    """The plan's items of a bag recorded before ``DeviceCommand.update_seq``: the updates
    placed by the commands' ``update_age`` (see :mod:`haptic_topology.nodes.replay`)."""
    updates = sorted(updates, key=lambda u: int(u[1].seq))
    published = np.array([_stamp(u[1].header) for u in updates])  # VE stamps at publish
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
    items: list[Item] = []
    applied = -1  # index of the last update placed so far
    t_first = answered_states[0][0].log_time if answered_states else 0
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
    return items, len(groups)


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


