"""The haptic-topology command line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from haptic_topology import cli


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
