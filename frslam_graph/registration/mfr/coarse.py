"""MFR step 3, the coarse search: IoU and wall agreement over placements of room subsets.

Every (connected room subset, dihedral case, map wall direction) gets axis scales from second
moments (the paper's eq. 7 uses bounding boxes) within the aspect bound, ranked by scale- and
aspect-invariant shape features plus an aspect and door-width tie-break; the best are scored:
key = IoU with the footprint × wall precision (plan walls on the observed area that are map
walls) × wall recall (map walls explained by plan walls) × exit agreement × door-width
plausibility, all vectorised over the hypotheses (cv2.remap lookups). A poor best fit triggers a
scale/shift search (:func:`local_search`).

The moments assume the map's footprint is the union of whole plan rooms. Real maps break that
(rooms seen in part, corridors, walls, free space outside the building) and put the moment-fitted
scales 10-40 % off, beyond the refinement's basin (about ±5 %): :func:`wide_search` then searches
each axis's scale (×0.6 to ×1.75) and shift from the best placements, scored on the rooms each
trial places on the footprint, and finally at twice the gate's tolerance.

Placements are 3 × 3 matrices from plan units to the map's grid frame (metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from frslam_graph.registration.mfr.geometry import DIHEDRAL, apply_affine, dihedral, lookup, lookups
from frslam_graph.registration.mfr.map_side import MapObservation
from frslam_graph.registration.mfr.plan_side import PlanModel
from frslam_graph.registration.refine import RefineResult
from frslam_graph.registration.subsets import SubsetGeometry, mask_matrix
from frslam_graph.se2 import rot


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
    placed_iou: float = 0.0  # IoU of the rooms the screened placement puts on the footprint
    placed_rooms: int = 0  # how many rooms it puts there
    recall: float = 1.0  # share of the map's walls the screened placement explains
    score: float = 0.0
    rooms: tuple[int, ...] = ()


def subset_geometry(pm: PlanModel, masks: np.ndarray) -> SubsetGeometry:
    """Area moments and bounding boxes of the room subsets ``masks`` (in the plan's frame turned by
    ``-pm.angle``)."""
    return SubsetGeometry.of(mask_matrix(masks, len(pm.ids)), pm.moments, pm.bounds)


def coarse_hypotheses(
    pm: PlanModel,
    obs: MapObservation,
    masks: np.ndarray,
    *,
    max_aspect: float,
    top_k: int,
    door_width_m=None,
    cases: tuple[np.ndarray, ...] | None = None,
) -> dict[str, np.ndarray]:
    """The ``top_k`` (subset, dihedral case, map wall direction) by shape-feature distance to
    the map, each with its moment-matched plan -> grid-frame matrix, as arrays: ``mask``,
    ``case`` (index in :data:`DIHEDRAL`), ``mats`` (H, 3, 3), ``cost``, ``angle`` (map direction).
    ``cases``: :func:`dihedral_cases` of their geometry when the caller has them."""
    if cases is None:
        cases = dihedral_cases(subset_geometry(pm, masks))
    parts = [
        _coarse_hypotheses_at(pm, obs, masks, cases, ai, max_aspect, top_k, door_width_m)
        for ai in range(len(obs.angles))
    ]
    pool = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(pool["cost"], kind="stable")[:top_k]
    return {k: v[order] for k, v in pool.items()}


def smallest_stable(a: np.ndarray, k: int) -> np.ndarray:
    """``np.argsort(a, kind="stable")[:k]`` of a 1-D array (ties by index, NaN last) without
    sorting all of it: the values up to the k-th smallest (np.partition), then those sorted."""
    if k <= 0:
        return np.zeros(0, np.intp)
    if len(a) <= 4 * k:
        return np.argsort(a, kind="stable")[:k]
    kth = np.partition(a, k - 1)[k - 1]
    if np.isnan(kth):  # fewer than k numbers: NaNs among the first k, as argsort orders them
        return np.argsort(a, kind="stable")[:k]
    cand = np.flatnonzero(a <= kth)  # every value before the k-th, in index order
    return cand[np.argsort(a[cand], kind="stable")[:k]]


def dihedral_cases(geo: SubsetGeometry) -> tuple[np.ndarray, ...]:
    """The subsets' shape features as each dihedral case (:data:`DIHEDRAL` order) turns them
    (8, S, 7), and their variances ``vx``, ``vy`` and centroids ``cx``, ``cy`` along the map's
    axes (8, S each): what :func:`coarse_hypotheses` compares with the map, independent of it,
    stacked by case so that it scores every case in one call of each operation."""
    out = []
    for k, flipped in DIHEDRAL:
        g = dihedral(k, flipped)  # signed permutation
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
        out.append((_features(geo.area, cx, cy, vx, vxy, vy, x0, y0, x1, y1), vx, vy, cx, cy))
    return tuple(np.stack([c[j] for c in out]) for j in range(5))


# the dihedral cases' signed permutations (:func:`dihedral`), in :data:`DIHEDRAL` order
_DIHEDRAL_MATS = np.stack([dihedral(k, f) for k, f in DIHEDRAL])


def _coarse_hypotheses_at(
    pm: PlanModel, obs: MapObservation, masks, cases, ai: int, max_aspect: float, top_k: int, door_width_m
) -> dict[str, np.ndarray]:
    """:func:`coarse_hypotheses` for map wall direction ``ai``; ``cases``: :func:`dihedral_cases`
    (every case in one call of each operation)."""
    angle = obs.angles[ai]
    rm = rot(-angle)
    mc = rm @ obs.centroid
    mcov = rm @ obs.cov @ rm.T
    bx0, by0, bx1, by1 = obs.bboxes[ai]
    fmap = _features(obs.area, mc[0], mc[1], mcov[0, 0], mcov[0, 1], mcov[1, 1], bx0, by0, bx1, by1)
    f, vx, vy, cx_all, cy_all = cases
    a_all = np.sqrt(mcov[0, 0] / vx)  # (8, S)
    b_all = np.sqrt(mcov[1, 1] / vy)
    ratio = b_all / a_all
    # shape distance; ties (every rectangle looks alike) go to plausible aspect and door width
    cost = np.sum((f - fmap) ** 2, axis=2) + 0.01 * np.log(ratio) ** 2
    cost = cost - 0.01 * np.log(np.maximum(door_prior(pm, np.sqrt(a_all * b_all), door_width_m), 1e-6))
    cost = np.where((ratio > max_aspect) | (ratio < 1.0 / max_aspect), np.inf, cost)
    costs = np.ascontiguousarray(cost.T)  # (S, 8): subset-major, as ranked
    flat = smallest_stable(costs.ravel(), top_k)
    flat = flat[np.isfinite(costs.ravel()[flat])]
    si, ji = np.divmod(flat, len(DIHEDRAL))
    a = a_all[ji, si]
    b = b_all[ji, si]
    cx = cx_all[ji, si]
    cy = cy_all[ji, si]
    gs = _DIHEDRAL_MATS[ji]  # (H, 2, 2)
    rp = rot(-pm.angle)
    rmap = rot(angle)
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


def door_prior(pm: PlanModel, scale: np.ndarray, door_width_m) -> np.ndarray:
    """Plausibility (0..1] of a scale (metres per plan unit) from the plan's median door width:
    1 while the door is ``door_width_m`` = (lo, hi) metres wide, a log-normal fall-off outside."""
    scale = np.asarray(scale, dtype=np.float64)
    if door_width_m is None or pm.door_width <= 0:
        return np.ones_like(scale)
    lo, hi = door_width_m
    w = np.log(np.maximum(scale * pm.door_width, 1e-12))
    excess = np.maximum(0.0, np.maximum(math.log(lo) - w, w - math.log(hi)))
    return np.exp(-0.5 * (excess / 0.5) ** 2)


def exit_share(d: np.ndarray, scale: np.ndarray, tol: float, plan_res: float) -> np.ndarray:
    """(H,) exit agreement of :func:`coarse_scores`: 0.5 + 0.5 x the share of the map's
    doorway-like exits (free space running into unobserved space) that land near a plan opening
    (door or open-plan boundary), from their (H, J) plan distances (plan units) to the nearest
    opening under each placement (``scale`` metres per plan unit): within ``max(tol, 0.3)``
    metres plus one plan cell (``plan_res``)."""
    near = d < (np.maximum(tol, 0.3) / scale + plan_res)[:, None]
    return 0.5 + 0.5 * (near.sum(axis=1) / near.shape[1])  # near.mean(axis=1)'s values


# OpenBLAS runs a matrix product of more multiply-adds than about twice this on every core, and
# its threads then spin for up to ~0.1 s after it: on a busy machine that made the spinning a third
# of a registration's CPU time (tools/README.md, "Registration CPU (session 14)")
ONE_THREAD_MACS = 1 << 18


def room_counts(on: np.ndarray, onehot: np.ndarray) -> np.ndarray:
    """(H, n) float32 counts per room of the points each hypothesis puts on the footprint:
    ``on`` (H, P) 0/1 (uint8), ``onehot`` (P, n) float32 room of each point. The counts are
    exact integers whatever the summation order; the product runs in blocks of hypotheses small
    enough for one BLAS thread (:data:`ONE_THREAD_MACS`)."""
    rows = max(1, ONE_THREAD_MACS // max(onehot.size, 1))
    if len(on) <= rows:
        return on.astype(np.float32) @ onehot
    out = np.empty((len(on), onehot.shape[1]), np.float32)
    for i in range(0, len(on), rows):
        np.matmul(on[i : i + rows].astype(np.float32), onehot, out=out[i : i + rows])
    return out


def rows_dot(m: np.ndarray, v: np.ndarray, block: int | None = None) -> np.ndarray:
    """``m @ v`` of an (H, n) matrix and an (n,) vector, as one product per consecutive group
    of ``block`` rows when given (each group's bits as its own product's: OpenBLAS's matrix-vector
    product sums a row differently depending on how many rows the product has)."""
    if block is None or len(m) <= block:
        return m @ v
    return np.concatenate([m[i : i + block] @ v for i in range(0, len(m), block)])


def coarse_scores(
    pm: PlanModel,
    obs: MapObservation,
    mats: np.ndarray,
    masks: np.ndarray,
    door_width_m=None,
    points: int | None = None,
    tol: float | None = None,
    matched_cover: float | None = None,
    delta: np.ndarray | None = None,
    block: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Coarse IoU and structure key of every hypothesis at once (vectorised over hypotheses).

    IoU from the plan's interior grid points landing on the coarse footprint; precision from the
    boundary samples landing near a wall-side free cell; recall from the map's wall-side free
    cells landing near a plan boundary (all at tolerance 1.5 coarse cells). ``points`` caps the
    points of each kind (a cheaper first pass); ``tol`` overrides the tolerance (metres);
    ``matched_cover`` scores the rooms placed on the footprint (at least that share of their
    area) instead of each hypothesis's subset. ``delta`` (H,) metres, each placement's fitted
    wall half-thickness (plan room boundary to the map's free-space edge): precision then tests
    the wall faces (boundary samples moved that far into their room) and recall tests map walls
    at that distance from a plan boundary, as :func:`fine.wall_precision_recall` does.
    ``block``: the hypotheses are consecutive groups of this many, each scored as if alone (the
    rooms' area sums as one product per group: a BLAS product's bits depend on its shape).
    """
    n = len(pm.ids)

    def sub(arr: np.ndarray) -> np.ndarray:
        return arr if points is None or len(arr) <= points else arr[:: int(math.ceil(len(arr) / points))]

    a, t = mats[:, :2, :2], mats[:, :2, 2]
    det = np.abs(np.linalg.det(a))
    cf = obs.coarse_frame
    tol = 1.5 * cf.resolution if tol is None else tol
    # IoU
    inner, inner_onehot = sub(pm.inner), sub(pm.inner_onehot)
    x, y = apply_affine(a, t, inner)
    on = lookup(obs.coarse_footprint_u8, x, y, cf.resolution, (0.0, 0.0), 0)
    # points per room: the plan model's own sum when all points count (a plan constant)
    counts = pm.inner_counts if inner_onehot is pm.inner_onehot else inner_onehot.sum(axis=0)
    frac = room_counts(on, inner_onehot) / np.maximum(counts, 1.0)  # (H, n)
    if matched_cover is not None:  # the rooms the placement puts on the footprint, not the subset
        member = (frac >= matched_cover).astype(np.float64)
    else:
        member = mask_matrix(np.asarray(masks, dtype=np.uint64), n).astype(np.float64)  # (H, n)
    inter = rows_dot(frac * member, pm.room_areas, block) * det
    area_s = rows_dot(member, pm.room_areas, block) * det
    iou = np.clip(inter / np.maximum(area_s + obs.area - inter, 1e-12), 0.0, 1.0)
    # precision: plan walls that land on the observed area must be walls of the map
    samples = sub(pm.coarse_samples)
    x, y = apply_affine(a, t, samples)
    ainv = np.linalg.inv(a)
    if delta is not None:  # the wall faces: normals map by A^-T (perpendicular, still inward)
        nx, ny = apply_affine(np.transpose(ainv, (0, 2, 1)), np.zeros((len(a), 2)), sub(pm.coarse_normals))
        step = np.asarray(delta, dtype=np.float32)[:, None] / np.maximum(np.hypot(nx, ny), 1e-12)
        x, y = x + step * nx, y + step * ny
    res = obs.frame.resolution
    on_fp, d_edge = lookups(((obs.footprint_u8, 0), (obs.edge_dt, 1e9)), x, y, res, (0.0, 0.0))
    inside = on_fp > 0
    near = (d_edge < tol) & inside
    precision = near.sum(axis=1) / np.maximum(inside.sum(axis=1), 1)
    # recall; the map's exits go into the plan frame with its wall cells (one transform and one
    # set of cell coordinates: the same element operations, point by point)
    tinv = -np.einsum("hij,hj->hi", ainv, t)
    edges, exit_pts = sub(obs.edge_points), sub(obs.exit_points)
    pf = pm.plan_frame
    with_exits = pm.open_dt is not None and len(exit_pts) > 0
    x, y = apply_affine(ainv, tinv, np.concatenate([edges, exit_pts]) if with_exits else edges)
    if with_exits:
        dp, d_exit = lookups(((pm.plan_dt, 1e9), (pm.open_dt, 1e9)), x, y, pf.resolution, pf.origin)
        dp, d_exit = dp[:, : len(edges)], d_exit[:, len(edges) :]
    else:
        dp = lookup(pm.plan_dt, x, y, pf.resolution, pf.origin, 1e9)
    tol_plan = tol / np.sqrt(det) + pf.resolution
    if delta is not None:  # map walls at the wall faces, |delta| from the plan's boundaries
        dp = np.abs(dp - (np.abs(np.asarray(delta, dtype=np.float64)) / np.sqrt(det))[:, None])
    # np.mean's value: the count of a bool row is exact in float64, then divided by the length
    recall = (dp < tol_plan[:, None]).sum(axis=1) / dp.shape[1] if len(edges) else np.zeros(len(mats))
    exits = exit_share(d_exit, np.sqrt(det), tol, pf.resolution) if with_exits else np.ones(len(mats))
    key = iou * precision * recall * exits * door_prior(pm, np.sqrt(det), door_width_m)
    return iou, key


