"""Issue 14 items 2 and 3 in real node processes: the linkage as a robot on
``/robot_description`` and ``/tf``, joint states named after the URDF's joints, frames in every
header, markers, and the standard Pose/Twist/Wrench mirrors.

Two lock-step runs of the whole graph (bringup, hosted layout) are recorded: ``wall`` (planar
Table I, VT coupling on, contacts with a wall: ``F_env``) and ``panda_link4`` (spatial, the
Panda's own URDF with side branches). What ``ve_sim`` published is checked against what the
bag holds of the loop's own messages: a link frame composed from ``/tf`` equals the dynamics'
forward kinematics at the joint state of the same stamp; the VT hand's mirrors are the VE's
state (a ``VtPath`` row); every device mirror copies the ``DeviceState`` of its stamp; the
coupling mirror is the ``HandInputs`` sample of its stamp in the VT hand's axes after that
sample. A ``ve_sim`` started alone serves ``/robot_description`` to a subscriber that comes
later (transient local) and its ``/tf`` puts ``vt_hand`` where the dynamics put the grasp
point at ``q0``. Every wait has a deadline; nothing is timed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
import yaml
from procs import stop_process

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bringup.run import run_graph
from haptic_topology.dynamics import LinkageDynamics
from haptic_topology.model import frames
from haptic_topology.model.urdf import RobotDescription, robot_description
from haptic_topology.nodes.markers import FORCE_SCALE
from haptic_topology.nodes.qos import QOS_LATCHED, QOS_TF, QOS_VIZ
from haptic_topology.paths import config_dir
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.vocabulary import (
    MIRROR_TOPICS,
    TOPIC_COMMAND,
    TOPIC_DEVICE_POSE,
    TOPIC_DEVICE_TWIST,
    TOPIC_HAND_INPUTS,
    TOPIC_JOINTS,
    TOPIC_LMI,
    TOPIC_MARKERS,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_STATE,
    TOPIC_TF,
    TOPIC_VT_PATH,
    TOPIC_VT_POSE,
    TOPIC_VT_TWIST,
    TOPIC_WRENCH_APPLIED,
    TOPIC_WRENCH_COUPLING,
    TOPIC_WRENCH_HAND,
    TaskSpace,
)

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
WAIT = 60.0          # s: generous, a loaded machine is only slower
TOL = 1e-12
#: (scenario, simulated seconds) of the recorded lock-step runs.
RUNS = (('wall', 1.0), ('panda_link4', 0.4))
CUSTOM = {TOPIC_STATE: frames.DEVICE_BASE, TOPIC_COMMAND: frames.DEVICE_BASE,
          TOPIC_HAND_INPUTS: frames.DEVICE_BASE}


def _topic(name: str) -> str:
    return '/' + name.lstrip('/')


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class Recorded:
    """One run's bag, decoded per topic (absolute names), and its scenario."""

    def __init__(self, bag: Path, scenario: str) -> None:
        self.bag = bag
        self.scenario: Scenario = load_scenario(scenario)
        self.robot: RobotDescription = robot_description(self.scenario.linkage)
        self.task: TaskSpace = self.scenario.linkage.task
        b = open_bag(bag)
        decode = decoder(bag=b)
        self.msgs: dict[str, list[Any]] = defaultdict(list)
        for m in iter_messages(b):
            self.msgs[m.topic].append(decode(m))

    def __getitem__(self, topic: str) -> list[Any]:
        return self.msgs[_topic(topic)]

    def by_stamp(self, topic: str) -> dict[int, Any]:
        return {_ns(m.header.stamp): m for m in self[topic]}


@pytest.fixture(scope='module')
def runs(tmp_path_factory: pytest.TempPathFactory,
         spare_domains: list[int]) -> dict[str, Recorded]:
    tmp = tmp_path_factory.mktemp('robot_viz')

    def one(scenario: str, duration: float, domain: int) -> Recorded:
        bag = tmp / scenario
        codes = run_graph(scenario, 'penalty', duration, bag, PARAMS, 'hosted',
                          startup_timeout=WAIT, clock='lockstep', domain_id=domain)
        assert all(c == 0 for c in codes.values()), codes
        return Recorded(bag, scenario)

    with ThreadPoolExecutor(len(RUNS)) as pool:
        futures = {sc: pool.submit(one, sc, d, dom)
                   for (sc, d), dom in zip(RUNS, spare_domains, strict=False)}
        return {sc: f.result() for sc, f in futures.items()}


