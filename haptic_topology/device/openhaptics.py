"""3D Systems Touch, Touch X and Phantom Premium through OpenHaptics' HD API: ``backend:
openhaptics``, with the unmodified PyPI package ``pyOpenHaptics`` (ctypes bindings of
``libHD.so``).

**The library** (:mod:`~haptic_topology.device.openhaptics_hd`): the variable
``HAPTIC_TOPOLOGY_LIBHD`` (a path; the emulator that ``scripts/setup.sh`` builds is
``<venv>/lib/haptic_topology/libHD.so``), else ``libHD.so`` on the loader's path (OpenHaptics
for Linux installs it in ``/usr/lib``; ``LD_LIBRARY_PATH`` adds directories). Without it, or
without the package, ``run`` stops before anything starts
(:class:`~haptic_topology.errors.VendorLibraryMissing`, exit status 2; this module's
:func:`support` is the backend's entry in the vendor registry, and
:meth:`OpenHapticsBackend.preflight` checks it too).

**The clock.** OpenHaptics' scheduler thread calls the servo callbacks at 1 kHz; that
callback is the device's clock
(:attr:`~haptic_topology.device.backend.DeviceBackend.drives_loop`): in the loop process
each cycle runs inside it (:meth:`OpenHapticsBackend.run_clocked`): ``hdBeginFrame`` (the
device state is snapshot), the cycle (``write``: ``hdSetDoublev(HD_CURRENT_FORCE)``;
``read``: the transform, velocity and buttons of the frame; the controller), ``hdEndFrame``
(the force goes to the motors), then the loop's work between two cycles. The callback is
this module's own (pyOpenHaptics' ``hd_callback`` wrapper ends the servo loop at the first
error ``hdGetError`` reports): an error makes the reading a device fault
(``DeviceStatus.FAULT``, the driver writes zero) and the loop goes on. Called from a loop
that paces itself (the in-process layouts, the conformance checks), ``read`` exchanges one
frame with the servo thread through ``hdScheduleSynchronous`` (it waits for the next servo
tick, at most one period) and ``write`` keeps the force for it.

**Frames and units** (:class:`~haptic_topology.device.vendor.VendorHand`, the vendor
options): OpenHaptics reports mm, mm/s and N in the device's axes: x right, y up, z toward the
user; the backend gives the hand metres. ``axes`` names the device axis of each task axis
(signed: ``[x, -z, y]``: task x is device x, task y is device -z, task z is device y;
default ``[x, y, z]``); the first grasp is where the scenario's hand starts (or ``origin``).
The task is a point task (``planar_point``: task x, y; ``spatial_point``: x, y, z): the
device senses 3 translations (and the stylus' orientation, not used) and actuates 3 forces.
The buttons (``HD_CURRENT_BUTTONS``) grasp and clutch (``engage_button``,
``clutch_button``). The Touch has no force sensor: the hand wrench reads zero, the controller
answers the motion. Each force sent is clamped in magnitude to the device's
``HD_NOMINAL_MAX_FORCE`` (the direction kept; ``max_force``: a lower limit).

**Several devices.** ``device`` names the OpenHaptics configuration to open (Touch_Setup's
name, ``Default Device`` unless renamed); with ``serial``, ``device`` may list several names:
each is opened, the one whose ``HD_DEVICE_SERIAL_NUMBER`` is ``serial`` is kept and the others
closed (:func:`~haptic_topology.device.openhaptics_hd.open_device`).

**Calibration.** A Touch needs its inkwell calibration after power-up: ``activate`` checks
``hdCheckCalibration``, asks ``hdUpdateCalibration`` when an update is due, and refuses to
start otherwise, saying to put the stylus in the inkwell (or run ``Touch_Setup`` /
``Touch_Diagnostic`` for a device that needs manual calibration).
"""

from __future__ import annotations

