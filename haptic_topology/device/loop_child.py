"""The child of :class:`~haptic_topology.device.loop_process.LoopProcess`: the hosted loop in
its one thread, no rclpy (``python -m haptic_topology.device.loop_child``; the module doc of
:mod:`haptic_topology.device.loop_process` describes the exchange and the lifetimes).

It reads its :class:`~haptic_topology.device.loop_process.LoopSpec` from stdin, opens the
device, builds the :class:`~haptic_topology.device.hosted.HostedCycle` (its updates taken
from the node's ring) and a :class:`~haptic_topology.device.runner.LoopRunner` whose outbox
goes into the cycle ring, applies the real-time options to itself and the LMI updates that
came while it started, freezes the collector's view of everything built so far, and runs
the cycles until asked to stop, until the run's end, or until its parent dies; then it
writes zero wrench and releases the device.
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
from typing import Any

import numpy as np

from haptic_topology.control.loop import ControllerLoop
from haptic_topology.control.port import HEALTH_MESSAGES
from haptic_topology.control.update_record import decode_update
from haptic_topology.device.backend import create_backend, zero_and_release
from haptic_topology.device.hosted import HostedCycle
from haptic_topology.device.loop import RTT_KEEP, DeviceLoop, device_report
from haptic_topology.device.loop_process import (
    CONTROL_BYTES,
    CYCLE_RECORDS,
    GC_EVERY,
    STATUS_BYTES,
    STATUS_PERIOD,
    UPDATE_RECORDS,
    LoopSpec,
    wait_eventfd,
)
from haptic_topology.device.pacing import PERIOD_WINDOW
from haptic_topology.device.realtime import (
    name_os_thread,
    set_parent_death_signal,
    set_thread_realtime,
)
from haptic_topology.device.records import CycleCodec, bytes_dtype, payloads, put_bytes
from haptic_topology.device.runner import LoopRunner
from haptic_topology.device.shm_ring import SharedArray, ShmRing
from haptic_topology.device.watchdog import CommandWatchdog
from haptic_topology.processes import stacks_on_signal

#: Wall clock: an LMI update is applied between two cycles only while at least this long (s)
#: is left before the next deadline; its decoding and re-sync take 0.1-0.2 ms here, and one
#: that came later would delay the next cycle. It waits in the ring for the gap after that
#: cycle instead.
APPLY_BEFORE = 0.3e-3


class _RingCycle(HostedCycle):
    """A :class:`HostedCycle` whose updates come from the node's ring.

    :meth:`apply_early` applies the updates that came while the loop sleeps towards its next
    deadline: nothing changes the loop's state between the end of one cycle and the start of
    the next, so the controller ends up where applying them at the start of the next cycle
    would leave it (the same loop time, the same inputs replayed), and the cycle that follows
    has only the step left. Their verdicts are returned with that cycle's.

    ``lockstep``: every step first takes what is in the ring, so each state is answered
    after exactly the updates the offline simulation applies before it. With the wall clock
    a step takes from the ring only the updates :meth:`defer` left there (no gap came since:
    the loop overran); the others wait for the gap after the step, so a step never waits for
    an update's re-sync."""

    def __init__(self, device: DeviceLoop, controller: ControllerLoop, ring: ShmRing,
                 wake_fd: int, poll: Any, lockstep: bool) -> None:
        super().__init__(device, controller)
        self._ring, self._wake_fd, self._poll = ring, wake_fd, poll
        self._early: tuple[str, ...] = ()
        self._lockstep = lockstep
        self._deferred = False

    def pull(self) -> bool:
        got = False
        for data in payloads(self._ring):
            self.offer_update(decode_update(data))
            got = True
        return got

    @property
    def waiting(self) -> bool:
        """Updates are waiting in the ring."""
        return self._ring.pending > 0

    def apply_updates(self) -> tuple[str, ...]:
        if self._lockstep or self._deferred:
            self._deferred = False
            self.pull()
        early, self._early = self._early, ()
        return early + super().apply_updates()

    def apply_early(self) -> None:
        """Take and apply the updates in the ring now, between two cycles (see class doc)."""
        self._deferred = False
        self.pull()
        self._early += super().apply_updates()

    def defer(self) -> None:
        """Leave the updates in the ring for the next gap between two cycles; if the loop
        steps before one comes (an overrun), that step takes them."""
        self._deferred = True

    def wait_offered(self, timeout: float) -> bool:
        if self.pull():
            return True
        wait_eventfd(self._wake_fd, timeout)
        self._poll()
        return self.pull()


