"""Network stages for running the graph across a link with delay, jitter and loss (no rclpy).

:mod:`haptic_topology.net.delay_bridge`: a layer-2 bridge between two interfaces that delays
and drops frames in user space, for kernels without the ``netem`` qdisc
(``scripts/two_hosts.sh`` puts it between two network namespaces).
"""
