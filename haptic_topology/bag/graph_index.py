"""The first pass over a bag of the node graph: which message fills which row of the trace.

:func:`index_bag` reads every message once, applies the checks and choices of
:mod:`haptic_topology.bag.graph_trace` (module doc there: foreign graphs, malformed messages,
duplicates, states far outside the run, the controller the device driver followed, the
update admission) and keeps, per message, only what those choices need (sequence numbers,
stamps, a status bit, controller ids): under 40 bytes a device cycle, no decoded message.
The result, :class:`BagIndex`, says for every row of the trace which messages fill it (the
first valid state of its seq, the command chosen among those answering it, the ``VtPath``
poses of its VT hand) and holds the VE's samples (``LmiUpdate``, 100 Hz) the rows
interpolate; the second pass (:func:`haptic_topology.bag.graph_trace.stream_graph_bag`)
applies the same checks, fills the rows and hands them on in chunks.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import Bag, BagMessage, Progress, decoder, iter_messages
from haptic_topology.control.admission import UpdateAdmission, UpdateFields
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import BagError, HapticTopologyError, MessageError
from haptic_topology.messages.check import (
    GraphFilter,
    array,
    check_command,
    check_state,
    check_update_contacts,
    check_update_header,
    check_vt_path,
)
from haptic_topology.model.linkage import Linkage
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import contact_depth
from haptic_topology.vocabulary import STATUS_CONTROLLER, STATUS_DEVICE, TaskSpace

WATCHDOG = 4
DEVICE_STATUS = STATUS_DEVICE
CONTROLLER_STATUS = STATUS_CONTROLLER
#: Topics the graph also publishes that newer bags have (not required to read a bag).
PATH_TOPIC = vocab.TOPIC_VT_PATH
#: Largest gap between consecutive state seqs within one run (10 s of 1 kHz states; a
#: recorder loses far less).
MAX_SEQ_GAP = 10_000
#: The message kinds of the trace: topic suffix -> kind.
KINDS = ((vocab.TOPIC_STATE, 'state'), (vocab.TOPIC_COMMAND, 'command'),
         (vocab.TOPIC_LMI, 'update'), (PATH_TOPIC, 'path'))
#: The order in which the skipped messages' reasons are first counted (the keys' order of
#: ``skipped``): while reading, then the checks of each kind, then the foreign seqs.
PHASES = ('read', 'state', 'state_duplicate', 'command', 'command_duplicate', 'update',
          'update_admission', 'path', 'state_foreign_seq')
_FIRST, _BLOCK = 1024, 65_536


def stamp(header: Any) -> float:
    """A header's stamp (s)."""
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


class Column:
    """A numpy column growing by blocks (no Python object per value): the first of
    :data:`_FIRST` values, each next one twice as large, up to :data:`_BLOCK`."""

    def __init__(self, dtype: Any, width: int | None = None) -> None:
        self.dtype, self.width = dtype, width
        self.blocks: list[np.ndarray] = []
        self.cur = self._new(_FIRST)
        self.n = 0

    def _new(self, size: int) -> np.ndarray:
        return np.empty((size,) if self.width is None else (size, self.width), self.dtype)

    def append(self, value: Any) -> None:
        if self.n == len(self.cur):
            self.blocks.append(self.cur)
            self.cur, self.n = self._new(min(2 * len(self.cur), _BLOCK)), 0
        self.cur[self.n] = value
        self.n += 1

    def array(self) -> np.ndarray:
        """The values so far (the column is emptied)."""
        out = np.concatenate([*self.blocks, self.cur[:self.n]])
        self.blocks, self.cur, self.n = [], self.cur[:0], 0
        return out


@dataclass
class BagIndex:
    """What the second pass needs (module doc). Rows are the run's states in seq order."""

    #: The run's task (:func:`bag_task`) and its dimension.
    task: TaskSpace
    m: int
    dof: int
    contacts: bool
    mode: int
    #: Per row: the state's seq; its command (0: none answers it, 1: the first valid one,
    #: 2: the first from a controller in :attr:`followed`); how many ``VtPath`` poses of the
    #: previous seq the bag has (the last one read is the row's VT pose).
    seqs: np.ndarray
    command: np.ndarray
    paths: np.ndarray
    #: Controller ids the device driver reported following.
    followed: set[int]
    #: The stamp (s) of the first row's state (t = 0).
    t0: float
    #: The VE's samples: rows they describe (ascending), their times (s from t0), VT hand
    #: poses, joint positions, constraint counts, deepest contacts (m), contact energies (J).
    known_rows: np.ndarray
    known_t: np.ndarray
    known_pose: np.ndarray
    known_q: np.ndarray
    known_count: np.ndarray
    known_depth: np.ndarray
    known_energy: np.ndarray
    #: Whether the bag has VtPath poses (then rows after the first take their VT pose there).
    vt_path: bool
    diagnostics: dict[str, dict[str, str]]
    skipped: dict[str, int]
    graph_id: str
    foreign_messages: dict[str, int]
    foreign_publishers: dict[str, list[str]]
    bag_states: int
    bag_commands: int
    update_rate_hz: float
    truncated: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


