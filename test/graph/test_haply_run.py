"""``haptic-topology run fig8_point`` with ``backend: haply`` against the Haply Inverse Service
emulator in a process of its own, as a user runs it (a params file with the backend and its
port, the command line): a run to the end; the service gone mid-run (killed: FAULT states,
zero force from then on, bag and summary written, the reason on ``/diagnostics``); the
service killed and started again mid-run (FAULT until the user grasps again, zero meanwhile);
the service not there at all (the run stops before any node starts, with one line naming the
address).
No time bound is asserted; waits are on events with generous deadlines.
"""

from __future__ import annotations

import json
import os
import select
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from haply_harness import Emulator, read_log

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.paths import config_dir

pytestmark = [pytest.mark.graph, pytest.mark.timeout(600)]

FAULT = int(vocab.DeviceStatus.FAULT)


def _params(tmp_path: Path, options: str) -> Path:
    """A copy of the default params file with ``backend: haply`` and ``backend_options``."""
    doc = yaml.safe_load((config_dir() / 'haptic_topology.yaml').read_text(encoding='utf-8'))
    driver = doc['device_driver']['ros__parameters']
    driver['backend'] = 'haply'
    driver['backend_options'] = options
    path = tmp_path / 'my_params.yaml'
    path.write_text(yaml.safe_dump(doc), encoding='utf-8')
    return path


def _command(params: Path, bag: Path, duration: float) -> list[str]:
    return [sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8_point', '--params',
            str(params), '--duration', str(duration), '--no-plot', '--out', str(bag)]


