"""``messages.cdr``: the bytes the driver and the controller publish at 1 kHz are rclpy's own
serialization of the messages ``state_msg``/``command_msg`` fill (padding aside), and rclpy
reads them back to those messages."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import MarkerArray

from haptic_topology.control.batch import HandBatch
from haptic_topology.control.controller import CycleOutput
from haptic_topology.control.loop import Answer, HandSample
from haptic_topology.device.backend import DeviceReading
from haptic_topology.device.hosted import HostedStep
from haptic_topology.device.loop import DeviceTick
from haptic_topology.device.records import CycleCodec
from haptic_topology.device.runner import Published
from haptic_topology.messages.cdr import CdrWriter
from haptic_topology.nodes.convert import (
    command_msg,
    hand_inputs_msg,
    lmi_msg,
    ns_to_stamp,
    state_msg,
)
from haptic_topology.nodes.wire import (
    LMI_FIELDS,
    PATH_FIELDS,
    STATE_FIELDS,
    CycleWire,
    command_cdr,
    command_writer,
    hand_inputs_cdr,
    hand_inputs_writer,
    lmi_cdr,
    lmi_writer,
    path_cdr,
    path_writer,
    state_cdr,
    state_writer,
)
from haptic_topology.sim import load_scenario
from haptic_topology.sim.lockstep import virtual_environment
from haptic_topology.vocabulary import ControlMode, DeviceStatus
from haptic_topology_msgs.msg import DeviceCommand, DeviceState, HandInputs, LmiUpdate, VtPath

GRAPH = 0x9E3779B97F4A7C15          # a graph id's wire value (uint64, high bit set)
FRAME = 'device_base'


def _same_bytes_but_padding(ours: bytes, ref: bytes, padding: list[int]) -> None:
    """Equal up to the alignment bytes, and up to the slack ``serialize_message`` may leave
    after the last field (the module doc)."""
    assert len(ours) <= len(ref)
    differ = [i for i in range(len(ours)) if ours[i] != ref[i]]
    assert set(differ) <= set(padding), differ
    assert all(ours[i] == 0 for i in padding)


@pytest.mark.parametrize('dim, env', [(3, None), (3, 3), (6, None), (6, 6)])
def test_device_state_bytes_are_rclpys_serialization(dim: int, env: int | None) -> None:
    rng = np.random.default_rng(dim * 10 + (env or 0))
    writer = state_writer(FRAME, GRAPH)
    msg = DeviceState()
    msg.header.frame_id, msg.graph_id = FRAME, GRAPH
    for k in range(3):          # the same writer, message after message
        reading = DeviceReading(*(rng.normal(size=dim) for _ in range(3)))
        applied = rng.normal(size=dim)
        env_wrench = None if env is None else rng.normal(size=env)
        seq, ns = 2**40 + k, 1_764_000_000_123_456_789 + k * 1_000_000
        status = int(DeviceStatus.SATURATED | DeviceStatus.WORKSPACE_LIMIT)
        state_msg(msg, seq, ns_to_stamp(ns), reading, applied, status, env_wrench)
        ours = state_cdr(writer, seq, ns, reading, applied, status, env_wrench)
        assert deserialize_message(ours, DeviceState) == msg
        values = writer_values(seq, ns, reading, applied, status, env_wrench)
        _same_bytes_but_padding(ours, serialize_message(msg), writer.padding(*values))


def writer_values(seq: int, ns: int, reading: DeviceReading, applied: np.ndarray,
                  status: int, env_wrench: np.ndarray | None) -> tuple:
    sec, nanosec = divmod(ns, 10**9)
    return (sec, nanosec, seq, reading.pose.size, reading.pose, reading.twist,
            reading.hand_wrench, applied, status, () if env_wrench is None else env_wrench)


@pytest.mark.parametrize('dim, env', [(3, None), (6, 6)])
def test_device_command_bytes_are_rclpys_serialization(dim: int, env: int | None) -> None:
    rng = np.random.default_rng(dim)
    writer = command_writer(FRAME, GRAPH)
    msg = DeviceCommand()
    msg.header.frame_id, msg.graph_id = FRAME, GRAPH
    for mode, update_seq in ((ControlMode.PENALTY, -1), (ControlMode.ZERO, 2**53)):
        out = CycleOutput(*(rng.normal(size=dim) for _ in range(5)), constraint_count=2,
                          mode=mode, env_wrench=None if env is None else rng.normal(size=env))
        ns, age, cid = 1_764_000_000_000_000_001, 0.0123, 2**63 - 1
        command_msg(msg, 77, ns_to_stamp(ns), out, age, cid, update_seq)
        ours = command_cdr(writer, 77, ns, out, age, cid, update_seq)
        assert deserialize_message(ours, DeviceCommand) == msg
        sec, nanosec = divmod(ns, 10**9)
        values = (sec, nanosec, 77, cid, int(mode), dim, out.wrench, out.vt_pose, out.vt_twist,
                  2, age, () if out.env_wrench is None else out.env_wrench, update_seq)
        _same_bytes_but_padding(ours, serialize_message(msg), writer.padding(*values))


@pytest.mark.parametrize('scenario, push', [('circle', 0), ('wall', 0), ('wall', 400),
                                             ('spatial_arm4', 0)])
def test_lmi_update_bytes_are_rclpys_serialization(scenario: str, push: int) -> None:
    """``lmi_cdr`` (what ``ve_sim`` publishes) is the message ``lmi_msg`` fills, without
    obstacles, with obstacles but no contact near, and pressed into a wall (two contacts)."""
    ve = virtual_environment(load_scenario(scenario))
    wrench = np.zeros(ve.dyn.task.dim)
    wrench[0] = 0.4
    for _ in range(push):
        ve.integrate(wrench, 1e-3)
    writer = lmi_writer('world', GRAPH)
    for seq in (0, 2**40):
        snap = ve.snapshot(seq)
        assert (snap.contacts is None) == (scenario != 'wall')
        assert push == 0 or len(snap.contacts or ()) >= 1
        ns = 1_764_000_000_123_456_789 + seq
        msg = lmi_msg(LmiUpdate(), snap, ns_to_stamp(ns))
        msg.header.frame_id, msg.graph_id = 'world', GRAPH
        ours = lmi_cdr(writer, snap, ns)
        assert deserialize_message(ours, LmiUpdate) == msg
        values = [getattr(msg, f) for f in LMI_FIELDS[2:]]
        _same_bytes_but_padding(ours, serialize_message(msg),
                                writer.padding(*divmod(ns, 10**9), *values))
        ve.integrate(wrench, 1e-3)


def test_vt_path_bytes_are_rclpys_serialization() -> None:
    writer = path_writer('world', GRAPH)
    for n in (1, 10, 3):
        path = [(2**35 + k, np.array([0.1 * k, -0.2, 3.0 + k])) for k in range(n)]
        ns = 1_764_000_000_000_000_007 + n
        msg = VtPath(update_seq=41 + n, task_dim=3, graph_id=GRAPH,
                     hand_input_seqs=[s for s, _ in path],
                     hand_pose=np.concatenate([x for _, x in path]).tolist())
        msg.header.frame_id, msg.header.stamp = 'world', ns_to_stamp(ns)
        ours = path_cdr(writer, 41 + n, 3, path, ns)
        assert deserialize_message(ours, VtPath) == msg
        values = [getattr(msg, f) for f in PATH_FIELDS[2:]]
        _same_bytes_but_padding(ours, serialize_message(msg),
                                writer.padding(*divmod(ns, 10**9), *values))


@pytest.mark.parametrize('dim', [3, 6])
def test_hand_inputs_bytes_are_rclpys_serialization(dim: int) -> None:
    """``hand_inputs_cdr`` (what the controller publishes) is the message
    ``hand_inputs_msg`` fills: its ``builtin_interfaces/Time[]`` stamps included, for a full
    batch and for partial ones."""
    rng = np.random.default_rng(dim)
    writer = hand_inputs_writer(FRAME, GRAPH)
    for n in (10, 1, 4, 10):
        first = int(rng.integers(1, 10**6))
        batch = HandBatch(np.arange(first, first + n), np.arange(first + 1, first + 1 + n),
                          np.sort(rng.integers(0, 4 * 10**9, size=n)),
                          *(rng.normal(size=(n, dim)) for _ in range(4)))
        msg = HandInputs()
        msg.header.frame_id, msg.graph_id = FRAME, GRAPH
        hand_inputs_msg(msg, batch)
        ours = hand_inputs_cdr(writer, batch)
        assert deserialize_message(ours, HandInputs) == msg
        assert [s.nanosec for s in msg.stamp] == (batch.stamp_ns % 10**9).tolist()
        sec, nanosec = np.divmod(batch.stamp_ns, 10**9)
        _same_bytes_but_padding(ours, serialize_message(msg), writer.padding(
            sec[-1], nanosec[-1], dim, batch.seq, batch.state_seq,
            np.stack((sec, nanosec), axis=1), batch.pose, batch.twist, batch.hand_wrench,
            batch.coupling))


def test_sequence_lengths_may_change_between_messages() -> None:
    """A layout per combination of lengths, empty sequences included (no alignment after
    an empty sequence's length); a matrix goes in row-major, whatever its memory order."""
    writer = CdrWriter(LmiUpdate, ('q', 'mass_matrix', 'constraint_count'))
    for n in (0, 3, 1, 0, 7):
        q, d = np.arange(n, dtype=float), np.arange(n * n, dtype=float).reshape(n, n).T
        msg = LmiUpdate(q=q.tolist(), mass_matrix=d.ravel().tolist(), constraint_count=n)
        ours = writer.pack(q, d, n)
        assert deserialize_message(ours, LmiUpdate) == msg
        _same_bytes_but_padding(ours, serialize_message(msg), writer.padding(q, d, n))


def test_bad_fields_and_values_are_refused_naming_them() -> None:
    with pytest.raises(ValueError, match=r"no field \['posture'\]"):
        CdrWriter(DeviceState, ('posture',))
    with pytest.raises(ValueError, match='must be constants'):
        CdrWriter(DeviceState, ('header.frame_id',))
    with pytest.raises(ValueError, match='both given per message and constant'):
        CdrWriter(DeviceState, ('graph_id',), {'graph_id': 1})
    with pytest.raises(ValueError, match=r"MarkerArray.markers: type 'sequence<visualization_"):
        CdrWriter(MarkerArray, ())                  # a message with strings, sequences
    with pytest.raises(ValueError, match=r'stamp: 3 values are not whole elements of 2'):
        CdrWriter(HandInputs, ('stamp',)).pack([1, 2, 3])
    writer = CdrWriter(DeviceState, STATE_FIELDS)
    with pytest.raises(ValueError, match='9 values for the 10 fields'):
        writer.pack(*range(9))
    good = (1, 2, 3, 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0, ())
    assert deserialize_message(writer.pack(*good), DeviceState).seq == 3
    with pytest.raises(ValueError, match='DeviceState: a value does not fit its field'):
        writer.pack(*good[:8], 256, ())               # status is a uint8


def test_gather_packs_what_pack_packs_from_one_list() -> None:
    """``CdrWriter.gather``: each field from its position in one list (a sequence from its
    first), the same bytes as ``pack`` of those values, for both lengths of a sequence."""
    writer = CdrWriter(DeviceState, STATE_FIELDS, {'header.frame_id': FRAME, 'graph_id': GRAPH})
    # src: seq, sec, nanosec, status, then pose, twist, F_h, applied, env (3 each), junk
    where = {'seq': 0, 'header.stamp.sec': 1, 'header.stamp.nanosec': 2, 'status': 3,
             'task_dim': 4, 'pose': 5, 'twist': 8, 'hand_wrench': 11, 'applied_wrench': 14,
             'env_wrench': 17}
    src = [2**40, 1_764_000_000, 999_999_999, 5, 3, *np.linspace(-1, 1, 15).tolist(),
           0.5, 0.25, 0.125, 'junk']
    for env in (0, 3):
        lengths = {'pose': 3, 'twist': 3, 'hand_wrench': 3, 'applied_wrench': 3,
                   'env_wrench': env}
        packer = writer.gather(len(src), where, lengths)
        expect = writer.pack(*src[1:3], src[0], 3, src[5:8], src[8:11], src[11:14],
                             src[14:17], 5, src[17:17 + env])
        assert packer(src) == expect
    with pytest.raises(ValueError, match=r"lengths must give the sequences \['applied_wrench'"):
        writer.gather(len(src), where, {'pose': 3})
    with pytest.raises(ValueError, match=r"fields \['env_wrench'\] need a position in 0..23"):
        writer.gather(len(src), {**where, 'env_wrench': 22}, {**lengths, 'env_wrench': 3})


@pytest.mark.parametrize('dim, env, answer, hand, out_env', [
    (3, False, False, False, False), (3, True, True, True, False),
    (6, False, True, False, True), (6, True, True, True, True)])
def test_cycle_wire_packs_the_records_cycle_as_state_cdr_and_command_cdr(
        dim: int, env: bool, answer: bool, hand: bool, out_env: bool) -> None:
    """The hosted publisher packs a cycle's state and command straight from its record
    (``CycleWire``): the bytes ``state_cdr`` and ``command_cdr`` give for the decoded cycle,
    and the hand input the port takes, with every optional part present or absent."""
    rng = np.random.default_rng(dim + 2 * env + 4 * answer + 8 * hand + 16 * out_env)

    def v() -> np.ndarray:
        return rng.normal(size=dim)

    status = DeviceStatus.SATURATED | (DeviceStatus.IDLE if not answer else DeviceStatus(0))
    tick = DeviceTick(2**33 + 1, 5, DeviceReading(v(), v(), v(), DeviceStatus.SATURATED), v(),
                      status, v() if env else None)
    ans = None
    if answer:
        out = CycleOutput(v(), v(), v(), v(), v(), 2, ControlMode.PENALTY,
                          v() if out_env else None)
        sample = HandSample(7, tick.seq, 0.25, v(), v(), v(), v(), v()) if hand else None
        ans = Answer(tick.seq, out, sample, 2**40)
    e = Published(HostedStep(tick, 0.25, ans, None, ()), 1_764_000_000_123_456_789)
    codec = CycleCodec(dim)
    rec = codec.records([e])
    wire = CycleWire(codec, state_writer(FRAME, GRAPH), command_writer(FRAME, GRAPH))
    src = rec['i'][0].tolist() + rec['f'][0].tolist() + wire.extras(e.stamp_ns)
    assert wire.state(src) == state_cdr(state_writer(FRAME, GRAPH), tick.seq, e.stamp_ns,
                                        tick.reading, tick.applied, int(status), tick.env_wrench)
    assert wire.answered(src) == answer and wire.idle(src) == (not answer)
    if ans is None:
        return
    assert wire.command(src, 0.0375) == command_cdr(
        command_writer(FRAME, GRAPH), tick.seq, e.stamp_ns, ans.out, 0.0375,
        update_seq=ans.update_seq)
    got = wire.hand(src, rec['f'][0])
    if ans.hand is None:
        assert got is None
        return
    assert got is not None and got[:2] == (7, tick.seq)
    h = ans.hand
    np.testing.assert_array_equal(got[2], np.stack([h.pose, h.twist, h.hand_wrench,
                                                    h.coupling]))
