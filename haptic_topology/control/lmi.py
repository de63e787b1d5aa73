"""Local model of interaction (LMI): reduced VT dynamics at the haptic rate (eqs. 17-20).

Between two updates from the full simulation the LMI integrates the virtual tool with ``D``,
``G``, ``J_h`` and the SVD of ``J_h`` frozen at the update (eqs. 17-19), Coriolis terms
neglected::

    eq. 17:  D^ qdd + G^ = J^_h^T F_vt        eq. 20:  D^ qdd = J^_h^T F_vt

and moves the VT hand with the frozen Jacobian, ``xd_vt = J^_h dq``. ``F_vt`` is the wrench
the haptic loop applies to the VT at the hand (the user's ``F_h``, minus the coordination
wrench ``F_pc`` when the coupling acts on the VT).

Timing: the LMI state "has consumed input k" when it has integrated the force computed at
device state k over the interval from state k to state k+1; it then represents the VT at the
time of state k+1. An update from the full simulation carries the seq of the last hand input
it consumed; on re-sync the LMI takes the VE's state and replays the inputs it has recorded
since (so the lag of the update costs no time), with the new matrices.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from haptic_topology.dynamics.constraints import ConstraintDirections, task_scale
from haptic_topology.dynamics.contacts import LocalContacts
from haptic_topology.dynamics.linkage_dynamics import DynamicsSnapshot
from haptic_topology.dynamics.spd import spd_factor, spd_solve
from haptic_topology.model.linkage import PenaltyDirection
from haptic_topology.vocabulary import TaskSpace

#: The contact accelerations of the compiled step when there are none.
_NO_CONTACTS = np.zeros(0)


class LmiModel(enum.Enum):
    """Which reduced dynamics the LMI integrates."""

    EQ17 = 'eq17'   # D^ qdd + G^ = J^T F_vt
    EQ20 = 'eq20'   # D^ qdd = J^T F_vt (Section VIII: the VT moves freely under F_vt)


@dataclass(frozen=True)
class LmiSnapshot:
    """Contents of one LMI update (``haptic_topology_msgs/LmiUpdate``), as numpy arrays."""

    seq: int
    hand_input_seq: int
    task: TaskSpace
    q: np.ndarray
    dq: np.ndarray
    mass_matrix: np.ndarray         # d x d
    gravity: np.ndarray             # d
    hand_jacobian: np.ndarray       # m x d
    singular_values: np.ndarray     # min(m, d), of the weighted Jacobian
    left_vectors: np.ndarray        # m x m
    weights: np.ndarray             # m
    constraint_count: int
    characteristic_length: float
    hand_pose: np.ndarray           # m
    hand_twist: np.ndarray          # m
    # Not in LmiUpdate (yet): the receiver's linkage setting decides it (see sync).
    penalty_direction: PenaltyDirection = PenaltyDirection.NULLSPACE
    #: The contacts within the margin at the update (eq. 17's ``J_i``, ``F_i``); None: the
    #: scenario has no obstacles.
    contacts: LocalContacts | None = None
    #: The VE's contact energy balance at the update (J, recorded for the analysis).
    contact_energy: float = 0.0

    @classmethod
    def from_dynamics(cls, snap: DynamicsSnapshot, task: TaskSpace, characteristic_length: float,
                      seq: int, hand_input_seq: int, contacts: LocalContacts | None = None,
                      contact_energy: float = 0.0) -> LmiSnapshot:
        c = snap.constraints
        return cls(seq, hand_input_seq, task, snap.q, snap.dq, snap.mass_matrix, snap.gravity,
                   snap.hand_jacobian, c.singular_values, c.left_vectors, c.weights, c.count,
                   characteristic_length, snap.hand_pose, snap.hand_twist, c.direction,
                   contacts, contact_energy)

    def constraints(self) -> ConstraintDirections:
        """The VE's directions of topological constraint (eq. 18) with this update's
        ``penalty_direction``: the LMI's projector of eq. 13 is built from them."""
        return ConstraintDirections(self.singular_values, self.left_vectors, self.weights,
                                    self.constraint_count,
                                    task_scale(self.task, self.characteristic_length),
                                    self.penalty_direction)


