"""The loop process (``haptic_topology/device/loop_process.py``) without ROS: the cycle
record's round trip, lock-step through the child equal to ``simulate`` at every cycle, and
either side killed (the other sees it; the child zeroes the device; nothing is left in
/dev/shm)."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loop_specs import spec_for
from procs import describe, pidfd, wait_exit

from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.loop import Answer, HandSample
from haptic_topology.device.backend import DeviceReading
from haptic_topology.device.hosted import HostedStep
from haptic_topology.device.loop import DeviceTick
from haptic_topology.device.loop_process import LoopProcess
from haptic_topology.device.realtime import sched_slice_ns
from haptic_topology.device.records import CycleCodec
from haptic_topology.device.runner import Published
from haptic_topology.errors import DeviceError
from haptic_topology.sim.lockstep import simulate, virtual_environment
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode, DeviceStatus

SUPPORT = Path(__file__).resolve().parents[2] / 'support'


def _v(*x: float) -> np.ndarray:
    return np.array(x, dtype=float)


def test_cycle_record_round_trip() -> None:
    codec = CycleCodec(3)
    reading = DeviceReading(_v(1, 2, 3), _v(4, 5, 6), _v(7, 8, 9), DeviceStatus.SATURATED)
    tick = DeviceTick(41, 40, reading, _v(0.1, 0.2, 0.3), DeviceStatus.WATCHDOG, _v(1, 1, 1))
    out = CycleOutput(_v(1, 0, 0), _v(2, 0, 0), _v(3, 0, 0), _v(4, 0, 0), _v(5, 0, 0), 1,
                      ControlMode.ACCELERATION_ONLY, None)
    hand = HandSample(7, 41, 0.04, _v(1, 2, 3), _v(4, 5, 6), _v(7, 8, 9), _v(2, 0, 0),
                      _v(3, 0, 0))
    full = Published(HostedStep(tick, 0.04, Answer(41, out, hand, 12), None, ()),
                     40_000_000)
    bare = Published(HostedStep(tick._replace(env_wrench=None), 0.0, None, None, ()), 0)
    for e in (full, bare):
        ints, floats = codec.encode(e)
        rec = np.zeros((), codec.dtype)
        rec['i'], rec['f'] = ints, floats
        back = codec.decode(rec)
        assert back.stamp_ns == e.stamp_ns and back.step.stamp == e.step.stamp
        t, t0 = back.step.tick, e.step.tick
        assert (t.seq, t.run_index, t.status, t.reading.status) == (
            t0.seq, t0.run_index, t0.status, t0.reading.status)
        for a, b in ((t.reading.pose, t0.reading.pose), (t.applied, t0.applied)):
            np.testing.assert_array_equal(a, b)
        assert (t.env_wrench is None) == (t0.env_wrench is None)
        assert (back.step.answer is None) == (e.step.answer is None)
    a = codec.decode(_record(codec, full)).step.answer
    assert a is not None and a.hand is not None
    assert (a.state_seq, a.update_seq, a.out.mode, a.out.constraint_count) == (
        41, 12, ControlMode.ACCELERATION_ONLY, 1)
    assert a.out.env_wrench is None
    assert (a.hand.seq, a.hand.state_seq, a.hand.stamp) == (7, 41, 0.04)
    np.testing.assert_array_equal(a.hand.vt_wrench, hand.vt_wrench)


def _record(codec: CycleCodec, e: Published) -> np.void:
    rec = np.zeros((), codec.dtype)
    rec['i'], rec['f'] = codec.encode(e)
    return rec[()]


@pytest.mark.parametrize('name', ['fig8', 'wall', 'panda_link4'])
def test_lockstep_through_the_loop_process_equals_simulate(name: str) -> None:
    """The child runs the cycle, this process runs the VE as ``simulate`` does (each hand
    input taken in order, an update offered after every update_period inputs): the device
    poses and commands equal ``simulate``'s at every cycle, bit for bit."""
    duration = 0.3
    sc = replace(load_scenario(name), duration=duration)
    offline = simulate(sc)
    spec, dim, dof = spec_for(name, lockstep=True, duration=duration)
    ve = virtual_environment(sc)
    proc = LoopProcess(spec, dim, dof)
    proc.may_engage = True                      # sent at start
    rows: list[Published] = []
    inputs, update_seq = 0, 1
    proc.start()
    try:
        proc.offer_update(ve.snapshot(seq=0))
        deadline = time.monotonic() + 120.0
        while len(rows) < len(offline) and time.monotonic() < deadline:
            proc.check()
            assert proc.error is None, proc.error
            proc.wait(0.05)
            for e in proc.drain():
                ans = e.step.answer
                if e.step.tick.run_index >= 0:
                    rows.append(e)
                if ans is not None and ans.hand is not None:
                    h = ans.hand
                    ve.push_input(h.state_seq, h.stamp, h.vt_wrench)
                    inputs += 1
                    if inputs % sc.update_period == 0:
                        proc.offer_update(ve.snapshot(seq=update_seq))
                        update_seq += 1
        proc.stop()
    finally:
        proc.close()
    assert len(rows) >= len(offline)
    rows = rows[:len(offline)]
    pose = np.array([e.step.tick.reading.pose for e in rows])
    cmd = np.array([e.step.answer.out.wrench for e in rows if e.step.answer is not None])
    np.testing.assert_array_equal(pose, offline.columns['device_pose'])
    np.testing.assert_array_equal(cmd, offline.columns['command'])
    assert [e.stamp_ns for e in rows] == [round(k * sc.dt * 1e9) for k in range(len(rows))]


