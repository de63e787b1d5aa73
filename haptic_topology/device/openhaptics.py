"""3D Systems Touch, Touch X and Phantom Premium through OpenHaptics' HD API: ``backend:
openhaptics``, with the unmodified PyPI package ``pyOpenHaptics`` (ctypes bindings of
``libHD.so``).

**The library** (:mod:`~haptic_topology.device.openhaptics_hd`): the option ``library``
(a path; ``emulator``: the emulator that ``scripts/setup.sh`` builds into
``<venv>/lib/haptic_topology/libHD.so``), else the variable ``HAPTIC_TOPOLOGY_LIBHD``, else
``libHD.so`` on the loader's path (OpenHaptics for Linux installs it in ``/usr/lib``;
``LD_LIBRARY_PATH`` adds directories). Without it, or without the package,
:meth:`OpenHapticsBackend.preflight` refuses the run before anything starts
(:class:`~haptic_topology.errors.MissingLibraryError`, exit status 2), naming both and the
variable.

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

**Frames and units.** OpenHaptics reports mm, mm/s and N in the device's axes: x right, y up,
z toward the user. The option ``axes`` names the device axis of each task axis (signed:
``[x, -z, y]``: task x is device x, task y is device -z, task z is device y; default ``[x, y,
z]``) and ``origin`` (m) is the task position of the device's origin (default: where the
scenario starts). The task is a point task (``planar_point``: task x, y; ``spatial_point``:
x, y, z): the device senses 3 translations (and the stylus' orientation, not used) and
actuates 3 forces. The Touch has no force sensor: the hand wrench reads zero, the controller
answers the motion. Each force sent is clamped to the device's ``HD_NOMINAL_MAX_FORCE``
(magnitude, direction kept; ``max_force`` option: a lower limit).

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
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from haptic_topology.device.backend import (
    BackendConfig,
    DeviceAxes,
    DeviceBackend,
    DeviceReading,
)
from haptic_topology.device.openhaptics_hd import (
    HD_CALIBRATION_NEEDS_UPDATE,
    HD_CALIBRATION_OK,
    HD_CALIBRATION_STYLE,
    HD_CALLBACK_CONTINUE,
    HD_CALLBACK_DONE,
    HD_CURRENT_INKWELL_SWITCH,
    HD_CURRENT_VELOCITY,
    HD_DEVICE_SERIAL_NUMBER,
    HD_FORCE_OUTPUT,
    HD_INVALID_HANDLE,
    HD_NOMINAL_MAX_FORCE,
    HD_SUCCESS,
    SERVO_HZ,
    STALL,
    HdLibrary,
    error_text,
    load_hd,
)
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import Axis, DeviceStatus, TaskSpace

_AXIS_INDEX = {'x': 0, 'y': 1, 'z': 2}
_OPTIONS = ('library', 'device', 'axes', 'origin', 'max_force')
#: The axes a 3-DOF force device of this family senses and actuates.
OH_AXES = DeviceAxes(frozenset((Axis.X, Axis.Y, Axis.Z)), frozenset((Axis.X, Axis.Y, Axis.Z)))


def _parse_axes(value: Any) -> np.ndarray:
    """The task <- device rotation of ``axes`` (rows: task axes, as signed device axes)."""
    ok = isinstance(value, list | tuple) and len(value) == 3
    m = np.zeros((3, 3))
    if ok:
        for row, name in enumerate(value):
            text = str(name).strip()
            sign = -1.0 if text.startswith('-') else 1.0
            axis = _AXIS_INDEX.get(text.lstrip('+-'))
            if axis is None:
                ok = False
                break
            m[row, axis] = sign
    if not ok or abs(np.linalg.det(m) - 1.0) > 1e-9:
        raise DeviceError(f'openhaptics: backend_options.axes: expected 3 signed device axis '
                          f'names such as [x, -z, y] (task x, y, z), right-handed, got {value!r}')
    return m


def _open(hd: Any, options: Mapping[str, Any]) -> int:
    """``hdInitDevice`` of the configuration ``options['device']``: its handle, or a
    :class:`~haptic_topology.errors.DeviceError` with the HD error (the error queue emptied:
    pyOpenHaptics' own ``init_device`` compares with the wrong constant)."""
    lib = hd._lib_hd
    lib.hdInitDevice.argtypes = [ctypes.c_char_p]
    lib.hdInitDevice.restype = ctypes.c_uint
    handle = int(lib.hdInitDevice(str(options.get('device', 'Default Device')).encode()))
    if handle != HD_INVALID_HANDLE:
        return handle
    code = int(hd._get_error().errorCode)
    while int(hd._get_error().errorCode) != HD_SUCCESS:
        pass
    raise DeviceError(f'openhaptics: hdInitDevice failed: {error_text(code)}: is the Touch '
                      'connected and its driver (Touch_Setup) configured?')


class OpenHapticsBackend(DeviceBackend):
    """A Touch / Touch X / Phantom Premium through OpenHaptics (module doc). Options:
    ``library`` (path, or ``emulator``), ``device`` (the OpenHaptics configuration name,
    default ``Default Device``), ``axes``, ``origin`` (m), ``max_force`` (N)."""

    name = 'openhaptics'
    lockstep = False
    drives_loop = True

    @classmethod
    def axes(cls, options: Mapping[str, Any]) -> DeviceAxes:
        """3 translations sensed, 3 forces actuated: point tasks only."""
        del options
        return OH_AXES

    def preflight(self, config: BackendConfig) -> None:
        """Before ``run`` starts a node: the library and the package load
        (:func:`~haptic_topology.device.openhaptics_hd.load_hd`; else
        :class:`~haptic_topology.errors.MissingLibraryError`, exit status 2) and the device
        opens (``hdInitDevice``, then ``hdDisableDevice``: no output is enabled)."""
        hd = load_hd(config.options).hd
        hd.close_device(_open(hd, config.options))

    def __init__(self) -> None:
        self._task: TaskSpace | None = None
        self._options: dict[str, Any] = {}
        self._rot = np.eye(3)
        self._origin = np.zeros(3)
        self._lib: HdLibrary | None = None
        self._handle: int | None = None
        self._active = False
        self._max_force = math.inf
        self._force = [0.0, 0.0, 0.0]           # device N, for the next frame
        self._in_frame = False
        self._reading: DeviceReading | None = None
        self._last_pose = np.zeros(0)
        self._fault = ''                 # from the errors drained since the last reading
        self._reason = ''
        self._model = self._serial = ''
        self.buttons = 0
        self.inkwell = False
        self.errors = 0
        self.nonfinite_commands = 0
        self.ticks = 0
        self._sync_cb: Any = None
        self._servo_cb: Any = None
        self._stop_clock = False
        self._stalled = False

    # -- configuration ---------------------------------------------------------------------
    def configure(self, config: BackendConfig) -> None:
        task = config.params.task
        opts = dict(config.options)
        unknown = sorted(set(opts) - set(_OPTIONS))
        if unknown:
            raise DeviceError(f'openhaptics: backend_options: unknown option {unknown[0]!r} '
                              f'(expected some of: {", ".join(_OPTIONS)})')
        if not task.point:
            raise DeviceError(f'openhaptics: the device applies forces only: the task must be '
                              f'a point task (planar_point, spatial_point), got {task.value}')
        rot = _parse_axes(opts.get('axes', ['x', 'y', 'z']))
        rows = task.translation_rows
        start = np.asarray(config.initial_pose, dtype=float)[rows]
        origin = opts.get('origin', start.tolist())
        if not (isinstance(origin, list | tuple) and len(origin) == start.size
                and all(isinstance(v, int | float) and math.isfinite(v) for v in origin)):
            raise DeviceError(f'openhaptics: backend_options.origin: expected {start.size} '
                              f'finite numbers (m, the task position of the device origin), '
                              f'got {origin!r}')
        max_force = opts.get('max_force', math.inf)
        if not (isinstance(max_force, int | float) and max_force > 0.0):
            raise DeviceError(f'openhaptics: backend_options.max_force: expected a number > 0 '
                              f'(N), got {max_force!r}')
        self._task, self._options, self._rot = task, opts, rot
        self._origin = np.zeros(3)
        self._origin[:start.size] = origin
        self._option_max_force = float(max_force)
        self._last_pose = np.array(origin, dtype=float)

    def task_dim(self) -> int:
        if self._task is None:
            raise DeviceError('openhaptics: used before configure()')
        return self._task.dim

    @property
    def hardware_id(self) -> str:
        if not self._model:
            return super().hardware_id
        return f'{self.name} {self._model} serial {self._serial}'

    def values(self) -> dict[str, str]:
        return {'openhaptics_buttons': str(self.buttons),
                'openhaptics_inkwell': str(int(self.inkwell)),
                'openhaptics_errors': str(self.errors),
                'openhaptics_nonfinite_commands': str(self.nonfinite_commands),
                'openhaptics_max_force_n': f'{self._max_force:g}',
                'openhaptics_servo_ticks': str(self.ticks)}

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
                self._fault = f'openhaptics: {self._model or "device"}: {error_text(code)}'

    def _fail_on_error(self, what: str) -> None:
        hd = self._require_hd()
        code = int(hd._get_error().errorCode)
        if code != HD_SUCCESS:
            self._drain_errors()
            raise DeviceError(f'openhaptics: {what} failed: {error_text(code)}')

    def activate(self) -> None:
        if self._task is None:
            raise DeviceError('openhaptics: activate() before configure()')
        self._lib = load_hd(self._options)
        hd = self._lib.hd
        lib = hd._lib_hd
        self._handle = _open(hd, self._options)
        lib.hdGetString.argtypes = [ctypes.c_uint]
        lib.hdGetString.restype = ctypes.c_char_p
        self._model = hd.get_model()
        self._serial = (lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b'').decode()
        self._check_calibration(lib)
        nominal = hd._get_doublev(HD_NOMINAL_MAX_FORCE, ctypes.c_double).value
        self._max_force = min(float(nominal) if nominal > 0 else math.inf,
                              self._option_max_force)
        self._fail_on_error('reading the device properties')
        self._force = [0.0, 0.0, 0.0]
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
            raise DeviceError(f'openhaptics: {self._model} serial {self._serial} needs '
                              'calibration: put the stylus in the inkwell and activate again '
                              '(a device that needs manual input: run Touch_Setup / '
                              f'Touch_Diagnostic), hdCheckCalibration 0x{state:04x}')

    def deactivate(self) -> None:
        """Zero force (one frame, while the scheduler runs), force output off, the scheduler
        stopped, the device closed. Harmless twice."""
        self._active = False
        self._force = [0.0, 0.0, 0.0]
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
        if not self._active:
            raise DeviceError('openhaptics: write() before activate()')
        u = np.zeros(3)
        w = np.asarray(wrench, dtype=float)
        bad = ~np.isfinite(w)
        if bad.any():
            self.nonfinite_commands += 1
            w = np.where(bad, 0.0, w)
        u[:w.size] = w
        f = self._rot.T @ u
        norm = float(np.linalg.norm(f))
        if norm > self._max_force:
            f *= self._max_force / norm
        self._force = [float(v) for v in f]
        if self._in_frame:
            self._require_hd().set_force(self._force)

    def task_force(self, device_force: np.ndarray) -> np.ndarray:
        """The task wrench (N) of a force on the device (N, device axes)."""
        assert self._task is not None
        return (self._rot @ np.asarray(device_force, dtype=float))[self._task.translation_rows]

    def read(self, dt: float) -> DeviceReading:
        if not self._active:
            raise DeviceError('openhaptics: read() before activate()')
        if not self._in_frame:
            self._reading = None
            assert self._lib is not None
            self._lib.scheduling.hdSyncSheduler(self._sync_cb)
            if self._reading is None:
                raise DeviceError('openhaptics: the servo loop did not run the frame '
                                  '(hdScheduleSynchronous)')
            return self._reading
        return self._frame_reading()

    def _frame_reading(self) -> DeviceReading:
        """The state of the open frame, as a reading (device fault on an error or NaN)."""
        hd = self._require_hd()
        assert self._task is not None
        t = hd.get_transform()
        p = np.array([t[3][0], t[3][1], t[3][2]])
        v = np.array(hd._get_doublev(HD_CURRENT_VELOCITY, ctypes.c_double * 3)[:])
        self.buttons = int(hd.get_buttons())
        self.inkwell = bool(hd._get_integerv(HD_CURRENT_INKWELL_SWITCH, ctypes.c_int).value)
        self._drain_errors()
        rows = self._task.translation_rows
        status = DeviceStatus.OK
        if self._fault:
            status, self._reason, self._fault = DeviceStatus.FAULT, self._fault, ''
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
            status = DeviceStatus.FAULT
            self._reason = f'openhaptics: {self._model}: non-finite position or velocity'
            zero = np.zeros(self._task.dim)
            return DeviceReading(self._last_pose.copy(), zero, zero.copy(), status)
        pose = (self._origin + self._rot @ (1e-3 * p))[rows]
        twist = (self._rot @ (1e-3 * v))[rows]
        self._last_pose = pose
        return DeviceReading(pose, twist, np.zeros(self._task.dim), status)

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
            self._reading = self._frame_reading()
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
