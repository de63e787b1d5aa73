"""``haptic-topology run`` when the device cannot be started: the run stops at the refused
transition and prints the backend's own one-line reason and where the driver's log is.

Each case runs the command as a user does (a params file with the backend, the command line),
in the session's ROS domain: a ``network`` device with no server and a lock-step run with a
device on its own clock (both refused by the run's preflight, before any node starts: no bag,
no node), a ``ros_topics`` device whose topics nobody publishes and a backend class whose
``configure`` raises (its own ``DeviceError``, and a bug): refused by the driver's transition.
No time bound is asserted (the machine's load decides how long the graph takes to start);
what the run must not do is wait for the recorder, as if the device had run.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from fake_backend import RefusingBackend

from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph

SUPPORT = Path(__file__).resolve().parents[1] / 'support'




def _params(tmp_path: Path, backend: str, options: str) -> Path:
    """A copy of the default params file with the driver's ``backend`` and
    ``backend_options`` (docs/devices.md: ``my_params.yaml``)."""
    doc = yaml.safe_load((config_dir() / 'haptic_topology.yaml').read_text(encoding='utf-8'))
    driver = doc['device_driver']['ros__parameters']
    driver['backend'] = backend
    driver['backend_options'] = options
    path = tmp_path / 'my_params.yaml'
    path.write_text(yaml.safe_dump(doc), encoding='utf-8')
    return path


def _run(tmp_path: Path, params: Path, *extra: str) -> tuple[int, str, Path]:
    """``haptic-topology run fig8 --params PARAMS`` (test doubles on PYTHONPATH): exit
    status, output, bag directory."""
    bag = tmp_path / 'bag'
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(SUPPORT), *filter(None, [env.get('PYTHONPATH')])])
    proc = subprocess.run(
        [sys.executable, '-m', 'haptic_topology.cli', 'run', 'fig8', '--params', str(params),
         '--duration', '2', '--no-plot', '--out', str(bag), *extra],
        capture_output=True, timeout=240, env=env)
    return proc.returncode, (proc.stdout + proc.stderr).decode(errors='replace'), bag


def _assert_failed(code: int, out: str, bag: Path, line: str) -> None:
    """The run failed with status 1 and printed ``line`` (the node, its transition and the
    backend's reason) and the driver's log, which exists; it did not run on."""
    assert code == 1, out
    assert f'haptic-topology run: error: {line}' in out, out
    found = re.search(r'; details: (\S+device_driver\.log)$', out.strip())
    assert found, out
    assert Path(found[1]) == bag / 'logs' / 'device_driver.log', out
    assert Path(found[1]).is_file()
    assert 'recorder has every message' not in out and 'Traceback' not in out, out
    assert 'device: backend' not in out, out


def _assert_refused_before_start(code: int, out: str, bag: Path, line: str) -> None:
    """The run failed with status 1 and printed ``line`` before starting anything: no bag
    directory, no node's output."""
    assert code == 1, out
    assert f'haptic-topology run: error: {line}' in out, out
    assert not bag.exists(), out
    assert 'running fig8' not in out and 'Traceback' not in out, out


def test_a_network_device_without_its_server(tmp_path: Path) -> None:
    # The port is held by a socket that never answers, so that no other program takes it.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(('127.0.0.1', 0))
        port = int(silent.getsockname()[1])
        params = _params(tmp_path, 'network',
                         f'{{host: 127.0.0.1, port: {port}, connect_timeout_ms: 500}}')
        code, out, bag = _run(tmp_path, params)
    _assert_refused_before_start(
        code, out, bag, 'device: network: no valid STATE from 127.0.0.1:'
        f'{port} within 500 ms (connect_timeout_ms); received 0 datagrams: is '
        '`haptic-topology device-server` running there')


def test_a_ros_topics_device_whose_topics_nobody_publishes(tmp_path: Path) -> None:
    params = _params(tmp_path, 'ros_topics',
                     '{pose_topic: /nobody/pose, twist_topic: /nobody/twist, '
                     'command_topic: /nobody/command, connect_timeout_ms: 300}')
    code, out, bag = _run(tmp_path, params)
    _assert_failed(code, out, bag, 'device_driver: activate failed: ros_topics: no valid '
                   'device sample on ')
    assert '/nobody/pose' in out and '/nobody/twist' in out, out


@pytest.mark.parametrize('refuse, reason', [
    ('device', RefusingBackend.REASON),
    ('bug', 'refusing_test_double: configure() raised RuntimeError: index 7 out of range '
     '(test)')])
def test_a_backend_whose_configure_raises(tmp_path: Path, refuse: str, reason: str) -> None:
    """The hosted layout configures the backend in the loop process, at activation."""
    params = _params(tmp_path, 'fake_backend:RefusingBackend', f'{{refuse: {refuse}}}')
    code, out, bag = _run(tmp_path, params)
    _assert_failed(code, out, bag, f'device_driver: activate failed: {reason}; details: ')


def test_lockstep_with_a_device_on_its_own_clock(tmp_path: Path) -> None:
    params = _params(tmp_path, 'network', '{host: 127.0.0.1}')
    code, out, bag = _run(tmp_path, params, '--clock', 'lockstep')
    _assert_refused_before_start(code, out, bag, 'device: backend network: the device runs '
                                 'on its own clock, so clock: lockstep cannot pace it')
