"""Compare ``penalty_direction: nullspace`` and ``weighted`` on the paper's scenarios (eq. 14).

For each scenario and setting: the drift figures of ``haptic-topology simulate`` (final, max,
RMS device - VT hand distance) and the work the penalty of eq. 13 does on the motions the
linkage allows, ``W_allowed = integral u_add . (J_h(q) qd) dt`` (J; N m/rad . rad/s = W for the
rotation row), where ``u_add`` is the penalty part of the device command computed by the LMI
and ``J_h(q) qd`` the VT hand twist in the VE at the same instant. ``|W|`` integrates the
absolute power. With ``nullspace`` the power is zero whenever the LMI's frozen J_h equals the
VE's (the residue comes from the LMI's J_h being up to one update period old).

It also plots that power, ``u_add . (J_h(q) qd)`` (W), over time for both settings, one panel
per scenario, into ``docs/img/penalty_direction.png`` (``--plot PATH`` to change, ``--plot ''``
for none).

Run from the repository root::

    python bench/penalty_direction.py [--plot PATH] [fig6 fig8 ...]
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.control.laws import penalty_acceleration
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.taskspace import pose_difference
from haptic_topology.model import PenaltyDirection
from haptic_topology.sim.lockstep import SimStep, simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode


def run(name: str, direction: PenaltyDirection) -> dict[str, Any]:
    """Simulate scenario ``name`` in penalty mode with ``direction``; drift and work figures."""
    sc = load_scenario(name)
    lk = sc.linkage
    sc = replace(sc, linkage=replace(lk, constraints=replace(
        lk.constraints, penalty_direction=direction)))
    u_add: list[np.ndarray] = []
    states: list[tuple[np.ndarray, np.ndarray]] = []

    def observe(step: SimStep) -> None:
        """The penalty addition of each controller cycle and the VT's state when the VE took
        that cycle's hand input."""
        if step.answer.hand is None:
            return
        ctrl, r = step.controller.ctrl, step.tick.reading
        lmi = ctrl.lmi
        if lmi.synced and ctrl.mode is ControlMode.PENALTY:
            e = pose_difference(lmi.x_vt, r.pose, ctrl.task)
            u_add.append(ctrl.m_d @ penalty_acceleration(
                lmi.projector, e, lmi.xd_vt - r.twist, ctrl.gains.k_tc, ctrl.gains.b_tc))
        else:
            u_add.append(np.zeros(ctrl.task.dim))
        states.append((step.ve.q.copy(), step.ve.dq.copy()))   # the VT at this device state

    trace = simulate(sc, ControlMode.PENALTY, observer=observe)

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
        'power_W': power, 'dt': sc.dt,
    }


def plot(results: list[dict[str, Any]], path: Path) -> None:
    """Penalty power on the allowed motions over time, both settings, a panel per scenario."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r['scenario'] for r in results))
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 3.2 * len(names)), squeeze=False)
    styles = {'nullspace': ('tab:blue', '-'), 'weighted': ('tab:red', '--')}
    for ax, name in zip(axes[:, 0], names, strict=True):
        for r in (r for r in results if r['scenario'] == name):
            p = r['power_W']
            t = np.arange(p.size) * r['dt']
            color, ls = styles[r['direction']]
            ax.plot(t, p * 1e3, color=color, ls=ls, lw=1.2,
                    label=f'{r["direction"]} (|W| = {r["abs_work_allowed_J"]:.2e} J)')
        ax.set_title(f'{name}: power of the eq. 13 penalty on the motions the linkage allows')
        ax.set_xlabel('t [s]')
        ax.set_ylabel('u_add . J_h qd [mW]')
        ax.grid(alpha=0.3)
        ax.legend(loc='best')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str]) -> int:
    out = Path('docs/img/penalty_direction.png')
    if argv[:1] == ['--plot']:
        out, argv = Path(argv[1]) if argv[1] else Path(), argv[2:]
    names = argv or ['fig6', 'fig8']
    results = []
    print(f'{"scenario":8}  {"direction":9}  {"final [mm]":>10}  {"max [mm]":>9}  '
          f'{"rms [mm]":>9}  {"W_allowed [J]":>14}  {"|W|_allowed [J]":>15}')
    for name in names:
        for direction in PenaltyDirection:
            r = run(name, direction)
            results.append(r)
            print(f'{r["scenario"]:8}  {r["direction"]:9}  {r["final_mm"]:10.4f}  '
                  f'{r["max_mm"]:9.4f}  {r["rms_mm"]:9.4f}  {r["work_allowed_J"]:14.3e}  '
                  f'{r["abs_work_allowed_J"]:15.3e}')
    if out != Path():
        plot(results, out)
        print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main(sys.argv[1:]))
