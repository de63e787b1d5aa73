"""Offline lock-step simulation: the paper's Section VI and VIII results, and the CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from haptic_topology.errors import ConfigError
from haptic_topology.paths import config_dir
from haptic_topology.sim import Trace, load_scenario, simulate
from haptic_topology.sim.trace_io import iter_trace, read_trace, write_trace
from haptic_topology.vocabulary import ControlMode


@pytest.fixture(scope='module')
def fig6() -> dict[ControlMode, Trace]:
    sc = load_scenario('fig6')
    return {mode: simulate(sc, mode)
            for mode in (ControlMode.PENALTY, ControlMode.ACCELERATION_ONLY)}


def test_fig6_penalty_halves_the_drift_at_2s(fig6: dict[ControlMode, Trace]) -> None:
    d14 = fig6[ControlMode.PENALTY].distance()
    d10 = fig6[ControlMode.ACCELERATION_ONLY].distance()
    t = fig6[ControlMode.PENALTY].t
    at_2s = int(np.argmin(np.abs(t - 2.0)))
    ratio = d14[at_2s] / d10[at_2s]
    print(f'fig6 drift at 2 s: eq.14 {d14[at_2s] * 1e3:.3f} mm, eq.10 {d10[at_2s] * 1e3:.3f} mm,'
          f' ratio {ratio:.3f}')
    assert ratio <= 0.5


def test_fig6_eq10_drift_grows_after_the_singularity(fig6: dict[ControlMode, Trace]) -> None:
    tr = fig6[ControlMode.ACCELERATION_ONLY]
    q2 = tr.columns['q'][:, 1]
    crossing = int(np.nonzero(np.diff(np.sign(q2)) != 0)[0][0]) + 1  # q2 crosses 0
    assert 0.5 < tr.t[crossing] < 2.0
    d = tr.distance()
    after = d[crossing:]
    assert after[-1] > 2.0 * d[crossing]
    assert np.all(np.diff(after) > 0.0)  # grows monotonically from there on
    # and the topology is recognised there: a constraint direction is active at the crossing
    assert tr.columns['constraint_count'][crossing] == 1


def test_fig6_initial_offset_and_determinism(fig6: dict[ControlMode, Trace]) -> None:
    tr = fig6[ControlMode.PENALTY]
    assert tr.distance()[0] == pytest.approx(np.hypot(0.005, 0.003), rel=1e-12)
    again = simulate(load_scenario('fig6'), ControlMode.PENALTY)
    np.testing.assert_array_equal(again.columns['device_pose'], tr.columns['device_pose'])


def test_fig8_only_eq10_reaches_the_workspace_limit() -> None:
    sc = load_scenario('fig8')
    assert sc.update_period == 10 and sc.gains.k_tc == 200.0 and sc.gains.b_tc == 50.0
    s14 = simulate(sc, ControlMode.PENALTY).summary()
    s10 = simulate(sc, ControlMode.ACCELERATION_ONLY).summary()
    assert s14['workspace_limit_time_s'] == 0.0
    assert s10['workspace_limit_time_s'] > 0.1
    assert s14['max_distance_m'] < 0.5 * s10['max_distance_m']


@pytest.mark.parametrize('name', ['trace.parquet', 'trace.csv'])
def test_trace_file_round_trip(fig6: dict[ControlMode, Trace], tmp_path: Path,
                               name: str) -> None:
    tr = fig6[ControlMode.PENALTY]
    write_trace(tr, tmp_path / name)
    back = read_trace(tmp_path / name)
    assert back.meta == tr.meta
    np.testing.assert_array_equal(back.t, tr.t)
    np.testing.assert_array_equal(back.seq, tr.seq)
    for name_, col in tr.columns.items():
        np.testing.assert_array_equal(back.columns[name_], col)
        assert back.columns[name_].dtype.kind == col.dtype.kind
    assert back.summary() == tr.summary()
    # In chunks (Parquet: row groups) the same rows come back, in order.
    chunks = list(iter_trace(tmp_path / name, rows=700))
    assert [len(c) for c in chunks] == ([700, 700, len(tr) - 1400] if name.endswith('parquet')
                                        else [len(tr)])
    np.testing.assert_array_equal(Trace.concat(chunks).columns['vt_pose'],
                                  tr.columns['vt_pose'])


def test_parquet_trace_opens_as_a_plain_table(fig6: dict[ControlMode, Trace],
                                              tmp_path: Path) -> None:
    """What docs/recording.md tells a user: pyarrow opens the trace, the metadata is the
    schema's ``haptic_topology`` key, the columns those of the CSV header."""
    import pyarrow.parquet as pq

    tr = fig6[ControlMode.PENALTY]
    write_trace(tr, tmp_path / 'trace.parquet')
    table = pq.read_table(tmp_path / 'trace.parquet')
    assert table.column_names == tr.header()
    assert table.num_rows == len(tr)
    assert json.loads(pq.read_schema(tmp_path / 'trace.parquet').metadata[b'haptic_topology']
                      ) == tr.meta
    np.testing.assert_array_equal(table.column('device_pose_0').to_numpy(),
                                  tr.columns['device_pose'][:, 0])
    assert str(table.schema.field('status').type) == 'int64'


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name('haptic-topology')
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=120,
                          check=False)


