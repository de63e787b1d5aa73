"""The ``haply`` backend against the Haply Inverse Service emulator in another process: options,
axes, identity and device choice, the task <-> device mapping, and the faults (service
unreachable, NaN and malformed states, the device unplugged, the service hung or stopped):
each is a FAULT reading with its reason, after which the driver's loop writes zero and the
device gets nothing but zero; nothing non-finite is passed on. Waits are on conditions with
deadlines; no timing is asserted."""

from __future__ import annotations

import re
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from backend_conformance import Bench, Subject
from haply_harness import Emulator, EmulatorDevice, read_log

from haptic_topology import cli
from haptic_topology.config.resolve import check_device_axes
from haptic_topology.device.backend import TRANSLATION_AXES, BackendConfig, create_backend
from haptic_topology.errors import AxesError, DeviceError
from haptic_topology.remote.haply import HaplyBackend, vendor_support
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import DeviceStatus

FAULT = DeviceStatus.FAULT
WAIT = 60.0


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return int(s.getsockname()[1])


def _configured(options: dict[str, Any], scenario: str = 'fig8_point') -> HaplyBackend:
    sc = load_scenario(scenario)
    b = create_backend('haply')
    assert isinstance(b, HaplyBackend)
    b.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, options, sc.source))
    return b


@pytest.fixture
def emulators(tmp_path: Path) -> Iterator[list[Emulator]]:
    made: list[Emulator] = []
    yield made
    for e in made:
        e.kill()


def _start(made: list[Emulator], tmp: Path, *extra: str) -> Emulator:
    e = Emulator(tmp / f'e{len(made)}', extra)
    made.append(e)
    return e


# -- options, axes, identity ---------------------------------------------------------------------
@pytest.mark.parametrize(('options', 'message'), [
    ({'port': 0}, 'haply: backend_options.port: expected an integer port in [1, 65535], got 0'),
    ({'axes': ['x', 'x', 'z']}, 'haply: backend_options.axes: expected 3 signed device axis '
     'names such as [x, -z, y] (task x, y, z)'),
    ({'origin': [0.1]}, 'haply: backend_options.origin: expected 3 numbers'),
    ({'max_force': 0}, 'haply: backend_options.max_force: expected a number in (0, 1000], '
     'got 0'),
    ({'max_in_flight': 0}, 'haply: backend_options.max_in_flight: expected an integer in '
     '[1, 64], got 0'),
    ({'engage_button': 40}, 'haply: backend_options.engage_button: expected a button index'),
    ({'speed': 1}, "haply: backend_options: unknown option 'speed'")])
def test_bad_options_are_refused_naming_the_field(options: dict[str, Any], message: str
                                                  ) -> None:
    with pytest.raises(DeviceError) as err:
        _configured(options)
    assert str(err.value).startswith(message), err.value


def test_a_translation_device_point_tasks_only(capsys: pytest.CaptureFixture[str]) -> None:
    assert HaplyBackend.axes({}) == TRANSLATION_AXES
    check_device_axes(load_scenario('fig8_point'), 'haply', {})
    with pytest.raises(AxesError, match=r'^scenario fig8 needs torque about z; device haply '
                       r'actuates x, y, z forces only: use fig8_point$'):
        check_device_axes(load_scenario('fig8'), 'haply', {})
    assert cli.main(['run', 'fig8', '--backend', 'haply']) == 2
    assert capsys.readouterr().err == ('haptic-topology run: error: scenario fig8 needs '
                                       'torque about z; device haply actuates x, y, z forces '
                                       'only: use fig8_point\n')
    with pytest.raises(DeviceError, match='a 3-axis device renders a point grasp only'):
        _configured({}, 'fig8')


def test_an_unreachable_service_fails_at_once_naming_the_address() -> None:
    port = _free_tcp_port()
    b = _configured({'port': port, 'connect_timeout_ms': 600_000})
    started = time.monotonic()
    with pytest.raises(DeviceError) as err:
        b.activate()
    assert str(err.value).startswith(f'haply: cannot connect to ws://127.0.0.1:{port}/: '
                                     'Connection refused: is the Haply Inverse Service'), err.value
    # "at once": long before the (10 min) connect timeout; no bound of this machine asserted
    assert time.monotonic() - started < 600.0
    b.deactivate()


