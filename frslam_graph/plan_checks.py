"""Checks and fits of a registered floor plan against the SLAM map and the keyframe scans.

Frames and units: the registered plan is in ``map`` (metres) through its plan -> map matrix; an
occupancy grid is the LiDAR map of the keyframes at their current estimates (``map``); scans are
points (M, 2) in base_link with poses (x, y, theta) in ``map``. Used by
:mod:`frslam_graph.plan_updates.updater` to judge a registration (how much of the map the plan's walls
explain, whether its walls cross space the map has seen free, how far two registrations
disagree) and to refine the plan's scale on the scans.
"""

from __future__ import annotations

import numpy as np

from frslam_graph.localisation.relocalisation import IGNORED, Relocaliser, tukey_weights


def occupied_points(grid, max_points: int = 4000) -> np.ndarray:
    """Centres (N, 2) of occupied cells of an OccupancyGrid, evenly subsampled."""
    rows, cols = np.nonzero(grid.occupied_mask())
    if not len(rows):
        return np.zeros((0, 2))
    if len(rows) > max_points:
        k = np.linspace(0, len(rows) - 1, max_points).round().astype(np.intp)
        rows, cols = rows[k], cols[k]
    return grid.cell_to_world(np.column_stack((cols, rows)).astype(np.float64) + 0.5)


def plan_seen(plan_map, grid) -> float:
    """Share (0..1) of the registered plan's room area (``plan_map``: FloorPlan in map metres)
    that the map has observed (free or occupied cells of ``grid``): how much of the building the
    robot had seen, e.g. when the registration was accepted."""
    import shapely

    rooms = shapely.union_all([r.polygon for r in plan_map.rooms]) if plan_map.rooms else None
    if rooms is None or rooms.is_empty or rooms.area <= 0.0:
        return 0.0
    rows, cols = np.nonzero(grid.free_mask() | grid.occupied_mask())
    if not len(rows):
        return 0.0
    xy = grid.cell_to_world(np.column_stack((cols, rows)).astype(np.float64) + 0.5)
    inside = int(np.count_nonzero(shapely.contains_xy(rooms, xy[:, 0], xy[:, 1])))
    return float(min(1.0, inside * grid.resolution**2 / rooms.area))


def walls_through_free_space(relocaliser: Relocaliser, grid, margin: float = 0.2) -> float:
    """Share of the plan's interior walls, where the map has observed them, that the map has
    seen *through*: every cell along the wall normal within ``2 * wall_offset + margin`` metres
    of the wall pixel is free. Near 0 for a right registration, even on a map drifted by less
    than ``margin`` (the displaced real wall is occupied, or the space behind it unknown, within
    reach); a wrong registration draws walls across rooms seen empty."""
    walls = _wall_pixels(relocaliser, grid, margin)
    if walls is None:
        return 0.0
    _, _, observed, through, _ = walls
    return int(through.sum()) / max(int(observed.sum()), 1)


#: m; side of the tiles that cut the plan's interior walls into pieces for the per-piece check
#: (:func:`wall_pieces_seen_through`); about a door's width: finer than a room, coarser than the
#: drawing error (0.5-1 m on the IPA plans)
WALL_PIECE_M = 1.0


def wall_pieces_seen_through(
    relocaliser: Relocaliser, grid, margin: float, max_share: float
) -> tuple[np.ndarray, float, float]:
    """The plan's interior walls cut into pieces (the wall pixels of :func:`walls_through_free_space`
    in one ``WALL_PIECE_M`` tile with one of four normal directions): a piece the map has seen
    through on more than ``max_share`` of its observed pixels disagrees with the building (a wall
    drawn where it has a corridor, a door the plan does not draw, a block drawn narrower).
    Returns (the pixels of the disagreeing pieces (K, 2) in map metres, their share of the
    observed wall pixels, the share of the other pieces' observed pixels seen through)."""
    walls = _wall_pixels(relocaliser, grid, margin)
    if walls is None:
        return np.zeros((0, 2)), 0.0, 0.0
    xy, normal, observed, through, _ = walls
    tile = np.floor(xy / WALL_PIECE_M).astype(np.int64)
    # a wall's normal up to its sign, in four bins of 45 deg: the walls meeting at a corner differ
    angle = np.mod(np.arctan2(normal[:, 1], normal[:, 0]), np.pi)
    direction = np.minimum((angle / (np.pi / 4)).astype(np.int64), 3)
    _, piece = np.unique(np.column_stack((tile, direction)), axis=0, return_inverse=True)
    piece = piece.reshape(-1)
    seen = np.bincount(piece, weights=observed)
    thr = np.bincount(piece, weights=through & observed)
    bad = thr > max_share * seen  # never true for a piece the map has not observed
    drop = bad[piece]
    n_obs = max(float(observed.sum()), 1.0)
    dropped = float((observed & drop).sum()) / n_obs
    kept = observed & ~drop
    rest = float((through & kept).sum()) / max(float(kept.sum()), 1.0)
    return xy[drop], dropped, rest


