"""The default install does without example-robot-data (issue 58 item 3): in a child process
whose site-packages hides the distribution and its files (test/support/without_distribution.py;
the shared venv keeps it installed), the shipped robot scenarios load and simulate from
config/robots/, the robot tests pass, and naming a robot is refused in one line saying how to
install the extra. Where the extra is not installed at all, the child runs as it is."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
from without_distribution import hidden_command

REPO = Path(__file__).resolve().parents[3]
#: The distributions of the optional extra (example-robot-data and what it alone requires).
EXTRA = [line.split('==')[0] for line in (REPO / 'requirements-robots.lock').read_text()
         .splitlines() if '==' in line and not line.startswith('#')]

PROBE = '''
import importlib.metadata as md
import sys
from dataclasses import replace
from pathlib import Path

from haptic_topology.errors import LinkageError
from haptic_topology.model.linkage import load_linkage
from haptic_topology.sim import load_scenario, simulate

try:
    md.distribution('example-robot-data')
    sys.exit('example-robot-data is visible')
except md.PackageNotFoundError:
    pass
robots = (Path(sys.argv[1]) / 'config' / 'robots').resolve()
for name in ('panda_link4', 'panda_link4_point', 'panda_table', 'ur5_table'):
    sc = load_scenario(name)
    assert sc.linkage.urdf_path.resolve().is_relative_to(robots), sc.linkage.urdf_path
    assert sc.linkage.disabled_collisions, name
    if sc.contacts is not None:
        meshes = [s.mesh.path.resolve() for s in sc.contacts.shapes(sc.linkage)
                  if s.kind == 'mesh']
        assert meshes and all(m.is_relative_to(robots) for m in meshes), meshes
    print(name, sc.linkage.name, len(simulate(replace(sc, duration=0.02))))
try:
    load_linkage('robot:panda')
    sys.exit('robot:panda loaded')
except LinkageError as exc:
    print(exc)
'''


def _child(tmp_path: Path, args: list[str]) -> subprocess.CompletedProcess[str]:
    """``python ARGS`` with the extra's distributions hidden (as they are where not
    installed)."""
    cmd = hidden_command(EXTRA, tmp_path / 'site-packages', args)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, (str(REPO), os.environ.get('PYTHONPATH', '')))))
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=240, check=False)


def test_the_hiding_works(tmp_path: Path) -> None:
    """The child sees none of the extra's distributions, nor any of their files by
    package://."""
    probe = tmp_path / 'p.py'
    probe.write_text(
        'import importlib.metadata as md, sys\n'
        'from haptic_topology.paths import resolve_package_uri\n'
        'from haptic_topology.errors import ConfigError\n'
        'for name in sys.argv[1:]:\n'
        '    try:\n        md.distribution(name); sys.exit(name + " visible")\n'
        '    except md.PackageNotFoundError:\n        pass\n'
        'try:\n    resolve_package_uri("package://example-robot-data/robots/ur_description/'
        'urdf/ur5_robot.urdf", "w"); sys.exit("resolved")\n'
        'except ConfigError as exc:\n    print(exc)\n')
    assert EXTRA == ['example-robot-data', 'jrl-cmakemodules']
    res = _child(tmp_path, [str(probe), *EXTRA])
    assert res.returncode == 0, res.stderr + res.stdout
    assert res.stdout.startswith("w: package 'example-robot-data' is not installed")


def test_default_scenarios_run_and_robot_names_say_how_to_install(tmp_path: Path) -> None:
    probe = tmp_path / 'probe.py'
    probe.write_text(PROBE)
    res = _child(tmp_path, [str(probe), str(REPO)])
    assert res.returncode == 0, res.stderr + res.stdout
    lines = res.stdout.splitlines()
    assert lines[:4] == ['panda_link4 panda_link4 21', 'panda_link4_point panda_link4 21',
                         'panda_table panda 21', 'ur5_table ur5 21']
    assert lines[4:] == [
        "robot:panda: linkage.robot: robot 'panda' comes from example-robot-data, an optional "
        "extra that is not installed (131 MB): make robots (outside a checkout: pip install "
        "'example-robot-data==6.0.0'); the Panda and the UR5 of config/robots/ need no extra "
        "(scenarios panda_table, ur5_table)"]


def test_the_cli_refuses_robot_panda_in_one_line(tmp_path: Path) -> None:
    res = _child(tmp_path, ['-m', 'haptic_topology.cli', 'simulate', 'fig8', '--linkage',
                            'robot:panda', '--out', str(tmp_path / 'out')])
    assert res.returncode != 0 and res.stdout == ''
    assert res.stderr.count('\n') == 1 and 'make robots' in res.stderr
    assert not (tmp_path / 'out').exists()


@pytest.mark.timeout(600)
def test_the_robot_tests_pass_without_the_extra(tmp_path: Path) -> None:
    res = _child(tmp_path, ['-m', 'pytest', '-n', '0', '-q', '-p', 'no:cacheprovider',
                            'test/unit/model/test_robots.py',
                            'test/unit/sim/test_core_sim_spatial.py::'
                            'test_panda_is_loaded_unchanged_from_the_shipped_copy',
                            'test/unit/sim/test_core_sim_spatial.py::'
                            'test_package_uri_errors_name_the_field'])
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert re.fullmatch(r'\d+ passed in [\d.]+s', res.stdout.splitlines()[-1]), res.stdout
