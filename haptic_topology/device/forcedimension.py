"""``backend: forcedimension``: Force Dimension devices (omega.x, delta.x, sigma.x, Novint
Falcon) through the vendor's SDK (``libdrd``) and its Python binding ``forcedimension-core``,
unmodified.

The binding is imported when the backend is configured (or ``haptic-topology devices`` and
``run`` ask, :func:`support`): it looks for ``libdrd`` as its documentation says,
``$FDSDK/lib/release/lin-<machine>-gcc/libdrd.so.<version>`` first, and needs SDK 3.16 or
later. A missing package or library is one
:class:`~haptic_topology.errors.VendorLibraryMissing` line naming ``forcedimension-core``,
``libdrd`` and ``FDSDK``.

Lifecycle: ``activate`` opens the device (``dhdOpenSerial`` with the option ``serial``, else
``dhdOpen``: the first device), reads its identity (``dhdGetSystemName``,
``dhdGetSerialNumber``, ``dhdGetSDKVersion``), calibrates it if it is not
(``drdIsInitialized``; ``drdAutoInit`` with ``auto_init: true``, else a
:class:`~haptic_topology.errors.DeviceError` saying so), sets gravity compensation, the
effector mass and the device's own force limit (``dhdSetGravityCompensation``,
``dhdSetEffectorMass``, ``dhdSetMaxForce``) and enables force (``dhdEnableForce``). Each cycle
``write`` sends the force (``dhdSetForce``, N) and ``read`` takes the position
(``dhdGetPosition``, m), the velocity (``dhdGetLinearVelocity``, m/s) and the buttons
(``dhdGetButtonMask``), mapped to the point task by
:class:`~haptic_topology.device.vendor.VendorHand` (axes, origin, units, grasp and clutch
buttons). ``deactivate`` (and ``cleanup``) sends zero, disables force and closes the device.

Faults: a call that fails (returns -1: the device unplugged, a communication error) or a
position or velocity that is not finite puts the backend in fault for the rest of the
activation: zero force and force disabled at once, every reading flagged
``DeviceStatus.FAULT`` (the driver writes zero, its diagnostics are at ERROR with
:meth:`ForceDimensionBackend.fault_reason`: the call and ``dhdErrorGetLastStr``), the pose
held at the last good one; the run goes on to its end and writes its bag and summary.

The device runs on its own clock (``lockstep`` False). Options: those of
:data:`~haptic_topology.device.vendor.VENDOR_OPTIONS` and :data:`OWN_OPTIONS` (see the table in
docs/devices.md).
"""

from __future__ import annotations

import contextlib
import io
import math
from typing import Any

import numpy as np

from haptic_topology.device.backend import BackendConfig, DeviceReading
from haptic_topology.device.vendor import (
    DeviceIdentity,
    VendorBackend,
    VendorHand,
    VendorSupport,
    flag_option,
    optional_number,
)
from haptic_topology.errors import DeviceError
from haptic_topology.vocabulary import DeviceStatus

BACKEND = 'forcedimension'
#: This backend's own options and their defaults: ``serial`` (the device's serial number;
#: None: the first device), ``max_force`` (N, the device's own limit, ``dhdSetMaxForce``;
#: None: the device's default), ``gravity_compensation`` (``dhdSetGravityCompensation``),
#: ``effector_mass`` (kg, ``dhdSetEffectorMass``; None: the device's default), ``auto_init``
#: (calibrate an uncalibrated device with ``drdAutoInit``, which moves it by itself).
OWN_OPTIONS: dict[str, Any] = {
    'serial': None, 'max_force': None, 'gravity_compensation': True, 'effector_mass': None,
    'auto_init': False,
}
#: Nominal workspaces of the devices (the vendor's data sheets), by system name prefix.
WORKSPACES = {
    'omega.3': 'translation 160 x 110 mm (diameter x height)',
    'omega.6': 'translation 160 x 110 mm (diameter x height)',
    'omega.7': 'translation 160 x 110 mm (diameter x height)',
    'delta.3': 'translation 400 x 260 mm (diameter x height)',
    'delta.6': 'translation 400 x 260 mm (diameter x height)',
    'sigma.7': 'translation 190 x 130 mm (diameter x height)',
    'Falcon': 'translation 100 x 100 x 100 mm',
}
_MOTOR_SATURATED = 2
_ERROR_TIMEOUT = 7
_FAULT = int(DeviceStatus.FAULT)
_SATURATED = int(DeviceStatus.SATURATED)

