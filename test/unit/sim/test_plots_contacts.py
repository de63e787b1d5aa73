"""Trace plots of runs with obstacles: the contact panel, the contact shading, the obstacles on
the workspace panels, and the unchanged figure of a run without contacts."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.axes import Axes

from haptic_topology.model.obstacles import Obstacle, ObstacleKind
from haptic_topology.sim.lockstep import simulate
from haptic_topology.sim.plots import contact_intervals, plot_trace, trace_figure
from haptic_topology.sim.scenario import Scenario, load_scenario
from haptic_topology.sim.trace import Trace

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels from the PNG's IHDR chunk; asserts the signature."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_MAGIC
    assert head[12:16] == b'IHDR'
    width, height = struct.unpack('>II', head[16:24])
    return int(width), int(height)


def _legend(ax: Axes) -> list[str]:
    """The texts of ``ax``'s legend (asserts it has one)."""
    legend = ax.get_legend()
    assert legend is not None
    return [x.get_text() for x in legend.get_texts()]


def _run(name: str, duration: float) -> tuple[Scenario, Trace]:
    sc = load_scenario(name)
    return sc, simulate(dataclasses.replace(sc, duration=duration))


@pytest.fixture(scope='module')
def wall() -> tuple[Scenario, Trace]:
    return _run('wall', 0.3)


@pytest.fixture(scope='module')
def fig8() -> tuple[Scenario, Trace]:
    return _run('fig8', 0.2)


# -- contact_intervals --------------------------------------------------------------------------

def test_contact_intervals_merge_runs_and_end_at_the_next_row() -> None:
    t = np.arange(8.0)
    depth = np.array([0.0, 0.1, 0.2, 0.0, 0.0, 0.3, np.nan, 0.0])
    # Rows 1-2 hold until row 3; row 5 holds until row 6 (NaN: unknown, not in contact).
    assert contact_intervals(t, depth) == [(1.0, 3.0), (5.0, 6.0)]


def test_contact_intervals_edges() -> None:
    t = np.array([0.0, 0.5, 1.0, 1.5])
    assert contact_intervals(t, np.zeros(4)) == []
    assert contact_intervals(t, np.full(4, np.nan)) == []
    assert contact_intervals(np.zeros(0), np.zeros(0)) == []
    assert contact_intervals(t, np.full(4, 1e-4)) == [(0.0, 1.5)]
    # A run reaching the last row ends there; a run of only the last row is empty.
    assert contact_intervals(t, np.array([0.0, 0.0, 1e-3, 1e-3])) == [(1.0, 1.5)]
    assert contact_intervals(t, np.array([1e-3, 0.0, 0.0, 1e-3])) == [(0.0, 0.5), (1.5, 1.5)]
    with pytest.raises(ValueError, match='same length'):
        contact_intervals(t, np.zeros(3))


# -- figures ------------------------------------------------------------------------------------

def test_wall_plot_has_the_contact_panel_and_the_wall(wall: tuple[Scenario, Trace],
                                                      tmp_path: Path) -> None:
    sc, tr = wall
    assert tr.has_contacts and sc.contacts is not None
    intervals = contact_intervals(tr.t, tr.columns['penetration'])
    assert len(intervals) >= 1 and intervals[0][1] > intervals[0][0]   # the hand hits the wall

    out = plot_trace(tr, tmp_path / 'sub' / 'wall.png', sc.linkage,
                     obstacles=sc.contacts.obstacles)
    assert out == tmp_path / 'sub' / 'wall.png'
    assert out.stat().st_size > 50_000
    assert _png_size(out) == (1320, 1430)         # 12 x (9 + 4) in at 110 dpi

    fig = trace_figure(tr, sc.linkage, obstacles=sc.contacts.obstacles)
    try:
        # (a), (b), (c), (d), the contact panel (e) and its penetration axis.
        assert len(fig.axes) == 6
        linkage_ax, zoom, drift, constraints, forces, depth = fig.axes
        assert forces.get_title().startswith('(e) contact')
        assert depth.get_ylabel() == 'penetration [mm]'
        assert {'F_env fx [N]', 'F_env fy [N]', '|F_env| [N]', '|applied| [N]',
                '|F_h| (user) [N]', 'penetration [mm]'} <= set(_legend(forces))
        # One grey span per merged interval in each time-axis panel.
        for ax in (drift, constraints, forces):
            assert len(ax.patches) == len(intervals)
        # The wall (x = 108 mm) is drawn on the linkage panel; the zoom on the hand (about
        # 92 mm) keeps its view and leaves it out.
        assert 'wall (half-plane)' in _legend(linkage_ax)
        assert linkage_ax.get_xlim()[1] > 108.0
        assert 'wall (half-plane)' not in _legend(zoom)
        assert zoom.get_xlim()[1] < 100.0
    finally:
        plt.close(fig)


