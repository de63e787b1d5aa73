"""Sample messages for the tests, generated from the .msg definitions themselves.

Every field gets a distinct non-default value (arrays get several elements), derived from the
field's position so the publisher and subscriber processes compute the same sample. Because the
samples come from the definitions, the tests keep covering every field when a .msg changes.
Plain data: nested messages are dicts, arrays are lists (of dicts for arrays of messages).
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

_INT_BITS = {'int8': 7, 'int16': 15, 'int32': 31, 'int64': 63,
             'uint8': 8, 'uint16': 16, 'uint32': 32, 'uint64': 64, 'byte': 8, 'char': 8}


def _base_value(kind: str, salt: int) -> Any:
    if kind == 'bool':
        return True
    if kind == 'string':
        return f'value_{salt}'
    if kind in ('float32', 'float64'):
        return (salt + 1) * 0.25 * (-1 if salt % 2 else 1)  # dyadic: exact in float32 too
    if kind in _INT_BITS:
        bits = _INT_BITS[kind]
        return 1 + salt % ((1 << bits) - 2) if bits < 63 else (1 << 40) + salt
    raise NotImplementedError(f'sample value for base type {kind!r}')


def sample_values(store: Typestore, type_name: str, salt: int = 1) -> dict[str, Any]:
    """Non-default values for every field of ``type_name`` (rosbags type name)."""
    out: dict[str, Any] = {}
    for i, (field, (node, desc)) in enumerate(store.fielddefs[type_name][1]):
        s = salt * 31 + i
        if node.name == 'BASE':
            out[field] = _base_value(desc[0], s)
        elif node.name == 'NAME':
            out[field] = sample_values(store, desc, s)
        elif node.name in ('SEQUENCE', 'ARRAY'):
            (elem_node, elem_desc), count = desc
            n = count if node.name == 'ARRAY' else 3 + i % 4
            if elem_node.name == 'NAME':
                out[field] = [sample_values(store, elem_desc, s + k) for k in range(n)]
            elif elem_node.name == 'BASE':
                out[field] = [_base_value(elem_desc[0], s + k) for k in range(n)]
            else:
                raise NotImplementedError(f'{type_name}.{field}: arrays of {elem_node}')
        else:
            raise NotImplementedError(f'{type_name}.{field}: node type {node}')
    return out


def rclpy_type(name: str) -> Any:
    """The rclpy message class ``haptic_topology_msgs.msg.<name>``."""
    return getattr(importlib.import_module('haptic_topology_msgs.msg'), name)


def fill_rclpy(msg: Any, values: dict[str, Any]) -> Any:
    """Set every field of rclpy message ``msg`` from ``values`` (nested dicts for submessages,
    lists of dicts for arrays of them)."""
    types = msg.get_fields_and_field_types()
    for field, value in values.items():
        if isinstance(value, dict):
            fill_rclpy(getattr(msg, field), value)
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            elem = _rclpy_class(types[field])
            setattr(msg, field, [fill_rclpy(elem(), v) for v in value])
        else:
            setattr(msg, field, value)
    return msg


def _rclpy_class(field_type: str) -> Any:
    """The element class of an rclpy field type such as ``sequence<builtin_interfaces/Time>``."""
    name = field_type.removeprefix('sequence<').split(',')[0].rstrip('>').split('[')[0]
    pkg, _, cls = name.partition('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), cls)


def rclpy_to_dict(msg: Any) -> dict[str, Any]:
    """Every field of an rclpy message as plain Python data (arrays become lists)."""
    out: dict[str, Any] = {}
    for field in msg.get_fields_and_field_types():
        value = getattr(msg, field)
        if hasattr(value, 'get_fields_and_field_types'):
            out[field] = rclpy_to_dict(value)
        elif isinstance(value, str | int | float | bool):
            out[field] = value
        else:
            out[field] = [rclpy_to_dict(v) if hasattr(v, 'get_fields_and_field_types')
                          else v.item() if hasattr(v, 'item') else v for v in value]
    return out


def rosbags_msg(store: Typestore, type_name: str, values: dict[str, Any]) -> Any:
    """Build a rosbags message of ``type_name`` from plain values (submessages as dicts)."""
    kwargs: dict[str, Any] = {}
    for field, (node, desc) in store.fielddefs[type_name][1]:
        value = values[field]
        if node.name == 'NAME':
            kwargs[field] = rosbags_msg(store, desc, value)
        elif node.name in ('SEQUENCE', 'ARRAY') and desc[0][0].name == 'NAME':
            kwargs[field] = [rosbags_msg(store, desc[0][1], v) for v in value]
        elif node.name in ('SEQUENCE', 'ARRAY'):
            kwargs[field] = np.asarray(value, dtype=np.dtype(desc[0][1][0]))
        else:
            kwargs[field] = value
    return store.types[type_name](**kwargs)


def rosbags_to_dict(store: Typestore, type_name: str, msg: Any) -> dict[str, Any]:
    """Every field of a rosbags message as plain Python data."""
    out: dict[str, Any] = {}
    for field, (node, desc) in store.fielddefs[type_name][1]:
        value = getattr(msg, field)
        if node.name == 'NAME':
            out[field] = rosbags_to_dict(store, desc, value)
        elif node.name in ('SEQUENCE', 'ARRAY') and desc[0][0].name == 'NAME':
            out[field] = [rosbags_to_dict(store, desc[0][1], v) for v in value]
        elif node.name in ('SEQUENCE', 'ARRAY'):
            out[field] = [v.item() if hasattr(v, 'item') else v for v in value]
        else:
            out[field] = value
    return out