@dataclass(frozen=True, slots=True)
class LmiSync:
    """An update with the matrices a re-sync takes (:meth:`LocalModel.prepare`): ``D^-1
    J_h^T`` (d x m), ``D^-1 G`` (d; 0 for eq. 20), ``Lambda_h^-1`` (m x m, eq. 19), the
    projector of eq. 13 (m x m), and with contacts ``(J_c^T, D^-1 J_c^T)``, the map from
    contact forces to ``F_env`` and the held forces (N; None when evaluated locally)."""

    snapshot: LmiSnapshot
    accel_map: np.ndarray
    accel_bias: np.ndarray
    lambda_inv: np.ndarray
    projector: np.ndarray
    contacts: LocalContacts | None
    contact_map: tuple[np.ndarray, np.ndarray]
    env_map: np.ndarray
    held_forces: np.ndarray | None


class LocalModel:
    """The LMI: frozen-matrix VT dynamics stepped once per device cycle (eqs. 17-20).

    With contacts in the update (:class:`~haptic_topology.dynamics.contacts.LocalContacts`)
    each step adds their joint torques ``sum_i J_i^T F_i`` of eq. 17, evaluated at the LMI's
    own state every cycle (or held at the update's values when the update says
    ``local: False``), and :attr:`env_wrench` is ``F_env`` of eqs. 10 and 14: the wrench at
    the hand that gives the hand the acceleration the contacts give it,
    ``Lambda_h^-1 F_env = J_h D^-1 sum_i J_i^T F_i`` (eq. 11), i.e.
    ``F_env = Lambda_h^+ J_h D^-1 tau_c`` with the pseudo-inverse where ``Lambda_h^-1`` is
    singular (no hand acceleration, hence no ``F_env``, along a constrained direction)."""

    def __init__(self, task: TaskSpace, model: LmiModel = LmiModel.EQ17,
                 history: int = 1024, device_inertia: np.ndarray | None = None) -> None:
        # Imported here: loading the compiled code costs about 1 s, which a process that
        # only reads updates (a recorder, a bag reader) does not pay.
        from haptic_topology.control.compiled import lmi_replay, lmi_step
        self._lmi_step, self._lmi_replay = lmi_step, lmi_replay
        self.task = task
        self.model = model
        #: ``M_d`` (m x m) of eq. 14: the metric of the penalty's directions (eq. 13, see
        #: :meth:`~haptic_topology.dynamics.constraints.ConstraintDirections.projector`);
        #: None: ``I``.
        self.device_inertia = device_inertia
        self.snapshot: LmiSnapshot | None = None
        # The inputs recorded (a ring of the newest ``history``, in seq order): seq, F_vt
        # and the duration it was held (NaN until the next state gave it one).
        self._in_seq = np.zeros(history, dtype=np.int64)
        self._in_wrench = np.zeros((history, task.dim))
        self._in_dt = np.full(history, np.nan)
        self._in_count = 0
        self.consumed = -1
        m = task.dim
        self.lambda_inv = np.zeros((m, m))
        self.projector = np.zeros((m, m))
        self.constraint_count = 0
        self.q = np.zeros(0)
        self.dq = np.zeros(0)
        self.x_vt = np.zeros(m)
        self.xd_vt = np.zeros(m)
        self._accel_map = np.zeros((0, m))   # D^-1 J^T
        self._accel_bias = np.zeros(0)       # D^-1 G (eq. 17) or 0 (eq. 20)
        self._jacobian = np.zeros((m, 0))
        self._contacts: LocalContacts | None = None
        self._held_forces: np.ndarray | None = None
        self._contact_map = (np.zeros((0, 0)), np.zeros((0, 0)))
        self._env_map = np.zeros((m, 0))
        self._contact_accel: np.ndarray | None = None
        self._forces: np.ndarray | None = None     # F_i at the current state, flattened
        #: ``F_env`` (m) at the current state (zero without contacts).
        self.env_wrench = np.zeros(m)

    def __getstate__(self) -> dict[str, object]:
        state = self.__dict__.copy()        # see HapticController.__getstate__
        del state['_lmi_step'], state['_lmi_replay']
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        from haptic_topology.control.compiled import lmi_replay, lmi_step
        self.__dict__.update(state)
        self._lmi_step, self._lmi_replay = lmi_step, lmi_replay

    @property
    def synced(self) -> bool:
        return self.snapshot is not None

    def prepare(self, snap: LmiSnapshot) -> LmiSync:
        """The matrices a re-sync to ``snap`` takes (eqs. 17-19), computed from the update
        alone: any thread may call this (e.g. the one that receives the update), so that
        :meth:`sync` on the loop's thread only adopts them."""
        if snap.task is not self.task:
            raise ValueError(f'task_dim must be {self.task.dim}, got {snap.task.dim}')
        factor = spd_factor(snap.mass_matrix)
        j = snap.hand_jacobian
        accel_map = spd_solve(factor, j.T)
        accel_bias = (spd_solve(factor, snap.gravity) if self.model is LmiModel.EQ17
                      else np.zeros_like(snap.gravity))
        lam = j @ accel_map
        lambda_inv = 0.5 * (lam + lam.T)      # eq. 19 (with J^T)
        contacts = snap.contacts if snap.contacts is not None and len(snap.contacts) else None
        contact_map = (np.zeros((0, 0)), np.zeros((0, 0)))
        env_map = np.zeros((self.task.dim, 0))
        held = None
        if contacts is not None:
            # Per contact force F (3c, flattened): joint torques J^T F, joint accelerations
            # D^-1 J^T F (eq. 17) and F_env = Lambda^+ J_h D^-1 J^T F, as three matrices.
            jt = contacts.stacked_jacobian.T
            contact_map = (jt, spd_solve(factor, jt))
            lambda_pinv = np.linalg.pinv(lambda_inv, rcond=1e-10, hermitian=True)
            env_map = lambda_pinv @ (j @ contact_map[1])
            if not contacts.local:
                held = contacts.forces(snap.q, snap.dq)
        projector = snap.constraints().projector(self.device_inertia)
        return LmiSync(snap, accel_map, accel_bias, lambda_inv, projector, contacts,
                       contact_map, env_map, held)

    def sync(self, update: LmiSnapshot | LmiSync) -> None:
        """Re-sync to an update (or to its :meth:`prepare`-d matrices): take its matrices and
        state, replay the newer inputs."""
        p = update if isinstance(update, LmiSync) else self.prepare(update)
        snap = p.snapshot
        if snap.task is not self.task:
            raise ValueError(f'task_dim must be {self.task.dim}, got {snap.task.dim}')
        self._accel_map = p.accel_map
        self._accel_bias = p.accel_bias
        self._jacobian = snap.hand_jacobian
        self.lambda_inv = p.lambda_inv
        self.projector = p.projector
        self.constraint_count = snap.constraint_count
        self.q = snap.q.copy()
        self.dq = snap.dq.copy()
        self.x_vt = snap.hand_pose.copy()
        self.xd_vt = snap.hand_twist.copy()
        self.snapshot = snap
        self.consumed = snap.hand_input_seq
        self._contacts = p.contacts
        self._held_forces = p.held_forces
        if p.contacts is not None:
            self._contact_map = p.contact_map
            self._env_map = p.env_map
        self._update_contacts()
        self._replay(None)

    def _update_contacts(self) -> None:
        """Contact forces, their accelerations and ``F_env`` at the current state."""
        c = self._contacts
        forces = None
        if c is not None:
            forces = c.forces(self.q, self.dq) if c.local else self._held_forces
        if forces is None:
            self._forces = self._contact_accel = None
            self.env_wrench = np.zeros(self.task.dim)
            return
        f = self._forces = forces.ravel()
        self._contact_accel = self._contact_map[1] @ f
        self.env_wrench = self._env_map @ f

    @property
    def contact_torques(self) -> np.ndarray:
        """``sum_i J_i^T F_i`` (d) at the current state (eq. 17; zero without contacts)."""
        if self._forces is None:
            return np.zeros(self.q.size)
        return self._contact_map[0] @ self._forces

    def record_input(self, seq: int, wrench: np.ndarray) -> None:
        """Remember the VT wrench computed at device state ``seq`` (used from then on)."""
        i = self._in_count % self._in_seq.size
        self._in_seq[i] = seq
        self._in_wrench[i] = wrench
        self._in_dt[i] = math.nan
        self._in_count += 1

    def advance(self, seq: int, dt: float) -> None:
        """Bring the VT to the time of device state ``seq``; ``dt`` (s) since the last state.

        The newest recorded input gets duration ``dt``; every recorded input not yet
        consumed is integrated in order.
        """
        if self._in_count:
            i = (self._in_count - 1) % self._in_seq.size
            if math.isnan(self._in_dt[i]) and self._in_seq[i] < seq:
                self._in_dt[i] = dt
        self._replay(seq)

    def _replay(self, seq: int | None) -> None:
        """Integrate the recorded inputs not consumed yet, in order, those with a duration
        only, up to (not including) the input of state ``seq`` (None: all)."""
        if self.snapshot is None:
            return
        bound = -1 if seq is None else seq
        if self._contacts is None:
            self.consumed = self._lmi_replay(
                self._accel_map, self._accel_bias, self._jacobian, self.q, self.dq, self.x_vt,
                self.xd_vt, self._in_seq, self._in_wrench, self._in_dt, self._in_count,
                self.consumed, bound)
            return
        # With contacts the forces are evaluated at each state between two steps (Python).
        size, count = self._in_seq.size, self._in_count
        first = count
        while first > max(count - size, 0) and self._in_seq[(first - 1) % size] > self.consumed:
            first -= 1
        for k in range(first, count):
            i = k % size
            if math.isnan(self._in_dt[i]):
                continue
            if bound >= 0 and self._in_seq[i] >= bound:
                break
            self._step(self._in_wrench[i], float(self._in_dt[i]))
            self.consumed = int(self._in_seq[i])

    def _step(self, wrench: np.ndarray, dt: float) -> None:
        """Semi-implicit Euler step of eq. 17 / eq. 20 with the frozen matrices (and the
        contact torques at the state before the step), in place
        (:func:`~haptic_topology.control.compiled.lmi_step`)."""
        self._lmi_step(self._accel_map, self._accel_bias,
                       _NO_CONTACTS if self._contact_accel is None else self._contact_accel,
                       self._jacobian, self.q, self.dq, self.x_vt, self.xd_vt, wrench, dt)
        if self._contacts is not None:
            self._update_contacts()


@dataclass(frozen=True)
class LmiSettings:
    """The ``lmi:`` block of a scenario: the reduced ``model`` and ``update_period``, the device
    cycles per LMI update in the offline simulation (1-10000)."""

    model: LmiModel = LmiModel.EQ17
    update_period: int = 10

    @classmethod
    def from_config(cls, raw: object, where: str) -> LmiSettings:
        """Parse the block (``where``: its path, e.g. ``file: scenario.lmi``)."""
        from haptic_topology.validate import as_int, as_str, check_keys
        lmi = check_keys(raw, where, optional=('model', 'update_period'))
        model = LmiModel(as_str(lmi.get('model', 'eq17'), f'{where}.model', ('eq17', 'eq20')))
        period = as_int(lmi.get('update_period', 10), f'{where}.update_period', lo=1, hi=10000)
        return cls(model, period)
