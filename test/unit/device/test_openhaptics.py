"""``backend: openhaptics`` through the unmodified pyOpenHaptics package against the OpenHaptics
emulator (``emulators/openhaptics/hd.c``, built by ``scripts/setup.sh`` into
``<venv>/lib/haptic_topology/libHD.so``): the shared conformance checks (the device's side
read from the emulator's committed force, ``hdEmuApplied``), the device's force limit, faults
injected through the emulator's variables (unplugged: ``HD_COMM_ERROR``; a NaN state; a
failing call; a device that needs calibration), the axes, the options, and a missing library
(exit status 2, one line). The loop on the device's servo clock: ``test_openhaptics_clock.py``.

One libHD per process: every test here uses the emulator, whose settings are read at each
``hdInitDevice`` (so each test sets its variables before ``activate``)."""

from __future__ import annotations

import ctypes
import math
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
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
    same,
)

from haptic_topology.cli import main as cli_main
from haptic_topology.device.backend import (
    BackendConfig,
    DeviceBackend,
    check_axes,
    create_backend,
)
from haptic_topology.device.openhaptics import OpenHapticsBackend
from haptic_topology.device.openhaptics_hd import EMULATOR
from haptic_topology.errors import AxesError, DeviceError, VendorLibraryMissing
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import DeviceStatus, TaskSpace

#: No engage or clutch button (the hand always grasps), no grasp fade (the driver's watchdog
#: fades in already; the checks compare each force with its command).
PARAMS = Path(__file__).resolve().parents[3] / 'config' / 'devices' / 'openhaptics_emulator.yaml'
OPTIONS = {'engage_button': None, 'clutch_button': None, 'grasp_ramp_ms': 0.0}
EMU_VARIABLES = ('HD_EMU_UNPLUG_AT', 'HD_EMU_NAN_AT', 'HD_EMU_NAN_FOR', 'HD_EMU_FAIL',
                 'HD_EMU_CALIBRATION', 'HD_EMU_INKWELL', 'HD_EMU_MAX_FORCE', 'HD_EMU_BUTTONS',
                 'HD_EMU_DEVICES')

pytestmark = pytest.mark.skipif(not EMULATOR.is_file(),
                                reason=f'{EMULATOR} not built: run scripts/setup.sh')


