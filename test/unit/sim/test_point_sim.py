"""Point-grasp scenarios in the offline simulation: each has a constrained direction on its
path, and there eq. 14 keeps the device closer to the grasp point than eq. 10 (final and RMS
drift) and off the device's stops; fig8_point's eq. 10 run drifts into the device's stop as
fig8's does; where nothing is constrained, eq. 14 is eq. 10 bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from haptic_topology.errors import ConfigError
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode, TaskSpace

POINT_SCENARIOS = ('fig6_point', 'fig8_point', 'spatial_arm4_point', 'panda_link4_point',
                   'fourbar_point')


@pytest.mark.timeout(600)
@pytest.mark.parametrize('name', POINT_SCENARIOS)
def test_eq14_keeps_the_device_closer_than_eq10(name: str) -> None:
    sc = load_scenario(name)
    assert sc.linkage.task.point
    s14 = simulate(sc, ControlMode.PENALTY).summary()
    s10 = simulate(sc, ControlMode.ACCELERATION_ONLY).summary()
    assert s14['constrained_time_s'] == s10['constrained_time_s'] > 0.0
    assert s14['final_distance_m'] < s10['final_distance_m']
    assert s14['rms_distance_m'] < s10['rms_distance_m']
    assert s14['workspace_limit_time_s'] == 0.0


def test_fig8_point_only_eq10_reaches_the_workspace_limit() -> None:
    sc = load_scenario('fig8_point')
    assert sc.linkage.task is TaskSpace.PLANAR_POINT
    assert sc.user == {'type': 'constant_wrench', 'wrench': [0.4, 0.0]}
    s10 = simulate(sc, ControlMode.ACCELERATION_ONLY).summary()
    assert s10['workspace_limit_time_s'] > 0.0


def test_a_point_task_must_keep_the_linkage_space(tmp_path: object) -> None:
    from pathlib import Path

    from haptic_topology.paths import config_dir
    text = (config_dir() / 'scenarios' / 'fig8_point.yaml').read_text().replace(
        'task: planar_point', 'task: spatial_point').replace(
        'linkage: table1_planar3', f'linkage: {config_dir() / "linkages/table1_planar3.yaml"}')
    path = Path(str(tmp_path)) / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError, match=r'scenario\.task: linkage table1_planar3 is planar, '
                       r"so expected planar or planar_point, got 'spatial_point'$"):
        load_scenario(str(path))


def test_the_drift_of_a_spatial_point_grasp_counts_z() -> None:
    """A trace of spatial_point (m = 3, like planar) measures its drift in x, y and z; one of
    planar_point (m = 2) in x, y; a planar one (m = 3) in x, y, not theta. The task is the
    trace's metadata, written with it and read back."""
    from haptic_topology.sim.trace import Trace
    from haptic_topology.sim.trace_io import empty_trace

    for task, pose, want in ((TaskSpace.SPATIAL_POINT, [0.0, 0.0, 0.004], 0.004),
                             (TaskSpace.PLANAR, [0.0, 0.003, 0.5], 0.003),
                             (TaskSpace.PLANAR_POINT, [0.003, 0.004], 0.005)):
        tr = Trace.empty(1, task.dim, 2, task=task.value)
        tr.record(0, t=0.0, device_pose=pose, vt_pose=np.zeros(task.dim))
        assert tr.task is task
        assert tr.distance().tolist() == [want]
        assert empty_trace(dict(tr.meta)).task is task
    with pytest.raises(ConfigError, match=r"trace metadata: task must be a task of dimension "
                       r"task_dim = 2 \(planar_point\), got 'spatial_point'"):
        empty_trace({'task_dim': 2, 'dof': 1, 'task': 'spatial_point'})


#: panda_link4 held through a ball joint at the COM of panda_link4 (joints 1-4 move the point:
#: rank J_h = 3 on this path, nothing constrained), pushed up by 2 N, no device stops.
PANDA_AT_COM = """
scenario:
  name: panda_com_point
  linkage: panda_link4
  task: spatial_point
  q0: [0, -pi/4, 0, -3*pi/4, 0, pi/2, pi/4]
  duration: 1.5
  dt: 0.001
  mode: penalty
  device:
    mass: [1.0, 1.0, 1.0]
    wrench_limit: [20.0, 20.0, 20.0]
  user: {type: constant_wrench, wrench: [0.0, 0.0, 2.0]}
  control: {k_pc: [100.0, 100.0, 100.0], b_pc: [70.0, 70.0, 70.0], k_tc: 200.0, b_tc: 50.0}
  lmi: {model: eq20, update_period: 10}
  ve: {internal_step: 0.001, vt_coupling: false}
"""


def test_with_nothing_constrained_eq14_is_eq10_bit_for_bit(tmp_path: object) -> None:
    """Where no direction is constrained the penalty of eq. 13 is zero, so eq. 14 is eq. 10:
    the two runs are the same to the last bit (a wall-clock run of either differs from run
    to run with the states the loop answered in time, not with the law)."""
    from pathlib import Path

    path = Path(str(tmp_path)) / 'panda_com_point.yaml'
    path.write_text(PANDA_AT_COM)
    sc = load_scenario(str(path))
    t14 = simulate(sc, ControlMode.PENALTY)
    t10 = simulate(sc, ControlMode.ACCELERATION_ONLY)
    assert t14.summary()['constrained_time_s'] == 0.0
    assert not np.any(t14.columns['lmi_constraint_count'])
    for col in ('device_pose', 'device_twist', 'command', 'applied', 'vt_pose', 'lmi_pose',
                'q'):
        np.testing.assert_array_equal(t14.columns[col], t10.columns[col], err_msg=col)
    assert t14.summary()['final_distance_m'] == t10.summary()['final_distance_m'] > 0.01
