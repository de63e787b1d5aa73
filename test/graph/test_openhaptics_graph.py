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
