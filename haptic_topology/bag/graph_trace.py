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

Loop figures: the device driver's own counts from its last ``/diagnostics`` status
(answered fraction, round trip p50/p99), and an estimate from the bag alone: the fraction of
states k whose command was computed (``DeviceCommand.header.stamp``) before state k+1 was
stamped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.bag.reader import Progress, decoder, iter_messages, open_bag, require_types
from haptic_topology.errors import BagError
from haptic_topology.msgdefs import type_name
from haptic_topology.sim.trace import Trace

_WATCHDOG = 4
#: Topic suffix -> type the graph publishes on it (a bag without any of them is foreign).
GRAPH_TYPES = {
    'haptic/device/state': type_name('DeviceState'),
    'haptic/device/command': type_name('DeviceCommand'),
    'haptic/hand': type_name('HandInput'),
    'haptic/lmi/update': type_name('LmiUpdate'),
}
#: Topics the graph also publishes that newer bags have (not required to read a bag).
PATH_TOPIC = 'haptic/ve/path'
_MODE_LABELS = {0: 'penalty', 1: 'acceleration_only', 2: 'zero'}


@dataclass
class GraphRun:
    """A recorded run: its trace and loop figures (``loop`` keys are documented above)."""

    trace: Trace
    loop: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def read_graph_bag(path: str | Path, scenario: str = '', dof: int | None = None,
                   progress: Progress | None = None) -> GraphRun:
    """Read the bag ``path`` (see module doc); ``progress`` gets the fraction read.

    A truncated bag (recorder killed) is read up to its last complete chunk; the trace's
    ``meta['truncated']`` is then True.
    """
    bag = open_bag(path)
    p = bag.path
    require_types(bag, GRAPH_TYPES)
    decode = decoder()
    states: dict[int, Any] = {}
    commands: dict[int, Any] = {}
    updates: list[Any] = []
    vt_path: dict[int, Any] = {}
    diags: dict[str, dict[str, str]] = {}
    for raw in iter_messages(bag, progress=progress):
        topic = raw.topic
        msg: Any
        if topic.endswith('haptic/device/state'):
            msg = decode(raw)
            states[int(msg.seq)] = msg
        elif topic.endswith('haptic/device/command'):
            msg = decode(raw)
            commands.setdefault(int(msg.state_seq), msg)
        elif topic.endswith('haptic/lmi/update'):
            updates.append(decode(raw))
        elif topic.endswith(PATH_TOPIC):
            msg = decode(raw)
            m_path = int(msg.task_dim)
            poses = np.asarray(msg.hand_pose, dtype=float).reshape(-1, max(m_path, 1))
            for s_in, pose in zip(msg.hand_input_seqs, poses, strict=True):
                vt_path[int(s_in)] = pose
        elif topic == '/diagnostics':
            msg = decode(raw)
            for st in msg.status:
                diags[st.name] = {kv.key: kv.value for kv in st.values}
    run_seqs = sorted(s for s, m in states.items() if not m.status & _WATCHDOG)
    if not run_seqs:
        raise BagError(f'{p}: no device state of a running loop (controller never engaged?)')
    k0 = run_seqs[0]
    seqs = np.array(sorted(s for s in states if s >= k0))
    first = states[k0]
    m = int(first.task_dim)
    if dof is None:
        dof = int(updates[0].dof) if updates else 0
    modes = [int(c.mode) for s, c in commands.items() if s >= k0]
    mode = max(set(modes), key=modes.count) if modes else 2
    trace = Trace.empty(len(seqs), m, dof, mode=_MODE_LABELS.get(mode, str(mode)),
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
        counts = np.array([int(known[r].constraint_count) for r in rows])
        idx = np.searchsorted(rows, np.arange(len(seqs)), side='right') - 1
        trace.columns['constraint_count'][:] = np.where(idx >= 0, counts[np.maximum(idx, 0)], 0)
    return GraphRun(trace, loop_figures(states, commands, seqs, diags), diags)


def loop_figures(states: dict[int, Any], commands: dict[int, Any], seqs: np.ndarray,
                 diags: dict[str, dict[str, str]]) -> dict[str, float]:
    """Loop figures from the device driver's diagnostics and from the bag's stamps."""
    out: dict[str, float] = {}
    dev = diags.get('device_driver: loop', {})
    for key in ('answered_fraction', 'answered_or_previous_fraction', 'round_trip_p50_ms',
                'round_trip_p99_ms', 'round_trip_max_ms', 'rate_hz', 'period_p99_ms',
                'overruns'):
        try:
            out[f'device_{key}'] = float(dev[key])
        except (KeyError, ValueError):
            out[f'device_{key}'] = math.nan
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
    out['bag_states'] = float(len(seqs))
    out['bag_commands'] = float(sum(1 for s in seqs if int(s) in commands))
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
