"""Device faults at the core (no ROS): a backend that reports ``DeviceStatus.FAULT`` gets zero
wrench written from the next cycle on, its states carry ``STATUS_FAULT``, the device side's
diagnostics are at ERROR with the backend's reason, and ``hardware_id`` names the backend and
its device. After the fault the output fades back in over the watchdog ramp."""

from __future__ import annotations

import numpy as np
import pytest
from fake_backend import CircleBackend, FaultBackend

from haptic_topology.device.backend import (
    BackendConfig,
    DeviceBackend,
    SimMaglevBackend,
)
from haptic_topology.device.loop import CommandVerdict, DeviceLoop, device_report, hardware_id
from haptic_topology.device.watchdog import CommandWatchdog, WatchdogConfig
from haptic_topology.messages.check import STATUS_BITS
from haptic_topology.messages.definitions import typestore_with_haptic_msgs
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode, DeviceStatus, TaskSpace

PENALTY = int(ControlMode.PENALTY)
FAULT = DeviceStatus.FAULT
REASON = 'amplifier over-temperature on axis 2'


def _configured(backend: DeviceBackend, scenario: str = 'fig8') -> DeviceBackend:
    sc = load_scenario(scenario)
    backend.configure(BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {},
                                    sc.source))
    return backend


def _loop(scenario: str = 'fig8') -> tuple[DeviceLoop, FaultBackend]:
    """A device loop on the fault double (fig8: planar, limit 20 N, 20 N, 2 N m, 1 ms, watchdog
    ramp 50 ms), activated, not engaged."""
    sc = load_scenario(scenario)
    backend = FaultBackend()
    _configured(backend, scenario)
    backend.activate()
    loop = DeviceLoop(backend, sc.device.wrench_limit,
                      CommandWatchdog(WatchdogConfig(), sc.linkage.task.dim), sc.dt)
    return loop, backend


def _engage(loop: DeviceLoop) -> float:
    """Idle state, its answer engages, the resting state; returns the time (s) of the last."""
    dt = loop.period
    tick = loop.tick(0.0, dt)
    assert loop.on_command(tick.seq, PENALTY, np.zeros(3), 0.0) == CommandVerdict.APPLIED
    loop.tick(dt, dt)
    assert loop.engaged and loop.run_index == 0
    return dt


def test_fault_zeroes_the_output_flags_the_states_and_reports_error() -> None:
    """Answered every cycle with ``u``: ``u`` is written until the reading that first carries
    FAULT (it was written before that read), then zero for as long as the backend reports the
    fault, whatever the commands say; the states carry FAULT (and WATCHDOG: the output is not
    the command), diagnostics are at ERROR with the backend's reason and unit; once the fault
    clears the output fades back to ``u`` at the watchdog's rate (1 ms / 50 ms of ``u`` per
    cycle) and the level goes back through WARN to OK."""
    loop, be = _loop()
    t = _engage(loop)
    dt = loop.period
    u = np.array([1.5, -0.8, 0.05])
    env = np.array([0.1, 0.0, 0.0])

    def cycle() -> tuple[np.ndarray, DeviceStatus, np.ndarray | None]:
        nonlocal t
        assert loop.on_command(loop.seq, PENALTY, u, t, env_wrench=env) == 'applied'
        t += dt
        n = len(be.writes)
        tick = loop.tick(t, dt)
        assert len(be.writes) == n + 1
        np.testing.assert_array_equal(tick.applied, be.writes[-1])
        return be.writes[-1], tick.status, tick.env_wrench

    for _ in range(10):
        written, status, _ = cycle()
        np.testing.assert_array_equal(written, u)
        assert status == DeviceStatus.OK
    assert loop.health() == (0, 'ok')

    be.fault = REASON
    written, status, _ = cycle()              # the read after this write reports the fault
    np.testing.assert_array_equal(written, u)
    assert status & FAULT and loop.fault_active
    assert loop.health() == (2, f'device fault: {REASON}')

    n_fault = 40
    for _ in range(n_fault):
        written, status, env_out = cycle()
        np.testing.assert_array_equal(written, np.zeros(3))
        assert status & FAULT and status & DeviceStatus.WATCHDOG
        assert env_out is None                 # no command applied, so no F_env applied
    level, message, values = device_report(loop, t, '', 0, {})
    assert (level, message) == (2, f'device fault: {REASON}')
    assert values['device_fault'] == REASON
    assert (values['device_faults'], values['fault_cycles']) == ('1', str(n_fault))
    assert hardware_id(be, 'fake_backend:FaultBackend') == 'fault_test_double unit 7'

    be.fault = ''
    written, status, _ = cycle()              # written while the last reading still faulted
    np.testing.assert_array_equal(written, np.zeros(3))
    assert not status & FAULT and not loop.fault_active
    assert loop.health() == (1, 'watchdog: fading back in')
    ramp = WatchdogConfig().ramp_time
    fade = [cycle()[0] for _ in range(int(round(ramp / dt)) + 5)]
    np.testing.assert_allclose(fade[0], u * dt / ramp, rtol=1e-12)
    steps = np.abs(np.diff(np.array([np.zeros(3), *fade]), axis=0))
    assert np.all(steps <= np.abs(u) * dt / ramp * (1.0 + 1e-9))
    np.testing.assert_array_equal(fade[-1], u)
    assert loop.health() == (0, 'ok')
    assert (loop.device_faults, loop.fault_cycles) == (1, n_fault + 1)
    assert device_report(loop, t, '', 0, {})[2]['device_fault'] == ''


