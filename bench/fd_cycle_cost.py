"""What the Force Dimension backend's vendor calls cost per device cycle through ctypes and
``forcedimension-core`` (read: ``dhdGetPosition``, ``dhdGetLinearVelocity``,
``dhdGetButtonMask``; write: ``dhdSetForce``), on the emulator (``FDSDK=.venv/fdsdk-emulator``,
``FDEMU_CLOCK=step``: its functions do next to nothing, so what is measured is the binding's and
ctypes' part). Prints the median and 99th percentile (us) of: each call alone, the four calls
of a cycle, and the backend's ``write`` + ``read`` (the calls plus the mapping of
``VendorHand``).

    FDSDK=.venv/fdsdk-emulator FDEMU_CLOCK=step .venv/bin/python bench/fd_cycle_cost.py [N]
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np

from haptic_topology.device.backend import BackendConfig, create_backend
from haptic_topology.device.forcedimension import binding
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario


def timed(call: Callable[[], object], n: int) -> tuple[float, float]:
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        call()
        out[i] = clock() - t0
    return float(np.median(out)) / 1e3, float(np.percentile(out, 99)) / 1e3


def main() -> int:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 20000
    sc = load_scenario('fig8_point')
    be = create_backend('forcedimension')
    be.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, {}, sc.source))
    be.activate()
    fdc = binding()
    dhd, direct = fdc.dhd, fdc.dhd.direct
    ident = 0
    pos, vel = fdc.containers.Vec3(), fdc.containers.Vec3()
    f = (0.1, 0.2, 0.0)
    u = np.array([0.1, 0.2])

    def four() -> None:
        direct.getPosition(pos, ident)
        direct.getLinearVelocity(vel, ident)
        dhd.getButtonMask(ident)
        dhd.setForce(f, ident)

    def backend_cycle() -> None:
        be.write(u)
        be.read(1e-3)

    rows = [('dhdGetPosition', lambda: direct.getPosition(pos, ident)),
            ('dhdGetLinearVelocity', lambda: direct.getLinearVelocity(vel, ident)),
            ('dhdGetButtonMask', lambda: dhd.getButtonMask(ident)),
            ('dhdSetForce', lambda: dhd.setForce(f, ident)),
            ('the four calls of a cycle', four),
            ('backend write + read', backend_cycle)]
    for _, call in rows:            # warm up
        timed(call, 1000)
    print(f'{"per cycle":30s} {"p50 [us]":>9s} {"p99 [us]":>9s}   (n = {n})')
    for name, call in rows:
        p50, p99 = timed(call, n)
        print(f'{name:30s} {p50:9.2f} {p99:9.2f}')
    be.deactivate()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
