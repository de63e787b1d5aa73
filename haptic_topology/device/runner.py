"""The loop thread of the hosted layout: one :class:`~haptic_topology.device.hosted.HostedCycle`
per device cycle, paced.

As ros2_control's controller manager runs ``read -> update -> write``, the hosted
``device_driver`` runs :meth:`~haptic_topology.device.hosted.HostedCycle.step` (device tick,
controller answer, command held
for the next write) in one thread of its own, and nothing else: no DDS, no diagnostics, no
recording. What observers need (the state, the command, the hand input, the lock-step
``/clock``) goes into an *outbox* that the node's executor thread drains and publishes, as
``realtime_tools.RealtimePublisher`` hands messages to a non-real-time thread. No ROS here:
clock, sleep and the executor's wake-up are injected, so the pacing logic is tested with a
fake clock (``test/unit/device/test_core_runner.py``).

Pacing (``RunnerConfig.lockstep``):

* **wall**: a :class:`~haptic_topology.device.pacing.DeadlinePacer` releases cycle ``k`` at
  ``t0 + k * period`` (absolute deadlines; an overrun skips the passed deadlines and counts
  them, no catch-up burst). The state is stamped with the injected wall clock (ns, the ROS
  system clock's time). The device integrates over the measured period, clipped to
  ``[0, 20 * period]`` as in the separate layout.
* **lockstep**: simulated time. Before engagement the device idles at stamp 0, one cycle per
  period; once engaged, each state ``k`` is stamped ``k * period`` (integer ns) and the loop
  steps as soon as the controller has the LMI update that the offline simulation applies
  before that state (:meth:`~haptic_topology.device.hosted.HostedCycle.waiting_for_update`),
  waiting at most
  ``lockstep_wait`` wall seconds for it (then a notice, counted in ``lockstep_timeouts``, and
  the answer from the local model). A full outbox makes it wait for the publisher (nothing
  recorded is lost); in wall mode the outbox drops its oldest entry instead and counts it
  (``outbox_dropped``): the deadline never waits for an observer.

``run_duration`` (s, 0 = none): the thread stops after the first state whose stamp is that
far from the run's first state; ``LoopRunner.finished`` is then True (the node
deactivates).

Threads: :meth:`LoopRunner.start`, :meth:`LoopRunner.stop`, :meth:`LoopRunner.drain` and
:meth:`LoopRunner.submit` belong to the node's executor thread; ``may_engage`` is set by it and
read by the loop thread (a bool). :meth:`LoopRunner.submit` hands a function (a live parameter
change) to the loop thread, which runs it between two cycles; when the thread is not running it
runs at once.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from haptic_topology.control.laws import ControlGains
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.device.hosted import HostedCycle, HostedStep
from haptic_topology.device.loop import ns_to_seconds, period_ns
from haptic_topology.device.pacing import DeadlinePacer, PacerFigures, PacerTick
from haptic_topology.errors import ConfigError
from haptic_topology.vocabulary import ControlMode

#: Outbox entries kept (4 s at 1 kHz): a publisher that falls further behind loses the oldest
#: (wall clock) or holds the loop (lock-step).
OUTBOX = 4096
#: Lock-step: a state that has waited this long (wall s) for its LMI update gets a notice;
#: the run goes on waiting up to ``lockstep_wait`` (a loaded machine runs slower, not
#: differently: a stress run once had the VE's update 5 s late, under 8 graphs on 2 cores).
LOCKSTEP_NOTICE_AFTER = 5.0
#: Why a lock-step driver refuses to be activated a second time.
LOCKSTEP_RUNS_ONCE = (
    'clock: lockstep: this driver has run once; a lock-step run cannot resume or start over in '
    "the same graph (the VE keeps the run's linkage state, simulated time would start again at "
    '0, and the run would no longer equal simulate): start ve_sim and device_driver again')
#: Onsets of a device fault that each get a notice (the driver's log): its reason, once.
FAULT_NOTICES = 10
#: Longest single wait of the loop thread for an update or for room in the outbox (s), so
#: that submitted calls and a stop request are served meanwhile.
_POLL = 0.01


@dataclass(frozen=True, slots=True)
class RunnerConfig:
    """``period`` (s, the device's); ``lockstep``: simulated time (see module doc);
    ``run_duration`` (s of loop time from the first engaged state, 0 = none);
    ``lockstep_wait`` (wall s) a lock-step state waits for its LMI update; ``outbox``:
    entries kept for the publisher."""

    period: float
    lockstep: bool = False
    run_duration: float = 0.0
    lockstep_wait: float = 60.0
    outbox: int = OUTBOX

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0.0):
            raise ConfigError(f'period must be a finite number > 0 s, got {self.period}')
        if not (math.isfinite(self.run_duration) and self.run_duration >= 0.0):
            raise ConfigError(f'run_duration must be >= 0 s, got {self.run_duration}')
        if not (math.isfinite(self.lockstep_wait) and self.lockstep_wait > 0.0):
            raise ConfigError(f'lockstep_wait must be > 0 s, got {self.lockstep_wait}')
        if self.outbox < 1:
            raise ConfigError(f'outbox must be >= 1 entry, got {self.outbox}')


#: The pacer's figures the device reports under their own names (the separate layout's):
#: the measured period and the wake-up lateness, p50 / p99 / max (ms).
DEVICE_PACING_KEYS = tuple(f'{what}_{q}_ms' for what in ('period', 'wake_late')
                           for q in ('p50', 'p99', 'max'))


class Published(NamedTuple):
    """One outbox entry: the cycle ``step`` and its state's stamp ``stamp_ns`` (integer ns,
    loop time: wall or simulated)."""

    step: HostedStep
    stamp_ns: int


class Outbox(Protocol):
    """Where :class:`LoopRunner` puts each cycle it ran (:class:`Published`) for the thread
    that publishes it: a :class:`DequeOutbox` in the node's process, the cycle ring of a loop
    process (:mod:`~haptic_topology.device.loop_child`). ``dropped``: entries lost because
    it was full (wall clock)."""

    @property
    def dropped(self) -> int: ...

    def __len__(self) -> int: ...

    def room(self) -> bool:
        """Whether an entry can be put without losing one (lock-step waits for it)."""

    def put(self, entry: Published) -> None:
        """Add ``entry``; when full, the oldest entry not yet taken is lost and counted."""


class DequeOutbox:
    """An :class:`Outbox` of ``capacity`` entries that the publishing thread drains."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._box: deque[Published] = deque()
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._box)

    def room(self) -> bool:
        return len(self._box) < self.capacity

    def put(self, entry: Published) -> None:
        if len(self._box) >= self.capacity:
            self._box.popleft()
            self.dropped += 1
        self._box.append(entry)

    def drain(self) -> list[Published]:
        """Take everything put so far, oldest first (any one thread)."""
        out = []
        box = self._box
        while box:
            out.append(box.popleft())
        return out


