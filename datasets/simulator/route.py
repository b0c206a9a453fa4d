"""A robot route through rooms of the true house: planned, smoothed, driven by a unicycle.

Frame: the house's metric frame (``map``), metres, radians, seconds from the route's start.

1. Plan on a free-space raster (``resolution``) whose clearance (distance transform) must be at
   least ``clearance``; the cost of a cell grows near walls, so paths keep to the middle of
   corridors and doorways. Dijkstra (scipy) from each target to the next.
2. Targets: one point per visited room, drawn among the room's cells with the most clearance.
   The room sequence is given, or drawn: every reachable room once (nearest unvisited first,
   with some randomness), then random rooms until the route is at least ``length`` metres.
3. The cell path is smoothed (moving average) and driven by a pure-pursuit unicycle controller
   at ``dt`` with limits on speed (``max_speed``), turn rate (``max_turn_rate``) and
   accelerations, slowing for turns and turning in place when the heading error is large.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
from frslam_graph.datasets.simulator.house import House
from scipy import sparse
from scipy.sparse.csgraph import dijkstra

from frslam_graph.errors import ConfigError
from frslam_graph.raster import RasterFrame, rasterise_plan, rasterise_polygons
from frslam_graph.se2 import interpolate_poses, wrap_atan2


@dataclass(frozen=True)
class RouteParams:
    """Route planning and driving limits (metres, seconds, radians)."""

    max_speed: float = 0.5
    max_turn_rate: float = 1.0
    max_accel: float = 0.5
    max_angular_accel: float = 2.0
    robot_radius: float = 0.18
    clearance: float = 0.24  # planned path keeps at least this far from walls and obstacles
    resolution: float = 0.05
    lookahead: float = 0.25
    smoothing: float = 0.4  # moving-average window along the path, metres
    dt: float = 0.01

    def __post_init__(self) -> None:
        checks = {
            "max_speed": 0.0 < self.max_speed <= 3.0,
            "max_turn_rate": 0.0 < self.max_turn_rate <= 2.0 * math.pi,
            "max_accel": self.max_accel > 0.0,
            "max_angular_accel": self.max_angular_accel > 0.0,
            "robot_radius": 0.0 <= self.robot_radius < 1.0,
            "clearance": self.robot_radius <= self.clearance < 2.0,
            "resolution": 0.005 <= self.resolution <= 0.5,
            "lookahead": 0.0 < self.lookahead <= 2.0,
            "smoothing": 0.0 <= self.smoothing <= 5.0,
            "dt": 0.0 < self.dt <= 0.1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"value {getattr(self, name)!r} out of range", where=f"route.{name}")


@dataclass
class Route:
    """The true trajectory: ``stamps`` (N,) seconds from 0, ``poses`` (N, 3) x y theta in map."""

    stamps: np.ndarray
    poses: np.ndarray
    rooms: list[str]  # room sequence visited (targets)
    path: np.ndarray  # (M, 2) the smoothed planned path the controller followed
    params: RouteParams = field(default_factory=RouteParams)

    @property
    def duration(self) -> float:
        return float(self.stamps[-1] - self.stamps[0]) if len(self.stamps) else 0.0

    @property
    def length(self) -> float:
        """Distance travelled, metres."""
        d = np.diff(self.poses[:, :2], axis=0)
        return float(np.hypot(d[:, 0], d[:, 1]).sum())

    def sample(self, stamps: np.ndarray) -> np.ndarray:
        """(len(stamps), 3) poses linearly interpolated at ``stamps`` (theta unwrapped, then wrapped)."""
        t = np.asarray(stamps, dtype=np.float64)
        if len(t) and (t.min() < self.stamps[0] - 1e-9 or t.max() > self.stamps[-1] + 1e-9):
            raise ConfigError("stamps outside the route's time span", where="route.sample")
        return interpolate_poses(self.stamps, self.poses, t)

    def speeds(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear (m/s) and angular (rad/s) speeds between consecutive poses."""
        dt = np.diff(self.stamps)
        d = np.diff(self.poses[:, :2], axis=0)
        v = np.hypot(d[:, 0], d[:, 1]) / dt
        w = np.diff(np.unwrap(self.poses[:, 2])) / dt
        return v, w

    def min_clearance(self, house: House, step: float = 0.02) -> float:
        """Exact smallest distance (metres) from the trajectory (every ``step`` metres) to any
        wall or obstacle."""
        d = np.hypot(*np.diff(self.poses[:, :2], axis=0).T)
        s = np.concatenate(([0.0], np.cumsum(d)))
        keep = np.unique(np.searchsorted(s, np.arange(0.0, s[-1] + step, step)).clip(0, len(s) - 1))
        pts = shapely.points(self.poses[keep, :2])
        solid = shapely.union_all([house.walls, *house.obstacles])
        return float(shapely.distance(pts, solid).min())


