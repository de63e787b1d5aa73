"""Offline lock-step simulation of the haptic loop, scenarios, traces and plots."""

from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.sim.trace import Trace, format_summary
from haptic_topology.sim.ve import VirtualEnvironment

__all__ = ['Scenario', 'Trace', 'VirtualEnvironment', 'format_summary', 'load_scenario',
           'simulate']
