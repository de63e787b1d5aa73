"""Loop health as ``/diagnostics``: one-status arrays, matched endpoints, queued notices."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node


def diagnostics(node: Node, name: str, values: dict[str, str], level: int = 0,
                message: str = 'ok', hardware_id: str | None = None) -> DiagnosticArray:
    """A one-status :class:`DiagnosticArray` (level: DiagnosticStatus.OK/WARN/ERROR).

    ``hardware_id``: the hardware the status is about (the device driver: backend and device,
    :func:`haptic_topology.device.loop.hardware_id`); None for a node that drives no hardware,
    which reports its fully qualified node name. Every status carries ``pid``: the reporting
    process, so a tool that restarts a node can tell the new process's reports from late ones
    of the process it replaced."""
    values = {**values, 'pid': str(os.getpid())}
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    status = DiagnosticStatus(level=bytes([level]), name=name, message=message,
                              hardware_id=(node.get_fully_qualified_name() if hardware_id is None
                                           else hardware_id))
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    arr.status = [status]
    return arr


def matched(endpoints: Mapping[str, Any]) -> dict[str, str]:
    """Diagnostic values ``matched <topic>``: for each publisher the DDS readers matched to
    it, for each subscription the DDS writers matched to it (what the middleware actually
    connected, not the graph cache). A restarted node whose topic stays at 0 here is not
    connected, whatever the graph says."""
    out = {}
    for key, ep in endpoints.items():
        n = (ep.get_subscription_count() if hasattr(ep, 'get_subscription_count')
             else ep.get_publisher_count())
        out[f'matched {key}'] = str(n)
    return out


def log_notices(node: Node, notices: Any) -> None:
    """Log each text of ``notices`` (a list or deque another thread appends to: the loop
    thread's) as a warning of ``node``, oldest first, removing it."""
    while notices:
        try:
            text = notices.pop(0) if isinstance(notices, list) else notices.popleft()
        except IndexError:          # taken by another thread meanwhile
            break
        node.get_logger().warn(text)


def monotonic() -> float:
    return time.monotonic()
