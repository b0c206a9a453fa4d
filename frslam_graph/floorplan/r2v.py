"""R2V vector floor plans (Liu et al., "Raster-to-Vector", ICCV 2017) -> :class:`FloorPlan`.

Each row of an R2V ``.txt`` is ``x1 y1 x2 y2 category d1 d2`` (tab separated, image pixels, y
down). ``wall`` and ``door`` rows are segments (a door is an opening in a wall); room rows
(``bedroom``, ``kitchen``, ...) are label boxes somewhere *inside* a room; icon rows (``toilet``,
``bathtub``, ...) are boxes and are ignored here.

Rooms are built from the walls by rasterising: walls and doors (doors close their openings) are
drawn ``wall_px`` pixels thick, exactly symmetric about their centre lines, and segment ends
that miss another segment by up to ``touch_px`` are joined to it (annotation joints are often a
few pixels off). The free space is cut into 4-connected regions; the region touching the image
border is the outside. Each room label claims the region under its centre (label rows whose
boxes coincide name one room); a region holding several labels (a Japanese LDK labelled
``kitchen`` and ``living_room``) is split between them by geodesic distance from the label
centres; other enclosed regions become ``unknown`` rooms (slivers below ``min_room_area`` are
dropped). Wall pixels are then shared out to the nearest region, so neighbouring rooms meet on
the wall centre lines without overlapping, and each region becomes a polygon with exact pixel
edges, simplified by ``simplify`` (Douglas-Peucker).

When a label lies outside every enclosed region (walls that do not close), the walls are
repaired in steps, each on the original walls, until every label is enclosed (or the step
enclosing most labels is kept): ``snap`` (loose wall ends extended along their direction up to
``snap_px`` to the next wall), ``extend`` (up to ``extend_frac`` of the plan size),
``bridge<k>`` (also join each loose end to the nearest segment within k px), optional
``close<k>`` (morphological closing; off by default: it bulges rooms out of the walls), and
finally ``+box`` (a box room around each label still outside, bounded by the nearest wall in
each axis direction or the plan's wall extent). :class:`R2VResult` reports the strategy used
and which room holds each label.

Output coordinates are plan pixels with y flipped (``y_plan = -y_px``) so the plan is
right-handed; ``units = "px"``, ``metres_per_unit = None``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import shapely
from shapely.geometry import Polygon

from frslam_graph import limits
from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan._raster_polygons import geodesic_split, labels_to_polygons, largest_polygon
from frslam_graph.floorplan.model import Door, FloorPlan, Room, normalise_room_type
from frslam_graph.limits import check_file_size, short_repr

ICON_CATEGORIES = frozenset(
    {"washing_basin", "cooking_counter", "bathtub", "toilet", "entrance", "special", "stairs", "PS", "point"}
)
ROOM_CATEGORIES = frozenset(
    {
        "bedroom",
        "closet",
        "bathroom",
        "balcony",
        "restroom",
        "kitchen",
        "corridor",
        "washing_room",
        "living_room",
    }
)
MAX_ABS_COORD = 1e7


@dataclass(frozen=True)
class R2VOptions:
    """Tuning of the wall -> room reconstruction (lengths in plan pixels unless noted)."""

    wall_px: int = 2  # thickness of drawn walls/doors, raster pixels
    max_raster: int = 3000  # longest image side; larger plans are rasterised coarser
    min_room_area: float = 60.0  # unlabelled regions smaller than this (plan px²) are dropped
    simplify: float = 1.0  # Douglas-Peucker tolerance of the room outlines
    touch_px: float = 6.0  # a wall end closer than this to another segment is joined to it
    snap_px: float = 12.0  # 'snap': extend dangling wall ends up to this far
    extend_frac: float = 0.25  # 'extend': up to this fraction of the plan's larger side
    bridge_px: tuple[float, ...] = (25.0, 50.0, 100.0)  # 'bridge<k>': join loose ends to the nearest wall
    close_kernels: tuple[int, ...] = ()  # 'close<k>': morphological closing kernels, raster px (off)
    split_multi_label: bool = True  # split a region holding several room labels between them
    repair: bool = True  # try the repair steps when a label is not enclosed (False: walls as drawn)


@dataclass(frozen=True)
class R2VLabel:
    """A labelled room: normalised type, label box (x1, y1, x2, y2; R2V pixels, y down), line
    number, and the id of the room that holds it (None when no room could be built around it).

    Label rows whose boxes coincide (IoU > 0.5) name one room; the first row gives ``type`` and
    the others are kept in ``other_types`` / ``other_lines`` (R2V has e.g. one box labelled both
    ``kitchen`` and ``washing_room``).
    """

    type: str
    box: tuple[float, float, float, float]
    line: int
    room: str | None = None
    other_types: tuple[str, ...] = ()
    other_lines: tuple[int, ...] = ()


@dataclass(frozen=True)
class R2VData:
    """Parsed rows of an R2V file (pixels, y down)."""

    walls: np.ndarray  # (K, 4)
    doors: np.ndarray  # (D, 4)
    labels: list[R2VLabel]
    icons: list[tuple[str, tuple[float, float, float, float], int]] = field(default_factory=list)
    source: str | None = None


@dataclass(frozen=True)
class R2VResult:
    """A loaded plan plus how it was built: per-label outcome and the repair strategy used."""

    plan: FloorPlan
    labels: list[R2VLabel]
    strategy: str

    @property
    def n_labels(self) -> int:
        return len(self.labels)

    @property
    def n_found(self) -> int:
        return sum(lab.room is not None for lab in self.labels)

    @property
    def all_found(self) -> bool:
        return self.n_found == self.n_labels


# --------------------------------------------------------------------------------- parsing
def parse_r2v(path: str | Path) -> R2VData:
    """Read and validate the rows of an R2V file (FloorPlanError naming the file and line)."""
    path = Path(path)
    src = str(path)
    check_file_size(path, limits.MAX_PLAN_BYTES, FloorPlanError, "R2V file")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FloorPlanError("file not found", source=src) from None
    except OSError as exc:
        raise FloorPlanError(f"cannot read file ({exc.strerror or exc})", source=src) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FloorPlanError(
            f"not a text file (byte {exc.start} is not UTF-8); expected R2V rows 'x1 y1 x2 y2 category d1 d2'",
            source=src,
        ) from None
    if not text.strip():
        raise FloorPlanError("file is empty (expected R2V rows 'x1 y1 x2 y2 category d1 d2')", source=src)
    walls, doors, labels, icons = [], [], [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        while fields and not fields[-1].strip():
            fields.pop()
        where = f"line {lineno}"
        if not 5 <= len(fields) <= 7:
            raise FloorPlanError(
                f"expected 7 tab-separated columns 'x1 y1 x2 y2 category d1 d2' (d1, d2 optional), got {len(fields)}",
                source=src,
                where=where,
            )
        try:
            coords = tuple(float(v) for v in fields[:4])
        except ValueError:
            raise FloorPlanError(
                f"columns 1-4 must be numbers x1 y1 x2 y2, got {short_repr(fields[:4])}",
                source=src,
                where=where,
            ) from None
        if not all(math.isfinite(v) for v in coords):
            raise FloorPlanError(
                f"coordinates must be finite, got {short_repr(coords)}", source=src, where=where
            )
        if max(abs(v) for v in coords) > MAX_ABS_COORD:
            raise FloorPlanError(
                f"absurd coordinate {max(abs(v) for v in coords):.3g} (|value| must be <= {MAX_ABS_COORD:.0e})",
                source=src,
                where=where,
            )
        category = fields[4].strip()
        if not category or _is_number(category):
            raise FloorPlanError(
                f"column 5 must be a category name (wall, door, bedroom, ...), got {short_repr(category)}",
                source=src,
                where=where,
            )
        for k, extra in enumerate(fields[5:], start=6):
            if extra.strip() and not _is_number(extra.strip()):
                raise FloorPlanError(
                    f"column {k} must be a number, got {short_repr(extra)}", source=src, where=where
                )
        if category in ("wall", "door"):
            (walls if category == "wall" else doors).append(coords)
            if len(walls) + len(doors) > limits.MAX_PLAN_WALLS:
                raise FloorPlanError(
                    f"more than {limits.MAX_PLAN_WALLS:,} walls and doors (limit MAX_PLAN_WALLS, "
                    "frslam_graph.limits)",
                    source=src,
                    where=where,
                )
        elif category in ROOM_CATEGORIES or (
            category not in ICON_CATEGORIES and normalise_room_type(category) != "unknown"
        ):
            labels.append(R2VLabel(normalise_room_type(category), _box(coords), lineno))
        else:
            icons.append((category, _box(coords), lineno))
    return R2VData(
        walls=np.asarray(walls, dtype=np.float64).reshape(-1, 4),
        doors=np.asarray(doors, dtype=np.float64).reshape(-1, 4),
        labels=_group_labels(labels),
        icons=icons,
        source=src,
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _box(c: tuple[float, ...]) -> tuple[float, float, float, float]:
    return (min(c[0], c[2]), min(c[1], c[3]), max(c[0], c[2]), max(c[1], c[3]))


def _group_labels(labels: list[R2VLabel]) -> list[R2VLabel]:
    """Merge label rows whose boxes coincide (IoU > 0.5) into one labelled room."""
    kept: list[R2VLabel] = []
    for lab in labels:
        for k, other in enumerate(kept):
            if _box_iou(other.box, lab.box) > 0.5:
                kept[k] = replace(
                    other,
                    other_types=(*other.other_types, lab.type),
                    other_lines=(*other.other_lines, lab.line),
                )
                break
        else:
            kept.append(lab)
    return kept


def _box_iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else float(a == b)


# --------------------------------------------------------------------------------- raster frame
@dataclass(frozen=True)
class _Frame:
    """Image of the plan: pixel (c, r) covers x in [x0 + c/s, x0 + (c+1)/s), y_px likewise."""

    x0: float
    y0: float
    s: float  # raster pixels per plan pixel
    shape: tuple[int, int]

    def to_img(self, xy: np.ndarray) -> np.ndarray:
        """Plan pixels -> continuous image coordinates (pixel (c, r) centre at (c + 0.5, r + 0.5))."""
        return (np.asarray(xy, dtype=np.float64) - (self.x0, self.y0)) * self.s


def _make_frame(data: R2VData, opts: R2VOptions) -> _Frame:
    pts = [data.walls.reshape(-1, 2), data.doors.reshape(-1, 2)]
    pts += [np.array([[b[0], b[1]], [b[2], b[3]]]) for b in (lab.box for lab in data.labels)]
    xy = np.concatenate(pts)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    extent = float(max(hi - lo))
    s = min(1.0, (opts.max_raster - 8 * opts.wall_px) / max(extent, 1.0))
    margin = (4 * opts.wall_px + 4) / s
    x0, y0 = lo - margin
    w = int(math.ceil((hi[0] - x0 + margin) * s))
    h = int(math.ceil((hi[1] - y0 + margin) * s))
    return _Frame(float(x0), float(y0), s, (h, w))


def _draw_segments(img: np.ndarray, frame: _Frame, segs: np.ndarray, thickness: float) -> None:
    """Mark the pixels whose centres lie within ``thickness / 2`` of a segment.

    Exact and symmetric: a wall on a pixel edge with thickness 2 covers one pixel on each side,
    so the rooms on both sides meet on its centre line (cv2.line's thick lines are biased).
    Axis-aligned segments get square caps (slices), slanted ones round caps (capsules)."""
    if len(segs) == 0:
        return
    hw = thickness / 2.0
    h, w = img.shape
    p = frame.to_img(segs[:, :2])
    q = frame.to_img(segs[:, 2:])
    lo = np.minimum(p, q) - hw
    hi = np.maximum(p, q) + hw
    # pixel c is inside [lo, hi] when its centre c + 0.5 is
    c0 = np.clip(np.ceil(lo - 0.5), 0, (w, h)).astype(np.int64)
    c1 = np.clip(np.floor(hi - 0.5) + 1, 0, (w, h)).astype(np.int64)
    d = q - p
    axis = (np.abs(d[:, 0]) < 1e-9) | (np.abs(d[:, 1]) < 1e-9)
    for i in np.flatnonzero(axis).tolist():
        img[c0[i, 1] : c1[i, 1], c0[i, 0] : c1[i, 0]] = 255
    slanted = np.flatnonzero(~axis & (c1[:, 0] > c0[:, 0]) & (c1[:, 1] > c0[:, 1]))
    if len(slanted):
        _fill_capsules(img, p[slanted], q[slanted], c0[slanted, 1], c1[slanted, 1], hw)


def _fill_capsules(
    img: np.ndarray, p: np.ndarray, q: np.ndarray, r0: np.ndarray, r1: np.ndarray, hw: float
) -> None:
    """Fill slanted capsules (segments p-q, radius hw; image coordinates) row by row, all at once:
    a convex capsule cuts each pixel-centre row in one interval, the hull of the intervals of
    its band (|distance to the line| <= hw, 0 <= t <= 1) and of its two end discs."""
    h, w = img.shape
    counts = (r1 - r0).astype(np.int64)
    seg = np.repeat(np.arange(len(p)), counts)
    rows = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(r0, counts)
    y = rows + 0.5
    px, py, qx, qy = p[seg, 0], p[seg, 1], q[seg, 0], q[seg, 1]
    dx, dy = qx - px, qy - py
    length2 = dx * dx + dy * dy
    lo = np.full(len(y), np.inf)
    hi = np.full(len(y), -np.inf)
    for cx, cy in ((px, py), (qx, qy)):  # end discs
        rem = hw * hw - (y - cy) ** 2
        ok = rem >= 0
        half = np.sqrt(np.where(ok, rem, 0.0))
        lo = np.where(ok, np.minimum(lo, cx - half), lo)
        hi = np.where(ok, np.maximum(hi, cx + half), hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        steep = np.abs(dy) > 1e-12
        xc = px + (y - py) * dx / np.where(steep, dy, 1.0)  # the centre line at this row
        half = hw * np.sqrt(length2) / np.where(steep, np.abs(dy), 1.0)
        band_lo, band_hi = xc - half, xc + half
        # 0 <= t <= 1 with t = ((x - px) dx + (y - py) dy) / |d|²; dx != 0 for slanted segments
        ta = px - (y - py) * dy / dx
        tb = px + (length2 - (y - py) * dy) / dx
        slab_lo, slab_hi = np.minimum(ta, tb), np.maximum(ta, tb)
        blo, bhi = np.maximum(band_lo, slab_lo), np.minimum(band_hi, slab_hi)
    ok = steep & (blo <= bhi)
    lo = np.where(ok, np.minimum(lo, blo), lo)
    hi = np.where(ok, np.maximum(hi, bhi), hi)
    c_start = np.clip(np.ceil(lo - 0.5), 0, w).astype(np.int64)
    c_end = np.clip(np.floor(hi - 0.5) + 1, 0, w).astype(np.int64)  # exclusive
    keep = np.isfinite(lo) & (c_end > c_start) & (rows >= 0) & (rows < h)
    rows, c_start, c_end = rows[keep], c_start[keep], c_end[keep]
    if len(rows) == 0:
        return
    ra, rb = int(rows.min()), int(rows.max()) + 1
    ca, cb = int(c_start.min()), int(c_end.max())
    diff = np.zeros((rb - ra, cb - ca + 1), dtype=np.int32)
    np.add.at(diff, (rows - ra, c_start - ca), 1)
    np.add.at(diff, (rows - ra, c_end - ca), -1)
    img[ra:rb, ca:cb][np.cumsum(diff[:, :-1], axis=1) > 0] = 255


def _closest_points(points: np.ndarray, segs: np.ndarray, own: np.ndarray | None = None):
    """Yield (slice, foot (c, M, 2), dist (c, M)) of the closest points on every segment, for
    chunks of ``points`` (bounded memory for large plans); ``own[k]`` = a segment to ignore."""
    a = segs[None, :, :2]
    d = segs[None, :, 2:] - a
    dd = np.maximum((d * d).sum(-1), 1e-12)
    chunk = max(1, 1_000_000 // max(len(segs), 1))
    for s0 in range(0, len(points), chunk):
        sl = slice(s0, min(s0 + chunk, len(points)))
        ap = points[sl, None, :] - a
        t = np.clip((ap * d).sum(-1) / dd, 0.0, 1.0)
        foot = a + t[..., None] * d
        dist = np.linalg.norm(points[sl, None, :] - foot, axis=-1)
        if own is not None:
            dist[np.arange(dist.shape[0]), own[sl]] = np.inf
        yield sl, foot, dist


def _connectors(segs: np.ndarray, tol: float, dangling_above: float | None = None) -> np.ndarray:
    """Short segments joining segment ends to other segments passing within ``tol``.

    By default every end is joined to every segment within ``tol`` (annotation joints that miss
    by a few pixels). With ``dangling_above``, only ends farther than that from every other
    segment (loose ends) are joined, each to its nearest segment ('bridge' repair)."""
    if len(segs) < 2:
        return np.zeros((0, 4))
    ends = np.concatenate([segs[:, :2], segs[:, 2:]])
    own = np.tile(np.arange(len(segs)), 2)
    out = [np.zeros((0, 4))]
    for sl, foot, dist in _closest_points(ends, segs, own):
        if dangling_above is None:
            i, j = np.nonzero((dist > 1e-9) & (dist <= tol))
        else:
            j_all = np.argmin(dist, axis=1)
            dmin = dist[np.arange(len(dist)), j_all]
            i = np.flatnonzero((dmin > dangling_above) & (dmin <= tol))
            j = j_all[i]
        out.append(np.concatenate([ends[sl][i], foot[i, j]], axis=1))
    return np.concatenate(out)


# --------------------------------------------------------------------------------- wall repair
def _min_distance(points: np.ndarray, segs: np.ndarray, own: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest segment other than ``own``."""
    out = np.full(len(points), np.inf)
    for sl, _, dist in _closest_points(points, segs, own):
        out[sl] = dist.min(axis=1)
    return out


def _extensions(
    data: R2VData, frame: _Frame, walls_img: np.ndarray, max_len: float, opts: R2VOptions
) -> np.ndarray:
    """Segments that extend dangling wall ends along their direction to the next wall (<= max_len)."""
    walls = data.walls
    if len(walls) == 0:
        return np.zeros((0, 4))
    length = np.hypot(walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1])
    walls = walls[length > 1e-6]
    length = length[length > 1e-6]
    allsegs = np.concatenate([walls, data.doors])
    ends = np.concatenate([walls[:, :2], walls[:, 2:]])  # (2K, 2)
    dirs = (
        np.concatenate([walls[:, :2] - walls[:, 2:], walls[:, 2:] - walls[:, :2]])
        / np.tile(length, 2)[:, None]
    )
    own = np.tile(np.arange(len(walls)), 2)
    dangling = _min_distance(ends, allsegs, own) > opts.touch_px
    if not dangling.any():
        return np.zeros((0, 4))
    ends, dirs = ends[dangling], dirs[dangling]
    # march each ray through the wall image, starting past the segment's own end cap
    start = (opts.wall_px + 1.0) / frame.s
    steps = np.arange(start, max_len + 1e-9, 0.5 / frame.s)
    if len(steps) == 0:
        return np.zeros((0, 4))
    pts = ends[:, None, :] + steps[None, :, None] * dirs[:, None, :]  # (N, S, 2)
    img = np.floor(frame.to_img(pts.reshape(-1, 2))).astype(np.int64)
    h, w = walls_img.shape
    inside = (img[:, 0] >= 0) & (img[:, 0] < w) & (img[:, 1] >= 0) & (img[:, 1] < h)
    hit = np.zeros(len(img), dtype=bool)
    hit[inside] = walls_img[img[inside, 1], img[inside, 0]] > 0
    hit = hit.reshape(len(ends), len(steps))
    found = hit.any(axis=1)
    first = hit.argmax(axis=1)
    reach = steps[first] + 0.5 * opts.wall_px / frame.s
    tips = ends + reach[:, None] * dirs
    return np.concatenate([ends, tips], axis=1)[found]


