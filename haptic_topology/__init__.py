"""Haptic rendering of topological constraints of serial virtual linkages.

The core library (``model``, ``dynamics``, ``control``, ``device``, ``sim``) is plain
numpy/scipy/Pinocchio and imports no rclpy; ``nodes`` adapts it to ROS 2 and ``bag`` handles
recorded rosbag2 (MCAP) data. Command line: ``haptic-topology`` (:mod:`haptic_topology.cli`).
"""

import os as _os

__version__ = '0.1.0'

#: Threads of numpy's BLAS (OpenBLAS) in every process that imports this package before numpy:
#: one, unless the environment says otherwise. The matrices here are small, and a threaded
#: BLAS call on a busy 2-core machine waits for its other thread to be scheduled (measured on
#: a loaded 2-core machine: a 100 x 100 product 5.2 ms with two threads, 0.09 ms with one). The
#: processes this package starts (nodes, the loop process) inherit the setting.
BLAS_THREADS_ENV = 'OPENBLAS_NUM_THREADS'
_os.environ.setdefault(BLAS_THREADS_ENV, '1')

#: ROS package names of this project (share directories resolve through ament_index).
PACKAGE_NAME = 'haptic_topology'
MSGS_PACKAGE_NAME = 'haptic_topology_msgs'
