"""``backend: forcedimension`` through the unmodified ``forcedimension-core`` against the
Force Dimension emulator (``emulators/forcedimension``, ``test/support/fd_emulator.py``): the
backend conformance checks, identity, options, faults (unplugged, a failing call, NaN, no
device, not calibrated), the grasp button, the missing library, and the emulator's exports."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from backend_conformance import (
    Bench,
    Subject,
    check_clamping,
    check_lifecycle,
    check_nonfinite,
    check_watchdog,
)
from fd_emulator import LIBRARY, EmulatorSide, applied, emulator

from haptic_topology.cli import main as cli_main
from haptic_topology.config.resolve import check_device_axes
from haptic_topology.device.backend import BackendConfig, activate_backend, create_backend
from haptic_topology.device.forcedimension import ForceDimensionBackend, list_devices
from haptic_topology.device.vendor import probe
from haptic_topology.errors import AxesError, DeviceError
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import DeviceStatus

REPO = Path(__file__).resolve().parents[3]
SCENARIO = 'fig8_point'
#: No grasp fade: the conformance checks expect the command at the device within cycles.
OPTIONS = {'grasp_ramp_ms': 0}


def subject(options: dict | None = None) -> Subject:
    m = load_scenario(SCENARIO).linkage.task.dim
    return Subject('forcedimension', lambda: EmulatorSide(m),
                   dict(OPTIONS if options is None else options), scenario=SCENARIO)


CHECKS: dict[str, Callable[[Bench], None]] = {
    'clamping': check_clamping, 'nonfinite': check_nonfinite, 'watchdog': check_watchdog,
    'lifecycle': check_lifecycle,
}


@pytest.mark.parametrize('check', sorted(CHECKS))
def test_forcedimension_conforms(check: str) -> None:
    # A device whose own limit (12 N for an omega.3) is above the scenario's (20 N): what it
    # gets is what the driver's clamp lets through.
    with emulator(max_force=100):
        CHECKS[check](Bench(subject()))


def test_the_stepped_emulator_is_deterministic() -> None:
    """``FDEMU_CLOCK=step``: the emulated device advances only by ``fdemuStep`` (here 1 ms
    before each cycle), so two runs of the same commands read and apply the same values bit
    for bit (the device and its simulated hand do move)."""

    def once() -> list[np.ndarray]:
        with emulator(clock='step') as lib:
            sub = subject()
            sub.pace = lambda: lib.fdemuStep(1e-3)
            bench = Bench(sub)
            bench.activate()
            bench.engage()
            rng = np.random.default_rng(3)
            for _ in range(500):
                bench.cycle(0.2 * rng.uniform(-1.0, 1.0, bench.m) * bench.limit)
            bench.release()
            return [np.array(bench.readings), np.array(bench.written), bench.device.log()[1]]

    first, second = once(), once()
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.ptp(first[0][:, 0]) > 1e-3        # x moved by more than a millimetre


def test_the_emulator_backend_follows_the_lockstep_clock() -> None:
    """``forcedimension_emulator``: accepted on the lock-step clock (``forcedimension`` is
    not), each read advances the emulated device by its ``dt``, so two runs are the same bit
    for bit; idle reads (before engagement) do not advance it."""
    with pytest.raises(DeviceError, match='backend forcedimension: the device runs on its own '
                                          'clock'):
        create_backend('forcedimension', lockstep=True)

    def once() -> list[np.ndarray]:
        with emulator():
            bench = Bench(Subject('forcedimension_emulator', lambda: EmulatorSide(2),
                                  dict(OPTIONS), scenario=SCENARIO))
            assert create_backend('forcedimension_emulator', lockstep=True).lockstep
            bench.activate()
            parked = [bench.tick().reading.pose for _ in range(5)]
            assert all(np.array_equal(p, parked[0]) for p in parked)
            bench.engage()
            rng = np.random.default_rng(5)
            for _ in range(400):
                bench.cycle(0.2 * rng.uniform(-1.0, 1.0, bench.m) * bench.limit)
            bench.release()
            return [np.array(bench.readings), np.array(bench.written), bench.device.log()[1]]

    first, second = once(), once()
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.ptp(first[0][:, 0]) > 1e-3


def test_a_velocity_timeout_falls_back_to_the_positions_difference() -> None:
    """Right after opening, the SDK's velocity estimate may have too few positions in its
    window: ``dhdGetLinearVelocity`` fails with DHD_ERROR_TIMEOUT (the emulator's
    ``FDEMU_VELOCITY_TIMEOUT=5``: its first 5 calls). That is no fault: the twist is the
    difference of the newest two positions over ``dt`` (zero at the first reading), counted
    in ``velocity_timeouts``; then the device's own estimate again."""
    with emulator(velocity_timeout=5):
        be = create_backend('forcedimension_emulator', lockstep=True)
        assert isinstance(be, ForceDimensionBackend)
        sc = load_scenario(SCENARIO)
        be.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, dict(OPTIONS),
                                   sc.source))
        be.activate()
        try:
            dt = 0.001
            readings = []
            for _ in range(8):
                be.write(np.array([2.0, 0.0]))      # pushes the handle along x
                readings.append(be.read(dt))
            assert [r.status for r in readings] == [DeviceStatus.OK] * 8
            np.testing.assert_array_equal(readings[0].twist, np.zeros(2))
            for prev, r in zip(readings[:4], readings[1:5], strict=True):
                np.testing.assert_allclose(r.twist, (r.pose - prev.pose) / dt, rtol=0.0,
                                           atol=1e-9)
            assert readings[4].twist[0] > 0.0, 'the device did not move'
            assert be.values()['velocity_timeouts'] == '5'
            assert all(np.all(np.isfinite(r.twist)) for r in readings)
        finally:
            be.write(np.zeros(2))
            be.deactivate()


