"""The controller regression check offline: its plan (which recorded states and LMI updates
the live controller is fed, in which order) and the comparison of the live controller's
commands with the recorded ones. The publishing side is
:mod:`haptic_topology.nodes.replay`, which documents ``replay --check-controller``.

The check streams: :func:`controller_plan` reads the bag once and keeps, in numpy arrays,
only what the plan and the verdict need per command (its state's seq, mode, ``update_seq``,
wrench) and per update (seq, stamp); :meth:`ControllerPlan.items` reads the states and
updates from the bag again as they are published, and :class:`CommandCheck` compares each
live answer as it arrives. Memory grows by about 70 bytes a recorded command; the messages
themselves are never all in memory.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from haptic_topology.bag.reader import (
    Bag,
    BagMessage,
    decoder,
    iter_messages,
    outdated_types,
    require_types,
    upgraders,
)
from haptic_topology.bag.replay import (
    COMMAND,
    HAND,
    HAND_INPUTS,
    STATE,
    UPDATE,
    Item,
    ReplayStats,
)
from haptic_topology.errors import BagError
from haptic_topology.messages.check import GraphFilter
from haptic_topology.messages.definitions import type_name
from haptic_topology.vocabulary import ControlMode


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def _find(sorted_seqs: np.ndarray, seq: int) -> int:
    """Index of ``seq`` in ``sorted_seqs`` (uint64, ascending), -1 if absent."""
    i = int(np.searchsorted(sorted_seqs, np.uint64(seq)))
    return i if i < sorted_seqs.size and int(sorted_seqs[i]) == seq else -1


def _u64(a: array) -> np.ndarray:
    return np.frombuffer(a, dtype=np.uint64) if len(a) else np.zeros(0, dtype=np.uint64)


def _f64(a: array) -> np.ndarray:
    return np.frombuffer(a, dtype=np.float64) if len(a) else np.zeros(0)


@dataclass
class ControllerPlan:
    """States and updates ordered as the recorded controller saw them (see module doc and
    :mod:`haptic_topology.nodes.replay`). The recorded commands are the first command of
    each state seq, sorted by seq: ``seqs``, ``modes``, their wrenches
    ``wrench[wrench_at[i]:wrench_at[i + 1]]`` (N, N m)."""

    bag: Bag
    scenario: str
    mode: str
    #: The recorder's graph: the replayed controller is of it (its messages only are read)
    graph_id: str
    #: Topic -> type of the states and updates published.
    topics: dict[str, str]
    #: Sorted seqs of the states the controller answered in the run.
    answered: np.ndarray
    seqs: np.ndarray
    modes: np.ndarray
    wrench: np.ndarray
    wrench_at: np.ndarray
    #: Own LMI updates in the bag: how many, their seqs (file order) and ordinals among the
    #: messages of the update topics (to find them again without decoding).
    updates: int
    update_seqs: np.ndarray
    update_ordinals: np.ndarray
    #: Per recorded command: ``update_seq``, or (bags recorded before it) ``update_age`` (s)
    #: and its header stamp (s).
    update_seq: np.ndarray | None
    ages: np.ndarray | None = None
    stamps: np.ndarray | None = None
    #: Bags before ``update_seq``: update stamps in seq order, and the groups of states that
    #: used one update (seq of the group's first state, sorted -> update receive time).
    published: np.ndarray | None = None
    group_seqs: np.ndarray | None = None
    group_got: np.ndarray | None = None
    #: Bags with ``update_seq``: the update indexes sorted by seq (equal seqs in file order)
    #: and the seqs in that order.
    by_seq: np.ndarray | None = None
    sorted_seqs: np.ndarray | None = None
    #: Set by a full iteration of :meth:`items`: states that had updates placed before them,
    #: and which recorded commands' states are in the bag (only those are compared).
    matched_updates: int = -1
    present: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: Set by a full iteration of :meth:`items` (bags with ``update_seq``): the recorded
    #: commands whose states are in the bag but not all of their inputs, so not published
    #: nor compared: the first command naming an update the bag does not hold (the
    #: recorder received it after that command and was stopped before writing it, e.g. a
    #: cut bag) and every command after it (the controller's state carries over); that
    #: update's seq (-1: none).
    unchecked: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    absent_update: int = -1

    def command(self, seq: int) -> int:
        """Index of the recorded command answering state ``seq``, -1 if none."""
        return _find(self.seqs, seq)

    def recorded_wrench(self, i: int) -> np.ndarray:
        return self.wrench[int(self.wrench_at[i]):int(self.wrench_at[i + 1])]

    def _reader(self) -> Iterator[BagMessage]:
        return iter_messages(replace(self.bag, truncated=[], topics={}))

    def _answered_states(self) -> Iterator[tuple[BagMessage, int, Any]]:
        """(message, seq, header) of the graph's answered states, in file order."""
        decode = decoder(bag=self.bag)
        graph = GraphFilter(self.graph_id)
        for m in self._reader():
            if m.topic.endswith(STATE):
                msg = decode(m)
                if graph.own(msg, m.topic) and _find(self.answered, int(msg.seq)) >= 0:
                    yield m, int(msg.seq), msg.header

    def _updates(self) -> Generator[BagMessage, None, None]:
        """The graph's updates in file order (in seq order for bags before ``update_seq``,
        through a buffer as deep as the file's order departs from it)."""
        def in_file_order() -> Iterator[BagMessage]:
            ordinal = k = 0
            for m in self._reader():
                if m.topic.endswith(UPDATE):
                    if k < self.update_ordinals.size and ordinal == self.update_ordinals[k]:
                        yield m
                        k += 1
                    ordinal += 1
        if self.update_seq is not None:
            yield from in_file_order()
            return
        order = np.argsort(self.update_seqs, kind='stable')   # as sorted() did
        waiting: dict[int, BagMessage] = {}
        source = enumerate(in_file_order())
        for j in order:
            while int(j) not in waiting:
                i, m = next(source)
                waiting[i] = m
            yield waiting.pop(int(j))

    def items(self) -> Iterator[Item]:
        """The plan's items, read from the bag as they are taken: before each state, the
        updates the controller had taken by then (module doc of
        :mod:`haptic_topology.nodes.replay`). They end before the first state whose
        recorded command names an update the bag does not hold (:attr:`unchecked`)."""
        upgrade = upgraders(self.bag)

        def data(m: BagMessage) -> bytes:    # as the installed type (fields appended since)
            return upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data

        present = np.zeros(self.seqs.size, dtype=bool)
        unchecked = np.zeros(self.seqs.size, dtype=bool)
        absent = -1                         # the first update named but not in the bag
        updates = self._updates()
        placed = 0                          # updates placed so far (plan order)
        groups = 0
        t_first = None
        target: Callable[[int, int, Any, int], tuple[int, bool]] = (
            self._target_by_seq if self.update_seq is not None else self._target_by_age)
        try:
            for m, seq, header in self._answered_states():
                t_first = m.log_time if t_first is None else t_first
                t = (m.log_time - t_first) * 1e-9
                ci = self.command(seq)
                if absent < 0 and ci >= 0:
                    absent = self._absent_update(ci)
                if absent >= 0:             # inputs incomplete from here on: not published
                    if ci >= 0:
                        unchecked[ci] = True
                    continue
                if ci >= 0:
                    present[ci] = True
                last, grouped = target(seq, ci, header, placed)
                groups += grouped
                for _ in range(placed, last + 1):
                    u = next(updates)
                    yield Item(max(t - 2e-4, 0.0), u.topic, u.msgtype, data(u))
                placed = max(placed, last + 1)
                yield Item(t, m.topic, m.msgtype, data(m), seq)
        finally:
            updates.close()
        self.present, self.unchecked, self.absent_update = present, unchecked, absent
        self.matched_updates = (groups if self.update_seq is not None
                                else int(self.group_seqs.size))  # type: ignore[union-attr]

    def _absent_update(self, ci: int) -> int:
        """The update that recorded command ``ci`` names as its controller's newest, if the
        bag does not hold it (-1 otherwise, and for bags before ``update_seq``)."""
        if self.update_seq is None or self.sorted_seqs is None:
            return -1
        newest = int(self.update_seq[ci])
        return newest if newest >= 0 and _find(self.sorted_seqs, newest) < 0 else -1

    def _target_by_seq(self, seq: int, ci: int, header: Any, placed: int) -> tuple[int, bool]:
        """Index of the last update to place before state ``seq``: the first update, not
        placed yet, that its command names as the newest the controller had taken."""
        assert self.update_seq is not None and self.by_seq is not None
        assert self.sorted_seqs is not None
        newest = -1 if ci < 0 else int(self.update_seq[ci])
        if newest < 0:
            return placed - 1, False
        lo, hi = (int(np.searchsorted(self.sorted_seqs, np.uint64(newest), side=side))
                  for side in ('left', 'right'))
        k = lo + int(np.searchsorted(self.by_seq[lo:hi], placed))
        return (int(self.by_seq[k]), True) if k < hi else (placed - 1, False)

    def _target_by_age(self, seq: int, ci: int, header: Any, placed: int) -> tuple[int, bool]:
        """The same for a bag recorded before ``update_seq``: the updates placed by the
        commands' ``update_age`` (module doc of :mod:`haptic_topology.nodes.replay`)."""
        assert self.published is not None and self.group_seqs is not None
        assert self.group_got is not None and self.ages is not None
        applied = placed - 1                # index of the last update placed so far
        target = applied
        gi = _find(self.group_seqs, seq)
        published = self.published
        if gi >= 0 and published.size:
            # A new update was taken before this state (except for the first group, which
            # may go on with the update of the watchdog phase): every update the VE had
            # published by then (at least the next one), in order.
            newer = applied + (0 if gi == 0 else 1)
            target = max(newer, int(np.searchsorted(published, self.group_got[gi],
                                                    side='right')) - 1)
        elif (ci >= 0 and int(self.modes[ci]) != 2 and published.size
              and not math.isfinite(self.ages[ci]) and applied < 0):
            # Answered by a synced controller without an age (a watchdog state before the
            # loop engaged): the updates published before the state was stamped.
            target = int(np.searchsorted(published, _stamp(header), side='right')) - 1
        return min(target, self.updates - 1), False

    def recorded_commands(self) -> Iterator[tuple[int, int, np.ndarray]]:
        """(state seq, mode, wrench) of the recorded commands whose states are in the bag,
        by seq (after a full iteration of :meth:`items`)."""
        for i in np.flatnonzero(self.present):
            yield int(self.seqs[i]), int(self.modes[i]), self.recorded_wrench(int(i))


