"""The VE's integrator (eq. 2) against the textbook RK4, and its cached hand quantities.

The VE runs RK4 on preallocated arrays with two Pinocchio calls per stage; these tests pin that
it computes exactly (bit for bit) what the plain formulation computes, so the lock-step graph,
``simulate`` and every figure in the README are unchanged by the speed-up.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest

from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.errors import SimulationError
from haptic_topology.model import load_linkage, serial_chain
from haptic_topology.paths import config_dir
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

RNG = np.random.default_rng(11)


def _linkage(name: str) -> LinkageDynamics:
    if name.startswith('chain'):
        n, task = name[5:].split('_')
        return LinkageDynamics(serial_chain(int(n), TaskSpace(task)))
    return LinkageDynamics(load_linkage(config_dir() / 'linkages' / f'{name}.yaml'))


def _textbook_rk4(dyn: LinkageDynamics, q: np.ndarray, dq: np.ndarray, wrench: np.ndarray,
                  duration: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """RK4 of eq. 2 written out: ``qdd = ABA(q, dq, J_h^T F)``, k1..k4, h/6 (k1 + 2k2 + ...);
    ABA in world coordinates as the VE runs it."""
    n = max(1, math.ceil(duration / step - 1e-9))
    h = duration / n

    def accel(q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        return pin.aba(dyn.model, dyn.data, q, dq, dyn.hand_jacobian(q).T @ wrench,
                       pin.Convention.WORLD)

    for _ in range(n):
        k1q, k1v = dq, accel(q, dq)
        k2q = dq + 0.5 * h * k1v
        k2v = accel(q + 0.5 * h * k1q, k2q)
        k3q = dq + 0.5 * h * k2v
        k3v = accel(q + 0.5 * h * k2q, k3q)
        k4q = dq + h * k3v
        k4v = accel(q + h * k3q, k4q)
        q = q + h / 6.0 * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
        dq = dq + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return q, dq


@pytest.mark.parametrize('name', ['chain1_planar', 'chain1_spatial', 'table1_planar3',
                                  'spatial_arm4', 'chain12_planar', 'chain9_spatial'])
def test_integrate_equals_textbook_rk4_bit_for_bit(name: str) -> None:
    dyn = _linkage(name)
    ref_dyn = _linkage(name)   # own Data workspace
    d, m = dyn.dof, dyn.task.dim
    q, dq = RNG.uniform(-1.0, 1.0, d), RNG.uniform(-0.5, 0.5, d)
    ve = VirtualEnvironment(dyn, q, dq, internal_step=2.5e-4)
    for duration in (1e-3, 2.7e-3, 1e-4):   # 4, 11 (not a whole number of steps), 1 substeps
        wrench = RNG.normal(0.0, 0.5, m)
        q, dq = _textbook_rk4(ref_dyn, q, dq, wrench, duration, 2.5e-4)
        ve.integrate(wrench, duration)
        np.testing.assert_array_equal(ve.q, q)
        np.testing.assert_array_equal(ve.dq, dq)


def test_path_and_snapshot_use_the_hand_at_the_current_state() -> None:
    dyn = _linkage('spatial_arm4')
    ref = _linkage('spatial_arm4')
    ve = VirtualEnvironment(dyn, np.array([0.2, 0.4, -0.7, 0.01]), np.zeros(4), 1e-3)
    wrench = np.array([0.0, 0.05, 0.0, 0.0, 0.0, 0.01])
    for k in range(5):
        ve.push_input(k, k * 1e-3, wrench)
    path = ve.take_path()
    assert [s for s, _ in path] == [0, 1, 2, 3]
    np.testing.assert_array_equal(path[-1][1], ref.hand_pose(ve.q))
    snap, fresh = ve.snapshot(1), ref.snapshot(ve.q, ve.dq)
    for got, want in ((snap.hand_jacobian, fresh.hand_jacobian), (snap.hand_pose,
                      fresh.hand_pose), (snap.mass_matrix, fresh.mass_matrix),
                      (snap.hand_twist, fresh.hand_twist),
                      (snap.singular_values, fresh.constraints.singular_values)):
        np.testing.assert_array_equal(got, want)


def test_state_is_replaced_not_changed_in_place() -> None:
    """The cached hand Jacobian is keyed on the identity of ``q``: the VE's own arrays are
    read-only, and a ``q`` assigned from outside is never taken from the cache."""
    dyn = _linkage('table1_planar3')
    ve = VirtualEnvironment(dyn, np.array([0.0, 0.5, -0.5]), np.zeros(3), 1e-3)
    ve.integrate(np.array([0.4, 0.0, 0.0]), 1e-3)
    with pytest.raises(ValueError, match='read-only'):
        ve.q[0] = 1.0
    ve.snapshot(1)   # caches the hand at the VE's q
    moved = np.array([0.3, 0.2, -0.1])
    ve.q = moved
    np.testing.assert_array_equal(ve.snapshot(2).hand_jacobian, dyn.hand_jacobian(moved))
    moved[0] = -0.4  # the caller's own array: changed in place, seen at once
    np.testing.assert_array_equal(ve.snapshot(3).hand_jacobian, dyn.hand_jacobian(moved))


@pytest.mark.parametrize('gravity', [[0.0, 0.0, 0.0], [0.0, -9.81, 0.0]])
def test_snapshot_terms_equal_the_separate_algorithms(gravity: list[float]) -> None:
    """The snapshot's D, G, B (eq. 1) are CRBA, RNEA's gravity and nonlinear terms exactly,
    also where it skips the gravity pass (no gravity: G = 0)."""
    linkage = dataclasses.replace(serial_chain(4, TaskSpace.PLANAR),
                                  gravity=np.array(gravity))
    dyn, ref = LinkageDynamics(linkage), LinkageDynamics(linkage)
    q, dq = RNG.uniform(-1.0, 1.0, 4), RNG.uniform(-1.0, 1.0, 4)
    snap = dyn.snapshot(q, dq)
    d = pin.crba(ref.model, ref.data, q)
    np.testing.assert_array_equal(snap.mass_matrix, np.triu(d) + np.triu(d, 1).T)
    np.testing.assert_array_equal(snap.gravity, ref.gravity(q))
    np.testing.assert_array_equal(snap.coriolis, ref.bias(q, dq) - ref.gravity(q))
    assert np.any(snap.gravity) == any(gravity)


@pytest.mark.parametrize('name', ['table1_planar3', 'spatial_arm4', 'chain1_spatial',
                                  'chain40_planar'])
def test_inverse_inertia_from_minverse_equals_cholesky(name: str) -> None:
    """The VE's ``Lambda_h^-1`` (eq. 6, for the stable hold) from Pinocchio's ``D^-1`` equals
    the Cholesky solve of the LMI's formula to rounding."""
    dyn = _linkage(name)
    for _ in range(5):
        q = RNG.uniform(-1.5, 1.5, dyn.dof)
        want = dyn.inverse_operational_inertia(q)
        got = dyn.inverse_operational_inertia_aba(q, dyn.hand_jacobian(q))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize('name', ['table1_planar3', 'spatial_arm4', 'chain100_spatial'])
