"""The controller's energy account row by row for a recorded run, reconstructed offline.

A bag holds the controller's commands, but its energy account (the work at the device port,
the passivity observer, the passivity controller's damping: :mod:`haptic_topology.control.
passivity`) only at the run's end (the controller's last ``/diagnostics`` status). The
controller is deterministic: fed the recorded device states and LMI updates in the order it
took them (:func:`~haptic_topology.bag.controller_check.controller_plan`, the plan of
``replay --check-controller``), the same core objects compute the same commands bit for
bit. :func:`energy_series` does that without ROS, in this process: it builds the controller
loop as ``lmi_controller`` does (:func:`~haptic_topology.sim.lockstep.build_controller_loop`
with the bag's scenario and, from the controller's last ``/diagnostics`` status, its mode,
``k_tc``, ``b_tc`` and whether the passivity controller was on; the other parameters are
``lmi_controller``'s defaults), feeds it the plan's items and after every state reads the
account, the same figures ``simulate`` writes into its trace
(:data:`~haptic_topology.sim.trace.ENERGY_FLOATS`: ``port_work``, ``passivity_observer``,
``passivity_damping``).

Every replayed command is compared with the recorded one, exactly (mode and every wrench
entry, ``==``): the series is the run's only if each of them is. At the first difference the
reconstruction stops and the series is refused with one line naming the state seq
(:attr:`EnergySeries.refused`); nothing of it is drawn or summed. A difference means the
bag's controller ran with other parameters than the ones read (a live change of ``k_tc``,
a params file other than the defaults), other code, or that the bag was altered. A bag
that lacks an LMI update some recorded command names (its recorder received the update after
the command and was stopped before writing it: a cut bag) has its series end before that
command (:attr:`EnergySeries.unchecked`): the controller's inputs from there on are not in
the bag.

Memory: the plan's arrays (about 70 bytes a recorded command) and the rows a plot draws
(:class:`~haptic_topology.sim.trace_stats.PlotRows`, at most
:data:`~haptic_topology.sim.trace_stats.PLOT_ROWS` buckets); the messages are read from the
bag as they are fed. Time: one decode of every state and update and one controller cycle per
state.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.bag.controller_check import controller_plan
from haptic_topology.bag.reader import Bag, open_bag
from haptic_topology.bag.replay import UPDATE
from haptic_topology.config.resolve import resolve_lmi_controller
from haptic_topology.config.settings import LmiControllerSettings
from haptic_topology.control.loop import StateSample
from haptic_topology.control.update_message import lmi_from_msg
from haptic_topology.errors import BagError, ConfigError, MessageError
from haptic_topology.messages.check import check_state
from haptic_topology.messages.definitions import typestore_with_haptic_msgs
from haptic_topology.sim.lockstep import build_controller_loop
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace
from haptic_topology.sim.trace_io import CHUNK_ROWS
from haptic_topology.sim.trace_stats import PlotRows
from haptic_topology.vocabulary import ControlMode

#: ``analyze`` reconstructs the series by default for bags of at most this many device
#: states (10 minutes at 1 kHz); ``--energy`` for longer ones, ``--no-energy`` never.
AUTO_STATES = 600_000


@dataclass
class EnergySeries:
    """The reconstructed account (module doc). ``refused``: why there is none (one line),
    else None; ``rows``: the rows of the series (the recorded commands from ``first_seq``
    on), ``compared``: the commands compared (every recorded command whose state is in the
    bag); the figures of ``simulate``'s summary over the rows (``observer_min``, ...);
    ``plot``: the rows the energy figure draws; ``account``: the account after the last
    state (:meth:`~haptic_topology.control.passivity.EnergyAccount.summary`); ``seconds``:
    the wall time the reconstruction took; ``unchecked``: the recorded commands at the end
    whose inputs are not all in the bag, not reconstructed
    (:attr:`~haptic_topology.bag.controller_check.ControllerPlan.unchecked`), the first of
    them answering state ``unchecked_from`` and naming LMI update ``absent_update``."""

    refused: str | None = None
    rows: int = 0
    compared: int = 0
    observer_min: float = math.inf
    observer_final: float = math.nan
    damping_rows: int = 0
    damping_first_s: float | None = None
    plot: Trace | None = None
    account: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    unchecked: int = 0
    unchecked_from: int = -1
    absent_update: int = -1

    @property
    def exact(self) -> bool:
        return self.refused is None and self.rows > 0

    def figures(self) -> dict[str, Any]:
        """The energy figures of ``simulate``'s summary
        (:meth:`~haptic_topology.sim.trace.SummaryStats.energy_result`) over the series."""
        return {'passivity_observer_min_j': self.observer_min,
                'passivity_observer_final_j': self.observer_final,
                'passivity_rows': self.damping_rows,
                'passivity_first_s': self.damping_first_s}


def _settings(scenario: str, controller: dict[str, str]) -> LmiControllerSettings:
    """``lmi_controller``'s settings as the controller's last status reports them (mode,
    gains, passivity on/off); the defaults otherwise."""
    values: dict[str, Any] = {'scenario': scenario}
    if controller.get('mode'):
        values['mode'] = controller['mode']
    for key in ('k_tc', 'b_tc'):
        if controller.get(key):
            values[key] = float(controller[key])
    on = controller.get('passivity_controller')
    if on in ('on', 'off'):
        values['passivity'] = 'enabled' if on == 'on' else 'disabled'
    return LmiControllerSettings.from_values(values)


class _Writable:
    """A decoded message whose arrays come out as writable copies: the bag reader's are
    read-only views of the bytes, which the compiled LMI code does not take (rclpy's are
    ``array.array``, copied by the checks alike)."""

    def __init__(self, msg: Any) -> None:
        self._msg = msg

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._msg, name)
        return value.copy() if isinstance(value, np.ndarray) else value


class _Rows:
    """The series' rows in chunks of :data:`CHUNK_ROWS`, given to a
    :class:`~haptic_topology.sim.trace_stats.PlotRows` (the energy figure's rows), with the
    trace's work integrals (``work_integral`` per axis, ``hand_work_integral``, J) summed
    over every row, so a plot of sampled rows draws them exactly."""

    def __init__(self, template: Trace, rows: int, plot: PlotRows | None) -> None:
        self.template = template
        self.m = template.task_dim
        self.plot = plot
        if plot is not None:
            plot.begin(template, rows)
        self.chunk = self._new()
        self.k = 0
        self.t_last = math.nan
        self.work = np.zeros(self.m)
        self.hand = 0.0

    def _new(self) -> Trace:
        tr = Trace.empty(CHUNK_ROWS, self.m, int(self.template.meta['dof']),
                         **{k: v for k, v in self.template.meta.items()
                            if k not in ('task_dim', 'dof')})
        tr.columns['work_integral'] = np.full((CHUNK_ROWS, self.m), np.nan)
        tr.columns['hand_work_integral'] = np.full(CHUNK_ROWS, np.nan)
        return tr

    def add(self, seq: int, t: float, twist: np.ndarray, hand: np.ndarray,
            applied: np.ndarray, command: np.ndarray, status: int, work: float,
            observer: float, damping: float) -> None:
        dt = t - self.t_last
        self.t_last = t
        if math.isfinite(dt):
            p = applied * twist * dt
            if np.all(np.isfinite(p)):
                self.work += p
            h = float(np.dot(hand, twist)) * dt
            if math.isfinite(h):
                self.hand += h
        tr, k = self.chunk, self.k
        tr.t[k], tr.seq[k] = t, seq
        c = tr.columns
        c['device_twist'][k], c['hand_wrench'][k], c['applied'][k] = twist, hand, applied
        c['command'][k], c['status'][k] = command, status
        c['port_work'][k], c['passivity_observer'][k] = work, observer
        c['passivity_damping'][k] = damping
        c['work_integral'][k], c['hand_work_integral'][k] = self.work, self.hand
        self.k += 1
        if self.k == CHUNK_ROWS:
            self.flush()

    def flush(self) -> None:
        if self.k and self.plot is not None:
            self.plot.add(self.chunk.take(slice(0, self.k)))
        self.chunk, self.k = self._new(), 0

    def end(self) -> Trace | None:
        self.flush()
        if self.plot is None:
            return None
        self.plot.end()
        return self.plot.trace


def energy_series(bag_path: str | Path, controller: dict[str, str] | None = None,
                  first_seq: int | None = None, plot: bool = True,
                  scenario: str = '') -> EnergySeries:
    """Reconstruct the energy account of the bag ``bag_path`` row by row (module doc).

    ``controller``: the controller's last ``/diagnostics`` key/values (mode, ``k_tc``,
    ``b_tc``, ``passivity_controller``; None or empty: ``lmi_controller``'s defaults);
    ``first_seq``: the state seq of the bag trace's first row (``t = 0`` there; None: the
    first state with a recorded command); ``plot``: keep the rows of the energy figure;
    ``scenario``: default the bag's."""
    started = time.perf_counter()
    try:
        out = _replay(open_bag(bag_path), dict(controller or {}), first_seq, plot, scenario)
    except BagError as exc:        # a message the plan cannot decode, ...
        out = EnergySeries(refused=f'the bag cannot be replayed: {exc}')
    out.seconds = time.perf_counter() - started
    return out