def same_placement(m1: np.ndarray, m2: np.ndarray, obs: MapObservation, within: float | None = None) -> bool:
    """True when two plan -> map matrices place the plan nearly the same on the observed area:
    the same handedness and the observed area's corners moved by less than ``within`` metres
    (default 15 % of its size)."""
    if (np.linalg.det(m1[:2, :2]) > 0) != (np.linalg.det(m2[:2, :2]) > 0):
        return False
    h, w = obs.frame.shape
    res = obs.frame.resolution
    corners = np.array([[0.0, w * res, 0.0, w * res], [0.0, 0.0, h * res, h * res], [1.0, 1.0, 1.0, 1.0]])
    d = (m1 @ np.linalg.solve(m2, corners) - corners)[:2]
    return bool(np.max(np.hypot(d[0], d[1])) < (0.15 * math.sqrt(obs.area) if within is None else within))


def _placed_mask(pm: PlanModel, obs: MapObservation, matrix: np.ndarray, min_cover: float) -> int:
    """Bit mask of the rooms the placement ``matrix`` puts on the coarse footprint (at least
    ``min_cover`` of each room's interior grid points)."""
    x, y = apply_affine(matrix[None, :2, :2], matrix[None, :2, 2], pm.inner)
    on = lookup(obs.coarse_footprint_u8, x, y, obs.coarse_frame.resolution, (0.0, 0.0), 0)
    frac = (on.astype(np.float32) @ pm.inner_onehot)[0] / np.maximum(pm.inner_counts, 1.0)
    return sum(1 << int(i) for i in np.flatnonzero(frac >= min_cover))


