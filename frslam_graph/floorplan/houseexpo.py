"""HouseExpo JSON (Li et al., 2019) -> :class:`FloorPlan` in metres.

A HouseExpo house is ``{"id", "room_num", "bbox": {"min": [x, y], "max": [x, y]}, "verts":
[[x, y], ...] (outer contour of the house, metres), "room_category": {"bedroom": [[x1, y1, x2,
y2], ...], ...}}``. Rooms are the category boxes clipped to the house contour; overlapping boxes
are made disjoint (smaller boxes first: a closet box inside a bedroom box stays the closet, the
bedroom keeps the rest). Types are normalised; the contour edges become the plan's walls; there
are no doors. Coordinates are kept as in the file (x, y in metres); ``units = "m"``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Polygon, box
from shapely.validation import explain_validity

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan._raster_polygons import largest_polygon
from frslam_graph.floorplan.model import MAX_ABS_COORD, FloorPlan, Room, normalise_room_type
from frslam_graph.textfile import read_json

# HouseExpo (SUNCG) room names that the generic synonyms do not cover
_HOUSEEXPO_TYPES = {
    "indoor": "unknown",
    "guest_room": "bedroom",
    "child_room": "bedroom",
    "lobby": "entrance",
    "entryway": "entrance",
    "garage": "storage",
    "boiler_room": "storage",
    "loggia": "balcony",
}


def _not_number(value: Any, depth: int = 3) -> bool:
    """True when a (nested, up to ``depth`` levels) list holds a bool or a string (which numpy
    would take as 1 / 0 or parse)."""
    if isinstance(value, bool | str):
        return True
    if isinstance(value, list | tuple) and depth > 0:
        return any(_not_number(v, depth - 1) for v in value)
    return False


def _numbers(value: Any, n: int | None, src: str | None, where: str) -> np.ndarray:
    if _not_number(value):
        raise FloorPlanError("expected numbers (not true / false, not strings)", source=src, where=where)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FloorPlanError("expected numbers", source=src, where=where) from None
    if n is not None and arr.shape != (n,):
        raise FloorPlanError(f"expected {n} numbers, got {np.shape(value)}", source=src, where=where)
    if not np.all(np.isfinite(arr)):
        raise FloorPlanError("values must be finite (found NaN or inf)", source=src, where=where)
    if arr.size and np.abs(arr).max() > MAX_ABS_COORD:
        raise FloorPlanError(f"absurd coordinate {np.abs(arr).max():.3g}", source=src, where=where)
    return arr


def _read(
    path_or_dict: str | Path | Mapping[str, Any], source: str | Path | None
) -> tuple[Mapping[str, Any], str | None]:
    if isinstance(path_or_dict, Mapping):
        return path_or_dict, (str(source) if source is not None else None)
    path = Path(path_or_dict)
    src = str(source) if source is not None else str(path)
    data = read_json(path, FloorPlanError, "HouseExpo JSON")
    if not isinstance(data, Mapping):
        raise FloorPlanError(f"expected a JSON object, got {type(data).__name__}", source=src)
    return data, src


def houseexpo_type(name: str) -> str:
    """Normalised room type of a HouseExpo category name."""
    key = str(name).strip().lower().replace(" ", "_").replace("-", "_")
    return _HOUSEEXPO_TYPES.get(key) or normalise_room_type(name)


def load_houseexpo(
    path_or_dict: str | Path | Mapping[str, Any],
    source: str | Path | None = None,
    disjoint: bool = True,
    min_area: float = 0.05,
) -> FloorPlan:
    """Load a HouseExpo house (file path or already parsed dict) as a FloorPlan in metres.

    ``disjoint``: make overlapping room boxes disjoint (smaller first). Room pieces smaller than
    ``min_area`` m² are dropped. A house without room boxes is one ``unknown`` room.
    """
    data, src = _read(path_or_dict, source)
    if "verts" not in data:
        raise FloorPlanError(
            "missing required field (outer contour [[x, y], ...])", source=src, where="verts"
        )
    verts = _numbers(data["verts"], None, src, "verts")
    if verts.ndim != 2 or verts.shape[1] != 2 or len(verts) < 3:
        raise FloorPlanError(
            f"expected at least 3 [x, y] points, got shape {verts.shape}", source=src, where="verts"
        )
    from frslam_graph import limits

    if len(verts) > limits.MAX_PLAN_WALLS:  # each contour edge becomes a wall
        raise FloorPlanError(
            f"{len(verts):,} contour points, over the limit of {limits.MAX_PLAN_WALLS:,} walls "
            "(MAX_PLAN_WALLS, frslam_graph.limits)",
            source=src,
            where="verts",
        )
    house = Polygon(verts)
    why = "" if house.is_valid else explain_validity(house)
    if house.convex_hull.area <= 0:  # all points on a line
        raise FloorPlanError("the house contour encloses no area", source=src, where="verts")
    if why:  # repairing it silently dropped part of the house (and its rooms)
        raise FloorPlanError(f"the house contour is not a simple polygon ({why})", source=src, where="verts")
    cats = data.get("room_category", {}) or {}
    if not isinstance(cats, Mapping):
        raise FloorPlanError(
            "expected an object {type: [[x1, y1, x2, y2], ...]}", source=src, where="room_category"
        )
    boxes: list[tuple[str, Polygon, str]] = []
    for name, entries in cats.items():
        where = f"room_category.{name}"
        arr = _numbers(entries, None, src, where)
        if arr.ndim == 1 and arr.shape == (4,):
            arr = arr[None]
        if arr.ndim != 2 or arr.shape[1] != 4:
            raise FloorPlanError(
                f"expected a list of [x1, y1, x2, y2] boxes, got shape {arr.shape}", source=src, where=where
            )
        for k, (x1, y1, x2, y2) in enumerate(arr.tolist()):
            b = box(min(x1, x2), min(y1, y2), max(x1, x2), max(y1, y2))
            if b.area > 0:
                boxes.append((houseexpo_type(name), b, f"{where}[{k}]"))
    if disjoint:
        boxes.sort(key=lambda t: t[1].area)
    rooms: list[Room] = []
    taken: Polygon | None = None
    for rtype, b, where in boxes:
        poly = b.intersection(house)
        if poly.area <= 0:  # dropped silently before: a room lost without a word
            raise FloorPlanError(
                f"room box {[round(v, 3) for v in b.bounds]} lies outside the house contour (verts)",
                source=src,
                where=where,
            )
        if disjoint and taken is not None:
            poly = poly.difference(taken)
        piece = largest_polygon(poly)
        if piece is None or piece.area < min_area:
            continue
        piece = shapely.geometry.polygon.orient(piece.simplify(0.0), 1.0)
        if not piece.is_valid:
            continue
        rooms.append(Room(f"r{len(rooms)}", rtype, piece))
        taken = piece if taken is None else taken.union(piece)
    if not rooms:
        rooms = [Room("r0", "unknown", shapely.geometry.polygon.orient(house, 1.0))]
    ring = np.asarray(house.exterior.coords)
    walls = np.concatenate([ring[:-1], ring[1:]], axis=1)
    name = data.get("id", "")
    return FloorPlan(
        rooms=rooms,
        doors=[],
        walls=walls,
        units="m",
        metres_per_unit=1.0,
        name=str(name) if name else (Path(src).stem if src else ""),
        source=src,
    )