@pytest.fixture(params=[sc for sc, _ in RUNS])
def run(request: pytest.FixtureRequest, runs: dict[str, Recorded]) -> Recorded:
    return runs[request.param]


# -- helpers --------------------------------------------------------------------------------------
def _se3(t: Any) -> pin.SE3:
    r, p = t.rotation, t.translation
    quat = pin.Quaternion(float(r.w), float(r.x), float(r.y), float(r.z))
    assert abs(quat.norm() - 1.0) < 1e-12
    return pin.SE3(quat.matrix(), np.array([p.x, p.y, p.z], dtype=float))


def _compose(edges: dict[str, tuple[str, pin.SE3]], frame: str, world: str) -> pin.SE3:
    """World placement of ``frame`` through the parent -> child transforms ``edges``."""
    out = pin.SE3.Identity()
    while frame != world:
        parent, t = edges[frame]
        out = t * out
        frame = parent
    return out


def _edges(tf: Any) -> dict[str, tuple[str, pin.SE3]]:
    return {t.child_frame_id: (t.header.frame_id, _se3(t.transform)) for t in tf.transforms}


def _pose_se3(p: Any) -> pin.SE3:
    o = p.orientation
    quat = pin.Quaternion(float(o.w), float(o.x), float(o.y), float(o.z))
    return pin.SE3(quat.matrix(), np.array([p.position.x, p.position.y, p.position.z]))


def _vec6(a: Any, b: Any) -> np.ndarray:
    return np.array([a.x, a.y, a.z, b.x, b.y, b.z], dtype=float)


def _assert_se3(a: pin.SE3, b: pin.SE3, what: str) -> None:
    np.testing.assert_allclose(a.translation, b.translation, rtol=0, atol=TOL, err_msg=what)
    np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=TOL, err_msg=what)


def _task_pose_se3(pose: np.ndarray, task: TaskSpace, z: float) -> pin.SE3:
    if task is TaskSpace.PLANAR:
        return pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, float(pose[2])),
                       np.array([pose[0], pose[1], z]))
    return pin.SE3(pin.exp3(np.asarray(pose[3:6], dtype=float)), np.asarray(pose[0:3]))


def _ve_tfs(run: Recorded) -> list[Any]:
    return [m for m in run[TOPIC_TF]
            if any(t.child_frame_id == frames.VT_HAND for t in m.transforms)]


# -- tf2_msgs -------------------------------------------------------------------------------------
def test_tf2_msgs_is_upstreams_type() -> None:
    """The TFMessage the setup builds (or the system has) has upstream's definition: its type
    hash equals the one rosbags computes from its own copy of ROS 2 Jazzy's definitions, so
    RViz or Foxglove on a full ROS install match it."""
    from ament_index_python.packages import get_package_share_directory
    from rosbags.typesys import Stores, get_typestore

    share = Path(get_package_share_directory('tf2_msgs'))
    desc = json.loads((share / 'msg' / 'TFMessage.json').read_text())
    ours = {h['type_name']: h['hash_string'] for h in desc['type_hashes']}
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    assert ours['tf2_msgs/msg/TFMessage'] == jazzy.hash_rihs01('tf2_msgs/msg/TFMessage')


