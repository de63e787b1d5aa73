"""Bags without ROS processes: writer/reader round trip, truncation and repair, analyze on
the reference bag and on a simulate trace, and bad inputs with one-line errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from haptic_topology.bag.analyze import analyze
from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.bag.reader import decoder, field_default, iter_messages, open_bag
from haptic_topology.bag.repair import repair_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, _mcap_internals, make_qos
from haptic_topology.cli import main as cli_main
from haptic_topology.errors import BagError
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.scenario import load_scenario
from haptic_topology.vocabulary import ControlMode

REPO = Path(__file__).resolve().parents[3]
#: The Fig. 8 reference as first recorded (2026-11-22): 1 kHz ``HandInput`` on ``/haptic/hand``,
#: ``DeviceCommand`` without ``controller_id``, states and updates without the contact fields;
#: kept to check that bags of older message definitions still read.
REFERENCE = REPO / 'test' / 'fixtures' / 'old_messages' / 'reference_fig8'
#: The reference recorded with the current messages (``bags/reference_fig8``).
CURRENT_REFERENCE = REPO / 'bags' / 'reference_fig8'
STATE = type_name('DeviceState')
COMMAND = type_name('DeviceCommand')
#: The controller id given to the reference bag's commands (recorded before the field
#: existed) when a test copies them into a bag of the current definitions.
CID = 4242


def _as_current(msg: Any, msgtype: str) -> Any:
    """``msg`` (decoded from a bag, maybe with an older definition of its type) as an object
    of the current definition: fields it lacks get :data:`CID` (``controller_id``) or their
    defaults (the contact fields: empty, zero)."""
    ts = typestore_with_haptic_msgs()
    fields = ts.fielddefs[msgtype][1]
    if all(hasattr(msg, n) for n, _ in fields):
        return msg
    return ts.types[msgtype](**{
        n: getattr(msg, n) if hasattr(msg, n) else CID if n == 'controller_id'
        else field_default(t)[1] for n, t in fields})


def _current_bytes(m: Any, msg: Any) -> bytes:
    """The CDR of the bag message ``m`` (decoded: ``msg``) under the current definition."""
    ts = typestore_with_haptic_msgs()
    if not m.msgtype.startswith('haptic_topology_msgs/') or all(
            hasattr(msg, n) for n, _ in ts.fielddefs[m.msgtype][1]):
        return bytes(m.data)
    return bytes(ts.serialize_cdr(_as_current(msg, m.msgtype), m.msgtype))


def _state_bytes(seq: int) -> bytes:
    ts = typestore_with_haptic_msgs()
    cls = ts.types[STATE]
    header = ts.types['std_msgs/msg/Header'](ts.types['builtin_interfaces/msg/Time'](1, 2),
                                             'base')
    v = np.array([0.1, 0.2, 0.3])
    return bytes(ts.serialize_cdr(cls(header, seq, 3, v, v, v, v, 0, np.zeros(0), 0), STATE))


def _write(path: Path, n: int, flush_at: int | None = None) -> BagWriter:
    w = BagWriter(path, [TopicSpec('/haptic/device/state', STATE, (make_qos(False, 1),))],
                  typestore_with_haptic_msgs(), sources=message_definitions())
    for i in range(1, n + 1):
        w.write(0, 1_000_000_000 + i * 1_000_000, _state_bytes(i))
        if i == flush_at:
            w.flush()
    return w


def test_writer_round_trip_rosbags_and_mcap(tmp_path: Path) -> None:
    _write(tmp_path / 'a', 2000).close()
    decode = decoder()
    assert [decode(m).seq for m in iter_messages(open_bag(tmp_path / 'a'))] == list(
        range(1, 2001))
    with AnyReader([tmp_path / 'a']) as reader:  # types from the embedded schema only
        seqs = [reader.deserialize(raw, c.msgtype).seq for c, _, raw in reader.messages()]
        qos = reader.connections[0].ext.offered_qos_profiles
    assert seqs == list(range(1, 2001))
    assert qos[0].depth == 1 and qos[0].reliability.name == 'BEST_EFFORT'
    with (tmp_path / 'a' / 'a_0.mcap').open('rb') as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_count == 2000
    text = next(iter(summary.schemas.values())).data.decode()
    assert text.startswith('# State of the haptic device')  # the .msg text, with comments
    assert '=' * 80 + '\nMSG: std_msgs/Header\n' in text


def test_unflushed_writer_reads_back_to_its_last_flush_and_repairs(tmp_path: Path) -> None:
    w = _write(tmp_path / 'k', 3000, flush_at=2500)
    # Simulated kill: the process dies, the file holds what was flushed (no close()).
    w._file.flush()
    bag = open_bag(tmp_path / 'k')
    decode = decoder()
    seqs = [decode(m).seq for m in iter_messages(bag)]
    assert bag.truncated
    assert seqs[:2500] == list(range(1, 2501))
    meta = (tmp_path / 'k' / 'metadata.yaml').read_text()
    assert 'message_count: 2500' in meta  # the flush's counts
    res = repair_bag(tmp_path / 'k')
    assert res.repaired and res.counts['/haptic/device/state'] == len(seqs)
    with AnyReader([tmp_path / 'k']) as reader:
        assert reader.message_count == len(seqs)


def test_truncated_mid_chunk(tmp_path: Path) -> None:
    _write(tmp_path / 'c', 3000).close()
    mcap = tmp_path / 'c' / 'c_0.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2 + 13])
    bag = open_bag(tmp_path / 'c')
    seqs = [decoder()(m).seq for m in iter_messages(bag)]
    assert bag.truncated and 0 < len(seqs) < 3000
    assert seqs == list(range(1, len(seqs) + 1))


def test_analyze_reference_bag_and_simulate_trace(tmp_path: Path) -> None:
    run = read_graph_bag(REFERENCE, 'fig8', 3)
    ref = json.loads((REFERENCE / 'summary.json').read_text())
    assert run.trace.summary()['final_distance_m'] == pytest.approx(ref['final_distance_m'])


    sc = load_scenario('fig8')
    sim = simulate(replace(sc, duration=0.5, update_period=10), ControlMode.PENALTY)
    (tmp_path / 'sim_fig8').mkdir()
    sim.to_csv(tmp_path / 'sim_fig8' / 'trace.csv')
    rows = analyze([REFERENCE, tmp_path / 'sim_fig8' / 'trace.csv'], tmp_path / 'out')
    assert [r['source'] for r in rows] == ['graph', 'simulate']
    for r in rows:
        for key in ('final_distance_m', 'max_distance_m', 'rms_distance_m',
                    'constrained_time_s'):
            assert np.isfinite(r[key])
    assert rows[0]['bag_missing_states'] == 0
    out = {p.name for p in (tmp_path / 'out').iterdir()}
    assert {'summary.json', 'comparison.png', 'reference_fig8.png', 'sim_fig8.png'} <= out


def _foreign_bag(path: Path) -> None:
    w = BagWriter(path, [TopicSpec('/chatter', 'std_msgs/msg/String')],
                  typestore_with_haptic_msgs())
    cls = typestore_with_haptic_msgs().types['std_msgs/msg/String']
    w.write(0, time.time_ns(), bytes(typestore_with_haptic_msgs().serialize_cdr(
        cls('hi'), 'std_msgs/msg/String')))
    w.close()


@pytest.mark.parametrize('case, expected', [
    ('missing', 'no such file or directory'),
    ('empty_dir', 'not a bag (no metadata.yaml and no .mcap file)'),
    ('not_mcap', 'not an MCAP file'),
    ('empty_file', 'empty file'),
    ('foreign', 'not a bag of the haptic_topology graph'),
    ('bad_metadata', 'cannot read rosbag2 metadata'),
    ('sqlite', "storage 'sqlite3' is not supported"),
    ('corrupt_chunk', 'corrupt'),
])
def test_bad_bags_name_the_file_and_the_problem(tmp_path: Path, case: str, expected: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / case
    culprit = target
    if case == 'empty_dir':
        target.mkdir()
    elif case == 'not_mcap':
        target.mkdir()
        culprit = target / 'x.mcap'
        culprit.write_text('hello, this is not a bag\n')
    elif case == 'empty_file':
        culprit = target = tmp_path / 'empty.mcap'
        target.write_bytes(b'')
    elif case == 'foreign':
        _foreign_bag(target)
    elif case == 'bad_metadata':
        target.mkdir()
        culprit = target / 'metadata.yaml'
        culprit.write_text('rosbag2_bagfile_information: [unclosed\n')
    elif case == 'sqlite':
        shutil.copytree(REFERENCE, target)
        culprit = target / 'metadata.yaml'
        culprit.write_text(culprit.read_text().replace('storage_identifier: mcap',
                                                       'storage_identifier: sqlite3'))
    elif case == 'corrupt_chunk':
        _write(target, 3000).close()
        culprit = target / f'{case}_0.mcap'
        data = bytearray(culprit.read_bytes())
        data[len(data) // 3: len(data) // 3 + 64] = b'\xff' * 64
        culprit.write_bytes(bytes(data))
    with pytest.raises(BagError) as err:
        read_graph_bag(target)
    assert expected in str(err.value)
    assert str(culprit) in str(err.value)
    # The command line: one line on stderr, exit status 1, no traceback. The console
    # script's main in this process for every case, and as its own process for one (the
    # process adds nothing else to check; each costs a second of start-up).
    for argv in (['analyze', str(target), '--out', str(tmp_path / 'o')],
                 ['replay', str(target), '--check-controller']):
        if case == 'corrupt_chunk':
            proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', *argv],
                                  capture_output=True, text=True, timeout=120)
            code, stderr = proc.returncode, proc.stderr
        else:
            capsys.readouterr()
            code = cli_main(argv)
            stderr = capsys.readouterr().err
        assert code == 1, stderr
        lines = stderr.strip().splitlines()
        assert len(lines) == 1 and expected in lines[0], stderr
        assert 'Traceback' not in stderr


# -- foreign and malformed messages in a bag -------------------------------------------------
def _hostile_copy(src: Path, dst: Path) -> dict[str, int]:
    """Copy the bag ``src`` to ``dst`` and add foreign/malformed messages on the graph's
    topics (each after the real message it imitates, but for one command of another
    controller id just before the real answer to the first running state, and a device
    driver diagnostics status that reports following :data:`CID`); return the skips
    expected per key."""
    from dataclasses import replace as dc_replace

    ts = typestore_with_haptic_msgs()
    bag = open_bag(src)
    topics = dict(bag.metadata_topics(), **{'/haptic/ve/path': type_name('VtPath')})
    names = sorted(topics)
    w = BagWriter(dst, [TopicSpec(t, topics[t], (make_qos(False, 1),)) for t in names], ts,
                  sources=message_definitions(),
                  custom=(bag.metadata or {}).get('custom_data') or {})
    index = {t: i for i, t in enumerate(names)}
    decode = decoder(bag=bag)
    first: dict[str, Any] = {}
    running_state: Any = None
    for m in iter_messages(bag):
        msg = decode(m)
        kind = m.topic.rsplit('/', 1)[-1]
        if (kind == 'command' and running_state is not None
                and int(msg.state_seq) == int(running_state[1].seq)):
            impostor = replace(_as_current(msg, COMMAND), controller_id=CID + 1,
                               wrench=np.array([7.5, -7.5, 0.75]))
            w.write(index[m.topic], m.log_time - 1,
                    bytes(ts.serialize_cdr(impostor, COMMAND)))
            diag = ts.types['diagnostic_msgs/msg/DiagnosticArray']
            status = ts.types['diagnostic_msgs/msg/DiagnosticStatus']
            kv = ts.types['diagnostic_msgs/msg/KeyValue']
            report = diag(msg.header, [status(0, 'device_driver: loop', 'ok', '',
                                              [kv('controller_id', str(CID))])])
            w.write(index['/diagnostics'], m.log_time + 1,
                    bytes(ts.serialize_cdr(report, 'diagnostic_msgs/msg/DiagnosticArray')))
        w.write(index[m.topic], m.log_time, _current_bytes(m, msg))
        first.setdefault(kind, (m, msg))
        if kind == 'state' and running_state is None and not msg.status & 4:
            running_state = (m, msg)
    nan3 = np.array([np.nan, 0.0, 0.0])
    z6 = np.zeros(6)

    def add(kind: str, msg: Any, log_time: int) -> None:
        raw = first[kind][0]
        w.write(index[raw.topic], log_time, bytes(ts.serialize_cdr(msg, raw.msgtype)))

    rm, st = running_state
    st = _as_current(st, STATE)
    t = rm.log_time + 1
    hostile_states = [
        dc_replace(st, pose=np.zeros(4)),                       # the (4,) into (3,)
        dc_replace(st, twist=nan3),
        dc_replace(st, task_dim=6, pose=z6, twist=z6, hand_wrench=z6, applied_wrench=z6),
        dc_replace(st, seq=2 ** 63 - 1),
        dc_replace(st, seq=2 ** 64 - 1),
        dc_replace(st, status=200),
        dc_replace(st, applied_wrench=np.array([-13.25, 11.5, 1.125])),   # same seq: false
        dc_replace(st, seq=10 ** 9),                            # far outside the run
    ]
    for msg in hostile_states:
        add('state', msg, t)
    cm, cmd = first['command'][0], _as_current(decode(first['command'][0]), COMMAND)
    for msg in (dc_replace(cmd, wrench=nan3), dc_replace(cmd, task_dim=6, wrench=z6),
                dc_replace(cmd, state_seq=2 ** 63 - 1),
                dc_replace(cmd, wrench=np.array([-13.25, 11.5, 1.125]))):  # duplicate
        add('command', msg, cm.log_time + 1)
    um, upd = first['update']
    upd = _as_current(upd, type_name('LmiUpdate'))
    for msg in (dc_replace(upd, dof=4), dc_replace(upd, seq=2 ** 64 - 1),
                dc_replace(upd, hand_input_seq=2 ** 63 - 1),
                dc_replace(upd, hand_pose=np.array([np.inf, 0.0, 0.0])),
                # a contact announced but not sent, a non-finite contact energy
                dc_replace(upd, contact_stiffness=1000.0, contact_slip_velocity=1e-3,
                           contact_count=1),
                dc_replace(upd, contact_energy=np.nan)):
        add('update', msg, um.log_time + 1)
    path_type = type_name('VtPath')
    path = ts.types[path_type](upd.header, 1, 3, np.array([2 ** 63 - 1], dtype=np.uint64),
                               np.zeros(3), 0)
    for msg in (path, dc_replace(path, hand_input_seqs=np.array([5], dtype=np.uint64),
                                 hand_pose=np.zeros(4))):
        w.write(index['/haptic/ve/path'], um.log_time + 2,
                bytes(ts.serialize_cdr(msg, path_type)))
    w.write(index[rm.topic], t, b'\x00\x01garbage')               # does not decode
    w.close()
    return {'state_size': 1, 'state_non_finite': 1, 'state_task_dim': 1, 'state_range': 3,
            'state_duplicate': 1, 'state_foreign_seq': 1, 'state_decode': 1,
            'command_non_finite': 1, 'command_task_dim': 1, 'command_range': 1,
            'command_duplicate': 2, 'update_dof': 1, 'update_range': 2,
            'update_non_finite': 2, 'update_size': 1, 'path_range': 1, 'path_size': 1}


def test_foreign_and_malformed_messages_in_a_bag_are_skipped_and_counted(
        tmp_path: Path) -> None:
    """A recorded run plus hostile messages on every graph topic (wrong sizes, NaN,
    task_dim 6, seq 2**63 - 1, false states with real seqs, a seq far outside the run,
    undecodable bytes, a command of another controller read before the real one): the trace
    is the clean run's, every hostile message is counted, and ``haptic-topology analyze``
    writes trace plot and summary."""
    expected = _hostile_copy(REFERENCE, tmp_path / 'hostile')
    clean = read_graph_bag(REFERENCE, 'fig8', 3)
    run = read_graph_bag(tmp_path / 'hostile', 'fig8', 3, task_dim=3)
    assert run.skipped == expected
    assert clean.skipped == {}
    for col in ('device_pose', 'applied', 'command', 'vt_pose', 'q'):
        np.testing.assert_array_equal(run.trace.columns[col], clean.trace.columns[col])
    # Without the scenario's sizes (task_dim, dof from the bag's majority): the same.
    assert read_graph_bag(tmp_path / 'hostile').skipped == expected
    out = tmp_path / 'out'
    proc = subprocess.run([sys.executable, '-m', 'haptic_topology.cli', 'analyze',
                           str(tmp_path / 'hostile'), '--out', str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'Traceback' not in proc.stderr
    assert f'skipped {sum(expected.values())} foreign or malformed messages' in proc.stdout
    summary = json.loads((out / 'summary.json').read_text())['runs'][0]
    assert summary['skipped_messages'] == expected
    assert (out / 'hostile.png').is_file()


def test_bags_recorded_before_controller_id_decode_with_their_own_definition() -> None:
    """The reference bag holds ``DeviceCommand`` without ``controller_id`` (and, like
    ``DeviceState`` and ``LmiUpdate``, without the contact fields): its bytes do not decode
    with the current definition, so the reader takes the bag's stored one for it, and plain
    replay leaves the topic out. States and updates, whose fields were only appended since,
    are replayed re-serialised as the installed types (the new fields empty or zero)."""
    from haptic_topology.bag.reader import outdated_types, upgraders
    from haptic_topology.bag.replay import left_out, plan

    bag = open_bag(REFERENCE)
    lmi = type_name('LmiUpdate')
    path = type_name('VtPath')      # recorded before graph_id, appended since
    assert outdated_types(bag) == {COMMAND, STATE, lmi, path}
    assert set(upgraders(bag)) == {STATE, lmi, path}
    assert left_out(bag) == {'/haptic/device/command': COMMAND}
    current = decoder()
    for topic, kind in (('/haptic/device/state', STATE), ('/haptic/lmi/update', lmi)):
        raw = next(iter_messages(bag, [topic]))
        old = decoder(bag=bag)(raw)
        new = current(replace(raw, data=upgraders(bag)[kind](raw.data)))
        assert int(new.seq) == int(old.seq) and new.header.stamp == old.header.stamp
        if kind == STATE:
            np.testing.assert_array_equal(new.pose, old.pose)
            assert new.env_wrench.size == 0 and new.graph_id == 0   # the default graph's
        else:
            np.testing.assert_array_equal(new.mass_matrix, old.mass_matrix)
            assert new.contact_count == 0 and new.contact_stiffness == 0.0
    decode = decoder(bag=bag)
    msgs = list(iter_messages(bag, ['/haptic/device/command']))
    commands = [decode(m) for m in msgs]
    assert len(commands) == 1606 and not hasattr(commands[0], 'controller_id')
    assert commands[0].task_dim == 3 and commands[0].wrench.shape == (3,)
    with pytest.raises(BagError, match='cannot decode haptic_topology_msgs/msg/DeviceCommand'):
        decoder()(msgs[0])
    # States decode with their stored definition from the same store.
    state = decode(next(iter_messages(bag, ['/haptic/device/state'])))
    assert state.task_dim == 3
    replayed = set(bag.metadata_topics()) - {'/haptic/device/command'}
    assert set(plan(bag).topics) == {it.topic for it in plan(bag)} == replayed
    with pytest.raises(BagError, match='cannot replay /haptic/device/command: recorded with '
                                       'an older definition of haptic_topology_msgs/msg/'
                                       'DeviceCommand'):
        plan(bag, ['/haptic/device/command'])


def test_the_reference_bag_holds_the_current_message_definitions() -> None:
    """``bags/reference_fig8`` is recorded with the messages as they are: every topic decodes
    with the installed definitions and replays as recorded, nothing left out."""
    from haptic_topology.bag.reader import outdated_types, upgraders
    from haptic_topology.bag.replay import left_out, plan

    bag = open_bag(CURRENT_REFERENCE)
    assert outdated_types(bag) == set() and upgraders(bag) == {}
    assert left_out(bag) == {}
    assert {it.topic for it in plan(bag)} == set(bag.metadata_topics())
    assert '/haptic/hand_inputs' in bag.metadata_topics()
    current = decoder()
    commands = [current(m) for m in iter_messages(bag, ['/haptic/device/command'])]
    assert commands and all(int(c.controller_id) != 0 for c in commands)


# -- bags of the batched hand inputs ------------------------------------------------------------
def _batched_copy(src: Path, dst: Path, drop_commands: set[int]) -> int:
    """Copy the bag ``src`` (1 kHz ``HandInput`` on ``/haptic/hand``) to ``dst`` as the graph
    records it now: ``HandInputs`` of 10 samples on ``/haptic/hand_inputs`` (written when the
    10th sample was, the rest at the end), without the commands answering ``drop_commands``.
    Returns the number of batches."""
    ts = typestore_with_haptic_msgs()
    bag = open_bag(src)
    topics = {t: ty for t, ty in bag.metadata_topics().items() if not t.endswith('/hand')}
    topics['/haptic/hand_inputs'] = type_name('HandInputs')
    names = sorted(topics)
    index = {t: i for i, t in enumerate(names)}
    w = BagWriter(dst, [TopicSpec(t, topics[t], (make_qos(True, 500),)) for t in names], ts,
                  sources=message_definitions(),
                  custom=(bag.metadata or {}).get('custom_data') or {})
    decode = decoder(bag=bag)
    batch_type = type_name('HandInputs')
    pending: list[Any] = []
    batches = 0

    def flush(log_time: int) -> None:
        nonlocal batches
        if not pending:
            return
        msg = ts.types[batch_type](
            header=pending[-1].header, task_dim=3,
            seq=np.array([h.seq for h in pending], dtype=np.uint64),
            state_seq=np.array([h.state_seq for h in pending], dtype=np.uint64),
            stamp=[h.header.stamp for h in pending],
            **{f: np.concatenate([getattr(h, f) for h in pending])
               for f in ('pose', 'twist', 'hand_wrench', 'coupling_wrench')}, graph_id=0)
        w.write(index['/haptic/hand_inputs'], log_time,
                bytes(ts.serialize_cdr(msg, batch_type)))
        pending.clear()
        batches += 1

    last = 0
    for m in iter_messages(bag):
        last = m.log_time
        if m.topic.endswith('/hand'):
            pending.append(decode(m))
            if len(pending) == 10:
                flush(m.log_time)
        elif not (m.topic.endswith('/command') and int(decode(m).state_seq) in drop_commands):
            w.write(index[m.topic], m.log_time, _current_bytes(m, decode(m)))
    flush(last)
    w.close()
    return batches


def test_bags_of_batched_hand_inputs_read_as_the_old_ones(tmp_path: Path) -> None:
    """The reference bag rewritten with HandInputs batches reads to the same trace (less the
    commands left out), and the controller check's plan takes the answered states from the
    batches: a state whose command the recorder lost is still replayed."""
    from haptic_topology.bag.controller_check import controller_plan

    old = open_bag(REFERENCE)
    assert '/haptic/hand' in old.metadata_topics()
    states = [int(it.seq) for it in controller_plan(old).items() if it.seq >= 0]
    drop = set(states[100:110]) | {states[-1]}
    new = tmp_path / 'batched'
    assert _batched_copy(REFERENCE, new, drop) >= len(states) // 10
    plan = controller_plan(open_bag(new))
    assert [int(it.seq) for it in plan.items() if it.seq >= 0] == states
    assert not drop & {seq for seq, _, _ in plan.recorded_commands()}
    a, b = read_graph_bag(REFERENCE, 'fig8', 3).trace, read_graph_bag(new, 'fig8', 3).trace
    assert len(a) == len(b)
    kept = ~np.isin(a.seq, list(drop))
    for col in ('device_pose', 'vt_pose', 'applied'):
        np.testing.assert_array_equal(a.columns[col], b.columns[col], err_msg=col)
    np.testing.assert_array_equal(a.columns['command'][kept], b.columns['command'][kept])
    assert np.all(np.isnan(b.columns['command'][~kept]))


def test_write_many_writes_the_same_bytes_as_write(tmp_path: Path) -> None:
    """The recorder's batch path (``write_many``, straight into mcap's chunk buffer) gives a
    file byte for byte equal to ``write`` one message at a time: two topics, receive times
    out of order across topics, chunks closed by size (small ``chunk_size``) and by flush."""
    names = ['/haptic/device/state', '/haptic/device/command']
    rng = np.random.default_rng(7)
    items = [(int(i % 2), 1_000_000_000 + i * 500_000 + int(rng.integers(0, 900_000)),
              _state_bytes(i)) for i in range(1, 3001)]
    files = []
    for how in ('one', 'many'):
        (tmp_path / how).mkdir()
        w = BagWriter(tmp_path / how / 'bag', [TopicSpec(t, STATE, (make_qos(False, 1),))
                                       for t in names],
                      typestore_with_haptic_msgs(), sources=message_definitions(),
                      chunk_size=20_000)
        for start in range(0, len(items), 700):
            batch = items[start:start + 700]
            if how == 'one':
                assert _mcap_internals(w._mcap) is not None    # the fast path is taken
                for item in batch:
                    w.write(*item)
            else:
                w.write_many(batch)
            w.flush()
        assert w.counts == {'/haptic/device/state': 1500, '/haptic/device/command': 1500}
        w.close()
        files.append((tmp_path / how / 'bag' / 'bag_0.mcap').read_bytes())
    assert len(files[0]) > 50_000 and files[0] == files[1]
    assert [decoder()(m).seq for m in iter_messages(open_bag(tmp_path / 'many' / 'bag'))][:3] == [
        1, 2, 3]


def test_bag_states_counts_the_device_states_the_bag_holds() -> None:
    """``bag_states`` and ``bag_commands`` (summary.json; the loop table's ``states``) are the
    numbers of the run's DeviceState and DeviceCommand messages in the bag, the idle ones
    before engagement included; the trace has a row per state from the first running one
    on."""
    bag = open_bag(REFERENCE)
    topics = [m.topic for m in iter_messages(bag)]
    states = sum(1 for t in topics if t.endswith('haptic/device/state'))
    commands = sum(1 for t in topics if t.endswith('haptic/device/command'))
    run = read_graph_bag(REFERENCE, 'fig8', 3)
    assert run.loop['bag_states'] == states
    assert run.loop['bag_commands'] == commands
    assert len(run.trace.t) < states
