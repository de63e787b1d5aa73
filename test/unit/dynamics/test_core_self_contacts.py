"""Self-collisions (``contacts.self_collisions``, issue 58 item 3): penalty contacts between a
linkage's own links, the SRDF's disabled pairs honoured.

The expectations do not come from the code under test: the gaps and normals of two capsules
placed by hand (and of random poses) are the closed-form distance of their axes less the radii
(computed here by enumerating the minima of the axes' squared distance, not as the code does);
the penalty force must conserve ``T + U`` without damping and inject nothing with it, and stop
a folding linkage's last link where without self-collisions it passes through the first; an
SRDF's disabled pair gives no force where the same pair enabled does; adjacent links never
touch."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin
import pytest
import yaml

from haptic_topology.control.lmi import LocalModel
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.dynamics.contacts import ContactModel, ContactParams, ContactSettings
from haptic_topology.dynamics.self_contacts import _coal_shape, self_pairs
from haptic_topology.errors import ConfigError
from haptic_topology.model import Linkage, load_linkage
from haptic_topology.model.linkage import linkage_from_dict
from haptic_topology.model.meshes import capsule_shape, distance_request
from haptic_topology.paths import config_dir
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.ve import VirtualEnvironment
from haptic_topology.vocabulary import TaskSpace

RADIUS = 0.01       # m, every default capsule here


def _link(name: str, length: float, **extra: object) -> dict[str, object]:
    return {'name': name, 'joint': 'revolute', 'length': length, 'mass': 0.1,
            'inertia': [1e-4, 1e-4, 1e-4], **extra}


def _fold(offset: list[float] | None = None) -> Linkage:
    """Three links about z (spatial task): l1 0.1 m, l2 0.03 m, l3 0.1 m; ``offset``: l3's
    origin in l2's frame (default: l2's tip)."""
    l3 = _link('l3', 0.1, **({'origin': {'xyz': offset}} if offset else {}))
    return linkage_from_dict({'linkage': {'name': 'fold', 'task': 'spatial', 'links': [
        _link('l1', 0.1), _link('l2', 0.03), l3]}})


def _model(linkage: Linkage, on: bool = True, **params: float
           ) -> tuple[LinkageDynamics, ContactModel]:
    dyn = LinkageDynamics(linkage)
    settings = ContactSettings(ContactParams(**params), (), RADIUS, where='test',
                               self_collisions=on)
    return dyn, ContactModel(dyn.model, linkage, settings)


def _segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
                      ) -> tuple[float, np.ndarray, np.ndarray]:
    """Distance of the segments ``p0 p1`` and ``q0 q1`` and their closest points: the
    smallest of the squared distance's stationary point inside the unit square and its
    minima along the square's four edges (a convex quadratic in (s, t))."""
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    a, b, c, d, e = u @ u, u @ v, v @ v, u @ w, v @ w
    candidates = []
    det = a * c - b * b
    if det > 1e-15:
        s, t = (b * e - c * d) / det, (a * e - b * d) / det
        if 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0:
            candidates.append((s, t))
    for s in (0.0, 1.0):
        candidates.append((s, min(max((b * s + e) / c, 0.0), 1.0)))
    for t in (0.0, 1.0):
        candidates.append((min(max((b * t - d) / a, 0.0), 1.0), t))
    best = min(candidates, key=lambda st: float(np.linalg.norm(
        p0 + st[0] * u - q0 - st[1] * v)))
    pa, pb = p0 + best[0] * u, q0 + best[1] * v
    return float(np.linalg.norm(pa - pb)), pa, pb


def _axis(dyn: LinkageDynamics, q: np.ndarray, link: int, length: float = 0.1
          ) -> tuple[np.ndarray, np.ndarray]:
    """World ends of link ``link``'s x axis from its joint to ``length`` (m)."""
    data = dyn.model.createData()
    pin.forwardKinematics(dyn.model, data, q)
    placement = data.oMi[link + 1]
    return placement.act(np.zeros(3)), placement.act(np.array([length, 0.0, 0.0]))