def ignoring_pieces(relocaliser: Relocaliser, pts: np.ndarray, margin: float) -> Relocaliser:
    """``relocaliser`` ignoring the wall pieces at ``pts`` (map metres, from
    :func:`wall_pieces_seen_through` at free-space ``margin`` metres) over the band that test
    looked in, at least the matcher's reach (:meth:`Relocaliser.ignoring`)."""
    radius = max(2.0 * relocaliser.field.wall_offset + margin, relocaliser.params.truncation)
    return relocaliser.ignoring(pts, radius)


def rooms_seen_through(relocaliser: Relocaliser, grid, margin: float = 0.2) -> dict[str, tuple[int, int]]:
    """Per room of the registered plan (``relocaliser.plan``, map metres): (its interior wall
    pixels the map has observed, those the map has seen through), as
    :func:`walls_through_free_space` counts them; a wall pixel counts for both rooms it
    separates (the rooms found at its place, ``2 * wall_offset`` + a cell in front of it and a
    cell beyond the wall's far face along its normal). A room drawn where the building has open space (a corridor through a block the
    plan draws closed) has most of its walls seen through; its neighbours only the shared part."""
    from frslam_graph.raster import rasterise_polygons

    plan = relocaliser.plan
    walls = _wall_pixels(relocaliser, grid, margin)
    out = {r.id: (0, 0) for r in plan.rooms}
    if walls is None or not plan.rooms:
        return out
    xy, normal, observed, through, thick = walls
    f = relocaliser.field
    labels = rasterise_polygons(
        [r.polygon for r in plan.rooms], f.frame, values=list(range(1, len(plan.rooms) + 1))
    )
    h, w = labels.shape
    reach = 2.0 * f.wall_offset + f.frame.resolution
    n = len(plan.rooms)
    hit = np.zeros((len(xy), n + 1), bool)
    for s in (-(thick + f.frame.resolution), np.zeros(len(xy)), np.full(len(xy), reach)):
        c = np.floor(f.frame.to_pixel(xy + s[:, None] * normal)).astype(np.intp)
        col, row = c[:, 0], c[:, 1]
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        lab = np.zeros(len(xy), np.intp)
        lab[ok] = labels[row[ok], col[ok]]
        hit[np.arange(len(xy)), lab] = True
    hit = hit[:, 1:]
    obs_n = (hit & observed[:, None]).sum(axis=0)
    thr_n = (hit & (through & observed)[:, None]).sum(axis=0)
    return {r.id: (int(obs_n[i]), int(thr_n[i])) for i, r in enumerate(plan.rooms)}


#: m; the thickest interior wall a plan draws (IPA drawings: 0.2-0.4 m at their scale): a wall
#: face with another room within this behind it is an interior wall, tested across its thickness
MAX_WALL_THICKNESS_M = 0.5


