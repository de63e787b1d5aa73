"""The processes of each layout of ``haptic-topology run``, and its options that become ROS
arguments or commands of those processes: ``-p NODE:NAME:=VALUE``, ``--node-prefix
NODE=COMMAND`` and ``--loop-cpu CPU|auto|off``. Each is checked for its form here, before anything
starts; the nodes check names and values when they start."""

from __future__ import annotations

import os
import shlex
from pathlib import Path
from typing import Any

from haptic_topology.config.params import override_value
from haptic_topology.errors import ConfigError
from haptic_topology.validate import load_yaml

NODES = ('recorder', 've_sim', 'lmi_controller', 'device_driver')
CLOCKS = ('wall', 'lockstep')
#: Layout -> the processes it starts (node modules), in start order.
LAYOUTS = {'hosted': ('recorder', 've_sim', 'device_driver'), 'separate': NODES,
           'composed': ('composed',), 'thread': ('recorder', 've_sim', 'device_driver')}
#: The Foxglove bridge's process name (``run --foxglove``).
FOXGLOVE_NODE = 'foxglove_bridge'


def param_overrides(items: list[str]) -> list[str]:
    """``-p NODE:NAME:=VALUE`` items as ROS arguments (each checked for its form here; the
    node checks the name and the value when it starts). A VALUE that is a YAML mapping
    (``device_driver:backend_options:={port: 10002}``) is passed on quoted, as the string
    parameter that carries it: ROS takes no mapping as a parameter value."""
    out: list[str] = []
    known = (*NODES, FOXGLOVE_NODE)
    for item in items:
        target, sep, value = item.partition(':=')
        node, colon, name = target.partition(':')
        if not sep or not colon or node not in known or not name or not value.strip():
            raise ConfigError(f'-p: expected NODE:NAME:=VALUE with NODE one of '
                              f'{", ".join(known)}, got {item!r}')
        if isinstance(override_value(value), dict):
            item = f"{target}:='{value.replace(chr(39), chr(39) * 2)}'"
        out += ['-p', item]
    return out


def loop_cpu_overrides(cpu: int | None, layout: str) -> list[str]:
    """``--loop-cpu``: ``-p`` arguments that keep CPU ``cpu`` for the loop process (its
    ``cpu_affinity``) and pin every other thread of the graph (``device_driver``'s own,
    ``ve_sim``'s, the recorder's, ``foxglove_bridge``'s) to the other CPUs this command may
    use; none for ``None``."""
    if cpu is None:
        return []
    if layout != 'hosted':
        raise ConfigError(f'--loop-cpu: needs --layout hosted (the loop process), got {layout}')
    cpus = sorted(os.sched_getaffinity(0))
    rest = [c for c in cpus if c != cpu]
    if cpu not in cpus or not rest:
        raise ConfigError(f'--loop-cpu: expected one of the CPUs {cpus} this command may use, '
                          f'with at least one other left for the nodes, got {cpu}')
    nodes = ','.join(map(str, rest))
    return ['-p', f'device_driver:cpu_affinity:=[{cpu}]',
            '-p', f'device_driver:node_cpu_affinity:=[{nodes}]',
            *[x for node in ('ve_sim', 'recorder', FOXGLOVE_NODE)
              for x in ('-p', f'{node}:cpu_affinity:=[{nodes}]')]]


def _settles(name: str, value: Any) -> bool:
    """Whether parameter ``name`` = ``value`` rules out ``--loop-cpu auto``: a node pinned
    already (``*cpu_affinity`` other than ``[-1]``), or one under SCHED_IDLE (``sched_policy:
    idle``), which, kept off the loop's CPU beside a busy program, would get no CPU time."""
    return ((name.endswith('cpu_affinity') and value not in ([-1], '[-1]'))
            or (name == 'sched_policy' and value == 'idle'))


def _settled(doc: Any) -> bool:
    """Whether a params document sets a parameter that rules out ``auto`` (:func:`_settles`)."""
    if isinstance(doc, dict):
        return any(_settles(str(k), v) or _settled(v) for k, v in doc.items())
    return isinstance(doc, list) and any(_settled(v) for v in doc)


def loop_cpu_choice(value: str | None, layout: str, clock: str, params: Path,
                    items: list[str]) -> int | str | None:
    """``--loop-cpu``: a CPU number (:func:`loop_cpu_overrides`), ``'auto'`` (pin only while
    other software keeps the machine busy: :mod:`haptic_topology.bringup.partition`) or None
    (``off``: no pinning but the nodes' own ``cpu_affinity``). Without the option: ``auto``
    for the hosted layout on the wall clock unless the params file or a ``-p`` item pins a
    node already or puts one under SCHED_IDLE (:func:`_settles`), else ``off``."""
    if value is None:
        settled = any(_settles(target.rpartition(':')[2], v.strip())
                      for target, _, v in (item.partition(':=') for item in items))
        if layout != 'hosted' or clock != 'wall' or settled or _settled(load_yaml(params)):
            return None
        return 'auto'
    if value == 'off':
        return None
    if value == 'auto':
        if layout != 'hosted' or clock != 'wall':
            raise ConfigError(f'--loop-cpu: auto needs --layout hosted and --clock wall, got '
                              f'--layout {layout} --clock {clock}')
        return 'auto'
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f'--loop-cpu: expected a CPU number, auto or off, got {value!r}') \
            from None


def node_prefixes(items: list[str], layout: str) -> dict[str, list[str]]:
    """``--node-prefix NODE=COMMAND`` values -> ``{NODE: argv}`` (NODE a process of
    ``layout``; COMMAND split as a shell would, e.g. ``ip netns exec ht_ve``)."""
    out: dict[str, list[str]] = {}
    for item in items:
        node, sep, command = item.partition('=')
        if not sep or node not in LAYOUTS.get(layout, ()) or not shlex.split(command):
            raise ConfigError(f'--node-prefix: expected NODE=COMMAND with NODE one of '
                              f'{", ".join(LAYOUTS.get(layout, ()))}, got {item!r}')
        out[node] = shlex.split(command)
    return out
