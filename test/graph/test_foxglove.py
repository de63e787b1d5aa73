"""Foxglove: the layout in docs/ against the graph's vocabulary and messages, and the live
bridge (``haptic-topology run ... --foxglove``) against a WebSocket client.

The layout check walks every topic and message path the layout names (3D topics, plot series,
diagnostics panels, the user script's inputs and the fields it reads) through the topic
vocabulary (``vocabulary.TOPIC_ROLES``/``TOPIC_TYPES``) and the message definitions (the
.msg files and the ROS 2 Jazzy types of ``rosbags``), so a renamed topic or field fails here.

The live test runs the real graph (recorder, ve_sim, device_driver and foxglove_bridge as
processes) through :func:`haptic_topology.bringup.run.run_graph` and speaks the Foxglove
WebSocket protocol to the bridge with the ``websockets`` package: serverInfo, advertise,
subscribe, binary messageData frames (opcode 1, subscription id, receive time, CDR bytes).
"""

from __future__ import annotations

import copy
import json
import math
import re
import struct
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO

from haptic_topology import vocabulary as vocab
from haptic_topology.bag.writer import MSGDEF_SEPARATOR, schema_text
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs
from haptic_topology.model import frames

LAYOUT = REPO / 'docs' / 'foxglove_layout.json'
#: Panel types the layout may use (the Foxglove app's ids for them).
PANEL_TYPES = {'3D', 'Plot', 'DiagnosticSummary', 'DiagnosticStatusPanel'}
#: What the Foxglove SDK's server accepts (the successor name of foxglove.websocket.v1).
SUBPROTOCOL = 'foxglove.sdk.v1'
WAIT = 90.0




def _absolute(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


# -- the vocabulary -----------------------------------------------------------------------------
def test_every_topic_of_the_vocabulary_has_a_type_and_a_schema() -> None:
    from haptic_topology.nodes.foxglove_bridge import message_class

    assert set(vocab.TOPIC_TYPES) == set(vocab.TOPIC_ROLES)
    store, sources = typestore_with_haptic_msgs(), message_definitions()
    for topic, type_name in vocab.TOPIC_TYPES.items():
        text = schema_text(store, type_name, sources)
        assert text.strip(), topic
        cls = message_class(type_name)
        assert f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}' == type_name


# -- the layout ---------------------------------------------------------------------------------
def _fields(type_name: str) -> dict[str, Any]:
    store = typestore_with_haptic_msgs()
    return dict(store.fielddefs[type_name][1])


_STEP = re.compile(r'\.(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?P<index>\[\d+\])?')
_NUMERIC = re.compile(r'u?int(8|16|32|64)|float(32|64)|bool|byte|char')


def check_path(type_name: str, path: str) -> str | None:
    """None if ``path`` (``.field[i].field...``) leads from ``type_name`` to a number, else
    what is wrong. Array fields must be indexed; nested messages must be walked into."""
    pos, current = 0, type_name
    kind: Any = None
    while pos < len(path):
        m = _STEP.match(path, pos)
        if m is None:
            return f'{type_name}{path}: cannot parse at {path[pos:]!r}'
        fields = _fields(current)
        name = m['name']
        if name not in fields:
            return f'{type_name}{path}: {current} has no field {name!r}'
        node, spec = fields[name]
        kind = node.name
        if kind in ('SEQUENCE', 'ARRAY'):
            if m['index'] is None:
                return f'{type_name}{path}: {name} is an array and needs an index'
            node, spec = spec[0]
            kind = node.name
        elif m['index'] is not None:
            return f'{type_name}{path}: {name} is not an array'
        if kind == 'NAME':
            current = spec
        elif kind == 'BASE':
            if not _NUMERIC.fullmatch(spec[0]):
                return f'{type_name}{path}: {name} is {spec[0]}, not a number'
            if m.end() != len(path):
                return f'{type_name}{path}: {name} is a number, the path goes on'
        pos = m.end()
    if kind != 'BASE':
        return f'{type_name}{path}: does not end at a number'
    return None


def _script_outputs(source: str) -> set[str]:
    body = re.search(r'type Output = \{(?P<body>[^}]*)\}', source)
    assert body, 'the user script declares no `type Output = {...}`'
    return set(re.findall(r'(\w+)\s*:', body['body']))


def _layout_tree_ids(node: Any) -> list[str]:
    if isinstance(node, str):
        return [node]
    return _layout_tree_ids(node['first']) + _layout_tree_ids(node['second'])


