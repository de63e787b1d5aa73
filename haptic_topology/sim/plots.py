"""Plots in the style of the paper's Fig. 6 / Fig. 8 (matplotlib, Agg backend, PNG files).

Planar (tasks ``planar`` and ``planar_point``), four panels. (a): the linkage drawn at a few
instants (Fig. 4 style) when its model is given, with the hand paths. (b): the hand trajectory
on the device ('HD') and in the VE ('VE') in the x-y plane. (c): device-VT distance over time.
(d): number of directions of topological constraint over time, with the intervals the device
spent at a workspace limit.

Spatial (tasks ``spatial`` and ``spatial_point``), six panels: the linkage (joint origins,
grasp point marked) with the hand paths projected on the world x-y and x-z planes, the hand
paths alone in both projections, the drift over time (translational distance, mm, and for
``spatial`` the orientation error ``|log3(R_vt R_h^T)|``, deg; a point grasp has no
orientation), and the constraint count with the workspace-limit intervals.

A run with obstacles (``trace.has_contacts``) gets one more panel, a full-width bottom row:
the translational components of ``F_env`` (the environment's contact wrench rendered at the
user's hand; planar fx, fy, spatial fx, fy, fz) and the translational norms of ``F_env``, of
the wrench the device applied and of the user's ``F_h`` (N), with the deepest penetration (mm)
on a second y axis. The contact intervals (:func:`contact_intervals`) are shaded light grey in
every time-axis panel. Without contacts the figure is exactly as described above.

``obstacles`` (the scenario's ``contacts.obstacles``) are drawn on the hand-path panels, in mm:
planar half-planes as their boundary line with the obstacle side hatched, segments as thick
lines, discs as hatched circles; spatial spheres as circles in each projection (planes and
boxes are not drawn). The linkage panels widen their view to show them; the zoomed hand panels
keep theirs, so an obstacle away from the hand is not shown there.

Long paths are drawn in chunks of :data:`PATH_CHUNK` vertices (Agg's ``agg.path.chunksize``,
in :func:`save_figure`): an hour's hand paths, whose points jump across the panel from one
plotted row to the next, would otherwise take the rasterizer gigabytes.

The title, unless given: ``<run> - <mode>: final drift ... mm, max ... mm``, the run named by
:func:`~haptic_topology.sim.trace.run_name` (the scenario, and the linkage it ran on when not
its own: ``fig8 on my_arm.urdf``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
import pinocchio as pin
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Polygon

from haptic_topology.model.build import build_model
from haptic_topology.model.linkage import Linkage
from haptic_topology.model.obstacles import Obstacle, ObstacleKind
from haptic_topology.sim.trace import Trace, run_name


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


#: Vertices per chunk of a drawn path (module doc).
PATH_CHUNK = 1000


def save_figure(fig: plt.Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (PNG, 110 dpi; the directory made if needed), its long paths
    drawn in chunks of :data:`PATH_CHUNK` vertices, and close it."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with matplotlib.rc_context({'agg.path.chunksize': PATH_CHUNK}):
            fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out


def plot_trace(trace: Trace, path: str | Path, linkage: Linkage | None = None,
               title: str | None = None, obstacles: Sequence[Obstacle] = ()) -> Path:
    """Write the figure of ``trace`` (see module doc) to ``path`` (PNG) and return the path."""
    return save_figure(trace_figure(trace, linkage, title, obstacles), path)


def trace_figure(trace: Trace, linkage: Linkage | None = None, title: str | None = None,
                 obstacles: Sequence[Obstacle] = ()) -> plt.Figure:
    """The figure :func:`plot_trace` writes (see module doc); the caller closes it
    (``plt.close(fig)``)."""
    if not trace.task.planar:
        return _plot_spatial(trace, linkage, title, obstacles)
    t = trace.t
    dev = trace.columns['device_pose']
    vt = trace.columns['vt_pose']
    dist_mm = trace.distance() * 1000.0
    fig, grid, forces = _figure(2, (12, 9), trace.has_contacts)
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
    _draw_obstacles(ax, obstacles, planar=True, widen=True)
    _draw_obstacles(zoom, obstacles, planar=True, widen=False)

    ax = axes[1]
    ax.plot(t, dist_mm, color='tab:purple')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    ax.set_title('(c) drift')
    ax.grid(alpha=0.3)

    _constraint_panel(axes[2], trace, linkage)
    if forces is not None:
        _forces_panel(forces, trace, '(e)', [axes[1], axes[2]])
    _finish(fig, trace, title)
    return fig


def _constraint_panel(ax: plt.Axes, trace: Trace, linkage: Linkage | None) -> None:
    """Constraint count over time with the intervals at a workspace limit (of the
    mechanism's hand Jacobian ``J_h N`` for a closed chain)."""
    t = trace.t
    closed = linkage is not None and bool(linkage.loops)
    ax.step(t, trace.columns['constraint_count'], where='post', color='tab:green',
            label=f't = m - rank(J_h{" N" if closed else ""}) (VE)')
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


def _finish(fig: plt.Figure, trace: Trace, title: str | None) -> None:
    summary = trace.summary()
    name = run_name(str(summary['scenario']), str(trace.meta.get('linkage_file', '')))
    fig.suptitle(title or f'{name} - {summary["mode"]}: final drift '
                 f'{summary["final_distance_m"] * 1000:.2f} mm, max '
                 f'{summary["max_distance_m"] * 1000:.2f} mm')
    fig.tight_layout()


#: Height (in) the contact panel adds to the figure, and its height relative to a panel row.
_FORCES_HEIGHT = 4.0
_FORCES_RATIO = 0.8
#: Fraction of the contact panel's height kept free of curves for its legend.
_LEGEND_ROOM = 0.22


def _figure(cols: int, size: tuple[float, float],
            contacts: bool) -> tuple[plt.Figure, np.ndarray, plt.Axes | None]:
    """The figure, its 2 x ``cols`` panel grid and, for a run with contacts, the full-width
    contact panel below it (else None)."""
    if not contacts:
        fig, grid = plt.subplots(2, cols, figsize=size)
        return fig, grid, None
    fig, grid = plt.subplots(3, cols, figsize=(size[0], size[1] + _FORCES_HEIGHT),
                             gridspec_kw={'height_ratios': (1.0, 1.0, _FORCES_RATIO)})
    for ax in grid[2]:
        ax.remove()
    forces = fig.add_subplot(grid[0, 0].get_gridspec()[2, :])
    return fig, grid[:2], forces


def contact_intervals(t: np.ndarray, penetration: np.ndarray) -> list[tuple[float, float]]:
    """The time intervals ``(start, end)`` (s) in contact: maximal runs of consecutive rows
    with ``penetration > 0`` (a NaN, unknown, row counts as not in contact and ends a run).

    Each row holds until the next one (as the ``step='post'`` plots): a run of rows
    ``i..j`` gives ``(t[i], t[j + 1])``, or ``(t[i], t[-1])`` when it reaches the last row (a
    run of only the last row is then an empty interval). E.g. ``t = 0, 1, ..., 7`` and
    penetration ``[0, 0.1, 0.2, 0, 0, 0.3, nan, 0]`` give ``[(1, 3), (5, 6)]``.
    """
    t = np.asarray(t, dtype=float)
    depth = np.asarray(penetration, dtype=float)
    if t.ndim != 1 or depth.shape != t.shape:
        raise ValueError(f'contact_intervals: expected t and penetration of the same length '
                         f'(1-D), got shapes {t.shape} and {depth.shape}')
    inside = np.zeros(t.size + 2, dtype=np.int8)
    inside[1:-1] = np.nan_to_num(depth, nan=0.0) > 0.0
    edges = np.diff(inside)
    starts = np.nonzero(edges == 1)[0]
    # The first row after each run, or the last row for a run that reaches it.
    stops = np.minimum(np.nonzero(edges == -1)[0], t.size - 1)
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, stops, strict=True)]