def _most_common(counts: Counter[int]) -> int:
    return max(set(counts), key=counts.__getitem__) if counts else 0


def census(bag: Bag, decode: Callable[[BagMessage], Any], graph_id: str
           ) -> tuple[Counter[int], Counter[int]]:
    """The task dimensions of the bag's states and the dofs of its updates (own graph)."""
    graph = GraphFilter(graph_id)
    dims: Counter[int] = Counter()
    dofs: Counter[int] = Counter()
    for raw in iter_messages(bag):
        for suffix, out, name in ((vocab.TOPIC_STATE, dims, 'task_dim'),
                                  (vocab.TOPIC_LMI, dofs, 'dof')):
            if raw.topic.endswith(suffix):
                try:
                    msg = decode(raw)
                except BagError:
                    break
                if graph.own(msg, suffix.lstrip('/')):
                    out[int(getattr(msg, name))] += 1
                break
    return dims, dofs


def _check_update(msg: Any, m: int, dof: int) -> None:
    """The fields of an ``LmiUpdate`` the trace uses: integers, VT hand pose, q, contacts."""
    check_update_header(msg, m, dof)
    array(msg, 'hand_pose', m)
    array(msg, 'q', dof)
    check_update_contacts(msg, dof)


def admission(scenario: str, m: int, dof: int, linkage: Linkage | None) -> UpdateAdmission:
    """The controller's checks of updates (:class:`~haptic_topology.control.admission.
    UpdateAdmission`): the model check against the scenario's linkage (``linkage``, else
    loaded by the name ``scenario``) when it matches ``dof`` and ``m``; the consumed input
    never going back. A bag records no publisher, so a seq going back is not refused."""
    dyn = None
    if linkage is None and scenario:
        linkage = load_scenario(scenario).linkage
    if linkage is not None:
        if linkage.dof == dof and linkage.task.dim == m and not linkage.loops:
            dyn = LinkageDynamics(linkage)
    return UpdateAdmission(dyn)


def bag_task(bag: Bag, m: int, linkage: Linkage | None) -> TaskSpace:
    """The task of the run in ``bag`` whose messages have ``task_dim`` ``m``, from what says
    it, in this order: ``linkage`` (the caller's scenario) when its task has dimension m; the
    linkage of the scenario the bag's metadata names (the recorder's
    ``custom_data.scenario``, when it loads); the only task of dimension m (2:
    ``planar_point``, 6: ``spatial``). Dimension 3 is ``planar`` or ``spatial_point``: a bag
    with neither is refused (:class:`~haptic_topology.errors.BagError`) rather than read with
    a guess. A dimension of no task (a foreign bag's): the rigid task of its size (its
    messages fail the task_dim checks)."""
    if linkage is not None and linkage.task.dim == m:
        return linkage.task
    custom = (bag.metadata or {}).get('custom_data') or {}
    custom = custom if isinstance(custom, dict) else {}
    tasks = [t for t in TaskSpace if t.dim == m]
    if len(tasks) > 1 and custom.get('scenario'):
        try:
            task = load_scenario(str(custom['scenario'])).linkage.task
        except HapticTopologyError:
            task = None
        if task is not None and task.dim == m:
            return task
    if len(tasks) == 1:
        return tasks[0]
    if tasks:
        raise BagError(f'{bag.path}: task_dim {m} is {" or ".join(t.value for t in tasks)} '
                       'and nothing tells which: metadata.yaml names no scenario that loads '
                       '(custom_data.scenario)')
    return TaskSpace.for_dim(m)


