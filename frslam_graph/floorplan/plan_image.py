"""Floor plans from images (PNG, JPEG, PGM): rooms, doors and walls in pixels, scale unknown.

Frame: x = column, y = image height - row, in pixels (pixel edges), so the image's top row is
the highest y and a plan image and an :meth:`OccupancyGrid.from_image` map of the same building
differ by a similarity without a flip (registration handles flips anyway). ``units`` "px",
``metres_per_unit`` None.

Pixels of a light colour (rooms filled with a colour, as listing plans draw them) are free;
the rest is read as ROS map_server reads a map (colour averaged, alpha ignored; p = (255 -
v) / 255): p < ``free_thresh`` is free space, p > ``occupied_thresh`` a wall (dark), anything
between (grey outside, hatched or filled areas) is neither. Light-grey fills that map_server's
``free_thresh`` still counts as free (p >= 0.1, lighter than grey 205 but darker than 230, at
least 3 px wide: walls drawn as grey fills between thin outlines, grey 211 on the IPA
``Freiburg52_scan.png``, read as free made rooms of the walls) are neither too; the one-pixel
anti-aliased fringe of dark lines stays free. Then:

1. Furniture: blobs of non-free pixels smaller than ``furniture_size`` on both sides and not
   touching the image border (chairs, dots, small boxes) become free space.
2. Rooms: the free space eroded by a disc of diameter ``door_width`` (so a gap in a wall up to
   that width closes) splits into room cores; the core connected to the image border is the
   outside; cores smaller than (door_width / 2)² are dropped; the cores grow back over the free
   space (geodesic), so neighbouring rooms meet in their door gap. Free regions no core reaches
   are rooms of their own when at least ``min_room_area`` px² and half a door wide. With the
   default (swept) door width, rooms joined through an opening wider than the one door width
   the sweep takes for the whole plan split: (a) at straight gaps in axis-aligned walls up to
   1.5 door widths (:data:`MAX_NECK`), from a wall's tip to the next wall in line (a room open
   on one side, IPA lab_a's cubicles), when the rooms read with those gaps closed split it;
   (b) at a neck: where its free space narrows to at most 1.5 door widths (a double door)
   between two parts each at least twice as wide (:data:`NECK_RATIO`; IPA NLB: 36 px doors
   against a 30 px sweep). With a ``segmentation`` image instead (same size; each room one colour, or
   white regions separated by dark lines as the IPA ``*_gt_segmentation.png``; its light-grey
   fills, walls as in the plan, are no room), its regions are the cores.
3. Doors: where two rooms meet over at least ``door_width / 4`` px.
4. Walls: outlines of the dark pixels, as segments.

Default ``door_width``: the erosion width that splits the free space into the most room cores
(:func:`door_width_sweep`: widths from twice the wall thickness up, 10 % apart; the middle of
those that reach the most). The door gaps of a plan are the narrowest free passages between its
rooms: below their width the rooms stay joined, well above it rooms vanish, and in between
(a plateau) every room is a core of its own. The sweep is in the drawing's own units, so the
same plan drawn at any pixel density gives the same rooms: the former fixed default (max(30 px,
4 × wall thickness); wall strokes of line drawings stay 1-3 px at any density) matched 80 % of
the IPA plans' ground-truth rooms at their 5 cm per pixel but 41 % at half that density and
70-76 % at 1.5-2x; the sweep alone matched 84-86 % at every density from 0.5x to 4x, and with
the splits of step 2 90-92 % from 0.5x to 2x, 86-88 % at 3-4x (``tools/bench_plan_images.py``).
When furniture blobs were removed, the sweep runs again on the space without them (furniture
splits rooms into pockets at narrow widths).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan._raster_polygons import geodesic_split
from frslam_graph.floorplan.model import FloorPlan
from frslam_graph.floorplan.roomseg import rooms_from_labels
from frslam_graph.image_files import grey_levels, read_image
from frslam_graph.occupancy import FREE, OCCUPIED, check_reading, image_to_occupancy

DOOR_SWEEP_STEP = 1.1  # ratio of successive door widths tried by door_width_sweep
MIN_DOOR_SWEEP_PX = 4.0  # px; narrowest door width tried (wall thickness permitting)
SEGMENTATION_SUFFIX = "_gt_segmentation"
FILL_P = 0.1  # light grey below 230: a fill (wall, hatching) when 3 px wide, not a room
_SATURATED = 30  # max - min channel above this: a colour, not a grey
COLOUR_FILL_MIN = 128  # brightest channel of a colour fill at least this (darker colours: walls)
NECK_RATIO = 2.0  # a room splits where its free space narrows below 1/this of both sides' widths
MAX_NECK = 1.5  # necks up to this many door widths (a double door); wider: open plan


@dataclass(frozen=True)
class ImagePlanResult:
    """A plan read from an image and the parameters it was built with (pixels)."""

    plan: FloorPlan
    door_width: float
    wall_thickness: float
    furniture_removed: int
    segmentation: Path | None


def load_image_plan(path: str | Path, **options) -> FloorPlan:
    """The :class:`FloorPlan` of a plan image (see :func:`load_image_plan_detailed`)."""
    return load_image_plan_detailed(path, **options).plan


def load_image_plan_detailed(
    path: str | Path,
    segmentation: str | Path | None = None,
    door_width: float | None = None,
    furniture_size: float | None = None,
    min_room_area: float | None = None,
    simplify: float = 1.0,
    negate: bool = False,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
    name: str | None = None,
) -> ImagePlanResult:
    """Rooms (polygons, type "unknown"), doors and walls of a plan image, in pixels (module doc).

    ``segmentation``: None (rooms from the free space), a path, or "auto" (``<stem>_gt_segmentation``
    beside the image, also for a ``<stem>_furnitures`` image). ``door_width`` (px; default
    :func:`door_width_sweep`), ``furniture_size`` (px, default 0.6 × door width),
    ``min_room_area`` (px², default door_width²), ``simplify`` (Douglas-Peucker, px).
    """
    path = Path(path)
    src = str(path)
    for field, value in (
        ("door_width", door_width),
        ("furniture_size", furniture_size),
        ("min_room_area", min_room_area),
    ):
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf
        ):
            raise FloorPlanError(f"expected a positive number of pixels, got {value!r}", src, field)
    check_reading(occupied_thresh, free_thresh, "trinary", src, FloorPlanError)
    img = read_image(path, FloorPlanError, "a floor-plan image")
    grey = grey_levels(img)
    if not negate:
        grey[colour_fills(img)] = 255.0  # rooms filled with a light colour are free space
    occ = image_to_occupancy(grey, int(bool(negate)), occupied_thresh, free_thresh, "trinary")
    free, dark = occ == FREE, occ == OCCUPIED
    free &= ~grey_fills(grey, free, negate)
    if not free.any():
        raise FloorPlanError("no free space (light pixels): expected white rooms and dark walls", src)
    thickness = wall_thickness(dark)
    dw = float(door_width) if door_width is not None else door_width_sweep(free, thickness)
    if dw > max(occ.shape):  # the erosion disc would be larger than the image (and its memory)
        raise FloorPlanError(
            f"door width {dw:g} px is wider than the {occ.shape[1]}x{occ.shape[0]} px image",
            src,
            "door_width",
        )
    free, dark, n_furniture = _remove_furniture(free, dark, furniture_size or 0.6 * dw)
    if door_width is None and n_furniture:  # furniture split rooms into pockets: sweep again
        dw = door_width_sweep(free, thickness)
    min_area = float(min_room_area) if min_room_area is not None else dw * dw
    seg_path = _segmentation_path(path, segmentation)
    if seg_path is None:
        labels = _rooms_from_free_space(free, dw, min_area)
        if door_width is None:  # rooms joined through a gap wider than the swept door width
            cuts = _wall_gaps(free, MAX_NECK * dw, thickness)
            if cuts.any():
                labels = _split_rooms(labels, _rooms_from_free_space(free, dw, min_area, cuts), min_area)
            labels = _split_at_necks(labels, free, dw)
    else:
        labels = _rooms_from_segmentation(seg_path, free, min_area)
    ids = np.unique(labels)
    ids = ids[ids > 0]
    if len(ids) == 0:
        raise FloorPlanError(
            "no closed room: all free space is outside (touches the image border) or smaller "
            f"than {min_area:.0f} px²; expected rooms enclosed by walls"
            + (f" (segmentation {seg_path})" if seg_path else ""),
            src,
        )
    h = labels.shape[0]
    rooms, doors = rooms_from_labels(
        labels.astype(np.int64),
        ids,
        [1.0, 0.0, 0.0, -1.0, 0.0, float(h)],
        simplify=simplify,
        min_door_width=dw / 4.0,
        source=src,
        id_format="r{}",
    )
    plan = FloorPlan(
        rooms=rooms,
        doors=doors,
        walls=_wall_segments(dark, max(1.0, thickness / 2.0)),
        units="px",
        metres_per_unit=None,
        name=name if name is not None else path.stem,
        source=src,
    )
    return ImagePlanResult(plan, dw, thickness, n_furniture, seg_path)


def colour_fills(img: np.ndarray) -> np.ndarray:
    """Pixels of a light colour (channels more than :data:`_SATURATED` apart in 8-bit levels,
    the brightest at least :data:`COLOUR_FILL_MIN`): rooms filled with a colour, as listing plans
    draw them (averaged to grey, a pastel fill of 150-230 was neither free nor a wall, and the
    plan had no room). All False for a grey image."""
    if img.ndim != 3 or img.shape[2] < 3:
        return np.zeros(img.shape[:2], bool)
    bgr = _bgr8(img)
    hi = bgr.max(axis=2)
    return (hi - bgr.min(axis=2) > _SATURATED) & (hi >= COLOUR_FILL_MIN)


def _bgr8(img: np.ndarray) -> np.ndarray:
    """An image's first three channels (a grey image's level thrice) in 8-bit levels, int16."""
    bgr = img[:, :, :3] if img.ndim == 3 else np.repeat(img[:, :, None], 3, 2)
    return (bgr // 257 if img.dtype == np.uint16 else bgr).astype(np.int16)


def grey_fills(grey: np.ndarray, free: np.ndarray, negate: bool = False) -> np.ndarray:
    """The light-grey areas of ``free`` (p = (255 - v) / 255 >= :data:`FILL_P`) at least 3 px
    wide: filled walls or hatching, not rooms; the one-pixel anti-aliased fringe of lines is left
    out (a 3x3 opening)."""
    p = grey / 255.0 if negate else (255.0 - grey) / 255.0
    light = (free & (p >= FILL_P)).astype(np.uint8)
    if not light.any():
        return np.zeros_like(free)
    return cv2.morphologyEx(light, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)


def door_width_sweep(free: np.ndarray, wall_thickness: float = 0.0) -> float:
    """The door width (px) that splits ``free`` into the most room cores (module doc): widths
    from max(:data:`MIN_DOOR_SWEEP_PX`, 2 × ``wall_thickness``) up, :data:`DOOR_SWEEP_STEP`
    apart, until the cores are gone; the middle of the widths that reach the most. A core is a
    4-connected component of the free space eroded by the width (at least (width / 2)² px; the
    outside, joined to the image border, not counted). At the narrowest widths the rooms may
    all be joined to the outside through open doors (no core yet). Without any core at any
    width, the narrowest width."""
    lo = max(MIN_DOOR_SWEEP_PX, 2.0 * wall_thickness)
    dt = cv2.distanceTransform(np.pad(free, 2, constant_values=True).astype(np.uint8), cv2.DIST_L2, 5)
    widths, counts = [], []
    width = lo
    while width <= max(free.shape):
        r = int(math.ceil(width / 2.0))
        n, cores = cv2.connectedComponents((dt > r).astype(np.uint8), connectivity=4)
        big = np.bincount(cores.ravel(), minlength=n) >= r * r
        big[0] = False
        big[int(cores[0, 0])] = False  # the outside (the padding ring)
        count = int(big.sum())
        if count == 0 and any(counts):
            break  # past the last core
        widths.append(width)
        counts.append(count)
        width *= DOOR_SWEEP_STEP
    if not any(counts):
        return lo
    best = np.flatnonzero(np.asarray(counts) == max(counts))
    return float(widths[best[len(best) // 2]])


def wall_thickness(dark: np.ndarray) -> float:
    """Median width (px) of the dark strokes: twice the distance transform on their ridge; 0
    without dark pixels."""
    if not dark.any():
        return 0.0
    dt = cv2.distanceTransform(dark.astype(np.uint8), cv2.DIST_L2, 5)
    ridge = (dt > 0) & (dt >= cv2.dilate(dt, np.ones((3, 3), np.uint8)))
    return float(2.0 * np.median(dt[ridge]))


def _remove_furniture(free: np.ndarray, dark: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Non-free blobs (8-connected) under ``size`` px on both sides, not on the border, become free."""
    h, w = free.shape
    n, comp, stats, _ = cv2.connectedComponentsWithStats((~free).astype(np.uint8), connectivity=8)
    left, top = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    inner = (left > 0) & (top > 0) & (left + bw < w) & (top + bh < h)
    small = inner & (bw < size) & (bh < size)
    small[0] = False  # the free space itself
    blob = small[comp]
    return free | blob, dark & ~blob, int(small.sum())


