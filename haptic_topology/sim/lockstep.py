"""Offline lock-step simulation of the whole haptic loop (the paper's Fig. 5 diagram).

One device period per step, in the order the ROS graph runs it:

1. the device integrates eq. 9 over the last period with the newest command and the user's
   wrench (``device_driver``), and the user's wrench at the new state is measured;
2. the controller answers the state: LMI step, ``F_pc``, eq. 14 or eq. 10 (``lmi_controller``);
3. the VE consumes the hand input (eq. 2) and, every ``update_period`` cycles, sends an LMI
   update (eqs. 17-19) that re-syncs the controller (``ve_sim``).

The same core objects (:class:`MaglevModel`, :class:`HapticController`,
:class:`VirtualEnvironment`) are used by the nodes. Deterministic: no clocks, no threads.
"""

from __future__ import annotations

import numpy as np

from haptic_topology.control.controller import HapticController
from haptic_topology.control.laws import ControlMode
from haptic_topology.device.maglev import MaglevModel
from haptic_topology.device.users import user_from_config
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.sim.scenario import Scenario
from haptic_topology.sim.trace import Trace
from haptic_topology.sim.ve import VirtualEnvironment


def simulate(scenario: Scenario, mode: ControlMode | None = None) -> Trace:
    """Run ``scenario`` with ``mode`` (default: the scenario's) and return its trace."""
    mode = scenario.mode if mode is None else mode
    sc = scenario
    task = sc.linkage.task
    m = task.dim
    dyn = LinkageDynamics(sc.linkage)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step)
    ve_check = LinkageDynamics(sc.linkage)  # separate workspace for the trace's truth
    x0 = dyn.hand_pose(sc.q0)
    device = MaglevModel(sc.device, x0 + sc.device_offset)
    user = user_from_config(sc.user, task, f'{sc.source}: scenario.user', device.pose)
    ctrl = HapticController(task, mode, sc.gains, sc.device.mass, sc.device.christoffel,
                            sc.lmi_model, sc.vt_coupling)
    ctrl.update(ve.snapshot(seq=0))

    n = int(round(sc.duration / sc.dt)) + 1
    trace = Trace.empty(n, m, dyn.dof, mode=mode.label, scenario=sc.name, dt=sc.dt)
    u = np.zeros(m)
    f_h = np.zeros(m)
    update_seq = 1
    for k in range(n):
        t = k * sc.dt
        status = 0
        if k > 0:
            status = int(device.step(u, f_h, sc.dt))
        f_h = user.wrench(t, device.pose, device.twist)
        out = ctrl.cycle(k, sc.dt, device.pose, device.twist, f_h)
        u = out.wrench
        # Consuming input k integrates input k-1 over the last period: the VE is at time t.
        ve.push_input(k, t, out.vt_wrench)
        cons = ve_check.constraints(ve.q)
        trace.record(k, t=t, device_pose=device.pose, device_twist=device.twist,
                     hand_wrench=f_h, command=u, applied=device.applied,
                     vt_pose=dyn.hand_pose(ve.q), lmi_pose=out.vt_pose, q=ve.q,
                     constraint_count=cons.count, lmi_constraint_count=out.constraint_count,
                     status=status)
        if (k + 1) % sc.update_period == 0:
            ctrl.update(ve.snapshot(seq=update_seq))
            update_seq += 1
    return trace