def test_plot_without_contacts_is_unchanged(fig8: tuple[Scenario, Trace],
                                            tmp_path: Path) -> None:
    sc, tr = fig8
    assert not tr.has_contacts
    out = plot_trace(tr, tmp_path / 'fig8.png', sc.linkage)
    assert out.stat().st_size > 50_000
    assert _png_size(out) == (1320, 990)          # 12 x 9 in at 110 dpi, as before
    fig = trace_figure(tr, sc.linkage)
    try:
        assert len(fig.axes) == 4                 # the 2 x 2 grid, as before
        assert all(not ax.patches for ax in fig.axes)
    finally:
        plt.close(fig)


def test_planar_obstacle_kinds_on_the_workspace_panel(fig8: tuple[Scenario, Trace]) -> None:
    sc, tr = fig8
    obstacles = (
        Obstacle(ObstacleKind.HALF_PLANE, 'floor', np.array([0.0, -0.03, 0.0]),
                 normal=np.array([0.0, 1.0, 0.0])),
        Obstacle(ObstacleKind.SEGMENT, 'bar', np.array([0.02, 0.05, 0.0]),
                 end=np.array([0.06, 0.05, 0.0]), radius=0.002),
        Obstacle(ObstacleKind.DISC, 'post', np.array([0.15, 0.0, 0.0]), radius=0.01),
        Obstacle(ObstacleKind.SPHERE, 'ball', np.zeros(3), radius=0.01),   # spatial: skipped
    )
    fig = trace_figure(tr, sc.linkage, obstacles=obstacles)
    try:
        assert len(fig.axes) == 4
        ax = fig.axes[0]
        names = _legend(ax)
        assert names == ['VE', 'HD', 'floor (half-plane)', 'bar (segment)', 'post (disc)']
        x0, x1 = ax.get_xlim()
        y0, y1 = ax.get_ylim()
        assert x1 >= 160.0 and y0 <= -30.0 and y1 >= 50.0    # the view shows all three
    finally:
        plt.close(fig)


def test_spatial_trace_with_contacts_and_spheres() -> None:
    sc, tr = _run('spatial_arm4', 0.1)
    assert tr.task_dim == 6 and not tr.has_contacts
    fig = trace_figure(tr, sc.linkage)
    try:
        assert len(fig.axes) == 7                 # 2 x 3 grid and the drift's twin, as before
    finally:
        plt.close(fig)

    # The same run with contact columns added by hand: contact from row 20 to row 49.
    n = len(tr)
    tr.meta['contacts'] = True
    env = np.zeros((n, 6))
    env[20:50, 0] = -0.5
    depth = np.zeros(n)
    depth[20:50] = 2e-4
    tr.columns.update(env_wrench=env, penetration=depth, contact_energy=np.zeros(n))
    grasp = tr.columns['vt_pose'][0, :3]
    ball = Obstacle(ObstacleKind.SPHERE, 'ball', grasp + np.array([0.02, 0.0, 0.0]),
                    radius=0.01)
    box = Obstacle(ObstacleKind.BOX, 'box', grasp, half_extents=np.full(3, 0.01))
    fig = trace_figure(tr, sc.linkage, obstacles=(ball, box))
    try:
        assert len(fig.axes) == 9                 # + the contact panel (g) and its twin
        forces = fig.axes[6]
        assert forces.get_title().startswith('(g) contact')
        assert 'F_env fz [N]' in _legend(forces)
        assert len(forces.patches) == 1           # one merged interval
        xy, xz = fig.axes[0], fig.axes[3]
        for ax in (xy, xz):
            names = _legend(ax)
            assert 'ball (sphere)' in names and 'box (box)' not in names
    finally:
        plt.close(fig)
