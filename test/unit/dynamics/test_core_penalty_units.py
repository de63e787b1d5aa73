"""Eq. 13's penalty is the same physical wrench whatever the unit of length.

The directions are orthonormal in the metric ``M_d^-1`` of the device inertia that multiplies
the penalty in eq. 14 (:meth:`ConstraintDirections.projector`): a linkage file, device inertia
and error rewritten in millimetres give the wrench of the metre file, converted (force x 1e3,
torque x 1e6 in kg mm / s^2 and kg mm^2 / s^2), and the wrench stays in ``N(J_h^T)``.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from haptic_topology.control.lmi import LmiSnapshot, LocalModel
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model import JointType, Linkage, load_linkage
from haptic_topology.paths import config_dir
from haptic_topology.vocabulary import TaskSpace

S = 1000.0      # metres -> millimetres
K_TC, B_TC = 200.0, 50.0     # 1/s^2 and 1/s: the same numbers in any unit of length


def _scaled(doc: dict[str, Any], s: float) -> dict[str, Any]:
    """The linkage document with every length multiplied by ``s`` (masses kept)."""
    out = copy.deepcopy(doc)
    lk = out['linkage']
    lk['gravity'] = [g * s for g in lk.get('gravity', [0.0, 0.0, 0.0])]
    for link in lk['links']:
        link['length'] = link['length'] * s
        if 'com' in link:
            link['com'] = [c * s for c in link['com']]
        if 'origin' in link and 'xyz' in link['origin']:
            link['origin']['xyz'] = [c * s for c in link['origin']['xyz']]
        inertia = link['inertia']
        link['inertia'] = (inertia * s * s if not isinstance(inertia, list) else
                           [[v * s * s for v in row] if isinstance(row, list) else row * s * s
                            for row in inertia])
    if 'point' in lk['grasp']:
        lk['grasp']['point'] = [c * s for c in lk['grasp']['point']]
    cons = lk.setdefault('constraints', {})
    if 'characteristic_length' in cons:
        cons['characteristic_length'] *= s
    return out


def _pair(name: str, grasp: str | None, tmp_path: Path) -> tuple[Linkage, Linkage]:
    doc = yaml.safe_load((config_dir() / 'linkages' / f'{name}.yaml').read_text())
    if grasp is not None:
        doc['linkage']['grasp'] = {'link': grasp}
    paths = []
    for s, unit in ((1.0, 'm'), (S, 'mm')):
        path = tmp_path / f'{name}_{unit}.yaml'
        path.write_text(yaml.safe_dump(_scaled(doc, s)))
        paths.append(path)
    return load_linkage(paths[0]), load_linkage(paths[1])


def _units(task: TaskSpace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(D, wrench scale, inertia scale): pose m -> mm is ``D x``, a wrench becomes
    ``diag(S, S^2) F``, M_d's rows ``diag(1, S^2)``."""
    trans = 2 if task is TaskSpace.PLANAR else 3
    rot = task.dim - trans
    d = np.r_[np.full(trans, S), np.ones(rot)]
    return d, np.r_[np.full(trans, S), np.full(rot, S * S)], np.r_[np.ones(trans),
                                                                   np.full(rot, S * S)]


def _penalty(dyn: LinkageDynamics, q: np.ndarray, m_d: np.ndarray, e: np.ndarray,
             ed: np.ndarray) -> np.ndarray:
    """``M_d P (k_tc e + b_tc edot)`` of eq. 13/14 through the LMI's re-sync."""
    snap = LmiSnapshot.from_dynamics(dyn.snapshot(q, np.zeros(dyn.dof)), dyn.task,
                                     dyn.linkage.constraints.characteristic_length, 1, 0)
    lmi = LocalModel(dyn.task, device_inertia=m_d)
    lmi.sync(snap)
    return m_d @ (lmi.projector @ (K_TC * e + B_TC * ed))


CASES = [
    # (file, grasp, q in SI, M_d diagonal in SI): the issue's Table I configuration, the
    # middle-link grasp (t = 1 everywhere), the spatial arm with its prismatic joint.
    ('table1_planar3', None, [0.3, 0.0, math.pi / 2], [1.0, 1.0, 1.0]),
    ('table1_planar3', 'link2', [0.3, 0.8, -0.2], [1.0, 1.0, 1.0]),
    ('table1_planar3', 'link2', [0.3, 0.8, -0.2], [2.0, 0.5, 0.003]),
    ('spatial_arm4', None, [0.3, 0.4, -0.8, 0.01], [1.0, 1.0, 1.0, 0.01, 0.01, 0.01]),
]


