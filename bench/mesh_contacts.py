"""What a robot's collision meshes cost the VE: per coal query and per 100 Hz VE update.

On the scenarios ``panda_table`` and ``ur5_table`` (the robot's own STL collision meshes, a
mesh table and a box): the cost of one signed-distance query of a link mesh's convex hull
against the table and the box (coal GJK/EPA, through ``CoalPair.gap``), of one
``ContactModel.torques`` (every RK4 stage: forward kinematics, the culled pairs, the forces),
and of one 100 Hz VE update as ``ve_sim`` runs it (10 hand inputs of 1 ms, RK4, then the LMI
snapshot), resting on the table and the box under the scenario's user wrench: with the
contacts against the obstacles, with the self-collisions too (as the scenarios ship), and
without contacts. CPU time of the calling thread (``time.thread_time_ns``), percentiles
after a warm-up. ``make bench`` runs it (:func:`section`; the two robots ship in
``config/robots/``, so it needs no extra). Run alone: ``.venv/bin/python
bench/mesh_contacts.py [--json OUT]``; the self-collisions alone, with the ``torques`` call's
cost: ``bench/self_contacts.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from typing import Any

import numpy as np

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import ContactModel
from haptic_topology.sim import VirtualEnvironment, load_scenario

CLOCK = time.thread_time_ns
BUDGET_US = 10_000.0    # one update period of a 100 Hz VE


def _pct(samples_ns: list[int]) -> dict[str, float]:
    a = np.asarray(samples_ns, dtype=float) / 1000.0
    return {'p50_us': round(float(np.percentile(a, 50)), 1),
            'p99_us': round(float(np.percentile(a, 99)), 1), 'n': int(a.size)}


def _ve(name: str, contacts: bool, self_collisions: bool = False
        ) -> tuple[VirtualEnvironment, ContactModel | None, np.ndarray]:
    sc = load_scenario(name)
    dyn = LinkageDynamics(sc.linkage)
    cm = (ContactModel(dyn.model, sc.linkage, dataclasses.replace(
        sc.contacts, self_collisions=self_collisions))
          if contacts and sc.contacts is not None else None)
    ve = VirtualEnvironment(dyn, sc.q0, sc.dq0, sc.internal_step,
                            coupling=sc.coupling_gains(), contacts=cm)
    return ve, cm, np.array(sc.user['wrench'], dtype=float)


def queries(name: str, n: int = 2000) -> dict[str, Any]:
    """One coal query per link mesh and obstacle at the scenario's start (apart, 2-4 mm)."""
    _, cm, _ = _ve(name, True)
    assert cm is not None
    sc = load_scenario(name)
    cm.detect(sc.q0)        # places the links (forward kinematics in cm.data)
    samples: list[int] = []
    for j, sol in enumerate(cm._solids):
        if sol.mesh is None:
            continue
        placement = cm.data.oMi[sol.link + 1]
        centre = placement.rotation @ sol.centre + placement.translation
        rotation = placement.rotation @ sol.rotation
        for _, pair in cm._pairs_of[j]:
            assert pair is not None
            for _ in range(20):
                pair.gap(centre, rotation)
            for _ in range(n // 10):
                t0 = CLOCK()
                pair.gap(centre, rotation)
                samples.append(CLOCK() - t0)
    meshes = sum(1 for s in cm._solids if s.mesh is not None)
    return {'mesh_solids': meshes, 'solids': len(cm._solids),
            'hull_vertices': [int(s.mesh.vertices.shape[0]) for s in cm._solids
                              if s.mesh is not None],
            'query': _pct(samples)}


def updates(name: str, contacts: bool, warm: int = 60, timed: int = 100,
            self_collisions: bool = False) -> dict[str, Any]:
    """One 100 Hz VE update (10 inputs held 1 ms each, then the snapshot), in contact;
    ``self_collisions``: the contacts check the links against each other too."""
    ve, cm, wrench = _ve(name, contacts, self_collisions)
    seq = 0
    total: list[int] = []
    torques: list[int] = []
    for i in range(warm + timed):
        t0 = CLOCK()
        for _ in range(10):
            ve.push_input(seq, seq * 1e-3, wrench)
            seq += 1
        ve.snapshot(i)
        if i >= warm:
            total.append(CLOCK() - t0)
            if cm is not None:
                q, dq = ve.q.copy(), np.zeros_like(ve.q)
                t1 = CLOCK()
                cm.torques(q, dq)
                torques.append(CLOCK() - t1)
    out: dict[str, Any] = {'update': _pct(total)}
    if cm is not None:
        gaps = cm.gaps(ve.q)
        out['torques_call'] = _pct(torques)
        out['penetrating_candidates'] = int((gaps < 0.0).sum())
    out['fits_100hz'] = out['update']['p99_us'] < BUDGET_US
    return out


def pairs(name: str) -> int:
    """The shape pairs scenario ``name`` checks against each other with self-collisions on."""
    sc = load_scenario(name)
    assert sc.contacts is not None
    cm = ContactModel(LinkageDynamics(sc.linkage).model, sc.linkage,
                      dataclasses.replace(sc.contacts, self_collisions=True))
    return len(cm._self) if cm._self is not None else 0


#: The scenarios measured: robots of example-robot-data touching a mesh table and a box.
SCENARIOS = ('panda_table', 'ur5_table')


def run(n: int = 2000, warm: int = 60, timed: int = 100) -> dict[str, Any]:
    """Per scenario: the coal query, the self pairs, and the VE update with the contacts
    against the obstacles, with the self-collisions too, and without contacts."""
    return {name: {'queries': queries(name, n), 'pairs': pairs(name),
                   'with_contacts': updates(name, True, warm, timed),
                   'with_self': updates(name, True, warm, timed, True),
                   'without_contacts': updates(name, False, warm, timed)}
            for name in SCENARIOS}


def section(n: int = 2000, warm: int = 60, timed: int = 1000) -> dict[str, Any]:
    """``make bench``'s mesh section: :func:`run` (the robots ship in ``config/robots/``),
    over 1000 timed updates (10 s of the robot resting on the table and the box), so the
    p99 is a percentile of many updates, not their maximum."""
    return run(n, warm, timed)


def _ms(r: dict[str, Any]) -> str:
    """A VE update's ``p50 / p99`` (ms)."""
    return f'{r["update"]["p50_us"] / 1e3:.2f} / {r["update"]["p99_us"] / 1e3:.2f}'


def table(res: dict[str, Any]) -> list[str]:
    """The section's lines: per scenario the coal query (a link mesh's hull against the table
    or the box), a ``torques`` call and the 100 Hz VE update with the contacts, with the
    self-collisions too (and their pairs), and without contacts, p50/p99."""
    lines = ['meshes (coal)  hulls  query p50/p99 [us]  torques p50/p99 [us]  VE update '
             'p50/p99 [ms] with contacts / + self-collisions (pairs) / without contacts  '
             'fits 100 Hz']
    for name, r in res.items():
        q, w, ws = r['queries'], r['with_contacts'], r['with_self']
        lines.append(
            f'{name:13s}  {q["mesh_solids"]:5d}  {q["query"]["p50_us"]:8.1f} / '
            f'{q["query"]["p99_us"]:6.1f}  {w["torques_call"]["p50_us"]:9.0f} / '
            f'{w["torques_call"]["p99_us"]:7.0f}  {_ms(w):>11s}  {_ms(ws):>11s} '
            f'({r["pairs"]:2d})  {_ms(r["without_contacts"]):>11s}  '
            f'{"yes" if w["fits_100hz"] and ws["fits_100hz"] else "NO"}')
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--json', help='also write the figures to this file')
    args = parser.parse_args()
    res = section()
    print('\n'.join(table(res)))
    print(json.dumps(res, indent=2))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as f:
            json.dump(res, f, indent=2)


if __name__ == '__main__':
    main()
