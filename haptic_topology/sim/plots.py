"""Plots in the style of the paper's Fig. 6 / Fig. 8 (matplotlib, Agg backend, PNG files).

Planar (task dim 3), four panels. (a): the linkage drawn at a few instants (Fig. 4 style) when
its model is given, with the hand paths. (b): the hand trajectory on the device ('HD') and in
the VE ('VE') in the x-y plane. (c): device-VT distance over time. (d): number of directions
of topological constraint over time, with the intervals the device spent at a workspace limit.

Spatial (task dim 6), six panels: the linkage (joint origins, grasp point marked) with the hand
paths projected on the world x-y and x-z planes, the hand paths alone in both projections,
the drift over time (translational distance, mm, and the orientation error
``|log3(R_vt R_h^T)|``, deg), and the constraint count with the workspace-limit intervals.
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


def _spatial_points(linkage: Linkage, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World positions (m) of the joint origins (rows; then the grasp point when the last link
    is grasped) and of the grasp point at q."""
    lm = build_model(linkage)
    data = lm.model.createData()
    pin.framesForwardKinematics(lm.model, data, q)
    pts = [np.array(data.oMi[j].translation) for j in range(1, lm.model.njoints)]
    grasp = np.array(data.oMf[lm.hand_frame].translation)
    if linkage.grasp_link == linkage.links[-1].name:
        pts.append(grasp)
    return np.array(pts), grasp


def _hand_paths(ax: plt.Axes, vt: np.ndarray, dev: np.ndarray, title: str,
                mark_start: bool, axes: tuple[int, int] = (0, 1)) -> None:
    """VE and device (HD) hand paths (mm) on ``ax``, projected on the world plane of the two
    coordinates ``axes`` (0 = x, 1 = y, 2 = z)."""
    i, j = axes
    ax.plot(vt[:, i] * 1000.0, vt[:, j] * 1000.0, '-', color='tab:blue', lw=2, label='VE',
            zorder=2)
    ax.plot(dev[:, i] * 1000.0, dev[:, j] * 1000.0, '--', color='tab:red', lw=2, label='HD',
            zorder=3)
    if mark_start:
        ax.plot(vt[:1, i] * 1000.0, vt[:1, j] * 1000.0, 'o', color='tab:blue')
        ax.plot(dev[:1, i] * 1000.0, dev[:1, j] * 1000.0, 'o', color='tab:red')
    ax.set_xlabel(f'{"xyz"[i]} [mm]')
    ax.set_ylabel(f'{"xyz"[j]} [mm]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.legend(loc='best')
    ax.set_title(title)
    ax.grid(alpha=0.3)


def plot_trace(trace: Trace, path: str | Path, linkage: Linkage | None = None,
               title: str | None = None) -> Path:
    """Write the figure of ``trace`` (see module doc) to ``path`` (PNG) and return the path."""
    if trace.task_dim == 6:
        return _plot_spatial(trace, Path(path), linkage, title)
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

    _constraint_panel(axes[2], trace)
    _finish(fig, trace, out, title)
    return out


def _constraint_panel(ax: plt.Axes, trace: Trace) -> None:
    """Constraint count over time with the intervals at a workspace limit."""
    t = trace.t
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


def _finish(fig: plt.Figure, trace: Trace, out: Path, title: str | None) -> None:
    summary = trace.summary()
    fig.suptitle(title or f'{summary["scenario"]} - {summary["mode"]}: final drift '
                 f'{summary["final_distance_m"] * 1000:.2f} mm, max '
                 f'{summary["max_distance_m"] * 1000:.2f} mm')
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _plot_spatial(trace: Trace, out: Path, linkage: Linkage | None,
                  title: str | None) -> Path:
    t = trace.t
    dev = trace.columns['device_pose']
    vt = trace.columns['vt_pose']
    fig, grid = plt.subplots(2, 3, figsize=(17, 10))
    for ax, axes, name in ((grid[0, 0], (0, 1), '(a)'), (grid[1, 0], (0, 2), '(d)')):
        if linkage is not None and trace.columns['q'].shape[1] == linkage.dof and len(trace):
            q = trace.columns['q']
            good = np.nonzero(np.all(np.isfinite(q), axis=1))[0]
            for k_i, k in enumerate(good[np.linspace(0, good.size - 1, 6).astype(int)]):
                pts, grasp = _spatial_points(linkage, q[k])
                shade = 'black' if k_i == 0 else '0.65'
                ax.plot(pts[:, axes[0]] * 1000.0, pts[:, axes[1]] * 1000.0, '-o', color=shade,
                        lw=1.5, ms=3, zorder=1)
                ax.plot(grasp[axes[0]] * 1000.0, grasp[axes[1]] * 1000.0, 'x', color=shade,
                        ms=7, zorder=1)
        plane = 'xy' if axes == (0, 1) else 'xz'
        _hand_paths(ax, vt, dev, f'{name} linkage (joints o, grasp x; start black) and hand, '
                    f'{plane}', mark_start=False, axes=axes)
    _hand_paths(grid[0, 1], vt, dev, '(b) hand on the device (HD) and in the VE, x-y',
                mark_start=True, axes=(0, 1))
    _hand_paths(grid[0, 2], vt, dev, '(c) hand on the device (HD) and in the VE, x-z',
                mark_start=True, axes=(0, 2))
    ax = grid[1, 1]
    ax.plot(t, trace.distance() * 1000.0, color='tab:purple', label='translation [mm]')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    rot = np.full(len(trace), np.nan)
    ok = np.all(np.isfinite(vt[:, 3:6]), axis=1) & np.all(np.isfinite(dev[:, 3:6]), axis=1)
    for k in np.nonzero(ok)[0]:
        rot[k] = np.linalg.norm(pin.log3(pin.exp3(vt[k, 3:6]) @ pin.exp3(dev[k, 3:6]).T))
    twin = ax.twinx()
    twin.plot(t, np.degrees(rot), color='tab:gray', ls=':', label='orientation [deg]')
    twin.set_ylabel('device - VT orientation error [deg]')
    lines = ax.get_lines() + twin.get_lines()
    ax.legend(lines, [str(ln.get_label()) for ln in lines], loc='upper left')
    ax.set_title('(e) drift')
    ax.grid(alpha=0.3)
    _constraint_panel(grid[1, 2], trace)
    grid[1, 2].set_title('(f) directions of topological constraint')
    _finish(fig, trace, out, title)
    return out
