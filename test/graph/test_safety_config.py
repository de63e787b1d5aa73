"""Bad configuration refuses to start with one message naming the file, the key and what was
expected: params files (checked before rclpy reads them), ``-p`` overrides, scenario and
linkage files; and the default DDS discovery range and transport."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_topology.config.node_params import KNOWN
from haptic_topology.config.params import check_overrides, check_params_file
from haptic_topology.errors import ConfigError
from haptic_topology.nodes.dds_env import localhost_discovery_default
from haptic_topology.paths import config_dir
from haptic_topology.sim.scenario import load_scenario

PARAMS = config_dir() / 'haptic_topology.yaml'


def test_shipped_params_file_is_valid() -> None:
    doc = check_params_file(PARAMS, KNOWN)
    assert set(doc) == {'device_driver', 'lmi_controller', 've_sim', 'recorder',
                        'foxglove_bridge'}


@pytest.mark.parametrize(('text', 'expected'), [
    ('device_driver:\n  ros__parameters:\n    rate_hz: [1, 2\n',
     'YAML syntax error at line 4'),
    ('device_driver:\n  ros__parameters:\n    watchdog_timout: 0.01\n',
     'device_driver.ros__parameters.watchdog_timout: unknown parameter of device_driver '
     '(expected one of:'),
    ('device_driver:\n  ros__parameters:\n    rate_hz: 1000\n',
     'device_driver.ros__parameters.rate_hz: expected a double (write 1000.0), got integer'),
    ('device_driver:\n  ros__parameters:\n    watchdog_timeout: 20.0\n',
     'watchdog_timeout: expected a value in [0.0001, 10], got 20.0'),
    ('device_driver:\n  ros__parameters:\n    watchdog_fallback: brake\n',
     'watchdog_fallback: expected one of zero, damping, got'),
    ('device_driver:\n  ros__parameters:\n    wrench_limit: [10, 10.0, 1.0]\n',
     'wrench_limit: expected a double array (write every entry with a decimal point'),
    ('lmi_controller:\n  ros__parameters:\n    k_tc: .nan\n',
     'k_tc: expected a finite number'),
    ('ve_sim:\n  ros__parameters:\n    update_period: ten\n',
     'update_period: expected an integer, got string'),
    ('device_drver:\n  ros__parameters:\n    rate_hz: 1000.0\n',
     'device_drver: unknown node (expected one of device_driver, foxglove_bridge, '
     'lmi_controller, recorder, ve_sim'),
    ('device_driver:\n  rate_hz: 1000.0\n',
     'device_driver: expected a mapping with the one key ros__parameters'),
    ('/**:\n  ros__parameters:\n    scenario: 6\n',
     '/**.ros__parameters.scenario: expected a string, got integer 6'),
    ('- device_driver\n', 'expected a YAML mapping at the top level'),
])
def test_bad_params_file_names_file_key_and_expectation(tmp_path: Path, text: str,
                                                        expected: str) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text(text, encoding='utf-8')
    with pytest.raises(ConfigError) as err:
        check_params_file(bad, KNOWN)
    msg = str(err.value)
    assert msg.startswith(str(bad)), msg
    assert expected in msg, msg


def test_params_file_wildcards_namespaces_and_recorder_keys(tmp_path: Path) -> None:
    ok = tmp_path / 'ok.yaml'
    ok.write_text('/**:\n  ros__parameters:\n    scenario: fig6\n'
                  '/ns/device_driver:\n  ros__parameters:\n    rate_hz: 500.0\n'
                  'recorder:\n  ros__parameters:\n    chunk_kib: 128\n',
                  encoding='utf-8')
    check_params_file(ok, KNOWN)
    check_params_file(ok, KNOWN, 'device_driver')
    with pytest.raises(ConfigError, match='file not found'):
        check_params_file(tmp_path / 'missing.yaml', KNOWN)


def test_unknown_override_is_refused() -> None:
    check_overrides(['-p', 'scenario:=fig6', '-p', 'recorder:output:=x'], KNOWN,
                    'device_driver')
    with pytest.raises(ConfigError, match=r'-p rate_hx:=5.0: unknown parameter of '
                       r'device_driver'):
        check_overrides(['-p', 'rate_hx:=5.0'], KNOWN, 'device_driver')
    with pytest.raises(ConfigError, match='unknown parameter of lmi_controller'):
        check_overrides(['-p', 'lmi_controller:kk_tc:=1.0'], KNOWN, None)


@pytest.mark.parametrize(('edit', 'expected'), [
    (('duration: 2.0', 'duration: -1'), 'scenario.duration: expected a value > 0.0'),
    (('duration: 2.0', 'durration: 2.0'), 'scenario.durration: unknown key'),
    (('duration: 2.0', 'duration: abc'), "scenario.duration: expected a number, got 'abc'"),
    (('q0: [0, pi/6, -pi/3]', 'q0: [0, pi/6'), 'YAML syntax error at line'),
    (('wrench_limit: [20.0, 20.0, 2.0]', 'wrench_limit: [20.0, 0.0, 2.0]'),
     'scenario.device.wrench_limit[1]: expected a value > 0.0'),
])
def test_bad_scenario_file_names_file_key_and_expectation(tmp_path: Path, edit: tuple[str, str],
                                                          expected: str) -> None:
    text = (config_dir() / 'scenarios' / 'fig8.yaml').read_text(encoding='utf-8')
    assert edit[0] in text
    bad = tmp_path / 'scenario.yaml'
    bad.write_text(text.replace(edit[0], edit[1]), encoding='utf-8')
    with pytest.raises(ConfigError) as err:
        load_scenario(str(bad))
    assert str(err.value).startswith(str(bad)) and expected in str(err.value), err.value


def test_bad_linkage_file_named_by_the_scenario(tmp_path: Path) -> None:
    link = (config_dir() / 'linkages' / 'table1_planar3.yaml').read_text(encoding='utf-8')
    (tmp_path / 'link.yaml').write_text(link.replace('mass: 3.0', 'mass: -3.0', 1),
                                        encoding='utf-8')
    sc = (config_dir() / 'scenarios' / 'fig8.yaml').read_text(encoding='utf-8')
    (tmp_path / 'sc.yaml').write_text(sc.replace('linkage: table1_planar3', 'linkage: link.yaml'),
                                      encoding='utf-8')
    with pytest.raises(ConfigError, match=r'link\.yaml: linkage\.links\[0\]\.mass: expected a '
                       r'value > 0\.0, got -3\.0'):
        load_scenario(str(tmp_path / 'sc.yaml'))


def _node(node: str, *args: str) -> tuple[int, str]:
    proc = subprocess.run([sys.executable, '-m', f'haptic_topology.nodes.{node}', *args],
                          capture_output=True, timeout=60)
    return proc.returncode, (proc.stdout + proc.stderr).decode(errors='replace')


def test_nodes_refuse_a_bad_params_file_before_rclpy(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('lmi_controller:\n  ros__parameters:\n    degrade_after: 0.25\n'
                   '    resync_rmp: 0.2\n', encoding='utf-8')
    code, out = _node('lmi_controller', '--ros-args', '--params-file', str(bad))
    assert code == 2, out
    assert 'Traceback' not in out
    assert out.strip().splitlines() == [
        f'lmi_controller: error: {bad}: lmi_controller.ros__parameters.resync_rmp: unknown '
        'parameter of lmi_controller (expected one of: ack_updates, b_tc, clock, '
        'degrade_after, executor, graph_id, k_tc, lockstep_wait, max_dt, mode, passivity, '
        'resync_max_jump, resync_ramp, scenario, sched_priority, stale_after)']
    code, out = _node('device_driver', '--ros-args', '--params-file', str(tmp_path / 'no.yaml'))
    assert code == 2 and f'device_driver: error: {tmp_path / "no.yaml"}: file not found' in out


def test_node_refuses_inconsistent_guard_times() -> None:
    code, out = _node('lmi_controller', '--ros-args', '--params-file', str(PARAMS), '-p',
                      'stale_after:=0.5', '-p', 'degrade_after:=0.1')
    assert code == 2, out
    assert 'lmi_controller: error: lmi_controller: parameters: degrade_after (0.1 s) must be ' \
           '>= stale_after (0.5 s)' in out


def test_discovery_defaults_to_localhost_unless_the_user_chose() -> None:
    profile = str(config_dir() / 'fastdds_localhost.xml')
    env: dict[str, str] = {}
    assert localhost_discovery_default(env) == 'LOCALHOST'
    assert env == {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
                   'FASTRTPS_DEFAULT_PROFILES_FILE': profile}
    assert Path(profile).is_file()
    env = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}       # chosen: the profile still
    assert localhost_discovery_default(env) == 'LOCALHOST'
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == profile
    env = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}
    assert localhost_discovery_default(env) == 'SUBNET' and len(env) == 1
    env = {'ROS_LOCALHOST_ONLY': '0'}
    assert localhost_discovery_default(env) == 'SUBNET' and len(env) == 1
    env = {'FASTRTPS_DEFAULT_PROFILES_FILE': '/lab/dds.xml'}  # the user's own profile
    assert localhost_discovery_default(env) == 'LOCALHOST'
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == '/lab/dds.xml'
    env = {'ROS_STATIC_PEERS': '192.168.1.20'}       # other hosts: their data is not loopback
    assert localhost_discovery_default(env) == 'LOCALHOST'
    assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in env
    env = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}      # not Fast DDS: the rmw's own
    assert localhost_discovery_default(env) == 'LOCALHOST'
    assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in env


@pytest.mark.graph
def test_node_processes_open_no_shared_memory_port(tmp_path: Path) -> None:
    """A node process set up as :func:`localhost_discovery_default` does it (as ``run_main``
    does) receives over UDP only: Fast DDS starts no shared-memory receive thread
    (``dds.shm.<port>``; the transport's watchdog ``dds.shm.wdog`` opens no port), so a killed
    and restarted process cannot be left on a dead port segment (config/fastdds_localhost.xml).
    The check that the setting takes effect: without the profile the same process under the
    same LOCALHOST range has shared-memory receive threads."""
    def threads(env: dict[str, str]) -> set[str]:
        code = ('import json, os, rclpy\n'
                'from haptic_topology.nodes.dds_env import localhost_discovery_default\n'
                'localhost_discovery_default(os.environ)\n'
                'rclpy.init(); n = rclpy.create_node("transport_probe")\n'
                'print(json.dumps(sorted({open(f"/proc/self/task/{t}/comm").read().strip()\n'
                '                         for t in os.listdir("/proc/self/task")})))\n')
        out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                             text=True, timeout=60, check=True).stdout
        return set(json.loads(out.strip().splitlines()[-1]))

    def shm_ports(names: set[str]) -> set[str]:
        return {t for t in names if t.startswith('dds.shm.') and t != 'dds.shm.wdog'}

    env = {k: v for k, v in os.environ.items() if k != 'FASTRTPS_DEFAULT_PROFILES_FILE'}
    default = threads(env)
    assert any(t.startswith('dds.udp') for t in default), default
    assert not shm_ports(default), default
    own = tmp_path / 'lab_profile.xml'      # a user's profile that leaves transports alone
    own.write_text('<?xml version="1.0" encoding="UTF-8" ?>\n<dds xmlns="http://www.eprosima.com/'
                   'XMLSchemas/fastRTPS_Profiles"><profiles/></dds>\n')
    plain = dict(env, FASTRTPS_DEFAULT_PROFILES_FILE=str(own))
    assert shm_ports(threads(plain))


