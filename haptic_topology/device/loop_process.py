"""The hosted 1 kHz loop in a process of its own: no GIL shared with ROS on the deadline path.

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
  its re-sync takes, computed by the node; applied at the start of the next cycle as
  in-process) and control requests (engagement permission, live law and gains, stop);
* child -> node, a status record every :data:`STATUS_PERIOD` s: the loop's, the device's and
  the controller's diagnostics values, and notices for the node's log. The last one, written
  after the device is released, carries what the backend hands over to the next activation's
  child (:meth:`~haptic_topology.device.backend.DeviceBackend.carry_over`: the simulated
  maglev's state, so that it resumes where it stopped, as an in-process backend does).

In lock-step each side wakes the other with an ``eventfd`` after writing (the child after a
cycle's record, the node after an update); with the wall clock the node takes the records
every few milliseconds and the child never makes a system call for it, and the child sleeps
towards its next deadline on the node's ``eventfd``: an update that comes while it sleeps is
decoded and applied then, off the deadline path (the loop's state does not change between
two cycles, so this is what applying it at the start of the next cycle would do), unless
less than ``loop_child.APPLY_BEFORE`` (0.3 ms) is left: then it waits for the gap after
the next cycle, which runs on the model it has.

Lifetimes: the node creates (and unlinks) the rings. The child stops at a stop request, or
when its parent dies (``PR_SET_PDEATHSIG`` delivers SIGTERM, and the parent pid is checked
every cycle), in both cases after writing zero wrench and releasing the device
(:func:`~haptic_topology.device.backend.zero_and_release`). The node sees the child exit at
its next check (every 20 ms) and reports it as the device's fault. The child unregisters the
rings from its resource tracker (:meth:`~haptic_topology.device.shm_ring.ShmRing.attach`),
so only the owner unlinks them: its :meth:`LoopProcess.close`, or its tracker when it dies.

In the child, after start-up, :func:`gc.freeze` moves every object built so far out of the
collector's view and automatic collection is off; a young-generation collection runs every
:data:`GC_EVERY` cycles right after a cycle, when the loop waits for its next deadline.
"""

from __future__ import annotations

import base64
import json
import os
import pickle
import select
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
from haptic_topology.device.loop import RTT_KEEP
from haptic_topology.device.pacing import PERIOD_WINDOW
from haptic_topology.device.records import (
    CycleCodec,
    bytes_dtype,
    payloads,
    put_bytes,
    update_bytes,
)
from haptic_topology.device.runner import Published, RunnerConfig
from haptic_topology.device.shm_ring import SharedArray, ShmRing
from haptic_topology.device.watchdog import WatchdogConfig
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import ControlMode

#: The module the loop process runs (``python -m``).
CHILD_MODULE = 'haptic_topology.device.loop_child'
#: Cycle records the ring keeps (4 s at 1 kHz), as the in-process outbox.
CYCLE_RECORDS = 4096
#: Seconds between two status records of the child.
STATUS_PERIOD = 0.2
#: Bytes of one status record (JSON) and of one control record (pickle).
STATUS_BYTES = 1 << 16
CONTROL_BYTES = 1 << 12
#: LMI update records the ring keeps (0.3 s at 100 Hz).
UPDATE_RECORDS = 32
#: Cycles between two young-generation collections in the child.
GC_EVERY = 1000
#: How long the node waits for the child to stop after a stop request (s); longer by
#: START_TIMEOUT while it has not reported from its loop (importing, opening the device).
STOP_TIMEOUT = 3.0
START_TIMEOUT = 30.0

def wait_eventfd(fd: int, timeout: float) -> bool:
    """Block until the eventfd ``fd`` (non-blocking) is signalled or ``timeout`` s have
    passed; reset it. Returns whether it was signalled."""
    ready, _, _ = select.select([fd], [], [], timeout)
    if not ready:
        return False
    try:
        os.eventfd_read(fd)
    except BlockingIOError:         # reset meanwhile: signalled all the same
        pass
    return True


@dataclass(frozen=True)
class LoopSpec:
    """What the child builds its loop from (pickled to its stdin): the backend (name and
    configuration: the child opens the device), the device loop's limits, watchdog, period
    and takeover time, the controller loop (built by the hosted ``lmi_controller``, never
    stepped in the node), the runner's pacing, real-time options, ring names and wake-up
    descriptors, and the parent's pid."""

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
    rings: dict[str, str]
    update_bytes: int
    wake_node: int            # eventfd the child writes (lock-step: after each record)
    wake_child: int           # eventfd the node writes (after an update or a request)
    parent: int
    generation: int           # the child's number: requests for an earlier one are ignored
    periods: str              # shared arrays the child's statistics live in (the node sorts
    round_trips: str          # them for the percentiles, never the loop)
    lateness: str
    #: What the previous child's backend carried over
    #: (:meth:`~haptic_topology.device.backend.DeviceBackend.carry_over`): resumed after
    #: ``configure``. None: the first activation, or a backend that carries nothing.
    carry: bytes | None = None