def test_simulate_command_writes_trace_plot_summary(tmp_path: Path) -> None:
    out = tmp_path / 'run'
    res = _cli('simulate', 'fig6', '--mode', 'acceleration_only', '--out', str(out),
               '--duration', '0.5')
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / 'summary.json').read_text())
    for key in ('final_distance_m', 'max_distance_m', 'rms_distance_m', 'constrained_time_s'):
        assert isinstance(summary[key], float)
    assert summary['mode'] == 'acceleration_only' and summary['duration_s'] == 0.5
    assert (out / 'plot.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert read_trace(out / 'trace.parquet').summary()['final_distance_m'] == pytest.approx(
        summary['final_distance_m'])
    assert not (out / 'trace.csv').exists()
    assert 'final [mm]' in res.stdout and 'acceleration_only' in res.stdout


def test_simulate_with_a_bad_linkage_fails_with_one_message(tmp_path: Path) -> None:
    doc = yaml.safe_load((config_dir() / 'linkages' / 'table1_planar3.yaml').read_text())
    doc['linkage']['links'][0]['mass'] = 0
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump(doc))
    res = _cli('simulate', 'fig6', '--mode', 'penalty', '--out', str(tmp_path / 'o'),
               '--linkage', str(bad))
    assert res.returncode == 1
    assert 'Traceback' not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1
    assert 'bad.yaml: linkage.links[0].mass: expected a value > 0.0, got 0.0' in lines[0]
    assert not (tmp_path / 'o').exists()


def test_simulate_with_another_linkage(tmp_path: Path) -> None:
    res = _cli('simulate', 'fig6', '--out', str(tmp_path / 'o'), '--duration', '0.2',
               '--linkage', str(config_dir() / 'linkages' / 'spatial_arm4.yaml'))
    assert res.returncode == 1
    assert 'linkage.task is spatial, the scenario fig6 needs planar' in res.stderr


def test_simulate_refuses_a_linkage_that_the_scenarios_q0_does_not_fit(tmp_path: Path) -> None:
    """The Panda (7 joints) through spatial_arm4 (q0 of 4): one line, nothing written;
    with ``--q0`` of the Panda's ready posture the device would start beyond
    spatial_arm4's stops: refused, naming the coordinate."""
    panda = str(config_dir() / 'linkages' / 'panda_link4.yaml')
    out = tmp_path / 'o'
    res = _cli('simulate', 'spatial_arm4', '--out', str(out), '--linkage', panda)
    assert res.returncode == 1 and 'Traceback' not in res.stderr
    assert res.stderr.strip().splitlines()[-1].endswith(
        'spatial_arm4.yaml: scenario.q0 has 4 entries, the linkage panda_link4 7 joints: '
        'give q0 (simulate --q0) or a scenario for it')
    res = _cli('simulate', 'spatial_arm4', '--out', str(out), '--linkage', panda,
               '--q0=0,-pi/4,0,-3*pi/4,0,pi/2,pi/4')
    assert res.returncode == 1 and 'Traceback' not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert 'spatial_arm4.yaml: the device would start at pose[0] = -0.0606' in last
    assert 'outside device.workspace [lo, hi] = [0.15, 0.257]' in last
    assert not out.exists()
    # The loader's note on the Panda's locked fingers is printed (stdout).
    assert 'locked 2 side-branch joint(s) at panda_finger_joint1=0' in res.stdout


def test_simulate_q0_sets_the_initial_state(tmp_path: Path) -> None:
    """``--q0`` with the scenario's own linkage: the run starts there (same trace as a
    scenario file with that q0); a wrong count or value is one line naming --q0."""
    from haptic_topology.sim.command import parse_q0

    np.testing.assert_array_equal(parse_q0('0, pi/6,-pi/3', 3), [0.0, math.pi / 6,
                                                                 -math.pi / 3])
    res = _cli('simulate', 'fig8', '--out', str(tmp_path / 'x'), '--q0=0,pi/6')
    assert res.returncode == 1 and res.stderr.strip().endswith('--q0: expected 3 numbers, got 2')
    doc = yaml.safe_load((config_dir() / 'scenarios' / 'fig8.yaml').read_text())
    doc['scenario']['q0'] = [0.0, 0.5, -1.0]
    doc['scenario']['linkage'] = str(config_dir() / 'linkages' / 'table1_planar3.yaml')
    (tmp_path / 'fig8_q.yaml').write_text(yaml.safe_dump(doc))
    a, b = tmp_path / 'a', tmp_path / 'b'
    assert _cli('simulate', 'fig8', '--out', str(a), '--duration', '0.2',
                '--q0=0,0.5,-1').returncode == 0
    assert _cli('simulate', str(tmp_path / 'fig8_q.yaml'), '--out', str(b), '--duration',
                '0.2').returncode == 0
    assert (a / 'trace.parquet').read_bytes() == (b / 'trace.parquet').read_bytes()
    assert (a / 'trace.parquet').read_bytes() != b''


