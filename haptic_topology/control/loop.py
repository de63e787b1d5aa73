"""Controller side of the haptic loop: LMI + control law + sync guard + session tracking.

One :class:`ControllerLoop` answers every device state with a command (eq. 14 or eq. 10 on
the LMI, eqs. 17-20) and takes every LMI update of the full simulation. The offline
simulation, the lock-step graph and the real-time graph drive the same object
(``lmi_controller`` only converts messages); it reads no clock: its time is *loop time*, the
device states' stamps (s), so its answers are a function of its inputs and a bag replayed in
lock-step reproduces them.

* :meth:`ControllerLoop.on_state`: a state flagged IDLE (device not engaged) is answered with
  zero wrench in the controller's mode once synced (which engages the device) and integrates
  nothing; a running state advances the LMI by the measured period (stamp difference, clipped
  to ``max_dt``), computes the law, scales it by the sync guard's force scale and returns the
  command plus the hand input for the VE (``F_vt`` of the LMI, pose, twist, F_h, F_pc).
* :meth:`ControllerLoop.on_update`: re-sync to the VE (the LMI replays the inputs the VE has
  not consumed yet), unless the update would step the force by more than ``max_jump`` (the
  VE lost inputs, or caught up on a backlog) or comes from a restarted VE: then it is held
  until the guard has faded the force out (:mod:`haptic_topology.control.safety`).

Sessions: a restarted ``device_driver`` (its seq goes backwards) continues the loop seq
(device seq + offset) so the LMI's and the VE's input numbering never goes backwards, and the
force fades in; joining a loop that already runs (no idle state seen, states already faded by
the device's watchdog) fades in too; a restarted ``ve_sim`` (update seq backwards) places its
VT at the hand and is synced at zero force once it has consumed one of our inputs. An update
that consumed no input (``hand_input_seq < 0``) from the VE we already send inputs to
describes its initial state: it is ignored.

Lock-step (``ControllerLoop.update_period`` set): the VE sends an update after every
``update_period``-th input; ``waiting_for_update`` says when the next state must not be
answered before that update has been taken, which is what makes the graph reproduce the
offline simulation exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from haptic_topology.control.controller import CycleOutput, HapticController, PreparedUpdate
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.safety import SyncGuard, scaled_wrench
from haptic_topology.vocabulary import ControlMode, DeviceStatus

#: Status bits as plain ints (an ``IntFlag`` operation costs microseconds, once per state).
_IDLE_BIT = int(DeviceStatus.IDLE)

#: Loop states whose VT hand is kept for comparing updates (> the LMI's input history).
_VT_KEEP = 512


class StateSample(NamedTuple):
    """One device state as the controller sees it: ``seq`` (device's, from 1), ``stamp`` (s,
    loop time), pose, twist and hand wrench F_h (task vectors), status bits."""

    seq: int
    stamp: float
    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    status: int = 0


class HandSample(NamedTuple):
    """The hand input for the VE: ``seq`` (from 1, per controller), ``state_seq`` (the loop
    seq it belongs to), ``stamp`` (s, the state's), pose, twist, F_h, F_pc, ``F_vt``."""

    seq: int
    state_seq: int
    stamp: float
    pose: np.ndarray
    twist: np.ndarray
    hand_wrench: np.ndarray
    coupling: np.ndarray
    vt_wrench: np.ndarray


class Answer(NamedTuple):
    """The command for device state ``state_seq`` and, while running, the hand input;
    ``update_seq``: the seq of the newest LMI update taken before it (-1: none), which with
    the states makes the answer reproducible (``DeviceCommand.update_seq``)."""

    state_seq: int
    out: CycleOutput
    hand: HandSample | None
    update_seq: int = -1


class UpdateVerdict:
    """What :meth:`ControllerLoop.on_update` did with an update."""

    APPLIED = 'applied'
    HELD = 'held'                # applied once the force has faded out
    IGNORED = 'ignored'          # consumed no input of ours (initial state, restarted VE)


class ControllerLoop:
    """The controller's loop policy (see module doc); ``dt`` is the nominal device period (s),
    used for the first state and for the VE's lag; ``update_period``: lock-step only."""

    def __init__(self, controller: HapticController, guard: SyncGuard, dt: float,
                 max_dt: float, max_jump: float, limit: np.ndarray,
                 update_period: int | None = None) -> None:
        self.ctrl = controller
        self.guard = guard
        self.dt = dt
        self.max_dt = max_dt
        self.max_jump = max_jump
        self.limit = np.asarray(limit, dtype=float)
        controller.energy.set_limit(self.limit)
        self.update_period = update_period
        m = controller.task.dim
        self._vt_seq = np.zeros(_VT_KEEP, dtype=np.int64)
        self._vt = np.zeros((_VT_KEEP, 2, m))
        self.loop_time = 0.0            # newest state's stamp (s): the guard's clock
        self._seen_state = False
        self.last_seq = 0               # newest loop seq answered while running
        self._last_stamp: float | None = None
        self.device_seq = 0
        self._seq_offset = 0
        self._running = False           # a running state of this device session was seen
        self._saw_idle = False
        self.device_sessions = 1
        self.hand_seq = 0
        self._prev_input_seq: int | None = None
        self._await_consumed: int | None = None
        self._ve_seq: int | None = None
        self._ve_new_session = False
        self._ve_consumed = -1
        self._pending: LmiSnapshot | PreparedUpdate | None = None
        self.notices: list[str] = []    # events for the node's log, drained by it
        self.ve_restarts = 0
        self.updates = 0
        self.updates_ignored = 0
        self.skipped = 0
        self.resync_jump_max = 0.0
        self.dt_capped = 0              # cycles whose period exceeded the stable LMI step
        self.jumps_held = 0

    # -- device states -----------------------------------------------------------------------
    def on_state(self, s: StateSample) -> Answer | None:
        """The answer to state ``s`` (None: an old state, nothing to answer)."""
        now = self.loop_time = max(self.loop_time, s.stamp)
        self._seen_state = True
        if s.seq < self.device_seq:
            self._new_device_session(s.seq)
        self.device_seq = s.seq
        if s.status & _IDLE_BIT:
            # Not engaged (start-up, or a restarted driver): answer "alive" (zero wrench; our
            # mode once synced, which engages it) and integrate nothing.
            self._saw_idle = True
            self.ctrl.energy.break_period()
            mode = self.ctrl.mode if self.ctrl.lmi.synced else ControlMode.ZERO
            zero = np.zeros(self.ctrl.task.dim)
            return Answer(s.seq, CycleOutput(zero, zero, zero, s.pose, s.twist, 0, mode), None,
                          self._taken())
        loop_seq = s.seq + self._seq_offset
        if loop_seq <= self.last_seq:
            return None
        if not self._running:
            self._running = True
            stale = bool(s.status & DeviceStatus.WATCHDOG)
            if self.device_sessions > 1 or (stale and not self._saw_idle):
                # Joined a loop that already runs: start from zero force and fade in. A state
                # stream that begins with a plain running state (a bag replayed from
                # engagement on) is not a rejoin.
                self.guard.rejoin()
                self.notices.append(f'joined a running loop at device state {s.seq}: the '
                                    'force fades in')
        if self._last_stamp is not None:
            self.skipped += loop_seq - self.last_seq - 1
            dt = s.stamp - self._last_stamp
        else:
            dt = self.dt
        dt = max(dt, 0.0)
        if dt > self.ctrl.stable_dt:
            self.dt_capped += 1
        dt = min(dt, self.max_dt, self.ctrl.stable_dt)
        self.last_seq, self._last_stamp = loop_seq, s.stamp
        scale = 1.0
        if self.ctrl.lmi.synced:
            scale, apply = self.guard.cycle(now)
            if apply and self._pending is not None:
                self.ctrl.update(self._pending)
                self._pending = None
        out = self.ctrl.cycle(loop_seq, dt, s.pose, s.twist, s.hand_wrench)
        slot = loop_seq % _VT_KEEP
        self._vt_seq[slot] = loop_seq
        self._vt[slot, 0] = out.vt_pose
        self._vt[slot, 1] = out.vt_twist
        if scale < 1.0:
            out = out._replace(wrench=scaled_wrench(out.wrench, scale, self.limit))
            self.ctrl.energy.scaled(scale, out.wrench)
        self.ctrl.energy.note(now)
        hand = None
        if out.mode is not ControlMode.ZERO:
            hand = self._hand_input(loop_seq, s, out, scale)
        return Answer(s.seq, out, hand, self._taken())

    def _taken(self) -> int:
        """The seq of the newest update taken (-1: none)."""
        return -1 if self._ve_seq is None else self._ve_seq

    def _hand_input(self, loop_seq: int, s: StateSample, out: CycleOutput,
                    scale: float) -> HandSample:
        """The VE's input for this cycle. While the guard fades the device's force (stale or
        re-syncing model), the coupling F_pc the VE feels fades with the same ``scale``: the
        spring acts on both ends alike, and a local model that drifted while stale must not
        push the full VE through it."""
        self.hand_seq += 1
        if (self.update_period is not None and self.hand_seq % self.update_period == 0
                and self._prev_input_seq is not None):
            # The VE answers this input with an update that has consumed the previous one.
            self._await_consumed = self._prev_input_seq
        self._prev_input_seq = loop_seq
        coupling, vt_wrench = out.coupling, out.vt_wrench
        if scale < 1.0:
            coupling = scale * out.coupling
            vt_wrench = s.hand_wrench - coupling if self.ctrl.vt_coupling else out.vt_wrench
        return HandSample(self.hand_seq, loop_seq, s.stamp, s.pose, s.twist, s.hand_wrench,
                          coupling, vt_wrench)

    def waiting_for_update(self) -> bool:
        """Lock-step: True while the update the offline simulation applies before the next
        state has not been taken yet."""
        return self._await_consumed is not None and self._ve_consumed < self._await_consumed

    def _new_device_session(self, seq: int) -> None:
        """The device's seq went backwards: a restarted device_driver."""
        self.device_sessions += 1
        self._seq_offset = self.last_seq
        self._last_stamp = None
        self._running = False
        self._saw_idle = False
        self.notices.append(f'device restarted (state {seq} after {self.device_seq}); the '
                            f'loop seq continues after {self.last_seq}')

    # -- LMI updates -------------------------------------------------------------------------
    def on_update(self, update: LmiSnapshot | PreparedUpdate) -> str:
        """Take an LMI update, or its prepared form
        (:meth:`~haptic_topology.control.controller.HapticController.prepare`), arriving at
        the current loop time; returns an :class:`UpdateVerdict` value."""
        snap = update.snapshot if isinstance(update, PreparedUpdate) else update
        now = self.loop_time
        if self._ve_seq is not None and snap.seq < self._ve_seq:
            self.ve_restarts += 1
            self._ve_new_session = True
            self._ve_consumed = -1
            self.notices.append(f've_sim restarted (update {snap.seq}); re-sync at zero '
                                'force once it has taken our hand input')
        self._ve_seq = snap.seq
        self.updates += 1
        if not self._seen_state:
            # No device state yet, so no loop time: sync (start-up); the guard starts counting
            # with the first update after the loop's first state.
            self.ctrl.update(update)
            return UpdateVerdict.APPLIED
        if snap.hand_input_seq < 0 and (self._ve_new_session or self.hand_seq > 0):
            # Consumed none of our inputs: a restarted VE that has not placed its VT at the
            # hand yet, or the initial state of the VE we already feed (a late keep-alive).
            self.updates_ignored += 1
            return UpdateVerdict.IGNORED
        self._ve_consumed = max(self._ve_consumed, snap.hand_input_seq)
        restart = self._ve_new_session
        self._ve_new_session = False
        # How far the VE lags behind the loop: its update describes the VT after consuming
        # input hand_input_seq, i.e. at loop state hand_input_seq + 1.
        lag = (max(self.last_seq - snap.hand_input_seq - 1, 0) * self.dt
               if snap.hand_input_seq >= 0 and not restart else 0.0)
        if not restart and self.ctrl.lmi.synced and snap.hand_input_seq >= 0:
            jump = self.resync_jump(snap)
            self.resync_jump_max = max(self.resync_jump_max, min(jump, 1e9))
            if jump > self.max_jump:
                # Syncing now would step the force: hold it until the force has faded.
                restart = True
                self.jumps_held += 1
        if self.guard.update_arrived(now, restart, lag):
            self.ctrl.update(update)
            self._pending = None
            return UpdateVerdict.APPLIED
        self._pending = update
        return UpdateVerdict.HELD

    def resync_jump(self, snap: LmiSnapshot) -> float:
        """Estimated force step (N or N m, largest axis) of syncing to ``snap`` now: the
        update's VT hand against ours at the same time (our first cycle after its
        ``hand_input_seq``); inf when ours is no longer known."""
        for seq in range(snap.hand_input_seq + 1, min(snap.hand_input_seq + 64,
                                                      self.last_seq + 1)):
            slot = seq % _VT_KEEP
            if self._vt_seq[slot] == seq:
                break
        else:
            return math.inf
        return self.ctrl.force_step(snap.hand_pose, snap.hand_twist, self._vt[slot, 0],
                                    self._vt[slot, 1])

    # -- diagnostics -------------------------------------------------------------------------
    def values(self, now: float) -> dict[str, str]:
        """Loop state as diagnostics key/values at loop time ``now`` (s)."""
        return {
            'mode': self.ctrl.mode.label,
            'k_tc': repr(self.ctrl.gains.k_tc),
            'b_tc': repr(self.ctrl.gains.b_tc),
            'last_state_seq': str(self.device_seq),
            'loop_seq': str(self.last_seq),
            'skipped_states': str(self.skipped),
            'dt_capped': str(self.dt_capped),
            'lmi_updates': str(self.updates),
            'lmi_updates_ignored': str(self.updates_ignored),
            'model_age_ms': f'{1e3 * self.guard.age(now):.2f}',
            'model': self.guard.health(now).value,
            'force_scale': f'{self.guard.scale:.3f}',
            'degradations': str(self.guard.degradations),
            'resyncs_held': str(self.guard.resyncs_held),
            'resync_jumps_held': str(self.jumps_held),
            'resync_jump_max': f'{self.resync_jump_max:.4g}',
            've_restarts': str(self.ve_restarts),
            'device_sessions': str(self.device_sessions),
            **self.ctrl.energy.values(),
        }