def _wall_image(data: R2VData, frame: _Frame, opts: R2VOptions, stage: str, size: float = 0.0) -> np.ndarray:
    """Walls and doors drawn ``wall_px`` thick, joints closed within ``touch_px``; repair stages
    add wall-end extensions ('snap', 'extend') and bridges from loose ends ('bridge')."""
    img = np.zeros(frame.shape, dtype=np.uint8)
    segs = np.concatenate([data.walls, data.doors])
    _draw_segments(img, frame, segs, opts.wall_px)
    _draw_segments(img, frame, _connectors(segs, opts.touch_px), opts.wall_px)
    if stage == "plain":
        return img
    extent = max(frame.shape) / frame.s
    max_len = opts.snap_px if stage == "snap" else opts.extend_frac * extent
    _draw_segments(img, frame, _extensions(data, frame, img, max_len, opts), opts.wall_px)
    if stage == "bridge":
        _draw_segments(img, frame, _connectors(segs, size, dangling_above=opts.touch_px), opts.wall_px)
    elif stage == "close":
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (int(size), int(size)))
        img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, k)
    return img


# --------------------------------------------------------------------------------- regions
def _label_pixels(frame: _Frame, labels: list[R2VLabel]) -> np.ndarray:
    """(N, 2) int (col, row) of each label box centre."""
    if not labels:
        return np.zeros((0, 2), dtype=np.int64)
    c = np.array([((b[0] + b[2]) / 2, (b[1] + b[3]) / 2) for b in (lab.box for lab in labels)])
    px = np.floor(frame.to_img(c)).astype(np.int64)
    return np.clip(px, 0, np.array(frame.shape[::-1]) - 1)


