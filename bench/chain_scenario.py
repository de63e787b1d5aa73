"""Scenario files of a long chain for the live graph (``make bench``, the VE's rate with a
100-link chain while the loop and the recorder run).

The chain is :func:`~haptic_topology.model.linkage.serial_chain` (the chain of
``core_costs.ve_update``), at a seeded random ``q0`` in +-0.5 rad. Planar: the ``circle``
scenario's device, user and gains, the user's circle centred on the chain's hand at ``q0``
(the device starts there). Spatial: the ``spatial_arm4`` scenario's device, user, gains and
LMI (eq. 20, no gravity), without its workspace stops (they are placed for that arm), with
the coordination spring on the VT (as ``circle``: the VT follows the device) and ``circle``'s
user (a 15 mm circle in x-y, 4 s per turn) about the device's initial pose, so that the
motion stays bounded for any duration.
``python bench/chain_scenario.py N planar|spatial DIR`` writes one and prints its path.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model.linkage import serial_chain, serial_chain_dict
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

#: The scenario each task's chain takes its device, user, gains and LMI from.
TEMPLATE = {TaskSpace.PLANAR: 'circle', TaskSpace.SPATIAL: 'spatial_arm4'}


def _scenario_doc(name: str) -> dict[str, Any]:
    """The scenario file ``name`` of the package, as YAML data."""
    doc: dict[str, Any] = yaml.safe_load((config_dir() / 'scenarios' / f'{name}.yaml')
                                         .read_text(encoding='utf-8'))
    return doc


def write_chain_scenario(n: int, task: TaskSpace, folder: Path, duration: float = 30.0,
                         seed: int = 1) -> Path:
    """Write ``chain<n>_<task>.yaml`` (linkage) and ``chain<n>_<task>_scenario.yaml`` into
    ``folder``; return the scenario's path."""
    name = f'chain{n}_{task.value}'
    link_path = folder / f'{name}.yaml'
    link_path.write_text(yaml.safe_dump(serial_chain_dict(n, task)), encoding='utf-8')
    q0 = np.random.default_rng(seed).uniform(-0.5, 0.5, n)
    doc = _scenario_doc(TEMPLATE[task])
    sc = doc['scenario']
    sc.update(name=name, linkage=link_path.name, q0=[float(v) for v in q0],
              dq0=[0.0] * n, duration=float(duration))
    if task is TaskSpace.PLANAR:
        hand = LinkageDynamics(serial_chain(n, task)).hand_pose(q0)
        sc['user']['start'] = [float(v) for v in hand]
    else:
        sc['device'].pop('workspace', None)
        sc['ve']['vt_coupling'] = True      # the VT follows the device, as in circle
        # circle's hand, about the device's initial pose (the chain's hand): spatial_arm4's
        # constant push, without that arm's stops, would drive the device off for ever
        user = _scenario_doc('circle')['scenario']['user']
        k, b = user['stiffness'][0], user['damping'][0]     # its x row, on x, y and z
        sc['user'] = {**{key: user[key] for key in ('type', 'path', 'radius', 'period')},
                      'stiffness': [k] * 3 + [0.0] * 3, 'damping': [b] * 3 + [0.0] * 3}
    path = folder / f'{name}_scenario.yaml'
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding='utf-8')
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('links', type=int)
    ap.add_argument('task', choices=[t.value for t in TaskSpace])
    ap.add_argument('folder', type=Path)
    ap.add_argument('--duration', type=float, default=30.0)
    a = ap.parse_args()
    a.folder.mkdir(parents=True, exist_ok=True)
    print(write_chain_scenario(a.links, TaskSpace(a.task), a.folder, a.duration))


if __name__ == '__main__':
    main()
