"""Offline lock-step simulation of the whole haptic loop (the paper's Fig. 5 diagram).

The same loop objects as the node graph, wired without messages, in the order the lock-step
graph runs them (``device_driver`` with ``clock: lockstep``). Steps 1-2 are one
:class:`~haptic_topology.device.hosted.HostedCycle`, the object the hosted ``device_driver``
runs in its loop thread; the VE's updates are offered to it and applied at the start of the
next step, before that step's state:

1. :class:`~haptic_topology.device.loop.DeviceLoop` ticks the simulated maglev
   (:class:`~haptic_topology.device.backend.SimMaglevBackend`: eq. 9 over the last period with
   the newest command and the user's wrench) and publishes state k at ``t_k = k * dt``;
2. :class:`~haptic_topology.control.loop.ControllerLoop` answers it: LMI step, ``F_pc``,
   eq. 14 or eq. 10, sync guard (``lmi_controller``); the device takes the command;
3. the VE (:class:`~haptic_topology.sim.ve.VirtualEnvironment`) consumes the hand input
   (eq. 2) and, after every ``update_period``-th input, sends an LMI update (eqs. 17-19)
   that the controller takes before the next state (``ve_sim``).

Before the run the device idles once (state flagged IDLE, answered in the controller's mode
once it has synced to the VE's initial state), which engages it, exactly as in the graph.
Times are integer nanoseconds turned into seconds as a ROS stamp is
(:func:`~haptic_topology.device.loop.ns_to_seconds`), so the lock-step graph, whose messages
carry those stamps, computes with the same numbers. Deterministic: no clocks, no threads.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from haptic_topology.control.controller import HapticController
from haptic_topology.control.laws import ControlGains
from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.control.loop import Answer, ControllerLoop, HandSample
from haptic_topology.control.passivity import PassivityConfig
from haptic_topology.control.safety import SyncGuard, SyncGuardConfig
from haptic_topology.device.backend import BackendConfig, SimMaglevBackend
from haptic_topology.device.hosted import HostedCycle, state_sample
from haptic_topology.device.loop import DeviceLoop, DeviceTick, ns_to_seconds, period_ns
from haptic_topology.device.maglev import DeviceParams
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig
from haptic_topology.dynamics.contacts import ContactModel
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.sim.scenario import Scenario
from haptic_topology.sim.trace import Trace, contact_depth
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import ControlMode

#: Defaults of the nodes' safety parameters (config/haptic_topology.yaml).
MAX_DT = 0.05
RESYNC_MAX_JUMP = 1.0


def build_controller_loop(sc: Scenario, mode: ControlMode,
                          guard: SyncGuardConfig | None = None, max_dt: float = MAX_DT,
                          max_jump: float = RESYNC_MAX_JUMP,
                          update_period: int | None = None,
                          gains: ControlGains | None = None,
                          passivity: PassivityConfig | None = None) -> ControllerLoop:
    """The controller-side loop of scenario ``sc`` (what ``lmi_controller`` builds);
    ``gains``: default the scenario's; ``passivity``: default the scenario's, else off."""
    ctrl = HapticController(sc.linkage.task, mode, gains or sc.gains, sc.device.mass,
                            sc.device.christoffel, sc.lmi_model, sc.vt_coupling,
                            passivity or sc.passivity, sc.dt)
    return ControllerLoop(ctrl, SyncGuard(guard or SyncGuardConfig(), sc.dt), sc.dt, max_dt,
                          max_jump, sc.device.wrench_limit, update_period)


def initial_device_pose(sc: Scenario) -> np.ndarray:
    """Where the device starts: the VT hand at ``q0`` plus the scenario's offset."""
    return LinkageDynamics(sc.linkage).hand_pose(sc.q0) + sc.device_offset


def build_device_loop(sc: Scenario) -> DeviceLoop:
    """The device-side loop of scenario ``sc`` as ``simulate`` runs it: the simulated maglev
    (with the scenario's user) at its initial pose, activated, default watchdog."""
    backend = SimMaglevBackend()
    backend.configure(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {},
                                    sc.source))
    backend.activate()
    return DeviceLoop(backend, sc.device.wrench_limit,
                      CommandWatchdog(WatchdogConfig(), sc.linkage.task.dim), sc.dt)