def _segments(names: list[str]) -> list[str]:
    return [n for n in names if (Path('/dev/shm') / n.lstrip('/')).exists()]


def test_a_killed_child_is_a_fault_and_close_leaves_no_segment() -> None:
    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    proc = LoopProcess(spec, dim, dof)
    proc.start()
    names = proc.ring_names()
    try:
        assert len(_segments(names)) == 7     # 4 rings, 3 statistics arrays
        deadline = time.monotonic() + 30.0
        while not proc.status and time.monotonic() < deadline:     # running: reports
            proc.wait(0.05)
            proc.drain()
        assert proc.status and proc.error is None
        while int(proc.status.get('n_periods', 0)) < 10 and time.monotonic() < deadline:
            proc.wait(0.05)
            proc.drain()
        # How late the child woke after its deadlines, sorted here from the shared array
        # (in a thread of this process's, once asked: the next reading has them).
        late = [math.nan]
        while math.isnan(late[0]) and time.monotonic() < deadline:
            late = [float(proc.device_values()[f'wake_late_{q}_ms'])
                    for q in ('p50', 'p99', 'max')]
            time.sleep(0.05)
        assert 0.0 <= late[0] <= late[1] <= late[2], late
        # This process's session (one autogroup with the node's threads), a process group of
        # its own (the terminal's Ctrl-C is not for it).
        assert os.getsid(proc.pid or 0) == os.getsid(0)
        assert os.getpgid(proc.pid or 0) == proc.pid != os.getpgid(0)
        # Its one thread asked for the spec's scheduler slice (100 us) where the kernel
        # keeps one per task, and said why not elsewhere.
        if sched_slice_ns(proc.pid or 0):
            assert sched_slice_ns(proc.pid or 0) == 100_000, proc.notices
        else:
            assert any('sched_slice_us 100' in n for n in proc.notices), proc.notices
        os.kill(proc.pid or 0, signal.SIGKILL)
        while proc.error is None and time.monotonic() < deadline:
            time.sleep(0.002)
            proc.check()
        assert isinstance(proc.error, DeviceError) and 'exited with code -9' in str(proc.error)
    finally:
        proc.close()
    assert _segments(names) == []


def test_a_child_stopped_while_it_starts_stops_at_its_first_cycle() -> None:
    # Stopped at once, it is still importing (seconds on a loaded machine, more than
    # STOP_TIMEOUT): the node waits for it to reach its loop, where it stops, zeroes the
    # device and exits 0, rather than killing it.
    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    proc = LoopProcess(spec, dim, dof)
    proc.start()
    try:
        assert not proc.status                  # nothing reported from its loop yet
        proc.stop()
        assert proc.status.get('generation') == proc.generation   # its final report
        assert proc._proc is not None and proc._proc.returncode == 0
        assert proc.error is None
    finally:
        proc.close()


def test_a_killed_parent_stops_the_child_with_zero_output_and_no_segment_left() -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(SUPPORT), *filter(None, [os.environ.get('PYTHONPATH')])]))
    parent = subprocess.Popen([sys.executable, str(SUPPORT / 'loop_parent.py')],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env=env)
    assert parent.stdout is not None
    try:
        first = parent.stdout.readline().split()
        child, names = int(first[0]), first[1:]
        fd = pidfd(child)               # that process, whatever later takes its number
        assert len(_segments(names)) == 7     # 4 rings, 3 statistics arrays
    finally:
        parent.kill()                   # also when a check above failed: never leak it
        parent.wait()
    rest = parent.stdout.read()         # the child's last words (it shares the pipe)
    deadline = time.monotonic() + 30.0
    assert wait_exit(fd, 30.0), describe(child)
    assert 'parent gone: output zeroed, device released' in rest, rest
    while _segments(names) and time.monotonic() < deadline:   # the parent's tracker
        time.sleep(0.01)
    assert _segments(names) == []


