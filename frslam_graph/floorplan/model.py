"""Floor-plan model: rooms (typed polygons), doors (opening segments) and optional walls.

Coordinates are *plan units* (``FloorPlan.units``: "px" for raster-derived plans, "m" once a
plan is registered to a map). Plans are right-handed with y up (REP-103); loaders of y-down
sources (R2V pixels) flip y. ``metres_per_unit`` is known only for some sources (room
segmentations of a metric map); an internet plan has ``None``, the scale being what registration
estimates.

Our JSON format (``format: frslam-floorplan``, ``version: 1``)::

    {"format": "frslam-floorplan", "version": 1, "name": "...", "units": "px",
     "metres_per_unit": null,
     "rooms": [{"id": "r0", "type": "bedroom", "polygon": [[x, y], ...], "holes": [[[x, y], ...]]}],
     "doors": [{"id": "d0", "segment": [[x, y], [x, y]], "rooms": ["r0", "r1"]}],
     "walls": [[x1, y1, x2, y2], ...]}

This module knows no other file format: the readers (:mod:`frslam_graph.floorplan.io` and the
modules it dispatches to) build FloorPlans from files, and ``FloorPlan.load`` calls them through
``FloorPlan.reader``, which the package installs on import.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon
from shapely.validation import explain_validity

from frslam_graph.errors import FloorPlanError
from frslam_graph.limits import short_repr

FORMAT_NAME = "frslam-floorplan"
FORMAT_VERSION = 1
MAX_ABS_COORD = 1e7  # beyond this a coordinate is absurd in any unit we support (px, mm, m)

ROOM_TYPES = (
    "living_room",
    "bedroom",
    "kitchen",
    "dining_room",
    "bathroom",
    "restroom",
    "washing_room",
    "corridor",
    "closet",
    "balcony",
    "office",
    "storage",
    "entrance",
    "stairs",
    "unknown",
)

_TYPE_SYNONYMS = {
    "livingroom": "living_room",
    "living": "living_room",
    "lounge": "living_room",
    "ldk": "living_room",
    "livingdiningkitchen": "living_room",
    "bed": "bedroom",
    "bedroom": "bedroom",
    "masterbedroom": "bedroom",
    "room": "bedroom",
    "kitchen": "kitchen",
    "dk": "kitchen",
    "dining": "dining_room",
    "diningroom": "dining_room",
    "bath": "bathroom",
    "bathroom": "bathroom",
    "shower": "bathroom",
    "restroom": "restroom",
    "toilet": "restroom",
    "wc": "restroom",
    "lavatory": "restroom",
    "washingroom": "washing_room",
    "laundry": "washing_room",
    "laundryroom": "washing_room",
    "utility": "washing_room",
    "corridor": "corridor",
    "hall": "corridor",
    "hallway": "corridor",
    "passage": "corridor",
    "closet": "closet",
    "wardrobe": "closet",
    "walkincloset": "closet",
    "balcony": "balcony",
    "terrace": "balcony",
    "veranda": "balcony",
    "office": "office",
    "study": "office",
    "storage": "storage",
    "store": "storage",
    "storeroom": "storage",
    "entrance": "entrance",
    "entry": "entrance",
    "foyer": "entrance",
    "stairs": "stairs",
    "staircase": "stairs",
    "unknown": "unknown",
    "other": "unknown",
    "": "unknown",
}


def normalise_room_type(label: str) -> str:
    """Map a free-form room label ("Living Room", "toilet", "WC") to one of :data:`ROOM_TYPES`.

    Unrecognised labels become ``"unknown"``.
    """
    key = "".join(ch for ch in str(label).lower() if ch.isalnum())
    if key in _TYPE_SYNONYMS:
        return _TYPE_SYNONYMS[key]
    canonical = str(label).strip().lower().replace(" ", "_").replace("-", "_")
    return canonical if canonical in ROOM_TYPES else "unknown"


@dataclass(frozen=True)
class Room:
    """A room: id, normalised type and a simple polygon (plan units)."""

    id: str
    type: str
    polygon: Polygon

    @property
    def area(self) -> float:
        return float(self.polygon.area)

    @property
    def centroid(self) -> tuple[float, float]:
        c = self.polygon.centroid
        return (float(c.x), float(c.y))


@dataclass(frozen=True)
class Door:
    """A door: the opening segment ``a``–``b`` in a wall, and the ids of the rooms it connects."""

    id: str
    a: tuple[float, float]
    b: tuple[float, float]
    rooms: tuple[str, ...] = ()

    @property
    def midpoint(self) -> tuple[float, float]:
        return ((self.a[0] + self.b[0]) / 2.0, (self.a[1] + self.b[1]) / 2.0)

    @property
    def width(self) -> float:
        return math.hypot(self.b[0] - self.a[0], self.b[1] - self.a[1])


def _fail(msg: str, source: str | None, where: str | None = None) -> FloorPlanError:
    return FloorPlanError(msg, source=source, where=where)


def _is_number(value: Any) -> bool:
    """A JSON number: int or float, not bool (``true`` is not 1), not a string."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def _as_points(value: Any, source: str | None, where: str, min_points: int) -> np.ndarray:
    """Validate a list of [x, y] pairs: numeric (JSON numbers: not ``true``, not ``"1.5"``),
    finite, not absurd."""
    if isinstance(value, list | tuple):
        for i, pair in enumerate(value):
            if not (isinstance(pair, list | tuple) and len(pair) == 2 and all(map(_is_number, pair))):
                raise _fail(f"expected [x, y] number pairs, got {short_repr(pair)}", source, f"{where}[{i}]")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail("expected a list of [x, y] number pairs", source, where) from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise _fail(f"expected a list of [x, y] pairs, got an array of shape {arr.shape}", source, where)
    if len(arr) < min_points:
        raise _fail(f"expected at least {min_points} points, got {len(arr)}", source, where)
    if not np.all(np.isfinite(arr)):
        raise _fail("coordinates must be finite numbers (found NaN or inf)", source, where)
    big = np.abs(arr).max()
    if big > MAX_ABS_COORD:
        raise _fail(f"absurd coordinate {big:.3g} (|x|, |y| must be <= {MAX_ABS_COORD:.0e})", source, where)
    return arr