def test_identity_reaches_hardware_id_and_values() -> None:
    with emulator(serial=4321, model='delta.3'):
        bench = Bench(subject())
        assert bench.backend.hardware_id == 'forcedimension planar_point'
        bench.activate()
        assert bench.backend.hardware_id == 'forcedimension delta.3 serial 4321'
        values = bench.backend.values()
        assert {k: values[k] for k in ('device_vendor', 'device_model', 'device_serial',
                                       'device_sdk')} == {
            'device_vendor': 'Force Dimension', 'device_model': 'delta.3',
            'device_serial': '4321', 'device_sdk': '3.16.0-0'}
        assert values['device_workspace'].startswith('translation 400 x 260 mm')
        bench.release()


def test_fig8_full_grasp_is_refused_in_one_line() -> None:
    with pytest.raises(AxesError) as err:
        check_device_axes(load_scenario('fig8'), 'forcedimension', {})
    assert str(err.value) == ('scenario fig8 needs torque about z; device forcedimension '
                              'actuates x, y, z forces only: use fig8_point')


def _fault_run(reason: str, **settings: str | int) -> None:
    """An engaged run whose device fails as ``settings`` say: from the cycle after the fault
    the loop writes zero, the device gets zero with force disabled, the readings stay finite
    and flagged FAULT, the reason names the failure; the release still works."""
    with emulator(**settings) as lib:
        bench = Bench(subject())
        bench.activate()
        bench.engage()
        u = 0.5 * bench.limit
        faulted_at = None
        for k in range(300):
            tick = bench.cycle(u)
            r = tick.reading
            assert all(np.all(np.isfinite(v)) for v in (r.pose, r.twist, r.hand_wrench))
            if tick.status & DeviceStatus.FAULT:
                faulted_at = k if faulted_at is None else faulted_at
                assert not applied(lib).any() and not lib.fdemuForceEnabled(0)
                if k > faulted_at:
                    assert not bench.written[-1].any()
            elif faulted_at is None and k > 5:
                np.testing.assert_array_equal(applied(lib)[:2], u)
        assert faulted_at is not None, 'no fault'
        assert bench.loop.device_faults == 1 and bench.loop.fault_cycles > 100
        level, message = bench.loop.health()
        assert level == 2 and reason in message, message
        bench.backend.deactivate()
        bench.backend.cleanup()


def test_unplugged_mid_run_is_a_fault_with_zero_force() -> None:
    _fault_run('forcedimension: dhdGetPosition failed: communication error between the host '
               'and the device', unplug_after=60)


def test_a_failing_call_is_a_fault() -> None:
    _fault_run('forcedimension: dhdGetLinearVelocity failed: undocumented error',
               fail='dhdGetLinearVelocity:80')


def test_nan_from_the_device_is_a_fault_and_never_force() -> None:
    _fault_run('forcedimension: the device reported a non-finite position or velocity',
               nan_after=70)


def _configured(options: dict | None = None) -> ForceDimensionBackend:
    sc = load_scenario(SCENARIO)
    be = create_backend('forcedimension')
    assert isinstance(be, ForceDimensionBackend)
    be.configure(BackendConfig(sc.device, initial_device_pose(sc), {},
                               dict(OPTIONS, **(options or {})), sc.source))
    return be