@pytest.fixture(autouse=True)
def clean_emulator(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """No emulator setting of another test (they are read at each hdInitDevice)."""
    for name in EMU_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv('HAPTIC_TOPOLOGY_LIBHD', str(EMULATOR))
    yield


def _emu() -> ctypes.CDLL:
    lib = ctypes.CDLL(str(EMULATOR))
    lib.hdEmuApplied.restype = ctypes.c_longlong
    lib.hdEmuApplied.argtypes = [ctypes.POINTER(ctypes.c_double),
                                 ctypes.POINTER(ctypes.c_longlong)]
    return lib


def applied() -> tuple[np.ndarray, int]:
    """The force the emulated motors got at the newest frame (N, device axes) and when (ns)."""
    out = (ctypes.c_double * 3)()
    t = ctypes.c_longlong()
    _emu().hdEmuApplied(out, ctypes.byref(t))
    return np.array(out[:]), int(t.value)


class EmulatedTouch:
    """The device side (``backend_conformance.DeviceSide``): the emulator's committed force,
    in task axes through the backend's mapping."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.w: list[np.ndarray] = []

    def after_cycle(self, backend: DeviceBackend) -> None:
        assert isinstance(backend, OpenHapticsBackend)
        force, t_ns = applied()
        self.t.append(t_ns)
        self.w.append(backend.task_force(force))

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        return bool(self.t) and self.t[-1] >= after_ns and same(self.w[-1], expected)

    def poll(self, seconds: float) -> None:
        pass

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.t, dtype=np.int64), np.array(self.w)


CHECKS: dict[str, Callable[[Bench], None]] = {
    'clamping': check_clamping, 'nonfinite': check_nonfinite, 'watchdog': check_watchdog,
    'lifecycle': check_lifecycle,
}


@pytest.mark.parametrize('check', sorted(CHECKS))
def test_openhaptics_conforms(check: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The shared checks on fig8_point (a force-only point task), the device's force limit
    above the scenario's 20 N per axis: the device gets what the driver's clamp lets
    through."""
    monkeypatch.setenv('HD_EMU_MAX_FORCE', '100')
    CHECKS[check](Bench(Subject('openhaptics', EmulatedTouch, dict(OPTIONS),
                                scenario='fig8_point')))


def _backend(options: dict[str, object] | None = None,
             scenario: str = 'fig8_point') -> OpenHapticsBackend:
    sc = load_scenario(scenario)
    be = create_backend('openhaptics')
    assert isinstance(be, OpenHapticsBackend)
    be.configure(BackendConfig(sc.device, initial_device_pose(sc), {},
                               dict(OPTIONS, **(options or {})), sc.source))
    return be


def test_identity_axes_and_units() -> None:
    """The device's identity from hdGetString; its origin at the scenario's start; task x, y
    = device x, y (mm -> m); ``axes: [x, -z, y]`` maps task y to the device's -z."""
    be = _backend()
    start = initial_device_pose(load_scenario('fig8_point'))
    be.activate()
    try:
        assert be.hardware_id == 'openhaptics Touch serial EMU-00001'
        be.write(np.zeros(2))
        r = be.read(0.001)
        assert r.status == DeviceStatus.OK
        np.testing.assert_allclose(r.pose, start, rtol=0.0, atol=1e-12)   # the first grasp
        values = be.values()
        assert (values['device_model'], values['device_serial']) == ('Touch', 'EMU-00001')
        np.testing.assert_array_equal(r.hand_wrench, np.zeros(2))   # no force sensor
        be.write(np.array([0.5, -0.25]))
        be.read(0.001)
        np.testing.assert_array_equal(applied()[0], [0.5, -0.25, 0.0])
    finally:
        be.write(np.zeros(2))
        be.deactivate()
    be = _backend({'axes': ['x', '-z', 'y']})
    be.activate()
    try:
        be.write(np.zeros(2))
        be.read(0.001)                  # the first reading: the hand grasps
        be.write(np.array([0.5, -0.25]))
        be.read(0.001)
        np.testing.assert_array_equal(applied()[0], [0.5, 0.0, 0.25])
        np.testing.assert_array_equal(be.task_force(np.array([0.5, 0.0, 0.25])), [0.5, -0.25])
    finally:
        be.write(np.zeros(2))
        be.deactivate()


def test_the_force_is_clamped_to_the_devices_nominal_maximum() -> None:
    """A Touch's HD_NOMINAL_MAX_FORCE is 3.3 N: a 20 N command (the scenario's limit) reaches
    the motors as 3.3 N in the same direction."""
    be = _backend()
    be.activate()
    try:
        be.read(0.001)                  # the first reading: the hand grasps
        be.write(np.array([20.0, 20.0]))
        be.read(0.001)
        f = applied()[0]
        assert math.isclose(float(np.linalg.norm(f)), 3.3, rel_tol=1e-12)
        np.testing.assert_allclose(f / np.linalg.norm(f), [2 ** -0.5, 2 ** -0.5, 0.0])
        assert be.values()['openhaptics_max_force_n'] == '3.3'
    finally:
        be.write(np.zeros(2))
        be.deactivate()


def _until_fault(be: OpenHapticsBackend, cycles: int = 5000) -> int:
    for k in range(cycles):
        be.write(np.array([1.0, 0.0]))
        r = be.read(0.001)
        assert all(np.all(np.isfinite(v)) for v in (r.pose, r.twist, r.hand_wrench))
        if r.status & DeviceStatus.FAULT:
            return k
    raise AssertionError(f'no fault in {cycles} cycles')


def test_an_unplugged_device_is_a_fault_with_its_reason_and_no_force(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Unplugged at servo tick 100: the readings carry FAULT with HD_COMM_ERROR as the reason,
    finite, and the motors get nothing."""
    monkeypatch.setenv('HD_EMU_UNPLUG_AT', '100')
    be = _backend()
    be.activate()
    try:
        _until_fault(be)
        assert be.fault_reason() == 'openhaptics: Touch: HD_COMM_ERROR (0x302)'
        np.testing.assert_array_equal(applied()[0], np.zeros(3))
        assert int(be.values()['openhaptics_errors']) >= 1
    finally:
        be.write(np.zeros(2))
        be.deactivate()


def test_a_nan_state_is_a_fault_and_never_passed_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """A NaN position for 300 servo ticks (0.3 s: long enough that a reading lands in it
    however late this thread runs): FAULT readings at the last valid pose with zero twist,
    then the readings are valid again."""
    monkeypatch.setenv('HD_EMU_NAN_AT', '100')
    monkeypatch.setenv('HD_EMU_NAN_FOR', '300')
    be = _backend()
    be.activate()
    try:
        last = None
        for _ in range(5000):
            r = be.read(0.001)
            if r.status & DeviceStatus.FAULT:
                break
            last = r.pose
        assert last is not None and r.status & DeviceStatus.FAULT
        np.testing.assert_array_equal(r.pose, last)
        np.testing.assert_array_equal(r.twist, np.zeros(2))
        assert be.fault_reason() == 'openhaptics: Touch: non-finite position or velocity'
        for _ in range(5000):
            r = be.read(0.001)
            assert np.all(np.isfinite(r.pose)) and np.all(np.isfinite(r.twist))
            if r.status == DeviceStatus.OK:
                break
        assert r.status == DeviceStatus.OK
    finally:
        be.write(np.zeros(2))
        be.deactivate()


@pytest.mark.parametrize(('call', 'text'), [
    ('hdInitDevice', 'openhaptics: hdInitDevice failed: HD_COMM_CONFIG_ERROR (0x303): is the '
                     'Touch connected and its driver (Touch_Setup) configured?'),
    ('hdEnable', 'openhaptics: hdEnable(HD_FORCE_OUTPUT) failed: HD_INVALID_OPERATION '
                 '(0x102)'),
    ('hdStartScheduler', 'openhaptics: hdStartScheduler failed: HD_TIMER_ERROR (0x304)'),
])
def test_a_failing_call_fails_the_activation_with_its_error_and_releases(
        call: str, text: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A call that fails: activate raises with the HD error; the release after it (the
    driver's) closes the device, and the next activation works."""
    monkeypatch.setenv('HD_EMU_FAIL', call)
    be = _backend()
    with pytest.raises(DeviceError) as err:
        be.activate()
    assert str(err.value) == text
    be.deactivate()
    monkeypatch.delenv('HD_EMU_FAIL')
    be.activate()
    try:
        assert be.read(0.001).status == DeviceStatus.OK
    finally:
        be.deactivate()


def test_calibration_is_asked_for_or_done_from_the_inkwell(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('HD_EMU_CALIBRATION', 'needs_manual_input')
    be = _backend()
    with pytest.raises(DeviceError, match='openhaptics: Touch serial EMU-00001 needs '
                                          'calibration: put the stylus in the inkwell'):
        be.activate()
    be.deactivate()
    # An update due and the stylus in the inkwell: hdUpdateCalibration, then it runs.
    monkeypatch.setenv('HD_EMU_CALIBRATION', 'needs_update')
    monkeypatch.setenv('HD_EMU_INKWELL', '1')
    be.activate()
    try:
        assert be.read(0.001).status == DeviceStatus.OK
        assert be.values()['openhaptics_inkwell'] == '1'
    finally:
        be.deactivate()


def test_the_engage_button_grasps_and_the_clutch_lets_go() -> None:
    """``engage_button: 0``, ``clutch_button: 1`` on the device's buttons (HD_CURRENT_BUTTONS):
    no button, no force (WATCHDOG); button 1 held, the command reaches the motors; the clutch
    held as well, zero again."""
    lib = _emu()
    lib.hdEmuSetButtons.argtypes = [ctypes.c_int, ctypes.c_int]
    be = _backend({'engage_button': 0, 'clutch_button': 1})
    be.activate()
    try:
        u = np.array([0.5, -0.25])
        for mask, expected, status in ((0, [0.0, 0.0, 0.0], DeviceStatus.WATCHDOG),
                                       (1, [0.5, -0.25, 0.0], DeviceStatus.OK),
                                       (3, [0.0, 0.0, 0.0], DeviceStatus.WATCHDOG)):
            lib.hdEmuSetButtons(mask, 0)
            be.write(u)
            r = be.read(0.001)          # the buttons of this frame: grasping from now on
            be.write(u)
            be.read(0.001)              # the force of the next frame follows them
            assert r.status == status and be.buttons == mask
            np.testing.assert_array_equal(applied()[0], expected)
        assert be.values()['grasps'] == '1'
    finally:
        lib.hdEmuSetButtons(0, 0)
        be.write(np.zeros(2))
        be.deactivate()


def test_applied_is_what_the_device_got_released_fading_in_and_limited() -> None:
    """The loop's ``applied`` (the trace's column) is what the motors were sent: exactly zero
    while the engage button is released, the faded force while the grasp fades in
    (``grasp_ramp_ms: 5``: 0.2 of the command more each 1 ms cycle), and within the Touch's
    3.3 N once the faded command exceeds it (a 5 N command: 0.66 of it). The emulated
    motors' committed force, in task axes, is the reference, cycle by cycle."""
    lib = _emu()
    lib.hdEmuSetButtons.argtypes = [ctypes.c_int, ctypes.c_int]
    bench = Bench(Subject('openhaptics', EmulatedTouch,
                          dict(OPTIONS, engage_button=0, grasp_ramp_ms=5.0),
                          scenario='fig8_point'))
    assert bench.dt == 0.001
    u = np.array([4.0, -3.0])
    try:
        bench.activate()
        bench.engage()

        def cycle() -> np.ndarray:
            bench.cycle(u)
            got = bench.written[-1]
            assert isinstance(bench.backend, OpenHapticsBackend)
            np.testing.assert_allclose(got, bench.backend.task_force(applied()[0]),
                                       rtol=0.0, atol=1e-12)
            return got

        for _ in range(10):
            assert not cycle().any(), 'applied while the engage button is released'
        lib.hdEmuSetButtons(1, 0)
        fractions = [float(cycle()[0] / u[0]) for _ in range(7)]
        np.testing.assert_allclose(fractions, [0.0, 0.2, 0.4, 0.6, 0.66, 0.66, 0.66],
                                   rtol=1e-12, atol=0.0)
        lib.hdEmuSetButtons(0, 0)
        cycle()                         # this cycle's read lets go
        assert not cycle().any(), 'applied after the engage button was released'
    finally:
        lib.hdEmuSetButtons(0, 0)
        bench.release()


THREE = 'Left Touch=EMU-L,Right Touch=EMU-R,Spare=EMU-S'
NAMES = ['Left Touch', 'Right Touch', 'Spare']


def test_a_device_is_chosen_among_several_by_serial(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three configured devices (the emulator's ``HD_EMU_DEVICES``): ``device`` lists their
    names, ``serial`` picks one. Each name is opened and its HD_DEVICE_SERIAL_NUMBER read; the
    matching one is kept and made current (its identity, its frames), the others are closed
    (they open again at once); preflight does the same and closes it too."""
    monkeypatch.setenv('HD_EMU_DEVICES', THREE)
    sc = load_scenario('fig8_point')
    OpenHapticsBackend().preflight(BackendConfig(
        sc.device, initial_device_pose(sc), {},
        dict(OPTIONS, device=NAMES, serial='EMU-R'), sc.source))
    be = _backend({'device': NAMES, 'serial': 'EMU-R'})
    be.activate()
    try:
        assert be.hardware_id == 'openhaptics Touch serial EMU-R'
        assert be.values()['device_serial'] == 'EMU-R'
        lib = ctypes.CDLL(str(EMULATOR))
        lib.hdInitDevice.argtypes = [ctypes.c_char_p]
        lib.hdInitDevice.restype = ctypes.c_uint
        lib.hdGetCurrentDevice.restype = ctypes.c_uint
        kept = lib.hdGetCurrentDevice()
        for name in (b'Left Touch', b'Spare'):          # closed: they open again
            other = lib.hdInitDevice(name)
            assert other not in (kept, 0xFFFFFFFF), name
            lib.hdDisableDevice(other)
        lib.hdMakeCurrentDevice(kept)
        be.write(np.zeros(2))
        assert be.read(0.001).status == DeviceStatus.OK
        be.write(np.array([0.5, -0.25]))
        be.read(0.001)
        np.testing.assert_array_equal(applied()[0], [0.5, -0.25, 0.0])
    finally:
        be.write(np.zeros(2))
        be.deactivate()
    # A serial number on its own (one name, the default configuration) is checked too.
    be = _backend({'device': 'Spare', 'serial': 'EMU-S'})
    be.activate()
    try:
        assert be.hardware_id == 'openhaptics Touch serial EMU-S'
    finally:
        be.deactivate()


def test_no_device_with_that_serial_names_the_serials_found(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """No device with the serial asked for: one line naming each name's serial (or its HD
    error), every device closed again (the next activation opens the right one)."""
    monkeypatch.setenv('HD_EMU_DEVICES', THREE)
    be = _backend({'device': [*NAMES, 'Elsewhere'], 'serial': 'EMU-X'})
    with pytest.raises(DeviceError) as err:
        be.activate()
    assert str(err.value) == (
        "openhaptics: no device with serial EMU-X among backend_options.device: found "
        "'Left Touch' serial EMU-L; 'Right Touch' serial EMU-R; 'Spare' serial EMU-S; "
        "'Elsewhere': HD_COMM_CONFIG_ERROR (0x303)")
    be.deactivate()
    be = _backend({'device': NAMES, 'serial': 'EMU-L'})
    be.activate()
    try:
        assert be.hardware_id == 'openhaptics Touch serial EMU-L'
    finally:
        be.deactivate()


@pytest.mark.parametrize(('options', 'text'), [
    ({'device': NAMES}, 'openhaptics: backend_options.device: 3 names need '
                        'backend_options.serial to choose among them'),
    ({'device': ['a', 'a'], 'serial': 'x'}, r"backend_options.device: expected an OpenHaptics "
                                            r"device name \(Touch_Setup\) or a list of "
                                            r"different names, got \['a', 'a'\]"),
    ({'serial': ['x']}, r"backend_options.serial: expected the device's serial number"),
])
def test_device_selection_options_name_the_field(options: dict, text: str) -> None:
    with pytest.raises(DeviceError, match=text):
        _backend(options)


def test_axes_point_tasks_only() -> None:
    """3 forces: fig8 (torque about z) is refused with check_axes' one line; configure
    refuses a rigid task too; options are checked naming the field."""
    with pytest.raises(AxesError, match='scenario fig8 needs torque about z; device openhaptics '
                                        'actuates x, y, z forces only: use fig8_point'):
        check_axes(TaskSpace.PLANAR, OpenHapticsBackend.axes({}), 'fig8', 'openhaptics',
                   'fig8_point')
    check_axes(TaskSpace.SPATIAL_POINT, OpenHapticsBackend.axes({}), 'x', 'openhaptics')
    with pytest.raises(DeviceError, match='a planar task needs torque; a 3-axis device '
                                          'renders a point grasp only'):
        _backend(scenario='fig8')
    with pytest.raises(DeviceError, match=r"backend_options.axes: expected .* got \['x', 'y', "
                                          r"'-z'\]"):
        _backend({'axes': ['x', 'y', '-z']})
    with pytest.raises(DeviceError, match=r"backend_options.max_force: expected a number in "
                                          r"\(0, 1000\] or null \(N; null: the device's own "
                                          r"limit\), got -1"):
        _backend({'max_force': -1})
    with pytest.raises(DeviceError, match="unknown option 'port'"):
        _backend({'port': 3})


def test_a_missing_library_stops_run_before_anything_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``run`` with HAPTIC_TOPOLOGY_LIBHD naming a libHD.so that is not there: exit status 2
    and one line naming the package, the library and the variable."""
    missing = tmp_path / 'libHD.so'
    monkeypatch.setenv('HAPTIC_TOPOLOGY_LIBHD', str(missing))
    assert cli_main(['run', 'fig8_point', '--params', str(PARAMS)]) == 2
    err = capsys.readouterr().err
    assert err == ('haptic-topology run: error: openhaptics: cannot load libHD.so through the '
                   f'Python package pyOpenHaptics==1.0.1 (HAPTIC_TOPOLOGY_LIBHD={missing}: no '
                   'such file); install both and set HAPTIC_TOPOLOGY_LIBHD '
                   '(docs/devices.md)\n')
    sc = load_scenario('fig8_point')
    with pytest.raises(VendorLibraryMissing):
        OpenHapticsBackend().preflight(BackendConfig(sc.device, initial_device_pose(sc), {},
                                                     dict(OPTIONS)))


def test_devices_reports_a_library_that_cannot_load_here_and_goes_on(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A process that holds the emulator's libHD asked to load ``libHD.so`` from the loader's
    path (another copy): ``haptic-topology devices`` lists openhaptics as not loading, with
    the reason, and the other backends (exit status 0), instead of stopping at it."""
    from haptic_topology.device.openhaptics_hd import load_hd

    load_hd()                           # the emulator, by its path (the fixture's variable)
    monkeypatch.delenv('HAPTIC_TOPOLOGY_LIBHD')
    assert cli_main(['devices']) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith('openhaptics '))
    assert f'this process has loaded {EMULATOR}; cannot load libHD.so too' in line, line
    assert '\nforcedimension ' in out and '\nhaply ' in out, out


def test_without_libhd_on_the_loaders_path_run_says_what_to_install() -> None:
    """No HAPTIC_TOPOLOGY_LIBHD and no libHD.so on the loader's path (a computer without
    OpenHaptics): exit status 2, one line."""
    env = {k: v for k, v in os.environ.items()
           if k not in ('HAPTIC_TOPOLOGY_LIBHD', 'LD_LIBRARY_PATH')}
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                           '--params', str(PARAMS)], capture_output=True, text=True,
                          timeout=120, env=env, check=False)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.count('\n') == 1, proc.stderr
    assert proc.stderr.startswith('haptic-topology run: error: openhaptics: cannot load '
                                  'libHD.so through the Python package pyOpenHaptics==1.0.1 '
                                  '(libHD.so: cannot open shared object file'), proc.stderr


def test_a_device_that_does_not_open_stops_run_before_anything_starts(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``run``'s preflight opens the device (and closes it): hdInitDevice failing is status 1
    and the HD error in one line, before any node starts."""
    monkeypatch.setenv('HD_EMU_FAIL', 'hdInitDevice')
    assert cli_main(['run', 'fig8_point', '--params', str(PARAMS)]) == 1
    err = capsys.readouterr().err
    assert err == ('haptic-topology run: error: device: openhaptics: hdInitDevice failed: '
                   'HD_COMM_CONFIG_ERROR (0x303): is the Touch connected and its driver '
                   '(Touch_Setup) configured?\n')
