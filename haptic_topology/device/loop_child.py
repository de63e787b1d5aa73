"""The child of :class:`~haptic_topology.device.loop_process.LoopProcess`: the hosted loop in
its one thread, no rclpy (``python -m haptic_topology.device.loop_child``; the module doc of
:mod:`haptic_topology.device.loop_process` describes the exchange and the lifetimes).

It reads its :class:`~haptic_topology.device.loop_process.LoopSpec` from stdin, attaches the
segments (:class:`~haptic_topology.device.loop_rings.LoopRings`), opens the device, and builds
the :class:`~haptic_topology.device.hosted.HostedCycle` (``_RingCycle``: its updates
taken from the node's ring when :class:`UpdateTiming` says) and a
:class:`~haptic_topology.device.runner.LoopRunner` whose outbox is the cycle ring
(:class:`RingOutbox`). Its loop, ``_Child.run``:

1. activate the device and write a first status (the node's activation waits for it),
   apply the LMI updates that came while it started, freeze the collector's view of
   everything built so far, start the deadline grid;
2. each cycle: the gap before the deadline (``_Child.gap``: the node's requests, and the
   updates that fit), then the cycle (read -> controller -> write, its record into the ring);
   with a backend whose servo loop is the clock
   (:attr:`~haptic_topology.device.backend.DeviceBackend.drives_loop`: OpenHaptics), the
   cycle and then the gap's work run inside the device's callback at each servo tick
   (``_Child.run_clocked``) and this thread only waits: no pacer of its own;
3. until asked to stop (a request, SIGTERM, its parent's death) or the run's end; then, in a
   ``finally`` that every way out of 1 and 2 takes, zero wrench and release the device, and a
   final status.

A backend that raises (at ``configure``, when the child starts, or later) ends the child
with its message in the final status's ``error``
(:func:`~haptic_topology.errors.error_line`) and the traceback on stderr (the
driver's log).
"""

from __future__ import annotations

import base64
import gc
import json
import os
import pickle
import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from haptic_topology.control.loop import ControllerLoop
from haptic_topology.control.port import HEALTH_MESSAGES
from haptic_topology.control.update_record import decode_update
from haptic_topology.device.backend import create_backend, zero_and_release
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop import RTT_KEEP, DeviceLoop, device_report
from haptic_topology.device.loop_process import GC_EVERY, STATUS_PERIOD, LoopSpec
from haptic_topology.device.loop_rings import STATUS_BYTES, LoopRings, wait_eventfd
from haptic_topology.device.pacing import PERIOD_WINDOW
from haptic_topology.device.realtime import (
    name_os_thread,
    set_parent_death_signal,
    set_thread_realtime,
)
from haptic_topology.device.records import CycleCodec, payloads, put_bytes
from haptic_topology.device.runner import LoopRunner, Published
from haptic_topology.device.shm_ring import ShmRing
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.errors import error_line
from haptic_topology.processes import stacks_on_signal

#: Wall clock: the least an LMI update is taken to cost to apply (s): its decoding and
#: re-sync take 0.1-0.2 ms with a few links here (about 1 ms with 100: then the measured
#: cost rules, :class:`UpdateTiming`).
APPLY_BEFORE = 0.3e-3
#: Applies whose duration :class:`UpdateTiming` keeps to estimate the next one's.
COST_WINDOW = 8


class UpdateTiming:
    """When the loop process applies the LMI updates waiting in its ring: the one object
    that decides it.

    * **Lock-step** (``before_step``): before every step, all of them, so each state is
      answered after exactly the updates the offline simulation applies before it.
    * **Wall clock**: never before a step (the deadline path). Between two cycles, oldest
      first, one at a time while the time left before the next deadline is more than one
      costs (``cost``: the longest of the last :data:`COST_WINDOW` applies, at least
      :data:`APPLY_BEFORE`); the rest wait for the gap after the next cycle, which runs on
      the model it has. Updates left over from a gap are owed: in the next gap the oldest of
      them is applied first whatever it costs, so an update costlier than any gap is applied
      one cycle late rather than never.
    """

    def __init__(self, lockstep: bool) -> None:
        self.before_step = lockstep
        self._recent: deque[float] = deque(maxlen=COST_WINDOW)
        self.cost = APPLY_BEFORE
        self._owed = False

    def fits(self, left: float, first: bool) -> bool:
        """Whether to apply the oldest waiting update now, ``left`` s before the deadline;
        ``first``: the gap's first look."""
        return left > self.cost or (first and self._owed)

    def applied(self, seconds: float) -> None:
        """One update took ``seconds`` to apply."""
        self._recent.append(seconds)
        self.cost = max(APPLY_BEFORE, max(self._recent))

    def end_gap(self, waiting: bool) -> None:
        """The gap ends with updates still ``waiting`` (owed to the next gap) or none."""
        self._owed = waiting


