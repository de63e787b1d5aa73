"""Compare ``penalty_direction: nullspace`` and ``weighted`` on the paper's scenarios (eq. 14).

For each scenario and setting: the drift figures of ``haptic-topology simulate`` (final, max,
RMS device - VT hand distance) and the work the penalty of eq. 13 does on the motions the
linkage allows, ``W_allowed = integral u_add . (J_h(q) qd) dt`` (J; N m/rad . rad/s = W for the
rotation row), where ``u_add`` is the penalty part of the device command computed by the LMI
and ``J_h(q) qd`` the VT hand twist in the VE at the same instant. ``|W|`` integrates the
absolute power. With ``nullspace`` the power is zero whenever the LMI's frozen J_h equals the
VE's (the residue comes from the LMI's J_h being up to one update period old).

Run from the repository root::

    python bench/penalty_direction.py [fig6 fig8 ...]
"""

from __future__ import annotations

import sys
from dataclasses import replace
from typing import Any

import numpy as np

import haptic_topology.sim.lockstep as lockstep
from haptic_topology.control.controller import CycleOutput, HapticController
from haptic_topology.control.laws import ControlMode, penalty_acceleration
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.model import PenaltyDirection
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment


def run(name: str, direction: PenaltyDirection) -> dict[str, Any]:
    """Simulate scenario ``name`` in penalty mode with ``direction``; drift and work figures."""
    sc = load_scenario(name)
    lk = sc.linkage
    sc = replace(sc, linkage=replace(lk, constraints=replace(
        lk.constraints, penalty_direction=direction)))
    u_add: list[np.ndarray] = []
    states: list[tuple[np.ndarray, np.ndarray]] = []

    class Controller(HapticController):
        def cycle(self, seq: int, dt: float, x_h: np.ndarray, xd_h: np.ndarray,
                  f_h: np.ndarray) -> CycleOutput:
            out = super().cycle(seq, dt, x_h, xd_h, f_h)
            lmi = self.lmi
            if lmi.synced and self.mode is ControlMode.PENALTY:
                e = pose_difference(lmi.x_vt, x_h, self.task)
                u_add.append(self.m_d @ penalty_acceleration(
                    lmi.projector, e, lmi.xd_vt - xd_h, self.gains.k_tc, self.gains.b_tc))
            else:
                u_add.append(np.zeros(self.task.dim))
            return out

    class Ve(VirtualEnvironment):
        def push_input(self, seq: int, stamp: float, wrench: np.ndarray) -> None:
            super().push_input(seq, stamp, wrench)
            states.append((self.q.copy(), self.dq.copy()))   # the VT at this device state

    # simulate() looks both classes up in its module: swap in the recording subclasses.
    saved = lockstep.HapticController, lockstep.VirtualEnvironment
    lockstep.HapticController, lockstep.VirtualEnvironment = Controller, Ve  # type: ignore
    try:
        trace = lockstep.simulate(sc, ControlMode.PENALTY)
    finally:
        lockstep.HapticController, lockstep.VirtualEnvironment = saved  # type: ignore

    dyn = LinkageDynamics(sc.linkage)
    power = np.array([u @ (dyn.hand_jacobian(q) @ dq)
                      for u, (q, dq) in zip(u_add, states, strict=True)])
    summary = trace.summary()
    return {
        'scenario': name, 'direction': direction.value,
        'final_mm': 1e3 * summary['final_distance_m'], 'max_mm': 1e3 * summary['max_distance_m'],
        'rms_mm': 1e3 * summary['rms_distance_m'],
        'work_allowed_J': float(power.sum() * sc.dt),
        'abs_work_allowed_J': float(np.abs(power).sum() * sc.dt),
    }


def main(argv: list[str]) -> int:
    names = argv or ['fig6', 'fig8']
    print(f'{"scenario":8}  {"direction":9}  {"final [mm]":>10}  {"max [mm]":>9}  '
          f'{"rms [mm]":>9}  {"W_allowed [J]":>14}  {"|W|_allowed [J]":>15}')
    for name in names:
        for direction in PenaltyDirection:
            r = run(name, direction)
            print(f'{r["scenario"]:8}  {r["direction"]:9}  {r["final_mm"]:10.4f}  '
                  f'{r["max_mm"]:9.4f}  {r["rms_mm"]:9.4f}  {r["work_allowed_J"]:14.3e}  '
                  f'{r["abs_work_allowed_J"]:15.3e}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main(sys.argv[1:]))
