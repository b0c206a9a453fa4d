"""Drawing helpers (matplotlib, Agg backend): occupancy grids in metric axes, trajectories.

Used by the CLI and ``tools/`` only (library code never draws on its own). Axes are the ``map``
frame in metres with y up (REP-103). Plans are drawn by :mod:`frslam_graph.floorplan.render`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from frslam_graph.atomic import save_figure
from frslam_graph.floorplan.render import draw_grid, draw_plan
from frslam_graph.occupancy import OccupancyGrid


def save_grid_png(grid: OccupancyGrid, out: str | Path, title: str = "") -> Path:
    """Write a PNG of the grid with metric axes."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    aspect = grid.height / max(grid.width, 1)
    fig = Figure(figsize=(8, max(3.0, 8 * aspect)))
    ax = fig.add_subplot(1, 1, 1)
    draw_grid(ax, grid)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)


def save_trajectory_png(
    out: str | Path,
    trajectories: dict[str, np.ndarray],
    ground_truth: np.ndarray | None = None,
    grid: OccupancyGrid | None = None,
    plan: Any = None,
    title: str = "",
) -> Path:
    """Trajectories ((N, 4) stamp, x, y, theta in map) over an optional map and registered plan."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(10, 8))
    ax = fig.add_subplot(1, 1, 1)
    if grid is not None:
        draw_grid(ax, grid)
    if plan is not None:
        draw_plan(ax, plan, alpha=0.25, labels=False, legend=False)
    if ground_truth is not None and len(ground_truth):
        ax.plot(ground_truth[:, 1], ground_truth[:, 2], color="black", lw=1.2, ls="--", label="ground truth")
    for name, traj in trajectories.items():
        if len(traj):
            ax.plot(traj[:, 1], traj[:, 2], lw=1.2, label=name)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)
