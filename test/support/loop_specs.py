"""The :class:`~haptic_topology.device.loop_process.LoopSpec` fields of a scenario as
``simulate`` runs it (the simulated maglev with the scenario's user, default watchdog)."""

from __future__ import annotations

from typing import Any

from haptic_topology.device.backend import BackendConfig
from haptic_topology.device.loop import TAKEOVER_AFTER
from haptic_topology.device.runner import RunnerConfig
from haptic_topology.device.watchdog import WatchdogConfig
from haptic_topology.sim.lockstep import build_controller_loop, initial_device_pose
from haptic_topology.sim.scenario import load_scenario


def spec_for(name: str, lockstep: bool, duration: float) -> tuple[dict[str, Any], int, int]:
    """``(spec fields, task dim, dof)`` of scenario ``name`` in its own mode."""
    sc = load_scenario(name)
    spec = dict(
        backend='sim_maglev',
        backend_config=BackendConfig(sc.device, initial_device_pose(sc), dict(sc.user), {},
                                     sc.source),
        limit=sc.device.wrench_limit, watchdog=WatchdogConfig(), period=sc.dt,
        takeover_after=TAKEOVER_AFTER,
        controller=build_controller_loop(sc, sc.mode,
                                         update_period=sc.update_period if lockstep else None),
        runner=RunnerConfig(sc.dt, lockstep, duration, 60.0),
        sched_priority=0, cpu_affinity=(-1,), lock_memory=False, sched_slice_us=100.0,
        timer_slack_ns=0)
    return spec, sc.linkage.task.dim, sc.linkage.dof
