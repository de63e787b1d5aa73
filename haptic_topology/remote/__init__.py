"""Devices on another computer: the UDP protocol (:mod:`.protocol`), the ``network`` device
backend (:mod:`.network`) and the device server that serves a simulated maglev over it
(:mod:`.server`, :mod:`.server_command`). No rclpy."""