def controller_plan(bag: Bag) -> ControllerPlan:
    """Read ``bag`` once for what the regression replay of its controller needs (module
    doc); the items come from :meth:`ControllerPlan.items`."""
    require_types(bag, {STATE: type_name('DeviceState'), COMMAND: type_name('DeviceCommand'),
                        UPDATE: type_name('LmiUpdate')})
    decode = decoder(bag=bag)
    custom = (bag.metadata or {}).get('custom_data') or {}
    graph = GraphFilter(str(custom.get('graph_id') or ''))
    # Recorded before DeviceCommand.update_seq: the plan is reconstructed from the ages.
    by_age = type_name('DeviceCommand') in outdated_types(bag)
    hands = array('Q')                      # states answered per the hand inputs
    c_seq, c_mode, c_useq = array('Q'), array('B'), array('q')
    c_age, c_stamp, c_len, c_wrench = array('d'), array('d'), array('H'), array('d')
    s_seq, s_topic = array('Q'), array('H')  # the graph's states: seq, topic (index)
    state_topics: dict[tuple[str, str], int] = {}
    u_seq, u_stamp, u_ordinal = array('Q'), array('d'), array('Q')
    update_topics: dict[str, str] = {}
    ordinal = 0                             # of the message among the update topics'
    for m in iter_messages(bag):
        if not m.topic.endswith((STATE, COMMAND, UPDATE, HAND_INPUTS)):
            if m.topic.endswith(HAND):
                hands.append(int(decode(m).state_seq))
            continue
        msg = decode(m)
        if m.topic.endswith(UPDATE):
            ordinal += 1
        if not graph.own(msg, m.topic):
            continue            # another graph's (module doc)
        if m.topic.endswith(STATE):
            s_seq.append(int(msg.seq))
            s_topic.append(state_topics.setdefault((m.topic, m.msgtype), len(state_topics)))
        elif m.topic.endswith(COMMAND):
            c_seq.append(int(msg.state_seq))
            c_mode.append(int(msg.mode))
            if by_age:
                c_age.append(float(msg.update_age))
                c_stamp.append(_stamp(msg.header))
            else:
                c_useq.append(int(msg.update_seq))
            c_len.append(len(msg.wrench))
            c_wrench.frombytes(np.asarray(msg.wrench, dtype=np.float64).tobytes())
        elif m.topic.endswith(UPDATE):
            u_seq.append(int(msg.seq))
            u_stamp.append(_stamp(msg.header))
            u_ordinal.append(ordinal - 1)
            update_topics[m.topic] = m.msgtype
        elif m.topic.endswith(HAND_INPUTS):
            hands.frombytes(np.asarray(msg.state_seq, dtype=np.uint64).tobytes())
    if not c_seq:
        raise BagError(f'{bag.path}: no {COMMAND} messages: nothing to compare')
    # The first command of each state seq, by seq.
    seqs, first = np.unique(_u64(c_seq), return_index=True)
    lengths = np.frombuffer(c_len, dtype=np.uint16).astype(np.int64)
    starts = np.cumsum(lengths) - lengths
    kept = lengths[first]
    wrench_at = np.concatenate(([0], np.cumsum(kept)))
    wrench = _f64(c_wrench)[np.repeat(starts[first] - wrench_at[:-1], kept)
                            + np.arange(wrench_at[-1])]
    modes = np.frombuffer(c_mode, dtype=np.uint8)[first]
    engaged = modes[modes != ControlMode.ZERO]
    mode = (ControlMode.ACCELERATION_ONLY.label
            if engaged.size and int(np.argmax(np.bincount(engaged))) == (
                ControlMode.ACCELERATION_ONLY) else ControlMode.PENALTY.label)
    answered = np.union1d(_u64(hands), seqs)
    states = _u64(s_seq)
    is_answered = np.isin(states, answered)
    used = set(np.frombuffer(s_topic, dtype=np.uint16)[is_answered].tolist()) if len(
        s_topic) else set()
    topics = {t: ty for (t, ty), i in state_topics.items() if i in used}
    topics.update(update_topics)
    update_seqs = _u64(u_seq).copy()
    cp = ControllerPlan(bag, str(custom.get('scenario', '')), mode, graph.graph_id, topics,
                        answered, seqs, modes, wrench, wrench_at, len(u_seq), update_seqs,
                        _u64(u_ordinal).copy(),
                        None if by_age else np.frombuffer(c_useq, dtype=np.int64)[first])
    if by_age:
        cp.ages, cp.stamps = _f64(c_age)[first], _f64(c_stamp)[first]
        order = np.argsort(update_seqs, kind='stable')
        cp.published = _f64(u_stamp)[order]        # VE stamps at publish, in seq order
        cp.group_seqs, cp.group_got = _groups(cp, states[is_answered])
    else:
        cp.by_seq = np.argsort(update_seqs, kind='stable')
        cp.sorted_seqs = update_seqs[cp.by_seq]
    return cp


