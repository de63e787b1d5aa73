"""The controller's energy account of a recorded run (haptic_topology.bag.analyze
.controller_account): read from the controller's last /diagnostics status, exact, and only
when that status was sent after the run's last state."""

from __future__ import annotations

import numpy as np

from haptic_topology.bag.analyze import controller_account
from haptic_topology.bag.graph_index import CONTROLLER_STATUS, DEVICE_STATUS
from haptic_topology.control.passivity import EnergyAccount, PassivityConfig


def _account() -> EnergyAccount:
    """An account with figures that do not print short (1/3 J of work and so on)."""
    from haptic_topology.control.energy import account as step

    acct = EnergyAccount(2, PassivityConfig(enabled=True, window=0.0), 1e-3, np.eye(2))
    zero, ml, c_d = np.zeros(2), np.eye(2), np.zeros((2, 2))
    for j in range(4):
        u = np.array([1.0 / 3.0, -2.0 / 7.0])
        step(0, 0, ml, c_d, np.array([0.01 * j / 3.0, 0.0]), np.array([10.0 / 3.0, 0.1]),
             zero, zero, zero, zero, u, 1e-3, acct.state)
    return acct


def test_the_last_status_after_the_last_state_gives_the_account_exactly() -> None:
    acct = _account()
    values = acct.values()
    diagnostics = {CONTROLLER_STATUS: dict(values, last_state_seq='42'),
                   DEVICE_STATUS: {'seq': '42', 'loop_running': 'false'}}
    assert controller_account(diagnostics) == acct.summary()
    assert acct.summary()['passivity_cycles'] > 0


def test_a_status_sent_while_the_run_went_on_gives_none() -> None:
    values = _account().values()
    for ctl_seq, dev in (('41', {'seq': '42', 'loop_running': 'false'}),
                         ('42', {'seq': '42', 'loop_running': 'true'}),
                         ('42', {})):
        assert controller_account({CONTROLLER_STATUS: dict(values, last_state_seq=ctl_seq),
                                   DEVICE_STATUS: dev}) is None
    assert controller_account({DEVICE_STATUS: {'seq': '1', 'loop_running': 'false'}}) is None
