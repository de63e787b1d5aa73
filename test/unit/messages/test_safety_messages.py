"""Bad messages are rejected where they enter (``convert``), with a reason the nodes count."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.linkage_dynamics import LinkageDynamics
from haptic_topology.messages import check
from haptic_topology.messages.check import MAX_SEQ, check_vt_path
from haptic_topology.nodes.convert import (
    MessageError,
    RejectCounter,
    command_from_msg,
    lmi_from_msg,
    lmi_msg,
    seconds_to_stamp,
    state_from_msg,
    vt_wrenches_from_hand_inputs,
)
from haptic_topology.sim.scenario import load_scenario
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate, VtPath

SC = load_scenario('fig8')
#: A controller id (any in [1, 2**63 - 1]).
CID = 12345
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
    msg = DeviceCommand(state_seq=5, controller_id=CID, task_dim=3, wrench=[1.0, 0.0, 0.0],
                        mode=0, vt_pose=[0.0] * 3, vt_twist=[0.0] * 3)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def _hand(**fields: Any) -> HandInputs:
    """A batch of two samples (seq 1, 2 of states 5, 6); ``fields`` replace its fields."""
    msg = HandInputs(task_dim=3, seq=[1, 2], state_seq=[5, 6],
                     stamp=[Time(sec=0, nanosec=5_000_000), Time(sec=0, nanosec=6_000_000)],
                     pose=[0.0] * 6, twist=[0.0] * 6, hand_wrench=[0.4, 0.0, 0.0, 0.5, 0.0, 0.0],
                     coupling_wrench=[0.0] * 6)
    msg.header.stamp = Time(sec=0, nanosec=6_000_000)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def _hand_inputs(m: Any) -> Any:
    return vt_wrenches_from_hand_inputs(m, TASK, True, 100.0)


def test_good_messages_pass() -> None:
    snap = lmi_from_msg(_update(), TASK, DOF)
    np.testing.assert_allclose(snap.mass_matrix, _snapshot().mass_matrix)
    assert state_from_msg(_state(), TASK)[0] == 5
    assert command_from_msg(_command(), TASK)[0] == 5
    assert command_from_msg(_command(), TASK)[3] == CID
    assert _hand_inputs(_hand())[1] == [5, 6]


def test_controller_ids_drawn_in_range_and_written_into_commands() -> None:
    """Every process draws its own random id in [1, 2**63 - 1]; ``command_msg`` writes it."""
    from haptic_topology.control.controller import CycleOutput
    from haptic_topology.messages.check import MAX_CONTROLLER_ID, new_controller_id
    from haptic_topology.nodes.convert import CONTROLLER_ID, command_msg
    from haptic_topology.vocabulary import ControlMode

    ids = {new_controller_id() for _ in range(1000)}
    assert len(ids) == 1000 and all(1 <= i <= MAX_CONTROLLER_ID for i in ids)
    assert 1 <= CONTROLLER_ID <= MAX_CONTROLLER_ID == 2 ** 63 - 1
    v = np.zeros(3)
    out = CycleOutput(wrench=np.array([1.0, 0.0, 0.0]), coupling=v, vt_wrench=v, vt_pose=v,
                      vt_twist=v, constraint_count=0, mode=ControlMode.PENALTY)
    msg = command_msg(DeviceCommand(), 5, Time(), out, 0.0)
    assert command_from_msg(msg, TASK)[3] == CONTROLLER_ID
    assert command_msg(DeviceCommand(), 5, Time(), out, 0.0, 77).controller_id == 77


def _spd_broken() -> list[float]:
    m = np.array(_snapshot().mass_matrix)
    m[0, 0] = -1.0
    return m.ravel().tolist()


def _mass_skewed(delta: float) -> list[float]:
    """The mass matrix with entry (0, 1) changed by ``delta`` times its largest entry."""
    m = np.array(_snapshot().mass_matrix)
    m[0, 1] += delta * float(np.abs(m).max())
    return m.ravel().tolist()


def _vectors_scaled(factor: float) -> list[float]:
    return (factor * np.array(_snapshot().left_vectors)).ravel().tolist()


def test_the_lmi_checks_hold_their_tolerances() -> None:
    """Symmetry of D to 1e-9 relative, orthonormality of U to 1e-6 (+ 1e-5 on the diagonal):
    values within pass, values beyond are refused (the CASES below)."""
    lmi_from_msg(_update(mass_matrix=_mass_skewed(5e-10)), TASK, DOF)
    lmi_from_msg(_update(left_singular_vectors=_vectors_scaled(1.0 + 5e-6)), TASK, DOF)


def _weights_out() -> list[float]:
    return [0.0, 2.0, 0.0]


def _contact_update(**fields: Any) -> LmiUpdate:
    """An update of the ``wall`` scenario pressed against its wall (two contacts), then
    ``fields`` replaced."""
    from haptic_topology.sim.lockstep import virtual_environment
    ve = virtual_environment(load_scenario('wall'))
    for _ in range(400):
        ve.integrate(np.array([0.4, 0.0, 0.0]), 1e-3)
    msg = lmi_msg(LmiUpdate(), ve.snapshot(3), seconds_to_stamp(1.0))
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def test_contacts_round_trip_through_lmi_update() -> None:
    from haptic_topology.sim.lockstep import virtual_environment
    ve = virtual_environment(load_scenario('wall'))
    for _ in range(400):
        ve.integrate(np.array([0.4, 0.0, 0.0]), 1e-3)
    snap = ve.snapshot(3)
    assert snap.contacts is not None and len(snap.contacts) >= 1
    back = lmi_from_msg(lmi_msg(LmiUpdate(), snap, seconds_to_stamp(1.0)), TASK, DOF)
    assert back.contacts is not None and back.contacts.params == dataclasses.replace(
        snap.contacts.params, margin=back.contacts.params.margin)
    for name in ('q', 'points', 'normals', 'gaps', 'jacobians'):
        np.testing.assert_array_equal(getattr(back.contacts, name),
                                      getattr(snap.contacts, name), err_msg=name)
    assert back.contacts.local and back.contact_energy == snap.contact_energy
    # A scenario without obstacles: no contacts on either side.
    assert lmi_from_msg(_update(), TASK, DOF).contacts is None


def test_lmi_update_fields_are_the_snapshots_entries_row_major() -> None:
    """``lmi_msg`` hands each array over as one block; the field holds the same doubles in
    row-major order, also from a matrix stored column-major."""
    snap = _snapshot()
    snap = dataclasses.replace(snap, mass_matrix=np.asfortranarray(snap.mass_matrix))
    msg = lmi_msg(LmiUpdate(), snap, seconds_to_stamp(1.0))
    assert list(msg.mass_matrix) == snap.mass_matrix.ravel().tolist()
    assert list(msg.hand_jacobian) == snap.hand_jacobian.ravel().tolist()
    assert list(msg.q) == snap.q.tolist() and list(msg.hand_pose) == snap.hand_pose.tolist()
    np.testing.assert_array_equal(lmi_from_msg(msg, TASK, DOF).mass_matrix, snap.mass_matrix)


CASES: list[tuple[str, Callable[[], Any], str, str]] = [
    ('lmi', lambda: _update(dof=4), 'dof', 'LmiUpdate.dof must be 3, got 4'),
    ('lmi', lambda: _update(task_dim=6), 'task_dim', 'LmiUpdate.task_dim must be 3, got 6'),
    ('lmi', lambda: _update(q=[0.0, 0.0]), 'size', 'LmiUpdate.q must have 3 entries, got 2'),
    ('lmi', lambda: _update(dq=[0.0, math.nan, 0.0]), 'non_finite', 'LmiUpdate.dq has non-fin'),
    ('lmi', lambda: _update(characteristic_length=math.inf), 'non_finite',
     'characteristic_length is not finite'),
    ('lmi', lambda: _update(mass_matrix=_spd_broken()), 'range', 'mass_matrix must be'),
    ('lmi', lambda: _update(constraint_weights=_weights_out()), 'range', 'in [0, 1]'),
    ('lmi', lambda: _update(mass_matrix=_mass_skewed(1e-6)), 'range',
     'LmiUpdate.mass_matrix must be symmetric'),
    ('lmi', lambda: _update(left_singular_vectors=_vectors_scaled(1.001)), 'range',
     'LmiUpdate.left_singular_vectors must be orthonormal'),
    ('lmi', lambda: _update(singular_values=[0.1, -0.2, 0.0]), 'range',
     'LmiUpdate.singular_values must be >= 0, got [0.1, -0.2, 0.0]'),
    ('lmi', lambda: _update(constraint_count=4), 'range',
     'constraint_count must be in [0, 3], got 4'),
    ('lmi', lambda: _contact_update(contact_gaps=[0.0] * 7), 'size',
     'LmiUpdate.contact_gaps must have'),
    ('lmi', lambda: _contact_update(
        contact_normals=[2.0] * len(_contact_update().contact_normals)), 'range',
     'LmiUpdate.contact_normals must be unit vectors'),
    ('lmi', lambda: _contact_update(contact_stiffness=-5.0), 'range',
     'LmiUpdate.contact_stiffness must be >= 0, got -5.0'),
    ('lmi', lambda: _contact_update(contact_slip_velocity=0.0), 'range',
     'LmiUpdate.contact_slip_velocity must be > 0, got 0.0'),
    ('lmi', lambda: _contact_update(contact_friction=math.nan), 'non_finite',
     'LmiUpdate.contact_friction is not finite'),
    ('lmi', lambda: _contact_update(contact_count=10 ** 6), 'range',
     'LmiUpdate.contact_count must be in [0, 4096]'),
    ('lmi', lambda: _update(contact_count=2), 'range',
     'contact_count must be 0 when contact_stiffness is 0, got 2'),
    ('lmi', lambda: _update(contact_normals=[0.0, 0.0, 1.0]), 'size',
     'LmiUpdate.contact_normals must have 0 entries, got 3'),
    ('lmi', lambda: _update(contact_energy=math.nan), 'non_finite',
     'LmiUpdate.contact_energy is not finite'),
    ('lmi', lambda: _contact_update(
        contact_jacobians=[math.inf] * len(_contact_update().contact_jacobians)),
     'non_finite', 'LmiUpdate.contact_jacobians has non-finite'),
    ('command', lambda: _command(env_wrench=[math.nan, 0.0, 0.0]), 'non_finite',
     'DeviceCommand.env_wrench has non-finite'),
    ('command', lambda: _command(env_wrench=[1.0]), 'size',
     'DeviceCommand.env_wrench must have 3'),
    ('state', lambda: _state(pose=[math.inf, 0.0, 0.0]), 'non_finite', 'DeviceState.pose'),
    ('state', lambda: _state(twist=[0.0] * 6), 'size', 'DeviceState.twist must have 3'),
    ('state', lambda: _state(task_dim=6), 'task_dim', 'DeviceState.task_dim must be 3'),
    ('state', lambda: _state(seq=0), 'range', 'DeviceState.seq must be in [1, '),
    ('command', lambda: _command(wrench=[math.nan, 0.0, 0.0]), 'non_finite',
     'DeviceCommand.wrench has non-finite'),
    ('command', lambda: _command(wrench=[1.0]), 'size', 'DeviceCommand.wrench must have 3'),
    ('command', lambda: _command(mode=7), 'range', 'DeviceCommand.mode must be one of'),
    ('hand', lambda: _hand(hand_wrench=[0.0] * 4 + [1e6, 0.0]), 'range',
     'HandInputs.hand_wrench must be within +-100, got [0.0, 1000000.0, 0.0] (sample 1)'),
    ('hand', lambda: _hand(coupling_wrench=[0.0, -math.inf] + [0.0] * 4), 'non_finite',
     'HandInputs.coupling_wrench'),
    ('hand', lambda: _hand(pose=[0.0] * 3), 'size', 'HandInputs.pose must have 6 entries, got 3'),
    ('hand', lambda: _hand(twist=[0.0] * 9), 'size', 'HandInputs.twist must have 6 entries'),
    ('hand', lambda: _hand(seq=[]), 'size', 'HandInputs.seq must have at least 1 entry, got 0'),
    ('hand', lambda: _hand(state_seq=[5]), 'size',
     'HandInputs.state_seq must have 2 entries (one per seq), got 1'),
    ('hand', lambda: _hand(stamp=[Time()]), 'size',
     'HandInputs.stamp must have 2 entries (one per seq), got 1'),
]


@pytest.mark.parametrize(('kind', 'make', 'reason', 'text'), CASES)
def test_bad_message_rejected_with_reason(kind: str, make: Callable[[], Any], reason: str,
                                          text: str) -> None:
    convert: dict[str, Callable[[Any], Any]] = {
        'lmi': lambda m: lmi_from_msg(m, TASK, DOF),
        'state': lambda m: state_from_msg(m, TASK),
        'command': lambda m: command_from_msg(m, TASK),
        'hand': _hand_inputs,
    }
    with pytest.raises(MessageError) as err:
        convert[kind](make())
    assert err.value.reason == reason
    assert text in str(err.value)
    counter = RejectCounter()
    counter.add(err.value)
    assert counter.values()[f'rejected_{reason}'] == '1' and counter.total == 1


def test_the_coupling_wrench_is_bounded_only_where_the_vt_feels_it() -> None:
    """``max_hand_wrench`` bounds what the VE applies to the VT. Without VT coupling (``F_vt =
    F_h``, the eq. 20 scenarios) ``coupling_wrench`` only reports ``F_pc`` on the device, which
    grows with the distance between device and VT (eq. 15: 100 N/m x 10 m on spatial_arm4's
    20 s run, once its device sits at a workspace stop): the batch is taken with ``F_h``; with
    VT coupling it is refused, naming the field. A non-finite one is refused either way."""
    far = [0.0] * 3 + [11.5, 1000.17, -3.97]       # sample 1: F_pc beyond +-100
    batch = _hand(coupling_wrench=far)
    *_, f_vt = vt_wrenches_from_hand_inputs(batch, TASK, False, 100.0)
    assert f_vt.tolist() == [[0.4, 0.0, 0.0], [0.5, 0.0, 0.0]]
    with pytest.raises(MessageError, match=r'HandInputs.coupling_wrench must be within \+-100, '
                       r'got \[11.5, 1000.17, -3.97\] \(sample 1\)'):
        vt_wrenches_from_hand_inputs(batch, TASK, True, 100.0)
    with pytest.raises(MessageError, match='HandInputs.coupling_wrench has non-finite'):
        vt_wrenches_from_hand_inputs(_hand(coupling_wrench=[math.nan] + [0.0] * 5), TASK,
                                     False, 100.0)


def test_huge_finite_values_are_finite_and_every_non_finite_kind_is_not() -> None:
    """Entries of any finite size pass the finiteness check; inf, -inf and NaN never do."""
    state = state_from_msg(_state(pose=[1e200, -1e300, 0.0]), TASK)
    assert state[2].tolist() == [1e200, -1e300, 0.0]
    for bad in (math.inf, -math.inf, math.nan):
        with pytest.raises(MessageError, match='DeviceState.twist has non-finite'):
            state_from_msg(_state(twist=[1e200, bad, 0.0]), TASK)


@pytest.mark.parametrize('kind', [list, np.array, lambda v: DeviceState(pose=v).pose])
@pytest.mark.parametrize('size', [3, 64, 65, 400])
def test_finiteness_holds_for_each_form_and_size_of_a_field(kind: Any, size: int) -> None:
    """A float field as a list (a message built in Python), an rclpy ``array.array`` or a
    numpy array (``rosbags``), short or long: finite entries whose sum overflows pass; one
    inf, -inf or NaN among them, or a pair that cancels to NaN, never does."""
    big = [1e308] * size
    assert check.array(SimpleNamespace(pose=kind(big)), 'pose', size).tolist() == big
    for bad in ([math.inf], [-math.inf], [math.nan], [math.inf, -math.inf]):
        values = kind(bad + [1.0] * (size - len(bad)))
        with pytest.raises(MessageError, match='SimpleNamespace.pose has non-finite') as err:
            check.array(SimpleNamespace(pose=values), 'pose', size)
        assert err.value.reason == 'non_finite'


def test_numbers_given_as_text_or_huge_ints_get_a_verdict_not_an_exception() -> None:
    """A list whose Python sum fails (text that numpy reads as a number) gets numpy's
    verdict; an int beyond any float is refused as non-finite, not raised as an
    OverflowError."""
    ok = SimpleNamespace(pose=['1.5', 2, 3.0])
    assert check.array(ok, 'pose', 3).tolist() == [1.5, 2.0, 3.0]
    ints = SimpleNamespace(pose=[10 ** 308, 10 ** 308])    # each a float, their sum none
    assert check.array(ints, 'pose', 2).tolist() == [1e308, 1e308]
    with pytest.raises(MessageError, match='pose has non-finite entries: \\[inf, 2.0, 3.0\\]'):
        check.array(SimpleNamespace(pose=['inf', 2, 3.0]), 'pose', 3)
    with pytest.raises(MessageError, match='pose has entries beyond the float range') as err:
        check.array(SimpleNamespace(pose=[10 ** 400, 0]), 'pose', 2)
    assert err.value.reason == 'non_finite'


def test_finite_command_beyond_the_limit_is_clamped_not_rejected() -> None:
    """A large finite wrench is the device's job (saturate, status SATURATED)."""
    assert command_from_msg(_command(wrench=[1e9, -1e9, 0.0]), TASK)[2][0] == 1e9


