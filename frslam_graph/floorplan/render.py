"""Draw a :class:`FloorPlan` with matplotlib (Agg): rooms filled by type with a legend, walls,
doors, room ids/types; optionally over an occupancy grid (map metres) after a 3×3 transform.

Coordinates are plan units (y up) unless ``transform`` (plan -> target frame, e.g. a
registration's ``matrix`` into map metres) is given. This module only draws into files or
axes given to it; it never shows windows or prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Polygon

from frslam_graph.atomic import save_figure
from frslam_graph.floorplan.model import ROOM_TYPES, FloorPlan

_PALETTE = (
    "#8dd3c7",
    "#ffffb3",
    "#bebada",
    "#fb8072",
    "#80b1d3",
    "#fdb462",
    "#b3de69",
    "#fccde5",
    "#bc80bd",
    "#ccebc5",
    "#ffed6f",
    "#a6cee3",
    "#b2df8a",
    "#fb9a99",
    "#d9d9d9",
)
TYPE_COLOURS: dict[str, str] = dict(zip(ROOM_TYPES, _PALETTE, strict=False))
TYPE_COLOURS["unknown"] = "#d9d9d9"


def type_colour(room_type: str) -> str:
    """Fill colour of a room type (unknown types are grey)."""
    return TYPE_COLOURS.get(room_type, TYPE_COLOURS["unknown"])


def _affine(matrix: np.ndarray | None) -> list[float] | None:
    if matrix is None:
        return None
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise ValueError("transform must be a finite 3x3 matrix")
    return [m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[0, 2], m[1, 2]]


def _apply(points: np.ndarray, params: list[float] | None) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if params is None:
        return pts
    a, b, d, e, xo, yo = params
    return np.column_stack([a * pts[:, 0] + b * pts[:, 1] + xo, d * pts[:, 0] + e * pts[:, 1] + yo])


def draw_grid(ax: Any, grid: Any, cmap: str = "gray") -> None:
    """Draw an occupancy grid (``data`` int8 -1/0/100, row 0 = lowest y; ``origin`` yaw 0) in map metres."""
    data = np.asarray(grid.data)
    img = np.full(data.shape, 0.75)  # unknown: light grey
    img[data == 0] = 1.0
    img[data >= 50] = 0.0
    ox, oy = float(grid.origin[0]), float(grid.origin[1])
    res = float(grid.resolution)
    h, w = data.shape
    ax.imshow(
        img, cmap=cmap, vmin=0, vmax=1, origin="lower", extent=(ox, ox + w * res, oy, oy + h * res), zorder=0
    )


def known_bounds(grid: Any, margin: float = 1.0) -> tuple[float, float, float, float] | None:
    """(xmin, xmax, ymin, ymax), map metres, of the grid's known cells (``data`` >= 0: free or
    occupied) widened by ``margin`` m, or None when no cell is known: the part of a map worth
    drawing (a sensor map's image is often mostly unknown border). The box's corners go through
    the grid's origin, its yaw too."""
    known = np.asarray(grid.data) >= 0
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if not len(rows):
        return None
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    xy = grid.cell_to_world(np.array([[c0, r0], [c1, r0], [c0, r1], [c1, r1]], dtype=np.float64))
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def draw_plan(
    ax: Any,
    plan: FloorPlan,
    transform: np.ndarray | None = None,
    alpha: float = 0.6,
    labels: bool = True,
    walls: bool = True,
    doors: bool = True,
    legend: bool = True,
    fontsize: float = 7.0,
    colour_by: str = "auto",
) -> None:
    """Draw ``plan`` into matplotlib axes ``ax`` (see module docstring).

    ``colour_by``: "type" (legend of room types), "room" (one colour per room) or "auto" (by
    room when every room has the same type, e.g. a room segmentation, else by type)."""
    from matplotlib.patches import Patch, PathPatch
    from matplotlib.path import Path as MplPath

    params = _affine(transform)
    used: dict[str, str] = {}
    if colour_by == "auto":
        colour_by = "room" if len({r.type for r in plan.rooms}) <= 1 and len(plan.rooms) > 1 else "type"
    for index, room in enumerate(plan.rooms):
        poly: Polygon = room.polygon
        if params is not None:
            poly = shapely.affinity.affine_transform(poly, params)
        rings = [np.asarray(poly.exterior.coords)] + [np.asarray(h.coords) for h in poly.interiors]
        verts = np.concatenate(rings)
        codes = np.concatenate(
            [[MplPath.MOVETO] + [MplPath.LINETO] * (len(r) - 2) + [MplPath.CLOSEPOLY] for r in rings]
        )
        if colour_by == "room":
            colour = _PALETTE[index % len(_PALETTE)]
        else:
            colour = type_colour(room.type)
            used[room.type] = colour
        ax.add_patch(
            PathPatch(
                MplPath(verts, codes), facecolor=colour, edgecolor="#555555", lw=0.6, alpha=alpha, zorder=1
            )
        )
        if labels:
            p = poly.representative_point()
            ax.text(
                p.x, p.y, f"{room.id}\n{room.type}", ha="center", va="center", fontsize=fontsize, zorder=4
            )
    if walls and plan.walls is not None and len(plan.walls):
        w = _apply(plan.walls.reshape(-1, 2), params).reshape(-1, 4)
        xs = np.column_stack([w[:, 0], w[:, 2], np.full(len(w), np.nan)]).ravel()
        ys = np.column_stack([w[:, 1], w[:, 3], np.full(len(w), np.nan)]).ravel()
        ax.plot(xs, ys, color="black", lw=1.5, zorder=2, solid_capstyle="butt")
    if doors and plan.doors:
        seg = _apply(np.array([[*d.a, *d.b] for d in plan.doors]).reshape(-1, 2), params).reshape(-1, 4)
        xs = np.column_stack([seg[:, 0], seg[:, 2], np.full(len(seg), np.nan)]).ravel()
        ys = np.column_stack([seg[:, 1], seg[:, 3], np.full(len(seg), np.nan)]).ravel()
        ax.plot(xs, ys, color="#d62728", lw=2.5, zorder=3, solid_capstyle="butt")
    if legend and (used or (doors and plan.doors)):
        handles = [
            Patch(facecolor=c, edgecolor="#555555", alpha=alpha, label=t) for t, c in sorted(used.items())
        ]
        if doors and plan.doors:
            from matplotlib.lines import Line2D

            handles.append(Line2D([], [], color="#d62728", lw=2.5, label="door"))
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_aspect("equal")
    ax.autoscale_view()


def render_plan(
    plan: FloorPlan,
    out_png: str | Path,
    transform: np.ndarray | None = None,
    grid: Any = None,
    title: str | None = None,
    dpi: int = 120,
    size: float = 8.0,
    **draw_options: Any,
) -> Path:
    """Render ``plan`` to a PNG (optionally over ``grid``, an OccupancyGrid in map metres, with
    ``transform`` mapping plan -> map). Returns the written path."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(size * 1.3, size))
    ax = fig.add_subplot(1, 1, 1)
    if grid is not None:
        draw_grid(ax, grid)
    draw_plan(ax, plan, transform=transform, **draw_options)
    units = "m" if transform is not None or grid is not None else plan.units
    ax.set_xlabel(f"x [{units}]")
    ax.set_ylabel(f"y [{units}]")
    ax.set_title(title if title is not None else (plan.name or "floor plan"))
    fig.tight_layout()
    return save_figure(fig, out, dpi=dpi)