def _bag(bag: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The bag's device states (seq order): their status and applied wrench; every
    ``/diagnostics`` message text."""
    decode = decoder()
    states, texts = [], []
    b = open_bag(next(bag.glob('*.mcap')))
    for m in iter_messages(b):
        if m.topic.endswith(vocab.TOPIC_STATE):
            states.append(decode(m))
        elif m.topic == vocab.TOPIC_DIAGNOSTICS:
            texts.extend(str(st.message) for st in decode(m).status)
    states.sort(key=lambda s: int(s.seq))       # type: ignore[attr-defined]
    status = np.array([int(s.status) for s in states])                 # type: ignore
    applied = np.array([list(s.applied_wrench) for s in states])        # type: ignore
    return status, applied, texts


def _interrupt(run: subprocess.Popen[bytes], monitor: socket.socket,
               then: Callable[[], None]) -> str:
    """Once the emulator's ``--monitor`` stream shows a force other than zero (the loop is
    engaged and the device pushes; at most 300 s), ``then()``; the run's output once it has
    ended. The run is killed if anything fails; the monitor is closed."""
    try:
        deadline = time.monotonic() + 300.0
        pushing = False
        while not pushing:
            assert time.monotonic() < deadline and run.poll() is None, 'never engaged'
            if select.select([monitor], [], [], 0.5)[0]:
                _, _, *f = monitor.recv(4096).decode().split(',')
                pushing = any(float(v) != 0.0 for v in f)
        then()
        return run.communicate(timeout=400)[0].decode(errors='replace')
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
        monitor.close()


def test_fig8_point_on_the_emulated_inverse3(tmp_path: Path) -> None:
    emu = Emulator(tmp_path / 'emu')
    try:
        bag = tmp_path / 'bag'
        proc = subprocess.run(_command(_params(tmp_path, f'{{port: {emu.port}}}'), bag, 2.0),
                              capture_output=True, timeout=400, env=dict(os.environ))
        out = (proc.stdout + proc.stderr).decode(errors='replace')
        assert proc.returncode == 0, out
        assert ('device: backend haply, haply Inverse3 (version 7.4, right-handed, port '
                f'emulated) serial 0E31 via ws://127.0.0.1:{emu.port}/') in out, out
        summary = json.loads((bag / 'summary.json').read_text())
        assert summary['scenario'] == 'fig8_point' and summary['samples'] > 0
        assert (summary.get('device_vendor'), summary.get('device_serial')) == (
            'Haply', '0E31'), summary
    finally:
        emu.stop()
    _, ids, f = read_log(emu.log)
    assert set(ids) == {'0E31'} and np.abs(f).max() > 0.0, 'the device got no force'
    assert not f[-1].any(), 'the device was not left at zero'
    assert '"bad_messages": 0' in emu.output, emu.output


def test_a_service_on_another_port_from_the_example_params_and_the_command_line(
        tmp_path: Path) -> None:
    """``config/devices/haply_other_port.yaml`` (a service on another port) with its
    ``backend_options`` replaced on the command line by an unquoted mapping: ``run`` passes it
    to ``device_driver`` as the string parameter ROS takes; the device chosen among two."""
    emu = Emulator(tmp_path / 'emu', ('--device', '04A1', '--device', '04B2'))
    try:
        bag = tmp_path / 'bag'
        params = Path(__file__).resolve().parents[2] / 'config' / 'devices' / \
            'haply_other_port.yaml'
        cmd = _command(params, bag, 1.0) + [
            '-p', f'device_driver:backend_options:={{port: {emu.port}, device_id: "04B2"}}']
        proc = subprocess.run(cmd, capture_output=True, timeout=400, env=dict(os.environ))
        out = (proc.stdout + proc.stderr).decode(errors='replace')
        assert proc.returncode == 0, out
        assert f'serial 04B2 via ws://127.0.0.1:{emu.port}/' in out, out
    finally:
        emu.stop()
    _, ids, f = read_log(emu.log)
    pushed = {i for i, row in zip(ids, f, strict=True) if row.any()}
    assert pushed == {'04B2'}, pushed


def test_the_service_gone_mid_run(tmp_path: Path) -> None:
    monitor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    monitor.bind(('127.0.0.1', 0))
    emu = Emulator(tmp_path / 'emu', monitor=('127.0.0.1', monitor.getsockname()[1]))
    bag = tmp_path / 'bag'
    run = subprocess.Popen(_command(_params(tmp_path, f'{{port: {emu.port}}}'), bag, 6.0),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           env=dict(os.environ))
    out = _interrupt(run, monitor, emu.kill)
    assert run.returncode == 0, out
    assert (bag / 'summary.json').is_file(), out
    status, applied, texts = _bag(bag)
    # the states from the kill to the end: FAULT (no service comes back to reconnect to; a stall of
    # the emulator on a loaded machine may have faulted some earlier states too)
    ok = np.flatnonzero(~status & FAULT)
    first = int(ok[-1]) + 1 if ok.size else 0
    assert first < len(status), 'the run did not end in FAULT with the service gone'
    assert not applied[first + 1:].any(), 'force written after the service was gone'
    assert applied[:first].any(), 'no force before the service was gone'
    # the kill is seen as the service's end of the stream or as a failed send (EPIPE,
    # ECONNRESET), whichever comes first: both name the connection that ended
    reason = f'haply: the connection to ws://127.0.0.1:{emu.port}/ ended ('
    assert any(reason in t for t in texts), sorted(set(texts))


def test_the_service_restarted_mid_run(tmp_path: Path) -> None:
    """The service killed once the device pushes and started again on the same port: the
    states are FAULT from the kill until the user grasps again (the grip's button a, held
    through the loss (messages 1-20 of the new service), released, pressed again from message
    60), the driver writes zero meanwhile and the new service gets nothing but zero before
    the press; then the output fades in (WATCHDOG) and the run ends normally. The run lasts
    20 s: the restart has that long to happen."""
    monitor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    monitor.bind(('127.0.0.1', 0))
    where = ('127.0.0.1', monitor.getsockname()[1])
    grip = ('--grip', '61548')
    emu = Emulator(tmp_path / 'e0', (*grip, '--press', 'a@1-100000000'), monitor=where)
    options = (f'{{port: {emu.port}, engage_button: 0, grasp_ramp_ms: 20.0, stale_ms: 2000.0, '
               'reconnect_max_ms: 200.0}')
    bag = tmp_path / 'bag'
    run = subprocess.Popen(_command(_params(tmp_path, options), bag, 20.0),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           env=dict(os.environ))
    made: list[Emulator] = []

    def restart() -> None:
        emu.kill()
        made.append(Emulator(tmp_path / 'e1', (*grip, '--press', 'a@1-20', '--press',
                                               'a@60-100000000'), monitor=where,
                             port=emu.port))

    try:
        out = _interrupt(run, monitor, restart)
    finally:
        for e in made:
            e.stop()
    assert run.returncode == 0, out
    assert made and (bag / 'summary.json').is_file(), out
    second = made[0]
    # (the fault's reasons are not looked for among the 1 Hz /diagnostics: the phases may be
    # shorter; test_haply_reconnect.py checks them cycle by cycle)
    status, applied, _ = _bag(bag)
    fault = (status & FAULT) != 0
    edges = np.flatnonzero(np.diff(fault.astype(int)))
    assert len(edges) == 2, f'expected one run of FAULT states, edges at {edges}'
    first, last = int(edges[0]) + 1, int(edges[1])
    assert applied[:first].any(), 'no force before the service was gone'
    assert not applied[first + 1:last + 1].any(), 'force written while the FAULT stood'
    assert status[last + 1] & int(vocab.DeviceStatus.WATCHDOG), 'no fade-in after the FAULT'
    assert applied[last + 1:].any(), 'no force after the grasp again'
    _, _, f = read_log(second.log)
    assert len(f) > 60 and not f[:60].any() and f.any(), 'not zero before the press'


def test_an_unreachable_service_stops_the_run_before_it_starts(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = int(s.getsockname()[1])
    bag = tmp_path / 'bag'
    proc = subprocess.run(_command(_params(tmp_path, f'{{port: {port}}}'), bag, 2.0),
                          capture_output=True, timeout=400, env=dict(os.environ))
    out = (proc.stdout + proc.stderr).decode(errors='replace')
    assert proc.returncode == 1, out
    assert out.strip() == (
        'haptic-topology run: error: device: haply: cannot connect to '
        f'ws://127.0.0.1:{port}/: Connection refused: is the Haply Inverse Service (or '
        '`python -m haptic_topology.remote.haply_emulator`) running there?'), out
    assert not bag.exists(), out           # refused before anything started
