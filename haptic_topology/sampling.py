"""A sampling profiler for a running node process (where the CPU goes, per thread).

Set ``HAPTIC_TOPOLOGY_PROFILE=<file>`` in a node's environment: a daemon thread then samples
every thread's Python stack (``sys._current_frames``) every ``HAPTIC_TOPOLOGY_PROFILE_PERIOD``
seconds (default 0.001) and, when the process exits, writes the counts as collapsed stacks
(``thread;outer;...;inner count`` per line, the format of flamegraph tools) to the file. A
sample counts only threads that were running Python code or in a C call made from it: a
thread blocked in ``sleep``/``wait`` shows that call as its innermost frame, so filter on
it when reading. Used by ``bench/profile_graph.py``; the cost is one stack walk per thread
and sample (a few us each).
"""

from __future__ import annotations

import atexit
import os
import sys
import threading
from collections import Counter
from collections.abc import Callable
from types import FrameType

ENV = 'HAPTIC_TOPOLOGY_PROFILE'
PERIOD_ENV = 'HAPTIC_TOPOLOGY_PROFILE_PERIOD'


def _stack(frame: FrameType | None) -> str:
    parts = []
    while frame is not None:
        code = frame.f_code
        parts.append(f'{code.co_name} ({os.path.basename(code.co_filename)}:'
                     f'{code.co_firstlineno})')
        frame = frame.f_back
    return ';'.join(reversed(parts))


def start_from_env() -> None:
    """Start the sampler if :data:`ENV` names an output file (once per process)."""
    path = os.environ.get(ENV)
    if not path:
        return
    period = float(os.environ.get(PERIOD_ENV, '0.001'))
    counts: Counter[str] = Counter()
    me = threading.get_ident()
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(period):
            names = {t.ident: t.name for t in threading.enumerate()}
            for ident, frame in sys._current_frames().items():
                if ident != me:
                    counts[f'{names.get(ident, ident)};{_stack(frame)}'] += 1

    def dump() -> None:
        stop.set()
        with open(f'{path}.{os.getpid()}', 'w', encoding='utf-8') as f:
            for stack, n in counts.most_common():
                f.write(f'{stack} {n}\n')

    threading.Thread(target=sample, name='sampler', daemon=True).start()
    atexit.register(dump)
    _dumps.append(dump)


#: The running sampler's dump (at most one): node processes end with ``os._exit``, which runs
#: no ``atexit`` function, so they call :func:`dump_now` first.
_dumps: list[Callable[[], None]] = []


def dump_now() -> None:
    """Write the samples now (once) if the sampler runs in this process."""
    while _dumps:
        fn = _dumps.pop()
        atexit.unregister(fn)
        fn()