@pytest.mark.parametrize(('mutate', 'expected'), [
    (lambda s: s.update(q0=[0, 'pi/6']), r'scenario\.q0: expected 3 numbers, got 2'),
    (lambda s: s.update(q0=[0, 'tau/6', 0]),
     r"scenario\.q0\[1\]: expected a number or an expression like -pi/4, got 'tau/6'"),
    (lambda s: s['control'].update(k_tc=-1), r'scenario\.control\.k_tc: expected a value >= 0'),
    (lambda s: s['lmi'].update(model='eq99'),
     r"scenario\.lmi\.model: expected one of eq17, eq20, got 'eq99'"),
    (lambda s: s.update(speed=3), r'scenario\.speed: unknown key'),
    (lambda s: s['user'].update(type='robot'),
     r"scenario\.user\.type: expected one of constant_wrench, spring_damper, got 'robot'"),
    (lambda s: s.update(linkage='nope'), r'nope: no such file, and no linkage of that name'),
    (lambda s: s.update(gravity=[0, -9.81]), r'scenario\.gravity: expected 3 numbers'),
    (lambda s: (s.update(gravity=[0, 0, -9.81]), s['lmi'].update(model='eq20')),
     r'scenario\.lmi\.model: eq20 \(D qdd = J_h\^T F_vt\) neglects the gravity \[0\.0, 0\.0, '
     r'-9\.81\] m/s\^2 of linkage table1_planar3 that the VE integrates; expected eq17, or '
     r'scenario\.gravity: \[0, 0, 0\]'),
])
def test_bad_scenarios_name_the_key(tmp_path: Path, mutate, expected: str) -> None:
    doc = yaml.safe_load((config_dir() / 'scenarios' / 'fig6.yaml').read_text())
    mutate(doc['scenario'])
    path = tmp_path / 'sc.yaml'
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=expected):
        load_scenario(str(path))


def test_spring_damper_user_tracks_its_path() -> None:
    from dataclasses import replace

    sc = load_scenario('fig6')
    sc = replace(sc, duration=0.5, user={'type': 'spring_damper', 'path': 'line',
                                         'velocity': [0.02, 0.0, 0.0],
                                         'stiffness': [200.0, 200.0, 1.0],
                                         'damping': [20.0, 20.0, 0.1]})
    tr = simulate(sc, ControlMode.PENALTY)
    x = tr.columns['device_pose'][:, 0]
    assert x[-1] > x[0] + 0.002  # the hand pulled the device along +x
    assert np.all(np.isfinite(tr.columns['command']))


def test_blend_removes_the_force_jolt_at_the_rank_switch() -> None:
    """Hard switching (the paper) jumps the penalty on in one cycle; the blend ramps it."""
    from dataclasses import replace

    sc = load_scenario('fig8')
    jolt = {}
    for blend in (0.0, 1.0):
        lk = replace(sc.linkage, constraints=replace(sc.linkage.constraints, blend=blend))
        tr = simulate(replace(sc, linkage=lk), ControlMode.PENALTY)
        jolt[blend] = float(np.abs(np.diff(tr.columns['command'][:, :2], axis=0)).max())
        assert tr.summary()['final_distance_m'] < 0.5e-3
    print(f'fig8 max force change per cycle: hard {jolt[0.0]:.4f} N, blend=1 {jolt[1.0]:.4f} N')
    assert jolt[1.0] < 0.25 * jolt[0.0]


def test_contact_columns_hold_each_update_until_the_next() -> None:
    """Penetration and contact energy as the VE's updates report them: update i at row
    rows[i], held to the next update; NaN before the first and after the last (the offline
    simulation and a recorded run sample them alike)."""
    tr = Trace.empty(8, 3, 3, contacts=True)
    tr.hold_contacts(np.array([2, 5]), [0.001, 0.0], [-0.1, -0.2])
    np.testing.assert_array_equal(
        tr.columns['penetration'], [np.nan, np.nan, 0.001, 0.001, 0.001, 0.0, np.nan, np.nan])
    np.testing.assert_array_equal(
        tr.columns['contact_energy'], [np.nan, np.nan, -0.1, -0.1, -0.1, -0.2, np.nan, np.nan])
    tr.hold_contacts(np.array([], dtype=int), [], [])
    assert np.isnan(tr.columns['penetration']).all()
