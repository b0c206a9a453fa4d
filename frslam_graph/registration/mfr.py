"""Our MFR registration: room-subset × dihedral search around the map's wall direction, then
sub-pixel refinement of rotation, translation and the two scales.

Frames and units: the plan is in plan units (right-handed, y up); the map in metres. Internally
the map is handled in the *grid frame* of the known-area crop (origin = corner of its cell (0, 0),
axes along the grid); the result is composed with the grid's ``origin`` (x, y, yaw) to give a
matrix from plan coordinates to ``map`` metres.

Steps
1. Map: observed footprint = free ∪ occupied with holes filled, main connected component; free
   space with small obstacles filled; the dominant wall direction ``phi_m`` (magnitude-weighted
   mean of 4·gradient angle, so walls at 90° agree); the footprint's area moments and bounding box
   in the frame rotated by ``-phi_m``.
2. Plan: dominant direction ``phi_p`` of its room edges; per-room area moments and bounding boxes
   in the frame rotated by ``-phi_p``; connected room subsets (doors, or shared walls where the
   plan has no door information) with their moments as one matrix product.
3. Coarse: every (subset, dihedral case) is scored by scale- and aspect-invariant shape features
   (fill of the bounding box, normalised centroid and spreads, correlation, area over spreads);
   the axis scales follow from the second moments (the paper's eq. 7 uses bounding boxes) and must
   respect the aspect bound. The best ``top_k`` are rasterised at a coarse resolution and scored by
   IoU with the footprint.
4. Fine: the best distinct hypotheses are refined on the full-resolution free-space signed
   distance (:mod:`frslam_graph.registration.refine`), then scored by IoU of the rooms they place
   on the observed footprint. ``ambiguity`` = best score of a different placement / best score.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import shapely

from frslam_graph.raster import RasterFrame
from frslam_graph.registration.refine import DistanceField, RefineResult, refine, sample_boundaries
from frslam_graph.registration.result import Registration, _wrap_deg, params_from_matrix
from frslam_graph.registration.subsets import (
    MAX_ROOMS,
    SubsetGeometry,
    adjacency_masks,
    connected_subsets,
    mask_ids,
    mask_matrix,
    polygon_moments,
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


def _dominant_angle(vectors: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Direction modulo 90° (radians in (-pi/4, pi/4]) of (N, 2) vectors, weighted by length."""
    z = vectors[:, 0] + 1j * vectors[:, 1]
    mag = np.abs(z)
    ok = mag > 0
    z, mag = z[ok], mag[ok]
    if weights is not None:
        w = weights[ok]
    else:
        w = mag
    s = np.sum(w * (z / mag) ** 4)
    if abs(s) == 0:
        return 0.0
    return float(np.angle(s) / 4.0)


