"""The energy figure of a run (``energy.png`` of ``simulate``, ``<run>_energy.png`` of
``analyze``): the work at the device port per axis and in total, the hand's work, and for a
run that carries its controller's account the passivity observer and the passivity
controller's damping (:mod:`haptic_topology.control.passivity`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np

from haptic_topology.sim.trace import Trace, run_name


def work_integrals(trace: Trace) -> tuple[np.ndarray, np.ndarray]:
    """The accumulated work (J) of the applied wrench per axis (rows x m) and of the hand
    wrench (rows): row k's wrench times its twist and period, the trace's work integral; a
    trace of sampled rows carries them summed over every row (``work_integral``,
    ``hand_work_integral``: ``haptic_topology.bag.energy_series``)."""
    if 'work_integral' in trace.columns:
        return trace.columns['work_integral'], trace.columns['hand_work_integral']
    dt = np.diff(trace.t, prepend=np.nan)
    ok = np.isfinite(dt)
    v = trace.columns['device_twist']
    port = trace.columns['applied'] * v * dt[:, None]
    port[~(ok & np.all(np.isfinite(port), axis=1))] = 0.0
    hand = (trace.columns['hand_wrench'] * v).sum(axis=1) * dt
    hand[~(ok & np.isfinite(hand))] = 0.0
    return np.cumsum(port, axis=0), np.cumsum(hand)


def energy_figure(trace: Trace, title: str | None = None) -> plt.Figure:
    """The figure (see module doc); the caller closes it."""
    port, hand = work_integrals(trace)
    t = trace.t
    rows = 2 if trace.has_energy else 1
    fig, axes = plt.subplots(rows, 1, figsize=(9, 3.2 * rows), sharex=True, squeeze=False)
    ax = axes[0][0]
    for i in range(port.shape[1]):
        ax.plot(t, 1e3 * port[:, i], lw=1, label=f'port, axis {i}')
    ax.plot(t, 1e3 * port.sum(axis=1), color='black', lw=1.5, label='port, total')
    ax.plot(t, 1e3 * hand, color='tab:purple', ls='--', label='hand (user)')
    ax.set_ylabel('work [mJ]')
    ax.set_title('(a) work into the device port (applied x twist x dt) and the hand\'s')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=3)
    if trace.has_energy:
        ax = axes[1][0]
        ax.plot(t, 1e3 * trace.columns['passivity_observer'], color='tab:green',
                label='passivity observer')
        ax.axhline(0.0, color='0.5', lw=0.8)
        ax.set_ylabel('observer [mJ]')
        ax.set_title('(b) passivity observer; passivity controller damping (right)')
        ax.grid(alpha=0.3)
        twin = ax.twinx()
        twin.plot(t, trace.columns['passivity_damping'], color='tab:red', lw=0.8,
                  label='damping')
        twin.set_ylabel('damping [N s/m]', color='tab:red')
    axes[-1][0].set_xlabel('t [s]')
    name = title or run_name(str(trace.meta.get('scenario', '')),
                             str(trace.meta.get('linkage_file', '')))
    fig.suptitle(f'{name}: energy ({trace.meta.get("mode", "")})')
    fig.tight_layout()
    return fig


def plot_energy(trace: Trace, path: str | Path, title: str | None = None) -> Path:
    """Write :func:`energy_figure` of ``trace`` to ``path`` (PNG) and return the path."""
    out = Path(path)
    fig = energy_figure(trace, title)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
