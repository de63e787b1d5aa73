"""Parameter declaration from the settings classes, and the check of params files and ``-p``
overrides before rclpy parses them."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
    ParameterUninitializedException,
)
from rclpy.node import Node

from haptic_topology.config.params import (
    NodeParams,
    ParamSpec,
    check_overrides,
    check_params_file,
    params_files,
)
from haptic_topology.config.settings import NodeSettings, param_specs
from haptic_topology.errors import ConfigError


def declare(node: Node, name: str, default: Any, description: str, *, read_only: bool = True,
            lo: float | None = None, hi: float | None = None,
            choices: Sequence[str] | None = None) -> Any:
    """Declare a parameter with description, range and read-only flag; return its value.

    rclpy refuses a value of the wrong type or outside the descriptor's range (a
    :class:`ConfigError` naming the node and the parameter); the value itself is checked
    once, against its :class:`ParamSpec`, where the settings are built
    (:func:`declare_settings`, :class:`~haptic_topology.config.settings.NodeSettings`).
    """
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if choices is not None:
        desc.additional_constraints = 'one of: ' + ', '.join(choices)
    if lo is not None and hi is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f'range given for non-numeric parameter {name}')
        if isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    where = f'{node.get_name()}: parameter {name}'
    try:
        value = node.declare_parameter(name, default, desc).value
    except InvalidParameterTypeException as exc:
        raise ConfigError(f'{where}: expected {type(default).__name__}, got {exc}') from None
    except InvalidParameterValueException as exc:
        raise ConfigError(f'{where}: {exc}') from None
    except (ParameterException, ParameterUninitializedException) as exc:
        raise ConfigError(f'{where}: {exc}') from None
    return value


def declare_spec(node: Node, spec: ParamSpec, default: Any = None) -> Any:
    """:func:`declare` from a :class:`ParamSpec` (``default`` overrides the spec's, e.g. a
    value taken from the scenario; it must have the spec's type)."""
    return declare(node, spec.name, spec.default if default is None else default,
                   spec.description, read_only=spec.read_only, lo=spec.lo, hi=spec.hi,
                   choices=spec.choices)


S = TypeVar('S', bound=NodeSettings)


def declare_settings(node: Node, cls: type[S],
                     scenario_defaults: Mapping[str, Any] | None = None) -> S:
    """Declare every parameter of the settings class ``cls`` on ``node`` (description, range,
    read-only flag from its fields) and return the frozen settings.

    ``scenario_defaults``: defaults to declare instead of the table's (see
    :func:`haptic_topology.config.settings.scenario_defaults`). Parameters the node has declared
    already (e.g. ``scenario``, read first to load the scenario the defaults come from) keep
    their value. A bad value raises :class:`ConfigError` naming the node and the parameter.
    """
    defaults = scenario_defaults or {}
    values: dict[str, Any] = {}
    for name, spec in param_specs(cls).items():
        if node.has_parameter(name):
            values[name] = node.get_parameter(name).value
        else:
            values[name] = declare_spec(node, spec, defaults.get(name))
    try:
        return cls.from_values(values)
    except ConfigError as exc:
        node_name = node.get_name()
        text = str(exc)
        if node_name != cls.NODE and text.startswith(f'{cls.NODE}: '):
            text = f'{node_name}: {text[len(cls.NODE) + 2:]}'
        raise ConfigError(text) from None


def check_config_args(argv: Sequence[str], known: Mapping[str, NodeParams | None],
                      node: str | None) -> None:
    """Check every ``--params-file`` and ``-p`` name of ``argv`` before rclpy parses them."""
    ros_args = _ros_args(argv)
    for path in params_files(ros_args):
        check_params_file(path, known, node)
    check_overrides(ros_args, known, node)


def _ros_args(argv: Sequence[str]) -> list[str]:
    out: list[str] = []
    inside = False
    for a in argv:
        if a == '--ros-args':
            inside = True
        elif a == '--':
            inside = False
        elif inside:
            out.append(a)
    return out
