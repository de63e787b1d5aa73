"""Child process of ``test/unit/bag/test_bag_kill.py``: writes a bag with
:class:`~haptic_topology.bag.writer.BagWriter` as the recorder does (its constructor's
arguments, batches through ``write_many``, a ``flush`` every 0.1 s of message time, splits by
size and by duration, ``close`` at the end) and reports on stdout, one line each, written
with ``os.write`` (so a line is in the pipe once written, whatever happens after):

- ``open`` once the writer is constructed;
- ``flushed N`` after each ``flush()`` returned: the first N messages are flushed;
- ``closed N`` after ``close()`` returned;
- ``paused KIND`` when it stops at the chosen point (see ``PAUSE``) to be killed there.

Message ``i`` (1, 2, ...) goes to topic ``i % 2``: a ``DeviceState`` with ``seq = i`` or a
``std_msgs/String`` ``'i'``; its receive time is ``T0 + i * 0.5 ms``.

``argv``: bag path, messages, max_bag_size (bytes), max_bag_duration (s), end ('plain', or
'split': keep writing after the given count until a flush splits the bag, then close, so
that ``close`` removes an empty last file), pause (``-`` for none, else ``PHASE:KIND:N``:
stop before the N-th (0-based) event ``KIND`` of :data:`PAUSE` counted in ``PHASE``, ``run``
(the whole life) or ``close`` (inside ``close()``). The pause point is found by a
``sys.addaudithook`` hook on the file operations the writer makes, so the writer itself has
no test hook.)
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.messages.definitions import (
    message_definitions,
    type_name,
    typestore_with_haptic_msgs,
)

STATE = type_name('DeviceState')
T0 = 1_800_000_000_000_000_000
STEP_NS = 500_000
BATCH = 20                  # messages per write_many (the recorder drains every 10 ms)
FLUSH_NS = 100_000_000      # a flush every 0.1 s of message time
CUSTOM = {'recorded_by': 'haptic_topology recorder', 'scenario': 'fig8',
          'graph_id': 'fig8-killtest'}
TOPICS = [TopicSpec('/haptic/device/state', STATE, (make_qos(False, 1),)),
          TopicSpec('/chatter', 'std_msgs/msg/String', (make_qos(True, 10),))]

#: Event kinds: (audit event, test on its first argument).
PAUSE = {
    'mkdir': ('os.mkdir', lambda p: True),
    'mcap_open': ('open', lambda p: p.endswith('.mcap')),        # before the file exists
    'spill_open': ('open', lambda p: os.path.isdir(p)),          # the file exists, empty
    'meta_open': ('open', lambda p: p.endswith('.metadata.yaml.tmp')),
    'rename': ('os.rename', lambda p: True),                     # metadata or the bag dir
    'remove': ('os.remove', lambda p: p.endswith('.mcap')),
}


def report(line: str) -> None:
    os.write(1, (line + '\n').encode())


def message(store: Any, i: int) -> tuple[int, int, bytes]:
    ns = T0 + i * STEP_NS
    if i % 2:
        return 1, ns, bytes(store.serialize_cdr(store.types['std_msgs/msg/String'](str(i)),
                                                'std_msgs/msg/String'))
    header = store.types['std_msgs/msg/Header'](
        store.types['builtin_interfaces/msg/Time'](i // 1000, i % 1000), 'base')
    v = np.array([0.1, 0.2, 0.3]) * i
    return 0, ns, bytes(store.serialize_cdr(
        store.types[STATE](header, i, 3, v, v, v, v, 0, np.zeros(0), 0), STATE))


def install_pause(spec: str, phase: list[str]) -> None:
    if spec == '-':
        return
    want_phase, kind, n = spec.split(':')
    event, test = PAUSE[kind]
    seen = [0]

    def hook(name: str, args: tuple[Any, ...]) -> None:
        if name != event or (want_phase == 'close' and phase[0] != 'close'):
            return
        first = args[0] if args else None
        if not isinstance(first, (str, bytes, os.PathLike)) or not test(os.fsdecode(first)):
            return
        seen[0] += 1
        if seen[0] - 1 == int(n):
            report(f'paused {kind}')
            while True:         # until the test kills this process
                time.sleep(3600)

    sys.addaudithook(hook)


def main() -> None:
    path, total, size, duration, end, pause = sys.argv[1:7]
    phase = ['run']
    install_pause(pause, phase)
    store = typestore_with_haptic_msgs()
    writer = BagWriter(Path(path), TOPICS, store, sources=message_definitions(),
                       compression='zstd', custom=CUSTOM, max_bag_size=int(size),
                       max_bag_duration=float(duration))
    report('open')
    i, next_flush = 0, T0 + FLUSH_NS
    files = len(writer.files)
    while True:
        batch = [message(store, k) for k in range(i + 1, i + BATCH + 1)]
        writer.write_many(batch)
        i += BATCH
        if batch[-1][1] >= next_flush:
            writer.flush()
            next_flush += FLUSH_NS
            report(f'flushed {i}')
            split, files = len(writer.files) > files, len(writer.files)
            if i >= int(total) and (end == 'plain' or split):
                break
    phase[0] = 'close'
    writer.close()
    report(f'closed {i}')


if __name__ == '__main__':
    main()