def _shade_contacts(ax: plt.Axes, intervals: list[tuple[float, float]],
                    label: str | None = None) -> None:
    """Light grey spans over ``intervals`` (the first one labelled ``label``)."""
    for i, (a, b) in enumerate(intervals):
        ax.axvspan(a, b, color='0.88', lw=0, zorder=0, label=label if i == 0 else None)


def _translation(wrench: np.ndarray, n: int) -> np.ndarray:
    """Norm of the first ``n`` (translational) entries of each row (NaN rows stay NaN)."""
    return np.asarray(np.linalg.norm(wrench[:, :n], axis=1))


def _forces_panel(ax: plt.Axes, trace: Trace, name: str, others: list[plt.Axes]) -> None:
    """``F_env`` (translational components and norm), the applied and user wrench norms (N)
    and the penetration (mm, right axis) over time; shades the contact intervals here and in
    the time-axis panels ``others``."""
    t = trace.t
    n = trace.task.translation_rows.stop
    env = trace.columns['env_wrench']
    depth = trace.columns['penetration']
    intervals = contact_intervals(t, depth)
    for ax_t in others:
        _shade_contacts(ax_t, intervals)
    _shade_contacts(ax, intervals, 'in contact (penetration > 0)')
    for i, color in zip(range(n), ('tab:blue', 'tab:orange', 'tab:green'), strict=False):
        ax.plot(t, env[:, i], color=color, lw=1.2, label=f'F_env f{"xyz"[i]} [N]')
    ax.plot(t, _translation(env, n), color='black', lw=1.8, label='|F_env| [N]')
    ax.plot(t, _translation(trace.columns['applied'], n), color='tab:red', ls='--', lw=1.5,
            label='|applied| [N]')
    ax.plot(t, _translation(trace.columns['hand_wrench'], n), color='tab:purple', ls=':',
            lw=1.8, label='|F_h| (user) [N]')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('force [N]')
    twin = ax.twinx()
    twin.plot(t, depth * 1000.0, color='tab:brown', lw=1.2, ls='-.', label='penetration [mm]')
    twin.set_ylabel('penetration [mm]')
    # Headroom on both y axes: the top _LEGEND_ROOM of the panel is left to the legend.
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo, hi + (hi - lo) * _LEGEND_ROOM / (1.0 - _LEGEND_ROOM))
    deepest = float(np.nanmax(depth)) if np.isfinite(depth).any() else 0.0
    twin.set_ylim(0.0, max(1e-3, deepest * 1000.0) * 1.05 / (1.0 - _LEGEND_ROOM))
    handles = ax.get_legend_handles_labels()
    more = twin.get_legend_handles_labels()
    ax.legend(handles[0] + more[0], handles[1] + more[1], loc='upper left', ncol=4,
              fontsize='small')
    ax.set_title(f'{name} contact: F_env (environment wrench at the hand), applied and user '
                 'wrench, penetration')
    ax.grid(alpha=0.3)


