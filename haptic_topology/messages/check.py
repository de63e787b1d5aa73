"""Checks of the graph's messages where they enter, without rclpy (nodes and bag readers).

Every field of an incoming ``haptic_topology_msgs`` message is checked before the core sees
it: ``task_dim`` and ``dof`` against the linkage, every array's size, every float finite (where
the core computes with it), every integer against its range. A failed check raises
:class:`~haptic_topology.errors.MessageError` naming the message type, the field, the
expected value and the value received, with a ``reason`` (one of :data:`REASONS`) that the
nodes count per reason in their diagnostics (``rejected_<reason>``) and the bag analysis
counts per reason in its summary.

The functions take any object with the message's attributes: an rclpy message in the nodes, a
``rosbags`` message in the bag tools.

Integer ranges: sequence numbers are ``uint64`` on the wire, but the core keeps them in Python
ints, ``int64`` arrays and float64 diagnostics, and adds offsets to them (a restarted
``device_driver`` continues the controller's loop seq at ``device seq + previous loop seq``).
So every sequence number must be at most :data:`MAX_SEQ` ``= 2**53``: exact as a float64,
and any sum of two stays below ``2**54``, far inside ``int64``. At 1 kHz, ``2**53`` cycles are
285,000 years; a larger value is not a counter but an impostor or a corrupt message.

Example::

    >>> from types import SimpleNamespace
    >>> try:
    ...     check_seq(SimpleNamespace(seq=2**63 - 1), 'seq')
    ... except MessageError as exc:
    ...     print(exc.reason, '|', exc)
    range | SimpleNamespace.seq must be in [1, 9007199254740992], got 9223372036854775807
"""

from __future__ import annotations

import array as _array
import hashlib
import math
import secrets
from collections import Counter
from collections.abc import Callable
from itertools import pairwise
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.errors import MessageError

#: Why a message was rejected (diagnostics keys ``rejected_<reason>``).
REASONS = ('task_dim', 'dof', 'size', 'non_finite', 'range', 'session', 'source', 'model',
           'continuity')

#: Largest sequence number accepted (see module doc).
MAX_SEQ = 2 ** 53
#: Bits of ``DeviceState.status`` (OK 0, WORKSPACE_LIMIT 1, SATURATED 2, WATCHDOG 4, FAULT 8,
#: IDLE 16).
STATUS_BITS = vocab.STATUS_BITS
#: ``DeviceCommand.mode``: MODE_PENALTY 0, MODE_ACCELERATION_ONLY 1, MODE_ZERO 2.
MODES = vocab.MESSAGE_MODES
#: Largest ``DeviceCommand.controller_id``: ids are in [1, 2**63 - 1], so they fit a signed
#: 64-bit integer wherever a tool keeps them (0 is no id: see :func:`check_command`).
MAX_CONTROLLER_ID = 2 ** 63 - 1


def new_controller_id() -> int:
    """A random controller id in [1, :data:`MAX_CONTROLLER_ID`] (``secrets``, 63 bits): two
    controller processes share one with probability 2**-63."""
    return 1 + secrets.randbelow(MAX_CONTROLLER_ID)


def graph_wire(graph_id: str) -> int:
    """The ``graph_id`` field of a graph's messages for the nodes' ``graph_id`` parameter:
    0 for the default graph (``''``), else the first 63 bits of its BLAKE2b hash, made
    nonzero. Two graphs named differently share a value with probability 2**-63."""
    if not graph_id:
        return 0
    h = int.from_bytes(hashlib.blake2b(graph_id.encode(), digest_size=8).digest(), 'little')
    return (h >> 1) or 1


