"""The graph's messages without rclpy: checks of received messages (:mod:`.check`), the
``.msg`` definitions for bag tools (:mod:`.definitions`), the serialization of the 1 kHz
messages (:mod:`.cdr`) and the check that the built ``haptic_topology_msgs`` package is
there (:mod:`.package`)."""