def test_fault_before_engagement_is_an_error_and_the_state_is_flagged() -> None:
    """A device that reports a fault while idle: the idle state carries FAULT with IDLE, the
    level is ERROR (not the idle WARN), and nothing but zero is applied."""
    loop, be = _loop()
    be.fault = REASON
    tick = loop.tick(0.0, loop.period)
    assert tick.status == DeviceStatus.IDLE | DeviceStatus.WATCHDOG | FAULT
    np.testing.assert_array_equal(tick.applied, np.zeros(3))
    assert device_report(loop, 0.0, '', 0, {})[:2] == (2, f'device fault: {REASON}')
    be.fault = ''
    loop.tick(loop.period, loop.period)
    assert loop.health() == (1, 'idle: no controller engaged yet')


def test_no_force_ever_follows_a_faulted_reading() -> None:
    """2000 cycles with the fault switching on and off at random, random commands (up to
    twice the limit) and missed answers: every wrench written after a reading that carried
    FAULT is exactly zero, every state carries FAULT exactly when its reading did, and every
    wrench is within the limit."""
    loop, be = _loop()
    t = _engage(loop)
    dt = loop.period
    rng = np.random.default_rng(14)
    limit = loop.limit
    faulted_before = False
    zero_writes = 0
    for _ in range(2000):
        if rng.random() < 0.05:
            be.fault = '' if be.fault else REASON
        if rng.random() < 0.9:
            loop.on_command(loop.seq, PENALTY, rng.uniform(-2.0, 2.0, 3) * limit, t)
        t += dt
        reported = bool(be.fault)
        n = len(be.writes)
        tick = loop.tick(t, dt)
        assert len(be.writes) == n + 1
        written = be.writes[-1]
        if faulted_before:
            np.testing.assert_array_equal(written, np.zeros(3))
            zero_writes += 1
        assert np.all(np.abs(written) <= limit)
        assert bool(tick.status & FAULT) == reported
        faulted_before = reported
    assert zero_writes == loop.fault_cycles > 100
    assert loop.device_faults > 10


def test_hardware_id_names_backend_and_device() -> None:
    """The default ``hardware_id`` is the backend's name and its task space once configured,
    the name alone before; a backend may name its unit; before a backend exists the driver
    reports the ``backend`` parameter."""
    assert SimMaglevBackend().hardware_id == 'sim_maglev'
    assert _configured(SimMaglevBackend()).hardware_id == 'sim_maglev planar'
    assert _configured(SimMaglevBackend(), 'spatial_arm4').hardware_id == 'sim_maglev spatial'
    backend = _configured(SimMaglevBackend())
    assert hardware_id(backend, 'ignored') == 'sim_maglev planar'
    assert hardware_id(None, 'my_pkg.dev:Dev') == 'my_pkg.dev:Dev'
    assert SimMaglevBackend().fault_reason() == 'sim_maglev: the device reports a fault'


@pytest.mark.parametrize('scenario,task', [('fig8', 'planar'), ('spatial_arm4', 'spatial'),
                                           ('fig8_point', 'planar_point'),
                                           ('spatial_arm4_point', 'spatial_point')])
def test_hardware_id_names_the_declared_task_not_a_guess_from_m(scenario: str,
                                                                 task: str) -> None:
    """m = 3 is planar or spatial_point: the default ``hardware_id`` names the task the
    backend says it was configured for (:meth:`DeviceBackend.task`); a backend that keeps
    only m is named by m where one task has it (2 planar_point, 6 spatial), else ``3-dof``,
    never ``planar`` for a spatial_point device."""
    class Declaring(CircleBackend):
        def configure(self, config: BackendConfig) -> None:
            super().configure(config)
            self.declared = config.params.task

        def task(self) -> TaskSpace | None:
            return self.declared

    assert _configured(SimMaglevBackend(), scenario).hardware_id == f'sim_maglev {task}'
    assert _configured(Declaring(), scenario).hardware_id == f'circle_test_double {task}'
    by_m = {'planar': '3-dof', 'spatial_point': '3-dof'}.get(task, task)
    assert _configured(CircleBackend(), scenario).hardware_id == f'circle_test_double {by_m}'


def test_fault_bit_is_the_message_constant_and_a_valid_status() -> None:
    """``DeviceStatus.FAULT`` is ``DeviceState.STATUS_FAULT`` of the .msg, and the message
    checks accept it."""
    msg = typestore_with_haptic_msgs().types['haptic_topology_msgs/msg/DeviceState']
    assert int(FAULT) == msg.STATUS_FAULT == 8
    assert STATUS_BITS & msg.STATUS_FAULT