def _rooms_from_free_space(
    free: np.ndarray, door_width: float, min_area: float, cuts: np.ndarray | None = None
) -> np.ndarray:
    """Room labels (uint16, 0 = none): cores of the free space (less ``cuts``) eroded by a
    door-wide disc, grown back over it; the outside (the core at the border) dropped;
    unreached regions added."""
    r = int(math.ceil(door_width / 2.0))
    pad = r + 2
    # pad with free space: free space at the border joins the pad ring, which is the outside
    padded = np.pad(free, pad, constant_values=True).astype(np.uint8)
    eroded = padded if cuts is None else padded & ~np.pad(cuts, pad).astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    n, cores, stats, _ = cv2.connectedComponentsWithStats(cv2.erode(eroded, disc), connectivity=4)
    outside = int(cores[0, 0])
    keep = stats[:, cv2.CC_STAT_AREA] >= r * r
    keep[0] = False
    keep[outside] = True
    lut = np.zeros(n, np.uint16)
    lut[keep] = np.arange(1, int(keep.sum()) + 1)
    grown = geodesic_split(eroded.astype(bool), lut[cores])[pad:-pad, pad:-pad].astype(np.int64)
    grown[grown == lut[outside]] = 0
    # free regions no core reached (closets narrower than a door): rooms when large enough
    space = free if cuts is None else free & ~cuts
    rest = _big_regions(space & (grown == 0), min_area, door_width / 4.0)
    labels = _renumber(np.where(rest > 0, rest + grown.max(), grown))
    if cuts is None:
        return labels
    # the cuts shared by the rooms on their two sides
    return geodesic_split((labels > 0) | (cuts & free), labels.astype(np.uint16)).astype(np.int64)


