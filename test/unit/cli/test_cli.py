"""The haptic-topology command line."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from haptic_topology import cli
from haptic_topology.errors import ConfigError


def test_commands_are_registered_once_with_help() -> None:
    names = [c.name for c in cli.COMMANDS]
    assert 'info' in names
    assert len(names) == len(set(names))
    assert all(c.help for c in cli.COMMANDS)
    help_text = cli.build_parser().format_help()
    assert all(name in help_text for name in names)


def test_info_lists_versions_share_and_messages(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(['info']) == 0
    out = capsys.readouterr().out
    for needle in ('rclpy', 'pinocchio', 'numpy', f'{sys.prefix}/share/haptic_topology',
                   'haptic_topology_msgs/msg/DeviceState  [built]',
                   'haptic_topology_msgs/msg/HandInputs  [built]',
                   'haptic_topology_msgs/msg/HandInput  [built]'):
        assert needle in out


def test_missing_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main([])
    assert exc.value.code == 2
    assert 'required: COMMAND' in capsys.readouterr().err


def test_console_script_runs() -> None:
    exe = Path(sys.prefix) / 'bin' / 'haptic-topology'
    out = subprocess.run([str(exe), '--help'], capture_output=True, text=True, timeout=60,
                         check=True).stdout
    assert 'info' in out


def test_run_param_overrides_pass_node_parameters_and_refuse_other_forms(
        capsys: pytest.CaptureFixture[str]) -> None:
    from haptic_topology.bringup.options import param_overrides
    from haptic_topology.errors import ConfigError

    assert param_overrides(['ve_sim:nice:=0', 'device_driver:sched_priority:=50']) == [
        '-p', 've_sim:nice:=0', '-p', 'device_driver:sched_priority:=50']
    for bad in ('nice:=0', 've_sim:nice=0', 'nosuch:nice:=0', 've_sim::=1', 've_sim:nice:='):
        with pytest.raises(ConfigError, match=r'-p: expected NODE:NAME:=VALUE with NODE '
                           r'one of recorder, ve_sim, lmi_controller, device_driver'):
            param_overrides([bad])
    # as a user types it: one line naming the form, before any node starts
    assert cli.main(['run', 'circle', '-p', 've_sim:nice']) == 1
    out = capsys.readouterr()
    assert out.out == ''
    assert out.err == ("haptic-topology run: error: -p: expected NODE:NAME:=VALUE with NODE "
                       "one of recorder, ve_sim, lmi_controller, device_driver, "
                       "foxglove_bridge, got 've_sim:nice'\n")


def test_loop_cpu_keeps_one_cpu_for_the_loop_and_pins_every_other_thread_off_it(
        capsys: pytest.CaptureFixture[str]) -> None:
    from haptic_topology.bringup.options import loop_cpu_overrides
    from haptic_topology.errors import ConfigError

    cpus = sorted(os.sched_getaffinity(0))
    assert loop_cpu_overrides(None, 'separate') == []
    if len(cpus) >= 2:
        loop, rest = cpus[-1], ','.join(map(str, cpus[:-1]))
        assert loop_cpu_overrides(loop, 'hosted') == [
            '-p', f'device_driver:cpu_affinity:=[{loop}]',
            '-p', f'device_driver:node_cpu_affinity:=[{rest}]',
            '-p', f've_sim:cpu_affinity:=[{rest}]', '-p', f'recorder:cpu_affinity:=[{rest}]',
            '-p', f'foxglove_bridge:cpu_affinity:=[{rest}]']
    with pytest.raises(ConfigError, match=r'^--loop-cpu: needs --layout hosted \(the loop '
                       r'process\), got separate$'):
        loop_cpu_overrides(cpus[0], 'separate')
    absent = max(cpus) + 1
    with pytest.raises(ConfigError, match=rf'^--loop-cpu: expected one of the CPUs '
                       rf'\[{", ".join(map(str, cpus))}\] this command may use, with at least '
                       rf'one other left for the nodes, got {absent}$'):
        loop_cpu_overrides(absent, 'hosted')
    # as a user types it: one line, before any node starts
    assert cli.main(['run', 'circle', '--loop-cpu', str(absent)]) == 1
    assert capsys.readouterr().err.startswith('haptic-topology run: error: --loop-cpu: ')


def test_a_second_run_on_a_claimed_domain_refuses_in_one_line(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from haptic_topology.bringup.run import claim_domain
    from haptic_topology.errors import ConfigError

    domain = 232        # the largest valid id: no test session's graphs use it
    fd = claim_domain(domain)
    try:
        with pytest.raises(ConfigError, match=rf'^ROS domain {domain}: another haptic-topology '
                           rf'run uses it on this machine \(pid {os.getpid()}\); stop it, or '
                           r'give this run another domain, e.g. ROS_DOMAIN_ID=\d+$'):
            claim_domain(domain)
        # as a user meets it: `haptic-topology run` on that domain, before any output
        monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
        assert cli.main(['run', 'circle', '--duration', '1']) == 1
        out = capsys.readouterr()
        assert out.out == ''
        assert out.err.startswith(f'haptic-topology run: error: ROS domain {domain}: another '
                                  'haptic-topology run uses it')
        assert out.err.count('\n') == 1
    finally:
        os.close(fd)
    os.close(claim_domain(domain))          # released: the next run gets it


@pytest.mark.parametrize('command', ['run', 'simulate', 'device-server'])
def test_help_lists_every_shipped_scenario(command: str) -> None:
    """``--help`` of a command taking a scenario names every file of ``config/scenarios``
    (the command reference, docs/cli.md, is this text)."""
    names = sorted(p.stem for p in (Path(cli.__file__).parents[1] / 'config' / 'scenarios')
                   .glob('*.yaml'))
    assert len(names) > 2
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == '_SubParsersAction')
    text = ' '.join(sub.choices[command].format_help().split())
    assert f'scenario name ({", ".join(names)}) or ' in text


def test_run_takes_backend_options_as_ros_reads_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``-p device_driver:backend_options:=...``: quoted (the string parameter ROS reads) or an
    unquoted mapping, run's own check takes the options and passes them on as the string
    parameter (ROS takes no mapping); the example params file for a Haply on another port."""
    from haptic_topology.bringup.options import param_overrides
    from haptic_topology.config.node_params import KNOWN
    from haptic_topology.config.params import check_params_file
    from haptic_topology.config.resolve import run_backend
    from haptic_topology.paths import config_dir

    params = config_dir() / 'haptic_topology.yaml'
    for value in ("'{port: 10002, device_id: \"04B2\"}'", '{port: 10002, device_id: "04B2"}'):
        item = f'device_driver:backend_options:={value}'
        assert run_backend(params, 'haply', [item]) == (
            'haply', {'port': 10002, 'device_id': '04B2'})
        assert param_overrides([item]) == [
            '-p', 'device_driver:backend_options:=\'{port: 10002, device_id: "04B2"}\'']
    assert param_overrides(["device_driver:backend_options:={path: '/x'}"]) == [
        '-p', "device_driver:backend_options:='{path: ''/x''}'"]
    example = Path(__file__).resolve().parents[3] / 'config' / 'devices' / 'haply_other_port.yaml'
    check_params_file(example, KNOWN)
    assert run_backend(example, None, []) == ('haply', {
        'host': '127.0.0.1', 'port': 10002, 'device_id': '0E31', 'reconnect_max_ms': 2000.0})
    # as a user types it: the options reach the backend's check (the port is named)
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    assert cli.main(['run', 'fig8_point', '--backend', 'haply', '-p',
                     f"device_driver:backend_options:='{{port: {port}}}'"]) == 1
    assert capsys.readouterr().err.startswith(
        f'haptic-topology run: error: device: haply: cannot connect to ws://127.0.0.1:{port}/')
    bad = tmp_path / 'p.yaml'
    bad.write_text('device_driver:\n  ros__parameters:\n    backend_options: {port: 1}\n')
    with pytest.raises(ConfigError, match=r"backend_options: expected a string, got a mapping: "
                       r"write it in quotes \(backend_options: '\{\.\.\.\}'\)$"):
        check_params_file(bad, KNOWN)