def test_world_aba_equals_local_aba(name: str) -> None:
    """The VE's ABA in world coordinates gives eq. 2's qdd of the local form (the one
    ``forward_dynamics`` uses) to rounding."""
    dyn = _linkage(name)
    for _ in range(5):
        q, dq = RNG.uniform(-1.5, 1.5, dyn.dof), RNG.uniform(-1.0, 1.0, dyn.dof)
        tau = RNG.uniform(-0.1, 0.1, dyn.dof)
        local = dyn.forward_dynamics(q, dq, tau)
        world = pin.aba(dyn.model, dyn.data, q, dq, tau, pin.Convention.WORLD)
        np.testing.assert_allclose(world, local, rtol=0, atol=1e-9 * np.abs(local).max())


def test_a_diverged_state_is_refused_with_when_never_sent_as_an_update() -> None:
    """Once the integration has left the finite numbers, snapshot names the time and the
    input instead of failing inside an SVD of NaN (or sending NaN to the controller)."""
    dyn = _linkage('table1_planar3')
    ve = VirtualEnvironment(dyn, np.array([0.0, math.pi / 2, -math.pi / 2]), np.zeros(3),
                            internal_step=1e-3)
    ve.snapshot(seq=0)
    ve.push_input(1, 0.0, np.zeros(3))
    ve.push_input(2, 0.001, np.array([math.inf, 0.0, 0.0]))
    with np.errstate(invalid='ignore'):        # inf * 0 in J^T F: NaN, as a blow-up gives
        ve.push_input(3, 0.002, np.zeros(3))   # integrates the infinite wrench for 1 ms
    assert not np.isfinite(ve.q).all()
    with pytest.raises(SimulationError,
                       match=r'VE state not finite at t = 0\.002 s \(hand input 2\): the '
                       r'integration of eq\. 2 diverged'):
        ve.snapshot(seq=1)