import ctypes
import math
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceReading
from haptic_topology.device.openhaptics_hd import (
    BACKEND,
    HD_CALIBRATION_NEEDS_UPDATE,
    HD_CALIBRATION_OK,
    HD_CALIBRATION_STYLE,
    HD_CALLBACK_CONTINUE,
    HD_CALLBACK_DONE,
    HD_CURRENT_INKWELL_SWITCH,
    HD_CURRENT_VELOCITY,
    HD_DEVICE_SERIAL_NUMBER,
    HD_DEVICE_VENDOR,
    HD_FORCE_OUTPUT,
    HD_NOMINAL_MAX_FORCE,
    HD_SUCCESS,
    HD_VERSION,
    LIBRARY,
    LIBRARY_ENV,
    PACKAGE,
    SERVO_HZ,
    STALL,
    HdLibrary,
    error_text,
    hd_string,
    load_hd,
    open_device,
)
from haptic_topology.device.vendor import (
    DeviceIdentity,
    VendorBackend,
    VendorSupport,
    optional_number,
)
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import DeviceStatus

#: The backend's own options (name -> default), besides the vendor ones
#: (:data:`~haptic_topology.device.vendor.VENDOR_OPTIONS`).
OWN_OPTIONS: dict[str, Any] = {'device': 'Default Device', 'serial': None, 'max_force': None}


def support() -> VendorSupport:
    """This backend's entry in the vendor registry
    (:data:`~haptic_topology.device.vendor.VENDOR_BACKENDS`, as
    ``'openhaptics': 'haptic_topology.device.openhaptics:support'``)."""
    return VendorSupport(BACKEND, PACKAGE, LIBRARY, LIBRARY_ENV, _where, list_devices)


def _where() -> str:
    """What :func:`~haptic_topology.device.openhaptics_hd.load_hd` loaded: the library."""
    return load_hd().path


def list_devices() -> list[str]:
    """The device of the default configuration, opened briefly (``hdInitDevice``, no output
    enabled): ``'<model> serial <serial>'``."""
    hd = load_hd().hd
    handle = open_device(hd, (str(OWN_OPTIONS['device']),), None)
    try:
        return [f'{hd.get_model()} serial {hd_string(hd, HD_DEVICE_SERIAL_NUMBER)}']
    finally:
        hd.close_device(handle)


def _names(value: Any) -> tuple[str, ...]:
    """``backend_options.device``: one configuration name or a list of them."""
    names = [value] if isinstance(value, str) else value
    if (not isinstance(names, list) or not names or len(set(names)) != len(names)
            or not all(isinstance(n, str) and n for n in names)):
        raise DeviceError(f'{BACKEND}: backend_options.device: expected an OpenHaptics device '
                          'name (Touch_Setup) or a list of different names, got '
                          f'{value!r}')
    return tuple(names)