#: The imported binding (module ``forcedimension_core``), once loaded.
_binding: Any = None


def support() -> VendorSupport:
    """This backend's entry in the vendor registry
    (:data:`~haptic_topology.device.vendor.VENDOR_BACKENDS`)."""
    return VendorSupport(BACKEND, 'forcedimension-core', 'libdrd', 'FDSDK', _where,
                         list_devices)


def _missing(detail: str) -> Exception:
    return support().missing(detail)


def binding() -> Any:
    """The ``forcedimension_core`` module, imported once (its library search prints to
    stderr; that text becomes the error's detail instead)."""
    global _binding
    if _binding is not None:
        return _binding
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            import forcedimension_core  # type: ignore[import-untyped]
            import forcedimension_core.dhd.direct  # type: ignore[import-untyped]
    except ModuleNotFoundError as exc:
        if exc.name is not None and exc.name.startswith('forcedimension_core'):
            raise _missing('the package is not installed') from None
        raise _missing(f'{exc}') from None
    except (ImportError, OSError, AttributeError) as exc:
        lines = [ln.strip() for ln in said.getvalue().splitlines() if ln.strip()]
        raise _missing(' '.join(lines) or f'{type(exc).__name__}: {exc}') from None
    _binding = forcedimension_core
    return _binding


def _where() -> str:
    """What :func:`binding` loaded: the library's path and SDK version."""
    fdc = binding()
    lib = getattr(fdc.runtime, '_libdrd', None)
    return f'{getattr(lib, "_name", "libdrd")} (SDK {fdc.dhd.getSDKVersion()})'


def list_devices() -> list[str]:
    """The connected devices (``dhdGetDeviceCount``), each opened briefly for its system
    name and serial number: ``'<name> serial <n>'``."""
    dhd = binding().dhd
    out = []
    for index in range(max(0, dhd.getDeviceCount())):
        ident = dhd.openID(index)
        if ident < 0:
            out.append(f'device {index}: cannot open ({dhd.errorGetLastStr()})')
            continue
        try:
            out.append(f'{dhd.getSystemName(ident)} serial {dhd.getSerialNumber(ident)}')
        finally:
            dhd.close(ident)
    return out