#: Obstacles drawn as a boundary line with the obstacle side hatched.
_FLAT = (ObstacleKind.HALF_PLANE, ObstacleKind.PLANE)


def _draw_obstacles(ax: plt.Axes, obstacles: Sequence[Obstacle], planar: bool, widen: bool,
                    axes: tuple[int, int] = (0, 1)) -> None:
    """Draw ``obstacles`` (mm) on a hand-path panel projected on the world plane ``axes``:
    planar half-planes, segments and discs (``planar``) or spatial spheres, and planes
    perpendicular to the panel (drawn as half-planes); other kinds are skipped. ``widen``:
    extend the view to show them (else keep the panel's view and skip those outside it)."""
    kinds = ((ObstacleKind.HALF_PLANE, ObstacleKind.SEGMENT, ObstacleKind.DISC) if planar
             else (ObstacleKind.SPHERE, ObstacleKind.PLANE))
    i, j = axes
    shown = [o for o in obstacles if o.kind in kinds and (
        o.kind is not ObstacleKind.PLANE or abs(float(np.hypot(*o.normal[[i, j]])) - 1.0) < 1e-9)]
    if not widen:
        x0, x1 = sorted(ax.get_xlim())
        y0, y1 = sorted(ax.get_ylim())
        shown = [o for o in shown if _in_view(o, axes, (x0, x1, y0, y1))]
    if not shown:
        return
    lim = ax.dataLim
    span = max(lim.width, lim.height, 1.0)
    centre = np.array([lim.x0 + lim.x1, lim.y0 + lim.y1]) / 2.0
    if widen:
        must: list[np.ndarray] = []
        for o in shown:
            p = o.point[[i, j]] * 1000.0
            if o.kind in _FLAT:
                nrm = o.normal[[i, j]]
                foot = centre - float(nrm @ (centre - p)) * nrm
                must += [foot, foot - 0.1 * span * nrm]
            elif o.kind is ObstacleKind.SEGMENT:
                must += [p, o.end[[i, j]] * 1000.0]
            else:
                r = o.radius * 1000.0
                must += [p - r, p + r]
        ax.update_datalim(np.array(must))
        ax.autoscale_view()
        lim = ax.dataLim
        span = max(lim.width, lim.height, 1.0)
        centre = np.array([lim.x0 + lim.x1, lim.y0 + lim.y1]) / 2.0
    # Drawn with add_artist so that they do not enter the data limits (autoscale, aspect).
    for o in shown:
        p = o.point[[i, j]] * 1000.0
        label = f'{o.name} ({o.kind.value.replace("_", "-")})'
        if o.kind in _FLAT:
            nrm = o.normal[[i, j]]
            foot = centre - float(nrm @ (centre - p)) * nrm
            along = np.array([-nrm[1], nrm[0]]) * 20.0 * span
            ax.add_artist(Polygon(_clip_half_plane(centre, 20.0 * span, p, nrm), closed=True,
                                  facecolor='none', edgecolor='0.55', hatch='//', lw=0.0,
                                  zorder=0.5))
            ax.add_artist(Line2D([foot[0] - along[0], foot[0] + along[0]],
                                 [foot[1] - along[1], foot[1] + along[1]], color='0.3', lw=1.5,
                                 label=label, zorder=1))
        elif o.kind is ObstacleKind.SEGMENT:
            b = o.end[[i, j]] * 1000.0
            ax.add_artist(Line2D([p[0], b[0]], [p[1], b[1]], color='0.3', lw=4.0,
                                 solid_capstyle='round', label=label, zorder=1))
        else:
            ax.add_artist(Circle((float(p[0]), float(p[1])), o.radius * 1000.0,
                                 facecolor='0.85', edgecolor='0.3', hatch='//', lw=1.2,
                                 label=label, zorder=1))
    ax.legend(loc='best')