# -- ve_sim alone: a late subscriber --------------------------------------------------------------
@pytest.mark.parametrize('scenario', ['fig8', 'panda_link4'])
def test_robot_description_reaches_a_late_subscriber_and_tf_places_vt_hand(
        scenario: str) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage

    sc = load_scenario(scenario)
    robot = robot_description(sc.linkage)
    hand = LinkageDynamics(sc.linkage).hand_placement(sc.q0)
    proc = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.ve_sim', '--ros-args', '--params-file',
         str(PARAMS), '-p', f'scenario:={scenario}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('robot_viz_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    got: dict[str, list[Any]] = defaultdict(list)

    def keep(key: str) -> Any:
        return lambda msg: got[key].append(msg)

    def wait(cond: Any, what: str) -> None:
        deadline = time.monotonic() + WAIT
        while not cond():
            assert proc.poll() is None, f'{what}: ve_sim died:\n{stop_process(proc)[1][-3000:]}'
            assert time.monotonic() < deadline, f'{what}: not within {WAIT:g} s'
            executor.spin_once(timeout_sec=0.05)

    try:
        node.create_subscription(TFMessage, TOPIC_TF, keep('tf'), QOS_TF)
        node.create_subscription(JointState, TOPIC_JOINTS, keep('joints'),
                                 QOS_VIZ)
        # ve_sim publishes the description once, before its first /tf: join after that
        wait(lambda: len(got['tf']) >= 2 and got['joints'], '/tf and joint states')
        node.create_subscription(String, TOPIC_ROBOT_DESCRIPTION, keep('urdf'),
                                 QOS_LATCHED)
        wait(lambda: got['urdf'], 'the robot description (transient local)')
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        code, out = stop_process(proc)
    assert 'Traceback' not in out, out
    assert [m.data for m in got['urdf']] == [robot.urdf]
    js = got['joints'][-1]
    assert list(js.name) == list(robot.joint_names)
    np.testing.assert_array_equal(js.position, robot.positions(sc.q0))
    edges = _edges(got['tf'][-1])
    assert edges[frames.DEVICE_BASE][0] == 'world'
    _assert_se3(_compose(edges, frames.VT_HAND, 'world'), hand, 'vt_hand at q0')
    for link in sc.linkage.links:
        assert _compose(edges, link.name, 'world') is not None


# -- recorded runs --------------------------------------------------------------------------------
def test_bag_holds_the_description_once_and_every_header_names_its_frame(
        run: Recorded) -> None:
    assert [m.data for m in run[TOPIC_ROBOT_DESCRIPTION]] == [run.robot.urdf]
    for topic, frame in CUSTOM.items():
        assert run[topic] and {m.header.frame_id for m in run[topic]} == {frame}, topic
    for topic in (TOPIC_LMI, TOPIC_VT_PATH, TOPIC_VT_POSE,
                  TOPIC_VT_TWIST):
        assert run[topic] and {m.header.frame_id for m in run[topic]} == {'world'}, topic
    expected = {TOPIC_DEVICE_POSE: frames.DEVICE_BASE,
                TOPIC_DEVICE_TWIST: frames.DEVICE_BASE,
                TOPIC_WRENCH_APPLIED: frames.DEVICE,
                TOPIC_WRENCH_HAND: frames.DEVICE,
                TOPIC_WRENCH_COUPLING: frames.VT_HAND,
                TOPIC_JOINTS: run.robot.root_link}
    for topic, frame in expected.items():
        assert len(run[topic]) >= 3 and {m.header.frame_id for m in run[topic]} == {frame}, \
            topic
    markers = [mk for arr in run[TOPIC_MARKERS] for mk in arr.markers]
    assert markers and {mk.header.frame_id for mk in markers} == {'world'}
    for tf in run[TOPIC_TF]:
        assert all(t.header.frame_id and t.child_frame_id for t in tf.transforms)
    parents = {t.child_frame_id: t.header.frame_id
               for tf in run[TOPIC_TF] for t in tf.transforms}
    assert parents[frames.DEVICE] == frames.DEVICE_BASE
    assert parents[frames.DEVICE_BASE] == 'world'
    assert parents[frames.VT_HAND] == run.scenario.linkage.grasp_link
    assert parents[run.robot.root_link] == 'world'
    for js in run[TOPIC_JOINTS]:
        assert list(js.name) == list(run.robot.joint_names)


def test_tf_link_frames_equal_the_forward_kinematics_of_the_joint_state(
        run: Recorded) -> None:
    """Every /tf of the VE: each link frame composed from the world down equals the
    dynamics' oMi at the joint positions published with the same stamp, and vt_hand equals
    the grasp frame there and the VT hand pose mirror of that stamp."""
    lk = run.scenario.linkage
    dyn = LinkageDynamics(lk)
    joints = run.by_stamp(TOPIC_JOINTS)
    vt = run.by_stamp(TOPIC_VT_POSE)
    tfs = _ve_tfs(run)
    assert len(tfs) >= 3
    moved = 0
    for tf in tfs:
        stamp = _ns(tf.transforms[0].header.stamp)
        assert {_ns(t.header.stamp) for t in tf.transforms} == {stamp}
        q = np.asarray(joints[stamp].position[:lk.dof], dtype=float)
        np.testing.assert_array_equal(joints[stamp].position[lk.dof:], run.robot.locked)
        moved += bool(np.any(q != run.scenario.q0))
        edges = _edges(tf)
        pin.forwardKinematics(dyn.model, dyn.data, q)
        for j, link in enumerate(lk.links, start=1):
            _assert_se3(_compose(edges, link.name, 'world'), dyn.data.oMi[j],
                        f'{link.name} at {q.tolist()}')
        hand = _compose(edges, frames.VT_HAND, 'world')
        _assert_se3(hand, dyn.hand_placement(q), 'vt_hand')
        _assert_se3(hand, _pose_se3(vt[stamp].pose), 'vt_hand pose mirror')
    assert moved >= 2, 'the VT never moved while /tf was recorded'