def test_no_device_found() -> None:
    with emulator(devices=0):
        with pytest.raises(DeviceError, match=r'^forcedimension: cannot open a device '
                                              r'\(0 found\): no device found$'):
            _configured().activate()
    with emulator():
        with pytest.raises(DeviceError, match=r'cannot open the device with serial 999 '
                                              r'\(1 found\)'):
            _configured({'serial': 999}).activate()
        be = _configured({'serial': 11029})
        be.activate()
        assert be.hardware_id == 'forcedimension omega.3 serial 11029'
        be.deactivate()


def test_run_without_a_device_stops_before_any_node_starts(tmp_path: Path) -> None:
    """``run`` asks the backend before anything starts (``preflight``): no device connected
    is one line, exit status 1, and no node was started (no bag directory)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith('FDEMU_')}
    env['FDEMU_DEVICES'] = '0'
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', SCENARIO,
                           '--backend', 'forcedimension', '--duration', '1', '--out',
                           str(tmp_path / 'bag')],
                          capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert proc.stderr.strip().splitlines() == [
        'haptic-topology run: error: device: forcedimension: cannot open a device (0 found): '
        'no device found'], proc.stderr
    assert not (tmp_path / 'bag').exists()
    with emulator() as lib:
        be = create_backend('forcedimension')
        sc = load_scenario(SCENARIO)
        be.preflight(BackendConfig(sc.device, initial_device_pose(sc), {}, {}, sc.source))
        assert not lib.fdemuIsOpen(0) and not lib.fdemuForceEnabled(0)
        assert lib.fdemuSetForceCalls(0) == 0


def test_an_uncalibrated_device_is_refused_or_calibrated_on_request() -> None:
    with emulator(uninitialized=1) as lib:
        with pytest.raises(DeviceError, match='is not calibrated: calibrate it .* or set '
                                              'backend_options.auto_init: true'):
            activate_backend(_configured(), 2)      # as the driver activates
        assert not lib.fdemuIsOpen(0)               # released after the refusal
        be = _configured({'auto_init': True})
        be.activate()
        assert lib.fdemuForceEnabled(0)
        be.deactivate()
        assert not lib.fdemuIsOpen(0) and not lib.fdemuForceEnabled(0)


def test_engage_button_gates_the_force() -> None:
    """With ``engage_button: 0`` the device gets no force until button 0 is held, and none
    once it is let go."""
    with emulator() as lib:
        bench = Bench(subject({'grasp_ramp_ms': 0, 'engage_button': 0}))
        bench.activate()
        bench.engage()
        u = 0.5 * bench.limit
        for _ in range(20):
            bench.cycle(u)
        assert not applied(lib).any()
        lib.fdemuSetButtons(1)
        for _ in range(3):
            bench.cycle(u)
        np.testing.assert_array_equal(applied(lib)[:2], u)
        lib.fdemuSetButtons(0)
        bench.cycle(u)
        bench.cycle(u)
        assert not applied(lib).any()
        bench.release()


def test_applied_is_what_the_device_got_released_and_fading_in() -> None:
    """The loop's ``applied`` (the states', the trace's and the bag's) is what the device was
    sent, not the controller's command: exactly zero while the engage button is released,
    the faded force while the grasp fades in (``grasp_ramp_ms: 5``, 1 ms cycles: 0.2 of the
    command more each cycle), the command once faded in, and zero again once released. The
    emulated device's own force is the reference, cycle by cycle."""
    with emulator() as lib:
        bench = Bench(subject({'grasp_ramp_ms': 5, 'engage_button': 0}))
        assert bench.dt == 0.001
        bench.activate()
        bench.engage()
        u = np.array([0.5, -0.25])[:bench.m]

        def cycle() -> np.ndarray:
            bench.cycle(u)
            got = bench.written[-1]
            np.testing.assert_array_equal(got, applied(lib)[:bench.m])
            return got

        for _ in range(10):
            assert not cycle().any(), 'applied while the engage button is released'
        lib.fdemuSetButtons(1)
        # The first cycle's read sees the button: its write went out before, as zero.
        fractions = [float(cycle()[0] / u[0]) for _ in range(8)]
        np.testing.assert_allclose(fractions, [0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.0, 1.0],
                                   rtol=1e-12, atol=0.0)
        assert all(0.0 < f < 1.0 for f in fractions[1:5])
        np.testing.assert_array_equal(bench.written[-1], u)
        lib.fdemuSetButtons(0)
        cycle()                         # this cycle's read lets go
        assert not cycle().any(), 'applied after the engage button was released'
        bench.release()


