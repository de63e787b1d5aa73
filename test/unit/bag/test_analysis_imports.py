"""A process that reads bags does not load the simulation's compiled code: ``run``'s analysis
and ``analyze`` import the bag readers, the plots and the scenario, and numba (with the
compiled functions it loads from its cache: 120 MB of the analysis's resident set) stays out
until something steps a device or a VE."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_reading_a_bag_imports_no_numba() -> None:
    code = textwrap.dedent('''
        import sys
        import haptic_topology.bag.analyze, haptic_topology.bringup.analysis
        import haptic_topology.sim.plots
        from haptic_topology.sim import Trace, load_scenario
        for name in ('circle', 'fig8', 'panda_link4'):
            load_scenario(name)
        print(sorted(m for m in sys.modules if m == 'numba' or m.endswith('.compiled')))
    ''')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    assert out.strip().splitlines()[-1] == '[]'


def test_a_simulated_user_still_compiles_where_it_steps() -> None:
    """The scenario's check builds its user without the compiled wrench; the device's
    backend builds it with (its first cycle does not load numba)."""
    code = textwrap.dedent('''
        import sys
        import numpy as np
        from haptic_topology.device.users import user_from_config
        from haptic_topology.vocabulary import TaskSpace
        raw = {'type': 'spring_damper', 'path': 'circle', 'radius': 0.1, 'period': 2.0,
               'stiffness': [100.0, 100.0, 0.0], 'damping': [1.0, 1.0, 0.0]}
        user_from_config(raw, TaskSpace.PLANAR, 'u', np.zeros(3), compile=False)
        print('numba' in sys.modules)
        u = user_from_config(raw, TaskSpace.PLANAR, 'u', np.zeros(3))
        print('numba' in sys.modules, u.wrench(0.5, np.zeros(3), np.zeros(3)).tolist())
    ''')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=300, check=True).stdout.strip().splitlines()
    assert out[0] == 'False'
    assert out[1].startswith('True [')
