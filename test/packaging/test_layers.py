"""The layer contracts of ``pyproject.toml`` (import-linter): they hold on this tree, and they
fail on a copy with one deliberate back-edge (a lower layer importing a higher one inside a
function, which no module-level import check would see)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from conftest import REPO

LINT_IMPORTS = Path(sys.executable).parent / 'lint-imports'


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, 'PYTHONPATH': str(root)}
    return subprocess.run([str(LINT_IMPORTS), '--no-cache'], cwd=root, env=env,
                          capture_output=True, text=True, timeout=120)


def _copy(tmp_path: Path) -> Path:
    root = tmp_path / 'tree'
    shutil.copytree(REPO / 'haptic_topology', root / 'haptic_topology',
                    ignore=shutil.ignore_patterns('__pycache__'))
    shutil.copy(REPO / 'pyproject.toml', root / 'pyproject.toml')
    return root


def test_the_tree_keeps_every_contract(tmp_path: Path) -> None:
    out = _lint(_copy(tmp_path))
    assert out.returncode == 0, out.stdout + out.stderr
    assert 'Contracts: 2 kept, 0 broken.' in out.stdout


def test_a_back_edge_inside_a_function_breaks_the_layers(tmp_path: Path) -> None:
    root = _copy(tmp_path)
    laws = root / 'haptic_topology' / 'control' / 'laws.py'
    laws.write_text(laws.read_text() + '\n\ndef _late() -> object:\n'
                    '    from haptic_topology.config import settings\n\n'
                    '    return settings\n')
    out = _lint(root)
    assert out.returncode == 1, out.stdout
    assert 'Layers run one way (a layer imports only the layers below it) BROKEN' in out.stdout
    assert 'haptic_topology.control.laws -> haptic_topology.config.settings' in out.stdout


def test_rclpy_below_the_nodes_breaks_the_core_contract(tmp_path: Path) -> None:
    root = _copy(tmp_path)
    lmi = root / 'haptic_topology' / 'control' / 'lmi.py'
    lmi.write_text(lmi.read_text() + '\n\ndef _ros() -> object:\n    import rclpy\n\n'
                   '    return rclpy\n')
    out = _lint(root)
    assert out.returncode == 1, out.stdout
    assert 'Below the nodes nothing imports ROS 2 (rclpy, generated messages) BROKEN' in out.stdout
    assert 'haptic_topology.control.lmi -> rclpy' in out.stdout


def test_the_architecture_page_lists_the_contracts_layers_in_order() -> None:
    """docs/architecture.md's table (top layer first) names the packages of each layer of
    the contract, in the contract's order: the page cannot drift from what is checked."""
    import re
    import tomllib

    config = tomllib.loads((REPO / 'pyproject.toml').read_text())['tool']['importlinter']
    layers = next(c for c in config['contracts'] if c['id'] == 'layers')['layers']
    want = [sorted(m.strip().removeprefix('haptic_topology.') for m in layer.split('|'))
            for layer in layers]
    rows = [line.split('|')[2] for line in
            (REPO / 'docs' / 'architecture.md').read_text().splitlines()
            if re.match(r'^\| \d+ \|', line)]
    got = [sorted(re.findall(r'`(\w+)`', row)) for row in rows]
    assert got == want
