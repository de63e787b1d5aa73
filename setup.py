"""ament_python packaging of haptic_topology (also installable with pip into a venv)."""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'haptic_topology'


def tree(folder):
    """``(share/haptic_topology/<dir>, [files])`` for every directory under ``folder`` (the
    robot descriptions of config/robots/: URDF, SRDF, meshes, licences), in sorted order."""
    out = []
    for here, dirs, files in os.walk(folder):
        dirs.sort()
        if files:
            out.append((f'share/{PACKAGE}/{here}', sorted(os.path.join(here, f) for f in files)))
    return out

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*']),
    package_data={PACKAGE: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', sorted(glob('config/*.yaml') + glob('config/*.xml')
                                               + glob('config/*.json'))),
        (f'share/{PACKAGE}/config/linkages', sorted(glob('config/linkages/*.yaml')
                                                     + glob('config/linkages/*.urdf'))),
        (f'share/{PACKAGE}/config/scenarios', sorted(glob('config/scenarios/*.yaml'))),
        (f'share/{PACKAGE}/config/meshes', sorted(glob('config/meshes/*.stl'))),
        (f'share/{PACKAGE}/config/devices', sorted(glob('config/devices/*.yaml'))),
        (f'share/{PACKAGE}/launch', sorted(glob('launch/*.launch.py'))),
        *tree('config/robots'),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='haptic_topology maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-de0d75a8.example',
    description='Haptic rendering of topological constraints of serial virtual linkages',
    license='Apache-2.0',
    python_requires='>=3.11',
    entry_points={
        'console_scripts': [
            'haptic-topology = haptic_topology.cli:main',
            'device_driver = haptic_topology.nodes.device_driver:main',
            'lmi_controller = haptic_topology.nodes.lmi_controller:main',
            've_sim = haptic_topology.nodes.ve_sim:main',
            'recorder = haptic_topology.nodes.recorder:main',
            # the live topics for the Foxglove app (haptic-topology run --foxglove)
            'foxglove_bridge = haptic_topology.nodes.foxglove_bridge:main',
            # the four nodes in one process (launch/haptic_lab.launch.py layout:=composed)
            'composed = haptic_topology.nodes.composed:main',
        ],
    },
)