def foreign_seqs(seqs: np.ndarray, running: np.ndarray) -> np.ndarray:
    """Mask of the states outside the run among ``seqs`` (sorted, unique): groups split at
    gaps larger than MAX_SEQ_GAP; the run is the largest group with a running state (the
    first of them), or the largest group when none runs."""
    if seqs.size == 0:
        return np.zeros(0, dtype=bool)
    starts = np.concatenate([[0], np.nonzero(np.diff(seqs) > MAX_SEQ_GAP)[0] + 1])
    ends = np.concatenate([starts[1:], [seqs.size]])
    runs = np.add.reduceat(running.astype(np.int64), starts) > 0
    sizes = ends - starts
    pick = np.nonzero(runs)[0] if runs.any() else np.arange(starts.size)
    g = pick[int(np.argmax(sizes[pick]))]
    out = np.ones(seqs.size, dtype=bool)
    out[starts[g]:ends[g]] = False
    return out


def _update_rate(t: np.ndarray, rows: np.ndarray) -> float:
    """The VE's LMI update rate (Hz) over the run, on the device's clock: updates that
    consumed a hand input of the run, per second between the first and the last of them
    (``t``: the times of ``rows``)."""
    sel = rows > 0
    t = t[sel]
    if t.size < 2 or t[-1] <= t[0]:
        return math.nan
    return (t.size - 1) / float(t[-1] - t[0])


class _Pass:
    """The first pass's state (module doc)."""

    def __init__(self, task: TaskSpace, m: int, dof: int, admit: UpdateAdmission) -> None:
        self.m, self.dof, self.admit, self.task = m, dof, admit, task
        self.skips: dict[str, dict[str, int]] = {p: {} for p in PHASES}
        self.s_seq, self.s_run, self.s_stamp = (Column(np.int64), Column(np.bool_),
                                                Column(np.float64))
        self.c_seq, self.c_ctrl, self.c_mode = Column(np.int64), Column(np.int16), Column(np.int8)
        self.controllers: dict[int, int] = {}
        self.u_seq, self.u_pose = Column(np.int64), Column(np.float64, m)
        self.u_q, self.u_count = Column(np.float64, dof), Column(np.int64)
        self.u_depth, self.u_energy = Column(np.float64), Column(np.float64)
        self.contacts = False
        self.p_seq = Column(np.int64)

    def skip(self, phase: str, key: str, n: int = 1) -> None:
        if n:
            table = self.skips[phase]
            table[key] = table.get(key, 0) + n

    def state(self, msg: Any) -> None:
        try:
            check_state(msg, self.m)
        except MessageError as exc:
            self.skip('state', f'state_{exc.reason}')
            return
        self.s_seq.append(int(msg.seq))
        self.s_run.append(not msg.status & WATCHDOG)
        self.s_stamp.append(stamp(msg.header))

    def command(self, msg: Any) -> None:
        try:
            check_command(msg, self.m)
        except MessageError as exc:
            self.skip('command', f'command_{exc.reason}')
            return
        self.c_seq.append(int(msg.state_seq))
        ctrl = int(getattr(msg, 'controller_id', 0))
        # (ids as small numbers; past 32767 distinct controllers, the rest share the last)
        self.c_ctrl.append(self.controllers.setdefault(ctrl, min(len(self.controllers),
                                                                  32767)))
        self.c_mode.append(int(msg.mode))

    def update(self, msg: Any) -> None:
        try:
            _check_update(msg, self.m, self.dof)
        except MessageError as exc:
            self.skip('update', f'update_{exc.reason}')
            return
        try:
            self.admit.admit(UpdateFields.from_msg(msg, self.task, self.dof))
        except MessageError as exc:
            self.skip('update_admission', f'update_{exc.reason}')
            return
        self.u_seq.append(int(msg.hand_input_seq))
        self.u_pose.append(np.asarray(msg.hand_pose, dtype=float))
        self.u_q.append(np.asarray(msg.q, dtype=float) if self.dof else np.zeros(0))
        self.u_count.append(int(msg.constraint_count))
        self.u_depth.append(contact_depth(np.asarray(getattr(msg, 'contact_gaps', []))))
        self.u_energy.append(float(getattr(msg, 'contact_energy', math.nan)))
        self.contacts |= float(getattr(msg, 'contact_stiffness', 0.0)) > 0.0

    def path(self, msg: Any) -> None:
        try:
            _, seqs, _ = check_vt_path(msg, self.m)
        except MessageError as exc:
            self.skip('path', f'path_{exc.reason}')
            return
        for s in seqs:
            self.p_seq.append(s)