@pytest.mark.parametrize('name,grasp,q,mass', CASES)
def test_a_linkage_in_millimetres_gives_the_same_penalty_wrench(
        name: str, grasp: str | None, q: list[float], mass: list[float],
        tmp_path: Path) -> None:
    metre, milli = _pair(name, grasp, tmp_path)
    dyn_m, dyn_mm = LinkageDynamics(metre), LinkageDynamics(milli)
    d, wrench_scale, inertia_scale = _units(metre.task)
    q_m = np.array(q)
    q_mm = np.array([v * S if link.joint is JointType.PRISMATIC else v
                     for v, link in zip(q, metre.links, strict=True)])
    m_d = np.diag(mass)
    rng = np.random.default_rng(29)
    checked = 0
    for _ in range(5):
        e, ed = rng.normal(size=d.size) * 1e-3, rng.normal(size=d.size) * 1e-2
        f_m = _penalty(dyn_m, q_m, m_d, e, ed)
        f_mm = _penalty(dyn_mm, q_mm, np.diag(np.array(mass) * inertia_scale), d * e, d * ed)
        assert dyn_m.constraints(q_m).count == dyn_mm.constraints(q_mm).count
        np.testing.assert_allclose(f_mm, wrench_scale * f_m, rtol=1e-12,
                                   atol=1e-12 * np.abs(wrench_scale * f_m).max())
        # No work on any motion the linkage allows: F . (J_h qd) = 0.
        j = dyn_m.hand_jacobian(q_m)
        if dyn_m.constraints(q_m).count == d.size - np.linalg.matrix_rank(j, tol=1e-9):
            assert np.abs(j.T @ f_m).max() <= 1e-12 * max(np.abs(f_m).max(), 1e-300)
        checked += int(np.any(f_m))
    assert checked == 5 or dyn_m.constraints(q_m).count == 0


def test_the_issues_example_projects_a_millimetre_error_alike_in_both_files(
        tmp_path: Path) -> None:
    """Table I at q = (0.3, 0, pi/2): 1 mm of x error, M_d = I (the paper's device), in the
    metre and the millimetre file: the same penalty acceleration, in mm."""
    metre, milli = _pair('table1_planar3', None, tmp_path)
    q = np.array([0.3, 0.0, math.pi / 2])
    acc_m = LinkageDynamics(metre).constraints(q).projector(np.eye(3)) @ [1e-3, 0.0, 0.0]
    acc_mm = (LinkageDynamics(milli).constraints(q).projector(np.diag([1.0, 1.0, S * S]))
              @ [1.0, 0.0, 0.0])
    assert np.abs(acc_m[:2]).max() > 1e-4                    # the error is penalised
    np.testing.assert_allclose(acc_mm, acc_m * [S, S, 1.0], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize('name,grasp', [('table1_planar3', 'link2'), ('spatial_arm4', None)])
def test_the_projector_is_the_inertia_orthogonal_one(name: str, grasp: str | None) -> None:
    """Where ``J_h`` is exactly rank-deficient, ``P = I - J (J^T M_d J)^+ J^T M_d`` (the
    M_d-orthogonal projection onto the complement of ``range(J_h)``), for diagonal and full
    SPD ``M_d``; with ``M_d = I`` the projector is the one without an inertia, bit for bit."""
    lk = load_linkage(config_dir() / 'linkages' / f'{name}.yaml')
    dyn = LinkageDynamics(lk if grasp is None else lk.with_grasp(grasp))
    m = dyn.task.dim
    rng = np.random.default_rng(3)
    for _ in range(10):
        q = rng.uniform(-1.5, 1.5, dyn.dof)
        j = dyn.hand_jacobian(q)
        cons = dyn.constraints(q)
        if cons.count != m - np.linalg.matrix_rank(j, tol=1e-9):
            continue        # inside the rank tolerance band: P is for the truncated J_h
        a = rng.normal(size=(m, m))
        for m_d in (np.diag(rng.uniform(0.01, 3.0, m)), a @ a.T + 0.1 * np.eye(m)):
            p = cons.projector(m_d)
            expected = np.eye(m) - j @ np.linalg.pinv(j.T @ m_d @ j) @ j.T @ m_d
            np.testing.assert_allclose(p, expected, atol=1e-9)
            np.testing.assert_allclose(p @ p, p, atol=1e-9)
            np.testing.assert_allclose(m_d @ p, (m_d @ p).T, atol=1e-9)
        np.testing.assert_array_equal(cons.projector(np.eye(m)), cons.projector())
