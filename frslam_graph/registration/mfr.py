"""Our MFR registration: room-subset × dihedral search around the map's wall direction, then
sub-pixel refinement of rotation, translation and the two scales.

Frames and units: the plan is in plan units (right-handed, y up); the map in metres. Internally
the map is handled in the *grid frame* of the known-area crop (origin = corner of its cell (0, 0),
axes along the grid); the result is composed with the grid's ``origin`` (x, y, yaw) to give a
matrix from plan coordinates to ``map`` metres.

Steps
1. Map: observed footprint = free ∪ occupied with holes filled, main connected component; free
   space with small obstacles filled; its signed distance field (full resolution); the
   "wall-side" free cells (free next to a wall) and doorway-like exits (free running into
   unobserved space, 0.4–2.5 m wide); up to two wall directions (peaks of the histogram of
   4 × gradient angle, so walls at 90° agree); area moments and bounding boxes per direction.
2. Plan: its wall direction; per-room area moments and bounding boxes; boundary samples with
   inward normals, leaving out doors and open-plan boundaries (no plan wall along them, as in
   R2V's living-dining-kitchens); the room graph (doors, open-plan boundaries, shared walls for
   rooms without doors) and its connected subsets (:mod:`frslam_graph.registration.subsets`).
3. Coarse: every (subset, dihedral case, map direction) gets axis scales from second moments
   (the paper's eq. 7 uses bounding boxes) within the aspect bound, ranked by scale- and
   aspect-invariant shape features plus an aspect and door-width tie-break; the best ``pool_k``
   are scored on few points, the best ``top_k`` of those on more: key = IoU with the footprint
   × wall precision (plan walls on the observed area that are map walls) × wall recall (map walls
   explained by plan walls) × exit agreement × door-width plausibility, all vectorised over the
   hypotheses (cv2.remap lookups). A poor best fit triggers a scale/shift search.
4. Fine: the best ``refine_k`` distinct placements are refined coarsely and re-scored; the best
   is refined at full resolution (:mod:`frslam_graph.registration.refine`: rotation, translation,
   two scales along the plan's wall directions and the wall offset) and scored: ``score`` = IoU of
   the rooms it places on the footprint; ``ambiguity`` = best re-score of a different placement
   (or unrefined coarse key, scaled) / the best's; ``details["alternatives"]`` hold up to
   ``alternatives`` runner-up placements (relative score, plan -> map matrix) for a caller that
   can tell them apart with other data; failure when IoU × precision × recall or the recall is
   too low.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import shapely

from frslam_graph.raster import RasterFrame
from frslam_graph.registration.refine import (
    DistanceField,
    RefineResult,
    refine,
    ring_edges,
    sample_boundaries,
)
from frslam_graph.registration.result import Registration, _wrap_deg, params_from_matrix
from frslam_graph.registration.subsets import (
    MAX_ROOMS,
    SubsetGeometry,
    adjacency_masks,
    connected_subsets,
    link_doors,
    mask_ids,
    mask_matrix,
    rings_moments,
)

METHOD = "mfr"
_SHIFT = 8  # cv2.fillPoly fractional bits
_FIX = float(1 << _SHIFT)
DIHEDRAL: tuple[tuple[int, bool], ...] = tuple((k, f) for f in (False, True) for k in range(4))


def _rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _dihedral(k: int, flipped: bool) -> np.ndarray:
    """2×2 ``R(k·90°) · diag(1, -1 if flipped)`` with exact integer entries."""
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4]
    r = np.array([[c, -s], [s, c]], dtype=np.float64)
    return r @ np.diag([1.0, -1.0 if flipped else 1.0])


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, K) distances from points (M, 2) to segments a–b (K, 2 each)."""
    u = b - a
    l2 = np.maximum((u * u).sum(axis=1), 1e-300)
    rx = p[:, None, 0] - a[None, :, 0]
    ry = p[:, None, 1] - a[None, :, 1]
    t = np.clip((rx * u[None, :, 0] + ry * u[None, :, 1]) / l2[None, :], 0.0, 1.0)
    return np.hypot(rx - t * u[None, :, 0], ry - t * u[None, :, 1])


def _dominant_angles(vectors: np.ndarray, max_peaks: int = 2, rel: float = 0.35) -> list[float]:
    """Wall directions modulo 90° (radians in (-pi/4, pi/4]) of (N, 2) vectors weighted by their
    length: peaks of a circular histogram (smoothed, σ = 3°), the strongest first, each refined by
    the weighted circular mean within ±10°; a second peak counts when it is at least ``rel`` of
    the first and 20° away. Robust to a few diagonal walls, unlike one overall mean."""
    if len(vectors) > 6000:  # a regular subsample keeps the histogram
        vectors = vectors[:: int(math.ceil(len(vectors) / 6000))]
    mag = np.hypot(vectors[:, 0], vectors[:, 1])
    ok = mag > 0
    if not ok.any():
        return [0.0]
    v, w = vectors[ok], mag[ok]
    a4 = np.mod(4.0 * np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi)  # 4x angle: walls at 90° agree
    bins = 360
    hist = np.bincount((a4 / (2 * np.pi) * bins).astype(np.intp) % bins, weights=w, minlength=bins)
    # smoothing σ = 3° of wall angle (12 bins of the 4x angle): gradients of rasterised oblique
    # walls alias into two lobes a few degrees either side of the true direction
    half = 36
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / 12.0) ** 2)
    smooth = np.convolve(np.concatenate([hist[-half:], hist, hist[:half]]), kernel, mode="valid")
    is_peak = (smooth >= np.roll(smooth, 1)) & (smooth > np.roll(smooth, -1))
    peaks = np.flatnonzero(is_peak)
    peaks = peaks[np.argsort(-smooth[peaks], kind="stable")].tolist()
    out: list[float] = []
    for i in peaks[:max_peaks]:
        if out and smooth[i] < rel * smooth[peaks[0]]:
            break
        centre = (i + 0.5) / bins * 2 * np.pi
        d = np.angle(np.exp(1j * (a4 - centre)))
        near = np.abs(d) < np.radians(40.0)  # ±10° of wall angle
        mean = centre + (np.sum(w[near] * d[near]) / max(np.sum(w[near]), 1e-12))
        ang = float(np.angle(np.exp(1j * mean)) / 4.0)
        if all(abs(np.angle(np.exp(4j * (ang - o)))) > np.radians(80.0) for o in out):  # 20° apart
            out.append(ang)
    return out or [0.0]


