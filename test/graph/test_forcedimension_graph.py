"""``backend: forcedimension`` in the node graph, on the Force Dimension emulator: the
documented command ``FDSDK=<venv>/fdsdk-emulator haptic-topology run fig8_point --params
config/devices/forcedimension_emulator.yaml``, with the device unplugged mid-run
(``FDEMU_UNPLUG_AFTER``): the run ends normally with its bag and summary, which name the
device (``summary.json``, the bag's ``custom_data``); from the fault on every state carries
FAULT and the device gets zero force.

Every process runs in the session's random ROS_DOMAIN_ID; every wait has a deadline.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from fd_emulator import FDSDK

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.vocabulary import DeviceStatus

pytestmark = pytest.mark.graph

REPO = Path(__file__).resolve().parents[2]
PARAMS = REPO / 'config' / 'devices' / 'forcedimension_emulator.yaml'
#: dhdSetForce calls (about 1 per ms) before the emulated device is unplugged.
UNPLUG_AFTER = 800


def test_run_on_the_emulator_unplugged_mid_run(tmp_path: Path) -> None:
    bag = tmp_path / 'fd'
    env = {k: v for k, v in os.environ.items() if not k.startswith('FDEMU_')}
    env.update(FDSDK=str(FDSDK), FDEMU_UNPLUG_AFTER=str(UNPLUG_AFTER))
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                           '--params', str(PARAMS), '--duration', '2', '--out', str(bag)],
                          capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert '\ndevice: backend forcedimension, forcedimension omega.3 serial 11029\n' in out, out
    summary = json.loads((bag / 'summary.json').read_text(encoding='utf-8'))
    assert summary['device_hardware_id'] == 'forcedimension omega.3 serial 11029'
    assert (summary['device_vendor'], summary['device_serial']) == ('Force Dimension', '11029')
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text(encoding='utf-8'))[
        'rosbag2_bagfile_information']['custom_data']
    assert (custom['device'], custom['device_model'], custom['device_serial']) == (
        'forcedimension omega.3 serial 11029', 'omega.3', '11029'), custom
    run = read_graph_bag(bag)
    device = run.diagnostics['device_driver: loop']
    assert device['device_fault'] == ('forcedimension: dhdGetPosition failed: communication '
                                      'error between the host and the device'), device
    trace = run.trace
    status = trace.columns['status'].astype(int)
    fault = (status & int(DeviceStatus.FAULT)) != 0
    assert fault.any() and not fault[0], 'no fault, or faulted from the start'
    first = int(np.argmax(fault))
    assert fault[first:].all(), 'the fault did not last to the end of the run'
    applied = trace.columns['applied']
    assert applied[:first].any(), 'no force before the fault'
    assert not applied[first + 1:].any(), 'force written after the fault'
    assert np.isfinite(trace.columns['device_pose']).all()


def _lockstep_run(bag: Path, cwd: Path) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith('FDEMU_')}
    env['FDSDK'] = str(FDSDK)
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point',
                           '--backend', 'forcedimension_emulator', '--clock', 'lockstep',
                           '--duration', '0.3', '--out', str(bag)],
                          capture_output=True, text=True, env=env, timeout=300, cwd=cwd)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    return out


def test_lockstep_runs_on_the_stepped_emulator_are_the_same(tmp_path: Path) -> None:
    """``backend: forcedimension_emulator`` on ``clock: lockstep``: the emulated device
    advances by each cycle's dt, so two runs record the same trace bit for bit (the device,
    pushed by the emulator's simulated hand, moves)."""
    runs = []
    for name in ('a', 'b'):
        out = _lockstep_run(tmp_path / name, tmp_path)
        assert ('\ndevice: backend forcedimension_emulator, forcedimension_emulator omega.3 '
                'serial 11029\n') in out, out
        runs.append(read_graph_bag(tmp_path / name).trace)
    a, b = runs
    # The trace starts at the first state without WATCHDOG: after the grasp's 50 ms fade-in.
    assert len(a) == len(b) > round(0.25 / 1e-3)
    for col in a.columns:
        np.testing.assert_array_equal(a.columns[col], b.columns[col], err_msg=col)
    assert np.ptp(a.columns['device_pose'][:, 0]) > 1e-4
