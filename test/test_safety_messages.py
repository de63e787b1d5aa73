"""Bad messages are rejected where they enter (``convert``), with a reason the nodes count."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.nodes.convert import (
    MessageError,
    RejectCounter,
    command_from_msg,
    lmi_from_msg,
    lmi_msg,
    seconds_to_stamp,
    state_from_msg,
    vt_wrench_from_hand,
)
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInput, LmiUpdate

SC = load_scenario('fig8')
TASK = SC.linkage.task
DOF = SC.linkage.dof


def _snapshot() -> LmiSnapshot:
    dyn = LinkageDynamics(SC.linkage)
    return LmiSnapshot.from_dynamics(dyn.snapshot(SC.q0, SC.dq0), TASK,
                                     SC.linkage.constraints.characteristic_length, 3, 7)


def _update(**fields: Any) -> LmiUpdate:
    msg = lmi_msg(LmiUpdate(), _snapshot(), seconds_to_stamp(1.0))
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def _state(**fields: Any) -> DeviceState:
    msg = DeviceState(seq=5, task_dim=3, pose=[0.1, 0.0, 0.0], twist=[0.0] * 3,
                      hand_wrench=[0.4, 0.0, 0.0], applied_wrench=[0.0] * 3)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def _command(**fields: Any) -> DeviceCommand:
    msg = DeviceCommand(state_seq=5, task_dim=3, wrench=[1.0, 0.0, 0.0], mode=0)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def _hand(**fields: Any) -> HandInput:
    msg = HandInput(seq=1, state_seq=5, task_dim=3, pose=[0.0] * 3, twist=[0.0] * 3,
                    hand_wrench=[0.4, 0.0, 0.0], coupling_wrench=[0.0] * 3)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def test_good_messages_pass() -> None:
    snap = lmi_from_msg(_update(), TASK, DOF)
    np.testing.assert_allclose(snap.mass_matrix, _snapshot().mass_matrix)
    assert state_from_msg(_state(), TASK)[0] == 5
    assert command_from_msg(_command(), TASK)[0] == 5
    assert vt_wrench_from_hand(_hand(), TASK, True, 100.0)[0] == 5


def _spd_broken() -> list[float]:
    m = np.array(_snapshot().mass_matrix)
    m[0, 0] = -1.0
    return m.ravel().tolist()


def _weights_out() -> list[float]:
    return [0.0, 2.0, 0.0]


CASES: list[tuple[str, Callable[[], Any], str, str]] = [
    ('lmi', lambda: _update(dof=4), 'dof', 'LmiUpdate.dof must be 3, got 4'),
    ('lmi', lambda: _update(task_dim=6), 'task_dim', 'LmiUpdate.task_dim must be 3, got 6'),
    ('lmi', lambda: _update(q=[0.0, 0.0]), 'size', 'LmiUpdate.q must have 3 entries, got 2'),
    ('lmi', lambda: _update(dq=[0.0, math.nan, 0.0]), 'non_finite', 'LmiUpdate.dq has non-fin'),
    ('lmi', lambda: _update(characteristic_length=math.inf), 'non_finite',
     'characteristic_length is not finite'),
    ('lmi', lambda: _update(mass_matrix=_spd_broken()), 'range', 'mass_matrix must be'),
    ('lmi', lambda: _update(constraint_weights=_weights_out()), 'range', 'in [0, 1]'),
    ('lmi', lambda: _update(constraint_count=4), 'range', 'constraint_count must be <= 3'),
    ('state', lambda: _state(pose=[math.inf, 0.0, 0.0]), 'non_finite', 'DeviceState.pose'),
    ('state', lambda: _state(twist=[0.0] * 6), 'size', 'DeviceState.twist must have 3'),
    ('state', lambda: _state(task_dim=6), 'task_dim', 'DeviceState.task_dim must be 3'),
    ('state', lambda: _state(seq=0), 'range', 'DeviceState.seq must be >= 1'),
    ('command', lambda: _command(wrench=[math.nan, 0.0, 0.0]), 'non_finite',
     'DeviceCommand.wrench has non-finite'),
    ('command', lambda: _command(wrench=[1.0]), 'size', 'DeviceCommand.wrench must have 3'),
    ('command', lambda: _command(mode=7), 'range', 'DeviceCommand.mode must be one of'),
    ('hand', lambda: _hand(hand_wrench=[1e6, 0.0, 0.0]), 'range', 'hand_wrench must be within'),
    ('hand', lambda: _hand(coupling_wrench=[0.0, -math.inf, 0.0]), 'non_finite',
     'HandInput.coupling_wrench'),
    ('hand', lambda: _hand(pose=[0.0, 0.0]), 'size', 'HandInput.pose must have 3'),
]


@pytest.mark.parametrize(('kind', 'make', 'reason', 'text'), CASES)
def test_bad_message_rejected_with_reason(kind: str, make: Callable[[], Any], reason: str,
                                          text: str) -> None:
    convert: dict[str, Callable[[Any], Any]] = {
        'lmi': lambda m: lmi_from_msg(m, TASK, DOF),
        'state': lambda m: state_from_msg(m, TASK),
        'command': lambda m: command_from_msg(m, TASK),
        'hand': lambda m: vt_wrench_from_hand(m, TASK, True, 100.0),
    }
    with pytest.raises(MessageError) as err:
        convert[kind](make())
    assert err.value.reason == reason
    assert text in str(err.value)
    counter = RejectCounter()
    counter.add(err.value)
    assert counter.values()[f'rejected_{reason}'] == '1' and counter.total == 1


def test_finite_command_beyond_the_limit_is_clamped_not_rejected() -> None:
    """A large finite wrench is the device's job (saturate, status SATURATED)."""
    assert command_from_msg(_command(wrench=[1e9, -1e9, 0.0]), TASK)[2][0] == 1e9
