"""MFR step 4, refinement: the best distinct coarse placements refined and scored.

The best ``refine_k`` distinct placements are refined coarsely and re-scored; the best is refined
at full resolution (:mod:`frslam_graph.registration.refine`: rotation, translation, two scales
along the plan's wall directions and the wall offset) and scored: the IoU of the rooms it places
on the footprint, and the wall precision and recall at the fine tolerance.

Placements are 3 × 3 matrices from plan units to the map's grid frame (metres).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from frslam_graph.registration.mfr.coarse import Hypothesis, coarse_scores, door_prior
from frslam_graph.registration.mfr.geometry import lookups
from frslam_graph.registration.mfr.map_side import MapObservation
from frslam_graph.registration.mfr.plan_side import PlanModel, fill_rooms
from frslam_graph.registration.refine import FitStart, RefineResult, refine, refine_many
from frslam_graph.registration.result import params_from_matrix
from frslam_graph.se2 import rot


def refine_from(
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
    walls: bool = False,
) -> RefineResult:
    """Refine the placement ``matrix`` (plan -> grid frame) on a subsample of the plan's boundary
    samples about ``spacing_px`` map cells apart (at most ``max_points``); ``walls``: the map's
    wall-side cells pull too (the two-sided fit, :func:`refine`'s ``map_walls``).

    The scales act along the plan's wall directions: the plan is first turned by ``-pm.angle``
    (zero for plans drawn axis-aligned); the result's matrix includes that turn.
    """
    st, pre = _fit_start(pm, obs, matrix, delta, spacing_px, max_points)
    r = refine(
        st.points,
        st.normals,
        obs.field,
        st.flipped,
        st.theta,
        st.tx,
        st.ty,
        st.sx,
        st.sy,
        delta=st.delta,
        delta_sigma=opts["delta_sigma"],
        scales=scales,
        iterations=iterations,
        fixed_delta_stages=_fixed_delta_stages(scales),
        correlation=st.correlation,
        map_walls=obs.edge_points if walls else None,
    )
    r.pre = pre
    return r


def refine_from_many(
    pm: PlanModel,
    obs: MapObservation,
    matrices: list[np.ndarray],
    deltas: list[float],
    opts: dict,
    *,
    scales: tuple,
    spacing_px: float,
    max_points: int,
    iterations: int,
) -> list[RefineResult]:
    """:func:`refine_from` (one-sided) of each placement with its wall offset, the same answers,
    the fits iterated together (:func:`refine_many`)."""
    starts = [
        _fit_start(pm, obs, m, d, spacing_px, max_points) for m, d in zip(matrices, deltas, strict=True)
    ]
    out = refine_many(
        [st for st, _ in starts],
        obs.field,
        delta_sigma=opts["delta_sigma"],
        scales=scales,
        iterations=iterations,
        fixed_delta_stages=_fixed_delta_stages(scales),
    )
    for r, (_, pre) in zip(out, starts, strict=True):
        r.pre = pre
    return out


def _fixed_delta_stages(scales: tuple) -> int:
    """The refinement's first stages that hold the wall offset: the wall offset trades against
    the scales under wide robust scales (above 0.16 m)."""
    return sum(1 for c in scales if c > 0.16)


def _fit_start(
    pm: PlanModel, obs: MapObservation, matrix: np.ndarray, delta: float, spacing_px: float, max_points: int
) -> tuple[FitStart, np.ndarray]:
    """The refinement's start from the placement ``matrix`` (see :func:`refine_from`) and the turn
    ``pre`` its parameters follow."""
    pre = np.eye(3)
    pre[:2, :2] = rot(-pm.angle)
    flipped, theta, sx, sy, tx, ty = params_from_matrix(matrix @ pre.T)
    base = pm.sample_step  # plan units between samples
    want = spacing_px * obs.frame.resolution / math.sqrt(sx * sy)
    stride = max(1, int(want / base), int(math.ceil(len(pm.samples) / max_points)))
    start = FitStart(
        pm.samples[::stride] @ pre[:2, :2].T,
        pm.sample_normals[::stride] @ pre[:2, :2].T,
        flipped,
        theta,
        tx,
        ty,
        sx,
        sy,
        delta=delta,
        # one independent wall error per 0.5 m of wall
        correlation=0.5 / max(stride * base * math.sqrt(sx * sy), 1e-9),
    )
    return start, pre


def plausible(r: RefineResult, opts: dict) -> bool:
    """Finite, non-degenerate, and the aspect within the bound."""
    m = r.matrix
    if not np.all(np.isfinite(m)) or not (r.sx > 0 and r.sy > 0):
        return False
    ratio = r.sy / r.sx
    return 1.0 / opts["max_aspect"] ** 2 <= ratio <= opts["max_aspect"] ** 2


def placed_rooms_iou(
    pm: PlanModel, obs: MapObservation, matrix: np.ndarray, min_cover: float
) -> tuple[float, tuple[int, ...]]:
    """IoU of the rooms the placement (plan -> ``obs``'s grid frame) puts on the map's footprint
    (>= ``min_cover`` of their area) with the footprint, and those rooms (indices). What it puts
    on the map's unexplored cells (``obs.unexplored``: enclosed regions the map has not observed)
    counts neither for nor against it."""
    if not np.all(np.isfinite(matrix)):
        return 0.0, ()
    det = abs(np.linalg.det(matrix[:2, :2]))
    if det <= 0:
        return 0.0, ()
    frame, footprint, unexplored = obs.frame, obs.footprint, obs.unexplored
    n = len(pm.ids)  # at most MAX_ROOMS = 64: the labels fit in uint8
    labels = fill_rooms(
        pm.room_rings, pm.room_holes, range(n), matrix, frame, labels=True, label_dtype=np.uint8
    )
    on = _label_counts(labels, footprint, n)
    px_area = pm.room_areas * det / frame.resolution**2
    # most maps have no unexplored core: no pixel there, zero counts without the histogram
    off = _label_counts(labels, unexplored, n) if obs.any_unexplored else np.zeros(n, np.int64)
    cover = on / np.maximum(px_area - off, 1e-9)
    rooms = tuple(int(i) for i in np.flatnonzero(cover >= min_cover))
    if not rooms:
        return 0.0, rooms
    # pixel counts from the per-room counts (each pixel holds one label): the placed rooms'
    # pixels on the footprint, all of them, and those on unexplored cells
    sel = np.asarray(rooms)
    lut = np.zeros(256, np.uint8)
    lut[sel + 1] = 1
    inter = int(on[sel].sum())
    union = int(cv2.countNonZero(cv2.LUT(labels, lut))) + obs.footprint_cells - inter
    union -= int(off[sel].sum())
    return (inter / union if union else 0.0), rooms


def _label_counts(labels: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
    """(n,) int64 pixel counts of the labels 1..n (uint8 image) on ``mask`` (bool, same shape):
    ``np.bincount(labels[mask])[1:]``, by cv2.calcHist (float32 counts: exact below 2^24 pixels)."""
    if labels.size >= 1 << 24:
        return np.bincount(labels[mask].ravel(), minlength=n + 1)[1 : n + 1]
    m8 = np.ascontiguousarray(mask).view(np.uint8)
    return cv2.calcHist([labels], [0], m8, [n + 1], [0, n + 1]).ravel().astype(np.int64)[1:]


def wall_precision_recall(
    pm: PlanModel,
    obs: MapObservation,
    matrix: np.ndarray,
    tol: float,
    max_points: int = 300,
    delta: float = 0.0,
) -> tuple[float, float]:
    """(precision, recall) of the room structure under a placement, within ``tol`` metres of the
    wall faces: the plan's room boundaries moved into their rooms by ``delta`` metres (the wall
    half-thickness the refinement fitted; a plan draws room boundaries at wall centres, a map
    sees wall faces, 0.06 m apart in the simulator but up to 0.2 m on thick real walls).

    precision: share of the plan's wall samples landing on the observed footprint that land near
    a wall-side free cell of the map (unobserved rooms' walls off the footprint do not count); recall: share of the map's wall-side free cells that land
    near a boundary of any plan room. A room stretched over several observed rooms explains
    the outline but not the inner walls: its recall is low.
    """
    faces = face_distances(pm, obs, matrix, max_points, delta)
    if faces is None:
        return 0.0, 0.0
    d_plan, dev, slack = faces
    precision = float(np.sum(d_plan < tol) / max(len(d_plan), 1))
    if dev is None:
        return precision, 0.0
    # a map wall cell lies |delta| from the plan's boundary (its wall face), within tol
    return precision, float(np.mean(dev < tol + slack))


def placement_test(mats: np.ndarray, obs: MapObservation):
    """A function ``same(m) -> (H,) bool``: which of the (H, 3, 3) placements ``mats`` place the
    plan nearly as ``m`` does (see :func:`coarse.same_placement`)."""
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


def choose_distinct(
    hyps: list[Hypothesis], obs: MapObservation, k: int
) -> tuple[list[Hypothesis], np.ndarray]:
    """The first ``k`` hypotheses of ``hyps`` (best first) that place the plan differently, and a
    (len(hyps),) bool mask of the hypotheses that place it as one of those."""
    chosen: list[Hypothesis] = []
    covered = np.zeros(len(hyps), bool)  # same placement as a chosen one
    same_as = placement_test(np.stack([h.matrix for h in hyps]), obs)
    for i, h in enumerate(hyps):
        if len(chosen) >= k:
            break
        if covered[i]:
            continue
        chosen.append(h)
        covered |= same_as(h.matrix)
    return chosen, covered


def screen(pm: PlanModel, obs: MapObservation, chosen: list[Hypothesis], opts: dict, tol: float) -> None:
    """Refine each of ``chosen`` cheaply (coarse robust scales, few points), set its ``refined``
    and its ``quick`` key (the coarse key of the refined placement at tolerance ``tol`` metres,
    0 for a degenerate one), and sort ``chosen`` by it, best first."""
    delta0 = float(opts["delta"])
    fits = refine_from_many(  # screen: coarse robust scales, few points, scored on the coarse grid
        pm,
        obs,
        [h.matrix for h in chosen],
        [delta0] * len(chosen),
        opts,
        scales=opts["quick_scales"],
        spacing_px=4.0,
        max_points=opts["quick_points"],
        iterations=opts["quick_iterations"],
    )
    for h, r in zip(chosen, fits, strict=True):
        h.refined = r
    mats = np.stack([h.refined.matrix for h in chosen])
    bad = ~np.all(np.isfinite(mats), axis=(1, 2))
    bad |= ~(np.abs(np.linalg.det(np.where(bad[:, None, None], np.eye(3), mats)[:, :2, :2])) > 1e-12)
    mats[bad] = np.stack([h.matrix for h in chosen])[bad]
    _, quick = coarse_scores(  # all screened placements at once, at the fine tolerance
        pm,
        obs,
        mats,
        np.array([h.mask for h in chosen], dtype=np.uint64),
        opts["door_width_m"],
        tol=tol,
        matched_cover=opts["min_cover"],
        # each at its own fitted wall offset: thick walls put the plan's boundaries (wall
        # centres) beyond the map's wall faces, and a right placement would score as a wrong one
        delta=np.array([0.0 if b else h.refined.delta for h, b in zip(chosen, bad, strict=True)]),
    )
    for h, q, b in zip(chosen, quick, bad, strict=True):
        h.quick = 0.0 if b or not np.isfinite(q) else float(q)
        if h.quick > 0.0:  # ranked by what the gate measures, not by the coarse grid's key
            h.quick, h.placed_iou, h.placed_rooms, h.recall = structure_key(pm, obs, h.refined, opts, tol)
    chosen.sort(key=lambda h: -h.quick)


def structure_key(
    pm: PlanModel, obs: MapObservation, r: RefineResult, opts: dict, tol: float
) -> tuple[float, float, int, float]:
    """The acceptance gate's measure of a refined placement: IoU of the rooms it places on the
    full-resolution footprint × wall precision × recall at its wall faces (``tol`` metres), times
    the door-width plausibility of its scale; and that IoU, the number of those rooms and that
    recall. The coarse key (80-cell footprint, boundaries at the wall centres) ranks a placement
    shifted by a wall or a room above the right one on maps with partly seen rooms and thick
    walls."""
    return _structure_key_with(pm, obs, r, opts, _wall_part(pm, obs, r, opts, tol))


def _wall_part(
    pm: PlanModel, obs: MapObservation, r: RefineResult, opts: dict, tol: float
) -> tuple[float, float, float]:
    """The factors of :func:`structure_key` but the IoU: (wall precision, recall, door-width
    plausibility)."""
    prec, rec = wall_precision_recall(pm, obs, r.matrix, tol, 1000, delta=r.delta)
    scale = math.sqrt(abs(float(np.linalg.det(r.matrix[:2, :2]))))
    return prec, rec, door_prior(pm, np.array([scale]), opts["door_width_m"])[0]


def _wall_bound(wall: tuple[float, float, float]) -> float:
    """An upper bound of :func:`structure_key` from its wall part (the IoU is at most 1): the
    same products in the same order, each rounding monotone, so never below the key."""
    prec, rec, door = wall
    return float(prec * rec * door)


def _structure_key_with(
    pm: PlanModel, obs: MapObservation, r: RefineResult, opts: dict, wall: tuple[float, float, float]
) -> tuple[float, float, int, float]:
    """:func:`structure_key` given its wall part (:func:`_wall_part`)."""
    prec, rec, door = wall
    iou, rooms = placed_rooms_iou(pm, obs, r.matrix, opts["min_cover"])
    return float(iou * prec * rec * door), float(iou), len(rooms), float(rec)


def best_bounded(bounds: list[float], value, above: float) -> tuple[int, Any] | None:
    """(i, value(i)) for the first ``i`` of the highest ``value(i)[0]`` (``np.argmax``'s choice)
    when that exceeds ``above``, else None; ``bounds[i] >= value(i)[0]`` lets it skip ``value(i)``
    where it cannot change the answer (tried highest bound first)."""
    best: tuple[float, int, Any] | None = None
    for i in sorted(range(len(bounds)), key=lambda j: (-bounds[j], j)):
        b = bounds[i]
        if not b > above or (best is not None and (b < best[0] or (b == best[0] and i > best[1]))):
            continue
        v = value(i)
        if best is None or v[0] > best[0] or (v[0] == best[0] and i < best[1]):
            best = (v[0], i, v)
    if best is None or not best[0] > above:
        return None
    return best[1], best[2]


# the joint scale steps of :func:`polish_scales`: about the refinement's basin (a start more than
# ~5 % off along an axis converges elsewhere)
POLISH_STEP = 0.05


def polish_scales(pm: PlanModel, obs: MapObservation, h: Hypothesis, opts: dict, tol: float) -> None:
    """Restart the screened placement of ``h`` with its two plan-axis scales changed jointly by
    ``POLISH_STEP`` (x (1 + s)^{-1, 0, 1} each, the plan point on the footprint's centroid kept
    in place), refine each start as :func:`screen` does, and adopt the best by
    :func:`structure_key` (tolerance ``tol`` metres) when it beats ``h.quick``.

    On maps seeing rooms in part the screening refinement stops a few per cent off in scale
    and aspect (a wall of the next room pulls one axis), and a placement shifted by a wall fits
    as well locally; the restarts reach the better basin."""
    polish_scales_many(pm, obs, [h], opts, tol)


def polish_scales_many(
    pm: PlanModel, obs: MapObservation, hs: list[Hypothesis], opts: dict, tol: float
) -> None:
    """:func:`polish_scales` of each of ``hs`` (each polished on its own: the same answers), the
    restarts of all of them refined together (:func:`refine_from_many`)."""
    todo = [h for h in hs if h.quick > 0.0 and h.refined is not None]
    if not todo:
        return
    steps = (1.0 / (1.0 + POLISH_STEP), 1.0, 1.0 + POLISH_STEP)
    moved: list[np.ndarray] = []
    deltas: list[float] = []
    for h in todo:
        m = h.refined.matrix
        p0 = np.linalg.solve(m, np.append(obs.centroid, 1.0))
        pre = h.refined.pre if h.refined.pre is not None else np.eye(3)
        about = np.eye(3)
        about[:2, 2] = p0[:2]
        for fx in steps:
            for fy in steps:
                if fx == 1.0 and fy == 1.0:
                    continue
                moved.append(m @ (about @ pre.T @ np.diag([fx, fy, 1.0]) @ pre @ np.linalg.inv(about)))
                deltas.append(h.refined.delta)
    fits = refine_from_many(
        pm,
        obs,
        moved,
        deltas,
        opts,
        scales=opts["quick_scales"],
        spacing_px=4.0,
        max_points=opts["quick_points"],
        iterations=opts["quick_iterations"],
    )
    per = len(fits) // len(todo)  # eight restarts each
    for k, h in enumerate(todo):
        starts = [rr for rr in fits[k * per : (k + 1) * per] if plausible(rr, opts)]
        if not starts:
            continue
        # ranked by the gate's measure itself: the coarse key (80-cell footprint, exits) ranked a
        # restart a wall off above one near the truth scoring it half as high. The rooms' IoU (a
        # full-resolution raster of the plan) only for restarts whose wall part could still win
        walls = [_wall_part(pm, obs, s, opts, tol) for s in starts]
        won = best_bounded(
            [_wall_bound(w) for w in walls],
            lambda i, starts=starts, walls=walls: _structure_key_with(pm, obs, starts[i], opts, walls[i]),
            h.quick,
        )
        if won is not None:
            h.refined = starts[won[0]]
            h.quick, h.placed_iou, h.placed_rooms, h.recall = won[1]


def refine_final(
    pm: PlanModel, obs: MapObservation, screened: RefineResult, opts: dict, *, walls: bool = False
) -> RefineResult:
    """The screened placement refined at full resolution (``sample_px``, ``max_points``,
    ``iterations``, robust scale 0.05 m); the screened one when that final fit is degenerate.
    ``walls``: two-sided (the map's walls pull too; see :func:`refine_from`)."""
    r = refine_from(
        pm,
        obs,
        screened.matrix,
        screened.delta,
        opts,
        scales=(0.05,),
        spacing_px=opts["sample_px"],
        max_points=opts["max_points"],
        iterations=opts["iterations"],
        walls=walls,
    )
    return r if plausible(r, opts) else screened


def face_distances(
    pm: PlanModel, obs: MapObservation, matrix: np.ndarray, max_points: int = 1000, delta: float = 0.0
) -> tuple[np.ndarray, np.ndarray | None, float] | None:
    """What :func:`wall_precision_recall` thresholds, for any tolerance: (metres from each of the
    plan's wall-face samples landing on the footprint to the nearest wall-side free cell; metres
    between each of the map's wall-side cells and the nearest plan wall face, None for a singular
    placement; the slack added to the tolerance there, one plan raster cell in metres). None
    without plan samples or map walls."""
    res = obs.frame.resolution
    pts = pm.samples
    if len(pts) == 0 or len(obs.edge_points) == 0:
        return None
    stride = max(1, len(pts) // max_points)
    pts = pts[::stride]
    a, t = matrix[:2, :2], matrix[:2, 2]
    q = pts @ a.T + t
    det = abs(float(np.linalg.det(a)))
    ainv = None if det <= 0 else np.linalg.inv(a)  # a NaN determinant: the inverse taken, as ever
    if delta and det > 0:  # normals map by A^-T: still inward
        nrm = pm.sample_normals[::stride] @ ainv
        q = q + delta * nrm / np.maximum(np.hypot(nrm[:, 0], nrm[:, 1]), 1e-12)[:, None]
    on_fp, d = lookups(((obs.footprint_u8, 0), (obs.edge_dt, 1e9)), q[:, 0], q[:, 1], res, (0.0, 0.0))
    inside = on_fp > 0
    d = d[inside]
    if ainv is None:
        return d, None, 0.0
    e = (obs.edge_points - t) @ ainv.T
    pf = pm.plan_frame
    pc = np.floor((e[:, 0] - pf.origin[0]) / pf.resolution).astype(np.intp)
    pr = np.floor((e[:, 1] - pf.origin[1]) / pf.resolution).astype(np.intp)
    hp, wp = pm.plan_dt.shape
    okp = (pc >= 0) & (pr >= 0) & (pc < wp) & (pr < hp)
    dp = np.full(len(e), np.inf, np.float32)
    dp[okp] = pm.plan_dt[pr[okp], pc[okp]] * np.float32(math.sqrt(det))
    return d, np.abs(dp - abs(delta)), pf.resolution * math.sqrt(det)