def _in_view(o: Obstacle, axes: tuple[int, int],
             view: tuple[float, float, float, float]) -> bool:
    """Whether ``o`` (projected on ``axes``, mm) may reach into the box ``x0, x1, y0, y1``
    (mm): a corner on the obstacle side of a half-plane, else bounding boxes overlap."""
    i, j = axes
    x0, x1, y0, y1 = view
    p = o.point[[i, j]] * 1000.0
    if o.kind in _FLAT:
        corners = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])
        return bool(np.any((corners - p) @ o.normal[[i, j]] < 0.0))
    if o.kind is ObstacleKind.SEGMENT:
        b = o.end[[i, j]] * 1000.0
        lo, hi = np.minimum(p, b), np.maximum(p, b)
    else:
        lo, hi = p - o.radius * 1000.0, p + o.radius * 1000.0
    return bool(lo[0] <= x1 and hi[0] >= x0 and lo[1] <= y1 and hi[1] >= y0)


def _clip_half_plane(centre: np.ndarray, half: float, point: np.ndarray,
                     normal: np.ndarray) -> np.ndarray:
    """The part of the square ``centre +- half`` on the obstacle side of the half-plane's
    boundary (``normal . (x - point) <= 0``), as polygon vertices (one pass of
    Sutherland-Hodgman)."""
    cx, cy = centre
    square = [np.array(v) for v in ((cx - half, cy - half), (cx + half, cy - half),
                                     (cx + half, cy + half), (cx - half, cy + half))]
    out: list[np.ndarray] = []
    for k, a in enumerate(square):
        b = square[(k + 1) % len(square)]
        da, db = float(normal @ (a - point)), float(normal @ (b - point))
        if da <= 0.0:
            out.append(a)
        if (da < 0.0 < db) or (db < 0.0 < da):
            out.append(a + (b - a) * (da / (da - db)))
    return np.array(out) if out else np.zeros((0, 2))


def _plot_spatial(trace: Trace, linkage: Linkage | None, title: str | None,
                  obstacles: Sequence[Obstacle]) -> plt.Figure:
    t = trace.t
    dev = trace.columns['device_pose']
    vt = trace.columns['vt_pose']
    fig, grid, forces = _figure(3, (17, 10), trace.has_contacts)
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
        _draw_obstacles(ax, obstacles, planar=False, widen=True, axes=axes)
    _hand_paths(grid[0, 1], vt, dev, '(b) hand on the device (HD) and in the VE, x-y',
                mark_start=True, axes=(0, 1))
    _hand_paths(grid[0, 2], vt, dev, '(c) hand on the device (HD) and in the VE, x-z',
                mark_start=True, axes=(0, 2))
    _draw_obstacles(grid[0, 1], obstacles, planar=False, widen=False, axes=(0, 1))
    _draw_obstacles(grid[0, 2], obstacles, planar=False, widen=False, axes=(0, 2))
    ax = grid[1, 1]
    ax.plot(t, trace.distance() * 1000.0, color='tab:purple', label='translation [mm]')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('device - VT distance [mm]')
    lines = ax.get_lines()
    if trace.task.rotation_dim:     # a point grasp (spatial_point) has no orientation
        rot = np.full(len(trace), np.nan)
        ok = (np.all(np.isfinite(vt[:, 3:6]), axis=1)
              & np.all(np.isfinite(dev[:, 3:6]), axis=1))
        for k in np.nonzero(ok)[0]:
            rot[k] = np.linalg.norm(pin.log3(pin.exp3(vt[k, 3:6]) @ pin.exp3(dev[k, 3:6]).T))
        twin = ax.twinx()
        twin.plot(t, np.degrees(rot), color='tab:gray', ls=':', label='orientation [deg]')
        twin.set_ylabel('device - VT orientation error [deg]')
        lines += twin.get_lines()
    ax.legend(lines, [str(ln.get_label()) for ln in lines], loc='upper left')
    ax.set_title('(e) drift')
    ax.grid(alpha=0.3)
    _constraint_panel(grid[1, 2], trace, linkage)
    grid[1, 2].set_title('(f) directions of topological constraint')
    if forces is not None:
        _forces_panel(forces, trace, '(g)', [ax, grid[1, 2]])
    _finish(fig, trace, title)
    return fig