def _assign_labels(
    comp: np.ndarray, outside: int, frame: _Frame, labels: list[R2VLabel], opts: R2VOptions
) -> np.ndarray:
    """Region id of each label (-1: outside or unresolved). A centre on a wall takes the nearest
    free pixel within the label box (or within a few wall widths)."""
    px = _label_pixels(frame, labels)
    out = np.full(len(labels), -1, dtype=np.int64)
    h, w = comp.shape
    for i, (c, r) in enumerate(px.tolist()):
        reg = int(comp[r, c])
        if reg == 0:  # on a wall: nearest free pixel in a small window
            rad = 3 * opts.wall_px
            r0, r1, c0, c1 = max(r - rad, 0), min(r + rad + 1, h), max(c - rad, 0), min(c + rad + 1, w)
            win = comp[r0:r1, c0:c1]
            rr, cc = np.nonzero(win)
            if len(rr):
                k = np.argmin((rr + r0 - r) ** 2 + (cc + c0 - c) ** 2)
                reg = int(win[rr[k], cc[k]])
        out[i] = reg if reg not in (0, outside) else -1
    return out


@dataclass
class _Regions:
    comp: np.ndarray  # int32 connected components of the free space (0 = wall)
    outside: int
    assign: np.ndarray  # region of each label, -1 outside
    stats: np.ndarray  # cv2 component stats (left, top, width, height, area)


