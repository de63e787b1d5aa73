"""The controller's side of the loop as the ``lmi_controller`` node runs it, without ROS.

:class:`ControllerPort` wraps a :class:`~haptic_topology.control.loop.ControllerLoop` (eq. 14
or eq. 10 with the LMI of eq. 17-20, sync guard, sessions) with what a node does around it:

* **hand-input batches**: the hand input of every answered state goes into a
  :class:`~haptic_topology.control.batch.HandBatcher`, one batch per VE update period
  (``update_period`` device cycles); :meth:`ControllerPort.flush` hands over a partial batch
  whose oldest sample is two update periods old (the end of a run, a stalled device);
* **the lock-step hold** (separate layout, ``lockstep``): a state that comes before the LMI
  update the offline simulation applies at that step is held until the update has come
  (:meth:`ControllerPort.on_update` answers it), at most ``lockstep_wait`` s
  (:meth:`ControllerPort.check_wait` then answers from the local model, counts a timeout
  and leaves a notice). The hosted layout's loop thread does this wait itself
  (:class:`~haptic_topology.device.runner.LoopRunner`);
* **figures**: the period between answered engaged states, commands sent, the age of the
  newest LMI update (s since it arrived), the model's health as a diagnostics level;
* **updates between answers** (:class:`UpdateGap`, separate layout, wall clock): an LMI update
  that arrives while device states come is taken right after the next answer is sent, in the
  gap before the following state, not when it arrives: taking it (its checks and re-sync,
  0.5-1 ms of one thread) would otherwise hold every state that arrives meanwhile.

Times ``now`` are monotonic seconds; stamps are integer ns (loop time).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.control.batch import HandBatch, HandBatcher
from haptic_topology.control.laws import ControlGains, check_live
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.loop import Answer, ControllerLoop, StateSample
from haptic_topology.control.safety import ModelHealth
from haptic_topology.control.stats import LoopStats
from haptic_topology.vocabulary import ControlMode, DeviceStatus

#: Diagnostics (level, message) of each stage of the local model (0 OK, 1 WARN).
HEALTH_MESSAGES = {
    ModelHealth.FRESH: (0, 'ok'),
    ModelHealth.UNSYNCED: (1, 'no LMI update yet'),
    ModelHealth.STALE: (1, 'LMI update stale: local model, last constraint set'),
    ModelHealth.DEGRADED: (1, 'LMI update too old: force faded to zero'),
    ModelHealth.PENDING: (1, 're-sync held until the force has faded out'),
}


def live_change(gains: ControlGains, mode: ControlMode,
                changes: Iterable[tuple[str, Any]]) -> tuple[ControlGains, ControlMode] | str:
    """The gains and mode after the live parameter ``changes`` (``(name, value)`` of
    ``mode``, ``k_tc``, ``b_tc``; others are left alone), or why one is refused (then none
    applies)."""
    for name, value in changes:
        reason = check_live(name, value)
        if reason:
            return reason
        if name == 'k_tc':
            gains = gains.with_penalty(float(value), gains.b_tc)
        elif name == 'b_tc':
            gains = gains.with_penalty(gains.k_tc, float(value))
        elif name == 'mode':
            mode = ControlMode.parse(str(value))
    return gains, mode


#: :class:`UpdateGap`: device states count as coming while the newest is younger than this
#: (s); an update that arrives later is taken at once.
STATES_COMING = 0.005


class UpdateGap:
    """When a node takes its LMI updates: in the gap after an answer while device states come
    (see module doc), at once otherwise. Each update waits for at most one answer, or, when
    the states stop, for the node's next timer (:meth:`due`); updates are taken in the order
    they arrived (an update: whatever the node takes, e.g. the message). Times are monotonic
    seconds; ``state_time``: when the newest state arrived (None: none yet).

    Example (states every ms; ``gap.deferred`` counts the updates that waited)::

        gap.arrived(u1, now=0.0102, state_time=0.0100)  # [] (waits for the answer)
        gap.answered()                                  # [u1] (after the next command)
        gap.arrived(u2, now=0.0500, state_time=0.0300)  # [u2] (states stopped: at once)
    """

    def __init__(self, states_coming: float = STATES_COMING) -> None:
        self.states_coming = states_coming
        self.deferred = 0
        self._waiting: list[Any] = []

    def _coming(self, now: float, state_time: float | None) -> bool:
        return state_time is not None and now - state_time < self.states_coming

    def arrived(self, item: Any, now: float, state_time: float | None) -> list[Any]:
        """An update arrived at ``now``: the updates to take now, oldest first (none while
        states come: it waits for the next answer)."""
        self._waiting.append(item)
        if self._coming(now, state_time):
            self.deferred += 1
            return []
        return self.answered()

    def answered(self) -> list[Any]:
        """An answer was sent: the waiting updates, oldest first (taken)."""
        out, self._waiting = self._waiting, []
        return out

    def due(self, now: float, state_time: float | None) -> list[Any]:
        """The node's timer: the waiting updates once states no longer come."""
        return [] if self._coming(now, state_time) else self.answered()