def _replay(bag: Bag, controller: dict[str, str], first_seq: int | None, plot: bool,
            scenario: str) -> EnergySeries:
    """:func:`energy_series` of an open bag."""
    cp = controller_plan(bag)
    name = scenario or cp.scenario
    if not name:
        return EnergySeries(refused='no scenario in the bag\'s metadata: the controller '
                                    'cannot be rebuilt')
    try:
        sc = load_scenario(name)
        c = resolve_lmi_controller(_settings(name, controller), sc)
    except ConfigError as exc:
        return EnergySeries(refused=f'the controller cannot be rebuilt: {exc}')
    loop = build_controller_loop(sc, c.mode, c.guard, c.max_dt, c.resync_max_jump, None,
                                 c.gains, c.passivity)
    account = loop.ctrl.energy
    task, dof = sc.linkage.task, sc.lmi_dof
    direction = sc.linkage.constraints.penalty_direction
    store = typestore_with_haptic_msgs()
    template = Trace.empty(0, task.dim, dof, energy=True, mode=c.mode.label,
                           scenario=sc.name, dt=sc.dt, task=task.value, source='graph',
                           bag=str(bag.path))
    rows = _Rows(template, int(cp.seqs.size), PlotRows() if plot else None)
    out = EnergySeries()
    t0: float | None = None
    items = cp.items()
    try:
        for item in items:
            msg = _Writable(store.deserialize_cdr(item.data, item.msgtype))
            if item.topic.endswith(UPDATE):
                try:
                    snap = lmi_from_msg(msg, task, dof, direction)
                except MessageError:
                    continue                # lmi_controller drops it too
                loop.on_update(snap)
                continue
            try:
                seq, stamp, pose, twist, f_h, applied, status = check_state(msg, task.dim)
            except MessageError:
                continue
            ans = loop.on_state(StateSample(seq, stamp, pose, twist, f_h, status))
            ci = cp.command(seq)
            if ci < 0:
                continue
            out.compared += 1
            rec = cp.recorded_wrench(ci)
            if ans is None:
                out.refused = f'state {seq}: the replayed controller did not answer it'
                break
            if int(ans.out.mode) != int(cp.modes[ci]) or not np.array_equal(
                    ans.out.wrench, rec):
                recorded = ControlMode(int(cp.modes[ci]))
                what = (f'mode {ans.out.mode.label}, recorded {recorded.label}'
                        if ans.out.mode != recorded else
                        f'max |difference| {float(np.max(np.abs(ans.out.wrench - rec))):.3g}'
                        if ans.out.wrench.shape == rec.shape else
                        f'{ans.out.wrench.size} wrench entries, recorded {rec.size}')
                out.refused = (f'state {seq}: the replayed command differs from the recorded '
                               f'one ({what}): not the recorded controller')
                break
            if first_seq is not None and seq < first_seq:
                continue
            t0 = stamp if t0 is None else t0
            t = stamp - t0
            observer, damping = account.observer, account.damping
            rows.add(seq, t, twist, f_h, applied, ans.out.wrench, status, account.work,
                     observer, damping)
            out.rows += 1
            out.observer_min = min(out.observer_min, observer)
            out.observer_final = observer
            if damping > 0.0:
                out.damping_rows += 1
                if out.damping_first_s is None:
                    out.damping_first_s = t
    finally:
        getattr(items, 'close', lambda: None)()     # the plan's reader, at a refusal
    if out.refused is not None:
        return out
    if not out.rows:
        out.refused = 'no recorded command to compare'
        return out
    out.plot = rows.end()
    out.account = account.summary()
    skipped = cp.seqs[cp.unchecked]
    if skipped.size:
        out.unchecked, out.unchecked_from = int(skipped.size), int(skipped[0])
        out.absent_update = cp.absent_update
    return out