def _wall_pixels(relocaliser: Relocaliser, grid, margin: float):
    """The interior wall pixels of :func:`walls_through_free_space`: (centres (N, 2) in map
    metres, unit normals (N, 2) out of the wall, observed by the map (N,), seen through (N,),
    the wall's thickness there (N,) in metres); None without any. A pixel is on a wall face (the one-pixel band of the field inside a wall,
    next to a room's free space) with another room's free space at most ``MAX_WALL_THICKNESS_M``
    + ``2 * wall_offset`` behind it along the normal: outer walls (with outside behind them, where
    the map may see through windows and doors) are not. Seen through: every map cell from
    ``2 * wall_offset + margin`` in front of the face to ``margin`` behind the opposite face is
    free. A plan drawing its walls thick (an image plan, a wall 0.3 m between rooms) is tested on
    all of them, not only on its thin ones (before: the walls thinner than about 0.2 m, on the
    Intel plan 0.5-4.5 m of wall, so the share seen through jumped between 0.2 and 0.7 on maps
    a few metres apart)."""
    f = relocaliser.field
    res = f.frame.resolution
    sdf = f.sdf
    rows, cols = np.nonzero((sdf <= 0) & (sdf > -1.5 * res))
    if not len(rows):
        return None
    grad = f.data[rows, cols, 1:].astype(np.float64)
    norm = np.hypot(grad[:, 0], grad[:, 1])
    keep = norm > 0.5  # the distance field's gradient is a unit normal off ridges
    rows, cols, normal = rows[keep], cols[keep], grad[keep] / norm[keep, None]
    xy = f.frame.to_world(np.column_stack((cols + 0.5, rows + 0.5)))
    # the wall's thickness: the first free-space sample behind the face (another room)
    depth = np.arange(res, MAX_WALL_THICKNESS_M + 2.0 * f.wall_offset + 1e-9, res)
    thick = np.full(len(xy), np.nan)
    todo = np.arange(len(xy))
    for d in depth:  # nearest first; only the pixels with no room behind them yet
        behind = f.lookup(xy[todo] - d * normal[todo], -1.0)[:, 0]
        hit = (behind > 0) & (behind < 0.5 * IGNORED)  # a room, not the surroundings of an ignored piece
        thick[todo[hit]] = d
        todo = todo[~hit]
    inner = np.isfinite(thick)
    if not inner.any():
        return None
    xy, normal, thick = xy[inner], normal[inner], thick[inner]
    if len(xy) > 20000:
        k = np.linspace(0, len(xy) - 1, 20000).round().astype(np.intp)
        xy, normal, thick = xy[k], normal[k], thick[k]
    front = 2.0 * f.wall_offset + margin
    free = grid.free_mask()
    known = free | grid.occupied_mask()
    h, w = grid.shape

    def sample(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
        cr = np.floor(grid.world_to_cell(pts)).astype(np.intp)
        ok = (cr[:, 0] >= 0) & (cr[:, 0] < w) & (cr[:, 1] >= 0) & (cr[:, 1] < h)
        out = np.zeros(len(pts), bool)
        out[ok] = mask[cr[ok, 1], cr[ok, 0]]
        return out

    observed = sample(known, xy)
    # every cell across the wall is free: no real wall (occupied) or unseen space (unknown)
    # anywhere near, the robot has seen straight through this plan wall
    n_steps = int(
        np.ceil((front + MAX_WALL_THICKNESS_M + 2.0 * f.wall_offset + margin) / (0.5 * grid.resolution))
    )
    span = front + thick + margin
    todo = np.arange(len(xy))
    for t in np.linspace(0.0, 1.0, n_steps + 1):  # along the normal; stop at the first cell not free
        offs = front - t * span[todo]
        todo = todo[sample(free, xy[todo] + offs[:, None] * normal[todo])]
    through = np.zeros(len(xy), bool)
    through[todo] = True
    return xy, normal, observed, through, thick


def fit_plan_scale(field, pts, poses, lin, t, centre, truncation, sigma, iterations: int = 15) -> np.ndarray:
    """Log scale factors (plan x, plan y, about ``centre`` in plan units) of the plan whose
    distance field is ``field`` (plan -> map: ``lin`` @ xy + ``t``) that best fit the scans
    ``pts`` (list of (Ni, 2) in base_link) with their poses ``poses`` (n, 3) refined jointly.

    A map point w fits the rescaled plan where its image q = lin (centre + (u / f)) + t, with
    u = lin⁻¹ (w - t) - centre, fits the accepted one. Levenberg-Marquardt on (poses, log f) with
    a Tukey kernel and a zero-mean prior of ``sigma`` on log f (weakly observed scales stay).
    Each point's Jacobian touches only its scan's pose and the two scales, so the normal
    equations are summed per scan (5 × 5 blocks) rather than from a dense (points × 3n+2) matrix.
    """
    keep = [k for k, q in enumerate(pts) if len(q)]
    pts = [pts[k] for k in keep]
    n = len(pts)
    counts = np.array([len(q) for q in pts])
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    sid = np.repeat(np.arange(n), counts)
    xy = np.vstack(pts)
    poses = np.asarray(poses, float)[keep].copy()
    log_s = np.zeros(2)
    lin_inv = np.linalg.inv(lin)
    pidx = 3 * np.arange(n)[:, None] + np.arange(3)[None, :]  # (n, 3) pose columns of each scan
    sidx = np.array([3 * n, 3 * n + 1])

    def residuals(poses, log_s):
        c, s = np.cos(poses[sid, 2]), np.sin(poses[sid, 2])
        w = np.column_stack((c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1])) + poses[sid, :2]
        u = (w - t) @ lin_inv.T - centre
        inv_f = np.exp(-log_s)
        q = (centre + u * inv_f) @ lin.T + t
        look = field.lookup(q, outside=-truncation)
        r, g = look[:, 0], look[:, 1:]
        ga = g @ (lin @ np.diag(inv_f) @ lin_inv)  # dr/dw
        dx, dy = w[:, 0] - poses[sid, 0], w[:, 1] - poses[sid, 1]
        j = np.column_stack(  # per point: d r / d (x, y, theta of its scan, log f_x, log f_y)
            (
                ga[:, 0],
                ga[:, 1],
                -ga[:, 0] * dy + ga[:, 1] * dx,
                -(g @ lin[:, 0]) * u[:, 0] * inv_f[0],
                -(g @ lin[:, 1]) * u[:, 1] * inv_f[1],
            )
        )
        return r, j

    def normal_equations(j, w, r):
        blk = np.add.reduceat((j * w[:, None])[:, :, None] * j[:, None, :], starts, axis=0)  # (n,5,5)
        vec = np.add.reduceat(j * (w * r)[:, None], starts, axis=0)  # (n, 5)
        h = np.zeros((3 * n + 2, 3 * n + 2))
        h[pidx[:, :, None], pidx[:, None, :]] = blk[:, :3, :3]
        h[pidx[:, :, None], sidx[None, None, :]] = blk[:, :3, 3:]
        h[sidx[None, :, None], pidx[:, None, :]] = blk[:, 3:, :3]
        h[3 * n :, 3 * n :] = blk[:, 3:, 3:].sum(axis=0)
        b = np.zeros(3 * n + 2)
        b[pidx] = vec[:, :3]
        b[3 * n :] = vec[:, 3:].sum(axis=0)
        return h, b

    prior = np.zeros(3 * n + 2)
    prior[-2:] = 1.0 / sigma**2
    lam = 1e-3
    r, j = residuals(poses, log_s)
    for it in range(iterations):
        tau = truncation if it < 3 else 0.5 * truncation
        w = tukey_weights(r, tau)
        if w.sum() < 10:
            break
        h, b = normal_equations(j, w, r)
        h += np.diag(prior)
        b[-2:] += prior[-2:] * log_s
        cost0 = float(np.sum(w * r * r) + np.sum(prior[-2:] * log_s**2))
        step = -np.linalg.solve(h + lam * (np.diag(np.diag(h)) + 1e-9 * np.eye(len(b))), b)
        step[-2:] = np.clip(step[-2:], -0.01, 0.01)
        cand_p = poses + step[:-2].reshape(n, 3)
        cand_s = log_s + step[-2:]
        r2, j2 = residuals(cand_p, cand_s)
        cost1 = float(np.sum(w * r2 * r2) + np.sum(prior[-2:] * cand_s**2))
        if cost1 <= cost0:
            poses, log_s, r, j = cand_p, cand_s, r2, j2
            lam = max(lam * 0.3, 1e-6)
            if it >= 3 and cost0 - cost1 <= 1e-5 * cost0:
                break
        else:
            lam *= 10.0
            if lam > 1e4:
                break
    return log_s


def matrix_disagreement(plan, m1: np.ndarray, m2: np.ndarray) -> float:
    """RMS distance (map metres) between the plan's room corners mapped by two matrices."""
    pts = np.vstack([np.asarray(r.polygon.exterior.coords)[:-1, :2] for r in plan.rooms])
    h = np.column_stack((pts, np.ones(len(pts))))
    a = h @ np.asarray(m1, float)[:2].T
    b = h @ np.asarray(m2, float)[:2].T
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


__all__ = [
    "fit_plan_scale",
    "matrix_disagreement",
    "occupied_points",
    "rooms_seen_through",
    "wall_pieces_seen_through",
    "walls_through_free_space",
]
