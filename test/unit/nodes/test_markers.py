"""linkage_markers filling its markers of the previous call again (``kept``) gives the same
messages as building them afresh, whatever changed between the calls; a point grasp drawn as a
point (no orientation), a rigid one with its axes."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from visualization_msgs.msg import Marker

from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.model import frames
from haptic_topology.model.urdf import robot_description
from haptic_topology.nodes.markers import (
    FORCE_SCALE,
    CouplingSample,
    DeviceSample,
    linkage_markers,
)
from haptic_topology.nodes.viz import RobotViz
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


@pytest.mark.parametrize('name', ['fig8_point', 'spatial_arm4_point'])
def test_a_point_grasp_is_drawn_as_a_point_without_orientation(name: str) -> None:
    """A point grasp holds a point: the device ghost is a ball with the identity orientation
    at the device's point (a planar one in the grasp point's plane), ``vt_hand`` on /tf and
    the VT hand's pose mirror have the world's axes at the grasp point, the force arrows
    are the forces (no torque row), the coupling wrench is in world axes."""
    sc = load_scenario(name)
    task = sc.linkage.task
    assert task.point
    ve = virtual_environment(sc)
    dyn = LinkageDynamics(sc.linkage)
    q = ve.q + 0.3
    hand = dyn.hand_placement(q)
    assert not np.allclose(hand.rotation, np.eye(3))     # the link itself is turned
    m = task.dim
    pose = np.asarray(dyn.hand_pose(q)) + 0.01
    f_h = np.arange(1.0, m + 1.0)
    stamp = Time(sec=3)
    device = DeviceSample(stamp, pose, np.zeros(m), f_h, -f_h, None)
    markers = linkage_markers(dyn, q, device, None, ve.snapshot(seq=0), 'world', stamp)
    (ghost,) = [mk for mk in markers.markers if mk.ns == 'device']
    assert ghost.type == Marker.SPHERE
    o, p = ghost.pose.orientation, ghost.pose.position
    assert [o.x, o.y, o.z, o.w] == [0.0, 0.0, 0.0, 1.0]
    z = float(hand.translation[2]) if task.planar else float(pose[2])
    np.testing.assert_array_equal([p.x, p.y, p.z], [pose[0], pose[1], z])
    (arrow,) = [mk for mk in markers.markers if mk.ns == 'F_h']
    start, end = ([pt.x, pt.y, pt.z] for pt in arrow.points)
    force = np.zeros(3)
    force[:m] = FORCE_SCALE * f_h
    np.testing.assert_allclose(np.subtract(end, start), force, rtol=0.0, atol=1e-15)

    rv = RobotViz(robot_description(sc.linkage), LinkageDynamics(sc.linkage), 'world')
    _, _, vt_pose, vt_twist = rv.ve(q, np.ones(sc.linkage.dof), stamp)
    o, p = vt_pose.pose.orientation, vt_pose.pose.position
    assert [o.x, o.y, o.z, o.w] == [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_allclose([p.x, p.y, p.z], hand.translation, rtol=0.0, atol=1e-15)
    w = vt_twist.twist.angular
    assert [w.x, w.y, w.z] == [0.0, 0.0, 0.0]
    tf_hand = rv.frames.link_placement(q, 'vt_hand')
    np.testing.assert_allclose(tf_hand.rotation, np.eye(3), rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(tf_hand.translation, hand.translation, rtol=0.0, atol=1e-12)
    f_pc = np.arange(1.0, m + 1.0)
    wrench = rv.coupling(CouplingSample(stamp, f_pc, q)).wrench
    got = [wrench.force.x, wrench.force.y, wrench.force.z, wrench.torque.x, wrench.torque.y,
           wrench.torque.z]
    np.testing.assert_array_equal(got, frames.spatial(f_pc, task))


def test_a_rigid_grasp_keeps_the_link_axes() -> None:
    """The same pictures of a rigid grasp: a box with the device's orientation, ``vt_hand``
    in the grasped link's axes."""
    sc = load_scenario('fig8')
    dyn = LinkageDynamics(sc.linkage)
    ve = virtual_environment(sc)
    q = ve.q + 0.3
    device = DeviceSample(Time(), np.array([0.05, 0.01, 0.4]), np.zeros(3), np.zeros(3))
    markers = linkage_markers(dyn, q, device, None, ve.snapshot(seq=0), 'world', Time())
    (ghost,) = [mk for mk in markers.markers if mk.ns == 'device']
    assert ghost.type == Marker.CUBE
    assert ghost.pose.orientation.z == pytest.approx(np.sin(0.2), abs=1e-15)
    rv = RobotViz(robot_description(sc.linkage), LinkageDynamics(sc.linkage), 'world')
    np.testing.assert_allclose(rv.frames.link_placement(q, 'vt_hand').rotation,
                               dyn.hand_placement(q).rotation, rtol=0.0, atol=1e-12)
