"""Thin rclpy adapters over the core.

``device_driver``, ``lmi_controller``, ``ve_sim``, ``recorder`` (and ``composed``: all four).

Topics (names relative, so a namespace moves the whole graph) and QoS, see :mod:`.common`.
"""