def test_the_devices_own_force_limit() -> None:
    """``max_force: 5``: the device saturates a 10 N command at 5 N (``dhdSetMaxForce``), and
    the states say so (SATURATED) and the diagnostics count it."""
    with emulator() as lib:
        bench = Bench(subject({'grasp_ramp_ms': 0, 'max_force': 5.0}))
        bench.activate()
        bench.engage()
        u = np.array([10.0, -10.0])
        for _ in range(5):
            tick = bench.cycle(u)
        np.testing.assert_array_equal(applied(lib), [5.0, -5.0, 0.0])
        np.testing.assert_array_equal(tick.applied, u)
        assert tick.status & DeviceStatus.SATURATED
        assert int(bench.backend.values()['device_saturated_writes']) >= 4
        bench.release()


def test_gravity_compensation_and_effector_mass_reach_the_device() -> None:
    with emulator() as lib:
        be = _configured({'gravity_compensation': False, 'effector_mass': 0.25,
                          'max_force': 7.5})
        be.activate()
        assert (lib.fdemuGravity(0), lib.fdemuEffectorMass(0), lib.fdemuMaxForce(0)) == (
            0, 0.25, 7.5)
        be.deactivate()
        be = _configured()
        be.activate()
        assert (lib.fdemuGravity(0), lib.fdemuEffectorMass(0), lib.fdemuMaxForce(0)) == (
            1, 0.25, 7.5)           # the defaults leave mass and limit as the device has them
        be.deactivate()


@pytest.mark.parametrize(('options', 'text'), [
    ({'serial': 'abc'}, "backend_options.serial: expected the device's serial number"),
    ({'max_force': -1}, r'backend_options.max_force: expected a number in \(0, 1000\]'),
    ({'auto_init': 'yes'}, 'backend_options.auto_init: expected true or false'),
    ({'port': 1}, "unknown option 'port'"),
])
def test_bad_options_name_the_field(options: dict, text: str) -> None:
    with pytest.raises(DeviceError, match=text):
        _configured(options)


def test_devices_lists_the_connected_ones(capsys: pytest.CaptureFixture[str]) -> None:
    with emulator(devices=2, serial=500):
        assert list_devices() == ['omega.3 serial 500', 'omega.3 serial 501']
        found = probe('forcedimension')
        assert found.found and found.devices == ('omega.3 serial 500', 'omega.3 serial 501')
        assert str(LIBRARY.parent) in found.detail
        capsys.readouterr()
        assert cli_main(['devices']) == 0
        out = capsys.readouterr().out.splitlines()
        rows = {line.split()[0]: line for line in out}
        assert list(rows)[:4] == ['backend', 'sim_maglev', 'ros_topics', 'network']
        assert {'forcedimension', 'forcedimension_emulator'} <= set(rows)
        for line in (rows['forcedimension'], rows['forcedimension_emulator']):
            assert line.endswith(' omega.3 serial 500, omega.3 serial 501'), line
            assert f'found: {LIBRARY} (SDK 3.16.0-0)' in line


def test_missing_library_is_one_line_and_exit_status_2(tmp_path: Path) -> None:
    """``run`` with the backend and no libdrd to be found: one line naming the package, the
    library and the variable, exit status 2, before anything starts."""
    env = dict(os.environ, FDSDK=str(tmp_path / 'nothing'), HOME=str(tmp_path))
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', SCENARIO,
                           '--backend', 'forcedimension', '--duration', '1'],
                          capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0] == ('haptic-topology run: error: forcedimension: cannot load libdrd '
                        'through the Python package forcedimension-core (Could not find '
                        'libdrd. Is it installed?); install both and set FDSDK '
                        '(docs/devices.md)')
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'devices', '--backend',
                           'forcedimension'], capture_output=True, text=True, env=env,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[1].split() == [
        'forcedimension', 'vendor', 'missing:', 'forcedimension-core', '/', 'libdrd', '(set',
        'FDSDK):', 'Could', 'not', 'find', 'libdrd.', 'Is', 'it', 'installed?', '-']


def test_the_emulator_exports_every_bound_symbol() -> None:
    """``fd_stubs.c`` is what ``scripts/fd_emulator_stubs.py`` makes of the installed
    binding, and the built library exports every function the binding binds."""
    proc = subprocess.run([sys.executable, str(REPO / 'scripts' / 'fd_emulator_stubs.py'),
                           '--check'], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    import ctypes
    import runpy

    bound_signatures = runpy.run_path(str(REPO / 'scripts' / 'fd_emulator_stubs.py'))[
        'bound_signatures']

    lib = ctypes.CDLL(str(LIBRARY))
    names = sorted(bound_signatures())
    assert len(names) > 200
    assert [n for n in names if not hasattr(lib, n)] == []
