"""The hosted 1 kHz loop in a process of its own: no GIL shared with ROS on the deadline path.

(One module of ~520 lines on purpose: the node's side of the loop process, its start, stop
and exchange with the child, described once, below.)

With ``loop_process: true`` the hosted ``device_driver`` (the ROS node: lifecycle,
parameters, topics, diagnostics) does not step the loop in a thread of its own process. At
activation it starts a child, ``python -m haptic_topology.device.loop_child``, which imports
no rclpy and runs the same :class:`~haptic_topology.device.hosted.HostedCycle` and
:class:`~haptic_topology.device.runner.LoopRunner` (absolute deadlines, or lock-step) that
``simulate`` and the in-process layout run, in its one thread, and owns the device backend.
The two processes exchange fixed-layout records through shared-memory rings
(:class:`~haptic_topology.device.shm_ring.ShmRing`, single producer / single consumer,
torn reads detected), never a lock:

* child -> node, one record per cycle
  (:class:`~haptic_topology.device.records.CycleCodec`: the state, the command, the hand
  input for the VE); the node publishes them (``DeviceState``, ``DeviceCommand``, hand-input
  batches). A full ring drops its oldest record and counts it (wall clock: the deadline never
  waits for the node) or holds the loop until the node has taken some (lock-step: nothing
  recorded is lost);
* node -> child, LMI updates (a
  :class:`~haptic_topology.control.controller.PreparedUpdate` as an
  :mod:`~haptic_topology.control.update_record`: the snapshot with the matrices
  its re-sync takes, computed by the node; applied between two cycles, see below) and
  control requests (engagement permission, live law and gains, stop);
* child -> node, a status record every :data:`STATUS_PERIOD` s: the loop's, the device's and
  the controller's diagnostics values, and notices for the node's log. The last one, written
  after the device is released, carries what the backend hands over to the next activation's
  child (:meth:`~haptic_topology.device.backend.DeviceBackend.carry_over`: the simulated
  maglev's state, so that it resumes where it stopped, as an in-process backend does).

The rings' layout and their losses: :mod:`~haptic_topology.device.loop_rings`.
In lock-step each side wakes the other with an ``eventfd`` after writing (the child after a
cycle's record, the node after an update); with the wall clock the node takes the records
every few milliseconds and the child never makes a system call for it, and the child waits
out the gap before its next deadline on the node's ``eventfd``: requests are served then,
and LMI updates applied when :class:`~haptic_topology.device.loop_child.UpdateTiming` says
(off the deadline path: the loop's state does not change between two cycles, so this is what
applying them at the start of the next cycle would do).

Lifetimes: the node creates the rings when the driver is configured (a ``/dev/shm`` without
room fails there) and unlinks them at cleanup. An activation starts a child and waits for
its first status, written once the backend is configured and activated
(:meth:`LoopProcess.wait_started`); a child that cannot open the device writes a final status
with ``error``, the backend's own message, which fails the activation. A deactivation
stops it: a stop request, then, if the child has not exited within :data:`STOP_TIMEOUT`
(or could not be asked: its control ring full), SIGTERM, then, after :data:`TERM_TIMEOUT`,
SIGKILL. The child turns a stop request, SIGTERM and its parent's death
(``PR_SET_PDEATHSIG`` delivers SIGHUP, and the parent pid is checked every cycle) into the
end of its loop, and writes zero wrench and releases the device
(:func:`~haptic_topology.device.backend.zero_and_release`) in a ``finally`` that every path
out of its loop takes, a failed activation included; only SIGKILL skips it (then the device's
own command timeout must hold it). The node sees an unrequested exit at its next check
(every 20 ms) and reports it as the device's fault. The child unregisters the rings from its
resource tracker (:meth:`~haptic_topology.device.shm_ring.ShmRing.attach`), so only the owner
unlinks them: its :meth:`LoopProcess.close`, or its tracker when it dies.

Each child is a generation: requests, status and hand-over carry its number, and nothing of
an earlier child is taken as the new one's (one that dies before its first status is a fault).

The percentiles of the child's statistics (720,000 periods, wake-up lateness and round
trips) are sorted in a thread of the node's (``loop_rings.SortedFigures``), once per
:data:`STATUS_PERIOD` at most, when diagnostics ask: never in the executor thread.

In the child, after start-up, :func:`gc.freeze` moves every object built so far out of the
collector's view and automatic collection is off; a young-generation collection runs every
:data:`GC_EVERY` cycles right after a cycle, when the loop waits for its next deadline.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.control.laws import ControlGains
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.loop import ControllerLoop
from haptic_topology.control.update_record import encode_update
from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.hosted import MAX_PENDING
from haptic_topology.device.loop_rings import (
    LoopRings,
    SortedFigures,
    add_counts,
    wait_eventfd,
)
from haptic_topology.device.records import CycleCodec, payloads, put_bytes, update_bytes
from haptic_topology.device.runner import Published, RunnerConfig
from haptic_topology.device.watchdog import WatchdogConfig
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import ControlMode

#: The module the loop process runs (``python -m``).
CHILD_MODULE = 'haptic_topology.device.loop_child'
#: Seconds between two status records of the child.
STATUS_PERIOD = 0.2
#: Cycles between two young-generation collections in the child.
GC_EVERY = 1000
#: How long the node waits for the child to stop after a stop request (s); longer by
#: START_TIMEOUT while it has not reported from its loop (importing, opening the device).
STOP_TIMEOUT = 3.0
START_TIMEOUT = 30.0
#: How long the node waits for the child to exit after SIGTERM before SIGKILL (s).
TERM_TIMEOUT = 2.0


@dataclass(frozen=True)
class LoopSpec:
    """What the child builds its loop from (pickled to its stdin): the backend (name and
    configuration: the child opens the device), the device loop's limits, watchdog, period
    and takeover time, the controller loop (built by the hosted ``lmi_controller``, never
    stepped in the node), the runner's pacing, real-time options, the segments' names
    (:class:`~haptic_topology.device.loop_rings.LoopRings`) and the linkage's joints (their
    layout), wake-up descriptors, and the parent's pid."""

    backend: str
    backend_config: BackendConfig
    limit: np.ndarray
    watchdog: WatchdogConfig
    period: float
    takeover_after: float
    controller: ControllerLoop
    runner: RunnerConfig
    sched_priority: int
    cpu_affinity: tuple[int, ...]
    lock_memory: bool
    sched_slice_us: float
    timer_slack_ns: int
    segments: dict[str, str]
    dof: int
    wake_node: int            # eventfd the child writes (lock-step: after each record)
    wake_child: int           # eventfd the node writes (after an update or a request)
    parent: int
    generation: int           # the child's number: requests for an earlier one are ignored
    #: What the previous child's backend carried over
    #: (:meth:`~haptic_topology.device.backend.DeviceBackend.carry_over`): resumed after
    #: ``configure``. None: the first activation, or a backend that carries nothing.
    carry: bytes | None = None


