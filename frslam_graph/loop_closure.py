"""Loop closure for the keyframe pose graph (``map`` frame; metres, radians).

Every ``attempt_every`` keyframes q, :class:`LoopCloser` looks for earlier keyframes c (not
recent ones: at least ``min_keyframe_gap`` keyframes and ``min_travel_gap`` metres of travel or
``min_rotation_gap_deg`` of turning back) near the current estimate. The search radius and the
heading window grow with the travel / turning between the two along the shortest path of the
graph (accepted closures count as zero length), so a long excursion is searched widely and a
freshly corrected one narrowly. One candidate per ``candidate_spacing`` cell; per attempt the
nearest cell not tried recently plus round-robin over the others (a wide area is covered over a
few keyframes); ``max_candidates`` per attempt, ``max_candidates_idle`` when nothing is queued (the
matching keeps up with the budget). When the prediction is too uncertain the search is centred on the candidate
itself ("is the robot back there?") instead of on the prediction.

Redundant work is skipped, as mature systems do (Karto's graph-distance exclusion, Cartographer's
constraint sampling): while the graph ties the current keyframe to an old keyframe within its
search radius by a short path (at most ``redundant_travel`` metres and ``redundant_turn_deg`` of
turning, accepted closures counting as zero length), a recent verified closure keeps their
relative uncertainty small and another closure would add little: the keyframe plans no search at
all. Not only the tied region: farther regions would take its place among the candidates, and
those are the places that merely look alike (an aliased pair confirmed there bent a simulated
house by 7 m). Once the travel or turning since the closure grows past these, the search resumes,
nearest region first. A queued candidate that a closure accepted after its plan ties already (e.g.
the keyframe's other candidate) is dropped unmatched, and so is a pending closure's check of a
place already tied. Counted in ``stats.redundant``. The graph distances are updated incrementally
while no closure is added. Without a floor plan this is off by default (``redundant_travel`` 0:
the fewer closures let aliased ones weigh more); once floor-plan priors are in the graph
``redundant_travel_with_plan`` applies: the priors hold the map to the plan, and most closures of
a robot re-traversing the plan's rooms would only repeat what the priors already say.

Each candidate is verified by :func:`match_scan`: the *query* submap (the points of the last
``query_travel`` metres of keyframes, in q's frame) is matched against the *reference* submap (the
points of c's neighbouring keyframes, in c's frame). A correlative grid search over (x, y, theta)
scores every pose at once (vectorised over poses × points) on a likelihood field of the reference
(``cv2.distanceTransform``), max-filtered so the coarse grid cannot step over the peak; the best
distinct peaks are refined by point-to-line ICP on the reference points. A match is accepted when
its inlier fraction is high and it is unambiguous (the best *distinct* second peak scores clearly
lower) and the query does not put points where the reference saw free space (another place that
looks alike: same walls, different furniture); it becomes ``gtsam.BetweenFactorPose2(x_c, x_q,
z)`` with the ICP covariance (inflated, floored) under a Cauchy kernel, so a wrong closure that
slips through cannot bend the map.

A robust kernel also refuses a *true* closure that disagrees with the current estimate by many
sigmas (after a long excursion). So a closure that would move the graph by more than
``confirm_xy`` / ``confirm_theta_deg`` waits until a second closure from another keyframe agrees
with it geometrically (pairwise consistency, as in PCM); then both enter the graph as plain
Gaussians (the graph converges to them with iSAM2, or an LM batch when the correction is large).
The bounded pull of a robust kernel could not hold such a correction against the stiff odometry
chain; the pairwise check takes its place as the guard against wrong closures. While a closure is
pending, each attempt first searches where it predicts the robot to be (same window and
ambiguity test as any candidate), which is what confirms the large corrections on ACES. The
keyframe ``verify_back_travel`` metres before the query is checked at once too (its query submap
shares no points with the pending one's), so the robot need not come back for a second look. A
match that agrees with a pending closure confirms it with a lower inlier fraction
(``confirm_min_inlier_fraction``: the agreement of two matches is the evidence); alone it is
rejected.

Closures already in the graph are re-checked after every addition and at the end
(:meth:`LoopCloser.flush`): at the converged estimate (an LM batch first), a closure whose residual
is far outside its covariance (``prune_chi2``, and ``prune_xy`` / ``prune_theta_deg``) is removed,
worst first: the odometry and the other closures disagree with it (on ACES, an aliased corridor
match confirmed by an unrelated closure of similar correction). Counted in ``stats.pruned``,
logged as ``loop_removed``. The lower confirmation threshold relies on it: without pruning,
regime-A houses 00dd / 026f went from 0.155 / 0.546 to 0.42 / 0.66 m ATE (0.04 / 0.05 with it).
A confirmed pair enters as plain Gaussians, so under its pull the older, robust closures show
the large residuals rather than the pair; when ``prune_pair_contradictions`` of them disagree at
once, the pair is removed first ("worst first" alone removed 134 good closures of a regime-A
house before the aliased pair that had bent it).

Bounded latency (anytime): a keyframe only *plans* (candidates into a queue, about 1 ms); the
work (query and reference submaps, the correlative search in chunks of at most
``max_lookups_per_step`` look-ups, the reference's ICP data, each ICP refinement, the iSAM2 update
and each relinearising iteration after a closure, an LM batch) is a chain of steps run by every
``add_scan`` (keyframe or not) while their estimated cost fits ``budget_ms``. Each step announces
its cost from the sizes involved (a fixed cost model: look-ups, grid cells, points, keyframes),
never from a clock, so the run is deterministic and the same on any machine; a step estimated
above the budget runs alone. ``wall_budget_ms`` optionally caps each call by the clock as well
(then the spread depends on the load). ``FRSlam.finish()`` runs what is left (:meth:`flush`).
With an unbounded budget the result is exactly that of doing everything in the keyframe's call.

Decisions go to ``slam.log`` as ``loop_closure`` / ``loop_pending`` / ``loop_rejected`` (with the
reason: ``no_overlap``, ``low_score``, ``low_inliers``, ``ambiguous``, ``free_space``).
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import cv2
import gtsam
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from frslam_graph.config import LoopClosureConfig
from frslam_graph.factors.between import pose2, regularise_covariance
from frslam_graph.factors.floorplan_prior import m_estimator
from frslam_graph.graph import key
from frslam_graph.motion_model import between, between_many, compose
from frslam_graph.steps import Steps, run_steps

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.pipeline import FRSlam, KeyframeInfo

T = TypeVar("T")

# Cost model: milliseconds on one core of the development machine (2-core x86 VM, 2020s); only
# needs to be right within a factor of about two. Fitted to the measured medians per step on ACES
# (180 beams) and regime-A houses (720 beams, 30 m; tools/bench_backend.py) as the geometric mean
# of the two ratios (before: the ICP, field and free-space steps took 2-3.5x their estimate on
# the houses, so a scan's 8 ms budget ran 15-30 ms of closure work).
_MS_PER_LOOKUP = 4.3e-6  # correlative search: one likelihood-field look-up (gather + mean)
_MS_PER_CELL_FIELD = 3.3e-5  # reference submap: distance transform with labels + field, per inner cell
_MS_PER_CELL_FILL = 2.3e-6  # zero padding of the whole grid
_MS_PER_CELL_DILATE = 3e-6  # max filter of the field (first use of a step size)
_MS_PER_CELL_NEAREST = 3.6e-6  # nearest-point map for ICP, per cell
_MS_PER_CELL_FREE = 6.5e-6  # free-space mask, per cell
_MS_PER_POINT_NORMALS = 1.8e-3  # k-d tree and PCA normals, per reference point
_MS_ICP = 1.1  # one ICP refinement: fixed part ...
_MS_PER_POINT_ICP = 3.7e-4  # ... and per query point and iteration
_MS_GATHER = 0.2  # submap points: fixed part ...
_MS_PER_POINT_GATHER = 4.2e-5  # ... and per end point of the keyframes gathered
_MS_PER_KEYFRAME_UPDATE = 0.01  # one relinearising iSAM2 update, per keyframe of the graph
_MS_PER_KEYFRAME_BATCH = 0.06  # LM batch and iSAM2 rebuild, per keyframe of the graph
_MS_FINE = 2.3  # finer level of the correlative search (a few hundred poses)


# ----------------------------------------------------------------------------- geometry helpers
def _wrap(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (M, 2) given in the frame ``pose`` (x, y, theta) -> the frame ``pose`` lives in."""
    return _rigid(pose[0], pose[1], np.cos(pose[2]), np.sin(pose[2]), np.asarray(points, dtype=np.float64))


