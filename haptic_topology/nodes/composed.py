"""All four nodes of the graph in one process, on one executor (``haptic-topology run
--composed``): ``ve_sim``, ``lmi_controller``, ``device_driver`` and ``recorder``.

Parameters come from the same params file as for separate processes (one section per node
name). With ``device_driver.host_controller`` (default) the driver runs the controller in its
loop thread as in its own process; otherwise the messages between the nodes go through the
middleware (no intra-process shortcut in rclpy), but no process boundary is crossed.
"""

from __future__ import annotations

from collections.abc import Sequence

from rclpy.node import Node

from haptic_topology.config import node_params
from haptic_topology.nodes.runtime import close_all, destroy_nodes, run_main


def build() -> list[Node]:
    from haptic_topology.nodes import device_driver
    from haptic_topology.nodes.lmi_controller import LmiController
    from haptic_topology.nodes.recorder import Recorder
    from haptic_topology.nodes.ve_sim import VeSim

    nodes: list[Node] = []
    try:
        for cls in (Recorder, VeSim):
            nodes.append(cls())
        # The driver with the controller it hosts (host_controller, default), or without.
        driver_nodes = device_driver.build()
        nodes.extend(driver_nodes)
        if len(driver_nodes) == 1:
            nodes.append(LmiController())
    except BaseException:
        close_all(nodes, 'composed')
        destroy_nodes(nodes)
        raise
    # The device driver's executor parameter decides (it is the clock master).
    return [nodes[2], *nodes[:2], *nodes[3:]]


def main(args: Sequence[str] | None = None) -> int:
    return run_main('composed', build, args, node_params.KNOWN)


if __name__ == '__main__':
    raise SystemExit(main())