class LoopHandle(Protocol):
    """What the hosted layout's node uses of its loop, wherever the loop runs: a thread of
    its own process (:class:`LoopRunner`) or a loop process
    (:class:`~haptic_topology.device.loop_process.LoopProcess`)."""

    may_engage: bool
    notices: deque[str]

    @property
    def error(self) -> BaseException | None: ...
    @property
    def running(self) -> bool: ...
    @property
    def finished(self) -> bool: ...
    @property
    def appended(self) -> int: ...
    @property
    def outbox_dropped(self) -> int: ...
    @property
    def outbox_pending(self) -> int: ...
    @property
    def lockstep_timeouts(self) -> int: ...

    def start(self, name: str = 'device_loop',
              on_start: Callable[[], None] | None = None) -> None: ...
    def stop(self) -> None: ...
    def offer_update(self, snap: LmiSnapshot) -> None: ...
    def change_law(self, gains: ControlGains, mode: ControlMode) -> None: ...
    def device_values(self) -> dict[str, str]: ...


class LoopRunner:
    """Runs a :class:`~haptic_topology.device.hosted.HostedCycle` in a paced loop thread (see
    module doc).

    ``wall_ns``: the wall clock that stamps states (ns; the node passes its ROS clock);
    ``clock``/``sleep``: monotonic time (s) and sleep, for the pacer and the waits; ``wake``
    (attribute, settable before ``start``): called after each outbox append, to wake the
    thread that publishes; ``outbox``: where the cycles go (default: a
    :class:`DequeOutbox` of ``cfg.outbox`` entries, which :meth:`drain` takes).
    """

    def __init__(self, cycle: HostedCycle, cfg: RunnerConfig,
                 wall_ns: Callable[[], int] = time.time_ns,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 wake: Callable[[], None] = lambda: None,
                 outbox: Outbox | None = None) -> None:
        if abs(cycle.device.period - cfg.period) > 1e-12:
            raise ConfigError(f'runner period {cfg.period} s differs from the device loop\'s '
                              f'{cycle.device.period} s')
        self.cycle = cycle
        self.cfg = cfg
        self.pacer = DeadlinePacer(cfg.period, clock, sleep)
        self._wall_ns = wall_ns
        self._clock = clock
        self._sleep = sleep
        self.wake = wake
        self._period_ns = period_ns(cfg.period)
        self.outbox: Outbox = DequeOutbox(cfg.outbox) if outbox is None else outbox
        self._calls: deque[Callable[[], None]] = deque()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.may_engage = False
        self.finished = False
        self.error: BaseException | None = None
        self._run_start_ns: int | None = None
        self.notices: deque[str] = deque(maxlen=100)
        self.appended = 0                # entries put in the outbox in all
        self.missed_deadlines = 0        # skipped while engaged (wall clock)
        self.max_missed_deadlines = 0    # ... the most in a row
        self.lockstep_timeouts = 0
        self.lockstep_waits = 0          # lock-step states that waited for their update

    # -- executor thread ---------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, name: str = 'device_loop',
              on_start: Callable[[], None] | None = None) -> None:
        """Start the loop thread; ``on_start`` runs first in it (e.g. real-time settings of
        the thread)."""
        if self._thread is not None:
            raise RuntimeError('LoopRunner.start: already started')
        self._stop.clear()
        self.finished = False           # a new run (after a deactivation) has its own end
        self._run_start_ns = None
        self.pacer.start()

        def body() -> None:
            try:
                if on_start is not None:
                    on_start()
                while not self._stop.is_set() and not self.finished:
                    self.cycle_once()
            except BaseException as exc:  # reported by the node, never silent
                self.error = exc
                self.wake()

        self._thread = threading.Thread(target=body, name=name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the loop thread to stop after its cycle and join it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise RuntimeError(f'device loop thread did not stop within {timeout} s')
            self._thread = None

    def request_stop(self) -> None:
        """Ask the loop to stop after its cycle (or while it waits), without joining."""
        self._stop.set()

    def offer_update(self, snap: LmiSnapshot) -> None:
        """Hand an LMI update to the loop (applied at the start of its next cycle; at once
        when the thread is not running)."""
        self.cycle.offer_update(snap)
        if not self.running:
            self.cycle.apply_updates()

    def change_law(self, gains: ControlGains, mode: ControlMode) -> None:
        """A live change of the controller's gains and mode, between two cycles."""
        ctrl = self.cycle.controller.ctrl

        def apply() -> None:
            ctrl.gains, ctrl.mode = gains, mode

        self.submit(apply)

    def submit(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` in the loop thread between two cycles (at once when not running)."""
        if self.running:
            self._calls.append(fn)
        else:
            fn()

    def drain(self) -> list[Published]:
        """Take what the loop thread has published so far, oldest first (the default
        outbox)."""
        assert isinstance(self.outbox, DequeOutbox)
        return self.outbox.drain()

    @property
    def outbox_dropped(self) -> int:
        """Entries the outbox lost (wall clock: the publisher fell behind)."""
        return self.outbox.dropped

    @property
    def outbox_pending(self) -> int:
        """Entries in the outbox not taken yet."""
        return len(self.outbox)

    # -- loop thread -------------------------------------------------------------------------
    def _run_calls(self) -> None:
        while self._calls:
            self._calls.popleft()()

    def cycle_once(self) -> Published | None:
        """One cycle of the loop (the thread's body calls this repeatedly; tests call it
        with a fake clock). Returns what it published, or None (stopped while waiting)."""
        if self.cfg.lockstep and self.cycle.device.engaged:
            return self._lockstep_step()
        return self._released(self.pacer.wait())

    def cycle_at(self, now: float) -> Published:
        """One wall-clock cycle released by the device's own servo clock at ``now`` (s, the
        pacer's clock; :meth:`DeadlinePacer.release
        <haptic_topology.device.pacing.DeadlinePacer.release>`): as :meth:`cycle_once`
        without waiting. The loop process calls it inside the device's callback."""
        if self.cfg.lockstep:
            raise ConfigError('a device whose servo loop is the clock cannot run lock-step')
        return self._released(self.pacer.release(now))

    def _released(self, tick: PacerTick) -> Published:
        if self.cycle.device.engaged:
            self.missed_deadlines += tick.missed
            self.max_missed_deadlines = max(self.max_missed_deadlines, tick.missed)
        self._run_calls()
        if self.cfg.lockstep:        # idle before engagement: simulated time stays 0
            stamp = 0
            dt = self.cfg.period
        else:
            stamp = self._wall_ns()
            dt = min(max(tick.dt, 0.0), 20.0 * self.cfg.period)
        device = self.cycle.device
        faults = device.device_faults
        step = self.cycle.step(tick.now, dt, ns_to_seconds(stamp), self.may_engage)
        if device.device_faults != faults and device.device_faults <= FAULT_NOTICES:
            more = (' (further onsets are counted in device_faults only)'
                    if device.device_faults == FAULT_NOTICES else '')
            self.notices.append(f'device fault: {device.backend.fault_reason()}: output '
                                f'zero while it lasts{more}')
        return self._publish(step, stamp)

    def _lockstep_step(self) -> Published | None:
        started = self._clock()
        waited = False
        noticed = False
        while self.cycle.waiting_for_update():
            self._run_calls()
            if self._stop.is_set():
                return None
            if not noticed and self._clock() - started >= LOCKSTEP_NOTICE_AFTER:
                noticed = True
                self.notices.append(
                    f'lock-step: state {self.cycle.device.seq + 1} has waited '
                    f'{LOCKSTEP_NOTICE_AFTER:g} s for its LMI update (a loaded machine, or '
                    f've_sim not running?); waiting up to {self.cfg.lockstep_wait:g} s')
            if self._clock() - started >= self.cfg.lockstep_wait:
                self.lockstep_timeouts += 1
                self.notices.append(
                    f'lock-step: no LMI update for state {self.cycle.device.seq + 1} within '
                    f'{self.cfg.lockstep_wait:g} s (is ve_sim running?): answering from the '
                    'local model; the run no longer matches simulate')
                break
            waited = True
            self.cycle.wait_offered(_POLL)
        self.lockstep_waits += waited
        while not self.outbox.room():       # the recorder must get everything
            self._run_calls()
            if self._stop.is_set():
                return None
            self.wake()             # the publisher takes some
            self._sleep(0.001)
        self._run_calls()
        d = self.cycle.device
        stamp = (d.run_index + 1) * self._period_ns
        return self._publish(self.cycle.step(self._clock(), self.cfg.period,
                                             ns_to_seconds(stamp), self.may_engage), stamp)

    def _publish(self, step: HostedStep, stamp: int) -> Published:
        entry = Published(step, stamp)
        self.appended += 1
        self.outbox.put(entry)
        if step.tick.run_index >= 0:
            if self._run_start_ns is None or step.tick.run_index == 0:
                self._run_start_ns = stamp
            duration = self.cfg.run_duration
            if duration > 0.0 and stamp - self._run_start_ns >= round(duration * 1e9):
                self.finished = True
        self.wake()
        return entry

    # -- figures (any thread; counters as they are) ------------------------------------------
    def values(self, figures: PacerFigures | None = None) -> dict[str, str]:
        """Pacing and hand-over figures as diagnostics key/values (``figures``: the pacer's,
        if the caller has them already: their percentiles sort a minute of periods)."""
        out = (figures or self.pacer.figures()).values('loop_')
        out.update(self.cycle.values())
        out.update({'outbox_dropped': str(self.outbox_dropped),
                    'lockstep_waits': str(self.lockstep_waits),
                    'lockstep_timeouts': str(self.lockstep_timeouts)})
        return out

    def answered_in_time(self) -> tuple[int, int]:
        """``(answered, expected)``: engaged cycles answered before the next write, with
        every skipped deadline counted as a cycle not answered in time (in the hosted layout
        the answer comes within the cycle, so a late cycle is the only way to miss)."""
        d = self.cycle.device
        return d.answered, d.expected + self.missed_deadlines

    def device_values(self, percentiles: bool = True) -> dict[str, str]:
        """The device's period and answer figures as the separate layout's ``device_driver``
        reports them, from the loop thread's pacing: the measured period as ``period_*``,
        skipped deadlines as ``overruns`` and as cycles not answered in time, and how late
        the loop woke after its deadlines as ``wake_late_*``; with :meth:`values`."""
        f = self.pacer.figures(percentiles)
        out = self.values(f)
        answered, expected = self.answered_in_time()
        pacing = f.values()
        out.update({key: pacing[key] for key in DEVICE_PACING_KEYS})
        out.update({'rate_hz': f'{1.0 / f.period_mean:.1f}' if f.period_mean > 0 else '0',
                    'overruns': str(self.missed_deadlines), 'cycles': str(f.cycles),
                    'answered_fraction': f'{answered / expected:.5f}' if expected else 'nan',
                    'answer_expected': str(expected),
                    'max_consecutive_missed': str(max(self.cycle.device.max_missed_run,
                                                      self.max_missed_deadlines))})
        return out