class LoopProcess:
    """The node's handle of the child (see module doc; a deactivation stops the child, an
    activation starts a new one on the same rings): a
    :class:`~haptic_topology.device.runner.LoopHandle`, with :meth:`drain_records`,
    :meth:`wait` and :meth:`check` for the node's publishing thread and timer."""

    def __init__(self, spec: dict[str, Any], task_dim: int, dof: int) -> None:
        self._spec = spec          # LoopSpec fields but the segments, fds and parent
        self.codec = CycleCodec(task_dim)
        self._dof = dof
        self._update_bytes = update_bytes(dof)
        self.lockstep = bool(spec['runner'].lockstep)
        self.notices: deque[str] = deque(maxlen=100)
        self.status: dict[str, Any] = {}
        self._proc: subprocess.Popen[bytes] | None = None
        self._may_engage = False
        self._stopping = False
        self.error: BaseException | None = None
        self.taken = 0              # cycle records taken
        self.generation = 0         # children started (requests carry it)
        self._pending: deque[bytes] = deque(maxlen=MAX_PENDING)    # update records
        self.updates_dropped = 0
        self.updates_refused = 0    # too large for a record
        self._status_lock = threading.Lock()    # the status ring's one consumer at a time
        #: The newest child's hand-over (its final status), for the next child.
        self._carry: bytes | None = None
        self._figures = SortedFigures(self._sorted, STATUS_PERIOD)
        #: An ended child's figures, and the status they were sorted for.
        self._final: tuple[dict[str, Any], dict[str, str]] | None = None
        # The segments now (the driver is being configured): no room is an error here.
        self._mem: LoopRings | None = LoopRings.create(task_dim, dof)
        self._fds: tuple[int, int] | None = (os.eventfd(0, os.EFD_NONBLOCK),
                                             os.eventfd(0, os.EFD_NONBLOCK))

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self, name: str = 'device_loop', on_start: Any = None) -> None:
        """Start a child (``on_start`` is not used: the child applies the real-time options
        itself)."""
        if self.running:
            raise RuntimeError('LoopProcess.start: already running')
        if self._mem is None or self._fds is None:
            raise RuntimeError('LoopProcess.start: closed')
        ended_final = self.status.get('final') is True
        self.error = None
        self._stopping = False
        self.generation += 1
        self.status = {}            # the new child's, from its first record on
        if self.generation > 1 and not ended_final:
            self._carry = None      # not an older child's: that state is not the device's now
            self.notices.append('the previous loop process ended without handing its device '
                                'state over: the device starts as configured (a simulated '
                                'one at its initial pose)')
        spec = LoopSpec(**self._spec, carry=self._carry, segments=self._mem.names(),
                        dof=self._dof, wake_node=self._fds[0], wake_child=self._fds[1],
                        parent=os.getpid(), generation=self.generation)
        # This node's session (as haptic-topology run starts every node), a process group of
        # its own: under the kernel's autogroup the scheduler weighs the loop thread against
        # the nodes' threads directly, by nice, SCHED_BATCH and its slice (docs/nodes.md).
        self._proc = subprocess.Popen(
            [sys.executable, '-m', CHILD_MODULE],
            stdin=subprocess.PIPE, pass_fds=self._fds, close_fds=True, process_group=0)
        assert self._proc.stdin is not None
        self._proc.stdin.write(pickle.dumps(spec))
        self._proc.stdin.close()
        if not self._request(('engage', self._may_engage)):
            self.notices.append('loop process: control ring full at the start')

    def stop(self, timeout: float = STOP_TIMEOUT) -> None:
        """Stop the child (see module doc: a request, then SIGTERM, then SIGKILL); it zeroes
        the device and releases it unless killed. Never raises: what went wrong is in
        ``notices``, and a child that had to be killed is ``error``."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            self._poll_status()
            return
        self._stopping = True
        asked = self._request(('stop',))
        self._poll_status()
        if self.status.get('generation') != self.generation:      # not in its loop yet
            timeout += START_TIMEOUT
        try:
            if asked:
                try:
                    proc.wait(timeout)
                    return
                except subprocess.TimeoutExpired:
                    why = f'did not stop within {timeout:g} s of a stop request'
            else:
                why = 'could not be asked to stop (its control ring is full)'
            self._terminate(proc, why)
        finally:
            self._poll_status()

    def _terminate(self, proc: subprocess.Popen[bytes], why: str) -> None:
        """SIGTERM (the child zeroes and releases the device), then SIGKILL after
        :data:`TERM_TIMEOUT`."""
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(TERM_TIMEOUT)
            self.notices.append(f'loop process {proc.pid} {why}: stopped by SIGTERM (output '
                                'zeroed, device released)')
            return
        except subprocess.TimeoutExpired:
            pass
        proc.kill()
        proc.wait()
        self.error = DeviceError(f'loop process {proc.pid} {why} and did not exit within '
                                 f'{TERM_TIMEOUT:g} s of SIGTERM: killed, device output not '
                                 'known to be zeroed')
        self.notices.append(str(self.error))

    def close(self) -> None:
        """Stop a running child (:meth:`stop`), stop the figures' thread, then unlink the
        segments and close the descriptors, each whatever the others do (at cleanup, or at
        shutdown)."""
        try:
            self.stop()
        finally:
            self._figures.stop()
            mem, fds = self._mem, self._fds
            self._mem = self._fds = None
            try:
                if mem is not None:
                    mem.close()
            finally:
                for fd in fds or ():
                    os.close(fd)

    def ring_names(self) -> list[str]:
        """The shared-memory segments (``/dev/shm/<name>``)."""
        return list(self._mem.names().values()) if self._mem else []

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def running(self) -> bool:
        """The child runs (and has not finished its run)."""
        return self._proc is not None and self._proc.poll() is None

    def check(self) -> None:
        """Sets ``error`` when the child exited without being asked to; moves waiting
        updates into the ring (executor thread, every 20 ms)."""
        self.flush_updates()
        proc = self._proc
        if proc is None or self._stopping or proc.poll() is None or self.error is not None:
            return
        self._poll_status()             # its last status: did it finish its run?
        if not self.finished:
            why = self.status.get('error') or 'device output lost'
            self.error = DeviceError(f'loop process {proc.pid} exited with code '
                                     f'{proc.returncode}: {why}')

    def wait_started(self, timeout: float = START_TIMEOUT) -> None:
        """Block until the child has configured and activated the device (its first status);
        raise :class:`~haptic_topology.errors.DeviceError` with the backend's own reason when
        it could not (its final status's ``error``), and when it ended without one or has
        not reported within ``timeout`` s (the caller stops it). The driver's activation
        waits here, so a device that cannot be opened fails the lifecycle transition."""
        proc, deadline = self._proc, time.monotonic() + timeout
        assert proc is not None, 'LoopProcess.wait_started: not started'
        while True:
            ended = proc.poll() is not None     # then its last status is in the ring
            self._poll_status()
            if self.status.get('error'):
                raise DeviceError(str(self.status['error']))
            if self.status.get('generation') == self.generation:
                return                  # in its loop (or stopped before it began)
            if ended or time.monotonic() > deadline:
                raise DeviceError(f'loop process {proc.pid} ' + (
                    f'exited with code {proc.returncode} before it opened the device' if ended
                    else f'had not opened the device {timeout:g} s after its start'))
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(0.01)

    # -- requests --------------------------------------------------------------------------------
    def _ring(self, name: str) -> Any:
        return self._mem.rings[name] if self._mem else None

    def _request(self, item: tuple[Any, ...]) -> bool:
        """Put a request for the current child; False when the control ring is full."""
        ring = self._ring('control')
        if ring is None:
            return False
        if not put_bytes(ring, pickle.dumps((self.generation, *item)), 'control request',
                         overwrite=False):
            return False
        self._wake_child()
        return True

    def _wake_child(self) -> None:
        if self._fds is not None:
            os.eventfd_write(self._fds[1], 1)

    @property
    def may_engage(self) -> bool:
        return self._may_engage

    @may_engage.setter
    def may_engage(self, value: bool) -> None:
        if bool(value) != self._may_engage:
            self._may_engage = bool(value)
            if not self._request(('engage', self._may_engage)):
                raise DeviceError('loop process: control ring full (the child does not read '
                                  'it)')

    def offer_update(self, snap: LmiSnapshot) -> None:
        """Hand an LMI update to the child, with the matrices its re-sync takes computed here
        (:meth:`~haptic_topology.control.controller.HapticController.prepare`, by the node's
        copy of the controller, which is never stepped): the child only adopts them. While
        the ring is full (the child starting up, or not stepping) updates wait here, at most
        :data:`~haptic_topology.device.hosted.MAX_PENDING` (then the oldest is dropped and
        counted in ``updates_dropped``). An update too large for a record is refused and
        counted (``updates_refused``). Call from one thread (the executor's), as
        :meth:`flush_updates`."""
        data = encode_update(self._spec['controller'].ctrl.prepare(snap))
        if len(data) > self._update_bytes:
            self.updates_refused += 1
            self.notices.append(f'LMI update {snap.seq}: {len(data)} bytes, more than a '
                                f'record holds ({self._update_bytes}): refused')
            return
        if len(self._pending) == self._pending.maxlen:
            self.updates_dropped += 1
        self._pending.append(data)
        self.flush_updates()

    def flush_updates(self) -> None:
        """Move waiting updates into the ring as room allows (the node's check timer calls
        this too, so the last update of a burst is not left waiting)."""
        ring = self._ring('updates')
        if ring is None:
            return
        moved = False
        while self._pending and put_bytes(ring, self._pending[0], 'LMI update',
                                          overwrite=False):
            self._pending.popleft()
            moved = True
        if moved:
            self._wake_child()

    def change_law(self, gains: ControlGains, mode: ControlMode) -> None:
        """A live change of gains and mode, applied between two cycles."""
        if not self._request(('law', gains, mode)):
            raise DeviceError('loop process: control ring full (the child does not read it)')

    # -- what the child produced ---------------------------------------------------------------
    def wait(self, timeout: float) -> None:
        """Block until the child signals a record (lock-step) or ``timeout`` s."""
        if self._fds is None:
            time.sleep(timeout)
            return
        wait_eventfd(self._fds[0], timeout)

    def drain(self) -> list[Published]:
        """The cycles the child has produced since the last call, oldest first."""
        return [self.codec.decode(r) for r in self.drain_records()]

    def drain_records(self) -> np.ndarray:
        """:meth:`drain` as the records of ``codec`` (not decoded)."""
        ring = self._ring('cycles')
        if ring is None:
            return np.empty(0, self.codec.dtype)
        recs = ring.take()
        self.taken += len(recs)
        self._poll_status()
        return recs

    def _poll_status(self) -> None:
        with self._status_lock:
            ring = self._ring('status')
            if ring is None:
                return
            for data in payloads(ring):
                status = json.loads(data)
                self.notices.extend(status.pop('notices', []))
                carry = status.pop('carry', None)
                if status.get('generation') != self.generation:
                    continue            # an earlier child's last words: not this one's
                if status.get('final'):
                    self._carry = None if carry is None else base64.b64decode(carry)
                self.status = status

    @property
    def outbox_pending(self) -> int:
        """Cycle records not taken yet."""
        ring = self._ring('cycles')
        return 0 if ring is None else ring.pending

    @property
    def appended(self) -> int:
        ring = self._ring('cycles')
        return self.taken if ring is None else ring.written

    @property
    def outbox_dropped(self) -> int:
        ring = self._ring('cycles')
        return 0 if ring is None else ring.lost

    @property
    def finished(self) -> bool:
        return bool(self.status.get('finished'))

    @property
    def lockstep_timeouts(self) -> int:
        return int(self.status.get('lockstep_timeouts', 0))

    # -- figures ---------------------------------------------------------------------------------
    def _sorted(self) -> dict[str, str]:
        """The figures' thread: period, wake-up lateness and round-trip percentiles (ms) of
        the child's shared statistics (the child reports them as NaN: sorting is this
        process's job)."""
        out: dict[str, str] = {}
        mem = self._mem
        if mem is None:
            return out
        for name, n_key, keys in (
                ('periods', 'n_periods', ('period', 'loop_period')),
                ('lateness', 'n_periods', ('wake_late', 'loop_wake_late')),
                ('round_trips', 'n_round_trips', ('round_trip',))):
            arr = mem.arrays[name].array
            n = min(int(self.status.get(n_key, 0)), arr.size)
            if n == 0:
                continue
            p50, p99 = (1e3 * float(v) for v in np.percentile(arr[:n], [50, 99]))
            for key in keys:
                out[f'{key}_p50_ms'], out[f'{key}_p99_ms'] = f'{p50:.3f}', f'{p99:.3f}'
        return out

    def _with_figures(self, values: dict[str, str]) -> dict[str, str]:
        """``values`` with the percentiles (where it has those keys: the newest the figures'
        thread has while a child runs; once it has ended, its final ones, sorted here once)
        and the rings' losses of both sides."""
        out = dict(values)
        if self.running:
            figures = self._figures.read()
        else:
            if self._final is None or self._final[0] is not self.status:
                self._final = (self.status, self._sorted())
            figures = self._final[1]
        for key, v in figures.items():
            if key in out:
                out[key] = v
        if self._mem is not None:
            out.update(add_counts(self._mem.counts(), self.status.get('rings', {})))
        return out

    def device_values(self) -> dict[str, str]:
        out = self._with_figures(self.status.get('device', {}))
        out.update({'loop_process_pid': str(self.pid or 0),
                    'loop_records_lost': str(self.outbox_dropped),
                    'updates_waiting': str(len(self._pending)),
                    'updates_refused': str(self.updates_refused),
                    'updates_dropped': str(int(out.get('updates_dropped', 0))
                                           + self.updates_dropped)})
        return out

    def device_report(self, fault: str, rejected: int) -> tuple[int, str, dict[str, str]]:
        """The device's diagnostics as the child last reported them (see
        :func:`~haptic_topology.device.loop.device_report`), with the node's ``fault`` and
        its ``rejected`` messages."""
        level, message, values = self.status.get('report', (1, 'loop process starting', {}))
        values = self._with_figures(values)
        values['rejected_commands'] = str(int(values.get('rejected_commands', 0)) + rejected)
        if fault:
            level, message = 2, f'fault: {fault}'
        return int(level), str(message), values

    def controller_values(self) -> dict[str, str]:
        """The controller loop's diagnostics values as the child last reported them."""
        return dict(self.status.get('controller', {}))

    def controller_health(self) -> tuple[int, str] | None:
        h = self.status.get('health')
        return None if h is None else (int(h[0]), str(h[1]))