def _score_hypotheses(pm: PlanModel, obs: MapObservation, hyps: list[Hypothesis], door_width_m=None) -> None:
    """:func:`coarse_scores` for a list of hypotheses (sets ``coarse_iou`` and ``key``)."""
    iou, key = coarse_scores(
        pm,
        obs,
        np.stack([h.matrix for h in hyps]),
        np.array([h.mask for h in hyps], dtype=np.uint64),
        door_width_m,
    )
    for h, i_, k_ in zip(hyps, iou, key, strict=True):
        h.coarse_iou = float(i_)
        h.key = float(k_)


def local_search(pm: PlanModel, obs: MapObservation, hyps: list[Hypothesis], opts: dict) -> None:
    """Coordinate search on the coarse key over each map axis's scale and shift (about the
    footprint's centroid, in the map's wall-aligned frame), two rounds, for each hypothesis.

    The hypotheses' searches are independent: each step scores every hypothesis's trials in one
    :func:`coarse_scores` call (``block``: each hypothesis's 15 as if alone, the same bits)."""
    rounds = (((0.85, 0.92, 1.0, 1.08, 1.17), 0.08), ((0.96, 0.98, 1.0, 1.02, 1.04), 0.03))
    frames = []
    for h in hyps:
        angle, bbox = obs.angles[h.angle_index], obs.bboxes[h.angle_index]
        rm = np.eye(3)
        rm[:2, :2] = rot(angle)
        frames.append((rm, rot(-angle) @ obs.centroid, bbox[2:] - bbox[:2]))
    masks = np.array([h.mask for h in hyps], dtype=np.uint64)
    for factors, shift in rounds:
        for axis in (0, 1):
            # every (factor, shift) at once: the same products, matrix by matrix
            f = np.repeat(np.array(factors), 3)
            sh = np.tile(np.array([-shift, 0.0, shift]), len(factors))
            trials = []
            for h, (rm, c, ext) in zip(hyps, frames, strict=True):
                d = np.broadcast_to(np.eye(3), (len(f), 3, 3)).copy()
                d[:, axis, axis] = f
                d[:, axis, 2] = c[axis] * (1.0 - f) + sh * ext[axis]
                trials.append(rm @ d @ rm.T @ h.matrix)
            mats = np.concatenate(trials)
            iou, key = coarse_scores(
                pm, obs, mats, np.repeat(masks, len(f)), opts["door_width_m"], block=len(f)
            )
            for j, h in enumerate(hyps):
                lo = j * len(f)
                top = lo + int(np.argmax(key[lo : lo + len(f)]))  # max()'s choice: the first of equal keys
                if float(key[top]) > h.key:
                    h.matrix, h.key, h.coarse_iou = mats[top], float(key[top]), float(iou[top])


