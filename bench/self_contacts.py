"""What self-collisions (``contacts.self_collisions``) cost the VE, on the robots' meshes.

On ``panda_table`` and ``ur5_table`` (the robots' own collision meshes, the SRDF's disabled
pairs left out): one ``ContactModel.torques`` call (every RK4 stage) and one 100 Hz VE update,
with the contacts checking the links against each other (the scenarios as shipped) and
without, as :func:`mesh_contacts.updates` measures them (CPU time of the calling thread,
percentiles after a warm-up). Run: ``.venv/bin/python bench/self_contacts.py [--json OUT]``
(needs nothing beyond the default install: the two robots ship in ``config/robots/``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import mesh_contacts


def run(warm: int = 60, timed: int = 100) -> dict[str, Any]:
    return {name: {'pairs': mesh_contacts.pairs(name),
                   'with_self': mesh_contacts.updates(name, True, warm, timed, True),
                   'without_self': mesh_contacts.updates(name, True, warm, timed, False)}
            for name in mesh_contacts.SCENARIOS}


def _pair(r: dict[str, Any], key: str, scale: float = 1.0) -> str:
    """``p50 / p99`` of ``r[key]`` (us, divided by ``scale``)."""
    return f'{r[key]["p50_us"] / scale:.1f} / {r[key]["p99_us"] / scale:.1f}'


def table(res: dict[str, Any]) -> list[str]:
    """Per scenario: the pairs, a torques call (us) and a VE update (ms), p50 / p99."""
    lines = ['self-collisions: pairs; torques call [us] with, without; VE update [ms] with, '
             'without (p50 / p99)']
    for name, r in res.items():
        w, wo = r['with_self'], r['without_self']
        lines.append(f'{name}: {r["pairs"]}; {_pair(w, "torques_call")}, '
                     f'{_pair(wo, "torques_call")}; {_pair(w, "update", 1e3)}, '
                     f'{_pair(wo, "update", 1e3)}')
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--json', help='also write the figures to this file')
    args = parser.parse_args()
    res = run()
    print('\n'.join(table(res)))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2), encoding='utf-8')


if __name__ == '__main__':
    main()