def test_crossing_capsules_by_hand() -> None:
    """l3 (0.015 m above l1's plane: its origin at (0.03, 0.02, 0.015) in l2) crosses over l1
    at right angles above x = 0.07: gap 0.015 - 2 r = -5 mm, normal -z (from l3 down to l1),
    the witness points on l1's top (z = r) and l3's bottom (z = 0.015 - r)."""
    dyn, cm = _model(_fold([0.03, 0.02, 0.015]))
    q = np.array([0.0, math.pi, -math.pi / 2])      # l2 back along -x, l3 along +y
    cs = cm.detect(q, margin=0.1)
    assert cs.links.tolist() == [0] and cs.obstacles.tolist() == [-1]
    assert cs.gaps[0] == pytest.approx(0.015 - 2 * RADIUS, abs=1e-12)
    np.testing.assert_allclose(cs.normals[0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(cs.points[0], [0.07, 0.0, RADIUS], atol=1e-12)
    assert cm.potential(q) == pytest.approx(0.5 * 2000.0 * 0.005 ** 2, rel=1e-9)
    # without self-collisions the same pose has no contact
    assert len(_model(_fold([0.03, 0.02, 0.015]), on=False)[1].detect(q, margin=0.1)) == 0


def test_random_poses_equal_the_closed_form_distance_of_the_axes() -> None:
    """At random poses of the folding linkage, the pair l1-l3's gap and normal are the axes'
    distance less both radii and its direction (from l3 towards l1), the point on l1."""
    linkage = _fold([0.03, 0.02, 0.012])
    dyn, cm = _model(linkage)
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(60):
        q = rng.uniform(-math.pi, math.pi, 3)
        dist, pa, pb = _segment_distance(*_axis(dyn, q, 0), *_axis(dyn, q, 2))
        cs = cm.detect(q, margin=10.0)
        assert cs.links.tolist() == [0]
        assert cs.gaps[0] == pytest.approx(dist - 2 * RADIUS, abs=1e-9)
        np.testing.assert_allclose(cs.normals[0], (pa - pb) / dist, atol=1e-7)
        np.testing.assert_allclose(cs.points[0], pa - RADIUS * (pa - pb) / dist, atol=1e-8)
        checked += dist < 2 * RADIUS
    assert checked >= 3         # some of them penetrate


def _run(on: bool, duration: float = 0.3, **params: float
         ) -> tuple[float, list[float], list[float], list[float], float]:
    """The folding linkage (in one plane) swinging l3 back over l1, free (no hand wrench):
    ``(E0, T + U, energy balance, l3's tip's y in l1's frame, peak U)`` every ms."""
    dyn, cm = _model(_fold(), on, **params)
    q0, dq0 = np.array([0.0, math.pi / 2, math.pi / 2 - 0.2]), np.array([0.0, 0.0, 3.0])
    ve = VirtualEnvironment(dyn, q0, dq0, internal_step=1e-4, contacts=cm)
    e0 = ve.kinetic_energy() + cm.potential(q0)
    data = dyn.model.createData()
    energy, balance, side, peak = [], [], [], 0.0
    for _ in range(int(round(duration / 1e-3))):
        ve.integrate(np.zeros(6), 1e-3)
        pin.forwardKinematics(dyn.model, data, ve.q)
        side.append(float(data.oMi[1].actInv(data.oMi[3].act(np.array([0.1, 0.0, 0.0])))[1]))
        u = cm.potential(ve.q)
        peak = max(peak, u)
        energy.append(ve.kinetic_energy() + u)
        balance.append(ve.contact_energy_balance())
    return e0, energy, balance, side, peak


def test_self_collisions_stop_a_folding_link_and_are_passive() -> None:
    """l3 swings at 3 rad/s towards l1 (its tip 20 mm above l1's axis, 10 mm capsules): without
    self-collisions it passes through (its tip crosses l1's axis); with them it stops and
    bounces back, conserving ``T + U`` without damping (no energy injected) and dissipating
    with damping and friction."""
    _, _, _, side, _ = _run(on=False)
    assert min(side) < -0.03                        # passed through l1
    e0, energy, balance, side, peak = _run(on=True, damping=0.0)
    assert peak > 0.5 * e0                          # the contact held most of the energy
    assert min(side) > 2 * RADIUS - 0.002 and side[-1] > side[0]    # stopped, bounced back
    np.testing.assert_allclose(energy, e0, rtol=1e-5)
    assert max(abs(b) for b in balance) < 1e-5 * e0
    e0, energy, balance, side, _ = _run(on=True, damping=20.0, friction=0.5)
    assert min(side) > 2 * RADIUS - 0.002
    assert energy[-1] < 0.5 * e0 and max(balance) <= 1e-12 and balance[-1] < -0.5 * e0


def test_gap_rate_is_the_relative_normal_velocity_and_the_lmi_equals_the_ve() -> None:
    """``dg/dq = n^T (J_a(p_a) - J_b(p_b))`` (central differences: the relative Jacobian of
    the candidate), and the LMI's frozen contacts give the VE's torques at the update."""
    dyn, cm = _model(_fold([0.03, 0.02, 0.012]), damping=30.0, friction=0.4)
    rng = np.random.default_rng(11)
    for _ in range(10):
        q = rng.uniform(-math.pi, math.pi, 3)
        cs = cm.detect(q, margin=10.0)
        fd = np.zeros(3)
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-6
            fd[j] = (cm.detect(q + e, margin=10.0).gaps[0]
                     - cm.detect(q - e, margin=10.0).gaps[0]) / 2e-6
        np.testing.assert_allclose(cs.normals[0] @ cs.jacobians[0], fd, atol=1e-7)
    q = np.array([0.0, math.pi, -math.pi / 2])
    dq = np.array([0.4, -0.7, 1.3])
    dyn, cm = _model(_fold([0.03, 0.02, 0.015]), damping=30.0, friction=0.4)
    ve = VirtualEnvironment(dyn, q, dq, contacts=cm)
    snap = ve.snapshot(seq=1)
    assert snap.contacts is not None and len(snap.contacts) == 1
    lmi = LocalModel(TaskSpace.SPATIAL)
    lmi.sync(snap)
    tau, power = cm.torques(q, dq)
    assert np.any(tau != 0.0) and power < 0.0
    np.testing.assert_allclose(lmi.contact_torques, tau, rtol=1e-12, atol=1e-15)


def _urdf(tmp_path: Path, disabled: tuple[str, str] | None, l1: str = '', l3: str = '',
          tip: str = '') -> Linkage:
    """l1 (capsule along x, 0.1 m), l2 (at l1's tip, a short capsule), l3 (at l2's tip, a
    capsule of 0.06 m) and ``tip``, fixed to l3 at x = 0.1 with a sphere: a URDF link merged
    into the chain link l3. ``disabled``: the SRDF's one pair; ``l1``, ``l3``, ``tip``: other
    ``<collision>`` elements for those links."""
    inertial = ('<inertial><mass value="0.1"/><inertia ixx="1e-4" iyy="1e-4" izz="1e-4" '
                'ixy="0" ixz="0" iyz="0"/></inertial>')

    def capsule(length: float) -> str:
        return (f'<collision><origin xyz="{length / 2} 0 0" rpy="0 1.5707963267948966 0"/>'
                f'<geometry><capsule radius="{RADIUS}" length="{length}"/></geometry>'
                f'</collision>')

    sphere = f'<collision><geometry><sphere radius="{RADIUS}"/></geometry></collision>'
    limit = '<limit lower="-4" upper="4" effort="1" velocity="1"/>'
    urdf = tmp_path / 'fold.urdf'
    urdf.write_text(f'''<robot name="fold">
  <link name="base"/>
  <link name="l1">{inertial}{l1 or capsule(0.1)}</link>
  <link name="l2">{inertial}{capsule(0.03)}</link>
  <link name="l3">{inertial}{l3 or capsule(0.06)}</link>
  <link name="tip">{inertial}{tip or sphere}</link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.03 0 0"/><axis xyz="0 0 1"/>{limit}</joint>
  <joint name="jt" type="fixed"><parent link="l3"/><child link="tip"/>
    <origin xyz="0.1 0 0"/></joint>
</robot>''')
    srdf = tmp_path / 'fold.srdf'
    pair = (f'<disable_collisions link1="{disabled[0]}" link2="{disabled[1]}" '
            'reason="Never"/>' if disabled else '')
    srdf.write_text(f'<robot name="fold">{pair}</robot>')
    return linkage_from_dict({'linkage': {'name': 'fold', 'task': 'spatial',
                                          'urdf': str(urdf), 'srdf': str(srdf)}})


#: l3 folded back over l1, pointing down by asin(0.15): the tip sphere's centre 15 mm from l1's
#: axis (5 mm deep in l1's capsule), l3's own capsule ends 21 mm from it (1 mm apart).
FOLDED = np.array([0.0, math.pi / 2, math.pi / 2 + math.asin(0.15)])


@pytest.mark.parametrize('disabled', [None, ('l1', 'l3'), ('l1', 'tip')])
def test_a_disabled_pair_of_the_srdf_is_not_checked(tmp_path: Path,
                                                    disabled: tuple[str, str] | None) -> None:
    """The sphere of ``tip`` (a URDF link merged into l3) penetrates l1 by 5 mm: a force
    (normal -y, from the sphere towards l1) unless the SRDF disables l1-tip; disabling l1-l3
    leaves the tip's sphere checked (only l3's own capsule is off)."""
    linkage = _urdf(tmp_path, disabled)
    assert [link.name for link in linkage.links] == ['l1', 'l2', 'l3']
    dyn, cm = _model(linkage)
    cs = cm.detect(FOLDED, margin=0.0)
    tau, _ = cm.torques(FOLDED, np.zeros(3))
    if disabled == ('l1', 'tip'):
        assert len(cs) == 0 and not np.any(tau) and cm.potential(FOLDED) == 0.0
        return
    assert len(cs) == 1 and cs.links.tolist() == [0]
    assert cs.gaps[0] == pytest.approx(0.015 - 2 * RADIUS, abs=1e-12)
    np.testing.assert_allclose(cs.normals[0], [0.0, -1.0, 0.0], atol=1e-12)
    assert np.any(tau != 0.0)
    # within 2 mm also l3's own capsule (1 mm apart), unless its pair with l1 is disabled
    near = cm.detect(FOLDED, margin=0.002)
    assert len(near) == (1 if disabled == ('l1', 'l3') else 2)


BOX12 = Path(__file__).resolve().parents[2] / 'fixtures' / 'meshes' / 'box12.stl'


def test_gap_rate_of_solid_pairs_is_the_relative_normal_velocity(tmp_path: Path) -> None:
    """A box on l1, a cylinder on l3 and a mesh box (12 triangles) on the merged ``tip``: at
    random poses, apart and overlapping, every pair's ``dg/dq`` (central differences) is
    ``n^T (J_a(p_a) - J_b(p_b))`` at coal's witness points (EPA's too), the gap's gradient
    that makes the force passive and the LMI's linearisation right."""
    linkage = _urdf(
        tmp_path, None,
        l1='<collision><origin xyz="0.05 0 0" rpy="0.1 -0.2 0.3"/><geometry>'
           '<box size="0.1 0.02 0.03"/></geometry></collision>',
        l3='<collision><origin xyz="0.03 0 0" rpy="0 1.4 0.2"/><geometry>'
           '<cylinder radius="0.012" length="0.06"/></geometry></collision>',
        tip=f'<collision><origin rpy="0.3 -0.1 0.2"/><geometry><mesh filename="{BOX12}" '
            f'scale="0.03 0.02 0.025"/></geometry></collision>')
    kinds = [getattr(s, 'kind', 'capsule') for s in
             ContactSettings(ContactParams(), (), RADIUS).shapes(linkage)]
    assert kinds == ['box', 'capsule', 'cylinder', 'mesh']
    dyn, cm = _model(linkage)
    rng = np.random.default_rng(5)
    overlapping = 0
    for _ in range(30):
        q = np.array([0.0, math.pi / 2, math.pi / 2]) + rng.uniform(-0.6, 0.6, 3)
        cs = cm.detect(q, margin=10.0)
        assert len(cs) == 2             # l1-l3 and l1-tip
        overlapping += int(np.sum(cs.gaps < 0.0))
        fd = np.zeros((2, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-6
            fd[:, j] = (cm.detect(q + e, margin=10.0).gaps
                        - cm.detect(q - e, margin=10.0).gaps) / 2e-6
        np.testing.assert_allclose(np.einsum('ci,cid->cd', cs.normals, cs.jacobians), fd,
                                   atol=1e-6)
    assert overlapping >= 5


def test_adjacent_links_are_never_checked() -> None:
    """Adjacent capsules overlap at their joint (coal: gap -2 r), yet no pair of adjacent
    links is checked: the stretched linkage has no self-contact, no torque, no energy; only
    l1-l3 is a pair."""
    linkage = _fold()
    dyn, cm = _model(linkage)
    shapes = cm.settings.shapes(linkage)
    assert [(shapes[i].link, shapes[j].link) for i, j in self_pairs(linkage, shapes)] == [(0, 2)]
    q = np.zeros(3)
    res = distance_request()
    out = coal.DistanceResult()
    first = coal.Transform3s(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
                             np.array([0.05, 0.0, 0.0]))
    second = coal.Transform3s(first.getRotation(), np.array([0.115, 0.0, 0.0]))
    gap = coal.distance(capsule_shape(RADIUS, 0.1), first, capsule_shape(RADIUS, 0.03),
                        second, res, out)
    assert gap == pytest.approx(-2 * RADIUS, abs=1e-9)
    assert len(cm.detect(q, margin=0.0)) == 0
    # within 5 cm only l1 and l3 (their capsules 10 mm apart along the axis)
    near = cm.detect(q, margin=0.05)
    assert near.links.tolist() == [0] and near.gaps[0] == pytest.approx(0.03 - 2 * RADIUS)
    tau, power = cm.torques(q, np.array([1.0, -2.0, 3.0]))
    assert not np.any(tau) and power == 0.0 and cm.potential(q) == 0.0
    # a loop closure joining l3's tip to l1's base makes l1 and l3 adjacent too
    looped = linkage_from_dict({'linkage': {'name': 'fold', 'task': 'spatial', 'links': [
        _link('l1', 0.1), _link('l2', 0.03), _link('l3', 0.1)], 'loops': [
        {'name': 'c', 'link': 'l3', 'point': [0.1, 0.0, 0.0], 'to': 'l1',
         'to_point': [0.0, 0.0, 0.0], 'kind': 'spherical'}]}})
    assert self_pairs(looped, ContactSettings(ContactParams(), (), RADIUS).shapes(looped)) == []
    # so does a link of zero length between them (joints 2 and 3 at one point, a wrist): their
    # capsules overlap at that point in every pose
    wrist = linkage_from_dict({'linkage': {'name': 'wrist', 'task': 'spatial', 'links': [
        _link('l1', 0.1), _link('l2', 0.0, axis=[1.0, 0.0, 0.0]), _link('l3', 0.1)]}})
    dyn, cm = _model(wrist)
    assert self_pairs(wrist, cm.settings.shapes(wrist)) == []
    q = np.array([0.3, 0.7, -1.1])
    assert len(cm.detect(q, margin=0.05)) == 0 and not np.any(cm.torques(q, np.zeros(3))[0])


def test_self_collisions_are_for_spatial_tasks_in_one_line() -> None:
    planar = load_linkage(config_dir() / 'linkages' / 'table1_planar3.yaml')
    with pytest.raises(ConfigError) as err:
        ContactSettings.from_config({'obstacles': [], 'self_collisions': True},
                                    's.yaml: scenario.contacts', planar)
    assert str(err.value) == (
        "s.yaml: scenario.contacts.self_collisions: only for spatial tasks (a planar "
        "linkage's links move in parallel planes and pass over one another, so their "
        "projections overlapping is no collision); remove the key or set it false")
    with pytest.raises(ConfigError, match=r'^s: contacts\.self_collisions: expected '):
        ContactSettings.from_config({'obstacles': [], 'self_collisions': 'yes'},
                                    's: contacts', _fold())
    assert not ContactSettings.from_config({'obstacles': []}, 'c', _fold()).self_collisions


def _every_self_pair(cm: ContactModel, linkage: Linkage, q: np.ndarray
                     ) -> list[tuple[int, list[float], list[float], float]]:
    """Every self pair of ``cm``'s linkage at ``q``, none skipped, each queried afresh (new
    coal placements and result): ``(link a, p_a, normal, gap)`` in the pairs' order, the
    shapes placed by the joints' stacked homogeneous placements as the model stacks them."""
    shapes = cm.settings.shapes(linkage)
    data = cm.model.createData()
    pin.forwardKinematics(cm.model, data, q)
    stacked = np.array([data.oMi[link + 1].homogeneous for link in range(linkage.dof)])
    made = [_coal_shape(shape) for shape in shapes]
    out = []
    for i, j in self_pairs(linkage, shapes):
        poses = []
        for k in (i, j):
            frame = stacked[shapes[k].link]
            rot, origin = frame[:3, :3], frame[:3, 3]
            poses.append(coal.Transform3s(rot @ made[k][1], rot @ made[k][2] + origin))
        res = coal.DistanceResult()
        gap = float(coal.distance(made[i][0], poses[0], made[j][0], poses[1],
                                  distance_request(), res))
        out.append((shapes[i].link, np.array(res.getNearestPoint1()).tolist(),
                    (-np.array(res.normal)).tolist(), gap))
    return out


@pytest.mark.parametrize('name', ['panda_table', 'ur5_table', 'mixed'])
def test_the_culled_pairs_are_every_pairs_bit_for_bit(name: str, tmp_path: Path) -> None:
    """The robots' meshes (32 and 11 pairs) and a box, a capsule, a cylinder, a sphere and a
    mesh (``mixed``: 6 pairs) at random configurations (any joint angles, and near the
    start): the self-contacts ``detect`` keeps below 0, the margin and 50 mm are every pair's
    below it, bit for bit (the same coal queries on the same placements; the broad phase's
    bounds and coal's reused placements and result make no difference), and pairs were
    skipped."""
    if name == 'mixed':
        linkage = _urdf(
            tmp_path, None,
            l1='<collision><origin xyz="0.05 0 0" rpy="0.1 -0.2 0.3"/><geometry>'
               '<box size="0.1 0.02 0.03"/></geometry></collision><collision><origin '
               'xyz="0.05 0.01 0.01" rpy="0.3 1.2 0"/><geometry><capsule radius="0.008" '
               'length="0.09"/></geometry></collision>',
            l3='<collision><origin xyz="0.03 0 0" rpy="0 1.4 0.2"/><geometry>'
               '<cylinder radius="0.012" length="0.06"/></geometry></collision>'
               '<collision><origin xyz="0.07 0.01 0"/><geometry><sphere radius="0.01"/>'
               '</geometry></collision>',
            tip=f'<collision><origin rpy="0.3 -0.1 0.2"/><geometry><mesh filename="{BOX12}" '
                f'scale="0.03 0.02 0.025"/></geometry></collision>')
        assert [getattr(s, 'kind', 'capsule') for s in ContactSettings(
            ContactParams(), (), RADIUS).shapes(linkage)] == [
                'box', 'capsule', 'capsule', 'cylinder', 'capsule', 'mesh']
        settings = ContactSettings(ContactParams(), (), RADIUS, where='test',
                                   self_collisions=True)
        q0 = FOLDED
    else:
        sc = load_scenario(name)
        assert sc.contacts is not None
        linkage, q0 = sc.linkage, sc.q0
        settings = dataclasses.replace(sc.contacts, self_collisions=True)
    cm = ContactModel(LinkageDynamics(linkage).model, linkage, settings)
    assert cm._self is not None
    assert len(cm._self) == {'panda_table': 32, 'ur5_table': 11, 'mixed': 6}[name]
    rng = np.random.default_rng(58)
    kept = queried = calls = 0
    for i in range(300):
        q = (rng.uniform(-math.pi, math.pi, linkage.dof) if i % 2
             else q0 + rng.uniform(-0.5, 0.5, linkage.dof))
        every = _every_self_pair(cm, linkage, q)
        for limit in (0.0, settings.params.margin, 0.05):
            cs = cm.detect(q, margin=limit, jacobians=False)
            mine = cs.obstacles == -1
            got = list(zip(cs.links[mine].tolist(), cs.points[mine].tolist(),
                           cs.normals[mine].tolist(), cs.gaps[mine].tolist(), strict=True))
            assert got == [c for c in every if c[3] < limit], (q, limit)
            kept += len(got)
            queried += cm._self._near_pairs(cm._placements(), cm._self._joint_slot,
                                            cm._self._rows, cm._self._a, cm._self._b, limit,
                                            cm._self._near)
            calls += len(every)
    assert kept > 100 and queried < calls, (kept, queried, calls)


def test_simulate_counts_self_contacts_in_penetration_and_injected_energy(tmp_path: Path
                                                                          ) -> None:
    """``simulate`` of a scenario folding l3 onto l1 (the user pushes the hand along -y):
    with ``self_collisions: true`` the summary has the self-contact's depth and time and no
    energy injected; without it, no contact at all."""
    summaries = {}
    for on in (False, True):
        doc = {'scenario': {
            'name': 'fold', 'linkage': {'name': 'fold', 'task': 'spatial', 'links': [
                _link('l1', 0.1), _link('l2', 0.03), _link('l3', 0.1)]},
            'gravity': [0.0, 0.0, 0.0], 'q0': [0.0, math.pi / 2, math.pi / 2 - 0.3],
            'duration': 1.0, 'dt': 0.001, 'mode': 'penalty',
            'device': {'mass': [1.0, 1.0, 1.0, 0.01, 0.01, 0.01],
                       'wrench_limit': [20.0, 20.0, 20.0, 2.0, 2.0, 2.0]},
            'user': {'type': 'constant_wrench', 'wrench': [0.0, -0.5, 0.0, 0.0, 0.0, 0.0]},
            'control': {'k_pc': [100.0] * 3 + [0.5] * 3, 'b_pc': [70.0] * 3 + [0.375] * 3,
                        'k_tc': 200.0, 'b_tc': 50.0},
            'lmi': {'model': 'eq20', 'update_period': 10},
            've': {'internal_step': 0.001, 'vt_coupling': False},
            'contacts': {'stiffness': 2000.0, 'damping': 20.0, 'link_radius': RADIUS,
                         'obstacles': [], 'self_collisions': on}}}
        path = tmp_path / f'fold_{on}.yaml'
        path.write_text(yaml.safe_dump(doc))
        summaries[on] = simulate(load_scenario(str(path))).summary()
    assert summaries[False]['max_penetration_m'] == 0.0
    assert summaries[False]['contact_time_s'] == 0.0
    s = summaries[True]
    assert 0.0 < s['max_penetration_m'] < RADIUS and s['contact_time_s'] > 0.1
    assert s['energy_injected_j'] == 0.0 and s['energy_dissipated_j'] > 0.0


@pytest.mark.parametrize('name', ['panda_table', 'ur5_table'])
def test_the_shipped_robots_check_their_own_links_and_run_as_without(name: str) -> None:
    """``panda_table`` and ``ur5_table`` ship with self-collisions on (their SRDFs' pairs left
    out); no pair of their links comes near in their runs, so their first 0.5 s (the links
    reach the table at 0.24-0.3 s) are those without self-collisions, every trace column
    bit for bit."""
    sc = dataclasses.replace(load_scenario(name), duration=0.5)
    assert sc.contacts is not None and sc.contacts.self_collisions
    on = simulate(sc).columns
    off = simulate(dataclasses.replace(sc, contacts=dataclasses.replace(
        sc.contacts, self_collisions=False))).columns
    assert list(on) == list(off)
    assert [k for k in on if on[k].tobytes() != off[k].tobytes()] == []
    assert np.nanmax(on['penetration']) > 0.0
