"""Node parameters declared once (name, default, description, range) and params files checked
against them before rclpy sees them.

rclpy's own handling of a ROS 2 params file is lenient where it hurts: a misspelt parameter
is silently ignored (the node runs on its default), and a YAML error comes back as an rcl
error string without the file name. :func:`check_params_file` reads the file first and raises
one :class:`~haptic_topology.errors.ConfigError` naming the file, the node section, the key and
what was expected:

* missing file, YAML syntax error (line and column), not a mapping;
* a node section without ``ros__parameters``, an unknown node name;
* an unknown parameter of a node whose parameters are known;
* a wrong type (ROS typing: ``1000`` is an integer, a double parameter needs ``1000.0``;
  lists must be homogeneous), a value out of range, a string not among the choices.

The file layout is the one of ``ros2 run ... --params-file``: ``<node name>: {ros__parameters:
{...}}``, where the node name may carry a namespace (``/ns/device_driver``) or be a wildcard
(``/**``, ``/**/device_driver``, ``device_*``); a wildcard's parameters must be known to at
least one node it matches, unless it also matches a node whose parameters this process does
not know (``known`` maps it to None): then unknown names pass. The tables of this package's
nodes are generated from their settings dataclasses (:mod:`haptic_topology.config.settings`).
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from haptic_topology.errors import ConfigError
from haptic_topology.validate import load_yaml


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter. ``lo``/``hi``: inclusive range of a number; ``choices``: the
    allowed strings; ``read_only``: may not change while the node runs."""

    name: str
    default: Any
    description: str
    read_only: bool = True
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] | None = None

    def kind(self) -> str:
        return ros_type(self.default)


#: Parameters every rclpy node declares itself (not in our tables, never refused).
ROS_BUILTIN = frozenset({'use_sim_time'})

#: Parameters of a node, by name.
NodeParams = Mapping[str, ParamSpec]


def specs(*items: ParamSpec) -> dict[str, ParamSpec]:
    return {p.name: p for p in items}


def ros_type(value: Any) -> str:
    """The ROS parameter type a YAML value gets (``bool``, ``integer``, ``double``, ``string``,
    ``<type> array``), or a description of why it has none."""
    if isinstance(value, bool):
        return 'bool'
    if isinstance(value, int):
        return 'integer'
    if isinstance(value, float):
        return 'double'
    if isinstance(value, str):
        return 'string'
    if isinstance(value, (list, tuple)):
        if not value:
            return 'empty array'
        kinds = {ros_type(v) for v in value}
        if len(kinds) != 1 or next(iter(kinds)).endswith('array'):
            return 'mixed array'
        return f'{next(iter(kinds))} array'
    return type(value).__name__


def check_value(spec: ParamSpec, value: Any, where: str) -> None:
    """Raise :class:`~haptic_topology.errors.ConfigError` (``where``: file and key) unless
    ``value`` fits ``spec``."""
    want, got = spec.kind(), ros_type(value)
    if got != want:
        hint = ''
        if want == 'double' and got == 'integer':
            hint = f' (write {value}.0)'
        elif want == 'double array' and got in ('integer array', 'mixed array'):
            hint = ' (write every entry with a decimal point, e.g. 1.0)'
        raise ConfigError(f'{where}: expected {_article(want)}{hint}, got {got} {value!r}')
    if got == 'double' and not math.isfinite(value):
        raise ConfigError(f'{where}: expected a finite number, got {value!r}')
    if got == 'double array' and not all(math.isfinite(v) for v in value):
        raise ConfigError(f'{where}: expected finite numbers, got {value!r}')
    if spec.lo is not None and spec.hi is not None and got in ('integer', 'double'):
        if not spec.lo <= value <= spec.hi:
            raise ConfigError(f'{where}: expected a value in [{spec.lo:g}, {spec.hi:g}], got '
                              f'{value!r}')
    if spec.choices is not None and value not in spec.choices:
        raise ConfigError(f'{where}: expected one of {", ".join(spec.choices)}, got {value!r}')


def _article(kind: str) -> str:
    return f'an {kind}' if kind[0] in 'aeiou' else f'a {kind}'


def _matches(section: str, node: str) -> bool:
    """Whether a params-file node key (maybe namespaced or a wildcard) applies to ``node``."""
    key = section.strip()
    if '*' in key or '?' in key:
        pattern = key.lstrip('/')
        return (fnmatch.fnmatchcase(node, pattern) or fnmatch.fnmatchcase(f'x/{node}', pattern)
                or pattern in ('**', '*'))
    return key.rsplit('/', 1)[-1] == node


