"""Point-grasp scenarios in the offline simulation: each has a constrained direction on its
path, and there eq. 14 keeps the device closer to the grasp point than eq. 10 (final and RMS
drift) and off the device's stops; fig8_point's eq. 10 run drifts into the device's stop as
fig8's does."""

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
