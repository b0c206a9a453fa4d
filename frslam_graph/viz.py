"""Drawing helpers (matplotlib, Agg backend): occupancy grids in metric axes, plan overlays.

Used by the CLI and ``tools/`` only (library code never draws on its own). Axes are the ``map``
frame in metres with y up (REP-103).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from frslam_graph.occupancy import OccupancyGrid  # noqa: E402


def grid_image(grid: OccupancyGrid) -> np.ndarray:
    """Grey image (H, W) float in [0, 1], row 0 = lowest y: white free, black occupied, grey unknown."""
    img = np.full(grid.shape, 0.8)
    img[grid.free_mask()] = 1.0
    img[grid.occupied_mask()] = 0.0
    return img


def draw_grid(ax, grid: OccupancyGrid, alpha: float = 1.0) -> None:
    """Draw a grid on ``ax`` in map metres (yaw of the origin is ignored for display)."""
    x0, y0, _ = grid.origin
    extent = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    ax.imshow(grid_image(grid), cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent, alpha=alpha,
              interpolation="nearest")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")


def save_grid_png(grid: OccupancyGrid, out: str | Path, title: str = "") -> Path:
    """Write a PNG of the grid with metric axes."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    aspect = grid.height / max(grid.width, 1)
    fig, ax = plt.subplots(figsize=(8, max(3.0, 8 * aspect)))
    draw_grid(ax, grid)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
