"""Pictures of fleet runs: a PNG of every robot's path and a GIF of the steps (matplotlib, Pillow).

Drawn in grid coordinates as seen from above: column to the right, row 0 at the top (the world
frame's +y is up the picture, docs/FLEET.md). Starts are hexagons, goals dots, as in the paper's
Fig. 7; robots 0, 1, 2 are red, green, blue. Optional odometry tracks (x, y in metres) are drawn
thin over the cell-to-cell path.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402

COLORS = ["#d62728", "#2ca02c", "#1f4fd8", "#ff9f0e", "#9467bd", "#17becf", "#8c564b", "#e377c2"]


def _check(grid, positions, goals):
    grid = np.asarray(grid)
    positions = np.asarray(positions)
    goals = np.asarray(goals)
    if grid.ndim != 2:
        raise ValueError(f"grid must be (H, W), got shape {grid.shape}")
    if positions.ndim != 3 or positions.shape[2] != 2 or positions.shape[0] < 1:
        raise ValueError(f"positions must be (T+1, N, 2), got shape {positions.shape}")
    if goals.shape != positions.shape[1:]:
        raise ValueError(f"goals must be ({positions.shape[1]}, 2), got shape {goals.shape}")
    return grid, positions, goals


def _draw(ax, grid, positions, goals, upto: int, tracks=None, cell_size: float = 1.0, title: str = ""):
    h, w = grid.shape
    ax.clear()
    ax.imshow(grid, cmap="Greys", vmin=0, vmax=1.4, origin="upper", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    ax.set_xticks(np.arange(-0.5, w, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, h, 1), minor=True)
    ax.grid(which="minor", color="#bbbbbb", linewidth=0.4)
    ax.tick_params(which="both", length=0, labelsize=6)
    for i in range(positions.shape[1]):
        c = COLORS[i % len(COLORS)]
        path = positions[: upto + 1, i]
        ax.plot(path[:, 1], path[:, 0], "-", color=c, linewidth=2.2, alpha=0.75)
        ax.plot(positions[0, i, 1], positions[0, i, 0], "h", color=c, markersize=11, markeredgecolor="k")
        ax.plot(goals[i, 1], goals[i, 0], "o", color=c, markersize=8, markeredgecolor="k")
        ax.plot(path[-1, 1], path[-1, 0], "s", color=c, markersize=7, alpha=0.9, markeredgecolor="k")
        if tracks and i in tracks and len(tracks[i]):
            xy = np.asarray(tracks[i])
            ax.plot(xy[:, 0] / cell_size, -xy[:, 1] / cell_size, "-", color="k", linewidth=0.6, alpha=0.7)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(title, fontsize=9)


def render_png(path, grid, positions, goals, tracks: Optional[Dict[int, Sequence]] = None,
               cell_size: float = 1.0, title: str = "") -> Path:
    """PNG of the whole run: paths (T+1, N, 2) cells; tracks[i] = (K, 2) odometry x, y in metres."""
    grid, positions, goals = _check(grid, positions, goals)
    h, w = grid.shape
    fig, ax = plt.subplots(figsize=(max(4.0, w * 0.45), max(4.0, h * 0.45)), dpi=110)
    _draw(ax, grid, positions, goals, positions.shape[0] - 1, tracks, cell_size, title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def render_gif(path, grid, positions, goals, title: str = "", fps: float = 3.0, max_frames: int = 300) -> Path:
    """GIF with one frame per grid step (at most max_frames, evenly picked)."""
    grid, positions, goals = _check(grid, positions, goals)
    h, w = grid.shape
    steps = positions.shape[0]
    frames = np.unique(np.linspace(0, steps - 1, min(steps, max_frames)).round().astype(int))
    fig, ax = plt.subplots(figsize=(max(3.5, w * 0.35), max(3.5, h * 0.35)), dpi=80)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=80):
        for t in frames:
            _draw(ax, grid, positions, goals, int(t), title=f"{title} step {t}/{steps - 1}".strip())
            writer.grab_frame()
    plt.close(fig)
    return path