def _split_rooms(labels: np.ndarray, finer: np.ndarray, min_area: float) -> np.ndarray:
    """``labels`` with each room that two or more rooms of ``finer`` share (each at least
    ``min_area`` px² of it and mostly within it) split as ``finer`` splits it (the rest of the room shared by those
    parts, geodesic); a room ``finer`` does not split keeps its outline. Labels, renumbered."""
    out = labels.astype(np.int64).copy()
    nxt = int(out.max()) + 1
    sizes = np.bincount(finer.ravel())
    for k, box in enumerate(ndimage.find_objects(out), start=1):
        if box is None:
            continue
        room = out[box] == k
        vals, counts = np.unique(finer[box][room], return_counts=True)
        # rooms of finer mostly within this one (not a neighbour whose outline moved)
        parts = vals[(vals > 0) & (counts >= min_area) & (2 * counts >= sizes[vals])]
        if len(parts) < 2:
            continue
        lut = np.zeros(int(finer.max()) + 1, np.uint16)
        lut[parts] = np.arange(1, len(parts) + 1)
        split = geodesic_split(room, np.where(room, lut[finer[box]], 0).astype(np.uint16))
        view = out[box]
        for j in range(2, len(parts) + 1):
            view[split == j] = nxt
            nxt += 1
    return _renumber(out)


