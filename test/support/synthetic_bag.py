"""Test helper: a synthetic lock-step bag of the graph written with the project's writer:
N device states 1 ms apart, each answered by a command naming the newest LMI update the
controller had (one update every 10 states, received 0.2 ms before the state that first
uses it), and the hand inputs in batches of 10 (as lmi_controller sends them). The updates
of ``without`` are left out: a recorder stopped after writing the commands that name one of
them and before writing it (it received the update after them, as a loaded machine may).

    python synthetic_bag.py OUT N
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.bag.reader import field_default
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

TOPICS = {'/haptic/device/state': 'DeviceState', '/haptic/device/command': 'DeviceCommand',
          '/haptic/lmi/update': 'LmiUpdate', '/haptic/hand_inputs': 'HandInputs'}
T0 = 1_700_000_000_000_000_000
UPDATE_EVERY = 10


def _message(store: Any, msgtype: str, **values: Any) -> Any:
    """``msgtype`` with every field at its default (a zero stamp for the header) but
    ``values``."""
    fields = {}
    for name, ftype in store.fielddefs[msgtype][1]:
        if name in values:
            fields[name] = values[name]
        elif name == 'header':
            fields[name] = store.types['std_msgs/msg/Header'](
                store.types['builtin_interfaces/msg/Time'](0, 0), 'base')
        else:
            ok, default = field_default(ftype)
            assert ok, (msgtype, name)
            fields[name] = default
    return store.types[msgtype](**fields)


def _stamp(store: Any, ns: int) -> Any:
    return store.types['std_msgs/msg/Header'](
        store.types['builtin_interfaces/msg/Time'](ns // 10**9, ns % 10**9), 'base')


def write_bag(path: Path, n: int, without: frozenset[int] = frozenset()) -> None:
    """The bag of ``n`` states at ``path`` (module doc)."""
    store = typestore_with_haptic_msgs()
    names = list(TOPICS)
    types = [type_name(TOPICS[t]) for t in names]
    w = BagWriter(path, [TopicSpec(t, m, (make_qos(True, 100),))
                         for t, m in zip(names, types, strict=True)], store,
                  sources=message_definitions(), custom={'scenario': 'fig8'},
                  compression='none')

    def put(i: int, ns: int, msg: Any) -> None:
        w.write(i, ns, bytes(store.serialize_cdr(msg, types[i])))

    v3 = np.array([0.01, 0.02, 0.03])
    hand: list[int] = []
    for s in range(1, n + 1):
        ns = T0 + s * 1_000_000
        if s % UPDATE_EVERY == 1 and s // UPDATE_EVERY + 1 not in without:
            put(2, ns - 200_000, _message(store, types[2], header=_stamp(store, ns - 200_000),
                                          seq=np.uint64(s // UPDATE_EVERY + 1), task_dim=3))
        put(0, ns, _message(store, types[0], header=_stamp(store, ns), seq=s, task_dim=3,
                            pose=v3 * s, twist=v3, hand_wrench=v3, applied_wrench=v3))
        put(1, ns + 300_000, _message(store, types[1], header=_stamp(store, ns + 300_000),
                                      state_seq=s, task_dim=3, wrench=v3 * (s % 7),
                                      vt_pose=v3, vt_twist=v3, update_age=0.0,
                                      update_seq=(s - 1) // UPDATE_EVERY + 1))
        hand.append(s)
        if len(hand) == 10:
            put(3, ns + 400_000, _message(store, types[3], header=_stamp(store, ns), task_dim=3,
                                          seq=np.array(hand, dtype=np.uint64),
                                          state_seq=np.array(hand, dtype=np.uint64),
                                          stamp=[_stamp(store, ns).stamp] * len(hand)))
            hand.clear()
        if s % 200 == 0:
            w.flush()
    w.close()


if __name__ == '__main__':
    write_bag(Path(sys.argv[1]), int(sys.argv[2]))