def _rigid(x, y, c, s, p: np.ndarray) -> np.ndarray:
    """(x, y) + R(c, s) p for points p (M, 2); x, y, c, s scalars or (M,) per point."""
    return np.column_stack((x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]))


def _bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (min, max) of (M, 2) points, M >= 1. Column by column: numpy's axis-0 reduction
    of an (M, 2) array is ~50x slower (two-element inner loops)."""
    return (
        np.array([points[:, 0].min(), points[:, 1].min()]),
        np.array([points[:, 0].max(), points[:, 1].max()]),
    )


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The first point of each occupied voxel (order kept)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    cells = np.floor(points / voxel).astype(np.int64)
    h = cells[:, 0] * 73856093 ^ cells[:, 1] * 19349663
    _, idx = np.unique(h, return_index=True)
    return points[np.sort(idx)]


def _normals(points: np.ndarray, tree: cKDTree, k: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 2) from PCA of the k nearest neighbours, and a line-quality weight (N,)."""
    k = min(k, len(points))
    _, nn = tree.query(points, k=k)
    nb = points[nn.reshape(len(points), k)]  # (N, k, 2)
    d = nb - nb.mean(axis=1, keepdims=True)
    sxx = np.einsum("ij,ij->i", d[:, :, 0], d[:, :, 0])
    syy = np.einsum("ij,ij->i", d[:, :, 1], d[:, :, 1])
    sxy = np.einsum("ij,ij->i", d[:, :, 0], d[:, :, 1])
    # smallest eigenvalue / eigenvector of [[sxx, sxy], [sxy, syy]] in closed form
    tr, det = sxx + syy, sxx * syy - sxy**2
    disc = np.sqrt(np.maximum(tr**2 / 4.0 - det, 0.0))
    lmin, lmax = tr / 2.0 - disc, tr / 2.0 + disc
    n = np.column_stack((sxy, lmin - sxx))
    alt = np.column_stack((lmin - syy, sxy))
    use_alt = np.hypot(*n.T) < np.hypot(*alt.T)
    n[use_alt] = alt[use_alt]
    norm = np.hypot(*n.T)
    degenerate = norm < 1e-12
    n[degenerate] = (1.0, 0.0)
    n /= np.maximum(np.hypot(*n.T), 1e-12)[:, None]
    quality = np.where(lmax > 1e-12, 1.0 - np.clip(lmin / np.maximum(lmax, 1e-12), 0.0, 1.0), 0.0)
    quality[degenerate] = 0.0
    return n, quality