def _wall_gaps(free: np.ndarray, length: float, thickness: float) -> np.ndarray:
    """Free pixels closing straight gaps up to ``length`` px in axis-aligned walls (a door, a
    room's open side): a run of free pixels between two non-free ones on one row (column), in
    a strip at most 2 x ``thickness`` + 2 px across and half as wide as long, that starts at the tip of a wall of its
    direction (a wall piece with no piece across it there). Not the space between two parallel
    walls (a wide strip), nor a wall's junction extended across a corridor: the tips are taken
    again with the gaps closed across them (a partition between two doors ends in a junction
    once its doors are closed, and is not extended across the corridor it faces)."""
    wall = ~free
    first = [_gaps_along(free, wall, length, thickness, h) for h in (True, False)]
    along_rows = _gaps_along(free, wall | first[1], length, thickness, True)
    return along_rows | _gaps_along(free, wall | first[0], length, thickness, False)


def _gaps_along(
    free: np.ndarray, wall: np.ndarray, length: float, thickness: float, rows: bool
) -> np.ndarray:
    """The gaps of :func:`_wall_gaps` along rows (``rows``) or columns, their tips in ``wall``."""
    k = 2 * int(round(length / 2.0)) + 1  # odd: a centred kernel
    m = 2 * int(round(1.5 * thickness)) + 1  # a wall piece: at least this long (odd)
    w8 = wall.astype(np.uint8)
    along, across = (
        cv2.morphologyEx(w8, cv2.MORPH_OPEN, np.ones(sh, np.uint8)) > 0 for sh in ((1, m), (m, 1))
    )
    if not rows:
        along, across = across, along
    tips = cv2.dilate((along & ~across).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    line = np.ones((1, k) if rows else (k, 1), np.uint8)
    fill = (cv2.morphologyEx((~free).astype(np.uint8), cv2.MORPH_CLOSE, line) > 0) & free
    n, comp, stats, _ = cv2.connectedComponentsWithStats(fill.astype(np.uint8), connectivity=8)
    run = stats[:, cv2.CC_STAT_WIDTH if rows else cv2.CC_STAT_HEIGHT]
    breadth = stats[:, cv2.CC_STAT_HEIGHT if rows else cv2.CC_STAT_WIDTH]
    keep = (breadth <= 2.0 * thickness + 2.0) & (run >= 2 * breadth)  # a strip, not a block
    at_tip = np.zeros(n, bool)
    at_tip[np.unique(comp[fill & tips])] = True
    keep &= at_tip
    keep[0] = False
    return keep[comp]


def _split_at_necks(labels: np.ndarray, free: np.ndarray, door_width: float) -> np.ndarray:
    """Rooms split where their free space narrows (a neck) to at most 1/:data:`NECK_RATIO` of the
    widest disc on both sides: two rooms joined through a gap wider than the door width (the
    sweep takes one width for the whole plan; a plan's wide openings stay open). Each room is
    eroded at widths from ``door_width`` up (:data:`DOOR_SWEEP_STEP` apart); at the first width
    where two or more of its cores are each at least :data:`NECK_RATIO` times that width wide,
    those cores are grown back over the room (geodesic), and each part is examined again.
    Labels (int, 0 = none), renumbered."""
    dt = cv2.distanceTransform(np.pad(free, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    out = labels.astype(np.int64).copy()
    # (label, its bounding box): a part of a split room lies within the room's box
    todo = [(k + 1, box) for k, box in enumerate(ndimage.find_objects(out)) if box is not None]
    nxt = int(out.max()) + 1
    while todo:
        k, box = todo.pop()
        view = out[box]
        room = view == k
        parts = _neck_split(room, np.where(room, dt[box], 0.0), door_width)
        if parts is None:
            continue
        for j in range(2, int(parts.max()) + 1):
            view[parts == j] = nxt
            todo.append((nxt, box))
            nxt += 1
        todo.append((k, box))
    return _renumber(out)


def _neck_split(room: np.ndarray, dt: np.ndarray, door_width: float) -> np.ndarray | None:
    """Parts (1..K, 0 outside ``room``) of one room split at its narrowest neck (see
    :func:`_split_at_necks`; ``dt``: distance to the nearest non-free pixel, px, 0 outside the
    room), or None without a neck."""
    top = 2.0 * float(dt.max())
    width = door_width
    while NECK_RATIO * width <= top and width <= MAX_NECK * door_width:
        n, cores = cv2.connectedComponents((dt > width / 2.0).astype(np.uint8), connectivity=4)
        if n <= 1:
            return None
        if n > 2:
            wide = 2.0 * np.asarray(ndimage.maximum(dt, cores, np.arange(1, n))) >= NECK_RATIO * width
            if wide.sum() >= 2:
                lut = np.zeros(n, np.uint16)
                lut[1:][wide] = np.arange(1, int(wide.sum()) + 1)
                return geodesic_split(room, lut[cores]).astype(np.int64)
        width *= DOOR_SWEEP_STEP
    return None


def _big_regions(mask: np.ndarray, min_area: float, min_width: float) -> np.ndarray:
    """4-connected regions of ``mask`` not touching the border, at least ``min_area`` px² and
    ``min_width`` px wide (twice the largest distance to their edge); labels (int, 0 = none)."""
    n, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros(mask.shape, np.int64)
    dt = cv2.distanceTransform(np.pad(mask, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    width = 2.0 * np.asarray(ndimage.maximum(dt, comp, np.arange(n)))
    h, w = mask.shape
    left, top = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    inner = (left > 0) & (top > 0)
    inner &= (left + stats[:, cv2.CC_STAT_WIDTH] < w) & (top + stats[:, cv2.CC_STAT_HEIGHT] < h)
    keep = inner & (stats[:, cv2.CC_STAT_AREA] >= min_area) & (width >= min_width)
    keep[0] = False
    lut = np.zeros(n, np.int64)
    lut[keep] = np.arange(1, int(keep.sum()) + 1)
    return lut[comp]


def _renumber(labels: np.ndarray) -> np.ndarray:
    """Labels 1..K in order of first appearance in raster order (deterministic room ids)."""
    flat = labels.ravel()
    vals, first = np.unique(flat, return_index=True)
    order = vals[np.argsort(first)]
    order = order[order > 0]
    lut = np.zeros(int(labels.max()) + 1, np.int64)
    lut[order] = np.arange(1, len(order) + 1)
    return lut[labels]


def _segmentation_path(path: Path, segmentation: str | Path | None) -> Path | None:
    if segmentation is None:
        return None
    if str(segmentation) != "auto":
        return Path(segmentation)
    stems = [path.stem]
    if path.stem.endswith("_furnitures"):
        stems.append(path.stem[: -len("_furnitures")])
    cands = [path.with_name(s + SEGMENTATION_SUFFIX + path.suffix) for s in stems]
    for cand in cands:
        if cand.is_file():
            return cand
    raise FloorPlanError(
        f"no segmentation beside the image (looked for {', '.join(c.name for c in cands)})", str(path)
    )


def _rooms_from_segmentation(seg_path: Path, free: np.ndarray, min_area: float) -> np.ndarray:
    """Room labels from a segmentation image: each region of one colour (white, or a saturated
    colour; greys and dark lines are not rooms) is a room core; the cores grow over the plan's
    free space so rooms meet where the segmentation drew a line across a door."""
    img = read_image(seg_path, FloorPlanError, "a room-segmentation image (one colour a room)")
    if img.shape[:2] != free.shape:
        raise FloorPlanError(
            f"segmentation is {img.shape[1]}x{img.shape[0]} px but the plan image is "
            f"{free.shape[1]}x{free.shape[0]} px",
            str(seg_path),
        )
    bgr = _bgr8(img).astype(np.int64)
    key = (bgr[:, :, 0] << 16) | (bgr[:, :, 1] << 8) | bgr[:, :, 2]
    saturated = (bgr.max(axis=2) - bgr.min(axis=2)) > _SATURATED
    seg_grey = grey_levels(img)
    white = image_to_occupancy(seg_grey, 0, 0.65, 0.196, "trinary") == FREE
    white &= ~grey_fills(seg_grey, white)  # walls drawn as light-grey fills are no room
    key = np.where(saturated, key + 1, np.where(white, 1, 0))  # white regions: one class
    # cut every pixel whose right or lower neighbour has another class: same-class regions
    # become 4-connected components of their own
    cut = np.zeros(key.shape, bool)
    cut[:, :-1] |= key[:, :-1] != key[:, 1:]
    cut[:-1, :] |= key[:-1, :] != key[1:, :]
    cores = _big_regions((key > 0) & ~cut, min_area, 4.0)
    if cores.max() == 0:
        return cores
    grown = geodesic_split(free | (cores > 0), cores.astype(np.uint16))
    return _renumber(grown.astype(np.int64))


def _wall_segments(dark: np.ndarray, tolerance: float = 1.0) -> np.ndarray:
    """Outlines of the dark pixels as (K, 4) segments x1 y1 x2 y2 in the plan frame (px),
    simplified within ``tolerance`` px (half the wall thickness, at least a pixel: a plan
    scanned or exported at a finer density has as many segments as at a coarse one, not the
    staircase of its anti-aliased strokes)."""
    h = dark.shape[0]
    contours, _ = cv2.findContours(dark.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    segs = []
    for c in contours:
        pts = cv2.approxPolyDP(c, tolerance, True).reshape(-1, 2).astype(np.float64)
        if len(pts) < 2:
            continue
        pts = np.column_stack([pts[:, 0] + 0.5, h - pts[:, 1] - 0.5])  # pixel centres, y up
        segs.append(
            np.hstack([pts, np.roll(pts, -1, axis=0)]) if len(pts) > 2 else np.hstack([pts[:1], pts[1:]])
        )
    if not segs:
        return np.zeros((0, 4))
    out = np.vstack(segs)
    return out[np.hypot(out[:, 2] - out[:, 0], out[:, 3] - out[:, 1]) > 0]
