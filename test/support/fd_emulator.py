"""The Force Dimension emulator (``emulators/forcedimension``, built by ``scripts/setup.sh``
into ``<venv>/fdsdk-emulator``) for the tests: where it is, the environment that makes
``forcedimension-core`` load it, and what it reports of the device (the force it applies).

Importing this module sets ``FDSDK`` to the emulator for this process (so that
``forcedimension-core``, imported later, loads it). The emulator's settings (``FDEMU_*``,
fd_emulator.c's header) are read again by :func:`reset`.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.device.backend import DeviceBackend

#: The emulator's SDK-like tree (FDSDK).
FDSDK = Path(sys.prefix) / 'fdsdk-emulator'
LIBRARY = FDSDK / 'lib' / 'release' / f'lin-{platform.machine()}-gcc' / 'libdrd.so.3.16.0'
assert LIBRARY.is_file(), (f'{LIBRARY}: the Force Dimension emulator is not built; run '
                           'scripts/setup.sh (it builds emulators/forcedimension with gcc)')
os.environ['FDSDK'] = str(FDSDK)


def library() -> Any:
    """The library ``forcedimension-core`` loaded (the emulator), with its emulator-only
    functions typed."""
    from haptic_topology.device.forcedimension import binding

    lib = binding().runtime._libdrd
    assert Path(lib._name).resolve() == LIBRARY.resolve(), lib._name
    lib.fdemuAppliedForce.argtypes = [ctypes.c_int, ctypes.POINTER(ctypes.c_double)]
    lib.fdemuAppliedForce.restype = None
    lib.fdemuSetButtons.argtypes = [ctypes.c_uint]
    lib.fdemuSetButtons.restype = None
    lib.fdemuForceEnabled.argtypes = [ctypes.c_int]
    lib.fdemuSetForceCalls.argtypes = [ctypes.c_int]
    lib.fdemuSetForceCalls.restype = ctypes.c_long
    lib.fdemuIsOpen.argtypes = [ctypes.c_int]
    lib.fdemuStep.argtypes = [ctypes.c_double]
    lib.fdemuGravity.argtypes = [ctypes.c_int]
    for name in ('fdemuEffectorMass', 'fdemuMaxForce'):
        getattr(lib, name).argtypes = [ctypes.c_int]
        getattr(lib, name).restype = ctypes.c_double
    return lib


@contextmanager
def emulator(**settings: str | int) -> Iterator[Any]:
    """The emulator reset with the settings ``FDEMU_<KEY>=value`` (and only those), yielded
    as its library; the environment and the emulator are restored after."""
    keys = [k for k in os.environ if k.startswith('FDEMU_')]
    saved = {k: os.environ.pop(k) for k in keys}
    os.environ.update({f'FDEMU_{k.upper()}': str(v) for k, v in settings.items()})
    lib = library()
    lib.fdemuReset()
    try:
        yield lib
    finally:
        for k in [k for k in os.environ if k.startswith('FDEMU_')]:
            del os.environ[k]
        os.environ.update(saved)
        lib.fdemuReset()


def applied(lib: Any, index: int = 0) -> np.ndarray:
    """The force (N, device frame) the emulated device applies now."""
    out = (ctypes.c_double * 3)()
    lib.fdemuAppliedForce(index, out)
    return np.array(out[:])


class EmulatorSide:
    """What reached the emulated device (a ``DeviceSide`` of ``backend_conformance``): the
    force it applies after each cycle, as a task wrench of ``m`` entries (the backend's
    default mapping: the device frame is the task's, newtons)."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.t: list[int] = []
        self.w: list[np.ndarray] = []
        self.lib = library()

    def after_cycle(self, backend: DeviceBackend) -> None:
        self.t.append(time.monotonic_ns())
        self.w.append(applied(self.lib)[:self.m])

    def got(self, expected: np.ndarray, after_ns: int) -> bool:
        from backend_conformance import same

        return bool(self.t) and self.t[-1] >= after_ns and same(self.w[-1], expected)

    def poll(self, seconds: float) -> None:
        pass

    def log(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.t, dtype=np.int64), np.array(self.w)