def virtual_environment(sc: Scenario) -> VirtualEnvironment:
    """The VE of scenario ``sc`` at its initial state, as ``simulate`` runs it."""
    dyn = LinkageDynamics(sc.linkage)
    contacts = (None if sc.contacts is None
                else ContactModel(dyn.model, sc.linkage, sc.contacts))
    return VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step,
                              coupling=sc.coupling_gains(), contacts=contacts)


@dataclass(frozen=True)
class SimStep:
    """What :func:`simulate` did in step ``k`` (time ``t``, s), as its observer sees it: the
    device tick, the controller's answer, the VE just after it took the step's hand input (if
    ``answer.hand`` is not None) and the controller loop (its controller: ``controller.ctrl``).
    The objects are the simulation's own: an observer reads them and changes nothing."""

    k: int
    t: float
    tick: DeviceTick
    answer: Answer
    ve: VirtualEnvironment
    controller: ControllerLoop


def simulate(scenario: Scenario, mode: ControlMode | None = None,
             observer: Callable[[SimStep], None] | None = None,
             passivity: PassivityConfig | None = None,
             gains: ControlGains | None = None, device: DeviceParams | None = None,
             ve_delay: int = 0, device_delay: int = 0) -> Trace:
    """Run ``scenario`` with ``mode`` (default: the scenario's) and return its trace, with
    the controller's energy account in its columns
    (:data:`~haptic_topology.sim.trace.ENERGY_FLOATS`) and its final figures in
    ``meta['energy_account']``
    (:meth:`~haptic_topology.control.passivity.EnergyAccount.summary`). ``passivity``: the
    passivity controller (default: the scenario's, else off); ``gains``: default the
    scenario's.

    ``observer``: called once per step, after the VE took the step's hand input and before
    the trace records the step, with a :class:`SimStep` (for figures the trace does not hold,
    e.g. ``bench/penalty_direction.py``); it must not change what it is given.

    Another device and links (for the Z-width maps, :mod:`haptic_topology.sim.zwidth`):
    ``device``: the simulated device's own parameters (eq. 9's ``M_d``, friction, sensor,
    wrench limit) where they differ from the scenario's ``device``, which the controller
    keeps as its model (as with a real device); ``ve_delay``: device cycles each hand input
    takes to the VE and each LMI update back (a VE on another host, one way);
    ``device_delay``: device cycles between the controller's answer and the device taking it
    (a device behind a link: the round trip of state and command). Deterministic: the
    delays are whole cycles, without jitter or loss."""
    if ve_delay < 0 or device_delay < 0:
        raise ValueError(f've_delay and device_delay must be >= 0 cycles, got {ve_delay} and '
                         f'{device_delay}')
    sc = scenario
    mode = sc.mode if mode is None else mode
    task = sc.linkage.task
    ve = virtual_environment(sc)
    dyn = ve.dyn
    # With the VE behind a link the controller does not wait for its updates (as on a
    # wall clock): they come ve_delay cycles late.
    cycle = HostedCycle(build_device_loop(sc if device is None else replace(sc, device=device)),
                        build_controller_loop(sc, mode, update_period=None if ve_delay
                                              else sc.update_period,
                                              gains=gains, passivity=passivity))
    account = cycle.controller.ctrl.energy
    first = ve.snapshot(seq=0)
    cycle.offer_update(first)
    step_ns = period_ns(sc.dt)

    answers: deque[Answer] = deque()        # answers on their way to the device

    def step(t: float) -> tuple[DeviceTick, Answer]:
        if not device_delay:
            done = cycle.step(t, sc.dt, t)
            if done.answer is None:
                raise RuntimeError(f'controller did not answer state {done.tick.seq}')
            return done.tick, done.answer
        cycle.apply_updates()
        tick = cycle.device.tick(t, sc.dt)
        ans = cycle.controller.on_state(state_sample(tick, t))
        if ans is None:
            raise RuntimeError(f'controller did not answer state {tick.seq}')
        answers.append(ans)
        if len(answers) > device_delay:
            late = answers.popleft()
            cycle.device.on_command(late.state_seq, int(late.out.mode), late.out.wrench, t,
                                    env_wrench=late.out.env_wrench)
        return tick, ans

    # Engagement: one idle state, answered in the controller's mode (behind a device link:
    # idle states until the answer has come).
    step(0.0)
    for _ in range(device_delay):
        if cycle.device.engaged:
            break
        step(0.0)
    n = int(round(sc.duration / sc.dt)) + 1
    trace = Trace.empty(n, task.dim, dyn.dof, sc.contacts is not None, mode=mode.label,
                        scenario=sc.name, dt=sc.dt, task=task.value, energy=True,
                        **({'linkage_file': sc.linkage_file} if sc.linkage_file else {}))
    vt_pose = dyn.hand_pose(ve.q)
    inputs = 0
    update_seq = 1
    to_ve: deque[tuple[int, HandSample]] = deque()     # (due step, input) behind the VE link
    to_ctrl: deque[tuple[int, LmiSnapshot]] = deque()  # (due step, update) on the way back
    # (row, depth m, energy J) per update; the VE's initial state describes the first row
    contact_rows = [(0, _depth(first), first.contact_energy)]
    count_rows = [(0, first.constraint_count)]      # (row, t) per update, as the graph's
    for k in range(n):
        t = ns_to_seconds(k * step_ns)
        if cycle.waiting_for_update():
            raise RuntimeError(f'state {k}: the VE update was not taken')
        tick, ans = step(t)
        while to_ctrl and to_ctrl[0][0] <= k:
            cycle.offer_update(to_ctrl.popleft()[1])
        if ans.hand is not None:
            to_ve.append((k + ve_delay, ans.hand))
        hand = to_ve.popleft()[1] if to_ve and to_ve[0][0] <= k else None
        if hand is not None:
            ve.push_input(hand.state_seq, hand.stamp, hand.vt_wrench)
            inputs += 1
        if observer is not None:
            observer(SimStep(k, t, tick, ans, ve, cycle.controller))
        path = ve.take_path()
        if path:
            vt_pose = path[-1][1]
        r = tick.reading
        trace.record(k, t=t, device_pose=r.pose, device_twist=r.twist,
                     hand_wrench=r.hand_wrench, command=ans.out.wrench, applied=tick.applied,
                     vt_pose=vt_pose, lmi_pose=ans.out.vt_pose, q=ve.q,
                     lmi_constraint_count=ans.out.constraint_count, status=int(tick.status))
        trace.record(k, t=t, port_work=account.work, passivity_observer=account.observer,
                     passivity_damping=account.damping)
        if ve.contacts is not None:
            trace.record_env_wrench(k, ans.out.env_wrench)
        if hand is not None and inputs % sc.update_period == 0:
            # Applied at the start of the next step, before its state: as the graph does.
            snap = ve.snapshot(seq=update_seq)
            if ve_delay:
                to_ctrl.append((k + ve_delay, snap))
            else:
                cycle.offer_update(snap)
            update_seq += 1
            # It describes the VE after the input before this one: at this row's state.
            contact_rows.append((k, _depth(snap), snap.contact_energy))
            count_rows.append((k, snap.constraint_count))
    trace.hold_constraint_counts([r for r, _ in count_rows], [c for _, c in count_rows])
    if ve.contacts is not None:
        rows, depth, energy = zip(*contact_rows, strict=True)
        trace.hold_contacts(np.array(rows, dtype=int), list(depth), list(energy))
    trace.meta['energy_account'] = account.summary()
    return trace


def _depth(snap: LmiSnapshot) -> float:
    """The deepest contact (m) an LMI update reports (0 without obstacles)."""
    return 0.0 if snap.contacts is None else contact_depth(snap.contacts.gaps)
