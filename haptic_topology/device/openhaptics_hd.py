"""OpenHaptics' HD library for ``backend: openhaptics``
(:mod:`haptic_topology.device.openhaptics`): where it is found, its loading under the
unmodified pyOpenHaptics package, the HDAPI constants the backend uses (hdDefines.h: the
package has some of them wrong, e.g. ``HD_INVALID_OPERATION``), and the one-line refusal of a
computer without it.

pyOpenHaptics loads ``CDLL("libHD.so")`` by its bare name when it is imported; :func:`load_hd`
loads the library first, by path, with ``RTLD_GLOBAL``, so that the package's own load finds
it (a library whose soname is ``libHD.so``, as OpenHaptics' and the emulator's are).

**Opening a device** (:func:`open_device`): OpenHaptics names devices by their configuration
(``hdInitDevice(name)``, the names set up with Touch_Setup; ``Default Device`` unless renamed)
and tells a unit by ``hdGetString(HD_DEVICE_SERIAL_NUMBER)``. Given a serial number, every
name given is opened in turn, its serial read, the matching one kept (made current) and the
others closed; none matching is one line naming the serials found."""

from __future__ import annotations

import ctypes
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from haptic_topology.errors import DeviceError, VendorLibraryMissing

#: The backend, the Python package and its pin, the library, and the variable that points at
#: the library.
BACKEND = 'openhaptics'
PACKAGE = 'pyOpenHaptics==1.0.1'
LIBRARY = 'libHD.so'
LIBRARY_ENV = 'HAPTIC_TOPOLOGY_LIBHD'
#: Where ``scripts/setup.sh`` builds the emulator (``emulators/openhaptics/hd.c``).
EMULATOR = Path(sys.prefix) / 'lib' / 'haptic_topology' / LIBRARY
#: The servo loop's rate (Hz): OpenHaptics' scheduler default.
SERVO_HZ = 1000
#: A servo loop that has not called back for this long (s) has stopped.
STALL = 1.0

# OpenHaptics constants (hdDefines.h; pyOpenHaptics 1.0.1 has some of them wrong).
HD_CALLBACK_DONE, HD_CALLBACK_CONTINUE = 0, 1
HD_SUCCESS = 0
HD_FORCE_OUTPUT = 0x4000
HD_CURRENT_INKWELL_SWITCH = 0x2002
HD_CURRENT_VELOCITY = 0x2051
HD_VERSION = 0x2500
HD_DEVICE_VENDOR = 0x2503
HD_DEVICE_SERIAL_NUMBER = 0x2504
HD_CALIBRATION_STYLE = 0x2555
HD_NOMINAL_MAX_FORCE = 0x2603
HD_CALIBRATION_OK = 0x5000
HD_CALIBRATION_NEEDS_UPDATE = 0x5001
HD_INVALID_HANDLE = 0xFFFFFFFF
#: hdDefines.h's error codes by value, for the operator's messages.
ERROR_NAMES = dict(zip(
    (0x100, 0x101, 0x102, 0x103, 0x104, 0x200, 0x201, 0x202, 0x203, 0x204, 0x300, 0x301, 0x302,
     0x303, 0x304, 0x400, 0x401, 0x402, 0x500, 0x501, 0x600),
    ('HD_INVALID_ENUM HD_INVALID_VALUE HD_INVALID_OPERATION HD_INVALID_INPUT_TYPE HD_BAD_HANDLE '
     'HD_WARM_MOTORS HD_EXCEEDED_MAX_FORCE HD_EXCEEDED_MAX_FORCE_IMPULSE '
     'HD_EXCEEDED_MAX_VELOCITY HD_FORCE_ERROR HD_DEVICE_FAULT HD_DEVICE_ALREADY_INITIATED '
     'HD_COMM_ERROR HD_COMM_CONFIG_ERROR HD_TIMER_ERROR HD_ILLEGAL_BEGIN HD_ILLEGAL_END '
     'HD_FRAME_ERROR HD_INVALID_PRIORITY HD_SCHEDULER_FULL HD_INVALID_LICENSE').split(),
    strict=True))


def error_text(code: int) -> str:
    """``HD_COMM_ERROR (0x302)`` for an HDAPI error code."""
    return f'{ERROR_NAMES.get(code, "HD error")} (0x{code:03x})'


