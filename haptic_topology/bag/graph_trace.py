"""Reduce a bag recorded from the node graph to a :class:`~haptic_topology.sim.trace.Trace`.

Rows are the device states of the run (from the first state not flagged STATUS_WATCHDOG,
the state at which the controller engaged; ``t = 0`` there), in sequence order:

* device pose/twist, hand wrench, applied wrench and status from ``DeviceState``;
* command, LMI VT hand pose and LMI constraint count from the ``DeviceCommand`` with
  ``state_seq`` equal to the row's seq (NaN / 0 when it was lost);
* the VE's VT hand pose from ``VtPath`` (the VT after every consumed input s, i.e. at the
  time of state s + 1) where the bag has it, the initial one from the first ``LmiUpdate``
  (``hand_input_seq`` 0); bags without ``VtPath`` (older recordings): from ``LmiUpdate``
  (the VE after consuming input s), interpolated linearly in time between updates (100 Hz);
  joint positions from ``LmiUpdate``, interpolated the same way; after the last sample they
  are NaN; the constraint count is held from the last update.

Messages that do not belong to the run are skipped and counted per ``<kind>_<reason>`` in
:attr:`GraphRun.skipped` (``analyze`` writes them to ``summary.json`` as
``skipped_messages``): messages of another graph than the recorder's (``graph_id`` field
against the bag's ``custom_data.graph_id``: ``<kind>_foreign_graph``, also counted per topic
in :attr:`GraphRun.foreign_messages`; ``/diagnostics`` statuses of another graph are not
read), messages on the graph's topics that do not decode (``<kind>_decode``),
fail the nodes' own checks (:mod:`haptic_topology.messages.check`: task_dim, dof, sizes,
non-finite values, integer ranges; the run's task_dim is the scenario's, else the most common
one among the states, its dof the scenario's, else the most common among the updates), repeat
a sequence number already read (``state_duplicate``, ``command_duplicate``; of several
commands answering one state, the one from a controller the device driver reported following
(``controller_id`` in its ``/diagnostics``, any time in the bag) is kept, else the first one
read; of states, the first one read: a bag cannot tell which publisher sent which), or lie
far outside the run (``state_foreign_seq``: states are grouped where consecutive seqs are at
most :data:`MAX_SEQ_GAP` apart, and the largest group holding running states is the run).
Messages are decoded with the definitions stored in the bag where they differ from the
current ones (:func:`~haptic_topology.bag.reader.bag_typestore`): bags recorded before
``DeviceCommand.controller_id`` existed read as before.

Loop figures: the device driver's own counts from its last ``/diagnostics`` status
(answered fraction, round trip p50/p99), and an estimate from the bag alone: the fraction of
states k whose command was computed (``DeviceCommand.header.stamp``) before state k+1 was
stamped.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import (
    BagMessage,
    Progress,
    decoder,
    iter_messages,
    open_bag,
    require_types,
)
from haptic_topology.control.admission import UpdateAdmission, UpdateFields
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import BagError, MessageError
from haptic_topology.messages.check import (
    GraphFilter,
    array,
    check_command,
    check_state,
    check_update_contacts,
    check_update_header,
    check_vt_path,
    env_wrench,
)
from haptic_topology.messages.definitions import type_name
from haptic_topology.model.linkage import Linkage
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace, contact_depth
from haptic_topology.vocabulary import ControlMode, TaskSpace

_WATCHDOG = 4
_DEVICE_STATUS = 'device_driver: loop'
#: Topic suffix -> type the graph publishes on it (a bag without any of them is foreign);
#: ``haptic/hand`` (one ``HandInput`` per cycle): bags recorded before the hand inputs were
#: batched on ``haptic/hand_inputs``.
GRAPH_TYPES = {
    vocab.TOPIC_STATE: type_name('DeviceState'),
    vocab.TOPIC_COMMAND: type_name('DeviceCommand'),
    vocab.TOPIC_HAND_INPUTS: type_name('HandInputs'),
    vocab.TOPIC_HAND_LEGACY: type_name('HandInput'),
    vocab.TOPIC_LMI: type_name('LmiUpdate'),
}
#: Topics the graph also publishes that newer bags have (not required to read a bag).
PATH_TOPIC = vocab.TOPIC_VT_PATH
_MODE_LABELS = {int(m): m.label for m in ControlMode}
#: Largest gap between consecutive state seqs within one run (10 s of 1 kHz states; a
#: recorder loses far less).
MAX_SEQ_GAP = 10_000


@dataclass
class GraphRun:
    """A recorded run: its trace and loop figures (``loop`` keys are documented above)."""

    trace: Trace
    loop: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    #: Skipped messages per ``<kind>_<reason>`` (module doc).
    skipped: dict[str, int] = field(default_factory=dict)
    #: The recorder's graph (``graph_id``; empty: the default graph) and the messages of
    #: other graphs on the loop topics, per topic (skipped: ``<kind>_foreign_graph``).
    graph_id: str = ''
    foreign_messages: dict[str, int] = field(default_factory=dict)
    #: Publishers of another node than the graph expects on its input topics, as the nodes
    #: reported them any time in the bag (``foreign_publishers``): name -> topics
    foreign_publishers: dict[str, list[str]] = field(default_factory=dict)


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def read_graph_bag(path: str | Path, scenario: str = '', dof: int | None = None,
                   progress: Progress | None = None, task_dim: int | None = None,
                   linkage: Linkage | None = None) -> GraphRun:
    """Read the bag ``path`` (see module doc); ``progress`` gets the fraction read;
    ``dof``/``task_dim``: the scenario's linkage (None: from the bag's majority);
    ``linkage``: the scenario's linkage itself (None: loaded by the name ``scenario``; give
    it for a scenario file, whose name is not a known scenario).

    A truncated bag (recorder killed) is read up to its last complete chunk; the trace's
    ``meta['truncated']`` is then True. Foreign and malformed messages are skipped and
    counted (:attr:`GraphRun.skipped`).
    """
    bag = open_bag(path)
    p = bag.path
    require_types(bag, GRAPH_TYPES)
    decode = decoder(bag=bag)
    skipped: dict[str, int] = {}

    def skip(kind: str, reason: str) -> None:
        key = f'{kind}_{reason}'
        skipped[key] = skipped.get(key, 0) + 1

    def decoded(kind: str, raw: BagMessage) -> Any:
        try:
            return decode(raw)
        except BagError:
            skip(kind, 'decode')
            return None

    raw_states: list[Any] = []
    raw_commands: list[Any] = []
    updates_in: list[Any] = []
    paths_in: list[Any] = []
    diags: dict[str, dict[str, str]] = {}
    publishers: dict[str, set[str]] = {}    # foreign publisher -> topics (nodes' reports)
    followed: set[int] = set()     # controller ids the device driver reported following
    # The recorder's graph (bag metadata; none: a bag of the default graph): messages and
    # statuses of another graph are skipped and counted as foreign.
    graph = GraphFilter(str(((bag.metadata or {}).get('custom_data') or {}).get('graph_id')
                            or ''))
    kinds = ((vocab.TOPIC_STATE, 'state', raw_states), (vocab.TOPIC_COMMAND, 'command',
                                                        raw_commands),
             (vocab.TOPIC_LMI, 'update', updates_in), (PATH_TOPIC, 'path', paths_in))
    for raw in iter_messages(bag, progress=progress):
        topic = raw.topic
        for suffix, kind, out in kinds:
            if topic.endswith(suffix):
                msg = decoded(kind, raw)
                if msg is not None and not graph.own(msg, suffix.lstrip('/')):
                    skip(kind, 'foreign_graph')
                    msg = None
                out.append(msg)
                break
        else:
            if topic != '/diagnostics':
                continue
            msg = decoded('diagnostics', raw)
            for st in getattr(msg, 'status', None) or []:
                pairs = {kv.key: kv.value for kv in st.values}
                if pairs.get('graph_id', graph.graph_id) != graph.graph_id:
                    skip('diagnostics', 'foreign_graph')
                    continue
                diags[st.name] = pairs
                for part in filter(None, pairs.get('foreign_publishers', '').split('; ')):
                    topic, _, names = part.partition(': ')
                    for name in names.split(', '):
                        publishers.setdefault(name, set()).add(topic)
                if st.name == _DEVICE_STATUS and pairs.get('controller_id', '').isdigit():
                    followed.add(int(pairs['controller_id']))
    m = task_dim if task_dim is not None else _most_common(
        [int(s.task_dim) for s in raw_states if s is not None])
    if dof is None:
        dof = _most_common([int(u.dof) for u in updates_in if u is not None]) or 0

    def valid(kind: str, msgs: list[Any], check: Any) -> list[Any]:
        out = []
        for msg in msgs:
            if msg is None:
                continue
            try:
                check(msg)
            except MessageError as exc:
                skip(kind, exc.reason)
                continue
            out.append(msg)
        return out

    states: dict[int, Any] = {}
    for msg in valid('state', raw_states, lambda s: check_state(s, m)):
        if int(msg.seq) in states:
            skip('state', 'duplicate')
        else:
            states[int(msg.seq)] = msg
    commands: dict[int, Any] = {}
    followed.discard(0)
    for msg in valid('command', raw_commands, lambda c: check_command(c, m)):
        seq = int(msg.state_seq)
        if seq in commands:
            skip('command', 'duplicate')
            if (int(getattr(msg, 'controller_id', 0)) in followed
                    and int(getattr(commands[seq], 'controller_id', 0)) not in followed):
                commands[seq] = msg
        else:
            commands[seq] = msg
    updates = _admitted(valid('update', updates_in, lambda u: _check_update(u, m, dof)),
                        scenario, m, dof, skip, linkage)
    vt_path: dict[int, Any] = {}
    for msg in valid('path', paths_in, lambda v: check_vt_path(v, m)):
        _, path_seqs, poses = check_vt_path(msg, m)
        vt_path.update(zip(path_seqs, poses, strict=True))
    for seq in _foreign_seqs(states):
        del states[seq]
        skip('state', 'foreign_seq')
    run_seqs = sorted(s for s, m in states.items() if not m.status & _WATCHDOG)
    if not run_seqs:
        raise BagError(f'{p}: no device state of a running loop (controller never engaged?)')
    k0 = run_seqs[0]
    seqs = np.array(sorted(s for s in states if s >= k0))
    first = states[k0]
    modes = [int(c.mode) for s, c in commands.items() if s >= k0]
    mode = max(set(modes), key=modes.count) if modes else 2
    contacts = any(float(getattr(u, 'contact_stiffness', 0.0)) > 0.0 for u in updates)
    trace = Trace.empty(len(seqs), m, dof, contacts, mode=_MODE_LABELS.get(mode, str(mode)),
                        scenario=scenario, dt=0.001, source='graph', bag=str(p),
                        truncated=bool(bag.truncated))
    t0 = _stamp(first.header)
    row_of = {int(s): i for i, s in enumerate(seqs)}
    for i, s in enumerate(seqs):
        st = states[int(s)]
        values: dict[str, Any] = dict(
            device_pose=st.pose, device_twist=st.twist, hand_wrench=st.hand_wrench,
            applied=st.applied_wrench, status=int(st.status))
        cmd = commands.get(int(s))
        if cmd is not None:
            values.update(command=cmd.wrench, lmi_pose=cmd.vt_pose,
                          lmi_constraint_count=int(cmd.constraint_count))
            if contacts:
                env = env_wrench(cmd, m)
                values['env_wrench'] = np.zeros(m) if env is None else env
        trace.record(i, t=_stamp(st.header) - t0, **values)
        trace.seq[i] = int(s)
    # VE samples at known rows, interpolated in time between them.
    known: dict[int, Any] = {}
    for u in updates:
        s = int(u.hand_input_seq)
        row = row_of.get(s + 1) if s > 0 else (0 if s == 0 else None)
        if row is not None and (s > 0 or row not in known):
            known[row] = u
    if known:
        rows = np.array(sorted(known))
        t_known = trace.t[rows]
        last = rows[-1]
        poses = np.array([known[r].hand_pose for r in rows])
        qs = np.array([known[r].q for r in rows]) if dof else np.zeros((len(rows), 0))
        span = slice(0, last + 1)
        for j in range(m):
            trace.columns['vt_pose'][span, j] = np.interp(trace.t[span], t_known, poses[:, j])
        for j in range(qs.shape[1]):
            trace.columns['q'][span, j] = np.interp(trace.t[span], t_known, qs[:, j])
        if vt_path:
            # The VE's own VT hand at every cycle it reported (exact, no interpolation).
            vt = trace.columns['vt_pose']
            vt[1:] = np.nan
            for i, s in enumerate(seqs[1:], start=1):
                if int(s) - 1 in vt_path:
                    vt[i] = vt_path[int(s) - 1]
        trace.hold_constraint_counts(rows, [int(known[r].constraint_count) for r in rows])
        if contacts:
            # The VE's deepest contact and energy balance at each update, held until the next
            # one (the VE reports them at its rate), NaN after the last.
            trace.hold_contacts(rows, [contact_depth(known[r].contact_gaps) for r in rows],
                                [float(known[r].contact_energy) for r in rows])
    figures = loop_figures(states, commands, seqs, diags)
    figures['ve_update_rate_hz'] = _update_rate(trace.t, sorted(known))
    return GraphRun(trace, figures, diags, skipped, graph.graph_id, dict(graph.foreign),
                    {n: sorted(t) for n, t in sorted(publishers.items())})


def _update_rate(t: np.ndarray, rows: list[int]) -> float:
    """The VE's LMI update rate (Hz) over the run, on the device's clock: updates that
    consumed a hand input of the run, per second between the first and the last of them."""
    rows = [r for r in rows if r > 0]
    if len(rows) < 2 or t[rows[-1]] <= t[rows[0]]:
        return math.nan
    return (len(rows) - 1) / float(t[rows[-1]] - t[rows[0]])


def _most_common(values: list[int]) -> int:
    return max(set(values), key=values.count) if values else 0


def _check_update(msg: Any, m: int, dof: int) -> None:
    """The fields of an ``LmiUpdate`` the trace uses: integers, VT hand pose, q, contacts."""
    check_update_header(msg, m, dof)
    array(msg, 'hand_pose', m)
    array(msg, 'q', dof)
    check_update_contacts(msg, dof)


def _admitted(updates: list[Any], scenario: str, m: int, dof: int,
              skip: Callable[[str, str], None], linkage: Linkage | None = None) -> list[Any]:
    """The updates the controller's checks admit, in the bag's order
    (:class:`~haptic_topology.control.admission.UpdateAdmission`: the model check against
    the scenario's linkage (``linkage``, else loaded by the name ``scenario``) when it
    matches ``dof`` and ``m``; the
    consumed input never going back): a sender that copied the graph id is skipped as
    ``update_model`` / ``update_continuity``. A bag records no publisher, so a seq going
    back is not refused here."""
    dyn = None
    if linkage is None and scenario:
        linkage = load_scenario(scenario).linkage
    if linkage is not None:
        if linkage.dof == dof and linkage.task.dim == m and not linkage.loops:
            dyn = LinkageDynamics(linkage)
    task = TaskSpace.PLANAR if m == TaskSpace.PLANAR.dim else TaskSpace.SPATIAL
    admission = UpdateAdmission(dyn)
    out = []
    for u in updates:
        try:
            admission.admit(UpdateFields.from_msg(u, task, dof))
        except MessageError as exc:
            skip('update', exc.reason)
            continue
        out.append(u)
    return out


def _foreign_seqs(states: dict[int, Any]) -> list[int]:
    """Seqs of the states outside the run (module doc: groups split at gaps larger than
    MAX_SEQ_GAP; the run is the largest group with a running state)."""
    seqs = sorted(states)
    if not seqs:
        return []
    cuts = [i + 1 for i, (a, b) in enumerate(zip(seqs[:-1], seqs[1:], strict=True))
            if b - a > MAX_SEQ_GAP]
    groups = [seqs[a:b] for a, b in zip([0, *cuts], [*cuts, len(seqs)], strict=True)]
    running = [g for g in groups if any(not states[s].status & _WATCHDOG for s in g)]
    run = max(running or groups, key=len)
    return [s for g in groups if g is not run for s in g]


def _float(values: dict[str, str], key: str) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return math.nan


def loop_figures(states: dict[int, Any], commands: dict[int, Any], seqs: np.ndarray,
                 diags: dict[str, dict[str, str]]) -> dict[str, float]:
    """Loop figures from the device driver's diagnostics and from the bag's stamps."""
    out: dict[str, float] = {}
    dev = diags.get(_DEVICE_STATUS, {})
    for key in ('answered_fraction', 'answered_or_previous_fraction', 'round_trip_p50_ms',
                'round_trip_p99_ms', 'round_trip_max_ms', 'rate_hz', 'period_p99_ms',
                'overruns', 'max_consecutive_missed'):
        out[f'device_{key}'] = _float(dev, key)
    out['max_consecutive_missed'] = out.pop('device_max_consecutive_missed')
    # How late the loop woke after its deadlines: a loop paced by deadlines (the hosted
    # layouts) reports it; the separate layout's executor timers do not.
    for key in ('wake_late_p50_ms', 'wake_late_p99_ms', 'wake_late_max_ms'):
        if key in dev:
            out[f'device_{key}'] = _float(dev, key)
    in_time = 0
    total = 0
    for a, b in zip(seqs[:-1], seqs[1:], strict=True):
        if b != a + 1:
            continue
        total += 1
        cmd = commands.get(int(a))
        if cmd is not None and _stamp(cmd.header) < _stamp(states[int(b)].header):
            in_time += 1
    out['bag_answered_fraction'] = in_time / total if total else math.nan
    # Every state and every command of the run in the bag (the idle ones before engagement
    # too), as a count of the bag's messages gives them; the trace's rows start at the first
    # running state.
    out['bag_states'] = float(len(states))
    out['bag_commands'] = float(len(commands))
    return out


def format_loop(rows: list[tuple[str, dict[str, float]]]) -> str:
    """A small table of loop figures, one row per run label."""
    cols = [('device_answered_fraction', 'answered [%]', 100.0, '{:.2f}'),
            ('bag_answered_fraction', 'answered, bag [%]', 100.0, '{:.2f}'),
            ('device_round_trip_p50_ms', 'rtt p50 [ms]', 1.0, '{:.3f}'),
            ('device_round_trip_p99_ms', 'rtt p99 [ms]', 1.0, '{:.3f}'),
            ('device_period_p99_ms', 'period p99 [ms]', 1.0, '{:.3f}'),
            ('bag_states', 'states', 1.0, '{:.0f}')]
    head = ['run'] + [c[1] for c in cols]
    cells = [head]
    for label, fig in rows:
        cells.append([label] + [fmt.format(fig.get(k, math.nan) * scale)
                                for k, _, scale, fmt in cols])
    widths = [max(len(r[i]) for r in cells) for i in range(len(head))]
    lines = ['  '.join(c.ljust(widths[i]) if i == 0 else c.rjust(widths[i])
                       for i, c in enumerate(r)) for r in cells]
    lines.insert(1, '  '.join('-' * w for w in widths))
    return '\n'.join(lines)
