"""Room-segmentation image + map_server YAML -> :class:`FloorPlan` in metres (map frame).

The image has one grey value per room (``1..max_id``, e.g. the PRBonn ``*RoomSeg.png``: room ids
1..12, 0 wall, 205 unknown, 255 free space outside rooms). Its YAML (``resolution`` m/px,
``origin`` [x, y, yaw] of the lower-left corner of the bottom-left pixel, as ROS map_server) puts
it in the map frame: image row 0 is the *top* row (highest y). One room per label: its largest
4-connected part, as a polygon with exact pixel edges simplified by ``simplify`` pixels (holes
kept), so its area matches the label's pixel count × resolution². Where two rooms' regions touch
(a doorway between them), the shared boundary becomes a :class:`Door` linking them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan._raster_polygons import labels_to_polygons, largest_polygon
from frslam_graph.floorplan.model import Door, FloorPlan, Room, normalise_room_type
from frslam_graph.image_files import image_size, read_image
from frslam_graph.limits import short_repr
from frslam_graph.textfile import read_yaml


def read_label_image(png: str | Path) -> np.ndarray:
    """Read a label image as a 2-D integer array (grey PNG/PGM; RGB only when all channels agree)."""
    src = str(png)
    img = read_image(png, FloorPlanError, "a room-segmentation image with one grey value per room")
    if img.ndim == 3:
        chans = img.shape[2]
        if chans == 4:
            img = img[:, :, :3]
        if not (np.array_equal(img[:, :, 0], img[:, :, 1]) and np.array_equal(img[:, :, 1], img[:, :, 2])):
            raise FloorPlanError(
                "colour image whose channels differ; expected grey values that are room ids", source=src
            )
        img = img[:, :, 0]
    if img.dtype.kind not in "ui":
        raise FloorPlanError(f"expected an integer image, got {img.dtype}", source=src)
    return np.ascontiguousarray(img)


def read_map_yaml(yaml_path: str | Path) -> tuple[float, tuple[float, float, float], Path | None]:
    """(resolution, origin (x, y, yaw), image path or None) from a map_server YAML.

    The map image itself is not needed to place a segmentation, so a missing one is not an
    error here (the caller checks the shape when it exists)."""
    path = Path(yaml_path)
    src = str(path)
    meta = read_yaml(path, FloorPlanError, "a map_server YAML with resolution and origin")
    if not isinstance(meta, dict):
        raise FloorPlanError("expected a YAML mapping with resolution and origin", source=src)
    if "resolution" not in meta:
        raise FloorPlanError("missing required field", source=src, where="resolution")
    res = meta["resolution"]
    if isinstance(res, bool) or not isinstance(res, int | float) or not math.isfinite(res) or res <= 0:
        raise FloorPlanError(
            f"expected a positive number (metres per pixel), got {short_repr(res)}",
            source=src,
            where="resolution",
        )
    if "origin" not in meta:
        raise FloorPlanError("missing required field", source=src, where="origin")
    origin = meta["origin"]
    if (
        not isinstance(origin, list | tuple)
        or len(origin) not in (2, 3)
        or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in origin
        )
    ):
        raise FloorPlanError(
            f"expected [x, y, yaw] numbers, got {short_repr(origin)}", source=src, where="origin"
        )
    yaw = float(origin[2]) if len(origin) == 3 else 0.0
    image = meta.get("image")
    img_path = None
    if image is not None:
        if not isinstance(image, str) or not image:
            raise FloorPlanError(
                f"expected an image file name, got {short_repr(image)}", source=src, where="image"
            )
        img_path = Path(image) if Path(image).is_absolute() else path.parent / image
    return float(res), (float(origin[0]), float(origin[1]), yaw), img_path


def from_room_segmentation(
    png: str | Path,
    yaml: str | Path,
    max_id: int = 204,
    min_pixels: int = 4,
    simplify: float = 1.0,
    room_type: str = "unknown",
    min_door_width: float = 0.3,
    fill_holes_below: float = 0.0,
    name: str | None = None,
) -> FloorPlan:
    """Rooms (metres, map frame) of a room-segmentation image with its map_server YAML.

    Values ``1..max_id`` are room ids (others: walls, unknown, free outside rooms); labels with
    fewer than ``min_pixels`` pixels are ignored. Room ids are ``room_<value>``, types
    ``room_type``. ``simplify``: Douglas-Peucker tolerance in pixels. Doors: shared boundaries
    of two rooms at least ``min_door_width`` metres long. Holes (furniture, noise inside a
    room) smaller than ``fill_holes_below`` m² are filled (default: none, so areas match the
    pixel counts).
    """
    src = str(png)
    res, (ox, oy, yaw), map_image = read_map_yaml(yaml)
    labels = read_label_image(png)
    h, w = labels.shape
    if map_image is not None and map_image.is_file():
        size = image_size(map_image)  # (width, height) from the header, or None
        if size is not None and size != (w, h):
            raise FloorPlanError(
                f"segmentation is {w}x{h} px but the map image {map_image.name} of {yaml} is {size[0]}x{size[1]} px",
                source=src,
            )
    lab = labels.astype(np.int64)
    lab[(lab < 1) | (lab > max_id)] = 0
    counts = np.bincount(lab.ravel())
    ids = np.flatnonzero(counts >= min_pixels)
    ids = ids[ids > 0]
    if len(ids) == 0:
        raise FloorPlanError(
            f"no room labels (grey values 1..{max_id} with >= {min_pixels} pixels)", source=src
        )
    # image (u right, v down, pixel edges) -> map: rotate by yaw about the origin
    c, s = math.cos(yaw), math.sin(yaw)
    # p = (u*res, (h - v)*res); world = R p + o
    params = [c * res, s * res, s * res, -c * res, ox - s * h * res, oy + c * h * res]
    rooms, doors = rooms_from_labels(
        lab, ids, params, simplify, room_type, min_door_width, fill_holes_below / (res * res), src
    )
    return FloorPlan(
        rooms=rooms,
        doors=doors,
        walls=None,
        units="m",
        metres_per_unit=1.0,
        name=name if name is not None else Path(png).stem,
        source=src,
    )


def rooms_from_labels(
    lab: np.ndarray,
    ids: np.ndarray,
    params: list[float],
    simplify: float = 1.0,
    room_type: str = "unknown",
    min_door_width: float = 0.0,
    fill_holes_below: float = 0.0,
    source: str | None = None,
    id_format: str = "room_{}",
) -> tuple[list[Room], list[Door]]:
    """Rooms and doors of a label image (int, 0 = no room) in the plan frame.

    ``params``: shapely affine [a, b, d, e, xoff, yoff] from image coordinates (x = column,
    y = row, pixel edges) to the plan frame. One room per label in ``ids`` (its largest
    4-connected part), id ``id_format.format(label)``; ``simplify`` (Douglas-Peucker) and
    ``fill_holes_below`` (area) in pixels; ``min_door_width`` in plan units: a door wherever
    two rooms share that much boundary.
    """
    from frslam_graph import limits

    if len(ids) > limits.MAX_PLAN_ROOMS:  # each label costs a pass over the image
        raise FloorPlanError(
            f"{len(ids):,} room labels, over the limit of {limits.MAX_PLAN_ROOMS:,} rooms "
            "(MAX_PLAN_ROOMS, frslam_graph.limits)",
            source=source,
        )
    # keep the largest 4-connected part of each label, so every room is one simple polygon
    keep = np.zeros_like(lab)
    for v in ids.tolist():
        n, comp, stats, _ = cv2.connectedComponentsWithStats((lab == v).astype(np.uint8), connectivity=4)
        big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        keep[comp == big] = v
    exact = labels_to_polygons(keep, ids=ids)
    rooms: list[Room] = []
    exact_world: dict[str, Polygon] = {}
    rtype = normalise_room_type(room_type)
    for v in ids.tolist():
        poly = largest_polygon(exact.get(v))
        if poly is None:
            continue
        simple = poly.simplify(simplify, preserve_topology=True) if simplify > 0 else poly
        simple = largest_polygon(simple if simple.is_valid else shapely.make_valid(simple))
        if simple is None:
            continue
        if fill_holes_below > 0 and simple.interiors:
            keep_holes = [h for h in simple.interiors if Polygon(h).area >= fill_holes_below]
            simple = Polygon(simple.exterior, keep_holes)
        rid = id_format.format(v)
        rooms.append(
            Room(
                rid, rtype, shapely.geometry.polygon.orient(shapely.affinity.affine_transform(simple, params))
            )
        )
        exact_world[rid] = shapely.affinity.affine_transform(poly, params)
    if not rooms:
        raise FloorPlanError("no room polygon could be built", source=source)
    return rooms, _doors(exact_world, min_door_width)


def _doors(polys: dict[str, Polygon], min_width: float) -> list[Door]:
    """A door per connected stretch of boundary shared by two rooms (at least ``min_width`` long)."""
    ids = list(polys)
    geoms = [polys[i] for i in ids]
    tree = shapely.STRtree(geoms)
    left, right = tree.query(geoms, predicate="touches")
    doors: list[Door] = []
    for i, j in zip(left.tolist(), right.tolist(), strict=True):
        if i >= j:
            continue
        shared = shapely.line_merge(shapely.intersection(geoms[i].boundary, geoms[j].boundary))
        parts = getattr(shared, "geoms", [shared])
        for part in parts:
            if not isinstance(part, LineString) or part.length < min_width:
                continue
            coords = np.asarray(part.coords)
            a, b = coords[0], coords[-1]
            if np.allclose(a, b):  # a closed loop: span its two farthest points
                d = np.linalg.norm(coords[:, None] - coords[None], axis=-1)
                k, m = np.unravel_index(np.argmax(d), d.shape)
                a, b = coords[k], coords[m]
            doors.append(
                Door(
                    f"d{len(doors)}", (float(a[0]), float(a[1])), (float(b[0]), float(b[1])), (ids[i], ids[j])
                )
            )
    return doors


def yaml_beside(png: str | Path) -> tuple[Path | None, list[Path]]:
    """(the map YAML beside a segmentation image or None, the names looked for): ``<stem>.yaml``
    or, for ``XRoomSeg.png``, ``X.yaml``."""
    png = Path(png)
    stem = png.stem
    cands = [png.with_suffix(".yaml")]
    if stem.lower().endswith("roomseg"):
        cands.append(png.with_name(stem[: -len("roomseg")] + ".yaml"))
    found = [c for c in cands if c.exists()]
    return (found[0] if found else None), cands


def load_room_segmentation(png: str | Path, yaml: str | Path | None = None, **options: Any) -> FloorPlan:
    """Like :func:`from_room_segmentation`; without ``yaml`` the YAML beside the image is used:
    ``<stem>.yaml`` or, for ``XRoomSeg.png``, ``X.yaml``."""
    png = Path(png)
    if yaml is None:
        yaml, cands = yaml_beside(png)
        if yaml is None:
            raise FloorPlanError(
                f"no map YAML beside the image (looked for {', '.join(c.name for c in cands)})",
                source=str(png),
            )
    return from_room_segmentation(png, yaml, **options)