def test_refused_real_time_options_are_one_warning_each_and_the_loop_runs() -> None:
    """Without the privileges (here: root of a user namespace, which has no CAP_SYS_NICE or
    CAP_IPC_LOCK over the machine) the loop process runs with normal scheduling and says
    once per option why."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(SUPPORT), *filter(None, [os.environ.get('PYTHONPATH')])]))
    res = subprocess.run(['unshare', '--user', '--map-root-user', sys.executable,
                          str(SUPPORT / 'loop_refused.py')], env=env,
                         capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == 'cycling', res.stdout
    assert sum('sched_priority 50: not permitted' in ln for ln in lines) == 1, res.stdout
    assert sum(ln.startswith('lock_memory') for ln in lines) == 1, res.stdout


def test_an_activation_again_resumes_the_simulated_device_where_the_last_child_left_it() -> None:
    """Each activation starts a new child, which opens the device anew: the simulated maglev
    the last child moved resumes where it stopped (its final status carries the state), not
    at the scenario's initial pose, as the same backend in the node's own process would. A
    child killed (no final status) hands nothing over, and the next one does not take an
    older child's state either: it starts at the initial pose, and the node says so."""
    duration = 0.1
    sc = replace(load_scenario('fig8'), duration=duration)
    spec, dim, dof = spec_for('fig8', lockstep=True, duration=duration)
    ve = virtual_environment(sc)
    proc = LoopProcess(spec, dim, dof)
    proc.may_engage = True
    poses: list[list[np.ndarray]] = [[], [], []]

    def idle(k: int) -> None:
        while len(poses[k]) < 5 and time.monotonic() < deadline:
            proc.check()
            assert proc.error is None, proc.error
            proc.wait(0.05)
            poses[k].extend(e.step.tick.reading.pose for e in proc.drain())

    inputs, update_seq = 0, 1
    try:
        proc.start()
        proc.offer_update(ve.snapshot(seq=0))
        deadline = time.monotonic() + 120.0
        while not proc.finished and time.monotonic() < deadline:
            proc.check()
            assert proc.error is None, proc.error
            proc.wait(0.05)
            for e in proc.drain():
                poses[0].append(e.step.tick.reading.pose)
                ans = e.step.answer
                if ans is not None and ans.hand is not None:
                    ve.push_input(ans.hand.state_seq, ans.hand.stamp, ans.hand.vt_wrench)
                    inputs += 1
                    if inputs % sc.update_period == 0:
                        proc.offer_update(ve.snapshot(seq=update_seq))
                        update_seq += 1
        proc.stop()
        poses[0].extend(e.step.tick.reading.pose for e in proc.drain())
        proc.may_engage = False           # the later children idle: the device stays parked
        proc.start()
        idle(1)
        assert not any('without handing' in n for n in proc.notices), list(proc.notices)
        os.kill(proc.pid or 0, signal.SIGKILL)
        while proc.error is None and time.monotonic() < deadline:
            time.sleep(0.002)
            proc.check()
        assert isinstance(proc.error, DeviceError)
        proc.start()
        idle(2)
        proc.stop()
    finally:
        proc.close()
    assert proc.finished or len(poses[0]) >= round(duration / sc.dt), len(poses[0])
    start = spec['backend_config'].initial_pose
    assert np.linalg.norm(poses[0][-1][:2] - start[:2]) > 1e-5      # the first child moved it
    assert len(poses[1]) >= 5 and len(poses[2]) >= 5, 'a child sent no states'
    for pose in poses[1]:
        np.testing.assert_array_equal(pose, poses[0][-1])
    for pose in poses[2]:
        np.testing.assert_array_equal(pose, start)
    assert any('without handing its device state over' in n for n in proc.notices)