def search(
    pm: PlanModel,
    obs: MapObservation,
    masks: np.ndarray,
    opts: dict,
    cases: tuple[np.ndarray, ...] | None = None,
) -> tuple[list[Hypothesis], list[Hypothesis]]:
    """The coarse step: hypotheses for the room subsets ``masks``, best ``key`` first (empty when
    no subset fits the map's shape within the aspect bound), and the seeds of
    :func:`wide_search`: the best hypothesis of each (dihedral case, map wall direction), best first.

    The best ``pool_k`` by shape features, the best ``top_k`` of those by the key on
    ``first_pass_points`` points, then all of those on every point; a best IoU below
    ``search_below_iou`` triggers :func:`local_search` on the two best. ``cases``:
    :func:`dihedral_cases` of ``masks`` when the caller has them.
    """
    pool = coarse_hypotheses(
        pm,
        obs,
        masks,
        max_aspect=opts["max_aspect"],
        top_k=opts["pool_k"],
        door_width_m=opts["door_width_m"],
        cases=cases,
    )
    if len(pool["mask"]) == 0:
        return [], []
    first_pass = len(pool["mask"]) > opts["top_k"]
    iou, key = coarse_scores(  # a cheap first pass on a few points of each kind when many
        pm,
        obs,
        pool["mats"],
        pool["mask"],
        opts["door_width_m"],
        points=opts["first_pass_points"] if first_pass else None,
    )
    # the best of each (dihedral case, wall direction) in the whole pool: a rotation whose
    # moment-fitted scales are far off ranks low on the key, but a wide search can still reach it
    order = np.argsort(-key, kind="stable")
    group = (pool["case"] * len(obs.angles) + pool["angle"])[order]
    _, at = np.unique(group, return_index=True)
    seeds = [
        Hypothesis(
            int(pool["mask"][i]),
            *DIHEDRAL[pool["case"][i]],
            pool["mats"][i],
            float(pool["cost"][i]),
            int(pool["angle"][i]),
            key=float(key[i]),
        )
        for i in order[np.sort(at)]
    ]
    if first_pass:
        keep = np.argsort(-key, kind="stable")[: opts["top_k"]]
        pool = {k: v[keep] for k, v in pool.items()}
        iou, key = coarse_scores(pm, obs, pool["mats"], pool["mask"], opts["door_width_m"])
    hyps = [
        Hypothesis(int(m), DIHEDRAL[c][0], DIHEDRAL[c][1], mat, float(cost), int(ai), float(i), key=float(k))
        for m, c, mat, cost, ai, i, k in zip(  # Python numbers from tolist: the same values
            pool["mask"].tolist(),
            pool["case"].tolist(),
            pool["mats"],
            pool["cost"].tolist(),
            pool["angle"].tolist(),
            iou.tolist(),
            key.tolist(),
            strict=True,
        )
    ]
    hyps.sort(key=lambda h: -h.key)
    if hyps[0].coarse_iou < opts["search_below_iou"]:
        # the map holds area the plan lacks (or the reverse): the moment fit is off; search
        local_search(pm, obs, hyps[:2], opts)
        hyps.sort(key=lambda h: -h.key)
    return hyps, seeds