def library_path() -> str:
    """The library to load: ``$HAPTIC_TOPOLOGY_LIBHD`` (a path; the emulator:
    :data:`EMULATOR`), else ``libHD.so`` on the loader's path."""
    return os.environ.get(LIBRARY_ENV, '') or LIBRARY


def missing(detail: str) -> VendorLibraryMissing:
    """The one-line refusal of a computer without the library or the package (exit status
    2)."""
    return VendorLibraryMissing(BACKEND, PACKAGE, LIBRARY, LIBRARY_ENV, detail)


@dataclass(frozen=True)
class HdLibrary:
    """pyOpenHaptics over the loaded library ``path``: ``hd`` (``pyOpenHaptics.hd``: the
    HDAPI calls and ``_lib_hd``, the library handle) and ``scheduling``
    (``pyOpenHaptics.hd_callback``: ``hdAsyncSheduler``, ``hdSyncSheduler``)."""

    path: str
    hd: Any
    scheduling: Any


_loaded: list[HdLibrary] = []


def load_hd() -> HdLibrary:
    """Load the library (:func:`library_path`, by path, ``RTLD_GLOBAL``) and import
    pyOpenHaptics over it; :class:`~haptic_topology.errors.VendorLibraryMissing` when either is
    missing. A process holds one libHD: another path later is refused."""
    path = library_path()
    if path != LIBRARY and not Path(path).is_file():
        raise missing(f'{LIBRARY_ENV}={path}: no such file')
    if _loaded:
        if _loaded[0].path != path:
            raise DeviceError(f'{BACKEND}: this process has loaded {_loaded[0].path}; '
                              f'cannot load {path} too')
        return _loaded[0]
    try:
        ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
    except OSError as exc:
        raise missing(str(exc)) from None
    try:
        import pyOpenHaptics.hd as hd
        import pyOpenHaptics.hd_callback as scheduling
    except ImportError as exc:
        raise missing(f'package pyOpenHaptics: {exc}') from None
    _loaded.append(HdLibrary(path, hd, scheduling))
    return _loaded[0]


def hd_string(hd: Any, what: int) -> str:
    """``hdGetString(what)`` of the current device (``pyOpenHaptics.hd`` ``hd``) as text."""
    lib = hd._lib_hd
    lib.hdGetString.argtypes = [ctypes.c_uint]
    lib.hdGetString.restype = ctypes.c_char_p
    return (lib.hdGetString(what) or b'').decode(errors='replace')


def _init(hd: Any, name: str) -> int | str:
    """``hdInitDevice(name)``: the handle, or the HD error's text (the error queue emptied:
    pyOpenHaptics' own ``init_device`` compares with the wrong constant)."""
    lib = hd._lib_hd
    lib.hdInitDevice.argtypes = [ctypes.c_char_p]
    lib.hdInitDevice.restype = ctypes.c_uint
    handle = int(lib.hdInitDevice(name.encode()))
    if handle != HD_INVALID_HANDLE:
        return handle
    code = int(hd._get_error().errorCode)
    while int(hd._get_error().errorCode) != HD_SUCCESS:
        pass
    return error_text(code)


def open_device(hd: Any, names: tuple[str, ...], serial: str | None) -> int:
    """Open a device (module doc) and make it current: the handle of ``names[0]`` when
    ``serial`` is None, else of the one among ``names`` whose serial number is ``serial``.
    :class:`~haptic_topology.errors.DeviceError` (one line) when it does not open or none
    matches (naming what each name gave)."""
    if serial is None:
        got = _init(hd, names[0])
        if isinstance(got, int):
            return got
        raise DeviceError(f'{BACKEND}: hdInitDevice failed: {got}: is the Touch connected and '
                          'its driver (Touch_Setup) configured?')
    kept: int | None = None
    found = []
    for name in names:
        got = _init(hd, name)
        if isinstance(got, str):
            found.append(f'{name!r}: {got}')
            continue
        its = hd_string(hd, HD_DEVICE_SERIAL_NUMBER)
        if kept is None and its == serial:
            kept = got
        else:
            hd.close_device(got)
            found.append(f'{name!r} serial {its}')
    if kept is None:
        raise DeviceError(f'{BACKEND}: no device with serial {serial} among '
                          f'backend_options.device: found {"; ".join(found)}')
    lib = hd._lib_hd
    lib.hdMakeCurrentDevice.argtypes = [ctypes.c_uint]
    lib.hdMakeCurrentDevice(kept)
    return kept
