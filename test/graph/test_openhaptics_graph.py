"""``backend: openhaptics`` in the node graph: ``HAPTIC_TOPOLOGY_LIBHD=<the emulator>
haptic-topology run fig8_point --params config/devices/openhaptics_emulator.yaml`` (the hosted
layout's loop process on the emulated Touch's servo clock, through the unmodified
pyOpenHaptics), with the device unplugged mid-run (``HD_EMU_UNPLUG_AT``): the run ends
normally with its bag and summary, the states carry FAULT from the unplug on with zero
output, and the driver's log says why in one line.

Every process runs in the session's random ROS_DOMAIN_ID (``conftest.ros_domain_env``); every
wait has a deadline.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_topology.device.openhaptics_hd import EMULATOR
from haptic_topology.sim.trace import Trace
from haptic_topology.vocabulary import DeviceStatus

pytestmark = [pytest.mark.graph,
              pytest.mark.skipif(not EMULATOR.is_file(),
                                 reason=f'{EMULATOR} not built: run scripts/setup.sh')]

PARAMS = Path(__file__).resolve().parents[2] / 'config' / 'devices' / 'openhaptics_emulator.yaml'
REASON = 'device fault: openhaptics: Touch: HD_COMM_ERROR (0x302): output zero while it lasts'


@pytest.mark.parametrize('layout', ['hosted', 'thread'])
def test_a_run_on_the_emulated_touch_unplugged_mid_run(tmp_path: Path, layout: str) -> None:
    """``hosted``: the loop process on the servo clock (``run_clocked``); ``thread``
    (``loop_process: false``): the driver's loop thread paces itself and each ``read``
    exchanges a frame with the servo thread (``hdScheduleSynchronous``)."""
    bag = tmp_path / 'fig8_point'
    env = dict(os.environ, HD_EMU_UNPLUG_AT='1500', HAPTIC_TOPOLOGY_LIBHD=str(EMULATOR))
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                           '--params', str(PARAMS), '--duration', '2', '--out', str(bag),
                           '--layout', layout],
                          capture_output=True, timeout=300, env=env, check=False)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 0, out
    assert '\ndevice: backend openhaptics, openhaptics Touch serial EMU-00001\n' in out, out
    summary = json.loads((bag / 'summary.json').read_text())
    assert summary['layout'] == layout
    trace = Trace.from_csv(bag / 'trace.parquet')
    fault = (trace.columns['status'].astype(int) & int(DeviceStatus.FAULT)) != 0
    assert not fault[0] and fault[-1], 'expected states before the unplug, FAULT at the end'
    first = int(np.argmax(fault))
    assert fault[first:].all(), 'the fault cleared while the device was unplugged'
    applied = np.asarray(trace.columns['applied'])
    assert np.abs(applied[:first]).max() > 0.0, 'no force before the unplug'
    assert not applied[first + 1:].any(), 'force after the unplug'
    log = (bag / 'logs' / 'device_driver.log').read_text()
    assert log.count(REASON) == 1, log


def test_the_trace_records_zero_while_the_engage_button_is_released(tmp_path: Path) -> None:
    """``engage_button: 0`` held from servo tick 300, released at 1300, held again at 1700
    (the emulator's ``HD_EMU_BUTTON_TICKS``): while released the controller still commands
    forces (the trace's ``command``) but the Touch gets none, and the trace's ``applied`` (the
    bag's device states) is exactly zero, WATCHDOG set; held again, the force comes back (its
    fade cycle by cycle: test_openhaptics.py, against the emulated motors)."""
    params = tmp_path / 'touch.yaml'
    params.write_text(PARAMS.read_text().replace(
        "'{engage_button: null, clutch_button: null}'",
        "'{engage_button: 0, clutch_button: null}'"))
    assert params.read_text() != PARAMS.read_text()
    bag = tmp_path / 'fig8_point'
    env = dict(os.environ, HD_EMU_BUTTONS='1', HD_EMU_BUTTON_TICKS='300,1300,1700',
               HAPTIC_TOPOLOGY_LIBHD=str(EMULATOR))
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                           '--params', str(params), '--duration', '3', '--out', str(bag)],
                          capture_output=True, timeout=300, env=env, check=False)
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 0, out
    trace = Trace.from_csv(bag / 'trace.parquet')
    applied = np.asarray(trace.columns['applied'])
    command = np.asarray(trace.columns['command'])
    watchdog = (trace.columns['status'].astype(int) & int(DeviceStatus.WATCHDOG)) != 0
    # Released: the hand holds the linkage still (twist exactly zero) and the state says the
    # output is not the command (WATCHDOG); a late command (the driver's own watchdog) keeps
    # the twist. The first state of a release was written while still grasping.
    released = watchdog & np.all(np.asarray(trace.columns['device_twist']) == 0.0, axis=1)
    after_first = released & np.concatenate([[False], released[:-1]])
    assert after_first.sum() > 0, 'no released states'
    assert np.abs(command[after_first]).max() > 0.0, 'the controller commanded nothing'
    assert not applied[after_first].any(), 'applied shows force the Touch never got'
    last = int(np.nonzero(released)[0][-1])
    assert np.abs(applied[last + 1:]).max() > 0.0, 'no force after the new grasp'