def _groups(cp: ControllerPlan, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A bag recorded before ``update_seq``: the commands grouped by the update they used
    (the seq of each group's first state, sorted, and the group's update receive time):
    the age grows from one command to the next while the update is the same, and the
    controller's receive time of its newest update (stamp - age, plus this cycle's compute
    time) jumps by ~1 update period. ``states``: the answered states' seqs in bag order."""
    assert cp.ages is not None and cp.stamps is not None
    first_seqs, gots = array('Q'), array('d')
    prev_age = prev_got = math.inf
    started = False
    for seq in states.tolist():
        ci = cp.command(seq)
        if ci < 0 or not math.isfinite(cp.ages[ci]):
            continue
        age = float(cp.ages[ci])
        got = float(cp.stamps[ci]) - age
        # The age of one update only grows; it falls when a newer one was taken. A jump of
        # the receive time by more than 5 ms also marks a new update (after a gap in the
        # states the age may have grown anyway); compute times of up to 2 ms were seen.
        if not started or age < prev_age or got > prev_got + 5e-3:
            started = True
            first_seqs.append(seq)
            gots.append(got)
        gots[-1] = min(gots[-1], got)   # least compute time: closest to receipt
        prev_age, prev_got = age, got
    # A seq that started two groups keeps the later one's time (as a dict would).
    keys, last = np.unique(_u64(first_seqs)[::-1], return_index=True)
    return keys, _f64(gots)[::-1][last]


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
    #: Seqs of the compared states and the largest |difference| of each command (inf: other
    #: mode or shape).
    seqs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint64))
    diffs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    missing_seqs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint64))
    #: Recorded commands not compared because the bag lacks some of their inputs (of
    #: ``recorded``; :attr:`ControllerPlan.unchecked`), from state ``unchecked_from`` on,
    #: the first naming LMI update ``absent_update``.
    unchecked: int = 0
    unchecked_from: int = -1
    absent_update: int = -1

    @property
    def ok(self) -> bool:
        return self.compared > 0 and self.max_abs_diff <= self.tolerance

    def line(self) -> str:
        unchecked = (f', {self.unchecked} not checked: from state {self.unchecked_from} on, '
                     f'LMI update {self.absent_update}, which the controller had taken, is not '
                     'in the bag' if self.unchecked else '')
        return (f'controller check ({self.scenario}, {self.mode}): {self.compared} commands '
                f'compared of {self.recorded} recorded ({self.missing} not answered live'
                f'{unchecked}); max |difference| {self.max_abs_diff:.3g} (tolerance '
                f'{self.tolerance:g}): {"OK" if self.ok else "DIFFERENT"}')


