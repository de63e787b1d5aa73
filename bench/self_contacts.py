"""What self-collisions (``contacts.self_collisions``) cost the VE, on the robots' meshes.

On ``panda_table`` and ``ur5_table`` (the robots' own collision meshes, the SRDF's disabled
pairs left out): one ``ContactModel.torques`` call (every RK4 stage) and one 100 Hz VE update,
with the contacts checking the links against each other and without (the scenarios as
shipped), as :func:`mesh_contacts.updates` measures them (CPU time of the calling thread,
percentiles after a warm-up). Run: ``.venv/bin/python bench/self_contacts.py [--json OUT]``
(needs nothing beyond the default install: the two robots ship in ``config/robots/``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

import mesh_contacts

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import ContactModel
from haptic_topology.sim import load_scenario


def pairs(name: str) -> int:
    """The shape pairs checked against each other in scenario ``name``."""
    sc = load_scenario(name)
    assert sc.contacts is not None
    cm = ContactModel(LinkageDynamics(sc.linkage).model, sc.linkage,
                      dataclasses.replace(sc.contacts, self_collisions=True))
    return len(cm._self) if cm._self is not None else 0


def run(warm: int = 60, timed: int = 100) -> dict[str, Any]:
    return {name: {'pairs': pairs(name),
                   'with_self': mesh_contacts.updates(name, True, warm, timed, True),
                   'without_self': mesh_contacts.updates(name, True, warm, timed, False)}
            for name in mesh_contacts.SCENARIOS}


def table(res: dict[str, Any]) -> list[str]:
    lines = ['self-collisions  pairs  torques p50/p99 [us] with / without  VE update p50/p99 '
             '[ms] with / without']
    for name, r in res.items():
        w, wo = r['with_self'], r['without_self']
        lines.append(
            f'{name:15s}  {r["pairs"]:5d}  {w["torques_call"]["p50_us"]:7.0f} / '
            f'{w["torques_call"]["p99_us"]:4.0f}  {wo["torques_call"]["p50_us"]:7.0f} / '
            f'{wo["torques_call"]["p99_us"]:4.0f}  {w["update"]["p50_us"] / 1e3:11.2f} / '
            f'{w["update"]["p99_us"] / 1e3:5.2f}  {wo["update"]["p50_us"] / 1e3:7.2f} / '
            f'{wo["update"]["p99_us"] / 1e3:5.2f}')
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--json', help='also write the figures to this file')
    args = parser.parse_args()
    res = run()
    print('\n'.join(table(res)))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as f:
            json.dump(res, f, indent=2)


if __name__ == '__main__':
    main()
