"""The core imports no rclpy: only ``haptic_topology.nodes`` adapts it to ROS 2.

Checked in a fresh interpreter (this test process may have imported rclpy for other tests):
every module outside ``haptic_topology.nodes`` is imported one by one, and the first one after
which rclpy (or a generated ROS message package) is loaded is named.
"""

from __future__ import annotations

import json
import subprocess
import sys

#: Loop modules that the hosted device_driver runs in its 1 kHz thread: named so that a rename
#: or a move out of the walk below fails here.
LOOP_MODULES = (
    'haptic_topology.control.loop',
    'haptic_topology.device.loop',
    'haptic_topology.device.pacing',
    'haptic_topology.device.hosted',
    'haptic_topology.sim.lockstep',
)
ROS_PACKAGES = ('rclpy', 'rosidl_runtime_py', 'haptic_topology_msgs', 'std_msgs',
                'rosgraph_msgs', 'diagnostic_msgs')

_PROBE = r'''
import importlib, json, pkgutil, sys
import haptic_topology
ros = set(sys.argv[1].split(','))
loaded = lambda: sorted({m.split('.')[0] for m in sys.modules} & ros)
names = [m.name for m in pkgutil.walk_packages(haptic_topology.__path__, 'haptic_topology.')
         if not m.name.startswith('haptic_topology.nodes')]
first = None
for name in names:
    importlib.import_module(name)
    if first is None and loaded():
        first = name
print(json.dumps({'modules': names, 'ros': loaded(), 'first': first}))
'''


def test_core_modules_import_no_rclpy() -> None:
    out = subprocess.run([sys.executable, '-c', _PROBE, ','.join(ROS_PACKAGES)],
                         capture_output=True, text=True, check=True, timeout=240)
    res = json.loads(out.stdout.splitlines()[-1])
    assert set(LOOP_MODULES) <= set(res['modules'])
    assert res['ros'] == [], f'{res["first"]} imports {res["ros"]}'