# ----------------------------------------------------------------------------------------- map
@dataclass
class MapObservation:
    """The map, prepared for registration (grid frame of the known-area crop, metres)."""

    to_map: np.ndarray
    frame: RasterFrame
    footprint: np.ndarray
    free: np.ndarray
    field: DistanceField
    angle: float
    area: float
    centroid: np.ndarray
    cov: np.ndarray
    bbox_aligned: np.ndarray  # x0, y0, x1, y1 in the frame rotated by -angle
    coarse_frame: RasterFrame
    coarse_footprint: np.ndarray


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
) -> MapObservation | str:
    """Prepare ``grid`` (an OccupancyGrid); returns a failure reason string when unusable."""
    known_all = ~grid.unknown_mask()
    if not known_all.any():
        return "map has no observed cells (all unknown)"
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

    # dominant wall direction from the free-space edges
    fimg = cv2.GaussianBlur(free.astype(np.float32), (5, 5), 1.0)
    gx = cv2.Sobel(fimg, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(fimg, cv2.CV_32F, 0, 1, ksize=3)
    sel = (np.abs(gx) + np.abs(gy)) > 0.05
    angle = _dominant_angle(np.column_stack([gx[sel], gy[sel]]).astype(np.float64)) if sel.any() else 0.0

    mom = cv2.moments(footprint.astype(np.uint8), binaryImage=True)
    m00 = max(mom["m00"], 1.0)
    centroid = np.array([(mom["m10"] / m00 + 0.5) * res, (mom["m01"] / m00 + 0.5) * res])
    cov = np.array([[mom["mu20"], mom["mu11"]], [mom["mu11"], mom["mu02"]]]) / m00 * res * res
    cov += np.eye(2) * res * res / 12.0
    contours, _ = cv2.findContours(footprint.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    pts = (np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64) + 0.5) * res
    pa = pts @ _rot(-angle).T
    half = 0.5 * res
    bbox = np.array(
        [pa[:, 0].min() - half, pa[:, 1].min() - half, pa[:, 0].max() + half, pa[:, 1].max() + half]
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
        angle=angle,
        area=area,
        centroid=centroid,
        cov=cov,
        bbox_aligned=bbox,
        coarse_frame=coarse_frame,
        coarse_footprint=block >= 0.5,
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
    extras: dict[str, Any] = field(default_factory=dict)


def prepare_plan(plan, *, adjacency: str = "doors") -> PlanModel:
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
    edges = np.concatenate([np.roll(r, -1, axis=0) - r for r in rings])
    angle = _dominant_angle(edges)
    rot = _rot(-angle)
    moments = np.array([polygon_moments(p, rot) for p in polys])
    bounds = []
    for p in polys:
        xy = np.asarray(p.exterior.coords) @ rot.T
        bounds.append([xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()])
    bounds = np.array(bounds)
    minx, miny, maxx, maxy = plan.bounds
    diag = float(math.hypot(maxx - minx, maxy - miny))
    doors_list = list(plan.doors)
    if doors_list and all(len(d.rooms) < 2 for d in doors_list):
        plan = plan.link_doors(0.02 * diag)
        doors_list = list(plan.doors)
    doors = np.array([[*d.a, *d.b] for d in doors_list], dtype=np.float64).reshape(-1, 4)
    adj = adjacency_masks(rooms, doors_list, mode=adjacency, touch_tol=0.01 * diag)
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
        area=float(sum(p.area for p in polys)),
        diag=diag,
        room_rings=room_rings,
        room_holes=room_holes,
        room_areas=np.array([p.area for p in polys]),
        perimeter=float(sum(np.hypot(*(np.roll(r, -1, axis=0) - r).T).sum() for r in rings)),
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
    coarse_iou: float = 0.0
    refined: RefineResult | None = None
    score: float = 0.0
    rooms: tuple[int, ...] = ()
    fit: float = 0.0


def _coarse_hypotheses(
    pm: PlanModel, obs: MapObservation, masks: np.ndarray, *, max_aspect: float, top_k: int
) -> list[Hypothesis]:
    n = len(pm.ids)
    member = mask_matrix(masks, n)
    geo = SubsetGeometry.of(member, pm.moments, pm.bounds)
    # map geometry in its aligned frame
    rm = _rot(-obs.angle)
    mc = rm @ obs.centroid
    mcov = rm @ obs.cov @ rm.T
    bx0, by0, bx1, by1 = obs.bbox_aligned
    fmap = _features(obs.area, mc[0], mc[1], mcov[0, 0], mcov[0, 1], mcov[1, 1], bx0, by0, bx1, by1)
    c = np.stack([geo.cx, geo.cy], axis=-1)
    corners = np.stack(
        [
            np.stack([geo.x0, geo.y0], -1),
            np.stack([geo.x1, geo.y0], -1),
            np.stack([geo.x0, geo.y1], -1),
            np.stack([geo.x1, geo.y1], -1),
        ],
        axis=1,
    )
    cov = np.stack([np.stack([geo.vxx, geo.vxy], -1), np.stack([geo.vxy, geo.vyy], -1)], axis=-2)
    costs, items = [], []
    for k, flipped in DIHEDRAL:
        g = _dihedral(k, flipped)
        cg = c @ g.T
        covg = g @ cov @ g.T
        cr = corners @ g.T
        x0, y0 = cr[..., 0].min(axis=1), cr[..., 1].min(axis=1)
        x1, y1 = cr[..., 0].max(axis=1), cr[..., 1].max(axis=1)
        f = _features(
            geo.area, cg[:, 0], cg[:, 1], covg[:, 0, 0], covg[:, 0, 1], covg[:, 1, 1], x0, y0, x1, y1
        )
        a = np.sqrt(mcov[0, 0] / covg[:, 0, 0])
        b = np.sqrt(mcov[1, 1] / covg[:, 1, 1])
        cost = np.sum((f - fmap) ** 2, axis=1)
        ratio = b / a
        cost = np.where((ratio > max_aspect) | (ratio < 1.0 / max_aspect), np.inf, cost)
        costs.append(cost)
        items.append((k, flipped, a, b, cg))
    costs = np.stack(costs, axis=1)  # (S, 8)
    flat = np.argsort(costs, axis=None, kind="stable")[:top_k]
    out = []
    rp = _rot(-pm.angle)
    rmap = _rot(obs.angle)
    for idx in flat:
        s, j = divmod(int(idx), len(DIHEDRAL))
        if not np.isfinite(costs[s, j]):
            break
        k, flipped, a, b, cg = items[j]
        lin_aligned = np.diag([a[s], b[s]]) @ _dihedral(k, flipped)
        t_aligned = mc - np.array([a[s], b[s]]) * cg[s]
        m = np.eye(3)
        m[:2, :2] = rmap @ lin_aligned @ rp
        m[:2, 2] = rmap @ t_aligned
        out.append(Hypothesis(int(masks[s]), k, flipped, m, float(costs[s, j])))
    return out


def _fill(pm: PlanModel, rooms, matrix: np.ndarray, frame: RasterFrame, labels: bool = False) -> np.ndarray:
    """Rasterise plan rooms (indices) under ``matrix`` (plan -> frame metres) with cv2.fillPoly at
    sub-pixel precision; a pixel is inside when its centre is. Mask (uint8) or 1-based labels."""
    m = np.diag([1.0 / frame.resolution, 1.0 / frame.resolution, 1.0]) @ matrix
    m[:2, 2] -= np.asarray(frame.origin) / frame.resolution + 0.5
    a, t = m[:2, :2], m[:2, 2]
    img = np.zeros(frame.shape, np.int32 if labels else np.uint8)
    ext, holes = [], []
    for i in rooms:
        for r in pm.room_rings[i]:
            ext.append(np.round((r @ a.T + t) * _FIX).astype(np.int32).reshape(-1, 1, 2))
        if labels:
            cv2.fillPoly(img, ext, int(i) + 1, lineType=cv2.LINE_8, shift=_SHIFT)
            ext = []
        for r in pm.room_holes[i]:
            holes.append(np.round((r @ a.T + t) * _FIX).astype(np.int32).reshape(-1, 1, 2))
    if ext:
        cv2.fillPoly(img, ext, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    if holes:
        cv2.fillPoly(img, holes, 0, lineType=cv2.LINE_8, shift=_SHIFT)
    return img


def _coarse_iou(pm: PlanModel, obs: MapObservation, hyps: list[Hypothesis]) -> None:
    fp = obs.coarse_footprint
    fp_sum = int(fp.sum())
    for h in hyps:
        rooms = [i for i in range(len(pm.ids)) if (h.mask >> i) & 1]
        img = _fill(pm, rooms, h.matrix, obs.coarse_frame).view(bool)
        inter = int(np.count_nonzero(img & fp))
        union = fp_sum + int(np.count_nonzero(img)) - inter
        h.coarse_iou = inter / union if union else 0.0


def _score(
    pm: PlanModel, frame: RasterFrame, footprint: np.ndarray, matrix: np.ndarray, min_cover: float
) -> tuple[float, tuple[int, ...]]:
    """IoU of the rooms the placement puts on the footprint (>= ``min_cover`` of their area) with
    the footprint, and those rooms (indices)."""
    n = len(pm.ids)
    labels = _fill(pm, range(n), matrix, frame, labels=True)
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


def _boundary_samples(pm: PlanModel, obs: MapObservation, scale: float, spacing_px: float, max_points: int):
    """Boundary points and inward normals of all plan rooms, about ``spacing_px`` map cells apart."""
    res = obs.frame.resolution
    step = max(spacing_px * res / scale, pm.perimeter / max_points)
    pts, normals, _ = sample_boundaries(pm.rings, step, pm.doors, door_tol=1.5 * res / scale)
    return pts, normals


def _refine_from(
    pm: PlanModel,
    obs: MapObservation,
    init: tuple,
    opts: dict,
    *,
    scales: tuple,
    spacing_px: float,
    max_points: int,
) -> RefineResult:
    flipped, theta, sx, sy, tx, ty, delta = init
    pts, normals = _boundary_samples(pm, obs, math.sqrt(sx * sy), spacing_px, max_points)
    return refine(
        pts,
        normals,
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
        iterations=opts["iterations"],
    )


DEFAULTS: dict[str, Any] = {
    "adjacency": "doors",  # room graph for subsets: doors | touch | both
    "max_aspect": 1.6,  # bound on sy/sx (plan aspect errors up to about ±30 %)
    "top_k": 48,  # hypotheses scored by coarse IoU
    "refine_k": 3,  # distinct hypotheses refined at full resolution
    "max_subsets_per_level": 3000,
    "coarse_px": 80,
    "sample_px": 1.5,  # boundary sample spacing in map pixels (final stage)
    "max_points": 3000,
    "quick_points": 600,  # boundary samples when screening the refined hypotheses
    "iterations": 8,  # Gauss-Newton iterations per robust-scale stage
    "delta": None,  # wall half-thickness prior (m); default one map cell
    "delta_sigma": 0.1,
    "min_cover": 0.5,  # a room is matched when this share of it lies on the footprint
    "min_score": 0.6,  # below: no match (another building)
    "min_fit": 0.4,  # share of boundary points on the walls needed for a match
    "min_area_m2": 2.0,
    "seed_rooms": None,  # room ids one of which the subset must contain (the robot's room)
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
    hyps = _coarse_hypotheses(pm, obs, masks, max_aspect=opts["max_aspect"], top_k=opts["top_k"])
    if not hyps:
        return fail("no room subset fits the map's shape within the aspect bound")
    _coarse_iou(pm, obs, hyps)
    hyps.sort(key=lambda h: -h.coarse_iou)
    t_coarse = time.perf_counter()

    chosen: list[Hypothesis] = []
    for h in hyps:
        if len(chosen) >= opts["refine_k"]:
            break
        if any(_same_placement(h.matrix, c.matrix, obs) for c in chosen):
            continue
        chosen.append(h)
    delta0 = opts["delta"] if opts["delta"] is not None else obs.frame.resolution
    quick: list[float] = []
    for h in chosen:  # screen: coarse robust scales, few points, scored at the coarse resolution
        flipped, theta, sx, sy, tx, ty = params_from_matrix(h.matrix)
        h.refined = _refine_from(
            pm,
            obs,
            (flipped, theta, sx, sy, tx, ty, delta0),
            opts,
            scales=(0.4, 0.15),
            spacing_px=4.0,
            max_points=opts["quick_points"],
        )
        h.fit = h.refined.inliers
        iou, _ = _score(pm, obs.coarse_frame, obs.coarse_footprint, h.refined.matrix, opts["min_cover"])
        quick.append(iou * (0.5 + 0.5 * h.fit))
    order = np.argsort(quick)[::-1]
    best = chosen[int(order[0])]
    r0 = best.refined
    best.refined = _refine_from(
        pm,
        obs,
        (r0.flipped, r0.theta, r0.sx, r0.sy, r0.tx, r0.ty, r0.delta),
        opts,
        scales=(0.1, 0.05),
        spacing_px=opts["sample_px"],
        max_points=opts["max_points"],
    )
    best.fit = best.refined.inliers
    best.score, best.rooms = _score(pm, obs.frame, obs.footprint, best.refined.matrix, opts["min_cover"])
    key = quick[int(order[0])]
    second = max(
        (
            quick[int(i)]
            for i in order[1:]
            if not _same_placement(chosen[int(i)].refined.matrix, r0.matrix, obs)
        ),
        default=0.0,
    )
    rest = [h.coarse_iou for h in hyps if all(not _same_placement(h.matrix, c.matrix, obs) for c in chosen)]
    if rest:  # unrefined placements: their coarse IoU relative to the best's coarse IoU
        second = max(second, key * max(rest) / max(best.coarse_iou, 1e-9))
    ambiguity = float(min(1.0, second / key)) if key > 0 else 1.0
    t_fine = time.perf_counter()

    r = best.refined
    matrix = obs.to_map @ r.matrix
    cov = r.covariance
    if cov is not None and grid.origin[2] != 0.0:
        rot3 = np.eye(3)
        rot3[:2, :2] = _rot(grid.origin[2])
        cov = rot3 @ cov @ rot3.T
    details = {
        "delta_m": r.delta,
        "fit": r.inliers,
        "rms_m": r.rms,
        "n_points": r.n_points,
        "map_angle_deg": math.degrees(obs.angle),
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
            float(quick[int(i)]),
            bool(chosen[int(i)].refined.flipped),
            _wrap_deg(math.degrees(chosen[int(i)].refined.theta)),
        )
        for i in order
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
    if best.score < opts["min_score"] or best.fit < opts["min_fit"]:
        reg.ok = False
        reg.reason = (
            f"no match: best IoU {best.score:.2f} (min {opts['min_score']}), wall fit {best.fit:.2f} "
            f"(min {opts['min_fit']}); is this plan of another building?"
        )
    reg.time_s = time.perf_counter() - t0
    return reg


def _same_placement(m1: np.ndarray, m2: np.ndarray, obs: MapObservation) -> bool:
    """True when two plan -> map matrices place the plan nearly the same on the observed area."""
    if (np.linalg.det(m1[:2, :2]) > 0) != (np.linalg.det(m2[:2, :2]) > 0):
        return False
    size = math.sqrt(obs.area)
    # compare where the two place the map's footprint corners (through their inverses)
    x0, y0 = 0.0, 0.0
    h, w = obs.frame.shape
    res = obs.frame.resolution
    corners = np.array([[x0, y0, 1], [w * res, y0, 1], [x0, h * res, 1], [w * res, h * res, 1]]).T
    a = np.linalg.solve(m1, corners)
    b = np.linalg.solve(m2, corners)
    # distance in map metres after mapping b back through m1
    d = (m1 @ b - corners)[:2]
    del a
    return bool(np.max(np.hypot(d[0], d[1])) < 0.15 * size)
