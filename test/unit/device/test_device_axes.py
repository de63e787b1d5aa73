"""A device declares the axes it senses and actuates; a scenario whose task needs an axis the
device lacks is refused before anything starts, in one line naming both (exit status 2)."""

from __future__ import annotations

import pytest

from haptic_topology import cli
from haptic_topology.config.resolve import check_device_axes
from haptic_topology.device.backend import (
    ALL_DEVICE_AXES,
    TRANSLATION_AXES,
    SimMaglevBackend,
    check_axes,
)
from haptic_topology.errors import AxesError
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import TaskSpace

FORCE3 = 'fake_backend:ForceOnlyBackend'


def test_simulated_maglev_declares_every_axis() -> None:
    assert SimMaglevBackend.axes({}) == ALL_DEVICE_AXES
    for task in TaskSpace:
        check_axes(task, ALL_DEVICE_AXES, 'any', 'sim_maglev')


def test_a_force_device_takes_point_tasks_and_refuses_torques() -> None:
    check_axes(TaskSpace.PLANAR_POINT, TRANSLATION_AXES, 'fig8_point', 'force3')
    check_axes(TaskSpace.SPATIAL_POINT, TRANSLATION_AXES, 'spatial_arm4_point', 'force3')
    with pytest.raises(AxesError, match=r'^scenario fig8 needs torque about z; device force3 '
                       r'actuates x, y, z forces only: use fig8_point$'):
        check_axes(TaskSpace.PLANAR, TRANSLATION_AXES, 'fig8', 'force3', 'fig8_point')
    with pytest.raises(AxesError, match=r'^scenario s needs torques about x, y, z; device '
                       r'force3 actuates x, y, z forces only$'):
        check_axes(TaskSpace.SPATIAL, TRANSLATION_AXES, 's', 'force3')


def test_the_driver_configuration_refuses_with_the_point_scenario_named() -> None:
    check_device_axes(load_scenario('fig8_point'), FORCE3, {})
    with pytest.raises(AxesError, match=rf'^scenario spatial_arm4 needs torques about x, y, '
                       rf'z; device {FORCE3} actuates x, y, z forces only: use '
                       r'spatial_arm4_point$'):
        check_device_axes(load_scenario('spatial_arm4'), FORCE3, {})
    with pytest.raises(AxesError, match=r'use a point grasp \(scenario\.task: planar_point\)$'):
        check_device_axes(load_scenario('circle'), FORCE3, {})


@pytest.mark.parametrize('how', [['--backend', FORCE3],
                                 ['-p', f'device_driver:backend:={FORCE3}']])
def test_run_refuses_in_one_line_with_exit_status_2(capsys: pytest.CaptureFixture[str],
                                                    how: list[str]) -> None:
    assert cli.main(['run', 'fig8', *how]) == 2
    out = capsys.readouterr()
    assert out.out == ''
    assert out.err == (f'haptic-topology run: error: scenario fig8 needs torque about z; '
                       f'device {FORCE3} actuates x, y, z forces only: use fig8_point\n')