def _logged_child(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, misbehave: str,
                  lockstep: bool = False) -> tuple[LoopProcess, Path]:
    """A loop process for fig8 whose device is ``fake_backend:CallLogBackend`` (its calls in
    the returned file; ``misbehave`` as that class says)."""
    log = tmp_path / 'calls.txt'
    monkeypatch.setenv('HAPTIC_TEST_CALL_LOG', str(log))
    monkeypatch.setenv('HAPTIC_TEST_MISBEHAVE', misbehave)
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(
        [str(SUPPORT), *filter(None, [os.environ.get('PYTHONPATH')])]))
    spec, dim, dof = spec_for('fig8', lockstep=lockstep, duration=0.0)
    spec['backend'] = 'fake_backend:CallLogBackend'
    return LoopProcess(spec, dim, dof), log


def _until(cond: Any, proc: LoopProcess, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not cond() and time.monotonic() < deadline:
        proc.wait(0.02)
        proc.drain()
    assert cond(), 'not within the time'


def _calls(log: Path) -> list[str]:
    return log.read_text().split() if log.exists() else []


def test_an_activation_that_fails_half_way_is_zeroed_and_released(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The backend enables its output, then its activate() raises: the child writes zero and
    deactivates the device before it exits, and the node sees the exit as a fault."""
    proc, log = _logged_child(monkeypatch, tmp_path, 'activate')
    try:
        proc.start()
        _until(lambda: proc._proc is not None and proc._proc.poll() is not None, proc)
        proc.check()
        assert isinstance(proc.error, DeviceError), proc.error
    finally:
        proc.close()
    assert _calls(log) == ['activate', 'zero', 'deactivate', 'cleanup'], _calls(log)


def test_a_zero_write_that_raises_anything_still_releases_the_device(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A backend whose write raises RuntimeError (its own bug, not a DeviceError): at the
    stop the device is deactivated all the same, and the failed write is reported."""
    proc, log = _logged_child(monkeypatch, tmp_path, 'write')
    try:
        proc.start()
        _until(lambda: bool(proc.status), proc)
        proc.stop()
        assert proc._proc is not None and proc._proc.returncode == 0
    finally:
        proc.close()
    assert _calls(log) == ['activate', 'deactivate', 'cleanup'], _calls(log)
    assert any('writing zero wrench failed: RuntimeError' in n for n in proc.notices), \
        list(proc.notices)


def test_a_new_child_starts_with_no_status_of_the_last_one(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The last child's status (here: finished, final) is not the new child's: the new one
    is neither finished nor reported before its own first status, and if it dies before
    that, its exit is a fault."""
    proc, log = _logged_child(monkeypatch, tmp_path, '')
    try:
        proc.start()
        _until(lambda: bool(proc.status), proc)
        proc.stop()
        assert proc.status.get('final') is True and proc.error is None
        proc.status['finished'] = True          # as a child that reached run_duration
        proc.start()
        assert proc.status == {} and not proc.finished
        os.kill(proc.pid or 0, signal.SIGKILL)   # before its first status
        _until(lambda: proc._proc is not None and proc._proc.poll() is not None, proc)
        proc.check()
        assert isinstance(proc.error, DeviceError) and 'exited with code -9' in str(proc.error)
    finally:
        proc.close()


def test_a_stop_the_child_does_not_answer_escalates_to_sigterm_and_it_zeroes(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A child stuck in a device call (1.5 s) does not answer the stop request within the
    stop timeout: the node sends SIGTERM, and the child zeroes and releases the device when
    the call returns, and exits 0; nothing is killed."""
    proc, log = _logged_child(monkeypatch, tmp_path, 'stall:20:1.5')
    try:
        proc.start()
        _until(lambda: 'stall' in _calls(log), proc)
        proc.stop(timeout=0.1)
        assert proc._proc is not None and proc._proc.returncode == 0
        assert proc.error is None and proc.status.get('final') is True
        assert any('stopped by SIGTERM' in n for n in proc.notices), list(proc.notices)
    finally:
        proc.close()
    calls = _calls(log)
    assert calls[-3:] == ['zero', 'deactivate', 'cleanup'] and 'stall' in calls, calls


def test_a_stop_that_cannot_be_asked_escalates_and_a_hung_child_is_killed(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The control ring full (the child stuck, not reading it): the stop goes to SIGTERM at
    once; a child that does not exit then is killed, and that is the loop's error."""
    proc, log = _logged_child(monkeypatch, tmp_path, 'stall:20:60')
    try:
        proc.start()
        _until(lambda: 'stall' in _calls(log), proc)
        _until(lambda: not proc._request(('engage', False)), proc, 30.0)   # ring full
        started = time.monotonic()
        proc.stop(timeout=30.0)                 # no request can be put: no 30 s wait
        assert time.monotonic() - started < 30.0
        assert proc._proc is not None and proc._proc.returncode == -signal.SIGKILL
        assert isinstance(proc.error, DeviceError) and 'killed' in str(proc.error)
    finally:
        proc.close()
    assert 'deactivate' not in _calls(log)      # SIGKILL: nothing could run


def test_close_stops_a_running_child_by_request(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    proc, log = _logged_child(monkeypatch, tmp_path, '')
    proc.start()
    try:
        _until(lambda: bool(proc.status), proc)
    finally:
        proc.close()
    assert proc._proc is not None and proc._proc.returncode == 0
    assert _calls(log)[-3:] == ['zero', 'deactivate', 'cleanup'], _calls(log)


def test_an_update_too_large_for_its_record_is_refused_and_counted() -> None:
    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    proc = LoopProcess(spec, dim, dof)
    try:
        proc._update_bytes = 16             # as if the linkage outgrew the record
        snap = virtual_environment(load_scenario('fig8')).snapshot(seq=3)
        proc.offer_update(snap)
        proc.flush_updates()
        assert proc.updates_refused == 1 and not proc._pending
        assert proc.device_values()['updates_refused'] == '1'
        assert any('LMI update 3' in n and 'refused' in n for n in proc.notices)
    finally:
        proc.close()


def test_a_dev_shm_without_room_fails_at_construction_and_leaves_nothing() -> None:
    """In a mount namespace of its own with a 256 kB /dev/shm, the rings do not fit: the
    construction (the driver's configure) fails with the segment named; the segments made
    before it are gone."""
    code = ('import os\n'
            'from loop_specs import spec_for\n'
            'from haptic_topology.device.loop_process import LoopProcess\n'
            'from haptic_topology.errors import DeviceError\n'
            "spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)\n"
            'try:\n'
            '    LoopProcess(spec, dim, dof)\n'
            'except DeviceError as exc:\n'
            '    print(exc)\n'
            "print('left', len(os.listdir('/dev/shm')))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(SUPPORT), *filter(None, [os.environ.get('PYTHONPATH')])]))
    res = subprocess.run(['unshare', '--user', '--map-root-user', '--mount', 'sh', '-c',
                          'mount -t tmpfs -o size=256k tmpfs /dev/shm && exec "$0" -c "$1"',
                          sys.executable, code], env=env, capture_output=True, text=True,
                         timeout=120, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    first, last = res.stdout.splitlines()[0], res.stdout.splitlines()[-1]
    assert first.startswith("shared memory: no room for the loop process's cycles ring"), \
        res.stdout
    assert 'free or enlarge /dev/shm' in first
    assert last == 'left 0', res.stdout


def test_rings_are_refused_on_a_machine_without_total_store_order() -> None:
    from haptic_topology.device.shm_ring import check_machine
    from haptic_topology.errors import ConfigError
    check_machine('x86_64')
    with pytest.raises(ConfigError, match=r"this machine is 'aarch64', expected one of "
                                          r'x86_64, amd64 .*loop_process: false'):
        check_machine('aarch64')


def test_the_percentiles_are_sorted_off_the_callers_thread_at_most_once_a_period(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """While a child runs, the node's diagnostics (device_values, device_report: the
    executor thread that also takes the LMI updates) never sort the statistics themselves:
    the figures' thread does, at most once per status period however often asked."""
    import threading

    import haptic_topology.device.loop_process as lp
    real = np.percentile
    sorted_in: list[str] = []

    def percentile(*args: Any, **kwargs: Any) -> Any:
        sorted_in.append(threading.current_thread().name)
        return real(*args, **kwargs)

    spec, dim, dof = spec_for('fig8', lockstep=False, duration=0.0)
    proc = LoopProcess(spec, dim, dof)
    try:
        proc.start()
        _until(lambda: int(proc.status.get('n_periods', 0)) > 10, proc)
        monkeypatch.setattr(lp.np, 'percentile', percentile)
        started = time.monotonic()
        values: dict[str, str] = {}
        while time.monotonic() - started < 1.0:
            values = proc.device_values()
            proc.device_report('', 0)
            time.sleep(0.005)
        monkeypatch.setattr(lp.np, 'percentile', real)
        assert sorted_in and set(sorted_in) == {'loop_figures'}, sorted_in
        # three arrays a time, at most once per STATUS_PERIOD (+1 for the first)
        assert len(sorted_in) <= 3 * (1.0 / lp.STATUS_PERIOD + 2), len(sorted_in)
        assert not math.isnan(float(values['period_p99_ms']))
    finally:
        proc.close()
