"""A lock-step graph run's trace against ``simulate()`` of the same scenario, mode and
duration (the graph tests' exact check)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.sim.trace import Trace
from haptic_topology.vocabulary import ControlMode

EXACT_COLUMNS = ('device_pose', 'device_twist', 'hand_wrench', 'command', 'applied',
                 'vt_pose', 'lmi_pose')


def assert_equals_offline(graph: Trace, scenario: str, mode: str, duration: float,
                          offline: Trace | None = None) -> None:
    """``graph`` (a lock-step run's trace) equals ``simulate()`` of the same scenario, mode
    and duration (``offline``: that run, made already): same rows and times, the exact
    columns to 1e-9 at every cycle, the drift summary to 1e-9 relative."""
    sc = load_scenario(scenario)
    if offline is None:
        offline = simulate(replace(sc, duration=duration), ControlMode.parse(mode))
    assert len(graph) == len(offline) == round(duration / sc.dt) + 1
    if scenario in ('fig6', 'fig8'):        # the run crosses the LMI's rank switch
        assert np.any(np.diff(offline.columns['lmi_constraint_count']))
    np.testing.assert_array_equal(graph.seq - graph.seq[0], np.arange(len(graph)))
    np.testing.assert_allclose(graph.t, offline.t, rtol=0.0, atol=1e-12)
    for col in EXACT_COLUMNS:
        np.testing.assert_allclose(graph.columns[col], offline.columns[col], rtol=0.0,
                                   atol=1e-9, err_msg=col)
    # The VE's constraint count as its updates report it, held to the next: both alike.
    np.testing.assert_array_equal(graph.columns['constraint_count'],
                                  offline.columns['constraint_count'])
    g, o = graph.summary(), offline.summary()
    assert g['constrained_time_s'] == o['constrained_time_s']
    for key in ('final_distance_m', 'max_distance_m', 'rms_distance_m'):
        assert g[key] == pytest.approx(o[key], rel=1e-9, abs=0.0), key
    assert graph.has_contacts == offline.has_contacts
    if offline.has_contacts:
        # F_env as the controller rendered it (DeviceCommand.env_wrench) at every cycle; the
        # VE's deepest contact and contact energy as each LmiUpdate reported them, held to
        # the next update, as the offline trace samples them: every row, and the summary.
        assert np.abs(offline.columns['env_wrench']).max() > 0.1
        np.testing.assert_allclose(graph.columns['env_wrench'], offline.columns['env_wrench'],
                                   rtol=0.0, atol=1e-9)
        assert np.count_nonzero(np.diff(offline.columns['contact_energy'])) > 10
        for col in ('penetration', 'contact_energy'):
            np.testing.assert_allclose(graph.columns[col], offline.columns[col],
                                       rtol=0.0, atol=1e-12, err_msg=col)
        for key in ('max_penetration_m', 'rms_penetration_m', 'contact_time_s',
                    'energy_dissipated_j'):
            assert g[key] == pytest.approx(o[key], rel=1e-9, abs=1e-15), key
        assert g['energy_injected_j'] == o['energy_injected_j'] == 0.0
