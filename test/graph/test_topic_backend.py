"""The ``ros_topics`` backend (``haptic_topology/nodes/topic_backend.py``) against a device
that plays a haptic device with a ROS 2 driver: the simulated maglev behind
``PoseStamped``/``TwistStamped``/``WrenchStamped`` topics, in a process of its own
(``python -m haptic_topology.nodes.topic_device``), publishing in millimetres with its axes
turned and its base offset from the task's (the backend's mapping both ways).

* options: every bad entry is refused naming the field and what it must be;
* conformance (``backend_conformance.py``, the checks the simulated maglev and the example
  backend pass): clamping, non-finite writes, watchdog, lifecycle, with the driver's core loop
  in this process and what the device process received as the device side;
* stale device data: the device process stopped (SIGSTOP) -> every reading FAULT with the
  reason, zero written from the next cycle on, back to the command (faded in) once the data
  return; the device process killed and started again -> the same, and the new process gets
  the command;
* the node graph: ``device_driver`` with ``backend: ros_topics`` in its own process, driven
  through its lifecycle by its services, this process playing the controller.

Real processes and DDS (the session's domain, ``conftest.py``), no ROS mocks; every wait has
a deadline; the assertions are on values.
"""

from __future__ import annotations

import itertools
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from backend_conformance import (
    Bench,
    Subject,
    check_clamping,
    check_lifecycle,
    check_nonfinite,
    check_watchdog,
    same,
)
from procs import stop_process

from haptic_topology.bringup.watch import GraphWatcher
from haptic_topology.device.backend import BackendConfig, backend_class, create_backend
from haptic_topology.device.pacing import DeadlinePacer
from haptic_topology.errors import DeviceError
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import DeviceStatus

pytestmark = pytest.mark.graph

STATUS = 'topic_device: device'
#: Longest wait (s) for a process or DDS to do what it should: generous, so a loaded machine
#: runs slower, never differently.
WAIT = 60.0


def topic_options(prefix: str, task_dim: int = 3, **extra: Any) -> dict[str, Any]:
    """Options of a device in mm, axes turned by +90 degrees about z, base offset from the
    task's; with a force sensor; stale after 2 s unless ``extra`` says otherwise (the
    conformance checks are not about staleness, and this machine is loaded)."""
    opts: dict[str, Any] = {
        'pose_topic': f'{prefix}/device/pose', 'twist_topic': f'{prefix}/device/twist',
        'wrench_topic': f'{prefix}/device/wrench', 'command_topic': f'{prefix}/device/cmd',
        'axes': ['y', '-x', 'z'], 'scale': 0.001, 'force_scale': 1.0,
        'torque_scale': 0.001, 'stale_ms': 2000.0, 'connect_timeout_ms': 1000.0 * WAIT,
        'origin': [0.01, -0.02, 0.3] if task_dim == 3 else [0.01, -0.02, 0.05, 0.1, 0.0, 0.2],
    }
    if task_dim == 6:
        # a rotation matrix instead of axis names: 30 degrees about x
        c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
        opts['axes'] = [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    opts.update(extra)
    return opts


class TopicDevice:
    """The device process (module doc) and a watcher of its ``/diagnostics``: a
    :class:`backend_conformance.DeviceSide`."""

    def __init__(self, scenario: str, options: dict[str, Any], record: Path) -> None:
        self.record = record
        self.options = options
        self.scenario = scenario
        self.watcher = GraphWatcher('topic_device_watch', lifecycle_nodes=())
        self.proc: subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'haptic_topology.nodes.topic_device', '--scenario',
             self.scenario, '--options', yaml.safe_dump(self.options, default_flow_style=True),
             '--record', str(self.record)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)

    def kill(self) -> None:
        """SIGKILL the process (it writes no record); :meth:`start` makes a new one."""
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(10)
        self.proc = None

    def alive(self) -> None:
        if self.proc is not None and self.proc.poll() is not None:
            out = self.proc.stdout.read().decode(errors='replace') if self.proc.stdout else ''
            raise AssertionError(f'topic_device exited ({self.proc.returncode}):\n{out}')

    def status(self) -> dict[str, str]:
        """The newest status of the current process ({} before its first)."""
        st = self.watcher.status.get(STATUS, {})
        return st if self.proc is not None and st.get('pid') == str(self.proc.pid) else {}

    def wait(self, cond: Any, what: str) -> None:
        self.watcher.alive = self.alive
        self.watcher.wait(cond, WAIT, what)

    # -- DeviceSide --------------------------------------------------------------------------
    def after_cycle(self, backend: Any) -> None:
        pass

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        st = self.status()
        if int(st.get('last_command_ns', '-1')) < after_ns or not st.get('last_command'):
            return False
        return same(np.array([float(v) for v in st['last_command'].split()]), expected)

    def poll(self, seconds: float) -> None:
        self.alive()
        self.watcher.spin(seconds)

    def stop(self) -> dict[str, Any]:
        """SIGINT the process; its record (it writes it on the way out)."""
        assert self.proc is not None
        code, out = stop_process(self.proc, timeout=20)
        assert code == 0, out
        with np.load(self.record) as rec:
            return {k: rec[k] for k in rec.files}

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        rec = self.stop()
        return rec['cmd_t'], rec['cmd_task']

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            stop_process(self.proc, timeout=20)
        self.watcher.close()