def turned_seeds(seed: Hypothesis, obs: MapObservation, about: np.ndarray | None = None) -> list[Hypothesis]:
    """The other 7 dihedral turns of ``seed``'s placement about the footprint's centroid (or the
    grid-frame point ``about``, metres), in the wall-aligned map frame of its wall direction: the
    same plan scales (metres per plan unit along the plan's axes), another flip and rotation. The
    moment fit of a (dihedral case, wall direction) assumes the footprint is a union of whole plan
    rooms; on a map seeing corridors and parts of rooms its scales are 20-40 % off, or the case
    has no hypothesis at all, and the wide search does not reach the truth from it: the best
    placement's scales are closer."""
    rm = rot(obs.angles[seed.angle_index])
    c = obs.centroid if about is None else np.asarray(about, dtype=np.float64)
    out = []
    for k, flipped in DIHEDRAL[1:]:
        d = np.eye(3)
        d[:2, :2] = rm @ dihedral(k, flipped) @ rm.T
        d[:2, 2] = c - d[:2, :2] @ c
        out.append(Hypothesis(seed.mask, k, flipped, d @ seed.matrix, 0.0, seed.angle_index))
    return out


# the wide search: per map axis, scale factors x shifts (fractions of the footprint's extent)
WIDE_FACTORS = np.exp(np.linspace(math.log(0.6), math.log(1.75), 15))  # ~7.6 % apart
WIDE_SHIFTS = np.linspace(-0.25, 0.25, 13)
WIDE_AXES = (0, 1, 0)  # x, y, x again (the first x search ran with the y scale still off)
WIDE_BEAM = 2  # distinct placements kept per round and per seed
# polishing stages: (factor half-range, factors, shift half-range, shifts, tolerance / the gate's;
# None: the coarse one), the first on ``first_pass_points``, the last on ``last_points``
WIDE_POLISH = ((1.11, 9, 0.04, 7, None), (1.05, 9, 0.015, 7, 2.0))