# ----------------------------------------------------------------------------- reference submap
class ReferenceSubmap:
    """Points of a reference submap with a likelihood field (correlative search) and a k-d tree
    with normals (ICP). ``points`` (M, 2) in the reference keyframe's frame.

    The likelihood field is built on construction; what only ICP and the free-space test need
    (nearest point per cell, normals, the free-space mask) is built on first use, so a candidate
    rejected by the correlative search never pays for it (and the anytime matcher can build it in
    a step of its own)."""

    def __init__(
        self,
        points: np.ndarray,
        resolution: float,
        sigma: float,
        margin: float,
        scans: list[tuple[np.ndarray, np.ndarray]] | None = None,
        free_margin: float = 0.3,
    ):
        pts = voxel_downsample(np.asarray(points, dtype=np.float64), resolution)
        self.points = pts
        self.resolution = res = float(resolution)
        lo, hi = _bounds(pts) if len(pts) else (np.zeros(2), np.zeros(2))
        lo, hi = lo - margin, hi + margin
        self.origin = lo
        self.margin_cells = int(np.ceil(margin / res))
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        self.shape = (h, w)
        # Distances are computed on an inner grid only (the points' box + max(16 sigma, 2 m)):
        # farther out the float32 likelihood is exactly 0 (it underflows beyond 14.4 sigma), no
        # nearest point is within 2 m and every cell is far from the end points. The outer
        # margin (for the correlative search's clamped look-ups) is zero padding.
        pad = max(0, int(np.floor((margin - max(16.0 * sigma, 2.0)) / res)))
        pad = min(pad, (h - 1) // 2, (w - 1) // 2)
        hi_, wi = h - 2 * pad, w - 2 * pad
        self._inner = (pad, hi_, wi)
        free = np.full((hi_, wi), 255, np.uint8)
        self._cells = np.zeros(0, np.int64)  # flat index of each point's cell (full grid)
        if len(pts):
            ij = np.floor((pts - lo) / res).astype(int)
            free[ij[:, 1] - pad, ij[:, 0] - pad] = 0
            self._cells = ij[:, 1] * w + ij[:, 0]
        # distances (5×5 mask, within about 2 %) and the nearest occupied cell of every cell
        dist, self._labels = cv2.distanceTransformWithLabels(
            free, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
        )
        dist *= res
        self.field = np.zeros((h, w), np.float32)
        self.field[pad : pad + hi_, pad : pad + wi] = np.exp(-0.5 * (dist / sigma) ** 2)
        self._occupied = free.ravel() == 0  # inner grid
        self._scans = scans
        # free space must be farther than free_margin from any end point
        self._far = None
        if scans:
            far = np.ones((h, w), bool)
            far[pad : pad + hi_, pad : pad + wi] = dist > free_margin
            self._far = far.ravel()
        self._nearest: np.ndarray | None = None
        self._tree: cKDTree | None = None
        self._normals: tuple[np.ndarray, np.ndarray] | None = None
        self._free: np.ndarray | None = None
        self._dilated: dict[int, np.ndarray] = {}

    # ----- built on first use (ICP, free-space test)
    @property
    def nearest(self) -> np.ndarray:
        """Index of the nearest reference point of every cell (flattened; -1 without points)."""
        if self._nearest is None:
            h, w = self.shape
            pad, hi_, wi = self._inner
            nearest = np.full((h, w), -1, np.int32)
            if len(self.points):
                owner = np.full(h * w, -1, np.int32)  # reference point in each occupied cell
                owner[self._cells] = np.arange(len(self.points), dtype=np.int32)
                owner = owner.reshape(h, w)[pad : pad + hi_, pad : pad + wi].ravel()
                # labels number the (inner grid's) zero cells in raster order
                zeros = np.flatnonzero(self._occupied)
                labels = self._labels.ravel()
                inner = owner[zeros[np.clip(labels - 1, 0, len(zeros) - 1)]]
                nearest[pad : pad + hi_, pad : pad + wi] = inner.reshape(hi_, wi)
            self._nearest = nearest.ravel()
            self._labels = None
        return self._nearest

    @property
    def tree(self) -> cKDTree | None:
        if self._tree is None and len(self.points):
            self._tree = cKDTree(self.points)
        return self._tree

    def _normals_quality(self) -> tuple[np.ndarray, np.ndarray]:
        if self._normals is None:
            n = len(self.points)
            self._normals = _normals(self.points, self.tree) if n >= 3 else (np.zeros((n, 2)), np.zeros(n))
        return self._normals

    @property
    def normals(self) -> np.ndarray:
        return self._normals_quality()[0]

    @property
    def quality(self) -> np.ndarray:
        return self._normals_quality()[1]

    @property
    def free(self) -> np.ndarray | None:
        """Cells the reference scans saw free (sensor -> end points polygons) away from any end
        point (flattened bool), or None without scans: a query point there contradicts the match."""
        if self._free is None and self._scans:
            h, w = self.shape
            seen = np.zeros((h, w), np.uint8)
            polys = [
                np.round((np.vstack((o[None], e)) - self.origin) / self.resolution).astype(np.int32)
                for o, e in self._scans
                if len(e) >= 2
            ]
            cv2.fillPoly(seen, polys, 1)
            self._free = (seen.ravel() > 0) & self._far
        return self._free

    def prepare_icp(self) -> None:
        """Build what ICP needs now (nearest-point map, k-d tree, normals)."""
        self.nearest  # noqa: B018
        self._normals_quality()

    def nearest_points(self, points: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
        """(indices into ``points`` with a reference point within max_distance, those reference
        points' indices): nearest neighbours by a cell look-up (exact up to one cell)."""
        h, w = self.shape
        ij = np.floor((points - self.origin) / self.resolution).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        sel = np.flatnonzero(inside)
        j = self.nearest[ij[sel, 1] * w + ij[sel, 0]]
        d = np.hypot(*(points[sel] - self.points[np.maximum(j, 0)]).T)
        ok = (j >= 0) & (d <= max_distance)
        return sel[ok], j[ok]

    def dilated(self, cells: int) -> np.ndarray:
        """The likelihood field max-filtered over a (2·cells + 1)² window (flattened)."""
        f = self._dilated.get(cells)
        if f is None:
            if cells > 0:
                kernel = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
                f = cv2.dilate(self.field, kernel).ravel()
            else:
                f = self.field.ravel()
            self._dilated[cells] = f
        return f

    def free_violation(self, query: np.ndarray, pose: np.ndarray) -> float:
        """Share of query points (at ``pose``) in space the reference saw free (0 without scans)."""
        if self.free is None or len(query) == 0:
            return 0.0
        h, w = self.shape
        ij = np.floor((transform_points(pose, query) - self.origin) / self.resolution).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        return float(self.free[ij[inside, 1] * w + ij[inside, 0]].sum()) / len(query)

    def inlier_fraction(self, query: np.ndarray, pose: np.ndarray, distance: float) -> float:
        if len(self.points) == 0 or len(query) == 0:
            return 0.0
        sel, _ = self.nearest_points(transform_points(pose, query), distance)
        return len(sel) / len(query)


# ----------------------------------------------------------------------------- matcher
@dataclass(frozen=True, slots=True)
class ScanMatch:
    """Result of :func:`match_scan`: the query frame's pose in the reference frame.

    ``inlier_fraction``: share of query points within ``inlier_distance`` of the reference after
    ICP; ``ambiguity``: the best distinct second peak's inlier fraction / the best (0 = none);
    ``covariance``: 3×3 in GTSAM's Pose2 tangent (body frame of ``pose``).
    """

    pose: np.ndarray
    inlier_fraction: float
    ambiguity: float
    covariance: np.ndarray
    coarse_score: float
    n_points: int
    second: np.ndarray | None = None
    free_violation: float = 0.0  # share of query points in the reference's free space


def _dilation_cells(res: float, step_xy: float, step_theta: float, reach: float) -> int:
    """Max-filter radius (cells) so a grid pose bounds every pose within half a step of it."""
    return int(np.ceil((0.5 * step_xy + 0.5 * step_theta * reach) / res))


def _grid_search(
    ref: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    step_xy: float,
    step_theta: float,
    reach: float,
    max_lookups: int = 2_000_000,
) -> Steps[tuple[np.ndarray, np.ndarray]]:
    """Score every pose of a (thetas × offsets) grid: returns (P, 3) poses and (P,) scores.

    A generator (see :func:`match_scan_steps`): a step per chunk of headings scored with at most
    ``max_lookups`` field look-ups (at least one heading per chunk)."""
    res = ref.resolution
    h, w = ref.shape
    n_th = int(np.ceil(window_theta / step_theta))
    thetas = centre[2] + step_theta * np.arange(-n_th, n_th + 1)
    s = max(1, int(round(step_xy / res)))
    n_xy = int(np.ceil(window_xy / (s * res)))
    o = s * np.arange(-n_xy, n_xy + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(o, o))
    cells = _dilation_cells(res, s * res, step_theta, reach)
    c, sn = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    px = c * query[None, :, 0] - sn * query[None, :, 1] + centre[0]
    py = sn * query[None, :, 0] + c * query[None, :, 1] + centre[1]
    bx = np.floor((px - ref.origin[0]) / res).astype(np.int64)
    by = np.floor((py - ref.origin[1]) / res).astype(np.int64)
    # points whose whole offset range would leave the grid see only the zero margin
    lim = n_xy * s
    out = (bx < lim) | (bx >= w - lim) | (by < lim) | (by >= h - lim)
    bx[out] = lim
    by[out] = lim
    base = (by * w + bx).astype(np.int32)  # (T, M)
    off = (oy * w + ox).astype(np.int32)  # (O,)
    scores = np.empty((len(thetas), len(off)), np.float32)
    chunk = max(1, int(max_lookups // max(1, len(off) * query.shape[0])))
    for a in range(0, len(thetas), chunk):
        cost = _MS_PER_LOOKUP * len(off) * query.shape[0] * min(chunk, len(thetas) - a)
        yield cost + (_MS_PER_CELL_DILATE * h * w if cells not in ref._dilated else 0.0)
        field = ref.dilated(cells)
        idx = base[a : a + chunk, None, :] + off[None, :, None]  # (t, O, M) flat cells
        scores[a : a + chunk] = field[idx].mean(axis=2)
    tt = np.repeat(thetas, len(off))
    poses = np.column_stack(
        (np.tile(centre[0] + ox * res, len(thetas)), np.tile(centre[1] + oy * res, len(thetas)), tt)
    )
    return poses, scores.ravel()


def _score_poses(ref: ReferenceSubmap, query: np.ndarray, poses: np.ndarray, cells: int) -> np.ndarray:
    """Mean (max-filtered) likelihood of ``query`` at each of ``poses`` (P, 3)."""
    field = ref.dilated(cells)
    h, w = ref.shape
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    px = c * query[None, :, 0] - s * query[None, :, 1] + poses[:, 0:1]
    py = s * query[None, :, 0] + c * query[None, :, 1] + poses[:, 1:2]
    bx = np.floor((px - ref.origin[0]) / ref.resolution).astype(np.int64)
    by = np.floor((py - ref.origin[1]) / ref.resolution).astype(np.int64)
    out = (bx < 0) | (bx >= w) | (by < 0) | (by >= h)
    bx[out] = 0
    by[out] = 0  # the corner cell lies in the zero margin
    return field[by * w + bx].mean(axis=1)


def _coarse_search(
    ref: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    step_xy: float,
    step_theta: float,
    sep_xy: float = 1.0,
    sep_theta: float = np.deg2rad(10.0),
    max_lookups: int = 2_000_000,
) -> Steps[tuple[np.ndarray, np.ndarray]]:
    """Two-level correlative search: a grid at twice the steps on a wider max filter (an upper
    bound of the finer level), then the finer grid inside the best cells and the best distinct
    cells. Returns the finer-level (P, 3) poses and (P,) scores (a generator, see
    :func:`match_scan_steps`)."""
    reach = float(np.percentile(np.hypot(*query.T), 90)) if len(query) else 0.0
    poses1, scores1 = yield from _grid_search(
        ref, query, centre, window_xy, window_theta, 2.0 * step_xy, 2.0 * step_theta, reach, max_lookups
    )
    yield _MS_FINE + _MS_PER_CELL_DILATE * ref.shape[0] * ref.shape[1]
    n = min(len(scores1), 16)
    top = np.argpartition(-scores1, n - 1)[:n]
    cells = np.union1d(top, _distinct_peaks(poses1, scores1, 8, sep_xy, sep_theta))
    d = np.array([-1.0, 0.0, 1.0])
    dx, dy, dt = (a.ravel() for a in np.meshgrid(d * step_xy, d * step_xy, d * step_theta, indexing="ij"))
    fine = (poses1[cells][:, None, :] + np.column_stack((dx, dy, dt))[None]).reshape(-1, 3)
    res = ref.resolution
    s = max(1, int(round(step_xy / res)))
    scores = _score_poses(ref, query, fine, _dilation_cells(res, s * res, step_theta, reach))
    return fine, scores


def _distinct_peaks(
    poses: np.ndarray, scores: np.ndarray, k: int, sep_xy: float, sep_theta: float
) -> list[int]:
    """Indices of up to k best poses, pairwise at least (sep_xy or sep_theta) apart."""
    top = min(len(scores), 400)
    order = np.argpartition(-scores, top - 1)[:top]
    order = order[np.argsort(-scores[order])]
    cand = poses[order]
    alive = np.ones(len(order), bool)  # not within the separation of a picked peak
    picked: list[int] = []
    while len(picked) < k:
        left = np.flatnonzero(alive)
        if not len(left):
            break
        j = left[0]
        picked.append(int(order[j]))
        p = cand[j]
        near = (np.hypot(cand[:, 0] - p[0], cand[:, 1] - p[1]) < sep_xy) & (
            np.abs(_wrap(cand[:, 2] - p[2])) < sep_theta
        )
        alive &= ~near
    return picked


def icp_point_to_line(
    ref: ReferenceSubmap,
    query: np.ndarray,
    pose: np.ndarray,
    iterations: int = 15,
    max_distance: float = 0.5,
    kernel: float = 0.05,
    sigma: float = 0.05,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Point-to-line ICP of ``query`` onto the reference; returns (pose, 3×3 body covariance)."""
    if len(ref.points) == 0 or len(query) < 10:
        return None
    x = np.asarray(pose, dtype=np.float64).copy()
    h = None
    for it in range(iterations):
        dmax = max_distance if it < iterations // 2 else max(2.0 * kernel, max_distance / 2.0)
        p = transform_points(x, query)
        sel, j = ref.nearest_points(p, dmax)
        if len(sel) < 10:
            return None
        p = p[sel]
        n, q = ref.normals[j], ref.quality[j]
        r = np.einsum("ij,ij->i", p - ref.points[j], n)
        rel = p - x[:2]
        jac = np.column_stack((n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]))
        wgt = q / (1.0 + (r / kernel) ** 2)
        h = jac.T @ (wgt[:, None] * jac)
        g = jac.T @ (wgt * r)
        try:
            delta = -np.linalg.solve(h + 1e-9 * np.eye(3), g)
        except np.linalg.LinAlgError:
            return None
        x += delta
        x[2] = float(_wrap(x[2]))
        if np.hypot(delta[0], delta[1]) < 1e-4 and abs(delta[2]) < 1e-5:
            break
    if h is None:
        return None
    # world-frame (t, theta) -> body tangent (v, omega): t = t0 + R v
    c, s = np.cos(x[2]), np.sin(x[2])
    a = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    hb = a.T @ h @ a / sigma**2
    try:
        cov = np.linalg.inv(hb + 1e-9 * np.eye(3))
    except np.linalg.LinAlgError:
        return None
    return x, cov


def match_scan(
    reference: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    config: LoopClosureConfig | None = None,
    rng: np.random.Generator | None = None,
) -> ScanMatch | None:
    """Match ``query`` points (M, 2, query frame) against ``reference`` around ``centre``
    (x, y, theta of the query frame in the reference frame) within ± window_xy (m) and
    ± window_theta (rad). None when nothing can be matched (too few points / no overlap)."""
    return run_steps(match_scan_steps(reference, query, centre, window_xy, window_theta, config, rng))


def match_scan_steps(
    reference: ReferenceSubmap,
    query: np.ndarray,
    centre: np.ndarray,
    window_xy: float,
    window_theta: float,
    config: LoopClosureConfig | None = None,
    rng: np.random.Generator | None = None,
) -> Steps[ScanMatch | None]:
    """:func:`match_scan` as a generator that yields between bounded pieces of work (a chunk of
    the correlative search of at most ``config.max_lookups_per_step`` look-ups, the finer level,
    building the reference's ICP data, one ICP refinement); its return value is the match.
    The anytime loop closer runs a few pieces per scan; the result does not depend on how the
    pieces are spread."""
    cfg = config or LoopClosureConfig()
    q = np.asarray(query, dtype=np.float64).reshape(-1, 2)
    q = q[np.hypot(*q.T) <= cfg.max_point_range] if len(q) else q
    fine = voxel_downsample(q, 2.0 * cfg.resolution)
    if len(fine) < 20 or len(reference.points) < 20:
        return None
    coarse = fine
    if len(coarse) > cfg.max_query_points:
        rng = rng or np.random.default_rng(0)
        coarse = coarse[rng.choice(len(coarse), cfg.max_query_points, replace=False)]
    step_th = np.deg2rad(cfg.coarse_step_theta_deg)
    c0 = np.asarray(centre, dtype=np.float64)
    sep_xy, sep_th = cfg.peak_separation_xy, np.deg2rad(cfg.peak_separation_theta_deg)
    poses, scores = yield from _coarse_search(
        reference,
        coarse,
        c0,
        window_xy,
        min(window_theta, np.pi),
        cfg.coarse_step_xy,
        step_th,
        sep_xy,
        sep_th,
        cfg.max_lookups_per_step,
    )
    peaks = _distinct_peaks(poses, scores, 3, sep_xy, sep_th)
    top = float(scores[peaks[0]])
    if top < cfg.min_coarse_score:  # not even the optimistic coarse score: no ICP
        second = float(scores[peaks[1]]) / top if len(peaks) > 1 and top > 0 else 0.0
        return ScanMatch(poses[peaks[0]], 0.0, second, np.eye(3), top, len(fine), None)
    cells = reference.shape[0] * reference.shape[1]
    if reference._nearest is None:
        yield _MS_PER_CELL_NEAREST * cells
        reference.nearest  # noqa: B018
    if reference._normals is None:
        yield _MS_PER_POINT_NORMALS * len(reference.points)
        reference.prepare_icp()
    refined, unrefined = [], 0.0
    for j in peaks:
        if j != peaks[0] and scores[j] < cfg.refine_ratio * top:
            unrefined = max(unrefined, float(scores[j]) / top)  # clearly lower already
            continue
        yield _MS_ICP + _MS_PER_POINT_ICP * len(fine) * cfg.icp_iterations
        r = icp_point_to_line(
            reference,
            fine,
            poses[j],
            cfg.icp_iterations,
            cfg.icp_max_distance,
            kernel=cfg.inlier_distance / 2.0,
            sigma=cfg.icp_sigma,
        )
        if r is None:
            continue
        inl = reference.inlier_fraction(fine, r[0], cfg.inlier_distance)
        refined.append((inl, r[0], r[1], float(scores[j])))
    if not refined:
        return None
    if reference._free is None and reference._scans:
        yield _MS_PER_CELL_FREE * cells
        reference.free  # noqa: B018
    refined.sort(key=lambda t: -t[0])
    best = refined[0]
    second, second_pose = 0.0, None
    for inl, p, _, _ in refined[1:]:
        if np.hypot(*(p[:2] - best[1][:2])) >= sep_xy or abs(_wrap(p[2] - best[1][2])) >= sep_th:
            second, second_pose = inl, p
            break
    amb = max(second / best[0], unrefined) if best[0] > 0 else 1.0
    free = reference.free_violation(fine, best[1])
    return ScanMatch(best[1], best[0], float(amb), best[2], top, len(fine), second_pose, free)


# ----------------------------------------------------------------------------- loop closer
@dataclass(frozen=True, slots=True, eq=False)
class LoopClosure:
    """An accepted (or pending) closure: x_reference⁻¹ ⊕ x_query = relative."""

    reference: int
    query: int
    relative: np.ndarray
    covariance: np.ndarray
    match: ScanMatch
    correction: np.ndarray  # prediction⁻¹ ⊕ relative at the time of the match (x, y, theta)


@dataclass(frozen=True, slots=True)
class _Job:
    """A candidate queued for matching: keyframe ``query`` against old keyframe ``reference``
    within ± radius (m) and ± window_theta (rad), around ``predicted`` (pose of the query in the
    reference's frame) when a pending closure predicts it."""

    reference: int
    query: int
    radius: float
    window_theta: float
    predicted: np.ndarray | None = None
    closures: int = 0  # closures accepted when it was planned


def _gather_cost(slam: FRSlam, lo: int, hi: int) -> float:
    """Estimated cost (ms) of gathering the points of keyframes lo..hi into a submap."""
    pts, _ = slam.keyframe_scans()
    n = sum(len(pts[k]) for k in range(max(lo, 0), min(hi, len(pts) - 1) + 1))
    return _MS_GATHER + _MS_PER_POINT_GATHER * n


def _moved(after: np.ndarray, before: np.ndarray) -> float:
    """Largest xy displacement (m) of the keyframes in both arrays."""
    n = min(len(after), len(before))
    return float(np.max(np.hypot(*(after[:n, :2] - before[:n, :2]).T))) if n else 0.0


@dataclass(slots=True)
class LoopClosureStats:
    attempts: int = 0  # candidates matched
    accepted: int = 0  # closures in the graph
    rejected: int = 0
    pending: int = 0  # waited for confirmation at least once
    batches: int = 0
    seconds: float = 0.0  # wall clock spent in the loop closer
    cpu_seconds: float = 0.0  # process CPU time spent in the loop closer
    keyframes: int = 0
    redundant: int = 0  # searches skipped: the keyframe already tied to the region (see config)
    pruned: int = 0  # accepted closures removed again: the rest of the graph disagreed
    verifications: int = 0  # earlier keyframes matched to check a pending closure
    reasons: dict[str, int] = field(default_factory=dict)


class LoopCloser:
    """Keyframe hook adding verified loop-closure factors to ``slam.graph`` (see module docs)."""

    def __init__(
        self, config: LoopClosureConfig | None = None, clock: Callable[[], float] = time.perf_counter
    ):
        """``clock`` (seconds) measures ``wall_budget_ms`` (``budget_ms`` is in estimated
        milliseconds of the cost model, no clock involved); injectable for tests."""
        self.config = config or LoopClosureConfig()
        self.clock = clock
        self.closures: list[LoopClosure] = []
        self.stats = LoopClosureStats()
        self._travel: list[float] = []
        self._turn: list[float] = []
        self._odom: list[np.ndarray] = []
        self._last_closure = -1
        self._tried: dict[tuple[int, int], int] = {}
        self._pending: list[LoopClosure] = []
        self._factor_of: dict[int, gtsam.BetweenFactorPose2] = {}  # id(closure) -> its factor
        # graph distances of the latest plan: (keyframe, closures, travel, turn)
        self._dist: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._submaps: OrderedDict[int, ReferenceSubmap] = OrderedDict()
        self._local: list[np.ndarray | None] = []  # per keyframe: its points in range (_in_range)
        self._query: tuple[int, np.ndarray] | None = None  # (keyframe, query submap points)
        self._rng = np.random.default_rng(0)
        # anytime work: candidates planned at a keyframe, matched a few steps per scan
        self._jobs: deque[_Job] = deque()
        self._task: Steps[list[LoopClosure]] | None = None  # the job being worked on
        self._last_plan = -(10**9)
        # redundant_travel, or redundant_travel_with_plan once floor-plan priors are in the graph
        # (set by each plan)
        self._redundant_travel = self.config.redundant_travel
        self._next_cost = 0.0  # estimated cost (ms) of the current task's next step
        # steps run by the latest on_keyframe / on_scan / flush and their estimated cost (ms)
        self.steps_last_call, self.cost_last_call = 0, 0.0

    # ------------------------------------------------------------------ motion bookkeeping
    def _append_motion(self, pose_odom: np.ndarray) -> None:
        p = np.asarray(pose_odom, dtype=np.float64)
        if self._odom:
            prev = self._odom[-1]
            self._travel.append(self._travel[-1] + float(np.hypot(*(p[:2] - prev[:2]))))
            self._turn.append(self._turn[-1] + float(abs(_wrap(p[2] - prev[2]))))
        else:
            self._travel.append(0.0)
            self._turn.append(0.0)
        self._odom.append(p)

    def _sync(self, slam: FRSlam, index: int) -> None:
        if len(self._odom) == index:
            return
        self._travel, self._turn, self._odom = [], [], []
        self._dist = None
        self._local = []
        for kf in slam.keyframes()[:index]:
            self._append_motion(kf.pose_odom)

    # ------------------------------------------------------------------ hooks
    def on_keyframe(self, slam: FRSlam, keyframe: KeyframeInfo, work: bool = True) -> list[LoopClosure]:
        """A new keyframe: every ``attempt_every`` keyframes queue its candidates (a pending
        closure's check ahead of the older ones), then work on the queue within the per-scan
        budget (not with ``work`` False: this scan's budget is spent elsewhere; the queue goes
        on at the next scan). Returns the closures that entered the graph during this call (of
        this or an earlier keyframe)."""
        i = keyframe.index
        self._sync(slam, i)
        self._append_motion(keyframe.pose_odom)
        self.stats.keyframes += 1
        cfg = self.config
        if not cfg.enabled:
            return []
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            if i >= cfg.min_keyframe_gap and i % cfg.attempt_every == 0:
                self._plan(slam, i)
            if not work:
                self.steps_last_call, self.cost_last_call = 0, 0.0
                return []
            return self._work(slam, min(cfg.keyframe_budget_ms, cfg.budget_ms), cfg.wall_budget_ms)
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    def on_scan(self, slam: FRSlam, budget_ms: float | None = None) -> list[LoopClosure]:
        """A scan that is not a keyframe: continue the queued work within the per-scan budget.
        ``budget_ms``: what is left of it after other work on this scan (a deferred step); then
        only steps that fit run (none may)."""
        if self.idle:
            self.steps_last_call, self.cost_last_call = 0, 0.0
            return []
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            if budget_ms is not None:
                wall = self.config.wall_budget_ms
                if wall is not None:
                    wall *= min(budget_ms / self.config.budget_ms, 1.0)
                return self._work(slam, min(budget_ms, self.config.budget_ms), wall, first_free=False)
            return self._work(slam, self.config.budget_ms, self.config.wall_budget_ms)
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    def flush(self, slam: FRSlam) -> list[LoopClosure]:
        """Finish all queued work now (offline, before the final batch)."""
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            added = self._work(slam, None, None)
            run_steps(self._prune(slam))
            return added
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    @property
    def idle(self) -> bool:
        """No candidate waiting or being matched."""
        return self._task is None and not self._jobs

    def _work(
        self,
        slam: FRSlam,
        budget: float | None,
        wall_budget_ms: float | None,
        first_free: bool = True,
    ) -> list[LoopClosure]:
        """Run steps of the queued jobs while their estimated costs (cost model, ms) fit in
        ``budget`` (None: run everything) and, with ``wall_budget_ms``, while the time spent in
        this call (``clock``) is below it. With ``first_free`` the first step always runs, so
        the queue advances even when a single step is estimated above the budget (the scan's
        own budget); without it (the rest of a budget other work used) every step must fit."""
        added: list[LoopClosure] = []
        start = self.clock()
        spent, steps = 0.0, 0
        while not self.idle:
            cost = self._next_cost
            bounded = steps or not first_free
            if bounded and budget is not None and spent + cost > budget:
                break
            if bounded and wall_budget_ms is not None and 1e3 * (self.clock() - start) >= wall_budget_ms:
                break
            if self._task is None:
                self._task = self._job(slam, self._jobs.popleft())
            try:
                self._next_cost = float(next(self._task))
            except StopIteration as stop:
                added.extend(stop.value)
                self._task = None
                self._next_cost = 0.0
            spent += cost
            steps += 1
        self.steps_last_call, self.cost_last_call = steps, spent
        return added

    def _graph_distances(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Travel (m) and turn (rad) from keyframe i to every keyframe along the shortest path of
        the graph, accepted closures counting as zero length: how far the relative drift can grow."""
        trav, turn = np.asarray(self._travel[: i + 1]), np.asarray(self._turn[: i + 1])
        n = i + 1
        d = self._dist
        if d is not None and d[0] <= i and d[1] == len(self.closures) and self._last_closure <= d[0]:
            # no closure since the previous keyframe i0 = d[0] and none after it: every path from
            # i runs down the chain to i0 (each edge of the chain counts + 1e-9, as below)
            i0 = d[0]
            k = np.arange(i0 + 1, n)
            out = [
                np.concatenate((prev + (x[i] - x[i0]) + 1e-9 * (i - i0), x[i] - x[k] + 1e-9 * (i - k)))
                for prev, x in ((d[2], trav), (d[3], turn))
            ]
            self._dist = (i, len(self.closures), out[0], out[1])
            return out[0], out[1]
        a = np.arange(n - 1)
        rows = [a, a + 1]
        cols = [a + 1, a]
        dt = np.diff(trav) + 1e-9
        dr = np.diff(turn) + 1e-9
        wt, wr = [dt, dt], [dr, dr]
        lc = [(c.reference, c.query) for c in self.closures if c.query <= i]
        if lc:
            r, q = np.asarray(lc).T
            rows += [r, q]
            cols += [q, r]
            wt += [np.full(len(r), 1e-9)] * 2
            wr += [np.full(len(r), 1e-9)] * 2
        rr, cc = np.concatenate(rows), np.concatenate(cols)
        # one sparsity structure for both weights (rows sorted; duplicate edges are kept, the
        # search takes the shorter)
        perm = np.argsort(rr, kind="stable")
        indptr = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(rr, minlength=n), out=indptr[1:])
        cols_sorted = cc[perm].astype(np.int32)
        out = []
        for w in (wt, wr):
            g = csr_matrix((np.concatenate(w)[perm], cols_sorted, indptr), shape=(n, n))
            out.append(dijkstra(g, indices=i, directed=True))
        self._dist = (i, len(self.closures), out[0], out[1])
        return out[0], out[1]

    def _tied(self, i: int) -> np.ndarray:
        """Mask over keyframes 0..i: tied to keyframe i by a short path of the graph (the relative
        uncertainty is small; see ``LoopClosureConfig.redundant_travel``)."""
        cfg = self.config
        d = self._dist
        d_rel, r_rel = (d[2], d[3]) if d and d[:2] == (i, len(self.closures)) else self._graph_distances(i)
        return (d_rel <= self._redundant_travel) & (r_rel <= np.deg2rad(cfg.redundant_turn_deg))

    def _eligible(self, i: int) -> np.ndarray:
        """Mask over keyframes 0..i-min_keyframe_gap far enough back (travel or turn)."""
        cfg = self.config
        n = i - cfg.min_keyframe_gap + 1
        if n <= 0:
            return np.zeros(0, bool)
        trav, turn = np.asarray(self._travel), np.asarray(self._turn)
        gap_t, gap_r = trav[i] - trav[:n], turn[i] - turn[:n]
        return (gap_t >= cfg.min_travel_gap) | (gap_r >= np.deg2rad(cfg.min_rotation_gap_deg))

    def _hypothesis(self, est: np.ndarray, i: int) -> tuple[int, float, float, np.ndarray] | None:
        """Where the latest pending closure says keyframe i is in the old map: (the old keyframe
        nearest to that place, window xy, window theta, predicted pose relative to it)."""
        cfg = self.config
        if not self._pending:
            return None
        p = self._pending[-1]
        if p.query == i or i - p.query > cfg.pending_keyframes:
            return None
        ok = self._eligible(i)
        if not ok.any():
            return None
        pred = compose(compose(est[p.reference], p.relative), between(est[p.query], est[i]))
        d = np.hypot(*(est[: len(ok), :2] - pred[:2]).T)
        d[~ok] = np.inf
        c = int(np.argmin(d))
        if d[c] > cfg.search_window_xy:
            return None
        return c, cfg.hypothesis_window_xy, np.deg2rad(cfg.hypothesis_window_theta_deg), between(est[c], pred)

    def _candidates(
        self, est: np.ndarray, i: int, limit: int | None = None
    ) -> list[tuple[int, float, float]]:
        """(keyframe, search radius, heading window) of the candidates to try now (at most
        ``limit``, default ``max_candidates``)."""
        cfg = self.config
        limit = cfg.max_candidates if limit is None else limit
        trav, turn = np.asarray(self._travel), np.asarray(self._turn)
        n = i - cfg.min_keyframe_gap + 1
        if n <= 0:
            return []
        idx = np.arange(n)
        gap_t, gap_r = trav[i] - trav[:n], turn[i] - turn[:n]
        ok = (gap_t >= cfg.min_travel_gap) | (gap_r >= np.deg2rad(cfg.min_rotation_gap_deg))
        d_rel, r_rel = self._graph_distances(i)
        d_rel, r_rel = d_rel[:n], r_rel[:n]
        radius = np.minimum(cfg.radius_max, cfg.radius_base + cfg.radius_per_m * d_rel)
        dist = np.hypot(*(est[:n, :2] - est[i, :2]).T)
        ok &= dist <= radius
        if not ok.any():
            return []
        idx = idx[ok]
        order = idx[np.argsort(dist[ok], kind="stable")]
        if self._tied(i)[order].any():
            # keyframe i is tied to a region around it (short path through a recent verified
            # closure): it is not searched, and neither are the others (farther regions would
            # take its place: places that look alike, where a wrong pair can be confirmed)
            self.stats.redundant += 1
            return []
        cells = list(map(tuple, np.floor(est[order, :2] / cfg.candidate_spacing).astype(int).tolist()))
        order = order.tolist()
        # one candidate per cell (the nearest); the first pick is the nearest cell not tried
        # recently, the others go round-robin (never tried first, then the least recently tried)
        # so that a wide search area is covered over the keyframes
        picks, seen = [], set()
        for rank, (c, cell) in enumerate(zip(order, cells, strict=True)):
            if cell in seen:
                continue
            seen.add(cell)
            last = self._tried.get(cell)
            if last is not None and i - last < cfg.retry_keyframes:
                continue
            picks.append((-1 if last is None else last, rank, c, cell))
        if picks:
            first = min(picks, key=lambda t: t[1])
            picks.remove(first)
            picks = [first, *sorted(picks)]
        out = []
        for _, _, c, cell in picks[:limit]:
            window = np.deg2rad(
                cfg.theta_window_base_deg
                + cfg.theta_window_per_m_deg * d_rel[c]
                + cfg.theta_window_per_turn * np.rad2deg(r_rel[c])
            )
            out.append((c, float(radius[c]), float(min(window, np.pi))))
            self._tried[cell] = i
        return out

    def _submap(
        self, slam: FRSlam, est: np.ndarray, centre: int, lo: int, hi: int, travel: float
    ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """Points of keyframes lo..hi (within ± travel of ``centre``) in ``centre``'s frame, and
        per keyframe (sensor origin, end points in beam order) in that frame."""
        pts_all, origins = slam.keyframe_scans()
        trav = self._travel
        ks = [
            k
            for k in range(max(lo, 0), min(hi, len(pts_all) - 1) + 1)
            if abs(trav[k] - trav[centre]) <= travel and len(pts_all[k])
        ]
        if not ks:
            return np.zeros((0, 2)), []
        local = [self._in_range(pts_all, origins, k) for k in ks]
        rels = [between(est[centre], est[k]) for k in ks]
        sizes = [len(p) for p in local]
        # one transform for all keyframes: per point the same products as transform_points
        rep = np.repeat(np.array([(r[0], r[1], np.cos(r[2]), np.sin(r[2])) for r in rels]), sizes, axis=0)
        pts = _rigid(*rep.T, np.concatenate(local))
        ends = np.split(pts, np.cumsum(sizes)[:-1])
        scans = [
            (transform_points(r, origins[k][None])[0], e) for r, k, e in zip(rels, ks, ends, strict=True)
        ]
        return pts, scans

    def _in_range(self, pts_all: list[np.ndarray], origins: list[np.ndarray], k: int) -> np.ndarray:
        """Keyframe k's end points within ``max_point_range`` of its sensor (float64, base_link;
        cached: keyframe scans never change)."""
        cache = self._local
        while len(cache) <= k:
            cache.append(None)
        p = cache[k]
        if p is None:
            q = pts_all[k]
            p = np.asarray(q[np.hypot(*(q - origins[k]).T) <= self.config.max_point_range], np.float64)
            cache[k] = p
        return p

    def _reference(self, slam: FRSlam, c: int, i: int) -> Steps[ReferenceSubmap]:
        """Reference submap of keyframe c (cached), two steps when built: points, field."""
        sub = self._submaps.get(c)
        if sub is not None:
            self._submaps.move_to_end(c)
            return sub
        cfg = self.config
        lo, hi = c - cfg.submap_keyframes, min(c + cfg.submap_keyframes, i - cfg.min_keyframe_gap)
        yield _gather_cost(slam, lo, hi)
        pts, scans = self._submap(slam, slam.graph.estimates(), c, lo, hi, cfg.submap_travel)
        margin = 2.0 * cfg.search_window_xy + 4.0 * cfg.likelihood_sigma + 1.5
        if len(pts):
            inner = min(margin, max(16.0 * cfg.likelihood_sigma, 2.0))  # see ReferenceSubmap
            lo, hi = _bounds(pts)
            extent = hi - lo
            cells = np.prod((extent + 2.0 * margin) / cfg.resolution + 1.0)
            cells_inner = np.prod((extent + 2.0 * inner) / cfg.resolution + 1.0)
            yield _MS_PER_CELL_FIELD * float(cells_inner) + _MS_PER_CELL_FILL * float(cells)
        sub = ReferenceSubmap(pts, cfg.resolution, cfg.likelihood_sigma, margin, scans, cfg.free_space_margin)
        self._submaps[c] = sub
        while len(self._submaps) > 24:
            self._submaps.popitem(last=False)
        return sub

    def _reject(self, slam: FRSlam, i: int, c: int, reason: str, **data: Any) -> None:
        self.stats.rejected += 1
        self.stats.reasons[reason] = self.stats.reasons.get(reason, 0) + 1
        slam.log_event("loop_rejected", f"keyframe {i} vs {c}: {reason}", keyframe=i, reference=c, **data)

    def _plan(self, slam: FRSlam, i: int) -> None:
        """Queue the candidates of keyframe i: first where a pending closure predicts the robot
        to be, then up to ``max_candidates`` in all (``max_candidates_idle`` when nothing is
        queued: the work keeps up with the budget)."""
        cfg = self.config
        limit = max(cfg.max_candidates, cfg.max_candidates_idle) if self.idle else cfg.max_candidates
        # pending closures too old when the previous plan was done
        self._pending = [p for p in self._pending if self._last_plan - p.query <= cfg.pending_keyframes]
        self._last_plan = i
        self._redundant_travel = (
            cfg.redundant_travel_with_plan if slam.graph.has_priors() else cfg.redundant_travel
        )
        est = slam.graph.estimates()
        cands: list[tuple[int, float, float, np.ndarray | None]] = [
            (c, r, w, None) for c, r, w in self._candidates(est, i, limit)
        ]
        hyp = self._hypothesis(est, i)
        if hyp is not None and self._tied(i)[hyp[0]]:
            # the graph already ties keyframe i to the predicted place by a recent verified
            # closure: the check is redundant (and the closure, if it agrees, adds little)
            self.stats.redundant += 1
            hyp = None
        if hyp is not None:
            cands = cands[: limit - 1]
        n = len(self.closures)
        self._jobs.extend(_Job(c, i, r, w, pred, n) for c, r, w, pred in cands)
        if hyp is not None:  # time-critical (the pending closure expires): ahead of older jobs
            self._jobs.appendleft(_Job(hyp[0], i, hyp[1], hyp[2], hyp[3], n))

    def _query_points(self, slam: FRSlam, i: int) -> np.ndarray:
        """Query submap of keyframe i (kept: shared by its candidates)."""
        if self._query is not None and self._query[0] == i:
            return self._query[1]
        cfg = self.config
        est = slam.graph.estimates()
        query, _ = self._submap(slam, est, i, i - cfg.submap_keyframes, i, cfg.query_travel)
        self._query = (i, query)
        return query

    def _job(self, slam: FRSlam, job: _Job) -> Steps[list[LoopClosure]]:
        """Match one candidate and act on the result (a step generator): query submap, reference
        submap, correlative search + ICP (:func:`match_scan_steps`), verification, graph update
        (:meth:`_add`)."""
        cfg = self.config
        c, i = job.reference, job.query
        if len(self.closures) != job.closures and self._tied(i)[c]:
            # a closure accepted since the plan (e.g. the keyframe's other candidate) ties the
            # region already: matching it would add little
            self.stats.redundant += 1
            return []
        if self._query is None or self._query[0] != i:
            yield _gather_cost(slam, i - cfg.submap_keyframes, i)
        query = self._query_points(slam, i)
        ref = yield from self._reference(slam, c, i)
        est = slam.graph.estimates()
        self.stats.attempts += 1
        guess = between(est[c], est[i])
        radius = job.radius
        if job.predicted is not None:  # check a pending closure's prediction
            centre, win = job.predicted, radius
        elif radius <= cfg.search_window_xy or np.hypot(guess[0], guess[1]) <= cfg.search_window_xy:
            centre, win = guess, min(cfg.search_window_xy, max(radius, 0.5))
        else:  # the prediction is too uncertain: is the robot back at the candidate itself?
            centre, win = np.array([0.0, 0.0, guess[2]]), cfg.search_window_xy
        m = yield from match_scan_steps(ref, query, centre, win, job.window_theta, cfg, self._rng)
        if m is None:
            self._reject(slam, i, c, "no_overlap")
            return []
        data = {
            "inliers": round(m.inlier_fraction, 3),
            "ambiguity": round(m.ambiguity, 3),
            "relative": m.pose.tolist(),
            "coarse": round(m.coarse_score, 3),
        }
        if m.coarse_score < cfg.min_coarse_score:
            self._reject(slam, i, c, "low_score", **data)
            return []
        weak = m.inlier_fraction < cfg.min_inlier_fraction  # only confirms a pending closure
        if m.inlier_fraction < min(cfg.min_inlier_fraction, cfg.confirm_min_inlier_fraction):
            self._reject(slam, i, c, "low_inliers", **data)
            return []
        if m.ambiguity > cfg.max_ambiguity:
            self._reject(slam, i, c, "ambiguous", **data)
            return []
        if m.free_violation > cfg.max_free_violation:
            self._reject(slam, i, c, "free_space", free=round(m.free_violation, 3), **data)
            return []
        cov = regularise_covariance(
            m.covariance * cfg.covariance_inflation,
            cfg.sigma_floor_xy,
            np.deg2rad(cfg.sigma_floor_theta_deg),
        )
        corr = between(guess, m.pose)
        lc = LoopClosure(c, i, m.pose.copy(), cov, m, corr)
        small = np.hypot(corr[0], corr[1]) <= cfg.confirm_xy and abs(corr[2]) <= np.deg2rad(
            cfg.confirm_theta_deg
        )
        partner = None if small else self._consistent_pending(lc, slam.graph.estimates())
        if weak and partner is None:
            self._reject(slam, i, c, "low_inliers", **data)
            return []
        if small:
            yield from self._add(slam, [lc], settle=False)
            return [lc]
        if partner is None:
            self._pending.append(lc)
            self.stats.pending += 1
            slam.log_event(
                "loop_pending",
                f"keyframe {i} vs {c}: large correction, waiting for a consistent second closure",
                keyframe=i,
                reference=c,
                correction=corr.tolist(),
                **data,
            )
            self._verify_back(slam, lc)
            return []
        self._pending = [q for q in self._pending if q is not partner]
        yield from self._add(slam, [partner, lc], settle=True)
        return [partner, lc]

    def _verify_back(self, slam: FRSlam, lc: LoopClosure) -> None:
        """Queue (first) a check of the pending ``lc`` from the keyframe ``verify_back_travel``
        metres before its query: matched against the old keyframe nearest to where ``lc`` puts it.
        Its query submap shares no points with ``lc``'s, so an agreeing match is a second piece of
        evidence even when the robot does not come back to the place."""
        cfg = self.config
        i = lc.query
        if cfg.verify_back_travel <= 0.0:
            return
        trav = np.asarray(self._travel[: i + 1])
        back = np.flatnonzero(trav[i] - trav >= cfg.verify_back_travel)
        if not len(back):
            return
        j = int(back[-1])
        ok = self._eligible(j)
        if not ok.any():
            return
        est = slam.graph.estimates()
        pred = compose(compose(est[lc.reference], lc.relative), between(est[i], est[j]))
        d = np.hypot(*(est[: len(ok), :2] - pred[:2]).T)
        d[~ok] = np.inf
        c = int(np.argmin(d))
        if d[c] > cfg.search_window_xy:
            return
        window = np.deg2rad(cfg.hypothesis_window_theta_deg)
        self._jobs.appendleft(
            _Job(c, j, cfg.hypothesis_window_xy, window, between(est[c], pred), len(self.closures))
        )
        self.stats.verifications += 1

    def _consistent_pending(self, lc: LoopClosure, est: np.ndarray) -> LoopClosure | None:
        cfg = self.config
        for p in reversed(self._pending):
            if p.query == lc.query:
                continue
            implied = between(compose(est[p.reference], p.relative), compose(est[lc.reference], lc.relative))
            odo = between(est[p.query], est[lc.query])
            d = between(implied, odo)
            tol_xy = cfg.consistency_xy + 0.02 * float(np.hypot(odo[0], odo[1]))
            if np.hypot(d[0], d[1]) <= tol_xy and abs(d[2]) <= np.deg2rad(cfg.consistency_theta_deg):
                return p
        return None

    def _factor(self, lc: LoopClosure, robust: bool) -> gtsam.BetweenFactorPose2:
        gauss = gtsam.noiseModel.Gaussian.Covariance(lc.covariance)
        est = m_estimator(self.config.kernel, self.config.kernel_param) if robust else None
        noise = gauss if est is None else gtsam.noiseModel.Robust.Create(est, gauss)
        return gtsam.BetweenFactorPose2(key(lc.reference), key(lc.query), pose2(lc.relative), noise)

    def _add(self, slam: FRSlam, closures: list[LoopClosure], settle: bool) -> Steps[None]:
        """Add closures to the graph (a step generator). A single closure with a small correction
        enters under the robust kernel. A confirmed pair (``settle``: two closures from different
        keyframes that agree) enters as plain Gaussians: a bounded-influence kernel cannot pull
        the stiff odometry chain far, not even after the graph has converged to the closure (the
        chain's stress exceeds the kernel's maximal pull and the graph slides back); an LM batch
        runs when the correction moved the graph far. The relinearising iSAM2 iterations after
        the factor (:meth:`PoseGraph.settle`) run one per step."""
        graph = slam.graph
        yield _MS_PER_KEYFRAME_UPDATE * len(graph)
        before = graph.estimates()
        # with floor-plan priors in the graph, absolute corrections come from the plan: a
        # confirmed pair stays under the robust kernel too, so an aliased pair (two matches of
        # the same repeated structure) cannot overrule the priors
        anchored = graph.has_priors()
        for lc in closures:
            factor = self._factor(lc, robust=not settle or anchored)
            self._factor_of[id(lc)] = factor
            graph.add_factor(factor, extra_iterations=0)
        if settle:
            yield from self._settle(graph, 10)
            moved = _moved(graph.estimates(), before)
            if moved >= self.config.batch_on_correction or self._residual_large(graph, closures):
                yield _MS_PER_KEYFRAME_BATCH * len(graph)
                graph.optimize_batch()
                self.stats.batches += 1
        yield from self._settle(graph, 10 if settle else self.config.settle_small)
        moved = _moved(graph.estimates(), before)
        for lc in closures:
            self.closures.append(lc)
            self.stats.accepted += 1
            self._last_closure = max(self._last_closure, lc.query)
            slam.log_event(
                "loop_closure",
                f"keyframe {lc.query} closes on {lc.reference}",
                keyframe=lc.query,
                reference=lc.reference,
                relative=lc.relative.tolist(),
                correction=lc.correction.tolist(),
                inliers=round(lc.match.inlier_fraction, 3),
                ambiguity=round(lc.match.ambiguity, 3),
                sigma_xy=float(np.sqrt(max(lc.covariance[0, 0], lc.covariance[1, 1]))),
                moved=moved,
                robust=not settle,
            )
        if settle:  # neighbouring keyframes may have moved relative to each other
            self._submaps.clear()
        yield from self._prune(slam, closures if settle else None)

    def _residual_chi2(self, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (K, 3: x, y, theta of prediction⁻¹ ⊕ measurement) of the accepted closures at
        ``est`` and their squared Mahalanobis norms (K,) under the closures' covariances."""
        if not self.closures:
            return np.zeros((0, 3)), np.zeros(0)
        ref = est[[lc.reference for lc in self.closures]]
        qry = est[[lc.query for lc in self.closures]]
        meas = np.array([lc.relative for lc in self.closures])
        cov = np.array([lc.covariance for lc in self.closures])
        pred = between_many(ref, qry)
        r = between_many(pred, meas)
        chi2 = np.einsum("ki,ki->k", r, np.linalg.solve(cov, r[:, :, None])[:, :, 0])
        return r, chi2

    def _prune(self, slam: FRSlam, suspects: list[LoopClosure] | None = None) -> Steps[None]:
        """Remove accepted closures the rest of the graph disagrees with (a step generator): while
        the worst residual exceeds ``prune_chi2`` and ``prune_xy`` / ``prune_theta_deg`` at the
        converged estimate (an LM batch first), remove that closure and settle again.

        ``suspects``: a confirmed pair that just entered as plain Gaussians. Under its pull the
        older, robust closures show the large residuals, so "worst first" would remove them one
        by one before the pair (a regime-A house: 134 good closures removed, then the aliased
        pair). When at least ``prune_pair_contradictions`` older closures disagree at once, the
        pair is removed first."""
        cfg = self.config
        if cfg.prune_chi2 <= 0.0:
            return
        graph = slam.graph
        converged = False
        suspects = list(suspects or [])
        while self.closures:
            r, chi2_all = self._residual_chi2(graph.estimates())
            big = (np.hypot(r[:, 0], r[:, 1]) > cfg.prune_xy) | (
                np.abs(r[:, 2]) > np.deg2rad(cfg.prune_theta_deg)
            )
            chi2 = np.where(big, chi2_all, 0.0)
            k = int(np.argmax(chi2))
            if chi2[k] <= cfg.prune_chi2:
                return
            if not converged:  # judge at the optimum, not after a few Gauss-Newton steps
                yield _MS_PER_KEYFRAME_BATCH * len(graph)
                graph.optimize_batch()
                self.stats.batches += 1
                converged = True
                continue
            suspect = np.array([any(lc is s for s in suspects) for lc in self.closures])
            others = int(np.count_nonzero((chi2 > cfg.prune_chi2) & ~suspect))
            if suspect.any() and others >= cfg.prune_pair_contradictions:
                worst = np.flatnonzero(suspect)
                why = f"it contradicts {others} accepted closures"
            else:
                worst = np.array([k])
                why = f"the graph disagrees (chi2 {chi2[k]:.0f})"
            suspects = []
            yield from self._remove(slam, worst.tolist(), r, chi2_all, why)

    def _remove(
        self, slam: FRSlam, which: list[int], r: np.ndarray, chi2: np.ndarray, why: str
    ) -> Steps[None]:
        """Remove the accepted closures at positions ``which`` of ``self.closures`` (residuals
        ``r`` / ``chi2`` as judged) in one iSAM2 update, then settle (a step generator)."""
        cfg = self.config
        graph = slam.graph
        yield _MS_PER_KEYFRAME_UPDATE * len(graph)
        before = graph.estimates()
        removed = [self.closures[k] for k in which]
        gone = set(which)
        self.closures = [lc for k, lc in enumerate(self.closures) if k not in gone]
        idx = [
            graph.factor_index(f)
            for f in (self._factor_of.pop(id(lc), None) for lc in removed)
            if f is not None
        ]
        idx = [i for i in idx if i >= 0]
        if idx:
            graph.remove_factors(idx, extra_iterations=0)
        yield from self._settle(graph, 10)
        if _moved(graph.estimates(), before) >= cfg.batch_on_correction:
            yield _MS_PER_KEYFRAME_BATCH * len(graph)
            graph.optimize_batch()
            self.stats.batches += 1
        self._dist = None
        self._submaps.clear()
        self._last_closure = max((c.query for c in self.closures), default=-1)
        for k, lc in zip(which, removed, strict=True):
            self.stats.pruned += 1
            slam.log_event(
                "loop_removed",
                f"keyframe {lc.query} on {lc.reference}: {why}",
                keyframe=lc.query,
                reference=lc.reference,
                residual=r[k].tolist(),
                chi2=float(chi2[k]),
            )

    @staticmethod
    def _settle(graph, max_iterations: int, tol: float = 1e-4) -> Steps[None]:
        """:meth:`PoseGraph.settle_steps` with this module's cost estimate for each step."""
        for _ in graph.settle_steps(max_iterations, tol):
            yield _MS_PER_KEYFRAME_UPDATE * len(graph)

    @staticmethod
    def _residual_large(graph, closures: list[LoopClosure]) -> bool:
        est = graph.estimates()
        for lc in closures:
            r = between(between(est[lc.reference], est[lc.query]), lc.relative)
            if np.hypot(r[0], r[1]) > 0.1 or abs(r[2]) > np.deg2rad(1.0):
                return True
        return False


__all__ = [
    "LoopCloser",
    "LoopClosure",
    "LoopClosureStats",
    "ReferenceSubmap",
    "ScanMatch",
    "icp_point_to_line",
    "match_scan",
    "match_scan_steps",
    "run_steps",
    "transform_points",
    "voxel_downsample",
]