def index_bag(bag: Bag, scenario: str, dof: int | None, task_dim: int | None,
              linkage: Linkage | None, progress: Progress | None = None) -> BagIndex:
    """The first pass over ``bag`` (module doc)."""
    decode = decoder(bag=bag)
    graph = GraphFilter(str(((bag.metadata or {}).get('custom_data') or {}).get('graph_id')
                            or ''))
    if task_dim is None or dof is None:
        dims, dofs = census(bag, decode, graph.graph_id)
        task_dim = task_dim if task_dim is not None else _most_common(dims)
        dof = dof if dof is not None else _most_common(dofs)
    m = task_dim
    if linkage is None and scenario:
        linkage = load_scenario(scenario).linkage
    run = _Pass(bag_task(bag, m, linkage), m, dof, admission(scenario, m, dof, linkage))
    diags: dict[str, dict[str, str]] = {}
    publishers: dict[str, set[str]] = {}    # foreign publisher -> topics (nodes' reports)
    followed: set[int] = set()     # controller ids the device driver reported following
    handlers = {'state': run.state, 'command': run.command, 'update': run.update,
                'path': run.path}
    for raw in iter_messages(bag, progress=progress):
        topic = raw.topic
        for suffix, kind in KINDS:
            if topic.endswith(suffix):
                try:
                    msg = decode(raw)
                except BagError:
                    run.skip('read', f'{kind}_decode')
                    break
                if not graph.own(msg, suffix.lstrip('/')):
                    run.skip('read', f'{kind}_foreign_graph')
                    break
                handlers[kind](msg)
                break
        else:
            if topic != vocab.TOPIC_DIAGNOSTICS:
                continue
            try:
                dmsg = decode(raw)
            except BagError:
                run.skip('read', 'diagnostics_decode')
                continue
            for st in getattr(dmsg, 'status', None) or []:
                pairs = {kv.key: kv.value for kv in st.values}
                pairs.setdefault('hardware_id', str(getattr(st, 'hardware_id', '') or ''))
                if pairs.get('graph_id', graph.graph_id) != graph.graph_id:
                    run.skip('read', 'diagnostics_foreign_graph')
                    continue
                diags[st.name] = pairs
                for part in filter(None, pairs.get('foreign_publishers', '').split('; ')):
                    topic, _, names = part.partition(': ')
                    for name in names.split(', '):
                        publishers.setdefault(name, set()).add(topic)
                if st.name == DEVICE_STATUS and pairs.get('controller_id', '').isdigit():
                    followed.add(int(pairs['controller_id']))
    followed.discard(0)
    index = _resolve(bag, run, followed)
    index.diagnostics = diags
    index.graph_id = graph.graph_id
    index.foreign_messages = dict(graph.foreign)
    index.foreign_publishers = {n: sorted(t) for n, t in sorted(publishers.items())}
    return index