class _Planner:
    """Grid graph over the free space with a clearance-weighted cost; Dijkstra queries."""

    def __init__(self, house: House, params: RouteParams) -> None:
        res = params.resolution
        self.frame = RasterFrame.around(house.bounds, res, margin=2 * res)
        free = rasterise_polygons([house.free_space], self.frame)
        # Every wall / obstacle edge blocks the cells it crosses (4-connected lines), so no wall
        # thinner than a cell can be crossed by the 8-connected grid graph.
        if len(house.segments):
            pix = self.frame.to_pixel(house.segments.reshape(-1, 2)) - 0.5
            lines = np.round(pix * 256.0).astype(np.int32).reshape(-1, 2, 2)
            cv2.polylines(free, list(lines), False, 0, thickness=1, lineType=cv2.LINE_4, shift=8)
        # Clearance of each cell centre: distance to the nearest non-free cell (minus half a cell).
        dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res - 0.5 * res
        self.clearance = dist
        ok = dist >= params.clearance
        self.labels = rasterise_plan(house.plan, self.frame, labels=True)
        self.ok = ok
        h, w = ok.shape
        idx = np.full((h, w), -1, np.int64)
        cells = np.flatnonzero(ok.ravel())
        idx.ravel()[cells] = np.arange(len(cells))
        self.cells = cells
        self.index = idx
        # Cell cost: 1 + (c0 / clearance)^2 keeps paths centred in doorways and corridors.
        cost = 1.0 + (0.3 / np.maximum(dist, res)) ** 2
        rows, cols, wts = [], [], []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            r0, r1 = 0, h - dr
            c0, c1 = max(0, -dc), w - max(0, dc)
            a = idx[r0:r1, c0:c1]
            b = idx[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
            ca = cost[r0:r1, c0:c1]
            cb = cost[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
            m = (a >= 0) & (b >= 0)
            step = res * math.hypot(dr, dc)
            wt = step * 0.5 * (ca[m] + cb[m])
            rows += [a[m], b[m]]
            cols += [b[m], a[m]]
            wts += [wt, wt]
        n = len(cells)
        self.graph = sparse.csr_matrix(
            (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
        )
        self.n_comp, self.comp = sparse.csgraph.connected_components(self.graph, directed=False)

    def node_xy(self, nodes: np.ndarray) -> np.ndarray:
        r, c = np.divmod(self.cells[nodes], self.frame.width)
        return self.frame.to_world(np.column_stack((c + 0.5, r + 0.5)))

    def room_nodes(self, room_index: int) -> np.ndarray:
        """Graph nodes inside the room (1-based label index)."""
        lab = self.labels.ravel()[self.cells]
        return np.flatnonzero(lab == room_index)

    def shortest(self, src: int) -> tuple[np.ndarray, np.ndarray]:
        return dijkstra(self.graph, directed=True, indices=src, return_predecessors=True)


def _pick_target(planner: _Planner, nodes: np.ndarray, rng: np.random.Generator) -> int:
    """A node among the 30 % of the room's nodes with the most clearance."""
    clr = planner.clearance.ravel()[planner.cells[nodes]]
    cut = np.quantile(clr, 0.7)
    good = nodes[clr >= cut]
    return int(good[rng.integers(len(good))])


def _walk(pred: np.ndarray, src: int, dst: int) -> list[int]:
    path = [dst]
    while path[-1] != src:
        p = int(pred[path[-1]])
        if p < 0:
            raise ConfigError("no path between route targets", where="route")
        path.append(p)
    return path[::-1]


def plan_route(
    house: House,
    rng: np.random.Generator,
    rooms: list[str] | None = None,
    length: float = 0.0,
    start_room: str | None = None,
    params: RouteParams | None = None,
) -> Route:
    """Plan and drive a route (see the module docstring). ``rooms`` fixes the room sequence;
    otherwise every room reachable from ``start_room`` (random when ``None``) is visited, then
    random rooms until the route is at least ``length`` metres."""
    params = params or RouteParams()
    if not (isinstance(length, int | float) and math.isfinite(length) and 0.0 <= length <= 1e5):
        raise ConfigError(f"must be in [0, 1e5] metres, got {length!r}", where="route.length")
    planner = _Planner(house, params)
    ids = house.plan.room_ids
    room_nodes = {rid: planner.room_nodes(i + 1) for i, rid in enumerate(ids)}
    usable = [rid for rid in ids if len(room_nodes[rid])]
    if not usable:
        raise ConfigError(
            f"no room has space for a robot with clearance {params.clearance} m", where="route.clearance"
        )
    if rooms is not None:
        bad = [r for r in rooms if r not in room_nodes]
        if bad:
            raise ConfigError(f"unknown room ids {bad} (the house has {ids})", where="route.rooms")
        tight = [r for r in rooms if not len(room_nodes[r])]
        if tight:
            raise ConfigError(f"rooms {tight} have no space for the robot", where="route.rooms")
        if len(rooms) < 1:
            raise ConfigError("give at least one room", where="route.rooms")
        start_room = rooms[0]
    if start_room is None:
        # Prefer a start in the largest connected part of the free space.
        sizes = np.bincount(planner.comp)
        best = [r for r in usable if sizes[planner.comp[room_nodes[r]]].max() == sizes.max()]
        start_room = best[int(rng.integers(len(best)))]
    elif start_room not in room_nodes or not len(room_nodes[start_room]):
        raise ConfigError(f"unknown or too small start room {start_room!r}", where="route.start_room")

    current = _pick_target(planner, room_nodes[start_room], rng)
    comp = planner.comp[current]
    reachable = [r for r in usable if (planner.comp[room_nodes[r]] == comp).any()]
    if rooms is not None:
        unreachable = [r for r in rooms if r not in reachable]
        if unreachable:
            raise ConfigError(
                f"rooms {unreachable} cannot be reached from {start_room!r}", where="route.rooms"
            )
    seq = [start_room]
    cells_path: list[int] = [current]
    planned = 0.0
    goal = length * 1.03
    todo = list(rooms[1:]) if rooms is not None else [r for r in reachable if r != start_room]
    recent: list[str] = [start_room]
    stalled = replans = 0
    while True:
        while True:
            dist, pred = planner.shortest(current)
            if rooms is not None:
                if not todo:
                    break
                nxt = todo.pop(0)
            elif todo:
                # nearest unvisited rooms first, with some randomness
                d_room = np.array([dist[room_nodes[r]].min() for r in todo])
                order = np.argsort(d_room)
                nxt = todo.pop(int(order[min(int(rng.integers(2)), len(order) - 1)]))
            elif planned < goal and stalled < 20:
                choices = (
                    [r for r in reachable if r not in recent[-2:]]
                    or [r for r in reachable if r != seq[-1]]
                    or [seq[-1]]  # a single reachable room: wander inside it
                )
                nxt = choices[int(rng.integers(len(choices)))]
            else:
                break
            nodes = room_nodes[nxt][planner.comp[room_nodes[nxt]] == comp]
            target = _pick_target(planner, nodes, rng)
            leg = _walk(pred, current, target)
            leg_xy = _smooth(planner.node_xy(np.asarray(leg)), params.smoothing, spacing=0.02)
            step = float(np.hypot(*np.diff(leg_xy, axis=0).T).sum())
            stalled = stalled + 1 if step < 0.1 else 0
            planned += step
            cells_path += leg[1:]
            current = target
            seq.append(nxt)
            recent.append(nxt)
        xy = planner.node_xy(np.asarray(cells_path))
        path = _smooth(xy, params.smoothing, spacing=0.02)
        poses = _drive(path, params)
        driven = float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum())
        replans += 1
        if rooms is not None or driven >= length or stalled >= 20 or replans >= 5:
            break
        goal = planned + 1.2 * (length - driven) + 1.0  # the driver cut corners: plan a little more
    stamps = np.arange(len(poses)) * params.dt
    return Route(stamps=stamps, poses=poses, rooms=seq, path=path, params=params)


def _resample(xy: np.ndarray, spacing: float) -> np.ndarray:
    d = np.hypot(*np.diff(xy, axis=0).T)
    keep = np.concatenate(([True], d > 1e-9))
    xy = xy[keep]
    if len(xy) < 2:
        return xy
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    q = np.linspace(0.0, s[-1], max(2, int(math.ceil(s[-1] / spacing)) + 1))
    return np.column_stack((np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])))