def layout_problems(layout: dict[str, Any]) -> list[str]:
    """Everything in ``layout`` that does not exist in the graph (empty: all found)."""
    from haptic_topology.bringup import watch

    types = {_absolute(t): n for t, n in vocab.TOPIC_TYPES.items()}
    problems: list[str] = []
    for key in ('configById', 'layout', 'globalVariables', 'userNodes', 'playbackConfig'):
        if key not in layout:
            problems.append(f'no {key}')
    config = layout.get('configById', {})
    ids = _layout_tree_ids(layout.get('layout', {}))
    if sorted(ids) != sorted(config):
        problems.append(f'panels in the layout tree {sorted(ids)} != configured {sorted(config)}')
    for pid in config:
        if pid.split('!')[0] not in PANEL_TYPES:
            problems.append(f'{pid}: unknown panel type')

    # User scripts: inputs are graph topics, the fields read exist, the output is declared.
    outputs: dict[str, set[str]] = {}
    for sid, script in layout.get('userNodes', {}).items():
        src = script['sourceCode']
        inputs = json.loads(re.search(r'export const inputs = (\[[^\]]*\]);', src)[1])
        output = re.search(r'export const output = "([^"]+)";', src)[1]
        if not output.startswith('/studio_script/'):
            problems.append(f'user script {sid}: output {output} must start with /studio_script/')
        outputs[output] = _script_outputs(src)
        read = {'state': 'haptic_topology_msgs/msg/DeviceState',
                'path': 'haptic_topology_msgs/msg/VtPath',
                'diag': 'diagnostic_msgs/msg/DiagnosticArray'}
        for topic in inputs:
            if topic not in types:
                problems.append(f'user script {sid}: input {topic} is not a graph topic')
        for var, type_name in read.items():
            if types.get(inputs[list(read).index(var)]) != type_name:
                problems.append(f'user script {sid}: input {var} is not {type_name}')
            for name in set(re.findall(rf'\b{var}\.(\w+)', src)):
                if name not in _fields(type_name):
                    problems.append(f'user script {sid}: {type_name} has no field {name!r}')

    def check_series(pid: str, value: str) -> None:
        topic, dot, path = value.partition('.')
        if topic in outputs:
            if not dot or path not in outputs[topic]:
                problems.append(f'{pid}: {value}: the user script outputs no {path!r}')
        elif topic not in types:
            problems.append(f'{pid}: {value}: {topic} is not a graph topic')
        else:
            problem = check_path(types[topic], '.' + path)
            if problem:
                problems.append(f'{pid}: {value}: {problem}')

    for pid, cfg in config.items():
        kind = pid.split('!')[0]
        if kind == '3D':
            for topic in cfg.get('topics', {}):
                if topic not in types:
                    problems.append(f'{pid}: {topic} is not a graph topic')
            frame_ids = [cfg.get('followTf')] + [layer.get('frameId')
                                                  for layer in cfg.get('layers', {}).values()]
            for f in frame_ids:
                if f != frames.WORLD:
                    problems.append(f'{pid}: frame {f!r} is not {frames.WORLD!r}')
        elif kind == 'Plot':
            if not cfg.get('paths'):
                problems.append(f'{pid}: no series')
            for series in cfg.get('paths', []):
                check_series(pid, series['value'])
        else:   # diagnostics panels
            if cfg.get('topicToRender') != _absolute(vocab.TOPIC_DIAGNOSTICS):
                problems.append(f'{pid}: topicToRender is not {vocab.TOPIC_DIAGNOSTICS}')
            name = cfg.get('selectedName')
            statuses = (watch.CONTROLLER_STATUS, watch.DEVICE_STATUS, watch.VE_STATUS,
                        watch.RECORDER_STATUS)
            if name is not None and name not in statuses:
                problems.append(f'{pid}: no node reports a status {name!r}')
    return problems


@pytest.fixture(scope='module')
def layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text(encoding='utf-8'))


def test_layout_names_only_topics_and_fields_that_exist(layout: dict[str, Any]) -> None:
    assert layout_problems(layout) == []


def test_layout_shows_linkage_device_arrows_distance_forces_and_health(
        layout: dict[str, Any]) -> None:
    config = layout['configById']
    three_d = [c for p, c in config.items() if p.startswith('3D!')]
    assert three_d and _absolute(vocab.TOPIC_MARKERS) in three_d[0]['topics']
    assert _absolute(vocab.TOPIC_ROBOT_DESCRIPTION) in three_d[0]['topics']
    values = [s['value'] for p, c in config.items() if p.startswith('Plot!')
              for s in c['paths']]
    assert any(v.endswith('.distance_m') for v in values)              # device-VT distance
    assert any('.applied_wrench[' in v for v in values)                # forces
    assert any('.update_age' in v for v in values)                     # loop health
    assert any(p.startswith('DiagnosticSummary!') for p in config)


@pytest.mark.parametrize(('where', 'old', 'new'), [
    ('Plot!forces', '.applied_wrench[0]', '.applied_force[0]'),        # a renamed field
    ('Plot!positions', '/haptic/device/state.', '/haptic/device/states.'),  # a renamed topic
    ('Plot!positions', '.pose[0]', '.pose'),                           # an array, no index
    ('Plot!distance', '.distance_m', '.distance'),                     # not a script output
])
def test_layout_check_fails_on_a_wrong_reference(layout: dict[str, Any], where: str, old: str,
                                                 new: str) -> None:
    bad = copy.deepcopy(layout)
    paths = bad['configById'][where]['paths']
    assert any(old in s['value'] for s in paths)
    for s in paths:
        s['value'] = s['value'].replace(old, new, 1)
    assert layout_problems(bad)