class ForceDimensionBackend(VendorBackend):
    """A Force Dimension device (module doc)."""

    name = BACKEND
    own_options = OWN_OPTIONS

    def __init__(self) -> None:
        super().__init__()
        self._id = -1
        self._fault = ''
        self._last: DeviceReading | None = None
        self._status_bits = 0
        self.saturated_writes = 0
        self.velocity_timeouts = 0
        self._serial: int | None = None
        self._max_force: float | None = None
        self._mass: float | None = None
        self._gravity = True
        self._auto_init = False

    # -- configuration -----------------------------------------------------------------------
    def configure_own(self, own: dict[str, Any]) -> None:
        serial = own['serial']
        if serial is not None and (isinstance(serial, bool) or not isinstance(serial, int)
                                   or not 0 <= serial <= 65535):
            raise DeviceError(f'{self.name}: backend_options.serial: expected the device\'s '
                              f'serial number (0-65535) or null (the first device), got '
                              f'{serial!r}')
        self._serial = serial
        self._max_force = optional_number(own['max_force'], 'max_force', self.name, 1000.0,
                                          "the device's default")
        self._mass = optional_number(own['effector_mass'], 'effector_mass', self.name, 100.0,
                                     "the device's default")
        self._gravity = flag_option(own['gravity_compensation'], 'gravity_compensation',
                                    self.name)
        self._auto_init = flag_option(own['auto_init'], 'auto_init', self.name)
        binding()           # a missing SDK: refused at configure, before anything moves

    # -- lifecycle ---------------------------------------------------------------------------
    def _error(self) -> str:
        return str(binding().dhd.errorGetLastStr())

    def _check(self, rc: int, call: str) -> None:
        if rc < 0:
            raise DeviceError(f'{self.name}: {call} failed: {self._error()}')

    def _open(self) -> int:
        """Open the device (``serial``, else the first): its ID, or a DeviceError."""
        dhd = binding().dhd
        if self._serial is not None:
            ident = dhd.openSerial(self._serial)
            what = f'the device with serial {self._serial}'
        else:
            ident = dhd.open()
            what = 'a device'
        if ident < 0:
            raise DeviceError(f'{self.name}: cannot open {what} ({dhd.getDeviceCount()} '
                              f'found): {self._error()}')
        return int(ident)

    def preflight(self, config: BackendConfig) -> None:
        """Before ``run`` starts any node: the options, the library (one line, exit status 2
        when it is missing) and the device, opened and closed again (force never enabled)."""
        self.configure(config)
        binding().dhd.close(self._open())

    def activate(self) -> None:
        if self._hand is None:
            raise DeviceError(f'{self.name}: activate() before configure()')
        fdc = binding()
        dhd, drd = fdc.dhd, fdc.drd
        ident = self._open()
        self._id = ident
        self._fault = ''
        self._last = None
        name = str(dhd.getSystemName(ident) or 'unknown')
        serial = dhd.getSerialNumber(ident)
        model = next((w for k, w in WORKSPACES.items() if name.startswith(k)), '')
        self.identity = DeviceIdentity('Force Dimension', name,
                                        str(serial) if serial >= 0 else '',
                                        str(dhd.getSDKVersion()), model)
        if not drd.isInitialized(ident):
            if not self._auto_init:
                raise DeviceError(f'{self.name}: the {name} (serial {serial}) is not '
                                  'calibrated: calibrate it (the vendor\'s autoinit tool) or '
                                  'set backend_options.auto_init: true (the device then moves '
                                  'by itself: hands off)')
            self._check(drd.openID(ident), 'drdOpenID')
            self._check(drd.autoInit(ident), 'drdAutoInit')
            self._check(drd.stop(True, ident), 'drdStop')
        self._check(dhd.setGravityCompensation(self._gravity, ident),
                    'dhdSetGravityCompensation')
        if self._mass is not None:
            self._check(dhd.setEffectorMass(self._mass, ident), 'dhdSetEffectorMass')
        if self._max_force is not None:
            self._check(dhd.setMaxForce(self._max_force, ident), 'dhdSetMaxForce')
        self._check(dhd.setForce((0.0, 0.0, 0.0), ident), 'dhdSetForce')
        self._check(dhd.enableForce(True, ident), 'dhdEnableForce')
        self._pos = fdc.containers.Vec3()
        self._vel = fdc.containers.Vec3()
        self._prev: tuple[float, float, float] | None = None
        self._hand.grasping = False         # a new activation grasps anew (no jump)

    def _release(self) -> None:
        """Zero force, force off, close: each tried whatever the others return."""
        if self._id < 0:
            return
        dhd = binding().dhd
        ident, self._id = self._id, -1
        dhd.setForce((0.0, 0.0, 0.0), ident)
        dhd.enableForce(False, ident)
        dhd.close(ident)

    def deactivate(self) -> None:
        self._release()
        if self._hand is not None:
            self._hand.grasping = False

    def cleanup(self) -> None:
        self.deactivate()

    # -- the cycle ---------------------------------------------------------------------------
    def _to_fault(self, reason: str) -> None:
        """Enter the fault (module doc): the reason kept, zero force and force off now."""
        self._fault = f'{self.name}: {reason}'
        dhd = binding().dhd
        dhd.setForce((0.0, 0.0, 0.0), self._id)
        dhd.enableForce(False, self._id)

    def write(self, wrench: np.ndarray) -> None:
        if self._id < 0 or self._hand is None:
            raise DeviceError(f'{self.name}: write() while not active')
        if self._fault:                 # force is off: nothing reaches the device
            self._hand.sent = np.zeros(self._m)
            return
        f = self._hand.force(wrench)
        rc = binding().dhd.setForce(f, self._id)
        if rc < 0:
            self._to_fault(f'dhdSetForce failed: {self._error()}')
            self._hand.sent = np.zeros(self._m)
        elif rc == _MOTOR_SATURATED:
            self.saturated_writes += 1
            self._status_bits = _SATURATED
        else:
            self._status_bits = 0

    def read(self, dt: float) -> DeviceReading:
        hand = self._hand
        if self._id < 0 or hand is None:
            raise DeviceError(f'{self.name}: read() while not active')
        if not self._fault:
            reading = self._sample(hand, dt)
            if reading is not None:
                self._last = reading
                return reading
        m = self._m
        pose = self._last.pose if self._last is not None else hand.pose
        return DeviceReading(pose, np.zeros(m), np.zeros(m), DeviceStatus(_FAULT))

    def _sample(self, hand: VendorHand, dt: float) -> DeviceReading | None:
        fdc = binding()
        dhd, direct = fdc.dhd, fdc.dhd.direct
        ident = self._id
        if direct.getPosition(self._pos, ident) < 0:
            self._to_fault(f'dhdGetPosition failed: {self._error()}')
            return None
        p = (self._pos[0], self._pos[1], self._pos[2])
        if direct.getLinearVelocity(self._vel, ident) < 0:
            if dhd.errorGetLast() != _ERROR_TIMEOUT:
                self._to_fault(f'dhdGetLinearVelocity failed: {self._error()}')
                return None
            # Too few positions in the SDK's velocity window yet: their difference instead.
            self.velocity_timeouts += 1
            q = self._prev
            v = ((0.0, 0.0, 0.0) if q is None or dt <= 0.0
                 else ((p[0] - q[0]) / dt, (p[1] - q[1]) / dt, (p[2] - q[2]) / dt))
        else:
            v = (self._vel[0], self._vel[1], self._vel[2])
        if not all(math.isfinite(x) for x in (*p, *v)):
            self._to_fault(f'the device reported a non-finite position or velocity '
                           f'(p {p}, v {v})')
            return None
        self._prev = p
        buttons = int(dhd.getButtonMask(ident))
        r = hand.reading(p, v, buttons, dt)
        if self._status_bits:
            return r._replace(status=DeviceStatus(int(r.status) | self._status_bits))
        return r

    # -- reporting ---------------------------------------------------------------------------
    def values(self) -> dict[str, str]:
        out = super().values()
        out['device_saturated_writes'] = str(self.saturated_writes)
        out['velocity_timeouts'] = str(self.velocity_timeouts)
        return out

    def fault_reason(self) -> str:
        return self._fault or super().fault_reason()


