"""The venv finds both packages through ament_index with no environment set up by hand."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_share_directory

from haptic_topology import MSGS_PACKAGE_NAME, PACKAGE_NAME


@pytest.mark.parametrize('package', [PACKAGE_NAME, MSGS_PACKAGE_NAME])
def test_share_directory_has_package_xml(package: str) -> None:
    share = Path(get_package_share_directory(package))
    assert (share / 'package.xml').is_file()
    assert f'<name>{package}</name>' in (share / 'package.xml').read_text()


def test_ament_prefix_path_comes_from_the_venv_pth() -> None:
    env = {k: v for k, v in os.environ.items() if k != 'AMENT_PREFIX_PATH'}
    code = (
        'import os, sys; from ament_index_python.packages import get_package_share_directory as g;'
        f' print(g({PACKAGE_NAME!r})); print(g({MSGS_PACKAGE_NAME!r}));'
        " print(os.environ['AMENT_PREFIX_PATH'].split(os.pathsep)[0] == sys.prefix)"
    )
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()
    assert out == [f'{sys.prefix}/share/{PACKAGE_NAME}', f'{sys.prefix}/share/{MSGS_PACKAGE_NAME}',
                   'True']


def test_built_messages_import() -> None:
    from haptic_topology_msgs.msg import (
        DeviceCommand,
        DeviceState,
        HandInput,
        HandInputs,
        LmiUpdate,
        VtPath,
    )

    assert DeviceState.STATUS_FAULT == 8
    classes = (DeviceCommand, DeviceState, HandInput, HandInputs, LmiUpdate, VtPath)
    assert {c.__name__ for c in classes} == {
        'DeviceCommand', 'DeviceState', 'HandInput', 'HandInputs', 'LmiUpdate', 'VtPath'}


@pytest.mark.parametrize('script', ['haptic-topology', 'device_driver', 'lmi_controller',
                                    've_sim', 'recorder'])
def test_console_scripts_are_on_the_venv_path(script: str) -> None:
    assert (Path(sys.prefix) / 'bin' / script).is_file()
