"""The graph's messages without rclpy: checks of received messages (:mod:`.check`), the
``.msg`` definitions for bag tools (:mod:`.definitions`) and the check that the built
``haptic_topology_msgs`` package is there (:mod:`.package`)."""