def _regions(walls_img: np.ndarray, frame: _Frame, labels: list[R2VLabel], opts: R2VOptions) -> _Regions:
    free = (walls_img == 0).astype(np.uint8)
    _, comp, stats, _ = cv2.connectedComponentsWithStats(free, connectivity=4, ltype=cv2.CV_32S)
    outside = int(comp[0, 0])  # the margin guarantees the corner is free and outside
    return _Regions(comp, outside, _assign_labels(comp, outside, frame, labels, opts), stats)


def _room_image(
    reg: _Regions, frame: _Frame, labels: list[R2VLabel], opts: R2VOptions
) -> tuple[np.ndarray, dict[int, str], np.ndarray]:
    """Final room label image (uint16; 0 = wall/dropped, `outside` id = outside), room types and
    the room label of each R2V label (0 = not found)."""
    comp, outside = reg.comp, reg.outside
    n_comp = len(reg.stats)
    areas = reg.stats[:, cv2.CC_STAT_AREA].astype(np.float64) / frame.s**2
    lut = np.zeros(n_comp, dtype=np.int32)  # component -> room label
    types: dict[int, str] = {}
    label_room = np.zeros(len(labels), dtype=np.int64)
    next_id = 1
    by_region: dict[int, list[int]] = {}
    for i, region in enumerate(reg.assign.tolist()):
        if region >= 0:
            by_region.setdefault(region, []).append(i)
    splits: list[tuple[int, list[int]]] = []
    for region, idx in by_region.items():
        if len(idx) == 1 or not opts.split_multi_label:
            lut[region] = next_id
            types[next_id] = _merge_types([labels[i].type for i in idx])
            label_room[idx] = next_id
            next_id += 1
        else:
            splits.append((region, idx))
    split_regions = {region for region, _ in splits}
    for region in range(1, n_comp):
        if region == outside or lut[region] or region in split_regions:
            continue
        if areas[region] >= opts.min_room_area:
            lut[region] = next_id
            types[next_id] = "unknown"
            next_id += 1
    outside_id = next_id + len(labels) + 1
    lut[outside] = outside_id
    room = lut[comp]
    for region, idx in splits:
        c0, r0, bw, bh = reg.stats[region, :4].tolist()
        r1, c1 = r0 + bh, c0 + bw
        mask = comp[r0:r1, c0:c1] == region
        seeds = _centre_seeds(mask, _label_pixels(frame, [labels[i] for i in idx]) - (c0, r0))
        ids = []
        for i in idx:
            ids.append(next_id)
            types[next_id] = labels[i].type
            label_room[i] = next_id
            next_id += 1
        part = geodesic_split(mask, seeds)
        ids_arr = np.array([0, *ids], dtype=np.int32)
        sub = room[r0:r1, c0:c1]
        sub[mask] = ids_arr[part[mask]]
    return room, types, label_room, outside_id