class CommandCheck:
    """The live controller's commands compared with the recorded ones as they arrive (the
    first answer to each state counts); ``seq in check``: state ``seq`` was answered."""

    def __init__(self, cp: ControllerPlan) -> None:
        self.cp = cp
        self.live = np.zeros(cp.answered.size, dtype=bool)   # per answered state
        self.got = np.zeros(cp.seqs.size, dtype=bool)         # per recorded command
        self.diff = np.zeros(cp.seqs.size)
        #: Answers to states outside the plan (none expected).
        self.other: set[int] = set()

    def answer(self, seq: int, mode: int, wrench: Any) -> None:
        i = _find(self.cp.answered, seq)
        if i < 0:
            self.other.add(seq)
            return
        if self.live[i]:
            return
        self.live[i] = True
        ci = self.cp.command(seq)
        if ci < 0:
            return
        rec, got = self.cp.recorded_wrench(ci), np.array(wrench, dtype=float)
        mode_diff = 0.0 if mode == int(self.cp.modes[ci]) else math.inf
        self.got[ci] = True
        self.diff[ci] = max(float(np.max(np.abs(rec - got), initial=0.0))
                            if rec.shape == got.shape else math.inf, mode_diff)

    def __contains__(self, seq: object) -> bool:
        if not isinstance(seq, int):
            return False
        i = _find(self.cp.answered, seq)
        return bool(self.live[i]) if i >= 0 else seq in self.other

    def result(self, tolerance: float, scenario: str, stats: ReplayStats) -> CheckResult:
        """The verdict over the recorded commands whose states were published (after
        :meth:`ControllerPlan.items` has run through)."""
        cp = self.cp
        present = cp.present if cp.present.size else np.zeros_like(self.got)
        unchecked = cp.unchecked if cp.unchecked.size else np.zeros_like(self.got)
        compared = present & self.got
        diffs = self.diff[compared]
        skipped = cp.seqs[unchecked]
        return CheckResult(int(compared.sum()), int(present.sum() + unchecked.sum()),
                           int(self.live.sum()) + len(self.other),
                           int((present & ~self.got).sum()),
                           float(np.max(diffs)) if diffs.size else math.inf, tolerance,
                           cp.mode, scenario, stats, cp.seqs[compared], diffs,
                           cp.seqs[present & ~self.got], int(skipped.size),
                           int(skipped[0]) if skipped.size else -1, cp.absent_update)
