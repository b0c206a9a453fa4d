"""A partial LiDAR occupancy map of a connected set of explored rooms (registration experiments).

Frame: the grid's ``map`` frame is the house's metric frame (metres), so the ground-truth
registration of the plan onto the map is ``house.distortion.matrix``. Cells follow
nav_msgs/OccupancyGrid (row 0 = lowest y; -1 unknown, 0 free, 100 occupied).

Rooms are grown from a start room through open doors until the explored share of the rooms'
total area is as close as possible to ``completeness`` (:func:`explored_fraction` gives the exact
share). The map is what a LiDAR sees from inside those rooms: their free space is free, the wall
and obstacle faces bordering it are occupied (one cell thick), everything else is unknown (a
doorway to an unexplored room is a frontier). ``noise=True`` adds a little realism: wall cells
thickened or missing here and there, a few spurious occupied cells, a few unknown holes.

The house is rasterised once per resolution and cached on the house, so a map costs a few
milliseconds.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import shapely
from frslam_graph.datasets.simulator.house import House
from scipy import ndimage

from frslam_graph.errors import ConfigError
from frslam_graph.occupancy import OccupancyGrid
from frslam_graph.raster import RasterFrame, rasterise_plan, rasterise_polygons

_KERNEL = np.ones((3, 3), np.uint8)


class _HouseRaster:
    """Per-house, per-resolution rasters: room labels of the free space, free and solid masks."""

    def __init__(self, house: House, resolution: float) -> None:
        self.frame = RasterFrame.around(house.bounds, resolution, margin=3 * resolution)
        self.free = rasterise_polygons([house.free_space], self.frame).astype(bool)
        solid = rasterise_polygons([house.walls, *house.obstacles], self.frame).astype(bool)
        # Faces one cell thick: every non-free cell next to free space that is not outside.
        self.solid = solid | ~self.free
        labels = rasterise_plan(house.plan, self.frame, labels=True)
        # Free cells outside every room polygon (doorways across gaps) take the nearest room.
        missing = self.free & (labels == 0)
        if missing.any() and (labels > 0).any():
            _, (ri, ci) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
            labels = np.where(missing, labels[ri, ci], labels)
        self.labels = np.where(self.free, labels, 0).astype(np.int32)


def _raster(house: House, resolution: float) -> _HouseRaster:
    key = ("partial_map_raster", float(resolution))
    if key not in house._cache:
        house._cache[key] = _HouseRaster(house, resolution)
    return house._cache[key]


def explored_fraction(house: House, rooms: list[str]) -> float:
    """Share of the house's total room area covered by ``rooms`` (0..1)."""
    areas = house.room_areas
    return float(sum(areas[r] for r in set(rooms)) / sum(areas.values()))


def random_start_room(house: House, completeness: float, rng: np.random.Generator) -> str:
    """A room (random, weighted by area) of a part of the house (rooms connected by open doors)
    big enough for ``completeness`` of its area, or of the biggest part when none is."""
    areas = house.room_areas
    total = sum(areas.values())
    ids = list(areas)
    comp_area: dict[str, float] = {}
    for rid in ids:
        if rid not in comp_area:
            members = house.reachable(rid)
            share = sum(areas[m] for m in members)
            comp_area.update(dict.fromkeys(members, share))
    enough = [r for r in ids if comp_area[r] >= completeness * total * 0.999]
    pool = enough or [r for r in ids if comp_area[r] == max(comp_area.values())]
    p = np.array([areas[r] for r in pool])
    return pool[int(rng.choice(len(pool), p=p / p.sum()))]


def grow_rooms(
    house: House, completeness: float, rng: np.random.Generator, start_room: str | None = None
) -> list[str]:
    """A connected (through open doors) set of rooms whose area share is closest to
    ``completeness``, grown from ``start_room`` (random, weighted by area, when ``None``)."""
    areas = house.room_areas
    total = sum(areas.values())
    ids = list(areas)
    adj = house.adjacency()
    if start_room is None:
        start_room = random_start_room(house, completeness, rng)
    elif start_room not in areas:
        raise ConfigError(
            f"unknown room {start_room!r} (the house has {ids})", where="partial_map.start_room"
        )
    target = completeness * total
    explored = [start_room]
    area = areas[start_room]
    while True:
        frontier = sorted({nb for r in explored for nb in adj[r]} - set(explored))
        if not frontier:
            break
        order = rng.permutation(len(frontier))
        added = False
        for k in order:
            cand = frontier[int(k)]
            if abs(area + areas[cand] - target) < abs(area - target):
                explored.append(cand)
                area += areas[cand]
                added = True
                break
        if not added:
            break
    return explored