def test_one_device_among_several_by_its_id(tmp_path: Path,
                                            emulators: list[Emulator]) -> None:
    e = _start(emulators, tmp_path, '--device', '04A1', '--device', '04B2')
    b = _configured({'port': e.port})
    with pytest.raises(DeviceError, match=r'^haply: 2 Inverse3 devices at ws://127\.0\.0\.1:'
                       r'\d+/ \(04A1, 04B2\): choose one with backend_options\.device_id$'):
        b.activate()
    b = _configured({'port': e.port, 'device_id': '0000'})
    with pytest.raises(DeviceError, match=r"no Inverse3 '0000' at .*; it has 04A1, 04B2$"):
        b.activate()
    b = _configured({'port': e.port, 'device_id': '04B2'})
    b.activate()
    assert b.hardware_id.startswith('haply Inverse3 (version 7.4, right-handed, port '
                                    'emulated) serial 04B2 via ws://127.0.0.1:')
    values = b.values()
    assert (values['device_vendor'], values['device_serial'], values['device_sdk']) == (
        'Haply', '04B2', 'Inverse Service protocol 3.5.x')
    for _ in range(20):
        b.write(np.array([0.5, -0.25]))
        b.read(0.001)
    b.deactivate()
    e.stop()
    _, ids, f = read_log(e.log)
    sent = [i for i, row in zip(ids, f, strict=True) if row.any()]
    assert sent and set(sent) == {'04B2'}


def test_preflight_checks_the_service_and_the_device_and_sends_nothing(
        tmp_path: Path, emulators: list[Emulator]) -> None:
    e = _start(emulators, tmp_path, '--device', '04A1')
    sc = load_scenario('fig8_point')
    config = BackendConfig(sc.device, initial_device_pose(sc), {}, {'port': e.port},
                           sc.source)
    create_backend('haply').preflight(config)
    wrong = BackendConfig(sc.device, initial_device_pose(sc), {},
                          {'port': e.port, 'device_id': '0000'}, sc.source)
    with pytest.raises(DeviceError, match=r"no Inverse3 '0000' at .*; it has 04A1$"):
        create_backend('haply').preflight(wrong)
    out = e.stop()
    assert '"sessions": 2, "received": 0, "commands": 0' in out, out


