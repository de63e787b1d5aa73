"""Without the built messages (haptic_topology_msgs) every node and ``haptic-topology run``
stops with one line saying what to build, not with a traceback.

Here the messages are hidden from a subprocess of this venv by a meta-path finder that answers
``haptic_topology_msgs`` exactly as an environment without the package does
(``ModuleNotFoundError: No module named 'haptic_topology_msgs'``); everything else imports
as usual. ``scripts/colcon_check.sh`` (``make colcon-check``) checks the same against a real
colcon workspace: a plain ``colcon build`` there builds ``haptic_topology`` only, and the
line's command builds both.
"""

from __future__ import annotations

import doctest
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

from haptic_topology.messages import package as msgs_package
from haptic_topology.messages.package import colcon_command, missing_msgs_line

#: Runs ``argv[1]`` as ``python -m`` would (``-c cli`` for the console script
#: haptic-topology), with haptic_topology_msgs not importable.
_HIDDEN = r'''
import runpy, sys
class Hide:
    def find_spec(self, name, path=None, target=None):
        if name == 'haptic_topology_msgs' or name.startswith('haptic_topology_msgs.'):
            raise ModuleNotFoundError(f'No module named {name!r}', name=name)
        return None
sys.meta_path.insert(0, Hide())
module, sys.argv = sys.argv[1], sys.argv[1:]
if module == 'cli':
    from haptic_topology.cli import main
    sys.exit(main(sys.argv[1:]))
runpy.run_module(module, run_name='__main__', alter_sys=True)
'''

ROS_ARGS = ['--ros-args', '-p', 'scenario:=fig8']


def _run_hidden(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-c', _HIDDEN, *argv], capture_output=True,
                          text=True, timeout=120, cwd=REPO)


@pytest.mark.parametrize('argv', [
    ['haptic_topology.nodes.device_driver', *ROS_ARGS],
    ['haptic_topology.nodes.lmi_controller', *ROS_ARGS],
    ['haptic_topology.nodes.ve_sim', *ROS_ARGS],
    ['haptic_topology.nodes.recorder', *ROS_ARGS],
    ['haptic_topology.nodes.composed', *ROS_ARGS],
    ['haptic_topology.nodes.foxglove_bridge', *ROS_ARGS],
    ['cli', 'run', 'fig8', '--duration', '1'],
], ids=lambda a: a[0].rsplit('.', 1)[-1] + ('' if a[0] != 'cli' else ' run'))
def test_missing_messages_stop_every_program_with_one_line(argv: list[str]) -> None:
    proc = _run_hidden(*argv)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout == ''
    assert len(lines) == 1 and 'Traceback' not in proc.stderr, proc.stderr
    # In this venv (pip-installed, see scripts/setup.sh) the line names `make setup`.
    assert lines[0] == missing_msgs_line("No module named 'haptic_topology_msgs'")
    assert lines[0].startswith('haptic_topology: the message package haptic_topology_msgs '
                               "is not built (No module named 'haptic_topology_msgs')")
    assert lines[0].endswith(f': run `make setup` in {REPO}')


def test_the_messages_are_importable_here() -> None:
    # The programs above start normally in this venv: the hidden finder is what stops them.
    msgs_package.require_msgs_package()


def test_colcon_line_names_the_command_that_builds_both(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(msgs_package, '_pip_installed', lambda: False)
    line = missing_msgs_line("No module named 'haptic_topology_msgs'")
    assert '\n' not in line
    command = re.findall(r'`([^`]*)`', line)
    assert command == ['colcon build', f'colcon build --symlink-install --base-paths . '
                       f'{REPO}/msg_schemas', 'source install/setup.bash']
    assert (REPO / 'msg_schemas' / 'package.xml').is_file()


def test_colcon_line_without_a_source_tree(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(msgs_package, '_pip_installed', lambda: False)
    monkeypatch.setattr(msgs_package, 'SOURCE_ROOT', Path('/nonexistent/install/site'))
    assert ('`colcon build --symlink-install --base-paths . <the haptic_topology repository>/'
            'msg_schemas`') in missing_msgs_line('x')


def test_module_example() -> None:
    result = doctest.testmod(msgs_package)
    assert result.attempted and not result.failed


def test_colcon_check_script_runs_the_readme_form_of_the_command() -> None:
    script = (REPO / 'scripts' / 'colcon_check.sh').read_text(encoding='utf-8')
    readme_cmd = re.search(r"^readme_cmd='([^']*)'$", script, re.M)
    assert readme_cmd, 'scripts/colcon_check.sh: no readme_cmd'
    assert readme_cmd[1] == colcon_command(Path('src/haptic_topology'))


def test_colcon_pins_are_exact() -> None:
    pins = [ln for ln in (REPO / 'scripts' / 'colcon_requirements.txt').read_text().splitlines()
            if ln.strip() and not ln.startswith('#')]
    assert pins and all(re.fullmatch(r'[A-Za-z0-9_.\-]+==[0-9][^\s]*', p) for p in pins), pins
    names = {p.split('==')[0] for p in pins}
    assert {'colcon-common-extensions', 'colcon-core', 'colcon-recursive-crawl',
            'colcon-ros', 'colcon-cmake', 'colcon-python-setup-py'} <= names