def make_polygon(
    exterior: Any, holes: Sequence[Any] = (), source: str | None = None, where: str = "polygon"
) -> Polygon:
    """Build and validate a simple polygon (at least 3 distinct corners, no self-intersection)."""
    ext = _as_points(exterior, source, where, 3)
    hole_arrs = [_as_points(h, source, f"{where}.holes[{i}]", 3) for i, h in enumerate(holes)]
    poly = Polygon(ext, hole_arrs)
    if not poly.is_valid:
        raise _fail(
            f"invalid polygon ({explain_validity(poly)}); rooms must be simple polygons", source, where
        )
    if poly.area <= 0.0:
        raise _fail("polygon has zero area", source, where)
    return poly


def _polygon_to_json(poly: Polygon) -> tuple[list[list[float]], list[list[list[float]]]]:
    ext = np.asarray(poly.exterior.coords)[:-1].tolist()
    holes = [np.asarray(h.coords)[:-1].tolist() for h in poly.interiors]
    return ext, holes


@dataclass(frozen=True)
class FloorPlan:
    """A floor plan: rooms, doors, optional walls (K, 4), units and optional metres per unit."""

    rooms: list[Room]
    doors: list[Door] = field(default_factory=list)
    walls: np.ndarray | None = None
    units: str = "unit"
    metres_per_unit: float | None = None
    name: str = ""
    source: str | None = None

    def __post_init__(self) -> None:
        src = self.source
        if not self.rooms:
            raise _fail("a floor plan needs at least one room (found none)", src, "rooms")
        _check_room_count(len(self.rooms), src)
        seen: set[str] = set()
        for i, room in enumerate(self.rooms):
            where = f"rooms[{i}]"
            if not isinstance(room, Room):
                raise _fail(f"expected a Room, got {type(room).__name__}", src, where)
            if not room.id:
                raise _fail("room id must be a non-empty string", src, f"{where}.id")
            if room.id in seen:
                raise _fail(f"duplicate room id {short_repr(room.id)}", src, f"{where}.id")
            seen.add(room.id)
            poly = room.polygon
            if not isinstance(poly, Polygon) or poly.is_empty:
                raise _fail("polygon must be a non-empty shapely Polygon", src, f"{where}.polygon")
            _as_points(np.asarray(poly.exterior.coords), src, f"{where}.polygon", 4)
            if not poly.is_valid:
                raise _fail(f"invalid polygon ({explain_validity(poly)})", src, f"{where}.polygon")
        for i, door in enumerate(self.doors):
            _as_points([door.a, door.b], src, f"doors[{i}].segment", 2)
            for rid in door.rooms:
                if rid not in seen:
                    raise _fail(f"door refers to unknown room {short_repr(rid)}", src, f"doors[{i}].rooms")
        if self.walls is not None:
            walls = np.asarray(self.walls, dtype=np.float64)
            if walls.ndim != 2 or walls.shape[1] != 4:
                raise _fail(
                    f"walls must be a (K, 4) array of x1 y1 x2 y2, got shape {walls.shape}", src, "walls"
                )
            from frslam_graph import limits

            if len(walls) > limits.MAX_PLAN_WALLS:  # every later step loops over the walls
                raise _fail(
                    f"{len(walls):,} walls, over the limit of {limits.MAX_PLAN_WALLS:,} "
                    "(MAX_PLAN_WALLS, frslam_graph.limits)",
                    src,
                    "walls",
                )
            if len(walls):
                _as_points(walls.reshape(-1, 2), src, "walls", 0)
            object.__setattr__(self, "walls", walls)
        if self.metres_per_unit is not None and not (
            math.isfinite(self.metres_per_unit) and self.metres_per_unit > 0
        ):
            raise _fail(f"must be a positive number, got {self.metres_per_unit}", src, "metres_per_unit")

    # ------------------------------------------------------------------ access
    @property
    def room_ids(self) -> list[str]:
        return [r.id for r in self.rooms]

    def room(self, room_id: str) -> Room:
        for r in self.rooms:
            if r.id == room_id:
                return r
        raise KeyError(f"no room {room_id!r} in plan {self.name or self.source or ''}".strip())

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(minx, miny, maxx, maxy) of all rooms, plan units."""
        b = np.array([r.polygon.bounds for r in self.rooms])
        return (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))

    @property
    def area(self) -> float:
        """Total room area (plan units²)."""
        return float(sum(r.area for r in self.rooms))

    def footprint(self) -> Polygon:
        """Union of all rooms (may be a MultiPolygon for disconnected plans)."""
        return shapely.union_all([r.polygon for r in self.rooms])

    # ------------------------------------------------------------------ derived plans
    def subset(self, ids: Iterable[str]) -> FloorPlan:
        """The plan restricted to the given rooms (doors kept when they touch a kept room)."""
        keep = set(ids)
        unknown = keep - set(self.room_ids)
        if unknown:
            raise KeyError(f"unknown room ids {sorted(unknown)}")
        rooms = [r for r in self.rooms if r.id in keep]
        doors = [
            replace(d, rooms=tuple(x for x in d.rooms if x in keep))
            for d in self.doors
            if not d.rooms or any(x in keep for x in d.rooms)
        ]
        return replace(self, rooms=rooms, doors=doors)

    def transformed(self, matrix: np.ndarray, units: str | None = None) -> FloorPlan:
        """Apply a 3×3 homogeneous affine (plan coords -> new coords) to rooms, doors and walls.

        A reflection (negative determinant) keeps polygons valid (shapely re-orients nothing, but
        validity does not depend on orientation). ``metres_per_unit`` becomes 1 when ``units="m"``.
        """
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError("matrix must be a finite 3x3 array")
        params = [m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[0, 2], m[1, 2]]
        rooms = [replace(r, polygon=shapely.affinity.affine_transform(r.polygon, params)) for r in self.rooms]

        def tp(p: tuple[float, float]) -> tuple[float, float]:
            q = m[:2, :2] @ np.asarray(p) + m[:2, 2]
            return (float(q[0]), float(q[1]))

        doors = [replace(d, a=tp(d.a), b=tp(d.b)) for d in self.doors]
        walls = None
        if self.walls is not None:
            w = self.walls.reshape(-1, 2) @ m[:2, :2].T + m[:2, 2]
            walls = w.reshape(-1, 4)
        new_units = units or self.units
        mpu = 1.0 if new_units == "m" else None
        return replace(self, rooms=rooms, doors=doors, walls=walls, units=new_units, metres_per_unit=mpu)

    def link_doors(self, tol: float) -> FloorPlan:
        """A copy whose doors list the rooms within ``tol`` (plan units) of their segment."""
        geoms = [r.polygon for r in self.rooms]
        tree = shapely.STRtree(geoms)
        doors = []
        for d in self.doors:
            seg = LineString([d.a, d.b])
            idx = tree.query(seg, predicate="dwithin", distance=tol)
            # the two closest rooms, by distance to the door midpoint
            mid = shapely.Point(d.midpoint)
            near = sorted(idx.tolist(), key=lambda i: geoms[i].distance(mid))[:2]
            doors.append(replace(d, rooms=tuple(self.rooms[i].id for i in near)))
        return replace(self, doors=doors)

    def adjacency(self) -> dict[str, set[str]]:
        """Rooms connected through doors: ``{room_id: {neighbour ids}}`` (every room is a key)."""
        adj: dict[str, set[str]] = {r.id: set() for r in self.rooms}
        for d in self.doors:
            if len(d.rooms) == 2 and d.rooms[0] != d.rooms[1]:
                a, b = d.rooms
                adj[a].add(b)
                adj[b].add(a)
        return adj

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        rooms = []
        for r in self.rooms:
            ext, holes = _polygon_to_json(r.polygon)
            entry: dict[str, Any] = {"id": r.id, "type": r.type, "polygon": ext}
            if holes:
                entry["holes"] = holes
            rooms.append(entry)
        out: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": self.name,
            "units": self.units,
            "metres_per_unit": self.metres_per_unit,
            "rooms": rooms,
            "doors": [
                {"id": d.id, "segment": [list(d.a), list(d.b)], "rooms": list(d.rooms)} for d in self.doors
            ],
        }
        if self.walls is not None:
            out["walls"] = self.walls.tolist()
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str | Path | None = None) -> FloorPlan:
        """Build a plan from our JSON structure, validating every field."""
        src = str(source) if source is not None else None
        if not isinstance(data, Mapping):
            raise _fail(f"expected a JSON object at the top level, got {type(data).__name__}", src)
        fmt = data.get("format", FORMAT_NAME)
        if fmt != FORMAT_NAME:
            raise _fail(f"unknown format {short_repr(fmt)} (expected {FORMAT_NAME!r})", src, "format")
        version = data.get("version", FORMAT_VERSION)
        if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
            raise _fail(
                f"unsupported version {short_repr(version)} (this library reads 1..{FORMAT_VERSION})",
                src,
                "version",
            )
        if "rooms" not in data:
            raise _fail("missing required field", src, "rooms")
        raw_rooms = data["rooms"]
        if not isinstance(raw_rooms, list):
            raise _fail("expected a list of rooms", src, "rooms")
        _check_room_count(len(raw_rooms), src)
        rooms = []
        for i, rr in enumerate(raw_rooms):
            where = f"rooms[{i}]"
            if not isinstance(rr, Mapping):
                raise _fail("expected an object with id, type, polygon", src, where)
            for key in ("id", "polygon"):
                if key not in rr:
                    raise _fail("missing required field", src, f"{where}.{key}")
            rid = rr["id"]
            if not isinstance(rid, str | int) or isinstance(rid, bool):
                raise _fail(f"expected a string id, got {short_repr(rid)}", src, f"{where}.id")
            rtype = rr.get("type", "unknown")
            if not isinstance(rtype, str):
                raise _fail(f"expected a string room type, got {short_repr(rtype)}", src, f"{where}.type")
            holes = rr.get("holes", [])
            if not isinstance(holes, list):
                raise _fail("expected a list of polygons", src, f"{where}.holes")
            poly = make_polygon(rr["polygon"], holes, src, f"{where}.polygon")
            rooms.append(Room(str(rid), normalise_room_type(rtype), poly))
        doors = []
        raw_doors = data.get("doors", []) or []
        if not isinstance(raw_doors, list):
            raise _fail("expected a list of doors", src, "doors")
        for i, dd in enumerate(raw_doors):
            where = f"doors[{i}]"
            if not isinstance(dd, Mapping) or "segment" not in dd:
                raise _fail("expected an object with a 'segment' [[x, y], [x, y]]", src, where)
            seg = _as_points(dd["segment"], src, f"{where}.segment", 2)
            if len(seg) != 2:
                raise _fail(f"a door segment has exactly 2 points, got {len(seg)}", src, f"{where}.segment")
            door_rooms = dd.get("rooms", [])
            if not isinstance(door_rooms, list) or len(door_rooms) > 2:
                raise _fail("expected a list of at most 2 room ids", src, f"{where}.rooms")
            doors.append(
                Door(
                    str(dd.get("id", f"d{i}")),
                    (float(seg[0, 0]), float(seg[0, 1])),
                    (float(seg[1, 0]), float(seg[1, 1])),
                    tuple(str(x) for x in door_rooms),
                )
            )
        walls = None
        if data.get("walls") is not None:
            raw_walls = data["walls"]
            if not _is_wall_list(raw_walls):
                raise _fail("expected a list of [x1, y1, x2, y2] segments", src, "walls")
            pairs = [pt for w in raw_walls for pt in (w[:2], w[2:])]
            walls = _as_points(pairs, src, "walls", 0).reshape(-1, 4)
        units = data.get("units", "unit")
        if not isinstance(units, str) or not units:
            raise _fail(f"expected a unit name such as 'px' or 'm', got {short_repr(units)}", src, "units")
        mpu = data.get("metres_per_unit")
        if mpu is not None and (isinstance(mpu, bool) or not isinstance(mpu, int | float)):
            raise _fail(f"expected a positive number or null, got {short_repr(mpu)}", src, "metres_per_unit")
        name = data.get("name", "")
        return cls(
            rooms=rooms,
            doors=doors,
            walls=walls,
            units=units,
            metres_per_unit=None if mpu is None else float(mpu),
            name=str(name) if name else (Path(src).stem if src else ""),
            source=src,
        )

    def save(self, path: str | Path) -> Path:
        """Write our JSON format atomically (creating parent folders)."""
        from frslam_graph.atomic import write_text

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text(path, json.dumps(self.to_dict(), indent=1))
        return path

    # ------------------------------------------------------------------ files (frslam_graph.floorplan.io)
    #: ``load(path, reader=None, **options) -> FloorPlan``: the file readers
    #: (:func:`frslam_graph.floorplan.io.load`), installed when the package ``frslam_graph.floorplan``
    #: is imported; the readers build FloorPlans, so this module does not import them
    reader: ClassVar[Callable[..., FloorPlan] | None] = None

    @classmethod
    def load(cls, path: str | Path, **options: Any) -> FloorPlan:
        """Load a plan, the reader chosen from the file: our ``.json`` (or HouseExpo JSON with
        ``verts``), an R2V vector ``.txt``, a room-segmentation ``.png`` / ``.pgm`` (pixel value =
        room id; with ``yaml=`` the map_server YAML of its map, or one beside it: ``<stem>.yaml``,
        ``X.yaml`` for ``XRoomSeg.png``), or else a drawn plan image (``.png``, ``.jpg``, ``.pgm``:
        :meth:`from_image`, options passed on). See :func:`frslam_graph.floorplan.io.load`."""
        return _reader()(path, **options)

    @classmethod
    def from_image(
        cls, path: str | Path, segmentation: str | Path | None = None, **options: Any
    ) -> FloorPlan:
        """Rooms, doors and walls of a drawn plan image, in pixels (x = column, y = height - row:
        the top row is the highest y, as in map_server maps). ``segmentation``: None (rooms from
        the free space, door gaps up to ``door_width`` px closed), an image path (one colour a
        room) or "auto" (``<stem>_gt_segmentation.png`` beside it). Options and method:
        :mod:`frslam_graph.floorplan.plan_image`."""
        return _reader()(path, reader="image", segmentation=segmentation, **options)

    @classmethod
    def from_room_segmentation(cls, png: str | Path, yaml: str | Path, **options: Any) -> FloorPlan:
        """Rooms from a room-segmentation image (pixel value = room id) and its map_server YAML."""
        return _reader()(png, reader="roomseg", yaml=yaml, **options)


def _reader() -> Callable[..., FloorPlan]:
    if FloorPlan.reader is None:  # the package installs it on import, before any plan exists
        raise FloorPlanError("no floor-plan readers installed (import frslam_graph.floorplan)")
    return FloorPlan.reader


def _check_room_count(n: int, src: str | None) -> None:
    """FloorPlanError when a plan has more than ``limits.MAX_PLAN_ROOMS`` rooms (read at call time)."""
    from frslam_graph import limits

    if n > limits.MAX_PLAN_ROOMS:
        raise _fail(
            f"{n:,} rooms, over the limit of {limits.MAX_PLAN_ROOMS:,} (MAX_PLAN_ROOMS, frslam_graph.limits)",
            src,
            "rooms",
        )


def _is_wall_list(value: Any) -> bool:
    """True when ``value`` looks like [[x1, y1, x2, y2], ...] (rather than a list of points)."""
    return isinstance(value, list) and all(isinstance(w, list | tuple) and len(w) == 4 for w in value)