def _axis_trials(mat: np.ndarray, rm: np.ndarray, c: np.ndarray, ext: np.ndarray, axis: int, factors, shifts):
    """(F·S, 3, 3) placements: ``mat`` scaled along one axis of the wall-aligned map frame
    (``rm`` turns it to the grid frame) about the footprint's centroid ``c`` by each factor,
    and shifted by each fraction of the footprint's extent ``ext`` (metres) along it."""
    f, sh = np.meshgrid(factors, shifts, indexing="ij")
    f, t = f.ravel(), c[axis] * (1.0 - f.ravel()) + sh.ravel() * ext[axis]
    q = rm.T @ mat  # the placement in the wall-aligned frame: only its row ``axis`` changes
    out = np.broadcast_to(q, (len(f), 3, 3)).copy()
    out[:, axis, :] = f[:, None] * q[axis] + t[:, None] * q[2]
    return rm[None] @ out


def _aspect_ok(pm: PlanModel, mats: np.ndarray, max_aspect: float) -> np.ndarray:
    """(H,) the scales along the plan's wall directions within the aspect bound."""
    axes = rot(pm.angle)  # columns: the plan's wall directions
    cols = np.linalg.norm(mats[:, :2, :2] @ axes[None], axis=1)  # (H, 2)
    ratio = cols[:, 1] / np.maximum(cols[:, 0], 1e-12)
    return (ratio <= max_aspect) & (ratio >= 1.0 / max_aspect)


