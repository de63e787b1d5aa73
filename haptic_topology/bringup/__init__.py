"""Starting the node graph (``haptic-topology run``)."""