def _centre_seeds(mask: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Seed image (uint16, k + 1 at seed k) with one pixel per (col, row) centre: the nearest
    pixel of ``mask`` not taken by an earlier seed."""
    seeds = np.zeros(mask.shape, dtype=np.uint16)
    h, w = mask.shape
    yy = xx = None
    for k, (c, r) in enumerate(centres.tolist(), start=1):
        if 0 <= r < h and 0 <= c < w and mask[r, c] and not seeds[r, c]:
            seeds[r, c] = k
            continue
        if yy is None:
            yy, xx = np.nonzero(mask)
        d2 = (yy - r) ** 2 + (xx - c) ** 2
        d2[seeds[yy, xx] > 0] = np.iinfo(d2.dtype).max
        j = int(np.argmin(d2))
        seeds[yy[j], xx[j]] = k
    return seeds


def _merge_types(types: list[str]) -> str:
    return max(dict.fromkeys(types), key=types.count)  # a tie: the first seen (not hash order)


def _absorb_walls(room: np.ndarray) -> np.ndarray:
    """Give every 0 pixel (walls, dropped slivers) the label of the nearest labelled pixel
    (in place)."""
    zero = room == 0
    if not zero.any():
        return room
    src = zero.astype(np.uint8)
    _, idx = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    values = room[~zero]  # raster order = the order OpenCV numbers the zero pixels of `src`
    room[zero] = values[idx[zero] - 1]
    return room


# --------------------------------------------------------------------------------- building
def build_r2v(data: R2VData, options: R2VOptions | None = None, name: str = "") -> R2VResult:
    """Build the FloorPlan of parsed R2V rows (see the module docstring for the method)."""
    opts = options or R2VOptions()
    src = data.source
    if len(data.walls) == 0:
        raise FloorPlanError("no wall rows: rooms are built from walls, and this file has none", source=src)
    frame = _make_frame(data, opts)
    labels = data.labels
    stages: list[tuple[str, str, float]] = [
        ("plain", "plain", 0),
        ("snap", "snap", 0),
        ("extend", "extend", 0),
    ]
    stages += [(f"bridge{k:g}", "bridge", k) for k in opts.bridge_px]
    stages += [(f"close{k}", "close", k) for k in opts.close_kernels]
    if not opts.repair:
        stages = stages[:1]
    best: tuple[int, str, np.ndarray, _Regions] | None = None
    for name_, stage, kernel in stages:
        walls_img = _wall_image(data, frame, opts, stage, kernel)
        reg = _regions(walls_img, frame, labels, opts)
        n_in = int((reg.assign >= 0).sum())
        if best is None or n_in > best[0]:
            best = (n_in, name_, walls_img, reg)
        if n_in == len(labels):
            break
    assert best is not None
    n_in, strategy, walls_img, reg = best
    room, types, label_room, outside_id = _room_image(reg, frame, labels, opts)
    missing = np.flatnonzero(label_room == 0)
    if len(missing) and opts.repair:
        next_id = max(types, default=0) + 1
        for i, box in _box_rooms(walls_img, room, outside_id, frame, labels, missing.tolist(), opts).items():
            room[box] = next_id
            types[next_id] = labels[i].type
            label_room[i] = next_id
            next_id += 1
        if (label_room[missing] > 0).any():
            strategy += "+box"
    full = _absorb_walls(room)
    full[full == outside_id] = 0
    return _to_plan(full, types, label_room, data, frame, opts, strategy, name)


def _box_rooms(
    walls_img: np.ndarray,
    room: np.ndarray,
    outside_id: int,
    frame: _Frame,
    labels: list[R2VLabel],
    missing: list[int],
    opts: R2VOptions,
) -> dict[int, np.ndarray]:
    """Fallback for labels still outside: box rooms (see :func:`_box_room`); where the boxes of
    several labels overlap, the pixels are shared between them by geodesic distance."""
    boxes = {}
    rows = np.flatnonzero(walls_img.any(axis=1))
    cols = np.flatnonzero(walls_img.any(axis=0))
    if len(rows) == 0:
        return boxes
    extent = (int(rows[0]), int(cols[0]), int(rows[-1]), int(cols[-1]))
    outside = room == outside_id
    for i in missing:
        mask = _box_room(walls_img, outside, extent, frame, labels[i], opts)
        if mask is not None:
            boxes[i] = mask
    if len(boxes) <= 1:
        return boxes
    union = np.logical_or.reduce(list(boxes.values()))
    ys, xs = np.nonzero(union)
    r0, r1, c0, c1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    crop = union[r0:r1, c0:c1]
    seeds = _centre_seeds(crop, _label_pixels(frame, [labels[i] for i in boxes]) - (c0, r0))
    part = geodesic_split(crop, seeds)
    out = {}
    for k, i in enumerate(boxes, start=1):
        mask = np.zeros(union.shape, dtype=bool)
        mask[r0:r1, c0:c1] = part == k
        out[i] = mask
    return out


def _box_room(
    walls_img: np.ndarray,
    outside: np.ndarray,
    extent: tuple[int, int, int, int],
    frame: _Frame,
    label: R2VLabel,
    opts: R2VOptions,
) -> np.ndarray | None:
    """Fallback: the box around the label bounded by the nearest wall in each axis direction (an
    open direction reaches the plan's wall extent, and at least past the label box), restricted
    to outside pixels connected to the label centre."""
    c, r = _label_pixels(frame, [label])[0]
    h, w = walls_img.shape
    (bc0, br0), (bc1, br1) = np.floor(frame.to_img(np.array([label.box[:2], label.box[2:]]))).astype(int)
    pad = opts.wall_px
    rmin, cmin = np.minimum(extent[:2], (br0 - pad, bc0 - pad)).clip(0)
    rmax, cmax = np.minimum(np.maximum(extent[2:], (br1 + pad, bc1 + pad)), (h - 1, w - 1))
    row = walls_img[r, :]
    col = walls_img[:, c]
    left = np.flatnonzero(row[:c] > 0)
    right = np.flatnonzero(row[c + 1 :] > 0)
    up = np.flatnonzero(col[:r] > 0)
    down = np.flatnonzero(col[r + 1 :] > 0)
    c0 = left[-1] + 1 if len(left) else cmin
    c1 = c + 1 + right[0] if len(right) else cmax + 1
    r0 = up[-1] + 1 if len(up) else rmin
    r1 = r + 1 + down[0] if len(down) else rmax + 1
    if c1 - c0 < 2 or r1 - r0 < 2:
        return None
    if not outside[r, c]:
        return None
    cand = outside[r0:r1, c0:c1].astype(np.uint8)
    _, comp = cv2.connectedComponents(cand, connectivity=4)
    mask = np.zeros((h, w), dtype=bool)
    mask[r0:r1, c0:c1] = comp == comp[r - r0, c - c0]
    return mask


def _to_plan(
    full: np.ndarray,
    types: dict[int, str],
    label_room: np.ndarray,
    data: R2VData,
    frame: _Frame,
    opts: R2VOptions,
    strategy: str,
    name: str,
) -> R2VResult:
    src = data.source
    ids = np.array(sorted(types), dtype=np.int64)
    geoms = labels_to_polygons(full, ids=ids, simplify=opts.simplify * frame.s)
    # image -> plan: x = x0 + c/s, y_plan = -(y0 + r/s)
    params = [1.0 / frame.s, 0.0, 0.0, -1.0 / frame.s, frame.x0, -frame.y0]
    rooms: list[Room] = []
    room_of: dict[int, str] = {}
    for lab_id in ids.tolist():
        geom = geoms.get(lab_id)
        poly = largest_polygon(geom) if geom is not None else None
        if poly is None or poly.area * 1.0 / frame.s**2 < 1.0:
            continue
        poly = shapely.affinity.affine_transform(poly, params)
        poly = _clean(poly)
        if poly is None:
            continue
        rid = f"r{len(rooms)}"
        room_of[lab_id] = rid
        rooms.append(Room(rid, types[lab_id], poly))
    if not rooms:
        raise FloorPlanError("no enclosed room could be built from the walls", source=src)
    labels = [
        replace(lab, room=room_of.get(int(label_room[i])) if label_room[i] else None)
        for i, lab in enumerate(data.labels)
    ]
    doors = _doors(data, frame, full, room_of, opts)
    walls = data.walls * np.array([1.0, -1.0, 1.0, -1.0])
    plan = FloorPlan(
        rooms=rooms, doors=doors, walls=walls, units="px", metres_per_unit=None, name=name, source=src
    )
    return R2VResult(plan=plan, labels=labels, strategy=strategy)


def _clean(poly: Polygon) -> Polygon | None:
    """Orient and validate a room polygon (largest valid part)."""
    if not poly.is_valid:
        poly = largest_polygon(shapely.make_valid(poly))
        if poly is None:
            return None
    poly = shapely.geometry.polygon.orient(poly, 1.0)
    return poly if poly.area > 0 else None


def _doors(
    data: R2VData, frame: _Frame, full: np.ndarray, room_of: dict[int, str], opts: R2VOptions
) -> list[Door]:
    """Doors in plan coordinates, linked to the rooms sampled on both sides of the opening."""
    doors: list[Door] = []
    if len(data.doors) == 0:
        return doors
    segs = data.doors
    a, b = segs[:, :2], segs[:, 2:]
    d = b - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1) / length[:, None]
    off = (opts.wall_px + 1.0) / frame.s
    fractions = np.array([0.25, 0.5, 0.75])
    h, w = full.shape
    for i in range(len(segs)):
        votes: list[str] = []
        for side in (-1.0, 1.0):
            pts = a[i] + fractions[:, None] * d[i] + side * off * normal[i]
            px = np.floor(frame.to_img(pts)).astype(np.int64)
            px[:, 0] = np.clip(px[:, 0], 0, w - 1)
            px[:, 1] = np.clip(px[:, 1], 0, h - 1)
            vals = full[px[:, 1], px[:, 0]].tolist()
            rids = [room_of[v] for v in vals if v in room_of]
            if rids:
                votes.append(max(dict.fromkeys(rids), key=rids.count))  # a tie: the first seen
        rooms = tuple(dict.fromkeys(votes))
        doors.append(
            Door(
                f"d{i}",
                (float(a[i, 0]), float(-a[i, 1])),
                (float(b[i, 0]), float(-b[i, 1])),
                rooms,
            )
        )
    return doors


def load_r2v_detailed(path: str | Path, options: R2VOptions | None = None) -> R2VResult:
    """Load an R2V file and report how each room label was resolved (see :class:`R2VResult`)."""
    path = Path(path)
    data = parse_r2v(path)
    try:
        return build_r2v(data, options, name=path.stem)
    except FloorPlanError:
        raise
    except Exception as exc:  # any internal failure names the file instead of escaping as a bare traceback
        raise FloorPlanError(
            f"could not build rooms from the walls ({type(exc).__name__}: {exc})", source=str(path)
        ) from exc


def load_r2v(path: str | Path, **options: Any) -> FloorPlan:
    """Load an R2V vector floor plan (``.txt``) as a :class:`FloorPlan` (plan pixels, y up).

    Keyword options are fields of :class:`R2VOptions` (e.g. ``wall_px=3``).
    """
    try:
        opts = R2VOptions(**options)
    except TypeError as exc:
        raise FloorPlanError(f"unknown R2V option ({exc})", source=str(path)) from None
    return load_r2v_detailed(path, opts).plan
