"""Plots in the style of the paper's Fig. 6 / Fig. 8 (matplotlib, Agg backend, PNG files).

Panel (a): the linkage drawn at a few instants (Fig. 4 style) when its model is given, with
the hand paths. Panel (b): the hand trajectory on the device ('HD') and in the VE ('VE') in
the x-y plane. Panel (c): device-VT distance over time. Panel (d): number of directions of
topological constraint over time, with the intervals the device spent at a workspace limit.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
import pinocchio as pin

from haptic_topology.model.linkage import Linkage, build_model
from haptic_topology.sim.trace import Trace


def _joint_points(linkage: Linkage, q: np.ndarray) -> np.ndarray:
    """World x-y of each joint and the grasp point for configuration q (m)."""
    lm = build_model(linkage)
    data = lm.model.createData()
    pin.framesForwardKinematics(lm.model, data, q)
    pts = [np.array(data.oMi[j].translation) for j in range(1, lm.model.njoints)]
    last = linkage.links[-1]
    tip = data.oMi[lm.model.njoints - 1].act(np.array([last.length, 0.0, 0.0]))
    pts.append(np.array(tip))
    return np.array(pts)[:, :2]


def _hand_paths(ax: plt.Axes, vt: np.ndarray, dev: np.ndarray, title: str,
                mark_start: bool) -> None:
    """VE and device (HD) hand paths in the x-y plane (mm) on ``ax``."""
    ax.plot(vt[:, 0] * 1000.0, vt[:, 1] * 1000.0, '-', color='tab:blue', lw=2, label='VE',
            zorder=2)
    ax.plot(dev[:, 0] * 1000.0, dev[:, 1] * 1000.0, '--', color='tab:red', lw=2, label='HD',
            zorder=3)
    if mark_start:
        ax.plot(vt[:1, 0] * 1000.0, vt[:1, 1] * 1000.0, 'o', color='tab:blue')
        ax.plot(dev[:1, 0] * 1000.0, dev[:1, 1] * 1000.0, 'o', color='tab:red')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('y [mm]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.legend(loc='best')
    ax.set_title(title)
    ax.grid(alpha=0.3)


def plot_trace(trace: Trace, path: str | Path, linkage: Linkage | None = None,
               title: str | None = None) -> Path:
    """Write the three-panel figure of ``trace`` to ``path`` (PNG) and return the path."""
    out = Path(path)
    t = trace.t
    dev = trace.columns['device_pose']
    vt = trace.columns['vt_pose']
    dist_mm = trace.distance() * 1000.0
    fig, grid = plt.subplots(2, 2, figsize=(12, 9))
    axes = [grid[0, 0], grid[1, 0], grid[1, 1]]
    zoom = grid[0, 1]
    ax = axes[0]
    if linkage is not None and trace.columns['q'].shape[1] == linkage.dof and len(trace):
        q = trace.columns['q']
        good = np.nonzero(np.all(np.isfinite(q), axis=1))[0]
        for i, k in enumerate(good[np.linspace(0, good.size - 1, 6).astype(int)]):
            pts = _joint_points(linkage, q[k]) * 1000.0
            shade = 'black' if i == 0 else '0.65'
            ax.plot(pts[:, 0], pts[:, 1], '-o', color=shade, lw=1.5, ms=3, zorder=1)
    _hand_paths(ax, vt, dev, '(a) linkage (start black, later grey) and hand paths',
                mark_start=False)
    _hand_paths(zoom, vt, dev, '(b) hand on the device (HD) and in the VE (o: start)',
                mark_start=True)

    ax = axes[1]
    ax.plot(t, dist_mm, color='tab:purple')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    ax.set_title('(c) drift')
    ax.grid(alpha=0.3)

    ax = axes[2]
    ax.step(t, trace.columns['constraint_count'], where='post', color='tab:green',
            label='t = m - rank(J_h) (VE)')
    at_limit = (trace.columns['status'] & 1) > 0
    if at_limit.any():
        ax.fill_between(t, 0, 1, where=at_limit, step='post', color='tab:orange', alpha=0.3,
                        transform=ax.get_xaxis_transform(), label='device at workspace limit')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('constraints')
    ax.set_ylim(-0.1, max(1.5, float(trace.columns['constraint_count'].max()) + 0.5))
    ax.set_title('(d) directions of topological constraint')
    ax.legend(loc='upper left')
    ax.grid(alpha=0.3)
    summary = trace.summary()
    fig.suptitle(title or f'{summary["scenario"]} - {summary["mode"]}: final drift '
                 f'{summary["final_distance_m"] * 1000:.2f} mm, max '
                 f'{summary["max_distance_m"] * 1000:.2f} mm')
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
