"""Parameters of the graph's nodes, generated from their settings dataclasses (no rclpy).

Each node's table is :func:`haptic_topology.config.settings.param_specs` of its settings class
(:class:`~haptic_topology.config.settings.DeviceDriverSettings`, ...). The nodes declare them
(``haptic_topology.nodes.parameters.declare_settings``) and
:func:`haptic_topology.config.params.check_params_file` checks params files against the same tables
before rclpy reads them. ``config/haptic_topology.yaml`` lists every one.
"""

from __future__ import annotations

from haptic_topology.config.params import NodeParams
from haptic_topology.config.settings import (
           EXECUTORS,
           FALLBACKS,
           MODES,
           DeviceDriverSettings,
           FoxgloveBridgeSettings,
           LmiControllerSettings,
           RecorderSettings,
           VeSimSettings,
           param_specs,
)
from haptic_topology.control.laws import GAIN_MAX

__all__ = ['DEVICE_DRIVER', 'EXECUTORS', 'FALLBACKS', 'FOXGLOVE_BRIDGE', 'GAIN_MAX', 'KNOWN',
           'LMI_CONTROLLER', 'MODES', 'RECORDER', 'SCHED_PRIORITY', 'VE_SIM']

DEVICE_DRIVER: NodeParams = param_specs(DeviceDriverSettings)
LMI_CONTROLLER: NodeParams = param_specs(LmiControllerSettings)
VE_SIM: NodeParams = param_specs(VeSimSettings)
RECORDER: NodeParams = param_specs(RecorderSettings)
FOXGLOVE_BRIDGE: NodeParams = param_specs(FoxgloveBridgeSettings)

#: Real-time scheduling of the whole process (every thread, DDS's included).
SCHED_PRIORITY = DEVICE_DRIVER['sched_priority']

#: Node name -> parameters known in this package's processes.
KNOWN: dict[str, NodeParams | None] = {
    'device_driver': DEVICE_DRIVER,
    'lmi_controller': LMI_CONTROLLER,
    've_sim': VE_SIM,
    'recorder': RECORDER,
    'foxglove_bridge': FOXGLOVE_BRIDGE,
}