# -- integers: every integer field of every incoming message has a range ---------------------
BIG = 2 ** 63 - 1
MAX = MAX_SEQ
INT_CASES: list[tuple[str, Callable[[], Any], str, str]] = [
    ('state', lambda: _state(seq=BIG), 'range', f'DeviceState.seq must be in [1, {MAX}]'),
    ('state', lambda: _state(seq=2 ** 64 - 1), 'range', 'DeviceState.seq must be in'),
    ('state', lambda: _state(seq=MAX + 1), 'range', f'got {MAX + 1}'),
    ('state', lambda: _state(status=32), 'range', 'DeviceState.status must be in [0, 31]'),
    ('state', lambda: _state(status=255), 'range', 'got 255'),
    ('state', lambda: _state(task_dim=255), 'task_dim', 'DeviceState.task_dim must be 3'),
    ('state', lambda: _stamped(_state(), 0, 10 ** 9), 'range',
     'DeviceState.header.stamp.nanosec must be < 1000000000'),
    ('state', lambda: _stamped(_state(), -1, 0), 'range',
     'DeviceState.header.stamp.sec must be >= 0'),
    ('command', lambda: _command(state_seq=BIG), 'range',
     f'DeviceCommand.state_seq must be in [1, {MAX}]'),
    ('command', lambda: _command(state_seq=0), 'range', 'DeviceCommand.state_seq must be in'),
    ('command', lambda: _command(mode=255), 'range', 'DeviceCommand.mode must be one of'),
    ('command', lambda: _command(task_dim=0), 'task_dim', 'DeviceCommand.task_dim must be 3'),
    ('command', lambda: _command(constraint_count=4), 'range',
     'DeviceCommand.constraint_count must be in [0, 3], got 4'),
    ('command', lambda: _command(update_age=math.nan), 'range',
     'DeviceCommand.update_age must be >= 0'),
    ('command', lambda: _command(vt_pose=[0.0] * 6), 'size',
     'DeviceCommand.vt_pose must have 3 entries'),
    ('command', lambda: _command(controller_id=0), 'range',
     f'DeviceCommand.controller_id must be in [1, {BIG}], got 0'),
    ('command', lambda: _command(controller_id=2 ** 64 - 1), 'range',
     f'DeviceCommand.controller_id must be in [1, {BIG}], got {2 ** 64 - 1}'),
    ('hand', lambda: _hand(seq=[1, BIG]), 'range',
     f'HandInputs.seq must be in [1, {MAX}], got [{BIG}]'),
    ('hand', lambda: _hand(state_seq=[BIG, BIG]), 'range',
     'HandInputs.state_seq must be in [1, '),
    ('hand', lambda: _hand(state_seq=[0, 1]), 'range', 'HandInputs.state_seq must be in [1, '),
    ('hand', lambda: _hand(seq=[2, 2]), 'range',
     'HandInputs.seq must be strictly ascending, got [2, 2]'),
    ('hand', lambda: _hand(state_seq=[6, 5]), 'range',
     'HandInputs.state_seq must be strictly ascending, got [6, 5]'),
    ('hand', lambda: _hand(task_dim=6), 'task_dim', 'HandInputs.task_dim must be 3'),
    ('hand', lambda: _hand(stamp=[Time(), _bad_stamp(-1, 0)]), 'range',
     'HandInputs.stamp[1].sec must be >= 0, got -1'),
    ('hand', lambda: _hand(stamp=[_bad_stamp(0, 10 ** 9), Time()]), 'range',
     'HandInputs.stamp[0].nanosec must be < 1000000000, got 1000000000'),
    ('hand', lambda: _stamped(_hand(), 0, 10 ** 9), 'range',
     'HandInputs.header.stamp.nanosec must be < 1000000000'),
    ('lmi', lambda: _update(seq=BIG), 'range', f'LmiUpdate.seq must be in [0, {MAX}]'),
    ('lmi', lambda: _update(hand_input_seq=2 ** 64 - 1), 'range',
     'LmiUpdate.hand_input_seq must be in [0, '),
    ('lmi', lambda: _update(dof=2 ** 32 - 1), 'dof', 'LmiUpdate.dof must be 3, got 4294967295'),
    ('lmi', lambda: _update(task_dim=255), 'task_dim', 'LmiUpdate.task_dim must be 3'),
    ('lmi', lambda: _update(constraint_count=255), 'range',
     'LmiUpdate.constraint_count must be in [0, 3], got 255'),
    ('path', lambda: _path(update_seq=BIG), 'range', f'VtPath.update_seq must be in [0, {MAX}]'),
    ('path', lambda: _path(hand_input_seqs=[1, BIG]), 'range',
     f'VtPath.hand_input_seqs must be in [1, {MAX}], got [{BIG}]'),
    ('path', lambda: _path(hand_input_seqs=[0, 1]), 'range', 'got [0]'),
    ('path', lambda: _path(task_dim=6), 'task_dim', 'VtPath.task_dim must be 3'),
    ('path', lambda: _path(hand_pose=[0.0] * 5), 'size', 'VtPath.hand_pose must have 6'),
]