class ForceDimensionEmulatorBackend(ForceDimensionBackend):
    """``backend: forcedimension_emulator``: :class:`ForceDimensionBackend` on the Force
    Dimension emulator (``emulators/forcedimension``) with the emulator's clock stepped by the
    loop, so that it follows the driver's lock-step clock (``clock: lockstep``) and a run is
    deterministic: each engaged ``read(dt)`` advances the emulated device by ``dt`` first
    (``fdemuStep``); until the loop engages, ``idle`` reads without advancing it (as the
    simulated maglev parks). Refused (:class:`~haptic_topology.errors.DeviceError`) when the
    library ``FDSDK`` leads to is not the emulator. Options: those of ``forcedimension``."""

    name = 'forcedimension_emulator'
    lockstep = True

    def __init__(self) -> None:
        super().__init__()
        self._step: Any = None

    def activate(self) -> None:
        if self._hand is None:
            raise DeviceError(f'{self.name}: activate() before configure()')
        import ctypes

        lib = binding().runtime._libdrd
        try:
            step, clock = lib.fdemuStep, lib.fdemuSetClock
        except AttributeError:
            raise DeviceError(f'{self.name}: {getattr(lib, "_name", "libdrd")} is not the '
                              'Force Dimension emulator (no fdemuStep): use backend '
                              'forcedimension for a device') from None
        step.argtypes, step.restype = [ctypes.c_double], ctypes.c_int
        clock.argtypes, clock.restype = [ctypes.c_int], None
        clock(1)
        self._step = step
        super().activate()

    def read(self, dt: float) -> DeviceReading:
        if self._id >= 0 and not self._fault and self._step is not None:
            self._step(dt)
        return super().read(dt)

    def idle(self, dt: float) -> DeviceReading:
        self.write(np.zeros(self._m))
        return super().read(dt)
