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
from frslam_graph.floorplan.render import draw_grid, draw_plan, known_bounds
from frslam_graph.occupancy import OccupancyGrid


def save_grid_png(grid: OccupancyGrid, out: str | Path, title: str = "") -> Path:
    """Write a PNG of the grid with metric axes, framed on its known cells (:func:`known_bounds`)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    box = known_bounds(grid)
    aspect = grid.height / max(grid.width, 1) if box is None else (box[3] - box[2]) / (box[1] - box[0])
    fig = Figure(figsize=(8, max(3.0, 8 * aspect)))
    ax = fig.add_subplot(1, 1, 1)
    draw_grid(ax, grid)
    if box is not None:
        ax.set_xlim(box[0], box[1])
        ax.set_ylim(box[2], box[3])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)


def _draw_overview(
    ax: Any,
    trajectories: dict[str, np.ndarray],
    grid: OccupancyGrid | None,
    plan: Any,
    ground_truth: np.ndarray | None = None,
    refused_plan: Any = None,
) -> None:
    """The map, the registered plan (faint) or a refused placement (dashed room outlines), the
    ground truth (dashed) and each trajectory on ``ax``."""
    if grid is not None:
        draw_grid(ax, grid)
    if plan is not None:
        draw_plan(ax, plan, alpha=0.25, labels=False, legend=False)
    elif refused_plan is not None:
        for k, room in enumerate(refused_plan.rooms):
            xy = np.asarray(room.polygon.exterior.coords)
            label = "plan: placement refused by the checks" if k == 0 else None
            ax.plot(xy[:, 0], xy[:, 1], color="tab:red", lw=0.9, ls="--", alpha=0.8, label=label)
    if ground_truth is not None and len(ground_truth):
        ax.plot(ground_truth[:, 1], ground_truth[:, 2], color="black", lw=1.2, ls="--", label="ground truth")
    for name, traj in trajectories.items():
        if len(traj):
            ax.plot(traj[:, 1], traj[:, 2], lw=1.2, label=name)


def save_trajectory_png(
    out: str | Path,
    trajectories: dict[str, np.ndarray],
    ground_truth: np.ndarray | None = None,
    grid: OccupancyGrid | None = None,
    plan: Any = None,
    title: str = "",
    refused_plan: Any = None,
) -> Path:
    """Trajectories ((N, 4) stamp, x, y, theta in map) over an optional map and registered plan
    (or, dashed, the placement of a registration its checks refused: ``refused_plan``)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(10, 8))
    ax = fig.add_subplot(1, 1, 1)
    _draw_overview(ax, trajectories, grid, plan, ground_truth, refused_plan)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)


def compare_figure(
    trajectories: dict[str, np.ndarray],
    ground_truth: np.ndarray | None = None,
    grid: OccupancyGrid | None = None,
    plan: Any = None,
    title: str = "",
) -> Figure:
    """The comparison of runs, evo-style: an overview (every trajectory over the map and the
    registered plan, map frame) and, with a ground truth, each run's trajectory coloured by its
    translation error (SE(2)-aligned to the ground truth, one colour scale for all) and the
    errors over the distance travelled. Without a ground truth only the overview."""
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    from frslam_graph.errors import TrajectoryError
    from frslam_graph.evaluation.metrics import translation_errors

    errors: dict[str, tuple[np.ndarray, ...]] = {}
    if ground_truth is not None and len(ground_truth) > 1:
        for name, traj in trajectories.items():
            try:
                errors[name] = translation_errors(traj, ground_truth)
            except TrajectoryError:  # another recording's ground truth: the run reports it
                pass
    n = len(errors)
    fig = Figure(figsize=(6 * (1 + n), 9 if n else 7), layout="constrained")
    grid_spec = fig.add_gridspec(2 if n else 1, 1 + n, height_ratios=[3, 1.4] if n else [1])
    ax = fig.add_subplot(grid_spec[0, 0])
    _draw_overview(ax, trajectories, grid, plan)
    ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", title="trajectories (map frame)")
    ax.legend(loc="best", fontsize=8)
    if n:
        top = max(float(e[1].max()) for e in errors.values()) or 1.0
        norm = Normalize(0.0, top)
        panels = []
        for k, (name, (_, err, est, ref)) in enumerate(errors.items(), start=1):
            axk = fig.add_subplot(grid_spec[0, k])
            axk.plot(ref[:, 1], ref[:, 2], color="0.6", lw=1.0, ls="--", label="ground truth")
            segments = np.stack([est[:-1, 1:3], est[1:, 1:3]], axis=1)
            lines = LineCollection(segments, cmap="jet", norm=norm, lw=2.0)
            lines.set_array(0.5 * (err[:-1] + err[1:]))
            axk.add_collection(lines)
            axk.autoscale_view()
            rmse = float(np.sqrt(np.mean(err**2)))
            axk.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", title=f"{name}: ATE RMSE {rmse:.3f} m")
            axk.legend(loc="best", fontsize=8)
            panels.append(axk)
        fig.colorbar(lines, ax=panels, label="translation error [m] (SE(2)-aligned)", shrink=0.8)
        ax_err = fig.add_subplot(grid_spec[1, :])
        for name, (dist, err, _, _) in errors.items():
            ax_err.plot(dist, err, lw=1.2, label=f"{name} (RMSE {float(np.sqrt(np.mean(err**2))):.3f} m)")
        ax_err.set(
            xlabel="distance travelled [m]", ylabel="translation error [m]", title="error over distance"
        )
        ax_err.grid(alpha=0.3)
        ax_err.legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def save_compare_png(
    out: str | Path,
    trajectories: dict[str, np.ndarray],
    ground_truth: np.ndarray | None = None,
    grid: OccupancyGrid | None = None,
    plan: Any = None,
    title: str = "",
) -> Path:
    """Write :func:`compare_figure` to ``out``."""
    return save_figure(compare_figure(trajectories, ground_truth, grid, plan, title), out, dpi=100)