def partial_map(
    house: House,
    completeness: float,
    rng: np.random.Generator,
    resolution: float = 0.05,
    start_room: str | None = None,
    noise: bool = True,
    crop: bool = True,
    see_through_doors: bool = False,
) -> tuple[OccupancyGrid, list[str]]:
    """(grid, explored room ids): see the module docstring. ``crop`` trims the grid to its known
    cells (plus a margin); the origin keeps it in the house frame either way.
    ``see_through_doors`` also marks free what a 360° scan taken 0.8 m inside each explored room
    in front of an open door to an unexplored room sees of that room (the explored fraction
    still counts explored rooms only)."""
    if not (isinstance(completeness, int | float) and 0.0 < completeness <= 1.0):
        raise ConfigError(f"must be in (0, 1], got {completeness!r}", where="partial_map.completeness")
    if not (isinstance(resolution, int | float) and math.isfinite(resolution) and 0.005 <= resolution <= 1.0):
        raise ConfigError(f"must be in [0.005, 1] metres, got {resolution!r}", where="partial_map.resolution")
    rooms = grow_rooms(house, completeness, rng, start_room)
    hr = _raster(house, resolution)
    index = {r.id: i + 1 for i, r in enumerate(house.plan.rooms)}
    lut = np.zeros(len(index) + 1, bool)
    lut[[index[r] for r in rooms]] = True
    free = lut[hr.labels]
    if see_through_doors:
        free |= _seen_through_doors(house, rooms, hr, index)
    near = cv2.dilate(free.view(np.uint8), _KERNEL).astype(bool)
    occ = near & hr.solid & ~free
    if noise:
        occ, free = _add_noise(occ, free, hr.solid, rng)
    data = np.full(free.shape, -1, np.int8)
    data[free] = 0
    data[occ] = 100
    x0, y0 = hr.frame.origin
    grid = OccupancyGrid(data, resolution, (x0, y0, 0.0))
    if crop:
        grid = grid.crop_to_known(margin_cells=3)
    return grid, rooms


def _seen_through_doors(
    house: House, rooms: list[str], hr: _HouseRaster, index: dict[str, int]
) -> np.ndarray:
    """Free cells of unexplored rooms visible through open doors from just inside explored rooms."""
    from frslam_graph.datasets.simulator.lidar import RayCaster

    if "caster" not in house._cache:
        house._cache["caster"] = RayCaster(house.segments, method="sweep")
    caster = house._cache["caster"]
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    seen = np.zeros(hr.labels.shape, bool)
    explored = set(rooms)
    opened = set(house.open_doors)
    views, targets = [], []
    for d in house.plan.doors:
        if d.id not in opened or len(set(d.rooms)) != 2:
            continue
        a, b = d.rooms
        if (a in explored) == (b in explored):
            continue
        inside, outside = (a, b) if a in explored else (b, a)
        mid = np.asarray(d.midpoint)
        u = np.asarray(d.b) - np.asarray(d.a)
        n = np.array([-u[1], u[0]]) / max(float(np.hypot(*u)), 1e-12)
        region = house.room_free[inside]
        for off in (0.8, -0.8, 0.4, -0.4):
            p = mid + off * n
            if region.contains(shapely.Point(p)):
                views.append(p)
                targets.append(index[outside])
                break
    if not views:
        return seen
    poses = np.column_stack((np.asarray(views), np.zeros(len(views))))
    ranges = np.minimum(caster.cast(poses, angles, 30.0), 30.0)
    for p, r, lab in zip(poses, ranges, targets, strict=True):
        ends = p[:2] + r[:, None] * np.column_stack((np.cos(angles), np.sin(angles)))
        poly = shapely.Polygon(ends).buffer(0)
        seen |= rasterise_polygons([poly], hr.frame).astype(bool) & (hr.labels == lab)
    return seen


def _add_noise(
    occ: np.ndarray, free: np.ndarray, solid: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Jitter wall faces (thicken 20 %, drop 2 %), add spurious hits and small unknown holes."""
    h, w = occ.shape
    thick = cv2.dilate(occ.view(np.uint8), _KERNEL).astype(bool) & solid & ~free
    occ = occ | (thick & (rng.random((h, w)) < 0.2))
    occ = occ & ~(rng.random((h, w)) < 0.02)
    n_free = int(free.sum())
    if n_free:
        fr, fc = np.nonzero(free)
        k = rng.poisson(max(1.0, n_free * 5e-4))
        pick = rng.integers(0, n_free, size=k)
        occ = occ.copy()
        occ[fr[pick], fc[pick]] = True
        holes = rng.integers(0, n_free, size=rng.poisson(max(1.0, n_free * 5e-4)))
        free = free.copy()
        free[fr[holes], fc[holes]] = False
        free &= ~occ
    return occ, free