def test_vt_hand_mirrors_are_the_ve_state(run: Recorded) -> None:
    """Each VT hand pose mirror is the VE's grasp frame after an input it consumed (a VtPath
    row) or at q0; its twist is the grasp point's twist at the joint state of its stamp."""
    lk, task = run.scenario.linkage, run.task
    dyn = LinkageDynamics(lk)
    z = float(dyn.hand_placement(run.scenario.q0).translation[2])
    m = task.dim
    rows = [np.asarray(p.hand_pose[i * m:(i + 1) * m]) for p in run[TOPIC_VT_PATH]
            for i in range(len(p.hand_input_seqs))]
    known = [dyn.hand_placement(run.scenario.q0)] + [_task_pose_se3(r, task, z) for r in rows]
    positions = np.array([k.translation for k in known])
    joints = run.by_stamp(TOPIC_JOINTS)
    on_path = 0
    for msg in run[TOPIC_VT_POSE]:
        placement = _pose_se3(msg.pose)
        i = int(np.argmin(np.linalg.norm(positions - placement.translation, axis=1)))
        _assert_se3(placement, known[i], 'VT hand mirror against the VE')
        on_path += i > 0
    assert on_path >= 2
    for msg in run[TOPIC_VT_TWIST]:
        js = joints[_ns(msg.header.stamp)]
        q, dq = np.asarray(js.position[:lk.dof]), np.asarray(js.velocity[:lk.dof])
        np.testing.assert_allclose(_vec6(msg.twist.linear, msg.twist.angular),
                                   frames.spatial(dyn.hand_twist(q, dq), task), rtol=0,
                                   atol=TOL)


def test_device_mirrors_copy_the_device_state_of_their_stamp(run: Recorded) -> None:
    task = run.task
    dyn = LinkageDynamics(run.scenario.linkage)
    z = float(dyn.hand_placement(run.scenario.q0).translation[2])
    states = run.by_stamp(TOPIC_STATE)
    twists = run.by_stamp(TOPIC_DEVICE_TWIST)
    hands = run.by_stamp(TOPIC_WRENCH_HAND)
    device_tf = {_ns(t.header.stamp): t for tf in run[TOPIC_TF]
                 for t in tf.transforms if t.child_frame_id == frames.DEVICE}
    poses = run[TOPIC_DEVICE_POSE]
    assert len(poses) >= 3 and len(run[TOPIC_WRENCH_APPLIED]) >= 3
    for msg in poses:
        stamp = _ns(msg.header.stamp)
        st = states[stamp]
        expected = _task_pose_se3(np.asarray(st.pose), task, z)
        _assert_se3(_pose_se3(msg.pose), expected, 'device pose mirror')
        _assert_se3(_se3(device_tf[stamp].transform), expected, 'device_base -> device')
        tw = twists[stamp].twist
        np.testing.assert_array_equal(_vec6(tw.linear, tw.angular),
                                      frames.spatial(np.asarray(st.twist), task))
        rot = expected.rotation
        w = hands[stamp].wrench
        np.testing.assert_allclose(
            _vec6(w.force, w.torque),
            frames.wrench_in_frame(np.asarray(st.hand_wrench), rot, task), rtol=0, atol=TOL)
    for msg in run[TOPIC_WRENCH_APPLIED]:
        st = states[_ns(msg.header.stamp)]
        rot = _task_pose_se3(np.asarray(st.pose), task, z).rotation
        w = msg.wrench
        np.testing.assert_allclose(
            _vec6(w.force, w.torque),
            frames.wrench_in_frame(np.asarray(st.applied_wrench), rot, task), rtol=0,
            atol=TOL)
        # in the world's axes again: the applied wrench as the state carries it
        back = np.concatenate([rot @ _vec6(w.force, w.torque)[0:3],
                               rot @ _vec6(w.force, w.torque)[3:6]])
        np.testing.assert_allclose(back, frames.spatial(np.asarray(st.applied_wrench), task),
                                   rtol=0, atol=1e-12)