@pytest.fixture
def device_factory(tmp_path: Path) -> Iterator[Any]:
    made: list[TopicDevice] = []

    def make(scenario: str, options: dict[str, Any]) -> TopicDevice:
        dev = TopicDevice(scenario, options, tmp_path / f'record{len(made)}.npz')
        made.append(dev)
        return dev

    yield make
    for dev in made:
        dev.close()


def _paced() -> Any:
    pacer = DeadlinePacer(0.001)
    return lambda: pacer.wait()


# -- options -----------------------------------------------------------------------------------
def _config(options: dict[str, Any], scenario: str = 'fig8') -> BackendConfig:
    sc = load_scenario(scenario)
    return BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), options,
                         sc.source)


BASE = {'pose_topic': '/d/pose', 'twist_topic': '/d/twist', 'command_topic': '/d/cmd'}


@pytest.mark.parametrize(('options', 'text'), [
    ({'twist_topic': '/t', 'command_topic': '/c'},
     'backend_options.pose_topic: expected a topic name (text), got None'),
    ({**BASE, 'wrench_topic': 3}, 'backend_options.wrench_topic: expected a topic name'),
    ({**BASE, 'axes': ['x', 'x', 'z']}, 'backend_options.axes: expected 3 signed device axis '
     'names such as [x, -z, y] (task x, y, z), or a 3 x 3 rotation matrix (rows), '
     "right-handed (orthonormal, determinant +1), got ['x', 'x', 'z']"),
    ({**BASE, 'axes': ['x', 'y', '-z']}, "(orthonormal, determinant +1), got ['x', 'y', '-z']"),
    ({**BASE, 'axes': ['x', 'y', 'w']}, "got ['x', 'y', 'w']"),
    ({**BASE, 'axes': [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}, 'determinant +1), got [[1, 0, 0], '),
    ({**BASE, 'scale': 0}, 'backend_options.scale: expected a number in (0, inf], got 0'),
    ({**BASE, 'force_scale': math.nan}, 'backend_options.force_scale: expected a number'),
    ({**BASE, 'stale_ms': 20000}, 'backend_options.stale_ms: expected a number in '
     '(0, 10000], got 20000'),
    ({**BASE, 'qos': 'fast'}, "backend_options.qos: expected best_effort or reliable, got "
     "'fast'"),
    ({**BASE, 'origin': [0.0, 0.0]}, 'backend_options.origin: expected 3 numbers: x, y '
     '(m), theta (rad), got [0.0, 0.0]'),
    ({**BASE, 'connect_timeout_ms': -1}, 'backend_options.connect_timeout_ms: expected a '
     'number in [0, 600000]'),
    ({**BASE, 'node_name': 'a b'}, 'backend_options.node_name: expected a ROS node name'),
    ({**BASE, 'pose_tpoic': '/x'}, "backend_options: unknown option 'pose_tpoic'"),
    ({**BASE, 'twist_topic': '/d/pose'}, 'backend_options: expected distinct topics'),
])
def test_bad_options_are_refused_naming_the_field(options: dict[str, Any], text: str) -> None:
    with pytest.raises(DeviceError) as err:
        create_backend('ros_topics').configure(_config(options))
    assert str(err.value).startswith('ros_topics: ') and text in str(err.value), err.value


def test_spatial_origin_takes_six_numbers_and_the_backend_is_built_in() -> None:
    assert backend_class('ros_topics').__name__ == 'RosTopicBackend'
    with pytest.raises(DeviceError, match='origin: expected 6 numbers'):
        create_backend('ros_topics').configure(_config({**BASE, 'origin': [0, 0, 0]},
                                                       'spatial_arm4'))
    be = create_backend('ros_topics')
    be.configure(_config(BASE, 'spatial_arm4'))
    assert be.hardware_id == 'ros_topics spatial /d/pose'
    with pytest.raises(DeviceError, match='write\\(\\) while not active \\(before activate'):
        be.write(np.zeros(6))
    with pytest.raises(DeviceError, match='read\\(\\) while not active \\(before activate'):
        be.read(0.001)
    be.deactivate()                                      # before activate: harmless
    be.cleanup()


# -- conformance against the device process ----------------------------------------------------
CHECKS = {'clamping': check_clamping, 'nonfinite': check_nonfinite,
          'watchdog': check_watchdog, 'lifecycle': check_lifecycle}


@pytest.mark.parametrize(('scenario', 'check'), [
    ('fig8', 'clamping'), ('fig8', 'nonfinite'), ('fig8', 'watchdog'), ('fig8', 'lifecycle'),
    ('spatial_arm4', 'clamping'), ('spatial_arm4', 'watchdog')])
def test_backend_conforms(scenario: str, check: str, device_factory: Any,
                          topic_prefix: str) -> None:
    dim = load_scenario(scenario).linkage.task.dim
    opts = topic_options(topic_prefix, dim)
    device = device_factory(scenario, opts)
    bench = Bench(Subject('ros_topics', lambda: device, opts, scenario, _paced()), device)
    try:
        CHECKS[check](bench)
    finally:
        bench.backend.cleanup()             # harmless after the check's own
    if check == 'nonfinite':
        assert bench.backend.nonfinite_writes == 20     # counted, sent as 0 on those axes
    rec = np.load(device.record)
    assert int(rec['frame_mismatches']) == 0       # commands in the device's own frame


def test_readings_are_the_device_state_mapped_to_the_task(device_factory: Any,
                                                         topic_prefix: str) -> None:
    """Parked, the device process publishes its initial pose and the simulated user's hand
    wrench in device units and axes: the backend reads them back as task vectors."""
    opts = topic_options(topic_prefix)
    device_factory('fig8', opts)
    cfg = _config(opts)
    be = create_backend('ros_topics')
    be.configure(cfg)
    be.activate()
    try:
        r = be.read(0.001)
        assert r.status == DeviceStatus.OK
        np.testing.assert_allclose(r.pose, cfg.initial_pose, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(r.twist, 0.0, atol=1e-15)
        np.testing.assert_allclose(r.hand_wrench, [0.4, 0.0, 0.0], rtol=0.0, atol=1e-12)
    finally:
        be.cleanup()


def test_invalid_device_samples_fault_and_are_never_passed_on(topic_prefix: str) -> None:
    """A device that publishes a NaN position, an unset (all-zero) quaternion or a NaN twist:
    from the next reading on FAULT with the reason naming the topic, the newest valid pose
    repeated with zero twist (nothing non-finite passed on); valid samples again clear it.
    The samples come from this process (its own rclpy context)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, TwistStamped

    from haptic_topology.device.topic_mapping import Reliability
    from haptic_topology.nodes.qos import topic_qos

    opts = {'pose_topic': f'{topic_prefix}/pose', 'twist_topic': f'{topic_prefix}/twist',
            'command_topic': f'{topic_prefix}/cmd', 'stale_ms': 5000.0,
            'connect_timeout_ms': 1000.0 * WAIT}
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('fake_device', context=context)
    qos = topic_qos(Reliability.BEST_EFFORT)
    pose_pub = node.create_publisher(PoseStamped, opts['pose_topic'], qos)
    twist_pub = node.create_publisher(TwistStamped, opts['twist_topic'], qos)
    pose, twist = PoseStamped(), TwistStamped()

    def publish(p: tuple[float, ...], q: tuple[float, ...], v: float) -> None:
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = p
        o = pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        twist.twist.linear.x = v
        pose_pub.publish(pose)
        twist_pub.publish(twist)

    be = create_backend('ros_topics')
    be.configure(_config(opts))
    result: list[BaseException] = []
    thread = threading.Thread(target=lambda: _capture(be.activate, result))
    thread.start()
    good = ((0.05, 0.04, 0.0), (0.0, 0.0, 0.0, 1.0), 0.1)
    try:
        deadline = time.monotonic() + WAIT
        while thread.is_alive():                # activate waits for the first samples
            assert time.monotonic() < deadline, 'activate did not return'
            publish(*good)
            time.sleep(0.005)
        assert not result, result

        def until(sample: tuple[Any, ...], fault: bool) -> Any:
            deadline = time.monotonic() + WAIT
            while True:
                publish(*sample)
                r = be.read(0.001)
                if bool(r.status & DeviceStatus.FAULT) == fault:
                    return r
                assert time.monotonic() < deadline, f'{sample}: fault {fault} not seen'
                time.sleep(0.002)

        r = until(good, False)
        np.testing.assert_allclose(r.pose, [0.05, 0.04, 0.0], atol=1e-15)
        valid = r.pose.copy()
        for bad, topic in ((((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.1), 'pose'),
                           (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), 0.1), 'pose'),
                           ((good[0], good[1], math.inf), 'twist')):
            r = until(bad, True)
            assert be.fault_reason().startswith('device data not valid: ')
            assert be.fault_reason().endswith(f'on {opts[f"{topic}_topic"]}')
            np.testing.assert_array_equal(r.pose, valid)
            assert not r.twist.any() and not r.hand_wrench.any()
            until(good, False)
        assert be.invalid_samples >= 3
    finally:
        thread.join(WAIT)
        be.cleanup()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def _capture(fn: Any, errors: list[BaseException]) -> None:
    try:
        fn()
    except BaseException as exc:
        errors.append(exc)


# -- stale device data, device restart ---------------------------------------------------------
class Cycler:
    """The driver's core loop over a ``ros_topics`` backend at 1 kHz in this thread, every
    state answered with ``u``; checks every cycle: finite and within the limit, zero written
    after every reading that carried FAULT."""

    def __init__(self, bench: Bench, u: np.ndarray) -> None:
        self.bench = bench
        self.u = u
        self.faulted_before = False
        self.fault_readings = 0
        self.zero_after_fault = 0
        self.reasons: set[str] = set()

    def cycle(self) -> tuple[bool, np.ndarray]:
        tick = self.bench.cycle(self.u)
        w = self.bench.written[-1]
        assert np.all(np.isfinite(w)) and np.all(np.abs(w) <= self.bench.limit)
        if self.faulted_before:
            assert not w.any(), f'{w} written after a faulted reading'
            self.zero_after_fault += 1
        fault = bool(tick.status & DeviceStatus.FAULT)
        if fault:
            self.fault_readings += 1
            self.reasons.add(self.bench.backend.fault_reason())
            r = tick.reading
            assert np.all(np.isfinite(np.concatenate([r.pose, r.twist, r.hand_wrench])))
        self.faulted_before = fault
        return fault, w

    def until(self, cond: Any, what: str) -> None:
        deadline = time.monotonic() + WAIT
        while not cond(*self.cycle()):
            assert time.monotonic() < deadline, f'{what}: not within {WAIT:g} s'


def test_stale_or_restarted_device_faults_writes_zero_and_recovers(
        device_factory: Any, topic_prefix: str) -> None:
    """Device process stopped -> FAULT (stale) readings, zero written from the next cycle on,
    the reason names the stale topic; continued -> the fault clears and the output fades back
    to the command; killed -> the same; a new device process -> the backend recovers by
    itself and the new process gets the command, clamped, never non-finite."""
    opts = topic_options(topic_prefix, stale_ms=100.0)
    device = device_factory('fig8', opts)
    bench = Bench(Subject('ros_topics', lambda: device, opts, 'fig8', _paced()), device)
    u = np.array([3.0, -2.0, 0.2])
    bench.activate()
    try:
        bench.engage()
        cyc = Cycler(bench, u)

        def back(fault: bool, w: np.ndarray) -> bool:
            return not fault and bool(np.array_equal(w, u))

        cyc.until(back, 'applying the command')

        def device_has(since: int, polls: Any) -> Any:
            """The device process's newest command is u, got at ``since`` or later (its
            status comes through DDS: asked every 20th cycle)."""
            def cond(fault: bool, w: np.ndarray) -> bool:
                if next(polls) % 20:
                    return False
                device.poll(0.0)
                return bool(device.got(u, since))
            return cond

        for event in ('stop', 'kill'):
            if event == 'stop':
                assert device.proc is not None
                os.kill(device.proc.pid, signal.SIGSTOP)
            else:
                device.kill()
            cyc.until(lambda fault, w: fault, f'{event}: a FAULT reading')
            for _ in range(20):
                assert cyc.cycle()[0]           # stays faulted while the device is away
            inputs = (opts['pose_topic'], opts['twist_topic'], opts['wrench_topic'])
            assert any(r.startswith('device data stale (') and any(t in r for t in inputs)
                       for r in cyc.reasons), cyc.reasons
            assert 'device fault: ' in bench.loop.health()[1]
            if event == 'stop':
                assert device.proc is not None
                os.kill(device.proc.pid, signal.SIGCONT)
            else:
                device.start()
            cyc.until(lambda fault, w: not fault, f'{event}: data fresh again')
            first = bench.written[-1].copy()
            cyc.until(back, f'{event}: the command faded back in')
            assert np.all(np.abs(first) < np.abs(u))        # faded in, not a step
            # Cycle on until the device process has the command itself, not for a fixed
            # count: a loaded machine can starve it past the stale limit once more (a second
            # fault, zero, a second fade), and it must get u all the same.
            cyc.until(device_has(time.monotonic_ns(), itertools.count(1)),
                      f'{event}: the device process gets the command')
            for _ in range(100):
                cyc.cycle()
        assert cyc.zero_after_fault >= 40 and bench.loop.device_faults >= 2
    except BaseException:
        bench.backend.cleanup()
        raise
    bench.release()
    bench.backend.cleanup()
    rec = device.stop()                      # the restarted process's record
    got = rec['cmd_task']
    assert np.all(np.isfinite(got)) and np.all(np.abs(got) <= bench.limit)
    assert np.any(np.all(np.abs(got - u) <= 1e-12, axis=1)), 'the new device never got u'
    assert not got[-1].any()


# -- the node graph: device_driver with backend ros_topics -------------------------------------
class Controller:
    """Plays the controller of the separate layout: answers every device state with
    ``wrench`` (None: silent; NaN allowed: the driver must refuse it), from its own rclpy
    context and thread; keeps ``(seq, status, applied wrench)`` of every state it got."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.experimental import EventsExecutor

        from haptic_topology.nodes.qos import QOS_LOOP
        from haptic_topology.vocabulary import TOPIC_COMMAND, TOPIC_STATE
        from haptic_topology_msgs.msg import DeviceCommand, DeviceState

        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('test_topic_controller', context=self.context)
        self._cmd = DeviceCommand()
        self.pub = self.node.create_publisher(DeviceCommand, TOPIC_COMMAND,
                                              QOS_LOOP)
        self.node.create_subscription(DeviceState, TOPIC_STATE, self._on_state,
                                      QOS_LOOP)
        self.wrench: list[float] | None = None
        self.states: list[tuple[int, int, list[float]]] = []
        self.id = int(np.random.default_rng().integers(1, 2 ** 62))
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop:
            self.executor.spin_once(timeout_sec=0.05)

    def _on_state(self, msg: Any) -> None:
        self.states.append((int(msg.seq), int(msg.status), list(msg.applied_wrench)))
        w = self.wrench
        if w is None:
            return
        c = self._cmd
        c.header.stamp.sec, c.header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
        c.state_seq = msg.seq
        c.controller_id = self.id
        c.mode = 0
        c.task_dim = 3
        c.wrench = w
        c.vt_pose = [0.0] * 3
        c.vt_twist = [0.0] * 3
        c.update_age = 0.0
        self.pub.publish(c)

    def newest(self) -> tuple[int, int, list[float]] | None:
        return self.states[-1] if self.states else None

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


def test_device_driver_runs_the_topic_backend_through_its_lifecycle(
        tmp_path: Path, device_factory: Any, topic_prefix: str) -> None:
    """``device_driver`` (separate layout, ``autostart: false``) with ``backend: ros_topics``
    against the device process, this process playing the controller; lifecycle transitions
    through the driver's services: configure (no device I/O yet) -> activate (the backend's
    node subscribes, zero wrench while idle) -> commands of 1e9 N (the device gets the
    limit), NaN commands (refused: the device gets zero, never NaN), silence (watchdog:
    zero), a command again (the device gets it exactly, through the units and axes) -> the
    device process stopped (states FAULT, zero applied from the next state on, diagnostics
    ERROR naming the stale data) and continued, killed and started again (recovers) ->
    deactivate (the device gets zero) -> cleanup (the backend's node is gone) -> configure
    and activate again (commands flow again) -> deactivate -> cleanup; SIGINT ends the driver
    with 0."""
    from haptic_topology.paths import config_dir

    limit = np.asarray(load_scenario('fig8').device.wrench_limit, dtype=float)
    opts = topic_options(topic_prefix, stale_ms=100.0, node_name='ros_topics_test')
    device = device_factory('fig8', opts)
    params = tmp_path / 'driver.yaml'
    params.write_text(yaml.safe_dump({'device_driver': {'ros__parameters': {
        'scenario': 'fig8', 'host_controller': False, 'autostart': False,
        'backend': 'ros_topics', 'min_subscribers': 1, 'watchdog_timeout': 0.02,
        'backend_options': yaml.safe_dump(opts, default_flow_style=True).strip()}}}),
        encoding='utf-8')
    driver = subprocess.Popen(
        [sys.executable, '-m', 'haptic_topology.nodes.device_driver', '--ros-args',
         '--params-file', str(config_dir() / 'haptic_topology.yaml'), '--params-file',
         str(params)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        start_new_session=True)
    ctl = Controller()
    watch = device.watcher

    def alive() -> None:
        device.alive()
        if driver.poll() is not None:
            out = driver.stdout.read().decode(errors='replace') if driver.stdout else ''
            raise AssertionError(f'device_driver exited ({driver.returncode}):\n{out}')

    def wait(cond: Any, what: str) -> None:
        watch.alive = alive
        watch.wait(cond, WAIT, what)

    def dev_status() -> dict[str, str]:
        st = watch.status.get('device_driver: loop', {})
        return st if st.get('pid') == str(driver.pid) else {}

    def device_got(u: list[float], after: int) -> Any:
        def cond() -> bool:
            st = device.status()
            return (int(st.get('last_command_ns', '-1')) >= after
                    and st.get('last_command', '') != ''
                    and np.allclose([float(v) for v in st['last_command'].split()], u,
                                    rtol=1e-12, atol=1e-12))
        return cond

    def state_with(bit: int, present: bool, after: int) -> Any:
        def cond() -> bool:
            s = ctl.newest()
            return s is not None and s[0] > after and bool(s[1] & bit) == present
        return cond

    try:
        watch_lc = GraphWatcher('topic_driver_watch', lifecycle_nodes=('device_driver',))
        watch_lc.alive = alive
        try:
            watch_lc.wait_lifecycle('device_driver', ('unconfigured',), WAIT)
            watch_lc.change_state('device_driver', 'configure', WAIT)
            wait(lambda: device.status().get('engaged') == 'false', 'device process up')
            assert device.status().get('commands') == '0'    # configure does no device I/O
            watch_lc.change_state('device_driver', 'activate', WAIT)
            wait(lambda: int(device.status().get('commands', '0')) > 0, 'idle zero commands')
            wait(lambda: ctl.newest() is not None, 'device states')
            assert ctl.newest()[1] & int(DeviceStatus.IDLE)  # type: ignore[index]

            ctl.wrench = [1e9, -1e9, 1e9]                      # clamped to the limit
            mark = time.monotonic_ns()
            wait(device_got([limit[0], -limit[1], limit[2]], mark), 'the device at the limit')
            ctl.wrench = [math.nan, 1.0, 1.0]                  # refused: commands stop
            mark = time.monotonic_ns()
            wait(device_got([0.0, 0.0, 0.0], mark), 'NaN commands: the device at zero')
            wait(lambda: int(dev_status().get('rejected_commands', '0')) > 0, 'refusals')
            ctl.wrench = None                                  # silent
            mark = time.monotonic_ns()
            wait(device_got([0.0, 0.0, 0.0], mark), 'silence: the device at zero')
            u = [2.0, -1.5, 0.25]
            ctl.wrench = u
            mark = time.monotonic_ns()
            wait(device_got(u, mark), 'the command again, exactly')
            wait(lambda: int(dev_status().get('watchdog_trips', '0')) >= 1,
                 'the driver counts the watchdog trip')

            for event in ('stop', 'kill'):
                seq = ctl.newest()[0]  # type: ignore[index]
                if event == 'stop':
                    assert device.proc is not None
                    os.kill(device.proc.pid, signal.SIGSTOP)
                else:
                    device.kill()
                wait(state_with(int(DeviceStatus.FAULT), True, seq), f'{event}: FAULT states')
                wait(lambda: 'device data stale' in dev_status().get('device_fault', ''),
                     f'{event}: diagnostics name the stale data')
                seq = ctl.newest()[0]  # type: ignore[index]
                if event == 'stop':
                    assert device.proc is not None
                    os.kill(device.proc.pid, signal.SIGCONT)
                else:
                    device.start()
                wait(state_with(int(DeviceStatus.FAULT), False, seq), f'{event}: fault over')
                mark = time.monotonic_ns()
                wait(device_got(u, mark), f'{event}: the device gets the command again')

            for rnd in range(2):
                mark = time.monotonic_ns()
                watch_lc.change_state('device_driver', 'deactivate', WAIT)
                wait(device_got([0.0, 0.0, 0.0], mark), 'deactivate: the device at zero')
                watch_lc.change_state('device_driver', 'cleanup', WAIT)
                wait(lambda: int(device.status().get('command_publishers', '1')) == 0,
                     "cleanup: the backend's node is gone")
                if rnd == 1:
                    break
                watch_lc.change_state('device_driver', 'configure', WAIT)
                watch_lc.change_state('device_driver', 'activate', WAIT)
                mark = time.monotonic_ns()
                wait(device_got(u, mark), 'activated again: the device gets the command')
        finally:
            watch_lc.close()
    finally:
        ctl.close()
        code, out = stop_process(driver, timeout=20)
    assert code == 0, out
    assert 'Traceback' not in out, out
    rec = device.stop()
    got = rec['cmd_task']
    assert got.size and np.all(np.isfinite(got)), 'a non-finite wrench reached the device'
    assert np.all(np.abs(got) <= limit * (1.0 + 1e-12))
    assert int(rec['frame_mismatches']) == 0
    # Every state that follows a FAULT state applied zero (consecutive seqs of one activation
    # only: the states are best effort, and each activation's device loop counts from 1, so
    # a seq names a state only within its activation).
    by_seq = {}
    session, last = 0, 0
    for seq, status, applied in ctl.states:
        if seq <= last:
            session += 1
        last = seq
        by_seq[session, seq] = (status, applied)
    pairs = [(by_seq[k], by_seq[k[0], k[1] + 1]) for k in by_seq if (k[0], k[1] + 1) in by_seq]
    after_fault = [b[1] for a, b in pairs if a[0] & int(DeviceStatus.FAULT)]
    assert len(after_fault) > 10
    assert all(not any(w) for w in after_fault)
    applied = np.array([a for _, _, a in ctl.states if len(a) == 3])
    assert np.all(np.isfinite(applied)) and np.all(np.abs(applied) <= limit)