def _top_cells(key: np.ndarray, shape: tuple[int, int], n: int, radius: int = 2) -> list[int]:
    """Flat indices of up to ``n`` local bests of ``key`` on the (factor, shift) grid ``shape``,
    each at least ``radius`` + 1 cells from the others (non-maximum suppression)."""
    grid = key.reshape(shape).copy()
    out = []
    for _ in range(n):
        i = int(np.argmax(grid))
        if not grid.flat[i] > 0.0:
            break
        out.append(i)
        a, b = np.unravel_index(i, shape)
        grid[max(0, a - radius) : a + radius + 1, max(0, b - radius) : b + radius + 1] = -np.inf
    return out


def _aligned_frame(obs: MapObservation, angle_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3x3 turn from the wall-aligned map frame of wall direction ``angle_index`` to the grid
    frame, the footprint's centroid and its extent (metres) in the wall-aligned frame)."""
    angle, bbox = obs.angles[angle_index], obs.bboxes[angle_index]
    rm = np.eye(3)
    rm[:2, :2] = rot(angle)
    return rm, rot(-angle) @ obs.centroid, bbox[2:] - bbox[:2]


def wide_search(
    pm: PlanModel,
    obs: MapObservation,
    seeds: list[Hypothesis],
    opts: dict,
    tol: float,
    limit: int,
    check: bool = False,
    polish_best: int | None = None,
) -> list[Hypothesis]:
    """Placements found by searching each seed's scale and shift along each wall-aligned map axis
    over a wide grid (x0.6 to x1.75, +-25 % of the footprint's extent), for maps whose footprint
    is not a union of whole plan rooms (rooms partly seen, corridors, walls, space outside the
    building), where the moment-fitted scales are 10-40 % off and the refinement's basin
    (about +-5 %) does not reach the truth.

    Per seed: a beam of ``WIDE_BEAM`` distinct placements through the axis rounds ``WIDE_AXES`` on
    the coarse key of the rooms each trial places on the footprint (``first_pass_points``), then
    the ``WIDE_POLISH`` rounds, the last on all points at twice the gate's tolerance ``tol``
    (metres): that one tells a right placement from one stretched by a room. ``check``: a cheaper
    check of an already refined placement (a beam of one, x and y once, shifts +-12.5 %, no
    polish when the grid's best is the placement itself, the last polish on ``quick_points``).
    ``polish_best``: polish only that many of all seeds' beams, best grid key first (many seeds).
    Returns up to ``limit`` distinct hypotheses, best first, each with its coarse key (default
    tolerance) as ``key``. The seeds' searches and the beams' polish are independent: each round
    scores all of them in one :func:`coarse_scores` call (``block``: each group as if alone).
    """
    door, cover, points = opts["door_width_m"], opts["min_cover"], opts["first_pass_points"]
    full = np.uint64((1 << len(pm.ids)) - 1) if len(pm.ids) < 64 else np.uint64(2**64 - 1)

    def score(mats: np.ndarray, pts, tl=None, block: int | None = None) -> np.ndarray:
        # ``block``: consecutive groups scored as if alone (every seed's or beam's at once)
        _, k = coarse_scores(
            pm, obs, mats, np.full(len(mats), full), door, pts, tl, matched_cover=cover, block=block
        )
        return np.where(_aspect_ok(pm, mats, opts["max_aspect"]), k, 0.0)

    width = 1 if check else WIDE_BEAM
    shifts = WIDE_SHIFTS[3:-3] if check else WIDE_SHIFTS  # a refined placement: +-12.5 %
    last_points = opts["quick_points"] if check else None
    if not seeds:
        return []
    grid = (len(WIDE_FACTORS), len(shifts))
    frames = [_aligned_frame(obs, seed.angle_index) for seed in seeds]
    beams: list[tuple[float, np.ndarray, int]] = []
    # the seeds' grid searches are independent: each round scores every seed's beam at once
    k0 = score(np.stack([seed.matrix for seed in seeds]), points, block=1)
    seed_beams = [[(float(k0[si]), seed.matrix)] for si, seed in enumerate(seeds)]
    for axis in WIDE_AXES[:2] if check else WIDE_AXES:
        trials = [
            (si, _axis_trials(m, *frames[si], axis, WIDE_FACTORS, shifts))
            for si, beam in enumerate(seed_beams)
            for _, m in beam
        ]
        n = grid[0] * grid[1]
        k_all = score(np.concatenate([t for _, t in trials]), points, block=n)
        grown = [list(beam) for beam in seed_beams]
        for j, (si, mats) in enumerate(trials):
            k = k_all[j * n : (j + 1) * n]
            grown[si] += [(float(k[i]), mats[i]) for i in _top_cells(k, grid, width)]
        for si, g in enumerate(grown):
            g.sort(key=lambda t: -t[0])
            beam = []
            for k_, m in g:
                if not any(same_placement(m, b, obs) for _, b in beam):
                    beam.append((k_, m))
                if len(beam) >= width:
                    break
            seed_beams[si] = beam
    for si, (seed, beam) in enumerate(zip(seeds, seed_beams, strict=True)):
        if check and np.allclose(beam[0][1], seed.matrix):
            continue  # no other scale or shift on the grid scores better: nothing to polish
        beams.extend((k_, m, si) for k_, m in beam)
    if polish_best is not None:  # only the best placements of all seeds' grids are polished
        beams = sorted(beams, key=lambda t: -t[0])[:polish_best]
    if not beams:
        return []
    ms = [m for _, m, _ in beams]
    for stage, (half, nf, shift, ns, tmul) in enumerate(WIDE_POLISH):
        factors = np.exp(np.linspace(-math.log(half), math.log(half), nf))
        pts = last_points if stage == len(WIDE_POLISH) - 1 else points
        tl = None if tmul is None else tmul * tol
        for axis in (0, 1):
            trials = [
                np.concatenate(
                    [m[None], _axis_trials(m, *frames[si], axis, factors, np.linspace(-shift, shift, ns))]
                )
                for m, (_, _, si) in zip(ms, beams, strict=True)
            ]
            n = len(trials[0])
            k_all = score(np.concatenate(trials), pts, tl, block=n)
            ms = [mats[int(np.argmax(k_all[j * n : (j + 1) * n]))] for j, mats in enumerate(trials)]
    k_last = score(np.stack(ms), last_points, WIDE_POLISH[-1][4] * tol, block=1)
    found = [(float(k_last[j]), m, si) for j, (m, (_, _, si)) in enumerate(zip(ms, beams, strict=True))]
    found.sort(key=lambda t: -t[0])
    out: list[Hypothesis] = []
    for k_, m, si in found:
        if k_ <= 0.0 or any(same_placement(m, h.matrix, obs) for h in out):
            continue
        iou, key = coarse_scores(pm, obs, m[None], np.array([full]), door, matched_cover=cover)
        out.append(
            Hypothesis(
                _placed_mask(pm, obs, m, cover),
                0,
                False,
                m,
                0.0,
                seeds[si].angle_index,
                coarse_iou=float(iou[0]),
                key=float(key[0]),
            )
        )
        if len(out) >= limit:
            break
    return out