def _first(values: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``np.unique(values, return_index=True)``; the index None when ``values`` already
    increase (the bag's usual order: nothing sorted, nothing copied)."""
    if values.size < 2 or bool(np.all(values[1:] > values[:-1])):
        return values, None
    return np.unique(values, return_index=True)


def _take(values: np.ndarray, index: np.ndarray | None) -> np.ndarray:
    return values if index is None else values[index]


def _resolve(bag: Bag, run: _Pass, followed: set[int]) -> BagIndex:
    """The choices after the first pass (module doc of graph_trace)."""
    # States: the first valid one of each seq; then the run's group; rows from the first
    # running state on.
    s_seq = run.s_seq.array()
    seqs, first = _first(s_seq)
    run.skip('state_duplicate', 'state_duplicate', int(s_seq.size - seqs.size))
    del s_seq
    s_run, s_stamp = _take(run.s_run.array(), first), _take(run.s_stamp.array(), first)
    del first
    foreign = foreign_seqs(seqs, s_run)
    if foreign.any():
        seqs, s_run, s_stamp = seqs[~foreign], s_run[~foreign], s_stamp[~foreign]
    if not s_run.any():
        raise BagError(f'{bag.path}: no device state of a running loop (controller never '
                       'engaged?)')
    i0 = int(np.argmax(s_run))
    k0 = int(seqs[i0])
    bag_states = int(seqs.size)
    rows_seq, row_stamp = seqs[i0:], s_stamp[i0:]
    del seqs, s_run, s_stamp
    n = rows_seq.size
    t0 = float(row_stamp[0])
    # Commands: per seq the first valid one, or the first from a controller the device
    # driver followed when the first is not (then the row waits for that one).
    c_seq = run.c_seq.array()
    c_seqs, chosen = _first(c_seq)
    run.skip('command_duplicate', 'command_duplicate', int(c_seq.size - c_seqs.size))
    c_ctrl = run.c_ctrl.array()
    is_followed = np.isin(c_ctrl, [i for c, i in run.controllers.items() if c in followed])
    del c_ctrl
    late = np.zeros(c_seqs.size, dtype=bool)
    if is_followed.any() and chosen is not None:
        f_seqs, f_first = np.unique(c_seq[is_followed], return_index=True)
        at = np.searchsorted(c_seqs, f_seqs)
        late[at] = ~is_followed[chosen[at]]
        chosen[at] = np.nonzero(is_followed)[0][f_first]
    del c_seq, is_followed
    c_mode = _take(run.c_mode.array(), chosen)
    del chosen
    modes = Counter(dict(zip(*(v.tolist() for v in np.unique(c_mode[c_seqs >= k0],
                                                                 return_counts=True)),
                             strict=True)))
    mode = _most_common(modes) if modes else 2
    del c_mode
    command = np.zeros(n, dtype=np.int8)
    if c_seqs.size:
        at = np.minimum(np.searchsorted(c_seqs, rows_seq), c_seqs.size - 1)
        hit = c_seqs[at] == rows_seq
        command[hit] = np.where(late[at[hit]], 2, 1)
        del at, hit
    bag_commands = int(c_seqs.size)
    del c_seqs, late
    # VtPath: how many poses each row's VT hand gets (the last one read counts).
    p_seq = run.p_seq.array()
    has_path = bool(p_seq.size)
    if p_seq.size < 2 or bool(np.all(p_seq[1:] > p_seq[:-1])):
        path_seqs, path_count = p_seq, np.ones(p_seq.size, dtype=np.int64)
    else:
        path_seqs, path_count = np.unique(p_seq, return_counts=True)
    del p_seq
    paths = np.zeros(n, dtype=np.int16)
    if path_seqs.size and n > 1:
        at = np.minimum(np.searchsorted(path_seqs, rows_seq[1:] - 1), path_seqs.size - 1)
        hit = path_seqs[at] == rows_seq[1:] - 1
        paths[1:][hit] = np.minimum(path_count[at[hit]], np.iinfo(np.int16).max)
        del at, hit
    del path_seqs, path_count
    run.skip('state_foreign_seq', 'state_foreign_seq', int(np.count_nonzero(foreign)))
    # The VE's samples at known rows (an update that consumed input s describes the row of
    # state s + 1; the initial one, input 0, the first row).
    u_seq = run.u_seq.array()
    u_rows = np.searchsorted(rows_seq, u_seq + 1)
    found = (u_rows < n) & (rows_seq[np.minimum(u_rows, n - 1)] == u_seq + 1)
    known: dict[int, int] = {}
    for i, (s, r, ok) in enumerate(zip(u_seq.tolist(), u_rows.tolist(), found.tolist(),
                                       strict=True)):
        row = (r if ok else None) if s > 0 else (0 if s == 0 else None)
        if row is not None and (s > 0 or row not in known):
            known[row] = i
    known_rows = np.array(sorted(known), dtype=np.int64)
    pick = np.array([known[r] for r in known_rows.tolist()], dtype=np.int64)
    del known
    known_t = row_stamp[known_rows] - t0
    del row_stamp
    use_path = has_path and known_rows.size > 0
    if not use_path:
        paths[:] = 0
    skipped: dict[str, int] = {}
    for phase in PHASES:
        for key, v in run.skips[phase].items():
            skipped[key] = skipped.get(key, 0) + v
    return BagIndex(
        task=run.task, m=run.m, dof=run.dof, contacts=run.contacts, mode=mode, seqs=rows_seq,
        command=command, paths=paths, followed=followed, t0=t0,
        known_rows=known_rows, known_t=known_t, known_pose=run.u_pose.array()[pick],
        known_q=run.u_q.array()[pick], known_count=run.u_count.array()[pick],
        known_depth=run.u_depth.array()[pick], known_energy=run.u_energy.array()[pick],
        vt_path=use_path, diagnostics={}, skipped=skipped, graph_id='', foreign_messages={},
        foreign_publishers={}, bag_states=bag_states, bag_commands=bag_commands,
        update_rate_hz=_update_rate(known_t, known_rows), truncated=bool(bag.truncated))
