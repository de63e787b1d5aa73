"""linkage_markers filling its markers of the previous call again (``kept``) gives the same
messages as building them afresh, whatever changed between the calls."""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from visualization_msgs.msg import Marker

from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.nodes.markers import CouplingSample, DeviceSample, linkage_markers
from haptic_topology.sim.lockstep import virtual_environment
from haptic_topology.sim.scenario import load_scenario


def test_kept_markers_equal_fresh_ones_call_after_call() -> None:
    sc = load_scenario('fig8')
    ve = virtual_environment(sc)
    dyn = LinkageDynamics(sc.linkage)
    m = sc.linkage.task.dim
    kept: dict[tuple[str, int], Marker] = {}
    rng = np.random.default_rng(3)
    cases = 0
    for k in range(12):
        stamp = Time(sec=k, nanosec=7 * k)
        q = ve.q + rng.normal(0.0, 0.5, ve.q.size)
        snap = ve.snapshot(seq=k)
        # the device and the coupling come and go; a zero wrench deletes its arrow
        w = np.zeros(m) if k % 3 == 0 else rng.normal(0.0, 2.0, m)
        device = None if k % 4 == 1 else DeviceSample(stamp, rng.normal(0.0, 0.05, m),
                                                      np.zeros(m), w, -w, None)
        coupling = None if k % 5 == 2 else CouplingSample(stamp, rng.normal(0.0, 1.0, m), q)
        fresh = linkage_markers(dyn, q, device, coupling, snap, 'world', stamp)
        again = linkage_markers(dyn, q, device, coupling, snap, 'world', stamp, kept)
        assert [mk.ns for mk in again.markers] == [mk.ns for mk in fresh.markers]
        assert again.markers == fresh.markers
        cases += {mk.action for mk in fresh.markers} == {Marker.ADD, Marker.DELETE}
    assert cases > 0     # arrows were deleted and added again within the sequence
    assert len(kept) == len({(mk.ns, mk.id) for mk in fresh.markers} | {('device', 2)})


def test_a_closed_chain_draws_its_closing_joints() -> None:
    """The four-bar: the 'loops' marker holds both points of its closure, which coincide
    (assembled) at the rocker's free end, on the ground pivot O4 = (0.1, 0)."""
    sc = load_scenario('fourbar')
    ve = virtual_environment(sc)
    dyn = LinkageDynamics(sc.linkage)
    markers = linkage_markers(dyn, ve.q, None, None, ve.snapshot(seq=0), 'world', Time())
    (closing,) = [mk for mk in markers.markers if mk.ns == 'loops']
    a, b = ([p.x, p.y, p.z] for p in closing.points)
    np.testing.assert_allclose(a, [0.1, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(b, [0.1, 0.0, 0.0], atol=1e-15)
    serial = linkage_markers(LinkageDynamics(load_scenario('fig8').linkage),
                             np.zeros(3), None, None, ve.snapshot(seq=0), 'world', Time())
    assert 'loops' not in [mk.ns for mk in serial.markers]
