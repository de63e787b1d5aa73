"""Per-node settings: parameter tables generated from the dataclass fields, values checked at
construction, resolution with the scenario (messages name the parameter and what was
expected), scenario defaults, frozen objects."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_topology.config.node_params import KNOWN
from haptic_topology.config.params import check_overrides, check_params_file
from haptic_topology.config.resolve import (
    resolve_device_driver,
    resolve_lmi_controller,
    resolve_recorder,
    resolve_ve_sim,
)
from haptic_topology.config.settings import (
    DeviceDriverSettings,
    FoxgloveBridgeSettings,
    LmiControllerSettings,
    NodeSettings,
    RecorderSettings,
    VeSimSettings,
    param_specs,
    scenario_defaults,
)
from haptic_topology.control.laws import check_live
from haptic_topology.device.watchdog import WatchdogFallback
from haptic_topology.errors import ConfigError
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.vocabulary import Clock, ControlMode

_CPUS = os.cpu_count() or 1

_EX = ('events', 'single_threaded')
_COMMON: list[tuple[str, Any, float | None, float | None, tuple[str, ...] | None, bool]] = [
    ('scenario', 'fig8', None, None, None, True),
    ('executor', 'events', None, None, _EX, True),
    ('graph_id', '', None, None, None, True),
    ('sched_priority', 0, 0, 99, None, True),
]
#: name, ROS default, lo, hi, choices, read_only: the tables before the settings classes, plus
#: the parameters added with them (clock of every node but the recorder; lockstep_warn_after,
#: autostart, run_duration, lockstep_wait; rate_hz and update_period 0 = the scenario's).
EXPECTED: dict[type[NodeSettings], list[tuple[str, Any, float | None, float | None,
                                              tuple[str, ...] | None, bool]]] = {
    DeviceDriverSettings: [*_COMMON,
        ('backend', 'sim_maglev', None, None, None, True),
        ('backend_options', '', None, None, None, True),
        ('rate_hz', 0.0, 0.0, 10000.0, None, True),
        ('watchdog_timeout', 0.005, 1e-4, 10.0, None, True),
        ('watchdog_ramp', 0.05, 1e-3, 10.0, None, True),
        ('watchdog_fallback', 'zero', None, None, ('zero', 'damping'), True),
        ('watchdog_damping', [0.0], None, None, None, True),
        ('takeover_after', 0.5, 0.01, 3600.0, None, True),
        ('min_subscribers', 1, 0, 100, None, True),
        ('sampled_state_rate_hz', 30.0, 0.0, 1000.0, None, True),
        ('wrench_limit', [0.0], None, None, None, True),
        ('clock', 'wall', None, None, ('wall', 'lockstep'), True),
        ('lockstep_warn_after', 2.0, 0.1, 600.0, None, True),
        ('autostart', True, None, None, None, True),
        ('run_duration', 0.0, 0.0, 1e6, None, True),
        ('host_controller', True, None, None, None, True),
        ('loop_process', True, None, None, None, True),
        ('cpu_affinity', [-1], None, None, None, True),
        ('lock_memory', False, None, None, None, True),
        ('sched_slice_us', 100.0, 0.0, 100000.0, None, True),
        ('timer_slack_ns', 0, 0, 10_000_000, None, True),
        ('publisher_nice', 5, 0, 19, None, True),
        ('sched_policy', 'batch', None, None, ('other', 'batch'), True),
        ('node_cpu_affinity', [-1], None, None, None, True)],
    LmiControllerSettings: [*_COMMON,
        ('mode', 'penalty', None, None, ('penalty', 'acceleration_only'), False),
        ('k_tc', 0.0, 0.0, 1e5, None, False),
        ('b_tc', 0.0, 0.0, 1e5, None, False),
        ('max_dt', 0.05, 1e-4, 1.0, None, True),
        ('stale_after', 0.05, 1e-3, 60.0, None, True),
        ('degrade_after', 0.6, 1e-3, 60.0, None, True),
        ('resync_max_jump', 1.0, 0.0, 1e6, None, True),
        ('resync_ramp', 0.2, 1e-3, 10.0, None, True),
        ('clock', 'wall', None, None, ('wall', 'lockstep'), True),
        ('lockstep_wait', 60.0, 0.01, 600.0, None, True),
        ('passivity', 'auto', None, None, ('auto', 'enabled', 'disabled'), True),
        ('ack_updates', False, None, None, None, True)],
    VeSimSettings: [*_COMMON,
        ('nice', 5, 0, 19, None, True),
        ('sched_policy', 'batch', None, None, ('other', 'batch', 'idle'), True),
        ('cpu_affinity', [-1], None, None, None, True),
        ('update_period', 0, 0, 10000, None, True),
        ('idle_update_rate_hz', 50.0, 0.1, 1000.0, None, True),
        ('max_hand_wrench', 1000.0, 1e-3, 1e9, None, True),
        ('viz_rate_hz', 30.0, 0.1, 200.0, None, True),
        ('frame_id', 'world', None, None, None, True),
        ('clock', 'wall', None, None, ('wall', 'lockstep'), True)],
    RecorderSettings: [*_COMMON,
        ('nice', 10, 0, 19, None, True),
        ('sched_policy', 'batch', None, None, ('other', 'batch', 'idle'), True),
        ('cpu_affinity', [-1], None, None, None, True),
        ('output', '', None, None, None, True),
        ('topics', [''], None, None, None, True),
        ('topic_regex', '', None, None, None, True),
        ('flush_period', 0.2, 0.01, 10.0, None, True),
        ('chunk_kib', 64, 4, 65536, None, True),
        ('compression', 'zstd', None, None, ('zstd', 'lz4', 'none'), True),
        ('max_bag_size', 0, 0, 1 << 50, None, True),
        ('max_bag_duration', 600.0, 0.0, 1e7, None, True),
        ('clock', 'wall', None, None, ('wall', 'lockstep'), True)],
}


@pytest.fixture(scope='module')
def fig8() -> Scenario:
    return load_scenario('fig8')


@pytest.mark.parametrize('cls', list(EXPECTED))
def test_param_specs_are_generated_from_the_fields(cls: type[NodeSettings]) -> None:
    specs = param_specs(cls)
    got = [(s.name, s.default, s.lo, s.hi, s.choices, s.read_only) for s in specs.values()]
    assert got == EXPECTED[cls]
    for spec, row in zip(specs.values(), EXPECTED[cls], strict=True):
        assert type(spec.default) is type(row[1])       # 0.0 stays a double, 0 an integer
        assert spec.description
    assert KNOWN[cls.NODE] == specs


def test_new_parameters_are_described() -> None:
    dd = param_specs(DeviceDriverSettings)
    assert dd['clock'].description.startswith('wall: a 1 kHz wall timer paces the device; '
                                              'lockstep: simulated time (/clock) advances')
    assert 'warn when the answer to a state has not come' in dd['lockstep_warn_after'].description
    assert '0.0 = 1/scenario dt' in dd['rate_hz'].description
    assert 'longest wait (wall s) for the LMI update' in \
        param_specs(LmiControllerSettings)['lockstep_wait'].description
    assert "0 = the scenario's lmi.update_period" in \
        param_specs(VeSimSettings)['update_period'].description


def test_recorder_parameters_are_checked_in_params_files(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('recorder:\n  ros__parameters:\n    chunk_kb: 128\n', encoding='utf-8')
    with pytest.raises(ConfigError, match=r'recorder\.ros__parameters\.chunk_kb: unknown '
                       r'parameter of recorder \(expected one of: chunk_kib, clock, '
                       r'compression, '):
        check_params_file(bad, KNOWN)
    bad.write_text('recorder:\n  ros__parameters:\n    flush_period: 1\n', encoding='utf-8')
    with pytest.raises(ConfigError, match=r'flush_period: expected a double \(write 1\.0\)'):
        check_params_file(bad, KNOWN, 'recorder')
    with pytest.raises(ConfigError, match='unknown parameter of recorder'):
        check_overrides(['-p', 'recorder:outptu:=x'], KNOWN, None)
    check_overrides(['-p', 'recorder:output:=x', '-p', 'topics:=[haptic/lmi/update]'], KNOWN,
                    'recorder')


def test_settings_are_frozen_and_normalised() -> None:
    s = DeviceDriverSettings(wrench_limit=[10, 10.0, 1.0])   # type: ignore[arg-type]
    assert s.wrench_limit == (10.0, 10.0, 1.0)
    assert isinstance(s.wrench_limit[0], float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.rate_hz = 500.0  # type: ignore[misc]
    assert LmiControllerSettings(k_tc=3).k_tc == 3.0


@pytest.mark.parametrize(('make', 'expected'), [
    (lambda: DeviceDriverSettings(rate_hz=5.0),
     'device_driver: parameter rate_hz: expected 0.0 (1/scenario dt) or a value in [10, 10000] '
     'Hz, got 5.0'),
    (lambda: DeviceDriverSettings(rate_hz=20000.0),
     'device_driver: parameter rate_hz: expected a value in [0, 10000], got 20000.0'),
    (lambda: DeviceDriverSettings(clock='sim'),
     "device_driver: parameter clock: expected one of wall, lockstep, got 'sim'"),
    (lambda: DeviceDriverSettings(backend_options='[1, 2]'),
     "device_driver: parameter backend_options: expected a mapping, got '[1, 2]'"),
    (lambda: DeviceDriverSettings(backend_options='{a: [1'),
     'device_driver: parameter backend_options: not YAML'),
    (lambda: DeviceDriverSettings(lockstep_warn_after=0.0),
     'device_driver: parameter lockstep_warn_after: expected a value in [0.1, 600], got 0.0'),
    (lambda: LmiControllerSettings(stale_after=0.5, degrade_after=0.1),
     'lmi_controller: parameters: degrade_after (0.1 s) must be >= stale_after (0.5 s)'),
    (lambda: LmiControllerSettings(k_tc=-1.0),
     'lmi_controller: parameter k_tc: expected a value in [0, 100000], got -1.0'),
    (lambda: LmiControllerSettings(b_tc=float('nan')),
     'lmi_controller: parameter b_tc: expected a finite number, got nan'),
    (lambda: LmiControllerSettings(mode='sideways'),
     "lmi_controller: parameter mode: expected one of penalty, acceleration_only, got "
     "'sideways'"),
    (lambda: LmiControllerSettings(max_dt=1),
     None),
    (lambda: DeviceDriverSettings(rate_hz=None),  # type: ignore[arg-type]
     'device_driver: parameter rate_hz: expected a double, got NoneType None'),
    (lambda: VeSimSettings(update_period=1.5),  # type: ignore[arg-type]
     've_sim: parameter update_period: expected an integer, got double 1.5'),
    (lambda: RecorderSettings(topic_regex='(('),
     'recorder: parameter topic_regex: missing ), unterminated subpattern'),
    (lambda: RecorderSettings(compression='gzip'),
     "recorder: parameter compression: expected one of zstd, lz4, none, got 'gzip'"),
    (lambda: DeviceDriverSettings(sched_policy='idle'),
     "device_driver: parameter sched_policy: expected one of other, batch, got 'idle'"),
    (lambda: VeSimSettings(sched_policy='idle'),
     None),
    (lambda: RecorderSettings(sched_policy='fifo'),
     "recorder: parameter sched_policy: expected one of other, batch, idle, got 'fifo'"),
    (lambda: DeviceDriverSettings(cpu_affinity=(_CPUS,)),
     f'device_driver: parameter cpu_affinity: expected [-1] (no pinning) or CPU numbers in '
     f'[0, {_CPUS - 1}], got [{_CPUS}]'),
    (lambda: DeviceDriverSettings(node_cpu_affinity=(-2,)),
     f'device_driver: parameter node_cpu_affinity: expected [-1] (no pinning) or CPU numbers '
     f'in [0, {_CPUS - 1}], got [-2]'),
    (lambda: VeSimSettings(cpu_affinity=()),
     've_sim: parameter cpu_affinity: expected an integer array, got empty array []'),
    (lambda: RecorderSettings(cpu_affinity=(0, -1)),
     f'recorder: parameter cpu_affinity: expected [-1] (no pinning) or CPU numbers in '
     f'[0, {_CPUS - 1}], got [0, -1]'),
    (lambda: FoxgloveBridgeSettings(cpu_affinity=('0',)),  # type: ignore[arg-type]
     "foxglove_bridge: parameter cpu_affinity: expected"),
    (lambda: RecorderSettings(cpu_affinity=(0,)),
     None),
    (lambda: RecorderSettings.from_values({'outptu': 'x'}),
     'recorder: unknown parameter outptu (expected one of: chunk_kib, clock, compression,'),
])
def test_values_are_checked_at_construction(make: Any, expected: str | None) -> None:
    if expected is None:
        make()
        return
    with pytest.raises(ConfigError) as err:
        make()
    assert str(err.value).startswith(expected), err.value


@pytest.mark.parametrize(('settings', 'expected'), [
    (DeviceDriverSettings(wrench_limit=(10.0, 10.0)),
     'device_driver: parameter wrench_limit: expected 3 positive numbers, got [10.0, 10.0]'),
    (DeviceDriverSettings(wrench_limit=(10.0, 0.0, 1.0)),
     'device_driver: parameter wrench_limit: expected 3 positive numbers, got '
     '[10.0, 0.0, 1.0]'),
    (DeviceDriverSettings(watchdog_damping=(-1.0,)),
     'device_driver: parameter watchdog_damping: expected one or 3 numbers >= 0, got [-1.0]'),
    (DeviceDriverSettings(watchdog_damping=(1.0, 1.0)),
     'device_driver: parameter watchdog_damping: expected one or 3 numbers >= 0, got '
     '[1.0, 1.0]'),
    (DeviceDriverSettings(clock='lockstep', rate_hz=500.0),
     'device_driver: parameter rate_hz: clock lockstep needs 0.0 or 1/dt = 1000 Hz (scenario '
     'fig8, dt 0.001 s), got 500.0'),
])
def test_device_resolution_errors_name_parameter_and_expectation(
        fig8: Scenario, settings: DeviceDriverSettings, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        resolve_device_driver(settings, fig8)
    assert str(err.value) == expected


def test_device_resolution(fig8: Scenario) -> None:
    cfg = resolve_device_driver(DeviceDriverSettings(), fig8)
    assert cfg.clock is Clock.WALL and cfg.rate_hz == pytest.approx(1000.0)
    assert cfg.period == fig8.dt and cfg.period_ns == 1_000_000
    np.testing.assert_array_equal(cfg.wrench_limit, fig8.device.wrench_limit)
    assert cfg.watchdog.fallback is WatchdogFallback.ZERO
    np.testing.assert_array_equal(cfg.watchdog.damping, np.zeros(3))
    assert cfg.backend == 'sim_maglev' and cfg.backend_options == {}
    cfg = resolve_device_driver(DeviceDriverSettings(
        rate_hz=500.0, wrench_limit=(5.0, 5.0, 0.5), watchdog_fallback='damping',
        watchdog_damping=(2.0,), backend_options='{port: /dev/ttyUSB0}'), fig8)
    assert (cfg.rate_hz, cfg.period, cfg.period_ns) == (500.0, 0.002, 2_000_000)
    assert cfg.wrench_limit.tolist() == [5.0, 5.0, 0.5]
    assert cfg.watchdog.damping.tolist() == [2.0, 2.0, 2.0]
    assert cfg.backend_options == {'port': '/dev/ttyUSB0'}
    cfg = resolve_device_driver(DeviceDriverSettings(clock='lockstep', rate_hz=1000.0), fig8)
    assert cfg.clock is Clock.LOCKSTEP and cfg.period_ns == 1_000_000
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.rate_hz = 1.0  # type: ignore[misc]


def test_controller_defaults_come_from_the_scenario(fig8: Scenario) -> None:
    assert scenario_defaults(LmiControllerSettings, fig8) == {
        'mode': fig8.mode.label, 'k_tc': 200.0, 'b_tc': 50.0}
    assert scenario_defaults(DeviceDriverSettings, fig8) == {}
    cfg = resolve_lmi_controller(LmiControllerSettings(), fig8)
    assert cfg.mode is fig8.mode
    assert (cfg.gains.k_tc, cfg.gains.b_tc) == (200.0, 50.0)
    np.testing.assert_array_equal(cfg.gains.k_pc, fig8.gains.k_pc)
    assert cfg.guard.degrade_after == 0.6 and cfg.guard.ramp_time == 0.2
    assert cfg.cycle_time == fig8.dt and cfg.lockstep_wait == 60.0 and cfg.clock is Clock.WALL
    cfg = resolve_lmi_controller(LmiControllerSettings(
        mode='acceleration_only', k_tc=10.0, b_tc=7.0), fig8)
    assert cfg.mode is ControlMode.ACCELERATION_ONLY
    assert (cfg.gains.k_tc, cfg.gains.b_tc) == (10.0, 7.0)


def test_a_bad_gain_is_refused(fig8: Scenario) -> None:
    big = dataclasses.replace(fig8, gains=fig8.gains.with_penalty(2e5, 50.0))
    with pytest.raises(ConfigError, match=r'^lmi_controller: parameter k_tc must be <= 100000, '
                       r'got 200000\.0$'):
        resolve_lmi_controller(LmiControllerSettings(), big)
    assert check_live('k_tc', -1.0) == ('k_tc must be >= 0 (a negative penalty pushes off the '
                                        'manifold), got -1.0')
    assert check_live('b_tc', 'x') == "b_tc must be a number, got 'x'"
    assert check_live('mode', 'sideways') == ("mode must be one of penalty, "
                                              "acceleration_only, got 'sideways'")
    assert check_live('mode', 'penalty') is None and check_live('k_tc', 1.0) is None


def test_ve_update_period_zero_is_the_scenarios(fig8: Scenario) -> None:
    assert resolve_ve_sim(VeSimSettings(), fig8).update_period == fig8.update_period == 10
    fig6 = load_scenario('fig6')
    assert resolve_ve_sim(VeSimSettings(), fig6).update_period == 1
    cfg = resolve_ve_sim(VeSimSettings(update_period=5, viz_rate_hz=20.0), fig6)
    assert cfg.update_period == 5 and cfg.viz_period == 0.05
    assert resolve_ve_sim(VeSimSettings(clock='lockstep'), fig6).clock is Clock.LOCKSTEP


def test_recorder_resolution(tmp_path: Path) -> None:
    recorded = ['haptic/device/state', 'haptic/lmi/update', '/diagnostics']
    cfg = resolve_recorder(RecorderSettings(scenario='/x/fig6.yaml'), recorded)
    assert cfg.topics == tuple(recorded) and cfg.scenario_name == 'fig6'
    assert cfg.path.parent == Path('bags') and cfg.path.name.startswith('fig6_')
    assert cfg.chunk_size == 64 * 1024
    cfg = resolve_recorder(RecorderSettings(output=str(tmp_path / 'b'),
                                            topics=('/haptic/lmi/update',),
                                            topic_regex='diag'), recorded)
    assert cfg.topics == ('haptic/lmi/update', '/diagnostics') and cfg.path == tmp_path / 'b'
    with pytest.raises(ConfigError, match='recorder: parameter topics: unknown nope; known:'):
        resolve_recorder(RecorderSettings(topics=('nope',)), recorded)


def test_scenario_blocks_keep_their_attributes(fig8: Scenario) -> None:
    assert fig8.lmi.model is fig8.lmi_model and fig8.lmi.update_period == fig8.update_period
    assert fig8.ve.internal_step == fig8.internal_step
    assert fig8.ve.vt_coupling is fig8.vt_coupling
    assert dataclasses.replace(fig8, update_period=3).lmi.update_period == 3


def test_declare_settings_declares_every_field_on_a_node(fig8: Scenario) -> None:
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter

    from haptic_topology.nodes.parameters import declare_settings, declare_spec

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node('lmi_controller', context=ctx, parameter_overrides=[
            Parameter('k_tc', value=30.0)])
        try:
            name = declare_spec(node, param_specs(LmiControllerSettings)['scenario'])
            sc = load_scenario(name)
            settings = declare_settings(node, LmiControllerSettings,
                                               scenario_defaults(LmiControllerSettings, sc))
            assert (settings.mode, settings.k_tc, settings.b_tc) == (sc.mode.label, 30.0, 50.0)
            assert settings.lockstep_wait == 60.0
            desc = node.describe_parameter('k_tc')
            assert not desc.read_only and desc.floating_point_range[0].to_value == 1e5
            assert node.describe_parameter('stale_after').read_only
        finally:
            node.destroy_node()
        node = rclpy.create_node('device_driver', context=ctx, parameter_overrides=[
            Parameter('rate_hz', value=5.0)])
        try:
            with pytest.raises(ConfigError, match=r'^device_driver: parameter rate_hz: '
                               r'expected 0\.0 \(1/scenario dt\) or a value in \[10, 10000\]'):
                declare_settings(node, DeviceDriverSettings)
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
