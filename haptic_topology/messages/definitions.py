"""The project's .msg definitions as text, and a ``rosbags`` typestore that knows them.

Bags recorded by the node graph hold ``haptic_topology_msgs`` messages. This module lets the
offline tools decode them with ``rosbags`` alone: no rclpy and no built interface package are
needed, only the .msg texts, which are found in

1. ``<prefix>/share/haptic_topology_msgs/msg/*.msg`` of an installed interface package
   (the venv prefix, or any prefix on ``AMENT_PREFIX_PATH``), else
2. ``msg_schemas/msg/`` of the source tree this module was imported from.

Example::

    >>> from haptic_topology.messages.definitions import typestore_with_haptic_msgs
    >>> ts = typestore_with_haptic_msgs()
    >>> DeviceState = ts.types['haptic_topology_msgs/msg/DeviceState']
    >>> DeviceState.STATUS_WATCHDOG
    4
"""

from __future__ import annotations

import os
import sys
from functools import cache
from pathlib import Path

from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from haptic_topology import MSGS_PACKAGE_NAME
from haptic_topology.errors import MessageDefinitionError

#: Message names of haptic_topology_msgs, in the order they appear in the node graph
#: (``HandInput``: the graph no longer sends it; bags recorded before hold it).
MESSAGE_NAMES: tuple[str, ...] = ('DeviceState', 'DeviceCommand', 'LmiUpdate', 'HandInputs',
                                   'VtPath', 'HandInput')

_SOURCE_MSG_DIR = Path(__file__).resolve().parents[2] / 'msg_schemas' / 'msg'


def type_name(name: str) -> str:
    """Full type name of one of our messages, e.g. ``'haptic_topology_msgs/msg/DeviceState'``."""
    return f'{MSGS_PACKAGE_NAME}/msg/{name}'


def _candidate_dirs() -> list[Path]:
    prefixes = [sys.prefix]
    prefixes += [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    dirs = [Path(p) / 'share' / MSGS_PACKAGE_NAME / 'msg' for p in dict.fromkeys(prefixes)]
    dirs.append(_SOURCE_MSG_DIR)
    return dirs


def msg_directory() -> Path:
    """Directory holding all of ``DeviceState.msg``, ``DeviceCommand.msg``, ... (see module doc).

    Raises:
        MessageDefinitionError: no candidate directory holds every message file.
    """
    tried = _candidate_dirs()
    for d in tried:
        if all((d / f'{n}.msg').is_file() for n in MESSAGE_NAMES):
            return d
    raise MessageDefinitionError(
        f'.msg files of {MSGS_PACKAGE_NAME} ({", ".join(MESSAGE_NAMES)}) not found in any of: '
        + ', '.join(str(d) for d in tried)
    )


def message_definitions(directory: Path | None = None) -> dict[str, str]:
    """Map full type name -> .msg text, e.g. ``'haptic_topology_msgs/msg/DeviceState'`` -> text.

    Args:
        directory: where to read the .msg files; default :func:`msg_directory`.
    """
    d = msg_directory() if directory is None else directory
    defs: dict[str, str] = {}
    for name in MESSAGE_NAMES:
        path = d / f'{name}.msg'
        try:
            defs[type_name(name)] = path.read_text(encoding='utf-8')
        except OSError as exc:
            raise MessageDefinitionError(f'{path}: cannot read ({exc.strerror})') from None
    return defs


@cache
def typestore_with_haptic_msgs() -> Typestore:
    """A ROS 2 Jazzy ``rosbags`` typestore with the haptic_topology_msgs types registered.

    The result is cached; treat it as read-only.
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in message_definitions().items():
        try:
            types.update(get_types_from_msg(text, name))
        except TypesysError as exc:
            raise MessageDefinitionError(f'{name}: cannot parse .msg text: {exc}') from exc
    store.register(types)
    return store