class LoopProcess:
    """The node's handle of the child (see module doc; a deactivation stops the child, an
    activation starts a new one on the same rings), with the interface the node's
    publishing thread and checks use of an in-process
    :class:`~haptic_topology.device.runner.LoopRunner`: :meth:`start`,
    :meth:`stop`, :meth:`drain`, ``may_engage``, ``finished``, ``error``,
    ``device_values``, ``notices``; and :meth:`offer_update`, :meth:`change_law`
    for the hosted controller."""

    def __init__(self, spec: dict[str, Any], task_dim: int, dof: int) -> None:
        self._spec = spec          # LoopSpec fields but the rings, fds and parent
        self.codec = CycleCodec(task_dim)
        self._update_bytes = update_bytes(dof)
        self.lockstep = bool(spec['runner'].lockstep)
        self.notices: deque[str] = deque(maxlen=100)
        self.status: dict[str, Any] = {}
        self._proc: subprocess.Popen[bytes] | None = None
        self._rings: dict[str, ShmRing] = {}
        self._arrays: dict[str, SharedArray] = {}
        self._fds: tuple[int, int] | None = None
        self._may_engage = False
        self._stopping = False
        self.error: BaseException | None = None
        self.taken = 0              # cycle records taken
        self.generation = 0         # children started (requests carry it)
        self._pending: deque[bytes] = deque(maxlen=MAX_PENDING)    # update records
        self.updates_dropped = 0
        self._status_lock = threading.Lock()    # the status ring's one consumer at a time
        #: The newest child's hand-over (its final status), for the next child.
        self._carry: bytes | None = None

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self, name: str = 'device_loop', on_start: Any = None) -> None:
        """Create the rings and start the child (``on_start`` is not used: the child applies
        the real-time options itself)."""
        if self.running:
            raise RuntimeError('LoopProcess.start: already running')
        self.error = None
        self._stopping = False
        self.generation += 1
        if not self._rings:     # kept over a deactivation: the node's thread may drain them
            self._rings = {
                'cycles': ShmRing.create(self.codec.dtype, CYCLE_RECORDS),
                'updates': ShmRing.create(bytes_dtype(self._update_bytes), UPDATE_RECORDS),
                'control': ShmRing.create(bytes_dtype(CONTROL_BYTES), 64),
                'status': ShmRing.create(bytes_dtype(STATUS_BYTES), 4),
            }
            self._fds = (os.eventfd(0, os.EFD_NONBLOCK), os.eventfd(0, os.EFD_NONBLOCK))
            self._arrays = {'periods': SharedArray.create(PERIOD_WINDOW),
                            'round_trips': SharedArray.create(RTT_KEEP),
                            'lateness': SharedArray.create(PERIOD_WINDOW)}
        assert self._fds is not None
        if self.generation > 1 and self.status.get('final') is not True:
            self._carry = None      # not an older child's: that state is not the device's now
            self.notices.append('the previous loop process ended without handing its device '
                                'state over: the device starts as configured (a simulated '
                                'one at its initial pose)')
        spec = LoopSpec(**self._spec, carry=self._carry,
                        rings={k: r.name for k, r in self._rings.items()},
                        update_bytes=self._update_bytes, wake_node=self._fds[0],
                        wake_child=self._fds[1], parent=os.getpid(),
                        generation=self.generation, periods=self._arrays['periods'].name,
                        round_trips=self._arrays['round_trips'].name,
                        lateness=self._arrays['lateness'].name)
        # This node's session (as haptic-topology run starts every node), a process group of
        # its own: under the kernel's autogroup the scheduler weighs the loop thread against
        # the nodes' threads directly, by nice, SCHED_BATCH and its slice (docs/nodes.md).
        self._proc = subprocess.Popen(
            [sys.executable, '-m', CHILD_MODULE],
            stdin=subprocess.PIPE, pass_fds=self._fds, close_fds=True, process_group=0)
        assert self._proc.stdin is not None
        self._proc.stdin.write(pickle.dumps(spec))
        self._proc.stdin.close()
        self._request(('engage', self._may_engage))

    def stop(self, timeout: float = STOP_TIMEOUT) -> None:
        """Ask the child to stop (zero wrench, device released); wait (:data:`STOP_TIMEOUT`)."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        self._stopping = True
        self._request(('stop',))
        self._poll_status()
        if self.status.get('generation') != self.generation:      # not in its loop yet
            timeout += START_TIMEOUT
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise RuntimeError(f'loop process did not stop within {timeout} s: killed') from None
        finally:
            self._poll_status()

    def close(self) -> None:
        """Unlink the rings and close the descriptors (after :meth:`stop`, or at shutdown)."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        for ring in self._rings.values():
            ring.close()
        self._rings = {}
        for arr in self._arrays.values():
            arr.close()
        self._arrays = {}
        if self._fds is not None:
            for fd in self._fds:
                os.close(fd)
            self._fds = None

    def ring_names(self) -> list[str]:
        """The shared-memory segments of the rings (``/dev/shm/<name>``)."""
        return [r.name for r in self._rings.values()] + [a.name for a in self._arrays.values()]

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
            self.error = DeviceError(f'loop process {proc.pid} exited with code '
                                     f'{proc.returncode}: device output lost')

    # -- requests --------------------------------------------------------------------------------
    def _request(self, item: tuple[Any, ...]) -> None:
        ring = self._rings.get('control')
        if ring is None:
            return
        if not put_bytes(ring, pickle.dumps((self.generation, *item)), 'control request',
                         overwrite=False):
            raise DeviceError('loop process: control ring full (the child does not read it)')
        self._wake_child()

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
            self._request(('engage', self._may_engage))

    def offer_update(self, snap: LmiSnapshot) -> None:
        """Hand an LMI update to the child (applied at the start of its next cycle, after
        every update offered before it), with the matrices its re-sync takes computed here
        (:meth:`~haptic_topology.control.controller.HapticController.prepare`, by the node's
        copy of the controller, which is never stepped): the child only adopts them. While
        the ring is full (the child starting up, or not stepping) updates wait here, at most
        :data:`~haptic_topology.device.hosted.MAX_PENDING` (then the oldest is dropped and
        counted, as in-process). Call from one
        thread (the executor's), as :meth:`flush_updates`."""
        if len(self._pending) == self._pending.maxlen:
            self.updates_dropped += 1
        prepared = self._spec['controller'].ctrl.prepare(snap)
        self._pending.append(encode_update(prepared))
        self.flush_updates()

    def flush_updates(self) -> None:
        """Move waiting updates into the ring as room allows (the node's check timer calls
        this too, so the last update of a burst is not left waiting)."""
        ring = self._rings.get('updates')
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
        self._request(('law', gains, mode))

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
        ring = self._rings.get('cycles')
        if ring is None:
            return np.empty(0, self.codec.dtype)
        recs = ring.take()
        self.taken += len(recs)
        self._poll_status()
        return recs

    def _poll_status(self) -> None:
        with self._status_lock:
            ring = self._rings.get('status')
            if ring is None:
                return
            for data in payloads(ring):
                status = json.loads(data)
                self.notices.extend(status.pop('notices', []))
                carry = status.pop('carry', None)
                if status.get('final') and status.get('generation') == self.generation:
                    self._carry = None if carry is None else base64.b64decode(carry)
                self.status = status

    @property
    def outbox(self) -> int:
        """Cycle records not taken yet."""
        ring = self._rings.get('cycles')
        return 0 if ring is None else ring.pending

    @property
    def appended(self) -> int:
        ring = self._rings.get('cycles')
        return self.taken if ring is None else ring.written

    @property
    def outbox_dropped(self) -> int:
        ring = self._rings.get('cycles')
        return 0 if ring is None else ring.lost

    @property
    def finished(self) -> bool:
        return bool(self.status.get('finished'))

    @property
    def lockstep_timeouts(self) -> int:
        return int(self.status.get('lockstep_timeouts', 0))

    def _percentiles(self, values: dict[str, str]) -> dict[str, str]:
        """``values`` with the period, wake-up lateness and round-trip percentiles (ms) of the
        child's shared statistics (the child reports them as NaN: sorting is this process's
        job)."""
        out = dict(values)
        for name, n_key, keys in (
                ('periods', 'n_periods', ('period', 'loop_period')),
                ('lateness', 'n_periods', ('wake_late', 'loop_wake_late')),
                ('round_trips', 'n_round_trips', ('round_trip',))):
            arr = self._arrays.get(name)
            n = min(int(self.status.get(n_key, 0)), 0 if arr is None else arr.array.size)
            if arr is None or n == 0:
                continue
            p50, p99 = (1e3 * float(v) for v in np.percentile(arr.array[:n], [50, 99]))
            for key in keys:
                if f'{key}_p50_ms' in out:
                    out[f'{key}_p50_ms'], out[f'{key}_p99_ms'] = f'{p50:.3f}', f'{p99:.3f}'
        return out

    def device_values(self) -> dict[str, str]:
        out = self._percentiles(self.status.get('device', {}))
        out.update({'loop_process_pid': str(self.pid or 0),
                    'loop_records_lost': str(self.outbox_dropped),
                    'updates_waiting': str(len(self._pending)),
                    'updates_dropped': str(int(out.get('updates_dropped', 0))
                                           + self.updates_dropped)})
        return out

    def device_report(self, fault: str, rejected: int) -> tuple[int, str, dict[str, str]]:
        """The device's diagnostics as the child last reported them (see
        :func:`~haptic_topology.device.loop.device_report`), with the node's ``fault`` and
        its ``rejected`` messages."""
        level, message, values = self.status.get('report', (1, 'loop process starting', {}))
        values = self._percentiles(values)
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