class GraphFilter:
    """Which messages belong to this node's graph (``graph_id`` equals the graph's
    :func:`graph_wire`); the others are foreign, counted per topic, never applied.

    A message recorded before the field existed reads as graph 0 (the default graph)."""

    def __init__(self, graph_id: str) -> None:
        self.graph_id = graph_id
        self.wire = graph_wire(graph_id)
        self.foreign: Counter[str] = Counter()

    def own(self, msg: Any, topic: str) -> bool:
        """True if ``msg`` (on ``topic``) is of this graph; else counts it."""
        if getattr(msg, 'graph_id', 0) == self.wire:
            return True
        self.foreign[topic] += 1
        return False

    @property
    def total(self) -> int:
        return sum(self.foreign.values())

    def values(self) -> dict[str, str]:
        """``/diagnostics`` values: the graph and the foreign messages per topic."""
        return {'graph_id': self.graph_id, 'foreign_messages': str(self.total),
                **{f'foreign {t}': str(n) for t, n in sorted(self.foreign.items())}}


class SourceGate:
    """Which publishers of one input topic are the graph's own, and whether a message may
    open a new session of its sender.

    A message carries no publisher identity here (rclpy gives none per message), so the gate
    works from the graph: the node feeds it the topic's publishers with :meth:`observe`
    (endpoint gids of the node names the graph expects on the topic, in its namespace, and the
    names of the others). Two decisions follow:

    * :meth:`new_session`: a message numbered below its predecessor (seq 0 after seq 5,000)
      claims that its sender restarted. That is believed only when an own endpoint is there
      that the current session never saw (the restarted node's new publisher); a message that
      only *says* so, from the same endpoints, is refused (reason ``session``). The session
      starts over (:meth:`start_session`) only once the message passed every other check
      too: a false message sent as the restarted sender appears uses nothing up.
    * :meth:`distinct`: the graph can tell its own messages from foreign ones while an own
      publisher is there or no foreign one is. With the own one gone and a foreign one left,
      a message with this graph's ``graph_id`` can only be foreign: refused (reason
      ``source``). Before an own publisher has been seen once, none is *gone*: the node may
      have discovered a foreign one first, or a user's node under another name may be the
      graph's only source (``PublisherWatch`` names it at ERROR either way).
    """

    def __init__(self, topic: str, owner: str, refresh: Callable[[], None] | None = None
                 ) -> None:
        self.topic = topic
        self.owner = owner                  # the expected publisher, for messages
        self.own: frozenset[bytes] = frozenset()
        self.foreign: tuple[str, ...] = ()
        self._session: set[bytes] = set()   # own endpoints seen while the session ran
        self._unseen = False                # messages taken before any own endpoint was seen
        self._had_own = False               # an own publisher was seen once
        #: Asks the graph again (it calls :meth:`observe`) before a refusal: a publisher that
        #: has just appeared may send before the node's periodic look at the graph.
        self.refresh = refresh

    def observe(self, own: frozenset[bytes], foreign: tuple[str, ...]) -> None:
        """The topic's publishers now: the own endpoints' gids and the foreign ones' names.

        Messages can arrive before their publisher is in the node's view of the graph
        (discovery is slower under load): the own endpoints first seen after the session took
        such messages are the session's, not a restarted sender's."""
        self.own, self.foreign = own, foreign
        self._had_own = self._had_own or bool(own)
        if self._unseen and own:
            self._session |= own
            self._unseen = False

    def accepted(self) -> None:
        """A message of the current session was applied: its endpoints belong to it."""
        self._session |= self.own
        self._unseen = self._unseen or not self.own

    def new_session(self) -> bool:
        """Whether a message that restarts its sender's numbering may be believed: an own
        endpoint is there that this session never saw (see class doc). Nothing changes
        until the message passed every check: then :meth:`start_session`."""
        if not self.own - self._session and self.refresh is not None:
            self.refresh()
        return bool(self.own - self._session)

    def start_session(self) -> None:
        """The restart was admitted (:meth:`new_session`, then every other check): the
        session starts over with the endpoints there now."""
        self._session = set(self.own)
        self._unseen = False

    def distinct(self) -> bool:
        """Whether this graph's messages on the topic can be told from foreign ones."""
        return bool(self.own) or not self.foreign or not self._had_own

    def lost(self) -> str | None:
        """What the graph can no longer tell apart on the topic (None while it can): the one
        sentence a node logs, reports and refuses with."""
        if self.distinct():
            return None
        return (f'{self.topic}: no {self.owner} of this graph publishes it and '
                f'{", ".join(self.foreign)} does: this graph\'s messages on it cannot be told '
                'from foreign ones')

    def refuse(self) -> MessageError | None:
        """Why a message of this graph on the topic cannot be taken now (None: it can): the
        own publisher gone while a foreign one publishes (:meth:`lost`)."""
        if self.distinct():
            return None
        if self.refresh is not None:
            self.refresh()
            if self.distinct():
                return None
        return MessageError('source', f'{self.lost()}: refused')

    def refuse_restart(self, seq: int, previous: int) -> MessageError:
        """The refusal of a message that restarts the numbering without a new endpoint."""
        return MessageError('session', f'{self.topic}: seq {seq} after {previous} but no new '
                            f'{self.owner} endpoint: not a restart, refused')


