"""Navigation on a registered floor plan: the map of rooms the robot has not yet visited.

The plan must be in map metres (``registration.apply(plan)``). Free space is every room eroded
by half a wall thickness plus an opening at every door joining two rooms (the same geometry as
:mod:`frslam_graph.localisation.relocalisation`); a cell is passable when its distance to the nearest wall
is at least ``clearance`` (the robot's radius plus a margin). Paths are shortest paths
(Dijkstra on the 8-connected raster, :func:`scipy.sparse.csgraph.dijkstra`) with a mild
penalty near walls, so they keep to the middle of door openings.

- :func:`room_graph`: rooms connected through doors (ids; doors without room links are linked
  by geometry);
- :func:`plan_path`: a path from a start (x, y) to a room id or a point (x, y);
- :func:`unvisited_rooms`: the rooms a LiDAR occupancy grid has not yet covered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from frslam_graph.errors import FloorPlanError, FrslamError
from frslam_graph.localisation.relocalisation import free_space_polygons
from frslam_graph.raster import RasterFrame, rasterise_plan, rasterise_polygons


@dataclass
class Path:
    """A planned path in map metres. ``ok`` False (with ``reason``) when there is none."""

    points: np.ndarray  # (N, 2)
    length: float
    rooms: tuple[str, ...]  # rooms traversed, in order
    ok: bool = True
    reason: str = ""
    goal: tuple[float, float] | None = None
    info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class NavigationMap:
    """Passable cells of a plan: frame, distance to walls (m), room labels (index + 1, 0 = none)."""

    frame: RasterFrame
    clearance_map: np.ndarray  # (H, W) float32 metres
    labels: np.ndarray  # (H, W) int32
    room_ids: tuple[str, ...]

    @classmethod
    def from_plan(cls, plan, resolution: float = 0.05, wall_offset: float = 0.06) -> NavigationMap:
        _check_metric(plan)
        if not (np.isfinite(resolution) and resolution > 0):
            raise FrslamError(f"grid resolution must be positive, got {resolution}", where="grid_resolution")
        try:
            frame = RasterFrame.around(plan.bounds, resolution, margin=2 * resolution + wall_offset)
        except ValueError as exc:
            raise FloorPlanError(
                f"plan too large to rasterise: {exc}", source=plan.source, where="bounds"
            ) from None
        free = rasterise_polygons(free_space_polygons(plan, max(wall_offset, 0.5 * resolution)), frame)
        dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(resolution)
        labels = rasterise_plan(plan, frame, labels=True)
        return cls(frame, dist.astype(np.float32), labels, tuple(plan.room_ids))

    def cell(self, xy) -> tuple[int, int]:
        c = self.frame.to_pixel(np.asarray(xy, dtype=np.float64).reshape(1, 2))[0]
        return int(np.floor(c[1])), int(np.floor(c[0]))

    def room_at(self, xy) -> str | None:
        r, c = self.cell(xy)
        h, w = self.labels.shape
        if not (0 <= r < h and 0 <= c < w):
            return None
        k = int(self.labels[r, c])
        return self.room_ids[k - 1] if k else None


def room_graph(plan) -> dict[str, set[str]]:
    """Rooms connected through doors (every room is a key)."""
    doors = plan.doors
    if any(len(set(d.rooms)) < 2 for d in doors):
        linked = plan.link_doors(tol=0.3 if plan.units == "m" else 0.02 * _diag(plan))
        doors = [d if len(set(d.rooms)) == 2 else ld for d, ld in zip(doors, linked.doors, strict=True)]
    adj: dict[str, set[str]] = {r.id: set() for r in plan.rooms}
    for d in doors:
        ids = tuple(dict.fromkeys(d.rooms))
        if len(ids) == 2:
            adj[ids[0]].add(ids[1])
            adj[ids[1]].add(ids[0])
    return adj


def plan_path(
    plan_in_map,
    start_xy,
    goal,
    grid_resolution: float = 0.05,
    clearance: float = 0.25,
    wall_offset: float = 0.06,
    nav: NavigationMap | None = None,
) -> Path:
    """Shortest passable path from ``start_xy`` to ``goal`` (a room id, or (x, y) in map metres).

    A goal room is reached at its most open cell. Start and goal points closer than
    ``clearance`` to a wall are snapped to the nearest passable cell within ``2 * clearance``.
    Raises :class:`FloorPlanError` for an unknown room id; returns ``ok=False`` with a reason
    when the start or goal is not in free space or the goal cannot be reached.
    """
    if not (np.isfinite(clearance) and clearance >= 0):
        raise FrslamError(f"clearance must be >= 0 metres, got {clearance}", where="clearance")
    nav = nav or NavigationMap.from_plan(plan_in_map, grid_resolution, wall_offset)
    start = np.asarray(start_xy, dtype=np.float64).reshape(-1)
    if start.shape != (2,) or not np.all(np.isfinite(start)):
        raise FrslamError(f"start must be a finite (x, y), got {start_xy!r}", where="start")
    passable = nav.clearance_map >= max(clearance, 0.5 * nav.frame.resolution)
    h, w = passable.shape

    def fail(reason: str, culprit: str = "goal") -> Path:
        """No path; ``info["culprit"]``: the input at fault ("start" or "goal")."""
        return Path(np.zeros((0, 2)), float("inf"), (), False, reason, info={"culprit": culprit})

    s = _snap(nav, passable, start, 2 * clearance + nav.frame.resolution)
    if s is None:
        return fail(f"start {_fmt(start)} is not in the plan's free space (clearance {clearance} m)", "start")
    if isinstance(goal, str):
        if goal not in nav.room_ids:
            raise FloorPlanError(
                f"unknown room {goal!r} (the plan has {', '.join(nav.room_ids)})",
                source=plan_in_map.source,
                where="goal",
            )
        k = nav.room_ids.index(goal) + 1
        in_room = (nav.labels == k) & passable
        if not in_room.any():
            return fail(f"room {goal!r} has no cell with {clearance} m clearance from its walls")
        targets = np.flatnonzero(in_room.reshape(-1))
    else:
        g = np.asarray(goal, dtype=np.float64).reshape(-1)
        if g.shape != (2,) or not np.all(np.isfinite(g)):
            raise FrslamError(f"goal must be a room id or a finite (x, y), got {goal!r}", where="goal")
        gc = _snap(nav, passable, g, 2 * clearance + nav.frame.resolution)
        if gc is None:
            return fail(f"goal {_fmt(g)} is not in the plan's free space (clearance {clearance} m)")
        targets = np.array([gc[0] * w + gc[1]])
    graph = _grid_graph(passable, nav.clearance_map, nav.frame.resolution, clearance)
    src = s[0] * w + s[1]
    dist, pred = dijkstra(graph, directed=False, indices=src, return_predecessors=True)
    if isinstance(goal, str):
        reach = targets[np.isfinite(dist[targets])]
        if not len(reach):
            return fail(_unreachable(goal, nav, start, plan_in_map, clearance))
        # the most open reachable cell of the room (ties: the nearest)
        open_ = nav.clearance_map.reshape(-1)[reach]
        best = reach[open_ >= open_.max() - nav.frame.resolution]
        tgt = int(best[np.argmin(dist[best])])
    else:
        tgt = int(targets[0])
        if not np.isfinite(dist[tgt]):
            return fail(_unreachable(nav.room_at(goal) or "the goal", nav, start, plan_in_map, clearance))
    cells = [tgt]
    while cells[-1] != src:
        cells.append(int(pred[cells[-1]]))
    cells = np.array(cells[::-1])
    rc = np.column_stack((cells // w, cells % w))
    pts = nav.frame.to_world(np.column_stack((rc[:, 1] + 0.5, rc[:, 0] + 0.5)))
    pts[0] = start if _dist(pts[0], start) < 2 * clearance + nav.frame.resolution else pts[0]
    if not isinstance(goal, str):
        pts[-1] = np.asarray(goal, float)
    length = float(np.sum(np.hypot(*np.diff(pts, axis=0).T))) if len(pts) > 1 else 0.0
    labs = nav.labels[rc[:, 0], rc[:, 1]]
    labs = labs[labs > 0]
    order = labs[np.r_[True, labs[1:] != labs[:-1]]] if len(labs) else labs
    rooms = tuple(nav.room_ids[k - 1] for k in order)
    return Path(pts, length, rooms, True, "", (float(pts[-1, 0]), float(pts[-1, 1])))


def unvisited_rooms(plan_in_map, visited_grid, min_observed: float = 0.3) -> list[str]:
    """Rooms of which less than ``min_observed`` of the area is known (free or occupied) in the
    occupancy grid (same map frame; the grid's yaw must be 0)."""
    _check_metric(plan_in_map)
    if visited_grid.origin[2] != 0.0:
        raise FrslamError("grids with a rotated origin are not supported", where="visited_grid.origin")
    labels = rasterise_plan(plan_in_map, visited_grid.frame, labels=True)
    known = ~visited_grid.unknown_mask()
    n = len(plan_in_map.rooms) + 1
    total_cells = np.bincount(labels.reshape(-1), minlength=n)
    known_cells = np.bincount(labels[known].reshape(-1), minlength=n)
    out = []
    for i, r in enumerate(plan_in_map.rooms):
        area_cells = r.area / visited_grid.resolution**2  # rooms partly off the grid count as unknown there
        seen = known_cells[i + 1] / max(area_cells, total_cells[i + 1], 1.0)
        if seen < min_observed:
            out.append(r.id)
    return out


# --------------------------------------------------------------------------- helpers
def _check_metric(plan) -> None:
    if plan.units != "m" and plan.metres_per_unit is None:
        raise FloorPlanError(
            f"the plan is in {plan.units!r}, not metres: register it first (frslam register PLAN MAP.yaml writes it in metres; in Python registration.apply(plan))",
            source=plan.source,
            where="units",
        )


def _diag(plan) -> float:
    b = plan.bounds
    return float(np.hypot(b[2] - b[0], b[3] - b[1]))


def _fmt(xy) -> str:
    return f"({float(xy[0]):.2f}, {float(xy[1]):.2f})"


def _dist(a, b) -> float:
    return float(np.hypot(a[0] - b[0], a[1] - b[1]))


def _snap(nav: NavigationMap, passable: np.ndarray, xy: np.ndarray, radius: float):
    """(row, col) of the nearest passable cell within ``radius`` of ``xy`` that is in the same
    free region (not through a wall), or None."""
    h, w = passable.shape
    r0, c0 = nav.cell(xy)
    if not (0 <= r0 < h and 0 <= c0 < w) or nav.clearance_map[r0, c0] <= 0:
        return None
    if passable[r0, c0]:
        return r0, c0
    k = int(np.ceil(radius / nav.frame.resolution))
    rs, cs = slice(max(r0 - k, 0), min(r0 + k + 1, h)), slice(max(c0 - k, 0), min(c0 + k + 1, w))
    win = passable[rs, cs]
    if not win.any():
        return None
    rr, cc = np.nonzero(win)
    rr, cc = rr + rs.start, cc + cs.start
    d = np.hypot(rr - r0, cc - c0)
    j = int(np.argmin(d))
    if d[j] * nav.frame.resolution > radius:
        return None
    return int(rr[j]), int(cc[j])


def _grid_graph(passable: np.ndarray, clearance_map: np.ndarray, res: float, clearance: float):
    """Sparse 8-connected graph of passable cells; edge weight = length · (1 + penalty near walls)."""
    h, w = passable.shape
    idx = np.arange(h * w).reshape(h, w)
    pref = max(2.0 * clearance, 2.0 * res)
    pen = 1.0 + 2.0 * np.clip((pref - clearance_map) / pref, 0.0, 1.0)  # up to 3x near walls
    rows, cols, wts = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        if dc >= 0:
            sa, sb = (slice(0, h - dr), slice(0, w - dc)), (slice(dr, h), slice(dc, w))
        else:
            sa, sb = (slice(0, h - dr), slice(-dc, w)), (slice(dr, h), slice(0, w + dc))
        m = passable[sa] & passable[sb]
        step = res * np.hypot(dr, dc)
        rows.append(idx[sa][m])
        cols.append(idx[sb][m])
        wts.append(step * 0.5 * (pen[sa][m] + pen[sb][m]))
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    v = np.concatenate(wts)
    return coo_matrix((v, (r, c)), shape=(h * w, h * w)).tocsr()


def _unreachable(goal: str, nav: NavigationMap, start: np.ndarray, plan, clearance: float) -> str:
    here = nav.room_at(start)
    links = room_graph(plan)
    seen, todo = {here}, [here]
    while todo:
        for nb in links.get(todo.pop(), ()):
            if nb not in seen:
                seen.add(nb)
                todo.append(nb)
    if here is not None and goal not in seen:
        return f"{goal!r} is not reachable from room {here!r}: no chain of doors connects them"
    return f"{goal!r} is not reachable from {_fmt(start)} with {clearance} m clearance (doors too narrow?)"


__all__ = ["NavigationMap", "Path", "plan_path", "room_graph", "unvisited_rooms"]