def _bad_stamp(sec: int, nanosec: int) -> Any:
    # rclpy's Time refuses such values; a message decoded from a bag (rosbags) carries them.
    return SimpleNamespace(sec=sec, nanosec=nanosec)


def _stamped(msg: Any, sec: int, nanosec: int) -> Any:
    # rclpy's Time refuses such values; a message decoded from a bag (rosbags) carries them.
    msg.header = SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec))
    return msg


def _path(**fields: Any) -> VtPath:
    msg = VtPath(update_seq=3, task_dim=3, hand_input_seqs=[4, 5], hand_pose=[0.0] * 6)
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


@pytest.mark.parametrize(('kind', 'make', 'reason', 'text'), INT_CASES)
def test_integer_out_of_range_rejected_naming_field_and_range(
        kind: str, make: Callable[[], Any], reason: str, text: str) -> None:
    convert: dict[str, Callable[[Any], Any]] = {
        'lmi': lambda m: lmi_from_msg(m, TASK, DOF),
        'state': lambda m: state_from_msg(m, TASK),
        'command': lambda m: command_from_msg(m, TASK),
        'hand': _hand_inputs,
        'path': lambda m: check_vt_path(m, TASK.dim),
    }
    with pytest.raises(MessageError) as err:
        convert[kind](make())
    assert err.value.reason == reason
    assert text in str(err.value), str(err.value)


def test_largest_sequence_numbers_pass_and_fit_the_core() -> None:
    """MAX_SEQ itself is accepted everywhere, and the controller's loop seq (device seq plus
    the previous session's loop seq) still fits its int64 ring."""
    assert state_from_msg(_state(seq=MAX), TASK)[0] == MAX
    assert command_from_msg(_command(state_seq=MAX), TASK)[0] == MAX
    assert _hand_inputs(_hand(seq=[MAX - 1, MAX], state_seq=[MAX - 1, MAX]))[1][-1] == MAX
    snap = lmi_from_msg(_update(seq=MAX, hand_input_seq=MAX), TASK, DOF)
    assert snap.seq == MAX and snap.hand_input_seq == MAX
    assert check_vt_path(_path(hand_input_seqs=[MAX], hand_pose=[0.0] * 3), TASK.dim)[1] == [MAX]
    assert 2 * MAX < np.iinfo(np.int64).max and float(MAX) == MAX


def test_msgcheck_docstring_example() -> None:
    import doctest

    from haptic_topology.messages import check as msgcheck

    assert doctest.testmod(msgcheck).failed == 0