def check_params_file(path: str | Path, known: Mapping[str, NodeParams | None],
                      node: str | None = None) -> dict[str, Any]:
    """Check a params file against the known nodes' parameters; return the parsed file.

    ``known``: node name -> its parameters, or None for a node whose parameters this process
    does not know (only the file's structure is checked for it). ``node``: the node being
    started (None: all ``known``); sections are checked for it and names are checked against
    ``known``.
    """
    p = Path(path)
    doc = load_yaml(p)
    targets = [node] if node is not None else list(known)
    for section, body in doc.items():
        where = f'{p}: {section}'
        if not isinstance(section, str):
            raise ConfigError(f'{where}: expected a node name, got {section!r}')
        wildcard = '*' in section or '?' in section
        matched = [n for n in known if _matches(section, n)]
        if not matched and not wildcard:
            raise ConfigError(f'{where}: unknown node (expected one of '
                              f'{", ".join(sorted(known))}, or a wildcard like /**)')
        if not isinstance(body, dict) or set(body) != {'ros__parameters'}:
            got = list(body) if isinstance(body, dict) else body
            raise ConfigError(f'{where}: expected a mapping with the one key ros__parameters, '
                              f'got {got!r}')
        params = body['ros__parameters']
        if params is None:
            continue
        if not isinstance(params, dict):
            raise ConfigError(f'{where}.ros__parameters: expected a mapping of parameter '
                              f'names to values, got {params!r}')
        relevant = [n for n in matched if n in targets]
        if not relevant:
            continue
        _check_section(where, params, [(n, known[n]) for n in relevant], wildcard)
    return doc


def _check_section(where: str, params: Mapping[str, Any],
                   nodes: Sequence[tuple[str, NodeParams | None]], wildcard: bool) -> None:
    known_nodes = [(n, s) for n, s in nodes if s is not None]
    if not known_nodes:
        return
    for key, value in params.items():
        at = f'{where}.ros__parameters.{key}'
        if isinstance(value, dict):
            if any(key in s and s[key].kind() == 'string' for _, s in known_nodes):
                raise ConfigError(f'{at}: expected a string, got a mapping: write it in quotes '
                                  f"({key}: '{{...}}')")
            raise ConfigError(f'{at}: nested parameter groups are not used by these nodes')
        owners = [(n, s[key]) for n, s in known_nodes if key in s]
        if not owners and key in ROS_BUILTIN:
            continue
        if not owners:
            if wildcard and len(known_nodes) < len(nodes):
                continue  # may belong to a node whose parameters this process does not know
            allowed = sorted({k for _, s in known_nodes for k in s})
            names = ', '.join(n for n, _ in known_nodes)
            raise ConfigError(f'{at}: unknown parameter of {names} (expected one of: '
                              f'{", ".join(allowed)})')
        for _, spec in owners:
            check_value(spec, value, at)


def check_overrides(args: Sequence[str], known: Mapping[str, NodeParams | None],
                    node: str | None = None) -> None:
    """Check ``-p name:=value`` / ``-p node:name:=value`` in ROS arguments for unknown names
    (values are checked by the node when it declares them)."""
    targets = [node] if node is not None else list(known)
    for i, a in enumerate(args):
        if a not in ('-p', '--param') or i + 1 >= len(args):
            continue
        item = args[i + 1]
        lhs, sep, _ = item.partition(':=')
        if not sep:
            continue
        target, _, name = lhs.rpartition(':')
        for n in targets:
            spec = known.get(n)
            if spec is None or (target and not _matches(target, n)):
                continue
            if name not in spec and name not in ROS_BUILTIN:
                raise ConfigError(f'-p {item}: unknown parameter of {n} (expected one of: '
                                  f'{", ".join(sorted(spec))})')


def override_value(value: str) -> Any:
    """The value of a ``-p NODE:NAME:=VALUE`` item as ROS reads it: YAML (``50`` an integer,
    ``'{port: 10002}'`` a string); text that is not YAML stays text."""
    try:
        return yaml.safe_load(value)
    except yaml.YAMLError:
        return value


def params_files(args: Sequence[str]) -> list[str]:
    """The ``--params-file`` paths among ROS arguments."""
    return [args[i + 1] for i, a in enumerate(args)
            if a == '--params-file' and i + 1 < len(args)]