def test_layout_check_fails_on_a_field_the_user_script_reads_that_does_not_exist(
        layout: dict[str, Any]) -> None:
    bad = copy.deepcopy(layout)
    script = next(iter(bad['userNodes'].values()))
    assert 'path.hand_pose' in script['sourceCode']
    script['sourceCode'] = script['sourceCode'].replace('path.hand_pose', 'path.vt_pose')
    assert any("no field 'vt_pose'" in p for p in layout_problems(bad))


# -- the run option -----------------------------------------------------------------------------
@pytest.mark.parametrize(('argv', 'port'), [([], None), (['--foxglove'], 8765),
                                            (['--foxglove', '9001'], 9001)])
def test_run_foxglove_option(argv: list[str], port: int | None) -> None:
    from haptic_topology.cli import build_parser

    args = build_parser().parse_args(['run', 'fig8', *argv])
    assert args.foxglove == port
    assert args.foxglove_host == '127.0.0.1'


# -- the live bridge ----------------------------------------------------------------------------
def _decode_with_schema(schema: str, type_name: str, data: bytes) -> Any:
    """Deserialise ``data`` with a typestore built from the advertised ``schema`` text alone
    (what a Foxglove client has), not from this project's definitions."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    parts = schema.split(MSGDEF_SEPARATOR)
    types = dict(get_types_from_msg(parts[0], type_name))
    for part in parts[1:]:
        head, _, text = part.partition('\n')
        assert head.startswith('MSG: '), head
        types.update(get_types_from_msg(text, head[5:].strip()))
    store.register(types)
    return store.deserialize_cdr(data, type_name)


@pytest.mark.graph
@pytest.mark.timeout(240)
def test_bridge_serves_the_live_graph_to_a_websocket_client(tmp_path: Path) -> None:
    from bridge_graph import BridgeGraph
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from websockets.sync.client import connect

    from haptic_topology_msgs.msg import DeviceState

    run = BridgeGraph('fig8', 6.0, tmp_path / 'bag', 'foxglove_test', WAIT)
    bridge, spin_until, deadline = run.bridge, run.spin_until, run.deadline
    state_topic = _absolute(vocab.TOPIC_STATE)
    marker_topic = _absolute(vocab.TOPIC_MARKERS)
    try:
        spin_until(lambda: 'port' in bridge, 'the bridge reports its port')
        channels: dict[str, dict[str, Any]] = {}
        received: dict[str, list[bytes]] = {state_topic: [], marker_topic: []}
        with connect(f'ws://127.0.0.1:{bridge["port"]}', subprotocols=[SUBPROTOCOL],
                     open_timeout=30) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            first = json.loads(ws.recv(timeout=30))
            assert first['op'] == 'serverInfo'
            while not {state_topic, marker_topic} <= set(channels):
                msg = json.loads(ws.recv(timeout=30))
                if msg['op'] == 'advertise':
                    channels.update({c['topic']: c for c in msg['channels']})
            subs = {1: state_topic, 2: marker_topic}
            ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                {'id': sid, 'channelId': channels[t]['id']} for sid, t in subs.items()]}))
            while min(len(v) for v in received.values()) < 3:
                assert time.monotonic() < deadline, (
                    f'messages on {state_topic} and {marker_topic} not within {WAIT:g} s: '
                    f'{ {t: len(v) for t, v in received.items()} }')
                frame = ws.recv(timeout=30)
                if isinstance(frame, bytes) and frame[0] == 1:      # messageData
                    sid, _stamp = struct.unpack_from('<IQ', frame, 1)
                    received[subs[sid]].append(frame[13:])
        # Every advertised channel: a graph topic, its type, ROS 2 CDR with .msg schemas.
        types = {_absolute(t): n for t, n in vocab.TOPIC_TYPES.items()}
        assert set(channels) == set(types)
        store, sources = typestore_with_haptic_msgs(), message_definitions()
        for topic, ch in channels.items():
            assert (ch['encoding'], ch['schemaEncoding']) == ('cdr', 'ros2msg'), topic
            assert ch['schemaName'] == types[topic], topic
            assert ch['schema'] == schema_text(store, types[topic], sources), topic
        # The graph's publishers use the vocabulary's types.
        for topic, type_name in types.items():
            for info in run.node.get_publishers_info_by_topic(topic):
                assert info.topic_type == type_name, (topic, info.node_name)
        # The forwarded bytes are the messages: rclpy's and the advertised schema agree.
        for data in received[state_topic]:
            state = deserialize_message(data, DeviceState)
            assert state.seq > 0 and state.task_dim == 3
            values = [*state.pose, *state.twist, *state.hand_wrench, *state.applied_wrench]
            assert len(state.pose) == 3 and all(math.isfinite(v) for v in values)
            other = _decode_with_schema(channels[state_topic]['schema'],
                                        types[state_topic], data)
            assert (other.seq, list(other.pose)) == (state.seq, list(state.pose))
        for data in received[marker_topic]:
            markers = deserialize_message(data, MarkerArray)
            assert {'linkage', 'grasp'} <= {m.ns for m in markers.markers}
        run.join()
    finally:
        run.close()