@dataclass(frozen=True, slots=True)
class Outgoing:
    """What to publish for one answered state: the ``answer`` (command of eq. 14/10), the
    stamp of the state it answers (``state_ns``), the age of the newest LMI update when it
    was computed (``update_age``, s; inf before the first), and the hand-input batch it
    completed (or None)."""

    answer: Answer
    state_ns: int
    update_age: float
    batch: HandBatch | None


#: LMI updates whose arrival times a port remembers (:meth:`ControllerPort.age_of`): 0.6 s of
#: them at 100 Hz, far more than a cycle record waits to be published.
ARRIVALS_KEPT = 64


class ControllerPort:
    """``loop`` with hand batches, the lock-step hold and figures (see module doc);
    ``update_period``: device cycles per VE update; ``dim``: task dimension; ``dt``: device
    period (s); ``lockstep_wait`` (s): the longest hold."""

    def __init__(self, loop: ControllerLoop, update_period: int, dim: int, dt: float,
                 lockstep: bool = False, lockstep_wait: float = 5.0) -> None:
        self.loop = loop
        batch_period = dt * update_period       # s: one VE update period
        self.batcher = HandBatcher(update_period, dim, 2.0 * batch_period)
        #: How often :meth:`flush` is due (s): one VE update period, at least 10 ms.
        self.flush_period = max(batch_period, 0.01)
        self.lockstep = lockstep
        self.lockstep_wait = lockstep_wait
        self.stats = LoopStats(dt)
        self.commands = 0
        self.lockstep_timeouts = 0
        self._held: tuple[StateSample, int, float] | None = None
        self._update_time: float | None = None   # when the newest update arrived (s)
        #: When each of the newest updates arrived (s), by seq (at most ARRIVALS_KEPT).
        self._arrived: dict[int, float] = {}
        self._state_time = 0.0                   # when the newest state arrived (s)

    def on_state(self, sample: StateSample, state_ns: int, now: float) -> Outgoing | None:
        """A device state stamped ``state_ns`` arrived at ``now``: its answer, or None
        (held in lock-step, or not answered: see
        :meth:`~haptic_topology.control.loop.ControllerLoop.on_state`)."""
        self._state_time = now
        if self.lockstep and self.loop.waiting_for_update():
            self._held = (sample, state_ns, now)
            return None
        return self._answer(sample, state_ns, now)

    def on_update(self, snap: LmiSnapshot, now: float, apply: bool = True) -> Outgoing | None:
        """An LMI update arrived at ``now``; ``apply``: give it to the loop (False when a
        hosted loop thread applies it). Returns the answer of a held state it releases."""
        if apply:
            self.loop.on_update(snap)
        self._update_time = now
        arrived = self._arrived
        arrived.pop(snap.seq, None)             # a restarted VE numbers from 0 again
        arrived[snap.seq] = now
        if len(arrived) > ARRIVALS_KEPT:
            del arrived[next(iter(arrived))]
        if self._held is None or self.loop.waiting_for_update():
            return None
        sample, state_ns, _ = self._held
        self._held = None
        return self._answer(sample, state_ns, now)

    def check_wait(self, now: float) -> Outgoing | None:
        """Lock-step: a held state waits at most ``lockstep_wait`` s for its update; then
        it is answered from the local model (a notice says so)."""
        if self._held is None or now - self._held[2] < self.lockstep_wait:
            return None
        sample, state_ns, _ = self._held
        self._held = None
        self.lockstep_timeouts += 1
        self.loop.notices.append(
            f'lock-step: no LMI update for state {sample.seq} within {self.lockstep_wait:g} '
            's (is ve_sim running?): answering from the local model; the run no longer '
            'matches simulate')
        return self._answer(sample, state_ns, now)

    def answered(self, ans: Answer, state_ns: int, now: float,
                 stats_time: float | None = None) -> Outgoing:
        """Account for ``ans`` (computed elsewhere: the hosted loop thread): command count,
        hand batch; ``stats_time`` (s): the time of the period statistics' tick (None: no
        tick, an idle state)."""
        batch = (self.batcher.add(ans.hand, state_ns, now) if ans.hand is not None
                 else None)
        return Outgoing(ans, state_ns, self._count(now, stats_time), batch)

    def answered_block(self, hand: tuple[int, int, np.ndarray] | None, state_ns: int,
                       now: float, stats_time: float | None,
                       used: tuple[int, float] | None = None
                       ) -> tuple[float, HandBatch | None]:
        """:meth:`answered` of an answer known by its hand input alone: ``hand`` is the
        input's ``seq``, ``state_seq`` and 4 x m rows (pose, twist, F_h, F_pc; None: the
        answer has none). Returns the ``update_age`` and the hand batch of its
        :class:`Outgoing`: the age at ``now`` of the newest update, or with ``used`` =
        ``(update_seq, t)`` (:meth:`age_of`) that of the update the answer was computed with
        at the time ``t`` of its state (the hosted publisher takes cycles some milliseconds
        after they ran)."""
        batch = (None if hand is None
                 else self.batcher.add_block(hand[0], hand[1], state_ns, hand[2], now))
        age = self._count(now, stats_time)
        return (age if used is None else self.age_of(*used)), batch

    def _count(self, now: float, stats_time: float | None) -> float:
        """An answer sent at ``now``: the statistics' tick, the count; its update age."""
        if stats_time is not None:
            self.stats.tick(stats_time)
        self.commands += 1
        self._state_time = now
        return self.update_age(now)

    def _answer(self, sample: StateSample, state_ns: int, now: float) -> Outgoing | None:
        engaged = not sample.status & DeviceStatus.IDLE
        ans = self.loop.on_state(sample)
        if ans is None:
            if engaged:
                self.stats.tick(now)
            return None
        return self.answered(ans, state_ns, now, now if engaged else None)

    def flush(self, now: float) -> HandBatch | None:
        """The pending hand samples once the oldest is two update periods old."""
        return self.batcher.due(now)

    @property
    def state_time(self) -> float | None:
        """When the newest device state arrived (monotonic s; None: none yet)."""
        return self._state_time or None

    def age_of(self, update_seq: int, at: float) -> float:
        """Seconds from the arrival of update ``update_seq`` to ``at`` (this port's clock),
        >= 0; :meth:`update_age` at ``at`` for an update it does not remember (none taken
        yet: -1, or one of more than :data:`ARRIVALS_KEPT` ago)."""
        arrived = self._arrived.get(update_seq)
        return self.update_age(at) if arrived is None else max(0.0, at - arrived)

    def update_age(self, now: float) -> float:
        """Seconds since the newest LMI update arrived (inf before the first), >= 0.

        Hosted, the publishing thread takes ``now`` once per batch of cycles while the
        executor thread may record an update after it: such an update is 0 s old, not
        negative (a negative ``DeviceCommand.update_age`` is malformed: the bag analysis
        skipped two such commands of a spatial lock-step run)."""
        return math.inf if self._update_time is None else max(0.0, now - self._update_time)

    def values(self, now: float) -> dict[str, str]:
        """Figures as diagnostics key/values (with the loop's)."""
        out = self.stats.values()
        out.update(self.loop.values(self._loop_now(now)))
        out.update({'update_age_ms': f'{1e3 * self.update_age(now):.2f}',
                    'lockstep_timeouts': str(self.lockstep_timeouts),
                    'hand_batches_sent': str(self.batcher.batches),
                    'hand_batches_partial': str(self.batcher.partial),
                    'hand_pending': str(self.batcher.pending),
                    'hand_last_seq': str(self.batcher.last_seq)})
        return out

    def health(self, now: float) -> tuple[int, str]:
        """``(level, message)`` of the local model's stage (:data:`HEALTH_MESSAGES`)."""
        return HEALTH_MESSAGES[self.loop.guard.health(self._loop_now(now))]

    def _loop_now(self, now: float) -> float:
        """Loop time now: the newest state's stamp plus the time since it came."""
        return self.loop.loop_time + (now - self._state_time if self._state_time else 0.0)