class _RingCycle(HostedCycle):
    """A :class:`HostedCycle` whose updates come from the node's ring (``ring``), applied
    straight to the controller when ``timing`` says: before each step (lock-step,
    :meth:`apply_updates`, which :meth:`step` calls first), in the gap between two cycles
    (wall clock, :meth:`apply_in_gap`) and all at once before the loop starts
    (:meth:`catch_up`). A step reports the verdicts of the updates applied since the step
    before it. ``wake_fd`` and ``poll``: lock-step's wait for an update (the node's eventfd,
    and the child's look at its requests meanwhile)."""

    def __init__(self, device: DeviceLoop, controller: ControllerLoop, ring: ShmRing,
                 timing: UpdateTiming, wake_fd: int, poll: Callable[[], None],
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(device, controller)
        self._ring, self.timing = ring, timing
        self._wake_fd, self._poll, self._clock = wake_fd, poll, clock
        self._applied: tuple[str, ...] = ()

    @property
    def waiting(self) -> bool:
        """Updates are waiting in the ring."""
        return self._ring.pending > 0

    def _apply(self, limit: int | None = None) -> None:
        for data in payloads(self._ring, limit):
            started = self._clock()
            self._applied += (self.controller.on_update(decode_update(data)),)
            self.updates_offered += 1
            self.updates_applied += 1
            self.timing.applied(self._clock() - started)

    def apply_updates(self) -> tuple[str, ...]:
        if self.timing.before_step:
            self._apply()
        done, self._applied = self._applied, ()
        return done

    def apply_in_gap(self, deadline: float, first: bool) -> None:
        """Wall clock: apply the waiting updates that fit before ``deadline`` (s, the
        clock's), oldest first (``first``: the gap's first look; see :class:`UpdateTiming`)."""
        while self.waiting and self.timing.fits(deadline - self._clock(), first):
            self._apply(limit=1)
            first = False

    def catch_up(self) -> None:
        """Apply every update waiting (before the deadline grid starts)."""
        self._apply()

    def wait_offered(self, timeout: float) -> bool:
        if self.waiting:
            return True
        wait_eventfd(self._wake_fd, timeout)
        self._poll()
        return self.waiting


class RingOutbox:
    """The runner's outbox (:class:`~haptic_topology.device.runner.Outbox`) as the cycle
    ring: each cycle's record is written straight into it, overwriting the oldest when full
    (wall clock: the deadline never waits for the node; lock-step waits for ``room()``),
    and ``wake`` is called after each (lock-step: the node's eventfd)."""

    def __init__(self, ring: ShmRing, codec: CycleCodec, overwrite: bool,
                 wake: Callable[[], None]) -> None:
        self._ring, self._codec, self._overwrite, self._wake = ring, codec, overwrite, wake

    @property
    def dropped(self) -> int:
        """Records overwritten (wall clock) or refused (lock-step, before engagement)."""
        return self._ring.overwritten + self._ring.refused

    def __len__(self) -> int:
        return self._ring.pending

    def room(self) -> bool:
        return not self._ring.full

    def put(self, entry: Published) -> None:
        self._ring.put(self._codec.encode(entry), self._overwrite)
        self._wake()


class _Child:
    """The child's loop (see module doc)."""

    def __init__(self, spec: LoopSpec) -> None:
        self.spec = spec
        m = spec.limit.size
        self.mem = LoopRings.attach(spec.segments, m, spec.dof)
        rings = self.mem.rings
        #: Why the child failed (the backend's own message), in its final status for the node.
        self.error = ''
        name = spec.backend
        try:
            self.backend = create_backend(spec.backend)
            name = self.backend.name
            self.backend.configure(spec.backend_config)
        except Exception as exc:        # the backend's own code: its reason goes to the node
            last_words(self.mem, spec.generation, error_line(exc, f'{name}: configure()'))
            self.mem.close()
            raise
        try:
            if spec.carry is not None:          # where the previous activation's child left it
                self.backend.resume(spec.carry)
            self.device = DeviceLoop(self.backend, spec.limit, CommandWatchdog(spec.watchdog, m),
                                     spec.period, spec.takeover_after)
            self.cycle = _RingCycle(self.device, spec.controller, rings['updates'],
                                    UpdateTiming(spec.runner.lockstep), spec.wake_child,
                                    self.poll_control)
            lockstep = spec.runner.lockstep
            outbox = RingOutbox(rings['cycles'], CycleCodec(m), not lockstep,
                                self._wake_node if lockstep else lambda: None)
            self.runner = LoopRunner(self.cycle, spec.runner, outbox=outbox)
            # The statistics the node sorts for the percentiles, in memory it reads.
            arrays = self.mem.arrays
            self.runner.pacer.use_period_buffer(arrays['periods'].array,
                                                arrays['lateness'].array)
            self.device.use_round_trip_buffer(arrays['round_trips'].array)
        except BaseException as exc:
            last_words(self.mem, spec.generation, error_line(exc, f'{name}: start'))
            self.backend.cleanup()
            self.mem.close()
            raise
        self.notices: list[str] = []
        self.stop = False
        self.parent_gone = False
        self._status_at = 0.0

    def _wake_node(self) -> None:
        os.eventfd_write(self.spec.wake_node, 1)

    def gap(self) -> None:
        """Wall clock: the gap before the next deadline. Serves the node's requests and
        applies the LMI updates that :class:`UpdateTiming` lets in, as they come (the node
        signals its eventfd after writing); returns at the deadline, or at a stop."""
        deadline = self.runner.pacer.next_deadline()
        first = True
        while True:
            self.poll_control()
            if self.stop:
                return
            self.cycle.apply_in_gap(deadline, first)
            first = False
            left = deadline - time.monotonic()
            if left <= 0.0 or not wait_eventfd(self.spec.wake_child, left):
                self.cycle.timing.end_gap(self.cycle.waiting)
                return

    def poll_control(self) -> None:
        for data in payloads(self.mem.rings['control']):
            generation, *item = pickle.loads(data)
            if generation != self.spec.generation:
                continue            # for the child before this one
            if item[0] == 'engage':
                self.runner.may_engage = bool(item[1])
            elif item[0] == 'law':
                self.cycle.controller.ctrl.gains, self.cycle.controller.ctrl.mode = item[1:]
            elif item[0] == 'stop':
                self.stop = True
                self.runner.request_stop()
        if os.getppid() != self.spec.parent:
            self.parent_gone = self.stop = True
            self.runner.request_stop()

    def report(self, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now - self._status_at < STATUS_PERIOD:
            return
        self._status_at = now
        r, c = self.runner, self.cycle.controller
        loop_now = c.loop_time
        self.notices.extend(r.notices)
        r.notices.clear()
        self.notices.extend(c.notices)
        c.notices.clear()
        carry = None
        if final:               # after zero_and_release: for the next activation's child
            try:
                carry = self.backend.carry_over()
            except Exception as exc:    # a backend's own code: the rings are closed all the same
                self.notices.append(f'{self.backend.name}: carry_over() failed: {exc}')
        device = r.device_values(percentiles=False)
        level, message, values = device_report(self.device, now, '', 0, device,
                                               percentiles=False)
        status = {'device': device, 'report': [level, message, values],
                  'n_periods': r.pacer.periods[1], 'n_round_trips': self.device.round_trips[1],
                  'hardware_id': self.backend.hardware_id,
                  'controller': c.values(loop_now),
                  'health': list(HEALTH_MESSAGES[c.guard.health(loop_now)]),
                  'finished': r.finished, 'lockstep_timeouts': r.lockstep_timeouts,
                  'rings': self.mem.counts(),
                  'generation': self.spec.generation, 'final': final, 'error': self.error,
                  'carry': None if carry is None else base64.b64encode(carry).decode(),
                  'notices': self.notices[-50:]}
        data = json.dumps(status).encode()
        if final and len(data) > STATUS_BYTES:      # the last record: without the notices
            print('\n'.join(self.notices), file=sys.stderr, flush=True)
            data = json.dumps(dict(status, notices=[])).encode()
        if len(data) <= STATUS_BYTES:       # else the notices wait for the next record
            put_bytes(self.mem.rings['status'], data, 'status')
            self.notices = []

    def run_clocked(self) -> None:
        """The loop on the device's servo clock
        (:meth:`~haptic_topology.device.backend.DeviceBackend.run_clocked`): each servo tick,
        the cycle inside the device's callback, then, once the frame has gone to the device,
        the gap's work before the next tick (the node's requests, the updates that
        :class:`UpdateTiming` lets in before ``now + period``, the status, a collection every
        :data:`GC_EVERY` cycles). This thread waits meanwhile; the signals end the wait."""
        s, k = self.spec, 0

        def cycle(now: float) -> None:
            nonlocal k
            if k == 0:          # the servo thread: named and scheduled as the loop's would be
                name_os_thread('device_loop')
                self.notices.extend(set_thread_realtime(s.sched_priority, s.cpu_affinity,
                                                        s.lock_memory, s.sched_slice_us,
                                                        s.timer_slack_ns))
            self.runner.cycle_at(now)

        def between(now: float) -> bool:
            nonlocal k
            self.poll_control()
            if self.stop or self.runner.finished:
                return False
            self.cycle.apply_in_gap(now + s.period, True)
            self.cycle.timing.end_gap(self.cycle.waiting)
            k += 1
            if k % GC_EVERY == 0:
                gc.collect(1)
            self.report()
            return True

        self.backend.run_clocked(s.period, cycle, between, lambda: not self.stop)

    def run(self) -> int:
        s = self.spec
        name_os_thread('device_loop')
        self.notices.extend(set_thread_realtime(s.sched_priority, s.cpu_affinity,
                                                s.lock_memory, s.sched_slice_us,
                                                s.timer_slack_ns))
        wall = not s.runner.lockstep
        activated = False
        try:
            if self.stop:               # asked before it began: the device is not enabled
                return 0
            activated = True
            try:
                self.backend.activate()
            except Exception as exc:
                self.error = error_line(exc, f'{self.backend.name}: activate()')
                raise
            self.report()       # the first status: the device is active (the node waits)
            # The updates that came while this process started (the VE's keep-alives, up to
            # the ring's capacity), before the first deadline: in the first gap between two
            # cycles their copy and re-syncs overran it (5 ms with 3 links, 35 ms with 100).
            # Then the collection, also before the clock starts.
            self.cycle.catch_up()
            gc.collect()
            gc.freeze()
            gc.disable()
            if self.backend.drives_loop:
                self.run_clocked()
                return 0
            self.runner.pacer.start()
            k = 0
            while not self.stop and not self.runner.finished:
                if wall:
                    self.gap()
                else:
                    self.poll_control()
                if self.stop:
                    break
                self.runner.cycle_once()
                k += 1
                if k % GC_EVERY == 0:
                    gc.collect(1)
                self.report()
        except Exception as exc:
            self.error = self.error or error_line(exc, f'{self.backend.name}: the loop')
            raise
        finally:
            if activated:
                self.notices.extend(zero_and_release(self.backend, s.limit.size))
            if self.parent_gone or os.getppid() != s.parent:
                print(f'loop process {os.getpid()}: parent gone: output zeroed, device '
                      'released', file=sys.stderr, flush=True)
            self.report(final=True)
            self.backend.cleanup()
            self.runner.pacer.use_period_buffer(np.zeros(PERIOD_WINDOW))
            self.device.use_round_trip_buffer(np.zeros(RTT_KEEP))
            self.mem.close()
        return 0


def last_words(mem: LoopRings, generation: int, error: str) -> None:
    """The final status of a child that failed before its loop could report: ``error`` (the
    node's :meth:`~haptic_topology.device.loop_process.LoopProcess.wait_started` raises it)."""
    status = {'generation': generation, 'final': True, 'finished': False, 'error': error,
              'notices': []}
    data = json.dumps(status).encode()
    if len(data) > STATUS_BYTES:
        data = json.dumps(dict(status, error=error[:STATUS_BYTES // 2])).encode()
    put_bytes(mem.rings['status'], data, 'status')


def child_main() -> int:
    """Entry point of the child (``python -m haptic_topology.device.loop_child``)."""
    spec: LoopSpec = pickle.loads(sys.stdin.buffer.read())
    child: _Child | None = None
    asked: set[int] = set()             # the signals that came before the child was built

    def on_signal(signum: int, frame: Any) -> None:
        # SIGHUP: the parent died (PR_SET_PDEATHSIG; it comes as the parent's thread exits,
        # when getppid() may still name it). SIGTERM: the node's escalation of a stop.
        asked.add(signum)
        if child is not None:
            child.stop = True
            child.parent_gone = child.parent_gone or signum == signal.SIGHUP
            child.runner.request_stop()

    stacks_on_signal()
    signal.signal(signal.SIGTERM, on_signal)          # before the signals can come
    signal.signal(signal.SIGHUP, on_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the node's Ctrl-C stops us by request
    set_parent_death_signal(signal.SIGHUP)
    if os.getppid() != spec.parent:         # the parent died before the signal was set
        print(f'loop process {os.getpid()}: parent gone before the start: device not opened',
              file=sys.stderr, flush=True)
        return 1
    child = _Child(spec)
    if asked:
        child.stop = True
        child.parent_gone = signal.SIGHUP in asked or os.getppid() != spec.parent
    return child.run()


if __name__ == '__main__':
    raise SystemExit(child_main())
