"""Thin rclpy adapters over the core.

``device_driver``, ``lmi_controller``, ``ve_sim``, ``recorder`` (and ``composed``: all four),
``foxglove_bridge`` (the live topics for Foxglove).

Topics (names relative, so a namespace moves the whole graph): :mod:`haptic_topology.vocabulary`;
their QoS: :mod:`.qos`.

Importing this package first checks that the built messages (``haptic_topology_msgs``) are
there: if not, the program ends with one line saying what to build
(:func:`haptic_topology.messages.package.require_msgs_package`), not with a traceback from the
first node module that imports them.
"""

from haptic_topology.messages.package import require_msgs_package

require_msgs_package()