class _Child:
    """The child's loop (see module doc)."""

    def __init__(self, spec: LoopSpec) -> None:
        self.spec = spec
        rings = spec.rings
        self.codec = CycleCodec(spec.limit.size)
        self.cycles = ShmRing.attach(rings['cycles'], self.codec.dtype, CYCLE_RECORDS)
        self.control = ShmRing.attach(rings['control'], bytes_dtype(CONTROL_BYTES), 64)
        self.status_ring = ShmRing.attach(rings['status'], bytes_dtype(STATUS_BYTES), 4)
        updates = ShmRing.attach(rings['updates'], bytes_dtype(spec.update_bytes),
                                 UPDATE_RECORDS)
        self.rings = [self.cycles, self.control, self.status_ring, updates]
        self.backend = create_backend(spec.backend)
        self.backend.configure(spec.backend_config)
        if spec.carry is not None:          # where the previous activation's child left it
            self.backend.resume(spec.carry)
        dim = spec.limit.size
        self.device = DeviceLoop(self.backend, spec.limit, CommandWatchdog(spec.watchdog, dim),
                                 spec.period, spec.takeover_after)
        self.cycle = _RingCycle(self.device, spec.controller, updates, spec.wake_child,
                                self.poll_control, spec.runner.lockstep)
        self.runner = LoopRunner(self.cycle, spec.runner, sleep=self.sleep, wake=self.flush)
        # The statistics the node sorts for the percentiles, in memory it reads.
        self.arrays = [SharedArray.attach(spec.periods, PERIOD_WINDOW),
                       SharedArray.attach(spec.round_trips, RTT_KEEP),
                       SharedArray.attach(spec.lateness, PERIOD_WINDOW)]
        self.runner.pacer.use_period_buffer(self.arrays[0].array, self.arrays[2].array)
        self.device.use_round_trip_buffer(self.arrays[1].array)
        self.notices: list[str] = []
        self.stop = False
        self.parent_gone = False
        self._status_at = 0.0

    def sleep(self, seconds: float) -> None:
        """The pacer's sleep until the next deadline: it ends early when the node signals
        (an update or a request), and the updates waiting are decoded and applied then,
        between two cycles (:meth:`_RingCycle.apply_early`), if at least
        :data:`APPLY_BEFORE` is left; the pacer sleeps again until the deadline. Else they
        wait for the gap after the next cycle (:meth:`_RingCycle.defer`)."""
        end = time.monotonic() + seconds
        if not self.cycle.waiting and not wait_eventfd(self.spec.wake_child, seconds):
            return
        left = end - time.monotonic()
        if left > APPLY_BEFORE:
            self.cycle.apply_early()
        else:
            self.cycle.defer()
            time.sleep(max(left, 0.0))

    def poll_control(self) -> None:
        for data in payloads(self.control):
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

    def flush(self) -> None:
        """Move the runner's outbox into the cycle ring (lock-step: as room allows)."""
        box = self.runner.outbox
        wrote = False
        while box:
            if not self.cycles.put(self.codec.encode(box[0]), not self.spec.runner.lockstep):
                break
            box.popleft()
            wrote = True
        if wrote and self.spec.runner.lockstep:
            os.eventfd_write(self.spec.wake_node, 1)

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
                  'generation': self.spec.generation, 'final': final,
                  'carry': None if carry is None else base64.b64encode(carry).decode(),
                  'notices': self.notices[-50:]}
        data = json.dumps(status).encode()
        if final and len(data) > STATUS_BYTES:      # the last record: without the notices
            print('\n'.join(self.notices), file=sys.stderr, flush=True)
            data = json.dumps(dict(status, notices=[])).encode()
        if len(data) <= STATUS_BYTES:       # else the notices wait for the next record
            put_bytes(self.status_ring, data, 'status')
            self.notices = []

    def run(self) -> int:
        s = self.spec
        name_os_thread('device_loop')
        self.notices.extend(set_thread_realtime(s.sched_priority, s.cpu_affinity,
                                                s.lock_memory, s.sched_slice_us,
                                                s.timer_slack_ns))
        self.backend.activate()
        # The updates that came while this process started (the VE's keep-alives, up to the
        # ring's UPDATE_RECORDS) are applied now, before the first deadline: in the first gap
        # between two cycles their copy and re-syncs overran it (5 ms with 3 links, 35 ms
        # with 100). Then the collection, also before the clock starts.
        self.cycle.apply_early()
        gc.collect()
        gc.freeze()
        gc.disable()
        self.runner.pacer.start()
        k = 0
        try:
            while not self.stop and not self.runner.finished:
                self.poll_control()
                if self.stop:
                    break
                self.runner.cycle_once()
                self.flush()
                k += 1
                if k % GC_EVERY == 0:
                    gc.collect(1)
                self.report()
            while self.runner.outbox and s.runner.lockstep and not self.stop:
                self.flush()
                time.sleep(0.001)
                self.poll_control()
        finally:
            zero_and_release(self.backend, s.limit.size)
            if self.parent_gone or os.getppid() != s.parent:
                print(f'loop process {os.getpid()}: parent gone: output zeroed, device '
                      'released', file=sys.stderr, flush=True)
            self.report(final=True)
            self.backend.cleanup()
            for ring in self.rings:
                ring.close()
            self.runner.pacer.use_period_buffer(np.zeros(PERIOD_WINDOW))
            self.device.use_round_trip_buffer(np.zeros(RTT_KEEP))
            for arr in self.arrays:
                arr.close()
        return 0


def child_main() -> int:
    """Entry point of the child (``python -m haptic_topology.device.loop_child``)."""
    spec: LoopSpec = pickle.loads(sys.stdin.buffer.read())
    child: _Child | None = None
    term = [False]

    def on_term(signum: int, frame: Any) -> None:     # the parent died (PR_SET_PDEATHSIG)
        term[0] = True
        if child is not None:
            child.parent_gone = child.stop = True
            child.runner.request_stop()

    stacks_on_signal()
    signal.signal(signal.SIGTERM, on_term)            # before the signal can come
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the node's Ctrl-C stops us by request
    set_parent_death_signal(signal.SIGTERM)
    if os.getppid() != spec.parent:         # the parent died before the signal was set
        print(f'loop process {os.getpid()}: parent gone before the start: device not opened',
              file=sys.stderr, flush=True)
        return 1
    child = _Child(spec)
    if term[0]:
        child.parent_gone = child.stop = True
    return child.run()


if __name__ == '__main__':
    raise SystemExit(child_main())

