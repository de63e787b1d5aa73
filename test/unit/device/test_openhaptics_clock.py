"""The loop process on the device's servo clock (``DeviceBackend.drives_loop``): with ``backend:
openhaptics`` against the OpenHaptics emulator, every cycle of the loop process runs inside the
emulated scheduler's callback (the backend counts its servo ticks; the loop counts its
cycles: they are equal, and without the clocked path the backend would see no tick), and an
unplugged device mid-run is a device fault: FAULT states, zero output from the next cycle
on, the reason once in the node's notices, the device released at the end. No ROS."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from loop_specs import spec_for

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.loop_process import LoopProcess
from haptic_topology.device.openhaptics_hd import EMULATOR
from haptic_topology.vocabulary import DeviceStatus

pytestmark = pytest.mark.skipif(not EMULATOR.is_file(),
                                reason=f'{EMULATOR} not built: run scripts/setup.sh')


@pytest.fixture(autouse=True)
def emulator(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop process loads the emulator (it inherits this variable)."""
    monkeypatch.setenv('HAPTIC_TOPOLOGY_LIBHD', str(EMULATOR))

#: Cycles each run waits for before it stops the child.
CYCLES = 600


def _spec() -> tuple[dict[str, Any], int, int]:
    spec, dim, dof = spec_for('fig8_point', lockstep=False, duration=0.0)
    cfg: BackendConfig = spec['backend_config']
    spec['backend'] = 'openhaptics'
    spec['backend_config'] = replace(cfg, options={'engage_button': None,
                                                   'clutch_button': None})
    return spec, dim, dof


def _run(proc: LoopProcess, cycles: int = CYCLES) -> list[Any]:
    """Start, collect the cycles until the child has reported :data:`CYCLES`, stop it (it
    zeroes and releases the device); its final status."""
    proc.start()
    records = []
    try:
        proc.wait_started()
        deadline = time.monotonic() + 120.0
        while int(proc.status.get('n_periods', 0)) < cycles:
            assert time.monotonic() < deadline, f'fewer than {cycles} cycles in 120 s'
            assert proc.running, proc.status
            proc.wait(0.02)
            records.extend(proc.drain())
    finally:
        proc.stop()
    records.extend(proc.drain())
    assert proc.status.get('final') is True, proc.status
    assert proc.status['error'] == '', proc.status['error']
    return records


def test_every_cycle_runs_inside_the_servo_callback() -> None:
    spec, dim, dof = _spec()
    proc = LoopProcess(spec, dim, dof)
    try:
        records = _run(proc)
    finally:
        proc.close()
    values = proc.status['report'][2]
    ticks = int(values['openhaptics_servo_ticks'])
    cycles = int(proc.status['device']['cycles'])
    assert ticks == cycles > 0, (ticks, cycles)
    assert len(records) == cycles
    assert proc.status['hardware_id'] == 'openhaptics Touch serial EMU-00001'


def test_an_unplugged_device_is_a_fault_with_zero_output_and_its_reason(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Unplugged at servo tick 300 (the child inherits the variable): the states carry FAULT
    from then on with zero output, and the reason is one notice for the node's log."""
    monkeypatch.setenv('HD_EMU_UNPLUG_AT', '300')
    spec, dim, dof = _spec()
    proc = LoopProcess(spec, dim, dof)
    try:
        records = _run(proc)
    finally:
        proc.close()
    fault = [bool(int(r.step.tick.status) & DeviceStatus.FAULT) for r in records]
    assert any(fault)
    first = fault.index(True)
    assert all(fault[first:]), 'the fault cleared while the device was unplugged'
    applied = np.array([r.step.tick.applied for r in records[first:]])
    assert applied.size and not applied.any(), 'output after the fault'
    reasons = [n for n in proc.notices if n.startswith('device fault:')]
    assert reasons == ['device fault: openhaptics: Touch: HD_COMM_ERROR (0x302): output zero '
                       'while it lasts'], list(proc.notices)


def test_a_servo_loop_that_stops_calling_back_ends_the_child_with_the_reason(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The scheduler stops calling back at servo tick 300 (a hung servo loop): after 1 s
    without a tick the child ends its loop with that reason, releases the device without
    waiting for a tick, and exits; the node sees a fault naming it."""
    monkeypatch.setenv('HD_EMU_STALL_AT', '300')
    spec, dim, dof = _spec()
    proc = LoopProcess(spec, dim, dof)
    try:
        proc.start()
        proc.wait_started()
        deadline = time.monotonic() + 120.0
        while proc.error is None:
            assert time.monotonic() < deadline, 'the child did not end'
            proc.wait(0.05)
            proc.drain()
            proc.check()
        assert 'openhaptics: the servo loop stopped calling back (1 s without a tick)' in \
            str(proc.error), str(proc.error)
        assert proc.status['final'] is True
    finally:
        proc.close()