def test_coupling_mirror_is_the_hand_input_in_the_vt_hand_axes(run: Recorded) -> None:
    task, m = run.task, run.task.dim
    dyn = LinkageDynamics(run.scenario.linkage)
    z = float(dyn.hand_placement(run.scenario.q0).translation[2])
    samples: dict[int, tuple[int, np.ndarray]] = {}
    for h in run[TOPIC_HAND_INPUTS]:
        for i, (seq, stamp) in enumerate(zip(h.state_seq, h.stamp, strict=True)):
            samples[_ns(stamp)] = (int(seq), np.asarray(h.coupling_wrench[i * m:(i + 1) * m]))
    path = {int(s): np.asarray(p.hand_pose[i * m:(i + 1) * m])
            for p in run[TOPIC_VT_PATH] for i, s in enumerate(p.hand_input_seqs)}
    checked = 0
    for msg in run[TOPIC_WRENCH_COUPLING]:
        seq, f_pc = samples[_ns(msg.header.stamp)]
        if seq - 1 not in path:          # the first input: the VE was still at q0
            continue
        rot = _task_pose_se3(path[seq - 1], task, z).rotation
        w = msg.wrench
        np.testing.assert_allclose(_vec6(w.force, w.torque),
                                   frames.wrench_in_frame(f_pc, rot, task), rtol=0, atol=TOL)
        checked += 1
    assert checked >= 3
    if run.scenario.vt_coupling:
        assert any(np.any(samples[_ns(msg.header.stamp)][1] != 0.0)
                   for msg in run[TOPIC_WRENCH_COUPLING])


def test_force_arrows_at_their_points(run: Recorded) -> None:
    """The F_h and u arrows start at the device ghost and are FORCE_SCALE m per N long; F_pc
    and F_env start at the grasp point; F_env appears where the run touches an obstacle."""
    seen: dict[str, int] = defaultdict(int)
    for arr in run[TOPIC_MARKERS]:
        by_ns = {mk.ns: mk for mk in arr.markers}
        for ns in ('F_h', 'u', 'F_pc', 'F_env'):
            mk = by_ns[ns]
            if mk.action != mk.ADD:
                continue
            seen[ns] += 1
            start, end = (np.array([p.x, p.y, p.z]) for p in mk.points)
            at = by_ns['device'].pose.position if ns in ('F_h', 'u') else \
                by_ns['grasp'].pose.position
            np.testing.assert_allclose(start, [at.x, at.y, at.z], rtol=0, atol=TOL)
            if ns == 'F_h':   # the scenario's user: a constant 0.4 N along x
                np.testing.assert_allclose(end - start, [FORCE_SCALE * 0.4, 0.0, 0.0],
                                           rtol=0, atol=1e-12)
    assert seen['F_h'] >= 3 and seen['u'] >= 3
    assert seen['F_pc'] >= 3 or not run.scenario.vt_coupling
    if run.scenario.contacts is not None:
        assert seen['F_env'] >= 1, 'the run never rendered a contact'
    else:
        assert seen['F_env'] == 0


def test_recorded_topics_include_the_robot_and_the_mirrors(run: Recorded) -> None:
    from haptic_topology.nodes.recorder import RECORDED

    for topic in (TOPIC_ROBOT_DESCRIPTION, TOPIC_TF, *MIRROR_TOPICS):
        assert topic in RECORDED and run[topic], topic
    # the bag offers /robot_description transient local again (ros2 bag play: a late RViz
    # still gets it), the others volatile
    meta = yaml.safe_load((run.bag / 'metadata.yaml').read_text())
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
           for t in meta['rosbag2_bagfile_information']['topics_with_message_count']}
    assert qos[TOPIC_ROBOT_DESCRIPTION][0]['durability'] == 'transient_local'
    assert qos[TOPIC_TF][0]['durability'] == 'volatile'
