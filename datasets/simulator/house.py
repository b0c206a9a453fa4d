"""The true house in metres built from a floor plan and a distortion.

Frame: the house's metric frame is the simulated robot's ``map`` frame (metres, REP-103). The
plan's rooms are mapped by ``distortion.matrix`` (``house.plan``). Geometry (shapely):

- free space = every room eroded by ``wall_thickness / 2`` (so two rooms sharing a boundary get a
  wall of ``wall_thickness`` between them), plus a rectangular opening through the wall at each
  **open** door (a door joining two distinct rooms that is not in ``closed_doors``; doors to the
  outside are closed), minus obstacles;
- walls = the rooms' union grown by ``wall_thickness / 2``, minus the rooms' free space and the
  open doorways (outer walls, inner walls, closed doors, unlabelled pockets between rooms);
- obstacles = ``clutter`` furniture boxes placed inside rooms, clear of walls and doors;
- ``segments`` (K, 4) = every edge of the walls' and obstacles' boundaries, for ray casting.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import shapely.affinity
from frslam_graph.datasets.simulator.distortion import Distortion
from shapely.geometry import MultiPolygon, Polygon, box, mapping, shape

from frslam_graph.errors import ConfigError, FloorPlanError
from frslam_graph.floorplan import FloorPlan
from frslam_graph.floorplan.openings import open_boundaries

FORMAT_NAME = "frslam-sim-house"
FORMAT_VERSION = 1


def polygon_segments(geom: Any) -> np.ndarray:
    """(K, 4) edges ``x1 y1 x2 y2`` of every ring of a (Multi)Polygon / collection."""
    geoms = shapely.get_parts(np.asarray([geom], dtype=object)) if geom is not None else []
    out = []
    for g in geoms:
        if g.is_empty or not isinstance(g, Polygon):
            continue
        for ring in (g.exterior, *g.interiors):
            c = np.asarray(ring.coords)[:, :2]
            if len(c) >= 2:
                out.append(np.hstack((c[:-1], c[1:])))
    if not out:
        return np.zeros((0, 4))
    seg = np.vstack(out)
    keep = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) > 1e-9
    return seg[keep]


def _polygons(geom: Any) -> list[Polygon]:
    if geom is None or geom.is_empty:
        return []
    return [g for g in shapely.get_parts(np.asarray([geom], dtype=object)) if isinstance(g, Polygon)]


def _polygonal(geom: Any) -> Polygon | MultiPolygon:
    """The polygonal part of a geometry as a Polygon or MultiPolygon (empty Polygon if none)."""
    parts = [p for p in _polygons(geom) if p.area > 0.0]
    if not parts:
        return Polygon()
    return parts[0] if len(parts) == 1 else MultiPolygon(parts)


def _erode(geom: Any, d: float) -> Polygon | MultiPolygon:
    """Inward offset by ``d``: mitre joins (square corners) for polygons without holes, bevel
    joins for polygons with holes (GEOS' negative mitre buffer can drop rings of those)."""
    parts = []
    for p in _polygons(geom):
        style = "bevel" if len(p.interiors) else "mitre"
        parts.append(p.buffer(-d, join_style=style, mitre_limit=3.0))
    return _polygonal(shapely.union_all(parts)) if parts else Polygon()


def _drop_slivers(walls: Any, e: float) -> Polygon | MultiPolygon:
    """Walls without slivers thinner than ``2 e`` (left where a doorway grazes a wall, or where
    rooms overlap): the pieces a morphological opening by ``e`` removes, except the tiny corner
    chamfers the opening also cuts (perimeter < 6 e), so wall corners stay square.

    Bevel joins: GEOS' negative mitre buffer loses whole rings of polygons with holes.
    """
    walls = _polygonal(walls)
    if walls.is_empty:
        return walls
    opened = walls.buffer(-e, join_style="bevel").buffer(e, join_style="bevel")
    residue = walls.difference(opened)
    slivers = [g for g in _polygons(residue) if g.length > 6.0 * e]
    if slivers:
        walls = walls.difference(shapely.union_all(slivers))
    return _polygonal(shapely.union_all([p for p in _polygons(walls) if p.area > 1e-6]))


def _door_opening(a: np.ndarray, b: np.ndarray, depth: float) -> Polygon:
    """Rectangle spanning the door segment a–b, ``depth`` across the wall (centred)."""
    u = b - a
    n = np.array([-u[1], u[0]]) / max(np.hypot(*u), 1e-12) * (depth / 2.0)
    return Polygon([a - n, b - n, b + n, a + n])


@dataclass
class House:
    """The true house (metres). Build with :meth:`from_plan`; see the module docstring."""

    plan: FloorPlan  # rooms/doors in metres (house frame)
    distortion: Distortion
    wall_thickness: float
    open_doors: tuple[str, ...]
    closed_doors: tuple[str, ...]
    walls: Polygon | MultiPolygon
    obstacles: list[Polygon]
    free_space: Polygon | MultiPolygon
    room_free: dict[str, Any]  # room id -> its free space (eroded room, with obstacles removed)
    segments: np.ndarray  # (K, 4) wall and obstacle edges, metres
    # room pairs whose shared boundary has no wall in the plan (open plan): no wall built there
    open_boundaries: tuple[tuple[str, str], ...] = ()
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_plan(
        cls,
        plan: FloorPlan,
        distortion: Distortion,
        wall_thickness: float = 0.12,
        closed_doors: Iterable[str] = (),
        clutter: int = 0,
        rng: np.random.Generator | None = None,
        min_opening: float = 0.5,
    ) -> House:
        """The true house for ``plan`` under ``distortion`` (see the module docstring)."""
        if not (isinstance(wall_thickness, int | float) and 0.0 < wall_thickness <= 1.0):
            raise ConfigError(
                f"must be in (0, 1] metres, got {wall_thickness!r}", where="house.wall_thickness"
            )
        if not isinstance(clutter, int | np.integer) or clutter < 0:
            raise ConfigError(f"must be an integer >= 0, got {clutter!r}", where="house.clutter")
        closed = tuple(str(c) for c in closed_doors)
        door_ids = {d.id for d in plan.doors}
        unknown = sorted(set(closed) - door_ids)
        if unknown:
            raise ConfigError(
                f"unknown door ids {unknown} (the plan has {sorted(door_ids)})", where="house.closed_doors"
            )
        hplan = plan.transformed(distortion.matrix, units="m")
        if any(len(set(d.rooms)) < 2 for d in hplan.doors):
            linked = hplan.link_doors(tol=max(0.3, 2.0 * wall_thickness))
            # Keep the plan's own links where it has them.
            doors = [
                d if len(set(d.rooms)) == 2 else ld for d, ld in zip(hplan.doors, linked.doors, strict=True)
            ]
            hplan = replace(hplan, doors=doors)
        half = wall_thickness / 2.0
        rooms_union = shapely.union_all([r.polygon for r in hplan.rooms])
        envelope = rooms_union.buffer(half, join_style="mitre", mitre_limit=3.0)
        eroded = {r.id: _erode(r.polygon, half) for r in hplan.rooms}
        openings, open_ids = [], []
        for d in hplan.doors:
            if d.id in closed or len(set(d.rooms)) < 2 or d.width <= 1e-9:
                continue
            a, b = np.asarray(d.a, float), np.asarray(d.b, float)
            seg = shapely.LineString([d.a, d.b])
            reach = max(hplan.room(rid).polygon.distance(seg) for rid in d.rooms)
            depth = wall_thickness + 0.5 + 2.0 * reach
            # Cut only the wall between the door's two rooms (never an outer wall).
            near = reach + half + 0.05
            ra, rb = (hplan.room(rid).polygon for rid in d.rooms[:2])
            opening = _door_opening(a, b, depth).intersection(envelope)
            opening = opening.intersection(ra.buffer(near)).intersection(rb.buffer(near))
            if opening.is_empty:
                continue
            openings.append(opening)
            open_ids.append(d.id)
        bare_openings, open_bounds = open_boundaries(hplan, wall_thickness, min_opening)
        openings += [o.intersection(envelope) for o in bare_openings]
        # The outer wall (half a wall either side of the house's outline) is never cut: exterior
        # doors are closed, and a misplaced door or open boundary along the outline leaks rays.
        # The outline closes gaps up to 1 m between rooms (plans from maps have thick walls).
        outline = _erode(rooms_union.buffer(0.5, join_style="mitre", mitre_limit=3.0), 0.5)
        outer = outline.buffer(half, join_style="mitre", mitre_limit=3.0).difference(_erode(outline, half))
        openings = [o.difference(outer) for o in openings]
        rooms_free = shapely.union_all(list(eroded.values()))
        open_space = shapely.union_all([rooms_free, *openings])
        walls = envelope.difference(open_space)
        walls = _drop_slivers(walls, wall_thickness / 4.0)
        rng = rng if rng is not None else np.random.default_rng(0)
        obstacles = _place_clutter(hplan, eroded, clutter, rng) if clutter else []
        free = envelope.difference(walls)
        free = free.difference(shapely.union_all(obstacles)) if obstacles else free
        # Keep polygons only (set operations may leave stray lines / points in a collection).
        free = _polygonal(free)
        room_free = {}
        for r in hplan.rooms:
            g = eroded[r.id]
            room_free[r.id] = _polygonal(g.difference(shapely.union_all(obstacles)) if obstacles else g)
        walls_s = walls.simplify(1e-6)
        segments = np.vstack([polygon_segments(walls_s), *[polygon_segments(o) for o in obstacles]])
        if len(segments) == 0:
            raise FloorPlanError("the plan gives a house without walls", source=plan.source, where="rooms")
        return cls(
            plan=hplan,
            distortion=distortion,
            wall_thickness=float(wall_thickness),
            open_doors=tuple(open_ids),
            closed_doors=tuple(d.id for d in hplan.doors if d.id not in open_ids),
            open_boundaries=tuple(open_bounds),
            walls=walls_s,
            obstacles=obstacles,
            free_space=free,
            room_free=room_free,
            segments=segments,
        )

    # ------------------------------------------------------------------ derived
    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(minx, miny, maxx, maxy) of the walls, metres."""
        return tuple(float(v) for v in self.walls.bounds)  # type: ignore[return-value]

    @property
    def room_areas(self) -> dict[str, float]:
        """Room areas in m² (full room polygons, as the completeness of a map is measured)."""
        return {r.id: float(r.polygon.area) for r in self.plan.rooms}

    def adjacency(self) -> dict[str, set[str]]:
        """Rooms connected through open doors."""
        adj: dict[str, set[str]] = {r.id: set() for r in self.plan.rooms}
        opened = set(self.open_doors)
        for d in self.plan.doors:
            if d.id in opened and len(set(d.rooms)) == 2:
                a, b = d.rooms
                adj[a].add(b)
                adj[b].add(a)
        for a, b in self.open_boundaries:
            adj[a].add(b)
            adj[b].add(a)
        return adj

    def reachable(self, start: str) -> list[str]:
        """Room ids reachable from ``start`` through open doors (breadth first, start included)."""
        adj = self.adjacency()
        seen, order = {start}, [start]
        i = 0
        while i < len(order):
            for nb in sorted(adj[order[i]]):
                if nb not in seen:
                    seen.add(nb)
                    order.append(nb)
            i += 1
        return order

    def room_at(self, xy: np.ndarray) -> list[str | None]:
        """Room id containing each (N, 2) point (``None`` outside every room)."""
        pts = shapely.points(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        out: list[str | None] = [None] * len(pts)
        for r in self.plan.rooms:
            inside = shapely.contains(r.polygon, pts)
            for i in np.flatnonzero(inside):
                if out[i] is None:
                    out[i] = r.id
        return out

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "units": "m",
            "frame": "map",
            "distortion": self.distortion.to_dict(),
            "wall_thickness": self.wall_thickness,
            "open_doors": list(self.open_doors),
            "closed_doors": list(self.closed_doors),
            "open_boundaries": [list(p) for p in self.open_boundaries],
            "plan": self.plan.to_dict(),
            "walls": mapping(self.walls),
            "obstacles": [mapping(o) for o in self.obstacles],
            "free_space": mapping(self.free_space),
            "room_free": {k: mapping(v) for k, v in self.room_free.items()},
            "segments": self.segments.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str | Path | None = None) -> House:
        if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
            raise FloorPlanError(f"not a simulated house (expected format {FORMAT_NAME!r})", source, "format")
        try:
            return cls(
                plan=FloorPlan.from_dict(data["plan"], source=source),
                distortion=Distortion.from_dict(data["distortion"]),
                wall_thickness=float(data["wall_thickness"]),
                open_doors=tuple(data["open_doors"]),
                closed_doors=tuple(data["closed_doors"]),
                walls=shape(data["walls"]),
                obstacles=[shape(o) for o in data["obstacles"]],
                free_space=shape(data["free_space"]),
                room_free={k: shape(v) for k, v in data["room_free"].items()},
                segments=np.asarray(data["segments"], dtype=np.float64).reshape(-1, 4),
                open_boundaries=tuple((str(a), str(b)) for a, b in data.get("open_boundaries", [])),
            )
        except KeyError as exc:
            raise FloorPlanError("missing field", source, str(exc.args[0])) from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise FloorPlanError(f"malformed house ({exc})", source) from None

    def save(self, path: str | Path) -> Path:
        """Write the house as JSON, atomically."""
        from frslam_graph.atomic import write_text

        return write_text(path, json.dumps(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> House:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise FloorPlanError(f"cannot read house JSON ({exc})", path) from None
        return cls.from_dict(data, source=path)


def _place_clutter(
    plan: FloorPlan, eroded: dict[str, Any], count: int, rng: np.random.Generator
) -> list[Polygon]:
    """Up to ``count`` furniture boxes (0.3–1.2 m sides, any yaw) inside rooms, each at least
    0.6 m from walls and other boxes and 1.0 m from every door, so rooms stay connected."""
    gap, door_clear = 0.6, 1.0
    doors = shapely.union_all([shapely.LineString([d.a, d.b]) for d in plan.doors]) if plan.doors else None
    areas = np.array([max(g.area, 0.0) for g in eroded.values()])
    ids = list(eroded)
    if areas.sum() <= 0:
        return []
    placed: list[Polygon] = []
    inner = {rid: g.buffer(-gap) for rid, g in eroded.items()}
    attempts = 0
    while len(placed) < count and attempts < 50 * count:
        attempts += 1
        rid = ids[int(rng.choice(len(ids), p=areas / areas.sum()))]
        region = inner[rid]
        if region.is_empty:
            continue
        minx, miny, maxx, maxy = region.bounds
        w, h = rng.uniform(0.3, 1.2, size=2)
        cx, cy = rng.uniform(minx, maxx), rng.uniform(miny, maxy)
        yaw = float(rng.uniform(0.0, math.pi))
        b = shapely.affinity.rotate(
            box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), yaw, use_radians=True
        )
        if not region.contains(b):
            continue
        if doors is not None and b.distance(doors) < door_clear:
            continue
        if any(b.distance(o) < gap for o in placed):
            continue
        placed.append(b)
    return placed