class RejectCounter:
    """Rejected messages per reason (for ``/diagnostics`` and bag summaries)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = dict.fromkeys(REASONS, 0)

    def add(self, exc: MessageError) -> None:
        self.counts[exc.reason] = self.counts.get(exc.reason, 0) + 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def values(self, prefix: str = 'rejected_') -> dict[str, str]:
        return {f'{prefix}{k}': str(v) for k, v in self.counts.items()}


def _name(msg: Any) -> str:
    return type(msg).__name__.rsplit('__', 1)[-1]


def array(msg: Any, field: str, size: int, finite: bool = True) -> np.ndarray:
    """``msg.field`` as a float array of ``size`` entries (finite unless ``finite=False``)."""
    values = getattr(msg, field)
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise MessageError('size', f'{_name(msg)}.{field} must be {size} numbers') from None
    except OverflowError:
        raise MessageError('non_finite', f'{_name(msg)}.{field} has entries beyond the '
                           'float range') from None
    if a.shape != (size,):
        raise MessageError('size', f'{_name(msg)}.{field} must have {size} entries, '
                           f'got {a.size}')
    if finite and not _all_finite(values, a):
        raise MessageError('non_finite', f'{_name(msg)}.{field} has non-finite '
                           f'entries: {a.tolist()}')
    return a


#: Up to this many entries a field's finiteness is tested on its Python floats: a few us less
#: per field than numpy's element-wise test, which costs more than the test itself.
_SUM_TEST_MAX = 64


def _all_finite(values: Any, a: np.ndarray) -> bool:
    """Whether every entry of ``a`` (the float array of the field's ``values``) is finite.
    A short ``array.array`` or list (how rclpy hands a message's float arrays over) is tested
    by its sum, which is finite when every entry is unless it overflows; only a sum that is
    not finite goes on to the element-wise test."""
    if (type(values) is _array.array or type(values) is list) and len(values) <= _SUM_TEST_MAX:
        try:
            if math.isfinite(sum(values)):
                return True
        except (TypeError, OverflowError):  # text, or ints whose sum no float holds
            pass
    return bool(np.isfinite(a).all())


def finite_scalar(msg: Any, field: str) -> float:
    v = float(getattr(msg, field))
    if not math.isfinite(v):
        raise MessageError('non_finite', f'{_name(msg)}.{field} is not finite: {v}')
    return v


def check_range(ok: bool, msg: Any, text: str) -> None:
    """Raise a ``range`` :class:`~haptic_topology.errors.MessageError`
    ``<Type>.<text>`` unless ``ok``."""
    if not ok:
        raise MessageError('range', f'{_name(msg)}.{text}')


def check_int(msg: Any, field: str, lo: int, hi: int) -> int:
    """``msg.field`` as an int in ``[lo, hi]``."""
    v = int(getattr(msg, field))
    if not lo <= v <= hi:       # the text only then: checks run per message at 1 kHz
        check_range(False, msg, f'{field} must be in [{lo}, {hi}], got {v}')
    return v


def check_seq(msg: Any, field: str, lo: int = 1) -> int:
    """A sequence number in ``[lo, MAX_SEQ]`` (see module doc)."""
    return check_int(msg, field, lo, MAX_SEQ)


def check_task_dim(msg: Any, dim: int) -> None:
    if int(msg.task_dim) != dim:
        raise MessageError('task_dim', f'{_name(msg)}.task_dim must be {dim}, '
                           f'got {msg.task_dim}')


def check_stamp(msg: Any) -> float:
    """``header.stamp`` in seconds; ``sec >= 0`` and ``nanosec < 1e9`` (a stamp from before
    1970 or with a nanosecond overflow is not one of ours)."""
    stamp = msg.header.stamp
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if sec < 0 or nanosec >= 1_000_000_000:
        check_range(sec >= 0, msg, f'header.stamp.sec must be >= 0, got {sec}')
        check_range(False, msg, f'header.stamp.nanosec must be < 1000000000, got {nanosec}')
    return float(sec) + 1e-9 * float(nanosec)


# -- per message ------------------------------------------------------------------------------
def check_state(msg: Any, dim: int) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray,
                                             np.ndarray, int]:
    """A ``DeviceState``: ``(seq, stamp_s, pose, twist, hand_wrench, applied_wrench,
    status)``; seq in [1, MAX_SEQ], status only known bits."""
    check_task_dim(msg, dim)
    seq = check_seq(msg, 'seq')
    status = check_int(msg, 'status', 0, STATUS_BITS)
    stamp = check_stamp(msg)
    return (seq, stamp, array(msg, 'pose', dim), array(msg, 'twist', dim),
            array(msg, 'hand_wrench', dim), array(msg, 'applied_wrench', dim), status)


def check_command(msg: Any, dim: int) -> tuple[int, int, np.ndarray, int]:
    """A ``DeviceCommand``: ``(state_seq, mode, wrench, controller_id)``. The wrench must be
    finite; ``controller_id`` in [1, MAX_CONTROLLER_ID] (a message recorded before the field
    existed has none: 0 is returned for it); the VT pose/twist (recorded, not applied) must
    have ``dim`` entries; ``constraint_count`` in [0, dim]; ``update_age`` >= 0 (inf before
    the controller's first update); ``update_seq`` in [-1, MAX_SEQ]."""
    check_task_dim(msg, dim)
    wrench = array(msg, 'wrench', dim)      # first: what is applied keeps its reason
    mode = int(msg.mode)
    if mode not in MODES:
        check_range(False, msg, f'mode must be one of {list(MODES)}, got {mode}')
    state_seq = check_seq(msg, 'state_seq')
    controller_id = (check_int(msg, 'controller_id', 1, MAX_CONTROLLER_ID)
                     if hasattr(msg, 'controller_id') else 0)
    check_int(msg, 'constraint_count', 0, dim)
    age = float(msg.update_age)
    if not age >= 0.0:
        check_range(False, msg, f'update_age must be >= 0 (or inf), got {age}')
    if hasattr(msg, 'update_seq'):      # recorded before the field existed: none
        check_int(msg, 'update_seq', -1, MAX_SEQ)
    check_stamp(msg)
    array(msg, 'vt_pose', dim, finite=False)
    array(msg, 'vt_twist', dim, finite=False)
    env_wrench(msg, dim)
    return state_seq, mode, wrench, controller_id


def env_wrench(msg: Any, dim: int) -> np.ndarray | None:
    """``msg.env_wrench`` (``DeviceCommand``/``DeviceState``): None when empty (no obstacles,
    or recorded before the field existed), else ``dim`` finite entries."""
    if len(getattr(msg, 'env_wrench', ())) == 0:
        return None
    return array(msg, 'env_wrench', dim)


#: Most contacts one LmiUpdate may carry (a scenario's capsule-obstacle candidates within the
#: margin; far more than any linkage the VE keeps at 100 Hz).
MAX_CONTACTS = 4096


def check_update_contacts(msg: Any, dof: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The contact fields of an ``LmiUpdate``: None when ``contact_stiffness`` is 0 (no
    obstacles; then every contact array must be empty), else ``(points c x 3, normals c x 3,
    gaps c, jacobians c x 3 x dof)``: sizes from ``contact_count`` (<= MAX_CONTACTS), every
    value finite, normals unit, model parameters in range (stiffness > 0, damping, friction
    >= 0, slip velocity > 0). Fields missing (a bag recorded before them): None."""
    if not hasattr(msg, 'contact_stiffness'):
        return None
    k = finite_scalar(msg, 'contact_stiffness')
    c = check_int(msg, 'contact_count', 0, MAX_CONTACTS)
    if k == 0.0:
        check_range(c == 0, msg, f'contact_count must be 0 when contact_stiffness is 0, got {c}')
        # No obstacles (every update of most scenarios, at 100 Hz): empty arrays only.
        for name in ('contact_points', 'contact_normals', 'contact_gaps', 'contact_jacobians'):
            if len(getattr(msg, name)):
                array(msg, name, 0)             # raises, naming the field and its size
        finite_scalar(msg, 'contact_energy')
        return None
    check_range(k >= 0.0, msg, f'contact_stiffness must be >= 0, got {k}')
    points = array(msg, 'contact_points', 3 * c).reshape(c, 3)
    normals = array(msg, 'contact_normals', 3 * c).reshape(c, 3)
    gaps = array(msg, 'contact_gaps', c)
    jac = array(msg, 'contact_jacobians', 3 * c * dof).reshape(c, 3, dof)
    finite_scalar(msg, 'contact_energy')
    check_range(bool(np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)), msg,
                'contact_normals must be unit vectors')
    for name in ('contact_damping', 'contact_friction'):
        v = finite_scalar(msg, name)
        check_range(v >= 0.0, msg, f'{name} must be >= 0, got {v}')
    v_s = finite_scalar(msg, 'contact_slip_velocity')
    check_range(v_s > 0.0, msg, f'contact_slip_velocity must be > 0, got {v_s}')
    return points, normals, gaps, jac


def check_hand_inputs(msg: Any, dim: int, max_wrench: float, coupling_applied: bool = True
                      ) -> tuple[list[int], list[int], list[float], np.ndarray, np.ndarray,
                                 np.ndarray, np.ndarray]:
    """A ``HandInputs`` batch of n samples: ``(seqs, state_seqs, stamps_s, pose, twist, F_h,
    F_pc)``, the vectors n x ``dim``. n >= 1; ``seq`` and ``state_seq`` n entries each in
    [1, MAX_SEQ], strictly ascending; ``stamp`` n stamps, each as ``header.stamp``; every
    vector n x dim and finite; every entry of a wrench the VE applies to the VT within
    ``max_wrench``: ``hand_wrench`` always, ``coupling_wrench`` when ``coupling_applied``
    (VT coupling, ``F_vt = F_h - F_pc``). Without VT coupling ``F_pc`` only reports the
    coordination wrench on the device, which grows with the distance between device and VT
    (eq. 15): bounding it would throw away the batch's ``F_h`` that the VT moves under. One
    bad field rejects the whole batch.

    Example::

        >>> from types import SimpleNamespace as NS
        >>> t = NS(sec=0, nanosec=1_000_000)
        >>> batch = NS(header=NS(stamp=t), task_dim=1, seq=[7, 6], state_seq=[3, 4],
        ...            stamp=[t, t], pose=[0.0, 0.0], twist=[0.0, 0.0],
        ...            hand_wrench=[0.0, 0.0], coupling_wrench=[0.0, 0.0])
        >>> try:
        ...     check_hand_inputs(batch, 1, 100.0)
        ... except MessageError as exc:
        ...     print(exc.reason, '|', exc)
        range | SimpleNamespace.seq must be strictly ascending, got [7, 6]
    """
    check_task_dim(msg, dim)
    check_stamp(msg)
    seqs = _seq_list(msg, 'seq', None)
    n = len(seqs)
    state_seqs = _seq_list(msg, 'state_seq', n)
    stamps = list(msg.stamp)
    if len(stamps) != n:
        raise MessageError('size', f'{_name(msg)}.stamp must have {n} entries (one per seq), '
                           f'got {len(stamps)}')
    seconds = []
    for i, st in enumerate(stamps):
        sec, nanosec = int(st.sec), int(st.nanosec)
        if sec < 0 or nanosec >= 1_000_000_000:
            check_range(sec >= 0, msg, f'stamp[{i}].sec must be >= 0, got {sec}')
            check_range(False, msg, f'stamp[{i}].nanosec must be < 1000000000, got {nanosec}')
        seconds.append(float(sec) + 1e-9 * float(nanosec))
    pose, twist, f_h, f_pc = (array(msg, f, n * dim).reshape(n, dim)
                              for f in ('pose', 'twist', 'hand_wrench', 'coupling_wrench'))
    bounded = (('hand_wrench', f_h), ('coupling_wrench', f_pc))
    for name, w in bounded if coupling_applied else bounded[:1]:
        bad = np.abs(w) > max_wrench
        if np.any(bad):
            row = int(np.flatnonzero(bad.any(axis=1))[0])
            check_range(False, msg, f'{name} must be within +-{max_wrench:g}, got '
                        f'{w[row].tolist()} (sample {row})')
    return seqs, state_seqs, seconds, pose, twist, f_h, f_pc


def _seq_list(msg: Any, field: str, size: int | None) -> list[int]:
    """``msg.field`` as sequence numbers: ``size`` entries (None: at least one), each in
    [1, MAX_SEQ], strictly ascending."""
    seqs = [int(v) for v in getattr(msg, field)]
    if size is None and not seqs:
        raise MessageError('size', f'{_name(msg)}.{field} must have at least 1 entry, got 0')
    if size is not None and len(seqs) != size:
        raise MessageError('size', f'{_name(msg)}.{field} must have {size} entries (one per '
                           f'seq), got {len(seqs)}')
    bad = [v for v in seqs if not 1 <= v <= MAX_SEQ]
    if bad:
        check_range(False, msg, f'{field} must be in [1, {MAX_SEQ}], got {bad[:3]}')
    if not all(a < b for a, b in pairwise(seqs)):
        check_range(False, msg, f'{field} must be strictly ascending, got {seqs[:12]}')
    return seqs


def check_update_header(msg: Any, dim: int, dof: int) -> tuple[int, int]:
    """The integers of an ``LmiUpdate``: ``(seq, hand_input_seq)``, both in [0, MAX_SEQ]
    (the VE's first update is seq 0; hand_input_seq 0: no input consumed yet); ``dof`` and
    ``task_dim`` those of the linkage; ``constraint_count`` in [0, task_dim]."""
    check_task_dim(msg, dim)
    if int(msg.dof) != dof:
        raise MessageError('dof', f'{_name(msg)}.dof must be {dof}, got {msg.dof}')
    seq = check_seq(msg, 'seq', 0)
    hand_input_seq = check_seq(msg, 'hand_input_seq', 0)
    check_int(msg, 'constraint_count', 0, dim)
    check_stamp(msg)
    return seq, hand_input_seq


def check_vt_path(msg: Any, dim: int) -> tuple[int, list[int], np.ndarray]:
    """A ``VtPath``: ``(update_seq, hand_input_seqs, hand_pose rows)``; every seq in
    [1, MAX_SEQ], ``hand_pose`` ``len(hand_input_seqs) x dim`` and finite."""
    check_task_dim(msg, dim)
    update_seq = check_seq(msg, 'update_seq', 0)
    seqs = [int(s) for s in msg.hand_input_seqs]
    bad = [s for s in seqs if not 1 <= s <= MAX_SEQ]
    check_range(not bad, msg, f'hand_input_seqs must be in [1, {MAX_SEQ}], got {bad[:3]}')
    poses = array(msg, 'hand_pose', len(seqs) * dim).reshape(len(seqs), dim)
    return update_seq, seqs, poses
