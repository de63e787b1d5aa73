"""The bringup's start of the device: its lifecycle transitions, the reason when one is
refused, and the one line naming the device once it runs.

``haptic-topology run`` configures and activates ``device_driver`` through its lifecycle
services (:func:`start_driver`). A refused transition stops the run at once: the driver
publishes its reason at ERROR on ``/diagnostics`` when it refuses (the backend's own message:
``network: no valid STATE from 127.0.0.1:47001 within 2000 ms ...``), and the run reports
``device_driver: activate failed: <reason>`` with where the driver's log is
; nothing is read from log lines. Once the driver is active, the run
prints ``device: backend <name>, <hardware_id>`` (:func:`device_line`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from haptic_topology.bringup.watch import DEVICE_STATUS, GraphWatcher
from haptic_topology.errors import (
    BringupError,
    DeviceError,
    TransitionRefused,
    VendorLibraryMissing,
    WaitTimeout,
)

if TYPE_CHECKING:
    from haptic_topology.sim.scenario import Scenario

#: How long the bringup waits for a node's diagnostics after a refused transition, and for
#: the device's identity after the activation (s).
FAULT_WAIT = 5.0
#: The node the bringup starts through its lifecycle.
DRIVER = 'device_driver'


def preflight_device(sc: Scenario, backend: str, options: dict[str, Any], clock: str) -> None:
    """Before any node starts: whether the device of ``backend`` (with its parsed
    ``options``) can run scenario ``sc`` on ``clock`` and can be reached
    (:meth:`~haptic_topology.device.backend.DeviceBackend.preflight`, on an instance of this
    process's own, released again), so that ``run`` fails at once with the backend's own
    line (:class:`~haptic_topology.errors.BringupError`) rather than after the graph's
    start."""
    from haptic_topology.device.backend import BackendConfig, DeviceBackend, create_backend
    from haptic_topology.sim.lockstep import initial_device_pose
    try:
        device = create_backend(backend, lockstep=clock == 'lockstep')
        if type(device).preflight is DeviceBackend.preflight:
            return
        device.preflight(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user),
                                       dict(options), sc.source))
    except VendorLibraryMissing:
        raise                   # an installation error: exit status 2, as require_library's
    except DeviceError as exc:
        raise BringupError(f'device: {exc}') from None


def start_driver(watch: GraphWatcher, timeout: float, logs: Path) -> None:
    """Configure, then activate ``device_driver`` (each answered within ``timeout`` s);
    raise :class:`~haptic_topology.errors.BringupError` naming the transition, the driver's
    reason (its diagnostics at ERROR, waited for up to :data:`FAULT_WAIT` s) and its log in
    the directory ``logs`` when it refuses one."""
    for transition in ('configure', 'activate'):
        try:
            watch.change_state(DRIVER, transition, timeout)
        except TransitionRefused:
            reason = (watch.error_message(DEVICE_STATUS, FAULT_WAIT)
                      or 'no reason in its /diagnostics')
            raise BringupError(f'{DRIVER}: {transition} failed: {reason}; details: '
                               f'{logs / DRIVER}.log') from None


def device_line(watch: GraphWatcher, timeout: float) -> str:
    """``device: backend <name>, <hardware_id>``: what the driver reports once active (its
    first report with the loop running, waited for up to ``timeout`` s; else the newest)."""

    def running() -> bool:
        return watch.status.get(DEVICE_STATUS, {}).get('loop_running') == 'true'

    try:
        watch.wait(running, timeout, 'the device driver reporting its loop running')
    except WaitTimeout:
        pass                # a run that has already ended: its newest report
    backend = watch.status.get(DEVICE_STATUS, {}).get('backend', '?')
    hardware = watch.report.get(DEVICE_STATUS, (0, '', ''))[2]
    return f'device: backend {backend}, {hardware or "(no hardware_id reported)"}'