def _smooth(xy: np.ndarray, window: float, spacing: float) -> np.ndarray:
    """Resample at ``spacing`` and apply a moving average of ``window`` metres (ends fixed)."""
    p = _resample(xy, spacing)
    k = int(round(window / spacing))
    if k < 2 or len(p) <= 2 * k:
        return p
    pad = np.vstack((np.repeat(p[:1], k, axis=0), p, np.repeat(p[-1:], k, axis=0)))
    kernel = np.ones(2 * k + 1) / (2 * k + 1)
    out = np.column_stack([np.convolve(pad[:, i], kernel, mode="valid") for i in range(2)])
    return _resample(out, spacing)


def _drive(path: np.ndarray, prm: RouteParams) -> np.ndarray:
    """Pure-pursuit unicycle along ``path`` (spacing about 2 cm); returns poses every ``dt``."""
    n = len(path)
    px, py = path[:, 0].tolist(), path[:, 1].tolist()
    if n >= 2:
        th = math.atan2(py[min(n - 1, 10)] - py[0], px[min(n - 1, 10)] - px[0])
    else:
        th = 0.0
    x, y = px[0], py[0]
    v = w = 0.0
    dt = prm.dt
    spacing = 0.02
    look = max(1, int(round(prm.lookahead / spacing)))
    i = 0
    out = [(x, y, th)]
    max_steps = int(10 * (n * spacing / prm.max_speed + 60.0) / dt)
    for _ in range(max_steps):
        # progress: nearest path point ahead within a small window
        j_end = min(n, i + 8)  # the robot advances at most one 2 cm point per step
        best, bi = float("inf"), i
        for j in range(i, j_end):
            d2 = (px[j] - x) ** 2 + (py[j] - y) ** 2
            if d2 < best:
                best, bi = d2, j
        i = bi
        if i >= n - 1 and best < 0.02**2:
            break
        t = min(n - 1, i + look)
        # never aim at (or next to) the robot itself, e.g. past a U-turn of the path
        near2 = (0.5 * prm.lookahead) ** 2
        while t < n - 1 and (px[t] - x) ** 2 + (py[t] - y) ** 2 < near2:
            t += 1
        i = max(i, t - look)
        err = math.atan2(py[t] - y, px[t] - x) - th
        err = wrap_atan2(err)
        if abs(err) > 2.8 and w != 0.0:
            # target (almost) straight behind: keep turning the way we already turn, or the sign
            # of the error flips every step and the acceleration limit freezes the robot
            err = math.copysign(abs(err), w)
        remaining = (n - 1 - i) * spacing + math.sqrt(best)
        w_cmd = max(-prm.max_turn_rate, min(prm.max_turn_rate, 2.5 * err))
        if abs(err) > 0.6:
            v_cmd = 0.0  # turn in place
        else:
            v_cmd = prm.max_speed * math.cos(err) ** 2 * (1.0 - abs(err) / 0.6)
            v_cmd = max(v_cmd, 0.0)
            # stop smoothly at the end of the path
            v_cmd = min(v_cmd, math.sqrt(2.0 * prm.max_accel * max(remaining - 0.01, 0.0)) + 0.02)
        v += max(-prm.max_accel * dt, min(prm.max_accel * dt, v_cmd - v))
        w += max(-prm.max_angular_accel * dt, min(prm.max_angular_accel * dt, w_cmd - w))
        w = max(-prm.max_turn_rate, min(prm.max_turn_rate, w))
        # exact unicycle step (arc)
        if abs(w) > 1e-9:
            x += v / w * (math.sin(th + w * dt) - math.sin(th))
            y -= v / w * (math.cos(th + w * dt) - math.cos(th))
        else:
            x += v * dt * math.cos(th)
            y += v * dt * math.sin(th)
        th = wrap_atan2(th + w * dt)
        out.append((x, y, th))
    return np.asarray(out)