def test_the_mapping_axes_origin_and_force_limit(tmp_path: Path,
                                                 emulators: list[Emulator]) -> None:
    """``axes: [y, -x, z]``: task x is device y, task y is device -x. The handle rests at
    the emulator's start (0, -0.12, 0.15) m (no hand): task position origin + (-0.12, 0)."""
    e = _start(emulators, tmp_path, '--hand-stiffness', '0', '--quantum', '0')
    b = _configured({'port': e.port, 'axes': ['y', '-x', 'z'], 'origin': [0.2, 0.1, 0.0],
                     'max_force': 2.5, 'grasp_ramp_ms': 0})
    b.activate()
    r = b.read(0.001)
    np.testing.assert_allclose(r.pose, [0.2 - 0.12, 0.1 - 0.0], rtol=0, atol=1e-15)
    b.write(np.array([1.0, 0.5]))       # device (-0.5, 1.0, 0)
    b.write(np.array([3.0, 4.0]))       # norm 5 -> 2.5 N: device (-2.0, 1.5, 0)
    b.deactivate()
    e.stop()
    _, _, f = read_log(e.log)
    # activation's zero, the two forces, deactivate's zero, then the service's idle on close
    assert f.tolist() == [[0.0, 0.0, 0.0], [-0.5, 1.0, 0.0], [-2.0, 1.5, 0.0],
                          [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    assert b.force_clamped == 1


def test_the_first_cycle_after_a_slow_start_is_not_stale(
        tmp_path: Path, emulators: list[Emulator]) -> None:
    """The driver's first cycle may come well after ``activate`` took its state: that state
    is not stale then; later ones are when no answer comes within ``stale_ms``."""
    e = _start(emulators, tmp_path, '--fault', 'hang@2')
    b = _configured({'port': e.port, 'stale_ms': 20.0})
    b.activate()
    time.sleep(0.1)
    assert b.read(0.001).status != FAULT
    b.write(np.zeros(2))                        # message 2: never answered
    deadline = time.monotonic() + WAIT
    while not b.read(0.001).status & FAULT:
        assert time.monotonic() < deadline
        time.sleep(0.002)
    assert 'no state from' in b.fault_reason()
    b.deactivate()


def test_the_hand_starts_at_the_grasp_point_and_the_force_fades_in(
        tmp_path: Path, emulators: list[Emulator]) -> None:
    """Default origin: the handle's position at activation is the scenario's initial pose;
    the force fades in over grasp_ramp_ms (readings WATCHDOG meanwhile)."""
    e = _start(emulators, tmp_path, '--hand-stiffness', '0')
    b = _configured({'port': e.port, 'grasp_ramp_ms': 10.0, 'max_in_flight': 64})
    b.activate()
    sc = load_scenario('fig8_point')
    statuses = []
    for k in range(15):
        r = b.read(0.001)
        if k == 0:
            np.testing.assert_allclose(r.pose, initial_device_pose(sc), rtol=0, atol=1e-12)
        statuses.append(r.status)
        b.write(np.array([1.0, 0.0]))
    b.deactivate()
    e.stop()
    _, _, f = read_log(e.log)
    fx = f[1:16, 0]
    assert statuses[0] == DeviceStatus.WATCHDOG and statuses[-1] == DeviceStatus.OK
    assert fx[0] == pytest.approx(0.1) and fx[-1] == 1.0
    assert np.all(np.diff(fx) >= 0.0)


def test_the_grip_button_engages(tmp_path: Path, emulators: list[Emulator]) -> None:
    """``engage_button: 0``: the device gets force only while the VerseGrip's button a is
    held (emulator messages 100-300); before and after, zero, whatever the loop writes."""
    e = _start(emulators, tmp_path, '--grip', '61548', '--press', 'a@100-300')
    b = _configured({'port': e.port, 'engage_button': 0, 'grasp_ramp_ms': 0,
                     'max_in_flight': 64})
    b.activate()
    deadline = time.monotonic() + WAIT
    while b.states < 400:
        assert time.monotonic() < deadline
        b.write(np.array([0.5, 0.0]))
        b.read(0.001)
        time.sleep(0.0005)
    b.deactivate()
    e.stop()
    _, _, f = read_log(e.log)
    on = np.flatnonzero(f[:, 0] != 0.0)
    assert on.size and np.all(f[on[0]:on[-1] + 1, 0] == 0.5), 'not one block of force'
    assert 50 < on[0] < 350 and on[-1] < len(f) - 50
    assert b.values()['grasps'] == '1'


# -- faults --------------------------------------------------------------------------------------
def _run_to_fault(tmp_path: Path, emulators: list[Emulator], fault: str, lasting: bool = False,
                  **options: Any) -> tuple[Bench, EmulatorDevice, int, list[DeviceStatus]]:
    """Engage a bench on the emulator with ``--fault fault`` and cycle with a constant force
    until a FAULT reading, then 30 cycles more (``lasting``: until the last 30 readings are
    all FAULT; a loaded machine may have stalled the emulator into a passing stale fault
    before); (bench, device, index in ``bench.written`` of the cycle of the first FAULT
    reading (``lasting``: of the final run of them), the statuses)."""
    device = EmulatorDevice(tmp_path / 'dev', 2, ('--fault', fault))
    emulators.append(device.emulator)
    opts = {'port': device.port, 'stale_ms': 2000.0, **options}
    bench = Bench(Subject('haply', lambda: device, opts, 'fig8_point'), device)
    bench.activate()
    bench.engage()
    u = np.array([1.5, -1.0])
    statuses: list[DeviceStatus] = []
    index: list[int] = []
    deadline = time.monotonic() + WAIT

    def cycle() -> None:
        statuses.append(bench.cycle(u).reading.status)
        index.append(len(bench.written) - 1)
        time.sleep(0.0005)

    while not statuses or not statuses[-1] & FAULT:
        assert time.monotonic() < deadline, 'no FAULT reading'
        cycle()
    first = index[-1]
    if lasting:
        while len(statuses) < 30 or not all(st & FAULT for st in statuses[-30:]):
            assert time.monotonic() < deadline, 'no lasting FAULT'
            cycle()
        k = len(statuses) - 1
        while k > 0 and statuses[k - 1] & FAULT:
            k -= 1
        first = index[k]
    else:
        for _ in range(30):
            cycle()
    return bench, device, first, statuses


def _zero_after_fault(bench: Bench, first: int) -> None:
    """The loop wrote zero from the cycle after the FAULT reading of cycle ``first`` (the
    existing fault path), after force before it: never force from bad data."""
    w = np.array(bench.written)
    assert w[:first].any()                          # force before the fault
    assert first + 1 < len(w) and not w[first + 1].any()
    for r in bench.readings:
        assert np.all(np.isfinite(r)), 'a non-finite reading was passed on'


@pytest.mark.parametrize(('fault', 'reason'), [
    ('nan@200', 'haply: a non-finite state of 0E31 from ws://127.0.0.1:'),
    ('malformed@200', "haply: a malformed message from ws://127.0.0.1:")])
def test_a_bad_state_is_a_fault_until_a_good_one(tmp_path: Path, emulators: list[Emulator],
                                                 fault: str, reason: str) -> None:
    # one command in flight: every answer is read (of several arriving together only the
    # newest is decoded, so a bad one among them is never used, nor seen)
    bench, device, first, statuses = _run_to_fault(tmp_path, emulators, fault,
                                                   max_in_flight=1)
    assert bench.backend.fault_reason().startswith(reason), bench.backend.fault_reason()
    _zero_after_fault(bench, first)
    assert not statuses[-1] & FAULT          # the next state cleared it
    assert bench.loop.device_faults == 1
    bench.release()
    c = bench.backend.counters()          # type: ignore[attr-defined]
    assert (c['nonfinite'], c['malformed']) == ((1, 0) if fault.startswith('nan') else (0, 1))


@pytest.mark.parametrize(('fault', 'reason', 'options'), [
    ('unplug@200', r"haply: the Inverse3 0E31 is gone from ws://127\.0\.0\.1:\d+/'s states "
     r'\(unplugged or powered off\?\)', {}),
    ('hang@200', r'haply: no state from ws://127\.0\.0\.1:\d+/ for [\d.]+ ms \(stale_ms 50\): '
     'the service is stalled or stopped', {'stale_ms': 50.0}),
    ('stop@200', r'haply: the connection to ws://127\.0\.0\.1:\d+/ ended \(the service '
     r'(closed|reset) the connection\); reconnecting( \(\d+ attempts?, the newest: cannot '
     r'connect to ws://127\.0\.0\.1:\d+/: Connection refused\))?', {})])
def test_a_lasting_fault_holds_zero(tmp_path: Path, emulators: list[Emulator], fault: str,
                                    reason: str, options: dict[str, Any]) -> None:
    bench, device, first, statuses = _run_to_fault(tmp_path, emulators, fault, True, **options)
    assert re.fullmatch(reason, bench.backend.fault_reason()), bench.backend.fault_reason()
    _zero_after_fault(bench, first)
    assert all(s & FAULT for s in statuses[-30:])
    w = np.array(bench.written)
    assert not w[first + 1:].any(), 'force written while the fault lasted'
    if fault.startswith('hang'):
        assert bench.backend.counters()['throttled'] > 0     # type: ignore[attr-defined]
    bench.backend.write(np.zeros(2))
    bench.backend.deactivate()               # harmless with the service gone or hung
    bench.backend.deactivate()
    device.stopped = True
    device.emulator.stop()
    if fault.startswith('unplug'):
        # the service still answers: what the device got after the force is zero only (a
        # hung service gets no more commands, max_in_flight; a stopped one none at all)
        _, _, f = read_log(device.emulator.log)
        cut = np.flatnonzero(np.abs(f - [1.5, -1.0, 0.0]).max(axis=1) == 0.0)
        assert cut.size, 'the device never got the force'
        assert cut[-1] + 1 < len(f) and not f[cut[-1] + 1:].any(), f[cut[-1] + 1:]
    device.close()


def test_service_stopped_output_ends_with_the_fault(tmp_path: Path) -> None:
    """The emulator's ``stop`` fault ends the process at once (exit 0) with its counters."""
    e = Emulator(tmp_path, ('--fault', 'stop@5'))
    b = _configured({'port': e.port})
    b.activate()
    deadline = time.monotonic() + WAIT
    while not b.read(0.001).status & FAULT:
        assert time.monotonic() < deadline
        b.write(np.zeros(2))
        time.sleep(0.001)
    assert e.proc.wait(timeout=WAIT) == 0
    b.deactivate()
    e.kill()
    assert 'haply_emulator: stopped (fault stop@5)' in e.output, e.output



def test_the_vendor_registry_entry_lists_the_service_devices(
        tmp_path: Path, emulators: list[Emulator], monkeypatch: pytest.MonkeyPatch) -> None:
    e = _start(emulators, tmp_path, '--device', '04A1', '--device', '04B2')
    monkeypatch.setenv('HAPLY_INVERSE_SERVICE', f'127.0.0.1:{e.port}')
    support = vendor_support()
    assert support.backend == 'haply'
    assert support.load() == ('no library needed: the Inverse Service protocol 3.5.x at '
                              f'ws://127.0.0.1:{e.port}/')
    assert support.devices() == [
        f'Haply Inverse3 (version 7.4, right-handed, port emulated) serial {i}'
        for i in ('04A1', '04B2')]
    monkeypatch.setenv('HAPLY_INVERSE_SERVICE', 'nowhere')
    with pytest.raises(DeviceError, match="HAPLY_INVERSE_SERVICE: expected host:port, got "
                       "'nowhere'"):
        support.devices()