# ----------------------------------------------------------------------------------------- map
@dataclass
class MapObservation:
    """The map, prepared for registration (grid frame of the known-area crop, metres)."""

    to_map: np.ndarray
    frame: RasterFrame
    footprint: np.ndarray
    free: np.ndarray
    field: DistanceField
    angles: list[float]  # wall directions (radians), strongest first
    area: float
    centroid: np.ndarray
    cov: np.ndarray
    bboxes: list[np.ndarray]  # per angle: x0, y0, x1, y1 in the frame rotated by -angle
    coarse_frame: RasterFrame
    coarse_footprint: np.ndarray
    coarse_footprint_u8: np.ndarray
    footprint_u8: np.ndarray
    edge_dt: np.ndarray  # metres to the nearest wall-side free cell (full resolution)
    edge_points: np.ndarray  # (K, 2) a subsample of those cells' centres, metres
    exit_points: np.ndarray  # (J, 2) free cells next to unobserved space outside the footprint


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every region not connected to the image border filled."""
    h, w = mask.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = mask
    ff = pad.copy()
    flood = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(ff, flood, (0, 0), 2)
    return ff[1:-1, 1:-1] != 2


def observe_map(
    grid,
    *,
    min_area_m2: float = 2.0,
    obstacle_m2: float = 0.5,
    coarse_px: int = 80,
    max_edge_points: int = 400,
    min_exit_m: float = 0.4,
    max_exit_m: float = 2.5,
    max_resolution: float = 0.5,
) -> MapObservation | str:
    """Prepare ``grid`` (an OccupancyGrid); returns a failure reason string when unusable."""
    known_all = ~grid.unknown_mask()
    if not known_all.any():
        return "map has no observed cells (all unknown)"
    if grid.resolution > max_resolution:
        return f"map resolution {grid.resolution:g} m per cell is too coarse (at most {max_resolution:g} m)"
    g = grid.crop_to_known(margin_cells=4)
    res = g.resolution
    free = g.free_mask()
    occ = g.occupied_mask()
    if not free.any():
        return "map has no free cells"
    known = free | occ
    filled = _fill_holes(known.astype(np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(filled.astype(np.uint8), connectivity=8)
    if n <= 1:
        return "map has no observed area"
    main = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    footprint = labels == main
    area = float(footprint.sum()) * res * res
    if area < min_area_m2:
        return f"observed area too small ({area:.2f} m² < {min_area_m2} m²)"
    free = free & footprint
    # small obstacles (furniture, people) inside free space are not walls
    nonfree = (~free & footprint).astype(np.uint8)
    m, lab2, st2, _ = cv2.connectedComponentsWithStats(nonfree, connectivity=8)
    small = np.zeros(m, bool)
    small[1:] = st2[1:, cv2.CC_STAT_AREA] * res * res < obstacle_m2
    # keep components that touch the footprint's outside (outer walls) even when small
    free = free | (small[lab2] & _interior(footprint, lab2, m))
    field_ = DistanceField.from_masks(free, res, (0.0, 0.0))
    # free cells on a wall (not on a frontier to unknown): the map's room structure
    walls_in = (footprint & ~free).astype(np.uint8)
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
    edge = free & cv2.dilate(walls_in, cross).astype(bool)
    edge_dt = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3) * np.float32(res)
    er, ec = np.nonzero(edge)
    if len(er) < 10:
        return "map shows no walls next to free space: nothing to match"
    stride = max(1, len(er) // max_edge_points)
    edge_points = (np.column_stack([ec[::stride], er[::stride]]).astype(np.float64) + 0.5) * res
    # exits: where free space runs out of the observed area (open doorways, open-plan boundaries)
    outside = (~footprint).astype(np.uint8)
    exits = free & cv2.dilate(outside, cross).astype(bool)
    # doorway-like exits: 0.4 to 2.5 m across (single missing wall cells are noise; big ragged
    # openings are gaps in what the sensor saw, not doors); one point (centroid) per doorway
    m, _, st3, cen3 = cv2.connectedComponentsWithStats(exits.astype(np.uint8), connectivity=8)
    span = np.maximum(st3[1:, cv2.CC_STAT_WIDTH], st3[1:, cv2.CC_STAT_HEIGHT]) * res
    door_like = (span >= min_exit_m) & (span <= max_exit_m)
    exit_points = (cen3[1:][door_like] + 0.5) * res

    # dominant wall direction from the free-space edges
    fimg = cv2.GaussianBlur(free.astype(np.float32), (9, 9), 2.0)  # σ 2 cells: less aliasing
    gx = cv2.Sobel(fimg, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(fimg, cv2.CV_32F, 0, 1, ksize=3)
    sel = (np.abs(gx) + np.abs(gy)) > 0.05
    if sel.sum() > 30000:  # plenty: a regular subsample keeps the histogram
        idx = np.flatnonzero(sel)
        sel = np.zeros(sel.shape, bool)
        sel.flat[idx[:: int(math.ceil(len(idx) / 30000))]] = True
    angles = _dominant_angles(np.column_stack([gx[sel], gy[sel]]).astype(np.float64)) if sel.any() else [0.0]

    mom = cv2.moments(footprint.astype(np.uint8), binaryImage=True)
    m00 = max(mom["m00"], 1.0)
    centroid = np.array([(mom["m10"] / m00 + 0.5) * res, (mom["m01"] / m00 + 0.5) * res])
    cov = np.array([[mom["mu20"], mom["mu11"]], [mom["mu11"], mom["mu02"]]]) / m00 * res * res
    cov += np.eye(2) * res * res / 12.0
    contours, _ = cv2.findContours(footprint.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    pts = (np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64) + 0.5) * res
    half = 0.5 * res
    bboxes = []
    for angle in angles:
        pa = pts @ _rot(-angle).T
        bboxes.append(
            np.array(
                [pa[:, 0].min() - half, pa[:, 1].min() - half, pa[:, 0].max() + half, pa[:, 1].max() + half]
            )
        )

    h, w = footprint.shape
    k = max(1, int(math.ceil(max(h, w) / coarse_px)))
    hc, wc = max(1, h // k), max(1, w // k)
    block = footprint[: hc * k, : wc * k].reshape(hc, k, wc, k).mean(axis=(1, 3))
    coarse_frame = RasterFrame(res * k, (0.0, 0.0), (hc, wc))
    return MapObservation(
        to_map=g.map_from_grid(),
        frame=RasterFrame(res, (0.0, 0.0), (h, w)),
        footprint=footprint,
        free=free,
        field=field_,
        angles=angles,
        area=area,
        centroid=centroid,
        cov=cov,
        bboxes=bboxes,
        coarse_frame=coarse_frame,
        coarse_footprint=block >= 0.5,
        coarse_footprint_u8=(block >= 0.5).astype(np.uint8),
        footprint_u8=footprint.astype(np.uint8),
        edge_dt=edge_dt,
        edge_points=edge_points,
        exit_points=exit_points,
    )


def _ring(mask: np.ndarray) -> np.ndarray:
    """One-pixel ring just outside ``mask`` (counts as observed: walls end there)."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask


