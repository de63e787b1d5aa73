"""What a plain replay of a bag publishes, offline: its plan (messages, times, topics left
out), read from the bag as it is published, and what it did. The controller check's plan is
:mod:`haptic_topology.bag.controller_check`; the publishing side (rclpy) is
:mod:`haptic_topology.nodes.replay`, which documents ``haptic-topology replay``.
"""

from __future__ import annotations

import argparse
import heapq
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import (
    Bag,
    BagMessage,
    iter_messages,
    outdated_types,
    read_channels,
    upgraders,
)
from haptic_topology.errors import BagError

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


class Lateness:
    """How far behind the recorded timing the messages were published (ms), as a histogram
    of bins 0.1 % wide from 0.1 us up (below: 0), so a replay of any length or a ``--loop``
    keeps a fixed 200 KB; a percentile is exact to 0.1 %."""

    LOW_MS = 1e-4
    STEP = 1e-3
    BINS = 25_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS + 1, dtype=np.int64)
        self.n = 0

    def add(self, ms: float) -> None:
        k = 0 if ms < self.LOW_MS else min(
            1 + int(math.log(ms / self.LOW_MS) / math.log1p(self.STEP)), self.BINS)
        self.counts[k] += 1
        self.n += 1

    def _value(self, k: int) -> float:
        """The middle of bin ``k`` (0 for the bin below 0.1 us)."""
        return 0.0 if k == 0 else self.LOW_MS * (1 + self.STEP) ** (k - 0.5)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (linear between the two nearest ranks, as numpy's)."""
        if not self.n:
            return math.nan
        rank = q / 100 * (self.n - 1)
        cum = np.cumsum(self.counts)
        lo, hi = (int(np.searchsorted(cum, r, side='right')) for r in (math.floor(rank),
                                                                      math.ceil(rank)))
        frac = rank - math.floor(rank)
        return self._value(lo) * (1 - frac) + self._value(hi) * frac


@dataclass
class ReplayStats:
    """What a replay did: messages published per topic, lateness of the publish times."""

    published: dict[str, int] = field(default_factory=dict)
    late_ms: Lateness = field(default_factory=Lateness)
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
        if self.late_ms.n:
            text += (f'; behind the recorded timing p50 {self.late_ms.percentile(50):.3f} ms, '
                     f'p99 {self.late_ms.percentile(99):.3f} ms')
        return text


def _copy(bag: Bag) -> Bag:
    """``bag`` for one more reader at the same time (its own truncation and topic lists)."""
    return replace(bag, truncated=[], topics={})


@dataclass
class Plan:
    """The messages of a plain replay, in time order (equal times in file order), read from
    the bag each time the plan is iterated: only the messages of a window as long as the
    bag's largest step back in receive time are in memory (none for a bag written in time
    order; a few ms of messages for our recorder's)."""

    bag: Bag
    #: Topic -> type of the topics published (those with a message from the start on).
    topics: dict[str, str]
    #: Time (s) of the last message from the start.
    span: float
    wanted: set[str] | None
    old: dict[str, str]
    #: Receive time (ns) of the replay's start.
    t0: int
    #: The largest step back in receive time (ns) from one message to a later one in the file.
    window: int

    def _messages(self) -> Iterator[BagMessage]:
        return (m for m in iter_messages(_copy(self.bag))
                if (self.wanted is None or m.topic in self.wanted) and m.topic not in self.old)

    def __iter__(self) -> Iterator[Item]:
        upgrade = upgraders(self.bag)
        heap: list[tuple[float, int, BagMessage]] = []
        newest = None
        n = 0
        for m in self._messages():
            newest = m.log_time if newest is None else max(newest, m.log_time)
            if m.log_time >= self.t0:
                heapq.heappush(heap, ((m.log_time - self.t0) * 1e-9, n, m))
                n += 1
            # No later message is received before newest - window: the first ones are due.
            while heap and heap[0][2].log_time <= newest - self.window:
                yield self._item(heapq.heappop(heap), upgrade)
        while heap:
            yield self._item(heapq.heappop(heap), upgrade)

    @staticmethod
    def _item(entry: tuple[float, int, BagMessage], upgrade: dict[str, Any]) -> Item:
        t, _, m = entry
        return Item(t, m.topic, m.msgtype,
                    upgrade[m.msgtype](m.data) if m.msgtype in upgrade else m.data)


def plan(bag: Bag, topics: Iterable[str] | None = None, start_offset: float = 0.0) -> Plan:
    """Messages of ``bag`` (``topics`` only if given) from ``start_offset`` s on, as items;
    without the topics of :func:`left_out` (an error if ``topics`` names one). A first read
    of the bag finds the start, the topics and the window (:class:`Plan`)."""
    wanted = None if topics is None else {'/' + t.lstrip('/') for t in topics}
    old = left_out(bag)
    if wanted is not None and wanted & set(old):
        raise BagError(f'{bag.path}: cannot replay {", ".join(sorted(wanted & set(old)))}: '
                       'recorded with an older definition of '
                       f'{", ".join(sorted({old[t] for t in wanted & set(old)}))} than the '
                       'installed one')
    first = newest = None
    window = 0
    last: dict[str, tuple[int, str]] = {}   # topic -> its latest receive time, type
    for m in iter_messages(bag):
        if (wanted is not None and m.topic not in wanted) or m.topic in old:
            continue
        if first is None or newest is None:
            first = newest = m.log_time
        window = max(window, newest - m.log_time)
        first, newest = min(first, m.log_time), max(newest, m.log_time)
        before = last.get(m.topic)
        last[m.topic] = (m.log_time if before is None else max(before[0], m.log_time),
                         m.msgtype)
    if wanted is not None:
        missing = wanted - set(last)
        if missing:
            raise BagError(f'{bag.path}: no messages on {", ".join(sorted(missing))} (it has '
                           f'{", ".join(sorted(bag.topics))})')
    if first is None or newest is None:
        raise BagError(f'{bag.path}: no messages to replay')
    t0 = first + int(start_offset * 1e9)
    if newest < t0:
        raise BagError(f'{bag.path}: --start-offset {start_offset:g} s is past the bag\'s end')
    return Plan(bag, {t: ty for t, (lt, ty) in last.items() if lt >= t0}, (newest - t0) * 1e-9,
                wanted, old, t0, window)


def left_out(bag: Bag) -> dict[str, str]:
    """Topic -> type of the topics plain replay leaves out: their type is recorded in an older
    definition than the installed one, changed other than by appended fields (module doc)."""
    old = outdated_types(bag) - set(upgraders(bag))
    return {t: ch['type'] for t, ch in read_channels(bag).items() if ch['type'] in old}


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


