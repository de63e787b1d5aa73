"""Haptic rendering of topological constraints of serial virtual linkages.

The core library (``model``, ``dynamics``, ``control``, ``device``, ``sim``) is plain
numpy/scipy/Pinocchio and imports no rclpy; ``nodes`` adapts it to ROS 2 and ``bag`` handles
recorded rosbag2 (MCAP) data. Command line: ``haptic-topology`` (:mod:`haptic_topology.cli`).
"""

__version__ = '0.1.0'

#: ROS package names of this project (share directories resolve through ament_index).
PACKAGE_NAME = 'haptic_topology'
MSGS_PACKAGE_NAME = 'haptic_topology_msgs'