def _interior(footprint: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Bool per pixel: its non-free component does not touch the footprint's border ring."""
    ring = _ring(footprint)
    border = cv2.dilate(ring.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    touching = np.zeros(n, bool)
    touching[np.unique(labels[border])] = True
    touching[0] = True
    return ~touching[labels]


# ---------------------------------------------------------------------------------------- plan
@dataclass
class PlanModel:
    """A floor plan prepared for registration (plan units)."""

    ids: list[str]
    polygons: list
    rings: list[np.ndarray]
    ring_room: np.ndarray
    doors: np.ndarray  # (D, 4)
    angle: float
    moments: np.ndarray  # (n, 6) in the frame rotated by -angle
    bounds: np.ndarray  # (n, 4) in the frame rotated by -angle
    adjacency: np.ndarray
    area: float
    diag: float
    room_rings: list[list[np.ndarray]]
    room_holes: list[list[np.ndarray]]
    room_areas: np.ndarray
    perimeter: float
    samples: np.ndarray  # (M, 2) boundary points on walls (door openings, open-plan boundaries left out)
    sample_step: float  # their spacing (plan units)
    sample_normals: np.ndarray  # (M, 2) unit inward normals
    sample_room: np.ndarray  # (M,) room index of each sample
    plan_dt: np.ndarray  # plan units to the nearest room boundary, on plan_frame
    open_dt: np.ndarray | None  # plan units to the nearest opening (door, open-plan boundary)
    plan_frame: RasterFrame
    inner: np.ndarray  # (P, 2) grid points inside rooms
    inner_onehot: np.ndarray  # (P, n) their room
    door_width: float  # median door width (plan units), 0 without doors
    coarse_samples: np.ndarray  # (M', 2) a subsample of ``samples``
    coarse_onehot: np.ndarray  # (M', n) their room


def prepare_plan(
    plan,
    *,
    adjacency: str = "doors",
    samples: int = 1000,
    dt_px: int = 240,
    inner_points: int = 1200,
    coarse_samples: int = 500,
) -> PlanModel:
    """Room polygons, rings, moments and the room graph of a FloorPlan."""
    rooms = list(plan.rooms)
    polys = [r.polygon for r in rooms]
    rings, ring_room, room_rings, room_holes = [], [], [], []
    for i, p in enumerate(polys):
        p = shapely.orient_polygons(p)  # exterior counter-clockwise: the room on the left
        rings.append(np.asarray(p.exterior.coords)[:-1])
        ring_room.append(i)
        room_rings.append([rings[-1]])
        room_holes.append([])
        for hole in p.interiors:
            rings.append(np.asarray(hole.coords)[:-1])
            ring_room.append(i)
            room_holes[-1].append(rings[-1])
    starts, ends, edge_ring = ring_edges(rings)
    ring_room_arr = np.array(ring_room)
    edge_room = ring_room_arr[edge_ring]
    n = len(rooms)
    angle = _dominant_angles(ends - starts, max_peaks=1)[0]
    if abs(angle) < math.radians(0.5):  # a plan drawn axis-aligned: its own axes, exactly
        angle = 0.0
    rot = _rot(-angle)
    moments = rings_moments(starts @ rot.T, ends @ rot.T, edge_room, n)
    xy = starts @ rot.T
    bounds = np.full((n, 4), np.inf)
    bounds[:, 2:] = -np.inf
    np.minimum.at(bounds[:, 0], edge_room, xy[:, 0])
    np.minimum.at(bounds[:, 1], edge_room, xy[:, 1])
    np.maximum.at(bounds[:, 2], edge_room, xy[:, 0])
    np.maximum.at(bounds[:, 3], edge_room, xy[:, 1])
    minx, miny = starts.min(axis=0)
    maxx, maxy = starts.max(axis=0)
    diag = float(math.hypot(maxx - minx, maxy - miny))
    doors_list = list(plan.doors)
    door_rooms = link_doors(rooms, doors_list, 0.025 * diag)
    doors = np.array([[*d.a, *d.b] for d in doors_list], dtype=np.float64).reshape(-1, 4)
    perimeter = float(np.hypot(*(ends - starts).T).sum())
    step = perimeter / samples
    pts, nrm, owner = sample_boundaries(rings, step, doors, door_tol=0.012 * diag)
    owner_room = ring_room_arr[owner]
    bare_pts = np.zeros((0, 2))
    # open plans: a boundary between two rooms that no plan wall runs along is not a wall (and
    # links the rooms)
    walls = getattr(plan, "walls", None)
    if walls is not None and len(walls):
        segs = np.vstack([np.asarray(walls, dtype=np.float64).reshape(-1, 4), doors])
        tol = 0.01 * diag
        supported = _segment_distance(pts, segs[:, :2], segs[:, 2:]).min(axis=1) <= tol
        bare = np.flatnonzero(~supported)
        if len(bare):
            d = _segment_distance(pts[bare], starts, ends)  # (U, E)
            d[edge_room[None, :] == owner_room[bare, None]] = np.inf
            nearest = np.full((len(bare), n), np.inf)
            np.minimum.at(nearest.T, edge_room, d.T)
            other = np.argmin(nearest, axis=1)
            close = nearest[np.arange(len(bare)), other] <= tol
            pairs = np.sort(np.column_stack([owner_room[bare][close], other[close]]), axis=1)
            if len(pairs):
                uniq, counts = np.unique(pairs, axis=0, return_counts=True)
                # both rooms sample the shared stretch: half the count times the spacing
                for (i, j), c in zip(uniq.tolist(), counts.tolist(), strict=True):
                    if 0.5 * c * step >= 0.025 * diag:
                        door_rooms.append((i, j))
            # only a boundary shared with another room can be open; outer walls stay walls
            keep = np.ones(len(pts), bool)
            keep[bare[close]] = False
            bare_pts = pts[~keep]
            pts, nrm, owner_room = pts[keep], nrm[keep], owner_room[keep]
    adj = adjacency_masks(rooms, door_rooms, mode=adjacency, touch_tol=0.01 * diag)
    pres = diag / dt_px
    pframe = RasterFrame.around((minx, miny, maxx, maxy), pres, margin=0.05 * diag)
    lines = np.zeros(pframe.shape, np.uint8)
    cells = np.floor((pts - pframe.origin) / pres).astype(np.intp)
    lines[np.clip(cells[:, 1], 0, pframe.height - 1), np.clip(cells[:, 0], 0, pframe.width - 1)] = 1
    openings = np.zeros(pframe.shape, np.uint8)
    for x1, y1, x2, y2 in doors:
        a, b = (np.array([[x1, y1], [x2, y2]]) - pframe.origin) / pres - 0.5
        a, b = tuple(np.round(a * _FIX).astype(int)), tuple(np.round(b * _FIX).astype(int))
        cv2.line(openings, a, b, 1, 1, cv2.LINE_8, _SHIFT)
    # a closed door looks like a wall: map walls at plan doors are explained too (recall)
    plan_dt = cv2.distanceTransform(1 - (lines | openings), cv2.DIST_L2, 3) * np.float32(pres)
    if len(bare_pts):
        cells = np.floor((bare_pts - pframe.origin) / pres).astype(np.intp)
        openings[np.clip(cells[:, 1], 0, pframe.height - 1), np.clip(cells[:, 0], 0, pframe.width - 1)] = 1
    open_dt = (
        cv2.distanceTransform(1 - openings, cv2.DIST_L2, 3) * np.float32(pres) if openings.any() else None
    )
    area = float(moments[:, 0].sum())
    cell = math.sqrt(area / inner_points)
    iframe = RasterFrame.around((minx, miny, maxx, maxy), cell)
    lab = _fill(room_rings, room_holes, range(n), np.eye(3), iframe, labels=True)
    ir, ic = np.nonzero(lab)
    inner = (np.column_stack([ic, ir]) + 0.5) * cell + iframe.origin
    inner_room = lab[ir, ic] - 1
    empty = np.setdiff1d(np.arange(n), inner_room)  # rooms too small for the grid: one point each
    if len(empty):
        extra = np.array([polys[i].representative_point().coords[0] for i in empty])
        inner = np.vstack([inner, extra])
        inner_room = np.concatenate([inner_room, empty])
    eye = np.eye(n)
    cstride = max(1, len(pts) // coarse_samples)
    return PlanModel(
        ids=[r.id for r in rooms],
        polygons=polys,
        rings=rings,
        ring_room=np.array(ring_room),
        doors=doors,
        angle=angle,
        moments=moments,
        bounds=bounds,
        adjacency=adj,
        area=area,
        diag=diag,
        room_rings=room_rings,
        room_holes=room_holes,
        room_areas=moments[:, 0].copy(),
        perimeter=perimeter,
        samples=pts,
        sample_step=step,
        sample_normals=nrm,
        sample_room=owner_room,
        plan_dt=plan_dt,
        open_dt=open_dt,
        plan_frame=pframe,
        inner=inner,
        inner_onehot=eye[inner_room].astype(np.float32),
        door_width=float(np.median(np.hypot(doors[:, 2] - doors[:, 0], doors[:, 3] - doors[:, 1])))
        if len(doors)
        else 0.0,
        coarse_samples=pts[::cstride],
        coarse_onehot=eye[owner_room[::cstride]].astype(np.float32),
    )


# ------------------------------------------------------------------------------------- coarse
def _features(area, cx, cy, vxx, vxy, vyy, x0, y0, x1, y1) -> np.ndarray:
    w = np.maximum(x1 - x0, 1e-12)
    h = np.maximum(y1 - y0, 1e-12)
    sx, sy = np.sqrt(vxx), np.sqrt(vyy)
    return np.stack(
        [
            area / (w * h),
            (cx - x0) / w,
            (cy - y0) / h,
            sx / w * 2.0,
            sy / h * 2.0,
            vxy / (sx * sy),
            area / (sx * sy) / 12.0,
        ],
        axis=-1,
    )


@dataclass
class Hypothesis:
    mask: int
    k: int
    flipped: bool
    matrix: np.ndarray  # plan -> grid frame metres
    feature_cost: float
    angle_index: int = 0  # which of the map's wall directions
    coarse_iou: float = 0.0
    refined: RefineResult | None = None
    key: float = 0.0  # coarse IoU x structure precision x recall
    quick: float = 0.0  # the same after the screening refinement
    score: float = 0.0
    rooms: tuple[int, ...] = ()


def _coarse_hypotheses(
    pm: PlanModel, obs: MapObservation, masks: np.ndarray, *, max_aspect: float, top_k: int, door_width_m=None
) -> dict[str, np.ndarray]:
    """The ``top_k`` (subset, dihedral case, map wall direction) by shape-feature distance to
    the map, each with its moment-matched plan -> grid-frame matrix, as arrays: ``mask``,
    ``case`` (index in :data:`DIHEDRAL`), ``mats`` (H, 3, 3), ``cost``, ``angle`` (map direction)."""
    n = len(pm.ids)
    member = mask_matrix(masks, n)
    geo = SubsetGeometry.of(member, pm.moments, pm.bounds)
    parts = [
        _coarse_hypotheses_at(pm, obs, masks, geo, ai, max_aspect, top_k, door_width_m)
        for ai in range(len(obs.angles))
    ]
    pool = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(pool["cost"], kind="stable")[:top_k]
    return {k: v[order] for k, v in pool.items()}


def _coarse_hypotheses_at(
    pm: PlanModel, obs: MapObservation, masks, geo, ai: int, max_aspect: float, top_k: int, door_width_m
) -> dict[str, np.ndarray]:
    angle = obs.angles[ai]
    rm = _rot(-angle)
    mc = rm @ obs.centroid
    mcov = rm @ obs.cov @ rm.T
    bx0, by0, bx1, by1 = obs.bboxes[ai]
    fmap = _features(obs.area, mc[0], mc[1], mcov[0, 0], mcov[0, 1], mcov[1, 1], bx0, by0, bx1, by1)
    costs, a_all, b_all, cx_all, cy_all = [], [], [], [], []
    for k, flipped in DIHEDRAL:
        g = _dihedral(k, flipped)  # signed permutation
        swap = g[0, 0] == 0
        ux, uy = (geo.cy, geo.cx) if swap else (geo.cx, geo.cy)
        vx, vy = (geo.vyy, geo.vxx) if swap else (geo.vxx, geo.vyy)
        lo_x, hi_x = (geo.y0, geo.y1) if swap else (geo.x0, geo.x1)
        lo_y, hi_y = (geo.x0, geo.x1) if swap else (geo.y0, geo.y1)
        sx_ = g[0, 1] if swap else g[0, 0]
        sy_ = g[1, 0] if swap else g[1, 1]
        cx, cy = sx_ * ux, sy_ * uy
        x0, x1 = (lo_x, hi_x) if sx_ > 0 else (-hi_x, -lo_x)
        y0, y1 = (lo_y, hi_y) if sy_ > 0 else (-hi_y, -lo_y)
        vxy = sx_ * sy_ * geo.vxy
        f = _features(geo.area, cx, cy, vx, vxy, vy, x0, y0, x1, y1)
        a = np.sqrt(mcov[0, 0] / vx)
        b = np.sqrt(mcov[1, 1] / vy)
        ratio = b / a
        # shape distance; ties (every rectangle looks alike) go to plausible aspect and door width
        cost = np.sum((f - fmap) ** 2, axis=1) + 0.01 * np.log(ratio) ** 2
        cost = cost - 0.01 * np.log(np.maximum(_door_prior(pm, np.sqrt(a * b), door_width_m), 1e-6))
        costs.append(np.where((ratio > max_aspect) | (ratio < 1.0 / max_aspect), np.inf, cost))
        a_all.append(a)
        b_all.append(b)
        cx_all.append(cx)
        cy_all.append(cy)
    costs = np.stack(costs, axis=1)  # (S, 8)
    flat = np.argsort(costs, axis=None, kind="stable")[:top_k]
    flat = flat[np.isfinite(costs.ravel()[flat])]
    si, ji = np.divmod(flat, len(DIHEDRAL))
    a = np.stack(a_all, axis=1)[si, ji]
    b = np.stack(b_all, axis=1)[si, ji]
    cx = np.stack(cx_all, axis=1)[si, ji]
    cy = np.stack(cy_all, axis=1)[si, ji]
    gs = np.stack([_dihedral(k, f) for k, f in DIHEDRAL])[ji]  # (H, 2, 2)
    rp = _rot(-pm.angle)
    rmap = _rot(angle)
    lin = rmap[None] @ (np.stack([a, b], axis=1)[:, :, None] * gs) @ rp[None]
    t_al = np.column_stack([mc[0] - a * cx, mc[1] - b * cy])
    mats = np.zeros((len(flat), 3, 3))
    mats[:, :2, :2] = lin
    mats[:, :2, 2] = t_al @ rmap.T
    mats[:, 2, 2] = 1.0
    return {
        "mask": masks[si],
        "case": ji,
        "mats": mats,
        "cost": costs[si, ji],
        "angle": np.full(len(si), ai),
    }


def _fill(
    room_rings, room_holes, rooms, matrix: np.ndarray, frame: RasterFrame, labels: bool = False
) -> np.ndarray:
    """Rasterise plan rooms (indices) under ``matrix`` (plan -> frame metres) with cv2.fillPoly at
    sub-pixel precision; a pixel is inside when its centre is. Mask (uint8) or 1-based labels."""
    m = np.diag([1.0 / frame.resolution, 1.0 / frame.resolution, 1.0]) @ matrix
    m[:2, 2] -= np.asarray(frame.origin) / frame.resolution + 0.5
    a, t = m[:2, :2], m[:2, 2]
    img = np.zeros(frame.shape, np.int32 if labels else np.uint8)
    ext, holes = [], []
    for i in rooms:
        for r in room_rings[i]:
            ext.append(np.round((r @ a.T + t) * _FIX).astype(np.int32).reshape(-1, 1, 2))
        if labels:
            cv2.fillPoly(img, ext, int(i) + 1, lineType=cv2.LINE_8, shift=_SHIFT)
            ext = []
        for r in room_holes[i]:
            holes.append(np.round((r @ a.T + t) * _FIX).astype(np.int32).reshape(-1, 1, 2))
    if ext:
        cv2.fillPoly(img, ext, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    if holes:
        cv2.fillPoly(img, holes, 0, lineType=cv2.LINE_8, shift=_SHIFT)
    return img


def _lookup(img: np.ndarray, x: np.ndarray, y: np.ndarray, resolution: float, origin, fill) -> np.ndarray:
    """Nearest-cell values of ``img`` (row 0 = lowest y; uint8 or float32) at metric points
    (x, y arrays of one shape, at most 32767 wide); ``fill`` outside (cv2.remap)."""
    shape = x.shape
    if x.size == 0:
        return np.full(shape, fill, dtype=img.dtype)
    x2 = x.reshape(shape[0], -1) if x.ndim == 2 else x.reshape(1, -1)
    y2 = y.reshape(x2.shape)
    inv = np.float32(1.0 / resolution)
    mx = (x2 - np.float32(origin[0])) * inv - np.float32(0.5)
    my = (y2 - np.float32(origin[1])) * inv - np.float32(0.5)
    out = cv2.remap(
        img,
        mx.astype(np.float32),
        my.astype(np.float32),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(fill),
    )
    return out.reshape(shape)


def _apply(a: np.ndarray, t: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, 2, 2), (H, 2) affine maps applied to (P, 2) points: x, y arrays of shape (H, P)."""
    a = a.astype(np.float32)
    t = t.astype(np.float32)
    p = pts.astype(np.float32)
    px, py = p[None, :, 0], p[None, :, 1]
    x = a[:, 0, 0, None] * px + a[:, 0, 1, None] * py + t[:, 0, None]
    y = a[:, 1, 0, None] * px + a[:, 1, 1, None] * py + t[:, 1, None]
    return x, y


def _door_prior(pm: PlanModel, scale: np.ndarray, door_width_m) -> np.ndarray:
    """Plausibility (0..1] of a scale (metres per plan unit) from the plan's median door width:
    1 while the door is ``door_width_m`` = (lo, hi) metres wide, a log-normal fall-off outside."""
    scale = np.asarray(scale, dtype=np.float64)
    if door_width_m is None or pm.door_width <= 0:
        return np.ones_like(scale)
    lo, hi = door_width_m
    w = np.log(np.maximum(scale * pm.door_width, 1e-12))
    excess = np.maximum(0.0, np.maximum(math.log(lo) - w, w - math.log(hi)))
    return np.exp(-0.5 * (excess / 0.5) ** 2)


def _exit_factor(pm: PlanModel, obs: MapObservation, ainv, tinv, scale, tol: float, exits=None) -> np.ndarray:
    """(H,) 0.5 + 0.5 × share of the map's doorway-like exits (free space running into unobserved
    space) that land near a plan opening (door or open-plan boundary); 1 without either."""
    exits = obs.exit_points if exits is None else exits
    if pm.open_dt is None or len(exits) == 0:
        return np.ones(len(ainv))
    x, y = _apply(ainv, tinv, exits)
    pf = pm.plan_frame
    d = _lookup(pm.open_dt, x, y, pf.resolution, pf.origin, 1e9)
    near = d < (np.maximum(tol, 0.3) / scale + pf.resolution)[:, None]
    return 0.5 + 0.5 * near.mean(axis=1)


def _coarse_scores(
    pm: PlanModel,
    obs: MapObservation,
    mats: np.ndarray,
    masks: np.ndarray,
    door_width_m=None,
    points: int | None = None,
    tol: float | None = None,
    matched_cover: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Coarse IoU and structure key of every hypothesis at once (vectorised over hypotheses).

    IoU from the plan's interior grid points landing on the coarse footprint; precision from the
    boundary samples landing near a wall-side free cell; recall from the map's wall-side free
    cells landing near a plan boundary (all at tolerance 1.5 coarse cells). ``points`` caps the
    points of each kind (a cheaper first pass); ``tol`` overrides the tolerance (metres);
    ``matched_cover`` scores the rooms placed on the footprint (at least that share of their
    area) instead of each hypothesis's subset.
    """
    n = len(pm.ids)

    def sub(arr: np.ndarray) -> np.ndarray:
        return arr if points is None or len(arr) <= points else arr[:: int(math.ceil(len(arr) / points))]

    a, t = mats[:, :2, :2], mats[:, :2, 2]
    det = np.abs(np.linalg.det(a))
    member = mask_matrix(np.asarray(masks, dtype=np.uint64), n).astype(np.float64)  # (H, n)
    cf = obs.coarse_frame
    tol = 1.5 * cf.resolution if tol is None else tol
    # IoU
    inner, inner_onehot = sub(pm.inner), sub(pm.inner_onehot)
    x, y = _apply(a, t, inner)
    on = _lookup(obs.coarse_footprint_u8, x, y, cf.resolution, (0.0, 0.0), 0)
    frac = (on.astype(np.float32) @ inner_onehot) / np.maximum(inner_onehot.sum(axis=0), 1.0)  # (H, n)
    if matched_cover is not None:  # the rooms the placement puts on the footprint, not the subset
        member = (frac >= matched_cover).astype(np.float64)
    inter = (frac * member) @ pm.room_areas * det
    area_s = member @ pm.room_areas * det
    iou = np.clip(inter / np.maximum(area_s + obs.area - inter, 1e-12), 0.0, 1.0)
    # precision: plan walls that land on the observed area must be walls of the map
    samples = sub(pm.coarse_samples)
    x, y = _apply(a, t, samples)
    res = obs.frame.resolution
    inside = _lookup(obs.footprint_u8, x, y, res, (0.0, 0.0), 0) > 0
    near = (_lookup(obs.edge_dt, x, y, res, (0.0, 0.0), 1e9) < tol) & inside
    precision = near.sum(axis=1) / np.maximum(inside.sum(axis=1), 1)
    # recall
    ainv = np.linalg.inv(a)
    tinv = -np.einsum("hij,hj->hi", ainv, t)
    edges = sub(obs.edge_points)
    x, y = _apply(ainv, tinv, edges)
    pf = pm.plan_frame
    dp = _lookup(pm.plan_dt, x, y, pf.resolution, pf.origin, 1e9)
    tol_plan = tol / np.sqrt(det) + pf.resolution
    recall = np.mean(dp < tol_plan[:, None], axis=1) if len(edges) else np.zeros(len(mats))
    exits = _exit_factor(pm, obs, ainv, tinv, np.sqrt(det), tol, sub(obs.exit_points))
    key = iou * precision * recall * exits * _door_prior(pm, np.sqrt(det), door_width_m)
    return iou, key


def _score_hypotheses(pm: PlanModel, obs: MapObservation, hyps: list[Hypothesis], door_width_m=None) -> None:
    """:func:`_coarse_scores` for a list of hypotheses (sets ``coarse_iou`` and ``key``)."""
    iou, key = _coarse_scores(
        pm,
        obs,
        np.stack([h.matrix for h in hyps]),
        np.array([h.mask for h in hyps], dtype=np.uint64),
        door_width_m,
    )
    for h, i_, k_ in zip(hyps, iou, key, strict=True):
        h.coarse_iou = float(i_)
        h.key = float(k_)


def _score(
    pm: PlanModel, frame: RasterFrame, footprint: np.ndarray, matrix: np.ndarray, min_cover: float
) -> tuple[float, tuple[int, ...]]:
    """IoU of the rooms the placement puts on the footprint (>= ``min_cover`` of their area) with
    the footprint, and those rooms (indices)."""
    if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:2, :2])) <= 0:
        return 0.0, ()
    n = len(pm.ids)
    labels = _fill(pm.room_rings, pm.room_holes, range(n), matrix, frame, labels=True)
    on = np.bincount(labels[footprint].ravel(), minlength=n + 1)[1:]
    det = abs(np.linalg.det(matrix[:2, :2]))
    px_area = pm.room_areas * det / frame.resolution**2
    cover = on / np.maximum(px_area, 1e-9)
    rooms = tuple(int(i) for i in np.flatnonzero(cover >= min_cover))
    if not rooms:
        return 0.0, rooms
    sel = np.zeros(n + 1, bool)
    sel[np.asarray(rooms) + 1] = True
    placed = sel[labels]
    inter = np.count_nonzero(placed & footprint)
    union = np.count_nonzero(placed | footprint)
    return (inter / union if union else 0.0), rooms


