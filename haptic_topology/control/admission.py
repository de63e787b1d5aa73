"""What a node takes of its own graph's messages: from its own publisher, in sequence, and
consistent with what it knows (the graph-identity issue's points 2-4; see ``docs/safety.md``).

``graph_id`` keeps another graph's messages out (``haptic_topology.messages.check.
GraphFilter``). A message that carries this graph's id may still be false: a replay of an old
bag, a second process that copies the id (it is no secret), a program gone wrong. The checks
here refuse what the receiver can prove wrong, each with a
:class:`~haptic_topology.errors.MessageError` whose ``reason`` the node counts in
``/diagnostics`` (``rejected_<reason>``):

* ``source``: the own publisher of the topic is gone and a foreign one publishes there
  (``SourceGate.refuse``): nothing is applied; the controller's staleness guard then
  fades the force to zero;
* ``session``: the sequence restarts (a message numbered below its predecessor) without a new
  endpoint of the own publisher (``SourceGate.new_session``): a message that only *says*
  its sender restarted is refused;
* ``model`` (:class:`UpdateAdmission`): an ``LmiUpdate`` whose hand pose, mass matrix
  ``D(q)``, gravity ``G(q)``, hand Jacobian ``J_h(q)`` or hand twist ``J_h dq`` disagree with
  the controller's own model of the linkage at the update's ``q`` (eqs. 1, 3, 18);
* ``continuity``: an ``LmiUpdate`` that consumed an older hand input than its predecessor,
  or none after one that did (a VE never goes back); a ``HandInputs`` batch that directly
  continues its predecessor (the next seq and the next device state) but is stamped earlier or
  puts the device further from the previous sample than the device's twist reaches
  (:class:`HandAdmission`).

Not protected: a sender that copies the graph id *and* publishes updates consistent with the
model and continuous with the own ones. Only authenticated transport (SROS2 over a
security-enabled DDS) keeps such a sender out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.errors import MessageError
from haptic_topology.messages.check import SourceGate, array
from haptic_topology.vocabulary import TaskSpace

#: Relative tolerance of the model check: the VE computes the same quantities with the same
#: code (Pinocchio), so an own update agrees to rounding (measured: exactly).
MODEL_RTOL = 1e-9
#: Slack of the hand-input continuity check on translation rows (m) ...
POSE_SLACK_M = 0.005
#: ... and on rotation rows (rad).
POSE_SLACK_RAD = 0.05


class Update(Protocol):
    """What the checks read of an LMI update (an
    :class:`~haptic_topology.control.lmi.LmiSnapshot`, or :class:`UpdateFields` of a
    recorded message)."""

    @property
    def seq(self) -> int: ...
    @property
    def hand_input_seq(self) -> int: ...
    @property
    def task(self) -> TaskSpace: ...
    @property
    def q(self) -> np.ndarray: ...
    @property
    def dq(self) -> np.ndarray: ...
    @property
    def mass_matrix(self) -> np.ndarray: ...
    @property
    def gravity(self) -> np.ndarray: ...
    @property
    def hand_jacobian(self) -> np.ndarray: ...
    @property
    def hand_pose(self) -> np.ndarray: ...
    @property
    def hand_twist(self) -> np.ndarray: ...


@dataclass(frozen=True)
class UpdateFields:
    """The fields of an ``LmiUpdate`` message the checks read, as arrays (a bag's
    messages: ``haptic_topology.bag.graph_trace.read_graph_bag`` applies the checks
    too)."""

    seq: int
    hand_input_seq: int
    task: TaskSpace
    q: np.ndarray
    dq: np.ndarray
    mass_matrix: np.ndarray
    gravity: np.ndarray
    hand_jacobian: np.ndarray
    hand_pose: np.ndarray
    hand_twist: np.ndarray

    @classmethod
    def from_msg(cls, msg: Any, task: TaskSpace, dof: int) -> UpdateFields:
        """From a message whose sizes were checked (raises
        :class:`~haptic_topology.errors.MessageError` otherwise)."""
        m = task.dim
        consumed = int(msg.hand_input_seq)        # 0 on the wire: none (-1, as the snapshot)
        return cls(int(msg.seq), consumed if consumed > 0 else -1, task,
                   array(msg, 'q', dof), array(msg, 'dq', dof),
                   array(msg, 'mass_matrix', dof * dof).reshape(dof, dof),
                   array(msg, 'gravity', dof),
                   array(msg, 'hand_jacobian', m * dof).reshape(m, dof),
                   array(msg, 'hand_pose', m), array(msg, 'hand_twist', m))


class UpdateAdmission:
    """The controller's checks of its graph's LMI updates, in the order applied:

    1. source and session (``gate``, None: not checked; the node's publisher watch feeds it);
    2. ``model``: the update's hand pose, ``D``, ``G``, ``J_h``, ``J_h dq`` against
       ``dynamics`` (the controller's linkage) at its ``q``, to :data:`MODEL_RTOL` of each
       quantity's largest entry (at least 1);
    3. ``continuity``: the hand input the update consumed is not older than the previous
       update's. A VE says -1 (none) after it dropped its held input for a new controller:
       then this controller is new too (no previous update), or its loop started over
       (:meth:`forget`: the next update's input is not compared; its numbering still is,
       the VE did not restart). Nor are the updates after it that consumed an input
       numbered beyond the newest this loop has sent (:meth:`sent`): until the VE has the
       new loop's first batch, its updates consume the input it held from the loop before.

    The update's joint motion is not bounded: a VT whirling under the hand (the circle
    scenario under fault injection reached ~80 rad/s, 37.8 rad in 0.54 s between two
    updates) outruns any bound from the joint velocities at the two updates, and a refused
    own update leaves the controller on a stale model. The re-sync's force-jump check
    (``resync_max_jump``) is what limits a jump that does get through.

    A new session (the VE restarted) starts without a previous update.
    """

    def __init__(self, dynamics: LinkageDynamics | None,
                 gate: SourceGate | None = None) -> None:
        self.dyn = dynamics
        self.gate = gate
        self._prev: Update | None = None
        self._forgot = False        # the next update's input is not compared (forget)
        self._sent = 0              # newest hand input sent since forget (sent)

    def admit(self, snap: Update) -> None:
        """Raise :class:`~haptic_topology.errors.MessageError` if ``snap`` may not be
        applied; otherwise it becomes the previous update of the continuity check."""
        prev = self._prev
        gate = self.gate
        restart = False
        if gate is not None:
            refusal = gate.refuse()
            if refusal is not None:
                raise refusal
            if prev is not None and snap.seq < prev.seq:
                if not gate.new_session():
                    raise gate.refuse_restart(snap.seq, prev.seq)
                prev, restart = None, True
        if self.dyn is not None:
            self._check_model(snap)
        if prev is not None and not self._forgot:
            self._check_continuity(prev, snap)
        if gate is not None:            # every check passed: only now is a restart taken
            if restart:
                gate.start_session()
            gate.accepted()
        self._prev = snap
        self._forgot = self._forgot and snap.hand_input_seq > self._sent

    def _check_model(self, snap: Update) -> None:
        dyn = self.dyn
        assert dyn is not None
        q = snap.q
        j6 = dyn.hand_frame_jacobian(q)          # also places the grasp frame
        jac = j6[list(dyn.task_rows), :]
        pose_error = pose_difference(snap.hand_pose, dyn.hand_pose_in_data(), snap.task)
        for name, got, want in (
                ('hand_pose', pose_error, np.zeros_like(pose_error)),
                ('mass_matrix', snap.mass_matrix, dyn.mass_matrix(q)),
                ('gravity', snap.gravity, dyn.gravity(q)),
                ('hand_jacobian', snap.hand_jacobian, jac),
                ('hand_twist', snap.hand_twist, jac @ snap.dq)):
            scale = max(1.0, float(np.max(np.abs(want))) if want.size else 1.0)
            err = float(np.max(np.abs(got - want))) if want.size else 0.0
            if not err <= MODEL_RTOL * scale:
                raise MessageError('model', f'LmiUpdate {snap.seq}: {name} differs from this '
                                   f'controller\'s linkage at its q by {err:.3g} (expected at '
                                   f'most {MODEL_RTOL * scale:.3g}): another linkage or a '
                                   'false update')

    def forget(self) -> None:
        """This controller's loop starts over (a new loop process numbers its hand inputs
        from 1 again, so the VE drops its held input and says -1): the next update's input
        is not compared with the previous update's. Its numbering still is: an update
        numbered below the previous one is a restart of the VE only with a new endpoint
        (an echo of an old update right after the loop started was taken for one)."""
        self._forgot = True
        self._sent = 0

    def sent(self, seq: int) -> None:
        """This controller has published its hand inputs up to ``seq`` (after
        :meth:`forget`, an update that consumed a later one consumed the loop before's)."""
        self._sent = max(self._sent, seq)

    @staticmethod
    def _check_continuity(prev: Update, snap: Update) -> None:
        if snap.hand_input_seq < prev.hand_input_seq:
            what = ('no hand input' if snap.hand_input_seq < 0
                    else f'hand input {snap.hand_input_seq}')
            raise MessageError('continuity', f'LmiUpdate {snap.seq}: consumed {what} after '
                               f'update {prev.seq} had consumed {prev.hand_input_seq}: a VE '
                               'never goes back (it drops its inputs only for a new '
                               'controller)')


class HandAdmission:
    """The VE's checks of its graph's hand-input batches, in the order applied:

    1. source (``gate``, as :class:`UpdateAdmission`) and session: a batch whose first seq
       is not above the previous batch's last starts a new session (a restarted controller,
       or a reactivated driver whose loop numbers its inputs from 1 again on the same
       endpoint) only when it is stamped later than the previous sample or comes with a new
       endpoint of the controller, never as a copy of inputs already taken;
    2. ``continuity``, for a batch that directly continues the previous one (its first seq
       the next, answering the next device state: one device cycle later, however long that
       cycle took): stamped no earlier, and its first device pose
       reachable from the previous sample, ``|x (-) x_prev| <= max(|xd_prev|, |xd|) dt +
       slack`` per row (slack :data:`POSE_SLACK_M` on translation rows,
       :data:`POSE_SLACK_RAD` on rotation rows; ``dt`` the stamp difference, s). After lost
       inputs or unanswered device states (a gap in either seq) the device may have gone
       anywhere its hand took it: not checked (measured: a device behind a lossy link,
       states 42 ms apart, turned 0.138 rad where this bound allowed 0.082).
       Within a batch the samples are consecutive cycles of one controller.
    3. ``complete`` (lock-step): every input arrives, in its controller's order, so a batch
       that skips inputs after the previous one is refused (``continuity``) instead of taken
       unchecked: the controller's own batch after it continues the previous one. (A sender
       with the graph's id whose copy of a batch overtook the controller's delayed one was
       taken that way, and the controller's own batches were refused from then on: the
       lock-step run waited for ever.) The wall clock can lose inputs (a starved VE): there
       a gap is taken, as above.
    4. ``origin`` (lock-step): the device's pose at the run's start (the scenario's, as
       ``simulate`` starts it). The run's first input, stamped 0, is where the device starts:
       a batch whose first sample is stamped 0 is refused (``continuity``) unless that
       sample is within the slack of ``origin``. Without it the session's first batch has no
       predecessor to continue, and a copy of it from a sender with the graph's id, arriving
       first, was taken and the controller's own refused as its copy (``session``): the
       lock-step run waited for ever.
    5. With ``complete`` also: a session's first batch starts at input 1 (every controller
       numbers its inputs from 1, and every input arrives). Without it a copy of the
       controller's *second* batch, arriving before its first (delayed on the wire), had no
       predecessor to continue and was taken, the copies after it continued it, and the
       controller's own batches were refused as copies: the VE integrated the copies.
    """

    def __init__(self, task: TaskSpace, gate: SourceGate | None = None,
                 complete: bool = False, origin: np.ndarray | None = None) -> None:
        self.task = task
        self.gate = gate
        self.complete = complete
        self.origin = None if origin is None else np.array(origin, dtype=float)
        slack = np.full(task.dim, POSE_SLACK_RAD)
        slack[task.translation_rows] = POSE_SLACK_M
        self.slack = slack
        self._last: tuple[int, int, float, np.ndarray, np.ndarray] | None = None

    def admit(self, seqs: list[int], state_seqs: list[int], stamps: list[float] | np.ndarray,
              pose: np.ndarray, twist: np.ndarray) -> None:
        """Raise :class:`~haptic_topology.errors.MessageError` if the batch (``seqs``, the
        ``state_seqs`` of the device states they answer, ``stamps`` s, n x m ``pose``,
        ``twist``) may not be taken; otherwise its last sample is remembered."""
        last = self._last
        gate = self.gate
        if gate is not None:
            refusal = gate.refuse()
            if refusal is not None:
                raise refusal
        if self.origin is not None and float(stamps[0]) == 0.0:
            beyond = self._beyond(pose[0], self.origin, self.slack)
            if beyond is not None:
                i, moved = beyond
                raise MessageError('continuity', f'HandInputs seq {seqs[0]}: device pose row '
                                   f'{i} is {moved:.4g} from where the run starts, '
                                   f'expected at most {self.slack[i]:.4g}')
        restart = False
        if last is not None and seqs[0] <= last[0]:
            # A new controller, or one whose loop was started again (a reactivated driver:
            # same endpoint, new numbering, later stamps); not a copy of inputs already taken.
            restart = gate is not None and gate.new_session()
            if not (float(stamps[0]) > last[2] or restart):
                raise MessageError('session', f'HandInputs seq {seqs[0]} after {last[0]}, '
                                   'stamped no later and from no new controller endpoint: '
                                   'not a restart, refused')
            last = None
        if self.complete and last is None and seqs[0] != 1:
            raise MessageError('continuity', f'HandInputs seq {seqs[0]}: a session\'s first '
                               'batch, expected to start at input 1: in lock-step every input '
                               'arrives, in order')
        if self.complete and last is not None and seqs[0] > last[0] + 1:
            raise MessageError('continuity', f'HandInputs seq {seqs[0]} after {last[0]}: '
                               f'inputs {last[0] + 1}-{seqs[0] - 1} missing, and in lock-step '
                               'every input arrives, in order')
        if (last is not None and seqs[0] == last[0] + 1
                and state_seqs[0] == last[1] + 1):           # the next device cycle's input
            _, _, t_prev, x_prev, v_prev = last
            dt = float(stamps[0]) - t_prev
            if dt < 0.0:
                raise MessageError('continuity', f'HandInputs seq {seqs[0]}: stamped '
                                   f'{-dt * 1e3:.3f} ms before the previous sample')
            reach = np.maximum(np.abs(v_prev), np.abs(twist[0])) * dt + self.slack
            beyond = self._beyond(pose[0], x_prev, reach)
            if beyond is not None:
                i, moved = beyond
                raise MessageError('continuity', f'HandInputs seq {seqs[0]}: device pose row '
                                   f'{i} moved {moved:.4g} in {dt * 1e3:.1f} ms, expected '
                                   f'at most {reach[i]:.4g} at its twist')
        if gate is not None:            # every check passed: only now is a restart taken
            if restart:
                gate.start_session()
            gate.accepted()
        self._last = (int(seqs[-1]), int(state_seqs[-1]), float(stamps[-1]), np.array(pose[-1]),
                      np.array(twist[-1]))

    def _beyond(self, x: np.ndarray, x_prev: np.ndarray, reach: np.ndarray
                ) -> tuple[int, float] | None:
        """The pose row in which ``x`` is farthest beyond ``reach`` of ``x_prev`` and how far
        it is from it there (m or rad, per row); None when every row is within reach."""
        moved = np.abs(pose_difference(x, x_prev, self.task))
        i = int(np.argmax(moved - reach))
        return (i, float(moved[i])) if moved[i] > reach[i] else None
