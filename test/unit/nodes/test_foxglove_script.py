"""The layout's user script ``device_vt_distance`` (``docs/foxglove_layout.json``) run on
Node.js with the messages Foxglove would hand it: the drift counts x, y of a planar task and
x, y, z of a spatial one, and at ``task_dim`` 3 (planar or spatial_point) it takes the task
from ve_sim's status on ``/diagnostics``, never from the dimension. The expected distances
are computed here in the script's order of operations, so they are equal bit for bit."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[3]
LAYOUT = REPO / 'docs' / 'foxglove_layout.json'
RUNNER = """import script from './script.mjs';
import { readFileSync } from 'node:fs';
const events = JSON.parse(readFileSync(0, 'utf8'));
console.log(JSON.stringify(events.map((e) => script(e) ?? null)));
"""


def _javascript(typescript: str) -> str:
    """The script as JavaScript: its import of Foxglove's types and its type annotations
    removed (the script keeps to the few forms removed here)."""
    js = typescript.replace('import { Input } from "./types";\n', '')
    js = re.sub(r'type Output = \{[^}]*\};\n', '', js)
    js = re.sub(r'new Map<[^>]*>\(', 'new Map(', js)
    js = re.sub(r'\(\s*event:[^)]*\)\s*:\s*Output \| undefined\s*\{', '(event) {', js)
    js = re.sub(r':\s*Output \| undefined', '', js)
    js = re.sub(r':\s*number\b', '', js)
    left = re.findall(r'\b(?:Input|Output)\b.*', js)
    assert not left, f'type annotations left in the script: {left}'
    return js


def run_script(events: list[dict[str, Any]], tmp_path: Path) -> list[Any]:
    """The script's output for each event (None: no output), in a fresh Node.js process."""
    node = shutil.which('node')
    if node is None:
        pytest.fail('node not found: this test runs the layout\'s user script on Node.js >= 20 '
                    '(install Node.js, then make setup-tests)')
    layout = json.loads(LAYOUT.read_text(encoding='utf-8'))
    source = layout['userNodes']['device-vt-distance']['sourceCode']
    (tmp_path / 'script.mjs').write_text(_javascript(source), encoding='utf-8')
    (tmp_path / 'run.mjs').write_text(RUNNER, encoding='utf-8')
    proc = subprocess.run([node, 'run.mjs'], cwd=tmp_path, input=json.dumps(events),
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def _state(seq: int, pose: list[float]) -> dict[str, Any]:
    return {'topic': '/haptic/device/state',
            'message': {'seq': seq, 'task_dim': len(pose), 'pose': pose}}


def _path(seq: int, pose: list[float]) -> dict[str, Any]:
    """The VT hand at device state ``seq`` (the input of state ``seq - 1`` integrated)."""
    return {'topic': '/haptic/ve/path',
            'message': {'task_dim': len(pose), 'hand_input_seqs': [seq - 1], 'hand_pose': pose}}


def _ve_status(task: str | None) -> dict[str, Any]:
    values = [{'key': 'hand_inputs', 'value': '10'}]
    if task is not None:
        values.append({'key': 'task', 'value': task})
    return {'topic': '/diagnostics',
            'message': {'status': [{'name': 've_sim: loop', 'values': values}]}}


def _distance(a: list[float], b: list[float], n: int) -> float:
    total = 0.0
    for k in range(n):
        total += (a[k] - b[k]) * (a[k] - b[k])
    return math.sqrt(total)


@pytest.mark.parametrize('task,device,vt,n', [
    ('spatial_point', [0.011, -0.02, 0.704], [0.01, -0.02, 0.7], 3),
    ('planar', [0.011, -0.02, 0.9], [0.01, -0.02, 0.1], 2),
    ('planar_point', [0.011, -0.02], [0.01, -0.023], 2),
    ('spatial', [0.011, -0.02, 0.704, 0.3, 0.0, 0.0], [0.01, -0.02, 0.7, 0.0, 0.0, 0.0], 3),
])
def test_the_drift_counts_the_translations_of_the_task(task: str, device: list[float],
                                                       vt: list[float], n: int,
                                                       tmp_path: Path) -> None:
    """spatial_point: x, y, z (not x, y, as a planar task of the same task_dim 3); planar:
    x, y, not theta."""
    out = run_script([_ve_status(task), _state(7, device), _path(7, vt)], tmp_path)
    assert out[:2] == [None, None]
    want = _distance(device, vt, n)
    assert out[2] == {'distance_m': want, 'max_distance_m': want, 'state_seq': 7}


def test_task_dim_3_waits_for_ve_sims_task_and_an_older_ve_sim_is_planar(
        tmp_path: Path) -> None:
    """Before ve_sim's first status a task_dim 3 path has no distance (planar or
    spatial_point?); a ve_sim status without ``task`` (a bag recorded before point grasps)
    means planar; a status of another node changes nothing."""
    device, vt = [0.0, 0.003, 0.5], [0.0, 0.0, 0.0]
    other = {'topic': '/diagnostics',
             'message': {'status': [{'name': 'lmi_controller: loop',
                                     'values': [{'key': 'task', 'value': 'spatial_point'}]}]}}
    out = run_script([_state(3, device), _path(3, vt), other, _path(3, vt),
                      _ve_status(None), _path(3, vt)], tmp_path)
    want = _distance(device, vt, 2)
    assert out == [None, None, None, None, None,
                   {'distance_m': want, 'max_distance_m': want, 'state_seq': 3}]