def _structure(
    pm: PlanModel,
    obs: MapObservation,
    matrix: np.ndarray,
    tol: float,
    max_points: int = 300,
) -> tuple[float, float]:
    """(precision, recall) of the room structure under a placement, within ``tol`` metres.

    precision: share of the plan's wall samples landing on the observed footprint that land near
    a wall-side free cell of the map (unobserved rooms' walls off the footprint do not count); recall: share of the map's wall-side free cells that land
    near a boundary of any plan room. A room stretched over several observed rooms explains
    the outline but not the inner walls: its recall is low.
    """
    res = obs.frame.resolution
    pts = pm.samples
    if len(pts) == 0 or len(obs.edge_points) == 0:
        return 0.0, 0.0
    pts = pts[:: max(1, len(pts) // max_points)]
    a, t = matrix[:2, :2], matrix[:2, 2]
    q = pts @ a.T + t
    inside = _lookup(obs.footprint_u8, q[:, 0], q[:, 1], res, (0.0, 0.0), 0) > 0
    d = _lookup(obs.edge_dt, q[:, 0], q[:, 1], res, (0.0, 0.0), 1e9)
    precision = float(np.sum((d < tol) & inside) / max(int(inside.sum()), 1))
    det = abs(float(np.linalg.det(a)))
    if det <= 0:
        return precision, 0.0
    ainv = np.linalg.inv(a)
    e = (obs.edge_points - t) @ ainv.T
    pf = pm.plan_frame
    pc = np.floor((e[:, 0] - pf.origin[0]) / pf.resolution).astype(np.intp)
    pr = np.floor((e[:, 1] - pf.origin[1]) / pf.resolution).astype(np.intp)
    hp, wp = pm.plan_dt.shape
    okp = (pc >= 0) & (pr >= 0) & (pc < wp) & (pr < hp)
    dp = np.full(len(e), np.inf, np.float32)
    dp[okp] = pm.plan_dt[pr[okp], pc[okp]] * np.float32(math.sqrt(det))
    recall = float(np.mean(dp < tol + pf.resolution * math.sqrt(det)))
    return precision, recall


def _local_search(pm: PlanModel, obs: MapObservation, hyps: list[Hypothesis], opts: dict) -> None:
    """Coordinate search on the coarse key over each map axis's scale and shift (about the
    footprint's centroid, in the map's wall-aligned frame), two rounds, for each hypothesis."""
    rounds = (((0.85, 0.92, 1.0, 1.08, 1.17), 0.08), ((0.96, 0.98, 1.0, 1.02, 1.04), 0.03))
    for h in hyps:
        angle, bbox = obs.angles[h.angle_index], obs.bboxes[h.angle_index]
        rm = np.eye(3)
        rm[:2, :2] = _rot(angle)
        c = _rot(-angle) @ obs.centroid
        ext = bbox[2:] - bbox[:2]
        for factors, shift in rounds:
            for axis in (0, 1):
                trials = []
                for f in factors:
                    for sh in (-shift, 0.0, shift):
                        d = np.eye(3)
                        d[axis, axis] = f
                        d[axis, 2] = c[axis] * (1.0 - f) + sh * ext[axis]
                        trials.append(
                            Hypothesis(h.mask, h.k, h.flipped, rm @ d @ rm.T @ h.matrix, h.feature_cost)
                        )
                _score_hypotheses(pm, obs, trials, opts["door_width_m"])
                top = max(trials, key=lambda t: t.key)
                if top.key > h.key:
                    h.matrix, h.key, h.coarse_iou = top.matrix, top.key, top.coarse_iou


def _refine_from(
    pm: PlanModel,
    obs: MapObservation,
    matrix: np.ndarray,
    delta: float,
    opts: dict,
    *,
    scales: tuple,
    spacing_px: float,
    max_points: int,
    iterations: int,
) -> RefineResult:
    """Refine the placement ``matrix`` (plan -> grid frame) on a subsample of the plan's boundary
    samples about ``spacing_px`` map cells apart (at most ``max_points``).

    The scales act along the plan's wall directions: the plan is first turned by ``-pm.angle``
    (zero for plans drawn axis-aligned); the result's matrix includes that turn.
    """
    pre = np.eye(3)
    pre[:2, :2] = _rot(-pm.angle)
    flipped, theta, sx, sy, tx, ty = params_from_matrix(matrix @ pre.T)
    base = pm.sample_step  # plan units between samples
    want = spacing_px * obs.frame.resolution / math.sqrt(sx * sy)
    stride = max(1, int(want / base), int(math.ceil(len(pm.samples) / max_points)))
    r = refine(
        pm.samples[::stride] @ pre[:2, :2].T,
        pm.sample_normals[::stride] @ pre[:2, :2].T,
        obs.field,
        flipped,
        theta,
        tx,
        ty,
        sx,
        sy,
        delta=delta,
        delta_sigma=opts["delta_sigma"],
        scales=scales,
        iterations=iterations,
        # the wall offset trades against the scales under wide robust scales: hold it there
        fixed_delta_stages=sum(1 for c in scales if c > 0.16),
        # one independent wall error per 0.5 m of wall
        correlation=0.5 / max(stride * base * math.sqrt(sx * sy), 1e-9),
    )
    r.pre = pre
    return r


DEFAULTS: dict[str, Any] = {
    "adjacency": "doors",  # room graph for subsets: doors | touch | both
    "max_aspect": 1.6,  # bound on sy/sx (plan aspect errors up to about ±30 %)
    "pool_k": 384,  # hypotheses (subset, dihedral case) kept by shape features, scored coarsely
    "first_pass_points": 80,  # points of each kind in that first, cheap coarse pass
    "top_k": 64,  # hypotheses scored on the coarse grid with all points
    "refine_k": 3,  # distinct hypotheses refined
    "search_below_iou": 0.85,  # search scales and shifts when the best coarse IoU is below this
    "max_subsets_per_level": 3000,
    "coarse_px": 80,
    "sample_px": 1.5,  # boundary sample spacing in map cells (final stage)
    "max_points": 1500,
    "quick_points": 300,  # boundary samples when screening the refined hypotheses
    "quick_scales": (0.15,),  # robust scales (m) of the screening refinement
    "quick_iterations": 6,  # Gauss-Newton iterations per robust-scale stage when screening
    "iterations": 10,  # Gauss-Newton iterations of the final stage
    "delta": 0.06,  # prior of the wall half-thickness (m): plan room boundary to free-space edge
    "delta_sigma": 0.05,
    "min_cover": 0.5,  # a room is matched when this share of it lies on the footprint
    "min_score": 0.25,  # below this IoU x structure precision x recall: no match (another building)
    "min_recall": 0.5,  # share of the map's walls the placed plan must explain
    "ambiguous_at": 0.9,  # details["ambiguous"] when the ambiguity reaches this
    "alternatives": 2,  # details["alternatives"]: up to this many runner-up placements
    "min_area_m2": 2.0,
    "seed_rooms": None,  # room ids one of which the subset must contain (the robot's room)
    "door_width_m": (0.3, 4.0),  # plausible median door opening (m); None: no scale prior
}


def register_mfr(plan, grid, **options: Any) -> Registration:
    """Register ``plan`` to ``grid`` with our MFR; see the module docstring and :data:`DEFAULTS`.

    Never raises on a valid FloorPlan and OccupancyGrid: failures are ``ok == False`` + reason.
    """
    t0 = time.perf_counter()
    unknown = set(options) - set(DEFAULTS)
    if unknown:
        from frslam_graph.errors import ConfigError

        raise ConfigError(f"unknown mfr option(s) {sorted(unknown)}; expected some of {sorted(DEFAULTS)}")
    opts = {**DEFAULTS, **options}
    try:
        return _register(plan, grid, opts, t0)
    except Exception as exc:  # never raise on data: report it
        return Registration.failure(
            f"internal error: {type(exc).__name__}: {exc}", METHOD, time.perf_counter() - t0
        )


def _register(plan, grid, opts: dict, t0: float) -> Registration:
    def fail(reason: str, **details: Any) -> Registration:
        return Registration.failure(reason, METHOD, time.perf_counter() - t0, **details)

    n = len(plan.rooms)
    if n < 2:
        return fail(f"plan has {n} room(s): flip and rotation of a single room are undetermined")
    if n > MAX_ROOMS:
        return fail(f"plan has {n} rooms; at most {MAX_ROOMS} are supported")
    obs = observe_map(grid, min_area_m2=opts["min_area_m2"], coarse_px=opts["coarse_px"])
    if isinstance(obs, str):
        return fail(obs)
    t_map = time.perf_counter()
    pm = prepare_plan(plan, adjacency=opts["adjacency"])
    seeds = None
    if opts["seed_rooms"]:
        seeds = np.array([pm.ids.index(r) for r in opts["seed_rooms"] if r in pm.ids], dtype=np.int64)
        if len(seeds) == 0:
            return fail(f"none of the seed rooms {list(opts['seed_rooms'])} is in the plan")
    masks = connected_subsets(pm.adjacency, seeds=seeds, max_per_level=opts["max_subsets_per_level"])
    pool = _coarse_hypotheses(
        pm, obs, masks, max_aspect=opts["max_aspect"], top_k=opts["pool_k"], door_width_m=opts["door_width_m"]
    )
    if len(pool["mask"]) == 0:
        return fail("no room subset fits the map's shape within the aspect bound")
    if len(pool["mask"]) > opts["top_k"]:  # cheap first pass on a few points of each kind
        _, key = _coarse_scores(
            pm, obs, pool["mats"], pool["mask"], opts["door_width_m"], points=opts["first_pass_points"]
        )
        keep = np.argsort(-key, kind="stable")[: opts["top_k"]]
        pool = {k: v[keep] for k, v in pool.items()}
    iou, key = _coarse_scores(pm, obs, pool["mats"], pool["mask"], opts["door_width_m"])
    hyps = [
        Hypothesis(int(m), DIHEDRAL[c][0], DIHEDRAL[c][1], mat, float(cost), int(ai), float(i), key=float(k))
        for m, c, mat, cost, ai, i, k in zip(
            pool["mask"], pool["case"], pool["mats"], pool["cost"], pool["angle"], iou, key, strict=True
        )
    ]
    hyps.sort(key=lambda h: -h.key)
    if hyps[0].coarse_iou < opts["search_below_iou"]:
        # the map holds area the plan lacks (or the reverse): the moment fit is off; search
        _local_search(pm, obs, hyps[:2], opts)
        hyps.sort(key=lambda h: -h.key)
    t_coarse = time.perf_counter()

    chosen: list[Hypothesis] = []
    covered = np.zeros(len(hyps), bool)  # same placement as a chosen one
    same_as = _placement_test(np.stack([h.matrix for h in hyps]), obs)
    for i, h in enumerate(hyps):
        if len(chosen) >= opts["refine_k"]:
            break
        if covered[i]:
            continue
        chosen.append(h)
        covered |= same_as(h.matrix)
    delta0 = float(opts["delta"])
    tol_f = max(3.0 * obs.frame.resolution, 0.1)
    for h in chosen:  # screen: coarse robust scales, few points, scored on the coarse grid
        h.refined = _refine_from(
            pm,
            obs,
            h.matrix,
            delta0,
            opts,
            scales=opts["quick_scales"],
            spacing_px=4.0,
            max_points=opts["quick_points"],
            iterations=opts["quick_iterations"],
        )
    mats = np.stack([h.refined.matrix for h in chosen])
    bad = ~np.all(np.isfinite(mats), axis=(1, 2))
    bad |= ~(np.abs(np.linalg.det(np.where(bad[:, None, None], np.eye(3), mats)[:, :2, :2])) > 1e-12)
    mats[bad] = np.stack([h.matrix for h in chosen])[bad]
    _, quick = _coarse_scores(  # all screened placements at once, at the fine tolerance
        pm,
        obs,
        mats,
        np.array([h.mask for h in chosen], dtype=np.uint64),
        opts["door_width_m"],
        tol=tol_f,
        matched_cover=opts["min_cover"],
    )
    for h, q, b in zip(chosen, quick, bad, strict=True):
        h.quick = 0.0 if b or not np.isfinite(q) else float(q)
    chosen.sort(key=lambda h: -h.quick)
    best = chosen[0]
    r0 = best.refined
    best.refined = _refine_from(
        pm,
        obs,
        r0.matrix,
        r0.delta,
        opts,
        scales=(0.05,),
        spacing_px=opts["sample_px"],
        max_points=opts["max_points"],
        iterations=opts["iterations"],
    )
    if not _plausible(best.refined, opts):  # a degenerate final fit: keep the screened one
        best.refined = r0
    r = best.refined
    if not _plausible(r, opts):
        return fail("degenerate fit (scales collapsed or exploded)")
    best.score, best.rooms = _score(pm, obs.frame, obs.footprint, r.matrix, opts["min_cover"])
    prec, rec = _structure(pm, obs, r.matrix, tol_f, 1000)
    quality = best.score * prec * rec
    second = max(
        (h.quick for h in chosen[1:] if not _same_placement(h.refined.matrix, r0.matrix, obs)), default=0.0
    )
    rest = [h.key for h, c in zip(hyps, covered, strict=True) if not c]
    if rest:  # unrefined placements: their coarse key relative to the best's coarse key
        second = max(second, best.quick * max(rest) / max(best.key, 1e-9))
    ambiguity = float(min(1.0, second / best.quick)) if best.quick > 0 else 1.0
    # the runner-up placements (each different from the best and from each other), for a caller
    # that can tell them apart with other data (e.g. the robot's scans)
    alternatives: list[dict[str, Any]] = []
    placed = [r0.matrix]
    for h in chosen[1:]:
        if len(alternatives) >= opts["alternatives"] or h.quick <= 0.0:
            break
        if any(_same_placement(h.refined.matrix, m, obs) for m in placed):
            continue
        placed.append(h.refined.matrix)
        alternatives.append({"relative_score": h.quick / best.quick, "matrix": obs.to_map @ h.refined.matrix})
    t_fine = time.perf_counter()

    matrix = obs.to_map @ r.matrix
    cov = r.covariance
    if cov is not None and grid.origin[2] != 0.0:
        rot3 = np.eye(3)
        rot3[:2, :2] = _rot(grid.origin[2])
        cov = rot3 @ cov @ rot3.T
    details = {
        "ambiguous": bool(ambiguity >= opts["ambiguous_at"]),
        "alternatives": alternatives,
        "quality": float(quality),
        "precision": prec,
        "recall": rec,
        "delta_m": r.delta,
        "fit": r.inliers,
        "rms_m": r.rms,
        "n_points": r.n_points,
        "map_angles_deg": [math.degrees(a) for a in obs.angles],
        "plan_angle_deg": math.degrees(pm.angle),
        "observed_area_m2": obs.area,
        "n_subsets": int(len(masks)),
        "n_hypotheses": len(hyps),
        "coarse_iou": best.coarse_iou,
        "coarse_rooms": list(mask_ids(best.mask, pm.ids)),
        "time_map_s": t_map - t0,
        "time_coarse_s": t_coarse - t_map,
        "time_fine_s": t_fine - t_coarse,
    }
    candidates = [
        (
            float(h.quick),
            *(lambda f, r: (bool(f), _wrap_deg(math.degrees(r))))(*params_from_matrix(h.refined.matrix)[:2]),
        )
        for h in chosen
    ]
    reg = Registration.from_matrix(
        matrix,
        score=float(best.score),
        ambiguity=ambiguity,
        rooms=tuple(pm.ids[i] for i in best.rooms),
        covariance=cov,
        method=METHOD,
        candidates=candidates,
        details=details,
    )
    if quality < opts["min_score"] or rec < opts["min_recall"]:
        reg.ok = False
        reg.reason = (
            f"no match: IoU {best.score:.2f} x wall precision {prec:.2f} x recall {rec:.2f} = {quality:.2f} "
            f"(needs >= {opts['min_score']} and recall >= {opts['min_recall']}; a plan of another building?)"
        )
    reg.time_s = time.perf_counter() - t0
    return reg


def _plausible(r: RefineResult, opts: dict) -> bool:
    """Finite, non-degenerate, and the aspect within the bound."""
    m = r.matrix
    if not np.all(np.isfinite(m)) or not (r.sx > 0 and r.sy > 0):
        return False
    ratio = r.sy / r.sx
    return 1.0 / opts["max_aspect"] ** 2 <= ratio <= opts["max_aspect"] ** 2


def _mask_rooms(mask: int, n: int) -> list[int]:
    return [i for i in range(n) if (mask >> i) & 1]


def _placement_test(mats: np.ndarray, obs: MapObservation):
    """A function ``same(m) -> (H,) bool``: which of the (H, 3, 3) placements ``mats`` place the
    plan nearly as ``m`` does (see :func:`_same_placement`)."""
    h, w = obs.frame.shape
    res = obs.frame.resolution
    corners = np.array([[0.0, w * res, 0.0, w * res], [0.0, 0.0, h * res, h * res], [1.0, 1.0, 1.0, 1.0]])
    plan_pts = np.linalg.solve(mats, np.broadcast_to(corners, (len(mats), 3, 4)))  # (H, 3, 4)
    signs = np.linalg.det(mats[:, :2, :2]) > 0
    thr = 0.15 * math.sqrt(obs.area)

    def same(m: np.ndarray) -> np.ndarray:
        d = np.einsum("ij,hjk->hik", m[:2], plan_pts) - corners[:2]
        dist = np.hypot(d[:, 0], d[:, 1]).max(axis=1)
        return (signs == (np.linalg.det(m[:2, :2]) > 0)) & (dist < thr)

    return same


def _same_placement(m1: np.ndarray, m2: np.ndarray, obs: MapObservation) -> bool:
    """True when two plan -> map matrices place the plan nearly the same on the observed area:
    the same handedness and the observed area's corners moved by less than 15 % of its size."""
    if (np.linalg.det(m1[:2, :2]) > 0) != (np.linalg.det(m2[:2, :2]) > 0):
        return False
    h, w = obs.frame.shape
    res = obs.frame.resolution
    corners = np.array([[0.0, w * res, 0.0, w * res], [0.0, 0.0, h * res, h * res], [1.0, 1.0, 1.0, 1.0]])
    d = (m1 @ np.linalg.solve(m2, corners) - corners)[:2]
    return bool(np.max(np.hypot(d[0], d[1])) < 0.15 * math.sqrt(obs.area))