class OpenHapticsBackend(VendorBackend):
    """A Touch / Touch X / Phantom Premium through OpenHaptics (module doc). Options: the
    vendor ones (:func:`~haptic_topology.device.vendor.parse_vendor_options`: ``axes``,
    ``origin``, ``scale``, ``force_scale``, ``engage_button``, ``clutch_button``,
    ``grasp_ramp_ms``), ``device`` (the OpenHaptics configuration name, default ``Default
    Device``, or a list of names), ``serial`` (the unit's HD_DEVICE_SERIAL_NUMBER: the one
    of those devices to open, :func:`~haptic_topology.device.openhaptics_hd.open_device`;
    null: the one name given), ``max_force`` (N, below the device's own limit)."""

    name = 'openhaptics'
    drives_loop = True
    velocity_filtered = True    # HD_CURRENT_VELOCITY: the driver's filtered difference
    own_options = OWN_OPTIONS

    def preflight(self, config: BackendConfig) -> None:
        """Before ``run`` starts a node: the options, the library and the package
        (:func:`~haptic_topology.device.openhaptics_hd.load_hd`; else
        :class:`~haptic_topology.errors.VendorLibraryMissing`, exit status 2) and the device,
        opened and closed again (``hdInitDevice``, ``hdDisableDevice``: no output enabled)."""
        self.configure(config)
        hd = load_hd().hd
        hd.close_device(open_device(hd, self._names, self._serial))

    def __init__(self) -> None:
        super().__init__()
        self._names: tuple[str, ...] = (str(OWN_OPTIONS['device']),)
        self._serial: str | None = None
        self._option_max_force = math.inf
        self._lib: HdLibrary | None = None
        self._handle: int | None = None
        self._active = False
        self._max_force = math.inf
        self._force = (0.0, 0.0, 0.0)           # device N, for the next frame
        self._in_frame = False
        self._reading: DeviceReading | None = None
        self._last: DeviceReading | None = None
        self._fault = ''                 # from the errors drained since the last reading
        self._reason = ''
        self.buttons = 0
        self.inkwell = False
        self.errors = 0
        self.ticks = 0
        self._sync_cb: Any = None
        self._servo_cb: Any = None
        self._stop_clock = False
        self._stalled = False
        self._dt = 0.0

    # -- configuration ---------------------------------------------------------------------
    def configure_own(self, own: dict[str, Any]) -> None:
        max_force = optional_number(own['max_force'], 'max_force', self.name, 1000.0,
                                    "N; null: the device's own limit")
        names = _names(own['device'])
        serial = own['serial']
        if isinstance(serial, int) and not isinstance(serial, bool) and serial >= 0:
            serial = str(serial)
        if serial is not None and (not isinstance(serial, str) or not serial):
            raise DeviceError(f'{self.name}: backend_options.serial: expected the device\'s '
                              'serial number (HD_DEVICE_SERIAL_NUMBER, text) or null, got '
                              f'{own["serial"]!r}')
        if serial is None and len(names) > 1:
            raise DeviceError(f'{self.name}: backend_options.device: {len(names)} names need '
                              'backend_options.serial to choose among them (or name one '
                              'device)')
        self._names, self._serial = names, serial
        self._option_max_force = math.inf if max_force is None else max_force

    def values(self) -> dict[str, str]:
        out = super().values()
        out.update({'openhaptics_buttons': str(self.buttons),
                    'openhaptics_inkwell': str(int(self.inkwell)),
                    'openhaptics_errors': str(self.errors),
                    'openhaptics_max_force_n': f'{self._max_force:g}',
                    'openhaptics_servo_ticks': str(self.ticks)})
        return out

    def fault_reason(self) -> str:
        return self._reason or super().fault_reason()

    # -- lifecycle -------------------------------------------------------------------------
    def _require_hd(self) -> Any:
        """``pyOpenHaptics.hd`` (after ``activate``)."""
        if self._lib is None:
            raise DeviceError('openhaptics: used before activate()')
        return self._lib.hd

    def _drain_errors(self) -> None:
        """Take every error the HDAPI holds (``hdGetError`` pops the oldest): a device fault of
        the next reading."""
        hd = self._require_hd()
        while True:
            code = int(hd._get_error().errorCode)
            if code == HD_SUCCESS:
                return
            self.errors += 1
            if not self._fault:
                model = self.identity.model if self.identity else 'device'
                self._fault = f'{self.name}: {model}: {error_text(code)}'

    def _fail_on_error(self, what: str) -> None:
        hd = self._require_hd()
        code = int(hd._get_error().errorCode)
        if code != HD_SUCCESS:
            self._drain_errors()
            raise DeviceError(f'openhaptics: {what} failed: {error_text(code)}')

    def activate(self) -> None:
        if self._hand is None:
            raise DeviceError(f'{self.name}: activate() before configure()')
        self._lib = load_hd()
        hd = self._lib.hd
        lib = hd._lib_hd
        self._handle = open_device(hd, self._names, self._serial)
        self.identity = DeviceIdentity(hd_string(hd, HD_DEVICE_VENDOR), hd.get_model(),
                                        hd_string(hd, HD_DEVICE_SERIAL_NUMBER),
                                        f'OpenHaptics {hd_string(hd, HD_VERSION)}')
        self._check_calibration(lib)
        nominal = hd._get_doublev(HD_NOMINAL_MAX_FORCE, ctypes.c_double).value
        self._max_force = min(float(nominal) if nominal > 0 else math.inf,
                              self._option_max_force)
        self._fail_on_error('reading the device properties')
        self._force = (0.0, 0.0, 0.0)
        lib.hdEnable.argtypes = [ctypes.c_uint]
        lib.hdEnable(HD_FORCE_OUTPUT)
        self._fail_on_error('hdEnable(HD_FORCE_OUTPUT)')
        hd.start_scheduler()
        self._fail_on_error('hdStartScheduler')
        self._sync_cb = self._callback(self._sync_frame)
        self._stalled = False
        self._active = True
        self._fault = self._reason = ''

    def _check_calibration(self, lib: Any) -> None:
        lib.hdCheckCalibration.restype = ctypes.c_uint
        state = int(lib.hdCheckCalibration())
        if state == HD_CALIBRATION_NEEDS_UPDATE:
            style = self._require_hd()._get_integerv(HD_CALIBRATION_STYLE, ctypes.c_int).value
            lib.hdUpdateCalibration.argtypes = [ctypes.c_uint]
            lib.hdUpdateCalibration(int(style))
            state = int(lib.hdCheckCalibration())
        if state != HD_CALIBRATION_OK:
            who = self.identity
            assert who is not None
            raise DeviceError(f'{self.name}: {who.model} serial {who.serial} needs '
                              'calibration: put the stylus in the inkwell and activate again '
                              '(a device that needs manual input: run Touch_Setup / '
                              f'Touch_Diagnostic), hdCheckCalibration 0x{state:04x}')

    def deactivate(self) -> None:
        """Zero force (one frame, while the scheduler runs), force output off, the scheduler
        stopped, the device closed. Harmless twice."""
        self._active = False
        self._force = (0.0, 0.0, 0.0)
        handle = self._handle
        if self._lib is None or handle is None:
            return
        hd = self._lib.hd
        lib = hd._lib_hd
        if self._sync_cb is not None and not self._stalled:
            self._lib.scheduling.hdSyncSheduler(self._sync_cb)      # a zero-force frame
        lib.hdDisable.argtypes = [ctypes.c_uint]
        lib.hdDisable(HD_FORCE_OUTPUT)
        hd.stop_scheduler()
        hd.close_device(handle)
        self._drain_errors()
        self._handle = None
        self._sync_cb = self._servo_cb = None     # no callback of ours is scheduled any more

    # -- the cycle ---------------------------------------------------------------------------
    def write(self, wrench: np.ndarray) -> None:
        if not self._active or self._hand is None:
            raise DeviceError(f'{self.name}: write() before activate()')
        # Zero while not grasping, faded in after a grasp, within the device's limit.
        f = self._hand.force(wrench, self._max_force)
        self._force = f
        if self._in_frame:
            self._require_hd().set_force(f)

    def task_force(self, device_force: np.ndarray) -> np.ndarray:
        """The task wrench (N) of a force on the device (N, device axes): the inverse of
        ``write``'s mapping at full grasp."""
        assert self._hand is not None
        f = [float(v) for v in device_force]
        task = self._hand.opts.mapping.task_command((f[0], f[1], f[2]), (0.0, 0.0, 0.0))
        assert task is not None
        return np.asarray(task[:self._m])

    def read(self, dt: float) -> DeviceReading:
        if not self._active:
            raise DeviceError(f'{self.name}: read() before activate()')
        if not self._in_frame:
            self._reading = None
            self._dt = dt
            assert self._lib is not None
            self._lib.scheduling.hdSyncSheduler(self._sync_cb)
            if self._reading is None:
                raise DeviceError(f'{self.name}: the servo loop did not run the frame '
                                  '(hdScheduleSynchronous)')
            return self._reading
        return self._frame_reading(dt)

    def _frame_reading(self, dt: float) -> DeviceReading:
        """The state of the open frame as a reading (:class:`~haptic_topology.device.vendor.
        VendorHand`: mm -> m, axes, grasp and clutch buttons), a device fault on an HD error
        or a non-finite state (then the newest valid pose, zero twist)."""
        hd = self._require_hd()
        hand = self._hand
        assert hand is not None
        t = hd.get_transform()
        p = (1e-3 * t[3][0], 1e-3 * t[3][1], 1e-3 * t[3][2])
        vel = hd._get_doublev(HD_CURRENT_VELOCITY, ctypes.c_double * 3)
        v = (1e-3 * vel[0], 1e-3 * vel[1], 1e-3 * vel[2])
        self.buttons = int(hd.get_buttons())
        self.inkwell = bool(hd._get_integerv(HD_CURRENT_INKWELL_SWITCH, ctypes.c_int).value)
        self._drain_errors()
        if not all(math.isfinite(x) for x in (*p, *v)):
            model = self.identity.model if self.identity else 'device'
            self._fault = self._fault or f'{self.name}: {model}: non-finite position or velocity'
        if self._fault:
            self._reason, self._fault = self._fault, ''
            m = self._m
            pose = self._last.pose if self._last is not None else self._start
            return DeviceReading(pose.copy(), np.zeros(m), np.zeros(m), DeviceStatus.FAULT)
        self._last = hand.reading(p, v, self.buttons, dt)
        return self._last

    def _callback(self, body: Callable[[], int]) -> Any:
        """A servo callback of ours (C function pointer, kept referenced by the caller)."""
        hd = self._require_hd()

        @ctypes.CFUNCTYPE(hd.HDCallbackCode, ctypes.POINTER(ctypes.c_void_p))
        def callback(data: Any) -> int:
            del data
            return body()

        return callback

    def _sync_frame(self) -> int:
        """One frame for a ``read`` outside the servo loop: the force kept by ``write``, the
        state snapshot."""
        hd = self._require_hd()
        try:
            hd.begin_frame(self._handle)
            self._in_frame = True
            self._drain_errors()
            hd.set_force(self._force)
            self._reading = self._frame_reading(self._dt)
        except BaseException as exc:    # never into C: reported by read() as no frame
            print(f'openhaptics: frame failed: {type(exc).__name__}: {exc}', file=sys.stderr)
        finally:
            self._in_frame = False
            hd.end_frame(self._handle)
            self._drain_errors()
        return HD_CALLBACK_DONE

    # -- the device's clock ----------------------------------------------------------------
    def run_clocked(self, period: float, cycle: Callable[[float], None],
                    between: Callable[[float], bool], keep_going: Callable[[], bool]) -> None:
        if abs(period * SERVO_HZ - 1.0) > 1e-9:
            raise DeviceError(f'openhaptics: the servo loop runs at {SERVO_HZ} Hz: the '
                              f'driver\'s rate_hz must be {SERVO_HZ} (period {period:g} s)')
        hd = self._require_hd()
        done = threading.Event()
        failure: list[BaseException] = []
        self._stop_clock = False

        def servo() -> int:
            now = time.monotonic()
            self.ticks += 1
            go = False
            try:
                hd.begin_frame(self._handle)
                self._in_frame = True
                try:
                    hd.set_force(self._force)       # held unless the cycle writes anew
                    cycle(now)
                finally:
                    self._in_frame = False
                    hd.end_frame(self._handle)
                go = between(now) and not self._stop_clock
            except BaseException as exc:    # never into C: re-raised in run_clocked's thread
                failure.append(exc)
            if not go:
                done.set()
                return HD_CALLBACK_DONE
            return HD_CALLBACK_CONTINUE

        self._servo_cb = self._callback(servo)
        assert self._lib is not None
        self._lib.scheduling.hdAsyncSheduler(self._servo_cb)
        seen, seen_at = self.ticks, time.monotonic()
        while not done.wait(0.02):
            if not keep_going():
                self._stop_clock = True
            now = time.monotonic()
            if self.ticks != seen:
                seen, seen_at = self.ticks, now
            elif now - seen_at > STALL:
                self._stalled = True        # deactivate must not wait for a servo tick
                self._drain_errors()
                why = f'; {self._fault}' if self._fault else ''
                raise DeviceError(f'openhaptics: the servo loop stopped calling back '
                                  f'({STALL:g} s without a tick){why}')
        if failure:
            raise failure[0]
