"""The memory a plot takes does not grow with the rows it draws (:func:`~haptic_topology.sim.
plots.save_figure`): an hour's hand paths, whose points jump across the panel from one plotted
row to the next, drawn in one piece took the rasterizer 1.3 GB for 183,010 rows of a 1-hour
``circle`` run.

Memory, not time: what Agg allocates for a figure depends on matplotlib and the figure alone,
so the bound holds on any machine. Measured in a fresh process (its peak resident set before
and after the figure is written)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent('''
    import json, resource
    import numpy as np
    from haptic_topology.sim.plots import plot_trace
    from haptic_topology.sim.scenario import load_scenario
    from haptic_topology.sim.trace import Trace

    n = 100_000
    sc = load_scenario('circle')
    tr = Trace.empty(n, 3, sc.linkage.dof, False, scenario='circle', mode='penalty', dt=0.05)
    # The hand goes round a 0.1 m circle 0.8 rad a row, as a run's plot rows sampled every
    # 55 ms of a fast circle do: every segment crosses the panel.
    a = 0.8 * np.arange(n)
    ring = np.column_stack([0.1 * np.cos(a), 0.1 * np.sin(a), a])
    tr.t[:] = 0.05 * np.arange(n)
    tr.columns['vt_pose'][:] = ring
    tr.columns['device_pose'][:] = ring * 1.01
    tr.columns['q'][:] = sc.q0
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    plot_trace(tr, OUT, sc.linkage)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"grew_mb": (after - before) / 1024}))
''')


def test_a_plot_of_paths_crossing_the_panel_at_every_row_stays_small(tmp_path) -> None:
    out = tmp_path / 'plot.png'
    proc = subprocess.run([sys.executable, '-c', f'OUT = {str(out)!r}\n' + SCRIPT],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    grew = json.loads(proc.stdout.strip().splitlines()[-1])['grew_mb']
    assert out.is_file()
    assert grew < 250.0, f'writing the plot took {grew:.0f} MB more'
