"""Final alignment: dense scan-to-submap constraints between passes at the end of a run.

Loop closure (:mod:`frslam_graph.loop_closure.closer`) adds a closure now and then while the robot
drives, searching widely because the estimate may have drifted. Once the graph has converged
(:meth:`FRSlam.finish`), every keyframe's estimate is within centimetres of the truth, so
every place the robot passed more than once can be tied cheaply: for each keyframe, the
keyframes of *other passes* near it (``map`` positions within ``final_alignment_radius``,
headings whose fields of view overlap) are matched by point-to-line ICP, started at the
current estimate, of the keyframe's query submap (itself and its neighbours) onto the other's
reference submap. A match that converges with most points on the reference and moves the
estimate by little is a between-factor under a Huber kernel; the graph is re-optimised (LM
batch); with ``final_alignment_rounds`` 2 the constraints are computed again at the new estimate.

A keyframe that no such ICP ties to another pass may lie beyond the ICP's reach: the online closer
tied the place once, then the odometry slipped while the robot stayed there (ACES: KISS-ICP lost
12° in the first second of a fast spin in place right after the return-to-start closure, and 5°
more in a second spin; 40 s of keyframes 11-17° off, no online candidate (every region near was
tried by the closure's keyframes), no ICP constraint (5° gate), relation error 0.85 m). For such a
keyframe each of its pairs is searched as the closer searches (:func:`~frslam_graph.loop_closure.
submap_matching.match_scan`: correlative search of ± ``SEARCH_WINDOW_XY`` / ``SEARCH_WINDOW_THETA``
around the estimate, ICP, inliers, ambiguity, free space: :func:`searched_constraints`); a found
constraint counts only when one of another keyframe agrees with it (the closer's pairwise
consistency): one aliased match is not enough. Pairs whose ICP converged within its gates from
the estimate (too few inliers only) are not searched: the estimate is within reach there, and
the search, started at it too, finds the same basin (session 23: every constraint the search had
found on the real logs was such a pair, within 5 cm / 0.8°).

This is the dense constraint set offline mappers end with (Cartographer's final optimisation,
Karto's and GraphMapping's scan matching against all near poses). It runs only with loop
closure on (``loop_closure.enabled``): these are loop closures too.

Frames: keyframe points are (M, 2) in ``base_link``; poses are ``base_link`` in ``map``
(x, y, theta; metres, radians). The constraint ``relative`` is x_reference⁻¹ ⊕ x_query with
its 3×3 covariance in GTSAM's Pose2 tangent (body frame of the query).
"""

from __future__ import annotations

import multiprocessing as mp
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from frslam_graph.backend.graph import key
from frslam_graph.config import LoopClosureConfig
from frslam_graph.factors.between import pose2
from frslam_graph.loop_closure.submap_matching import (
    ReferenceSubmap,
    match_scan,
    rigid_points,
    voxel_downsample,
)
from frslam_graph.se2 import between, between_many, compose, wrap

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext

T = TypeVar("T")

QUERY_SPAN = 1  # keyframes each side of the query keyframe in its submap
REFERENCE_SPAN = 4  # ... and of the reference keyframe in its submap
MIN_PASS_TRAVEL = 10.0  # m of travel between two keyframes of different passes, and between
#                         the passes matched to one keyframe
MIN_OVERLAP_DEG = 120.0  # fields of view must overlap by this much (sets the heading window)
RESOLUTION = 0.05  # m, submap voxel and grid
ICP_ITERATIONS = 10  # from a converged estimate (half at ICP_MAX_DISTANCE, half at half of it)
ICP_MAX_DISTANCE = 0.3  # m, association distance of the first ICP iterations (then half)
ICP_KERNEL = 0.05  # m, Cauchy scale of the point-to-line residual
ICP_SIGMA = 0.05  # m, residual sigma that scales the ICP covariance
INLIER_DISTANCE = 0.1  # m
MIN_INLIER_FRACTION = 0.7
MIN_START_OVERLAP = 0.5  # share of query points within 2 inlier distances before ICP, else skipped
MAX_CORRECTION_XY = 0.3  # m: a larger move from the converged estimate is not this method's job
MAX_CORRECTION_THETA = np.deg2rad(5.0)
COVARIANCE_FLOOR = np.diag([0.01**2, 0.01**2, np.deg2rad(0.2) ** 2])
# Huber kernel (whitened units): gated matches of a converged estimate are rarely wrong, but a
# redescending kernel (Cauchy 1 / 3) gave them too little pull against the stiff odometry chain
# (FR079 relation error 0.057 / 0.049 m; Huber 3 0.048, none 0.047); Huber bounds a wrong one's pull.
HUBER_SCALE = 3.0
# Search of the keyframes no ICP constraint ties (searched_constraints): the closer's matcher in
# this window around the estimate. The estimate has converged, so the window is the slip a
# stretch of odometry can leave after a closure, not the drift of a whole loop: ACES 17° after two
# spins in place (the closer's heading window after 300° of turning: 25°).
SEARCH_WINDOW_XY = 0.5  # m
SEARCH_WINDOW_THETA = np.deg2rad(30.0)
# two searched constraints agree when the query poses they imply keep the estimate's relative
# pose within this (the closer's CONSISTENCY_XY / _THETA_DEG: 0.3 m plus 2 % of the distance, 3°)
AGREE_XY = 0.3
AGREE_XY_PER_M = 0.02
AGREE_THETA = np.deg2rad(3.0)


@dataclass(frozen=True, slots=True)
class AlignmentConstraint:
    """x_reference⁻¹ ⊕ x_query measured by ICP, with its covariance and inlier fraction."""

    reference: int
    query: int
    relative: np.ndarray
    covariance: np.ndarray
    inlier_fraction: float
    searched: bool = False  # found by the correlative search (searched_constraints), not the ICP alone


def field_of_view(points: list[np.ndarray]) -> float:
    """Median angular coverage (radians) of the keyframes' points seen from base_link (5° bins)."""
    bins = 72
    cover = []
    for p in points[:: max(1, len(points) // 200)]:
        if len(p) < 10:
            continue
        b = ((np.arctan2(p[:, 1], p[:, 0]) + np.pi) / (2.0 * np.pi) * bins).astype(np.int64) % bins
        cover.append(np.count_nonzero(np.bincount(b, minlength=bins)) / bins)
    return 2.0 * np.pi * float(np.median(cover)) if cover else 2.0 * np.pi


#: keyframes whose neighbours are gathered at once by :func:`candidate_pairs` (its memory is this
#: times the keyframes within the radius of one, not the square of the keyframes in the map)
PAIRS_CHUNK = 128


def candidate_pairs(
    poses: np.ndarray, travel: np.ndarray, radius: float, heading_window: float, per_keyframe: int
) -> np.ndarray:
    """(P, 2) pairs (reference c, query k), c < k, of keyframes of different passes.

    ``poses`` (K, 3) in map, ``travel`` (K,) cumulative distance along the trajectory (m). For
    each k: keyframes within ``radius`` whose heading differs by at most ``heading_window``, at
    least ``MIN_PASS_TRAVEL`` of travel away; nearest first (ties: lower index first), at most
    ``per_keyframe`` of them, each from another pass (their travels ``MIN_PASS_TRAVEL`` apart).

    The neighbours are gathered for :data:`PAIRS_CHUNK` keyframes at a time: a place passed many
    times has many keyframes within the radius of each other, and all pairs of the map at once
    grew with the square of the recording (7,200 keyframes of a small house: 470 MB, now 30 MB).
    """
    if len(poses) < 2:
        return np.zeros((0, 2), np.int64)
    tree = cKDTree(poses[:, :2])
    out: list[tuple[int, int]] = []
    for lo in range(0, len(poses), PAIRS_CHUNK):
        near = cKDTree(poses[lo : lo + PAIRS_CHUNK, :2]).sparse_distance_matrix(
            tree, radius, output_type="ndarray"
        )
        k, c = near["i"].astype(np.int64) + lo, near["j"].astype(np.int64)
        ok = np.abs(travel[c] - travel[k]) >= MIN_PASS_TRAVEL  # also drops c == k
        ok &= np.abs(wrap(poses[c, 2] - poses[k, 2])) <= heading_window
        c, k = c[ok], k[ok]
        if len(k) == 0:
            continue
        d = np.hypot(*(poses[c, :2] - poses[k, :2]).T)
        order = np.lexsort((c, d, k))
        c, k = c[order], k[order]
        start = np.searchsorted(k, np.unique(k))
        for s, e in zip(start, [*start[1:], len(k)], strict=True):
            chosen: list[int] = []
            for ci in c[s:e]:
                if all(abs(travel[ci] - travel[o]) >= MIN_PASS_TRAVEL for o in chosen):
                    chosen.append(int(ci))
                    if len(chosen) >= per_keyframe:
                        break
            out.extend((ci, int(k[s])) for ci in chosen)
    # a pair found from both ends is matched once (query = the later keyframe)
    pairs = np.array(out, np.int64).reshape(-1, 2)
    pairs = np.sort(pairs, axis=1)
    return np.unique(pairs, axis=0)


def _in_range(points: list[np.ndarray], max_range: float) -> list[np.ndarray]:
    """Per keyframe its points within ``max_range`` of base_link (tested in float64), in their
    own dtype: what submaps take. The store's float32 points stay float32 (half the memory of a
    float64 copy of every keyframe's points, which the final alignment held in each round);
    :func:`_stacked`'s float64 transform takes them exactly (float32 -> float64 is exact)."""
    out = []
    for p in points:
        p = np.asarray(p)
        q = p.astype(np.float64, copy=False)
        out.append(p[np.hypot(q[:, 0], q[:, 1]) <= max_range])
    return out


def _stacked(
    poses: np.ndarray, local: list[np.ndarray], i: int, span: int
) -> tuple[range, np.ndarray, list[int], np.ndarray]:
    """Keyframes i-span..i+span, their poses relative to keyframe i as (K, 4) x, y, cos, sin
    (:func:`rigid_points`' parameters), their point counts, and their points (``local``:
    :func:`_in_range`) in keyframe i's frame, in keyframe order; one transform for all (per point
    the products of ``transform_points``)."""
    ks = range(max(0, i - span), min(len(local) - 1, i + span) + 1)
    rels = [between(poses[i], poses[j]) for j in ks]
    sizes = [len(local[j]) for j in ks]
    rig = np.array([(r[0], r[1], np.cos(r[2]), np.sin(r[2])) for r in rels])
    return (
        ks,
        rig,
        sizes,
        rigid_points(*np.repeat(rig, sizes, axis=0).T, np.concatenate([local[j] for j in ks])),
    )


def _submap(poses: np.ndarray, local: list[np.ndarray], i: int, span: int) -> np.ndarray:
    """Points of keyframes i-span..i+span (``local``: :func:`_in_range`) in keyframe i's frame
    (voxel-thinned)."""
    return voxel_downsample(_stacked(poses, local, i, span)[3], RESOLUTION)


class _ReferenceStack:
    """The nearest-point look-ups of many reference submaps as one (their cell grids and points
    concatenated): :meth:`ReferenceSubmap.nearest_points` for points that each belong to one of
    them, in a handful of array operations instead of a handful per submap."""

    def __init__(self, refs: list[ReferenceSubmap]):
        self.refs = refs
        self.resolution = refs[0].resolution
        self.origin = np.array([r.origin for r in refs])
        # each submap's nearest-point map: its inner grid ((h, w), ``pad`` cells in from its origin)
        self.shape = np.array([r.inner_grid[1:] for r in refs], dtype=np.int64)
        self.pad = np.array([r.inner_grid[0] for r in refs], dtype=np.int64)
        cells = self.shape[:, 0] * self.shape[:, 1]
        self.cell_offset = np.concatenate(([0], np.cumsum(cells)[:-1]))
        sizes = np.array([len(r.points) for r in refs])
        self.point_offset = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        self.nearest = np.concatenate([r.nearest for r in refs])  # indices into each submap's points
        self.points = np.concatenate([r.points for r in refs])
        self.normals = self.quality = None

    def prepare_icp(self, used: np.ndarray) -> None:
        """Normals and line quality of the submaps ``used`` (indices; the others' stay zero)."""
        self.normals = np.zeros_like(self.points)
        self.quality = np.zeros(len(self.points))
        for r in used:
            ref, o = self.refs[r], self.point_offset[r]
            self.normals[o : o + len(ref.points)] = ref.normals
            self.quality[o : o + len(ref.points)] = ref.quality

    def nearest_points(
        self, points: np.ndarray, ref: np.ndarray, max_distance: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(indices into ``points`` with a point of their submap ``ref`` (per point) within
        ``max_distance``, those points' indices into ``self.points``)."""
        h, w = self.shape[ref, 0], self.shape[ref, 1]
        ij = np.floor((points - self.origin[ref]) / self.resolution).astype(np.int64)
        ij -= self.pad[ref][:, None]
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        sel = np.flatnonzero(inside)
        rs = ref[sel]
        j = self.nearest[self.cell_offset[rs] + ij[sel, 1] * w[sel] + ij[sel, 0]]
        j = np.where(j >= 0, j + self.point_offset[rs], -1)
        d = np.hypot(*(points[sel] - self.points[np.maximum(j, 0)]).T)
        ok = (j >= 0) & (d <= max_distance)
        return sel[ok], j[ok]

    def exact_nearest(
        self, points: np.ndarray, ref: np.ndarray, max_distance: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`nearest_points` with the exact nearest point of each point's submap (ICP's
        correspondences; see :meth:`ReferenceSubmap.exact_nearest_offsets`): each run of points
        of one submap queries that submap's own k-d tree (``ref`` comes grouped by submap: one
        query per submap). The same neighbours as one k-d tree over all submaps, each lifted to
        a height of its own (FR079's final alignment: 9.1 -> 8.3 s of CPU)."""
        if len(ref) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        cut = (np.flatnonzero(ref[1:] != ref[:-1]) + 1).tolist()
        sels, js = [], []
        for lo, hi in zip([0, *cut], [*cut, len(ref)], strict=True):
            r = int(ref[lo])
            d, j = self.refs[r].tree.query(points[lo:hi], distance_upper_bound=max_distance)
            s = np.flatnonzero(np.isfinite(d))
            sels.append(s + lo)
            js.append(j[s] + self.point_offset[r])
        return np.concatenate(sels), np.concatenate(js)

    def inlier_fractions(
        self, queries: np.ndarray, owner: np.ndarray, ref: np.ndarray, poses: np.ndarray, distance: float
    ) -> np.ndarray:
        """Per pair: share of its query points (``queries`` rows of pair ``owner``) within
        ``distance`` of its reference ``ref[pair]`` at ``poses[pair]``."""
        sel, _ = self.nearest_points(_transform_each(poses, queries, owner), ref[owner], distance)
        n = np.bincount(owner, minlength=len(poses))
        return np.bincount(owner[sel], minlength=len(poses)) / np.maximum(n, 1)


def _transform_each(poses: np.ndarray, points: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """Points (N, 2) each in the frame ``poses[owner]`` -> the frame the poses live in."""
    return rigid_points(
        poses[owner, 0], poses[owner, 1], np.cos(poses[:, 2])[owner], np.sin(poses[:, 2])[owner], points
    )


def _icp_many(
    stack: _ReferenceStack,
    queries: np.ndarray,
    owner: np.ndarray,
    ref: np.ndarray,
    start: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~frslam_graph.loop_closure.submap_matching.icp_point_to_line` of many pairs at once (the same
    iterations, gates and covariance; ICP_* settings): pair p's query points are the rows of
    ``queries`` whose ``owner`` is p, matched onto submap ``ref[p]`` from ``start[p]``. Returns
    (poses (P, 3), body covariances (P, 3, 3), ok (P,): False where ICP gave up)."""
    n_pairs = len(start)
    x = np.array(start, dtype=np.float64)
    h = np.zeros((n_pairs, 3, 3))
    ok = np.ones(n_pairs, bool)
    done = np.zeros(n_pairs, bool)
    dropped = done.copy()  # pairs whose points left queries / owner
    eye = 1e-9 * np.eye(3)
    for it in range(ICP_ITERATIONS):
        dmax = ICP_MAX_DISTANCE if it < ICP_ITERATIONS // 2 else max(2.0 * ICP_KERNEL, ICP_MAX_DISTANCE / 2.0)
        if not np.array_equal(done, dropped):  # keep the points of the pairs still iterating
            live = ~done[owner]
            if not live.any():
                break
            queries, owner, dropped = queries[live], owner[live], done.copy()
        own = owner
        p = _transform_each(x, queries, own)
        sel, j = stack.exact_nearest(p, ref[own], dmax)
        own, p = own[sel], p[sel]
        running = ~done
        ok &= ~running | (np.bincount(own, minlength=n_pairs) >= 10)
        done |= ~ok
        n, q = stack.normals[j], stack.quality[j]
        r = np.einsum("ij,ij->i", p - stack.points[j], n)
        rel = p - x[own, :2]
        jac = np.column_stack((n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]))
        wgt = q / (1.0 + (r / ICP_KERNEL) ** 2)
        step = np.flatnonzero(~done)
        hh = np.zeros((n_pairs, 3, 3))
        g = np.zeros((n_pairs, 3))
        wr = wgt * r
        wj = wgt[:, None] * jac
        for a in range(3):  # per pair jac.T @ (wgt * r) and jac.T @ (wgt * jac), as icp_point_to_line
            g[:, a] = np.bincount(own, jac[:, a] * wr, n_pairs)
            for b in range(a, 3):
                hh[:, a, b] = hh[:, b, a] = np.bincount(own, jac[:, a] * wj[:, b], n_pairs)
        h[step] = hh[step]
        try:
            delta = -np.linalg.solve(hh[step] + eye, g[step][:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # a singular pair: each on its own
            delta = np.zeros((len(step), 3))
            for k, s in enumerate(step):
                try:
                    delta[k] = -np.linalg.solve(hh[s] + eye, g[s])
                except np.linalg.LinAlgError:
                    ok[s], done[s] = False, True
        x[step] += delta
        x[step, 2] = wrap(x[step, 2])
        done[step] |= (np.hypot(delta[:, 0], delta[:, 1]) < 1e-4) & (np.abs(delta[:, 2]) < 1e-5)
    # world-frame (t, theta) -> body tangent (v, omega): t = t0 + R v
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    a = np.zeros((n_pairs, 3, 3))
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1], a[:, 2, 2] = c, -s, s, c, 1.0
    hb = np.transpose(a, (0, 2, 1)) @ h @ a / ICP_SIGMA**2
    cov = np.full((n_pairs, 3, 3), np.nan)
    good = np.flatnonzero(ok)
    try:
        cov[good] = np.linalg.inv(hb[good] + eye)
    except np.linalg.LinAlgError:
        for s_ in good:
            try:
                cov[s_] = np.linalg.inv(hb[s_] + eye)
            except np.linalg.LinAlgError:
                ok[s_] = False
    return x, cov, ok


#: reference grid cells matched at once (the look-up tables of a chunk of reference submaps:
#: 4 bytes per cell, plus the pairs' query points). At 4 million the ICP's per-point arrays
#: (~45,000 points) were each a fresh mapping of 0.4-1 MB whose pages the kernel zero-filled
#: on first touch (FR079: 440,000 page faults a round); at 1 million they are about a quarter
#: (FR079's round 2 in one process: 4.2 -> 3.5 s of CPU, the same constraints).
_CHUNK_CELLS = 1_000_000


def align_pairs(
    poses: np.ndarray, points: list[np.ndarray], pairs: np.ndarray, max_range: float, processes: int = 1
) -> list[AlignmentConstraint]:
    """ICP of each pair's query submap onto its reference submap, from the current estimate.

    Vectorised over pairs, in chunks of reference submaps (each built once; each query submap
    once): the start-overlap gate, the ICP (:func:`_icp_many`) and the final gates. The
    constraints come in the order of ``pairs`` sorted (stably) by reference. ``processes`` 2:
    the pairs are shared with a forked process (:func:`_shared`: the same constraints)."""
    return _inliers_held(reached_pairs(poses, points, pairs, max_range, processes))


def reached_pairs(
    poses: np.ndarray, points: list[np.ndarray], pairs: np.ndarray, max_range: float, processes: int = 1
) -> list[AlignmentConstraint]:
    """:func:`align_pairs` before its inlier gate: every pair whose ICP converged from the
    estimate within ``MAX_CORRECTION_XY`` / ``_THETA`` (the estimate is within the ICP's reach),
    with its inlier fraction (the constraints: those of at least ``MIN_INLIER_FRACTION``)."""
    if len(pairs) == 0:
        return []
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    local = _in_range(points, max_range)
    return _shared(pairs, lambda part: _align_refs(poses, local, part), processes)


def _inliers_held(reached: list[AlignmentConstraint]) -> list[AlignmentConstraint]:
    """The constraints of :func:`reached_pairs`: inlier fraction at least ``MIN_INLIER_FRACTION``."""
    return [c for c in reached if c.inlier_fraction >= MIN_INLIER_FRACTION]


#: blocks of references the pairs are cut into for :func:`_shared`: the two processes take them one
#: at a time, so neither waits longer than one block (~3 % of the work) for the other
SHARED_BLOCKS = 32


def _shared(
    pairs: np.ndarray,
    run: Callable[[np.ndarray], list[AlignmentConstraint]],
    processes: int,
) -> list[AlignmentConstraint]:
    """``run(pairs)`` (``pairs`` sorted by reference), with ``processes`` 2 in this process and a
    forked one (Linux ``fork``): the pairs are cut into :data:`SHARED_BLOCKS` blocks of whole
    references (equal pair counts) and each process takes the next block not yet taken until
    none is left. The work of a block is not known beforehand (Intel's halves by pair count:
    2.2 / 2.8 s of ICP; the searched pairs' halves 1.65 / 1.2 s; a forked process is slowed by
    its copy-on-write faults and the machine's other load), so it is shared as it comes. Each
    pair's numbers do not depend on the others', so the constraints and their order are those
    of one ``run`` (a failed child: the blocks this process did not do, here)."""
    if processes < 2 or len(pairs) < 2 or "fork" not in mp.get_all_start_methods():
        return run(pairs)
    refs = pairs[:, 0]
    cuts = np.unique(np.searchsorted(refs, refs[np.arange(1, SHARED_BLOCKS) * len(pairs) // SHARED_BLOCKS]))
    blocks = np.split(pairs, cuts[(cuts > 0) & (cuts < len(pairs))])
    if len(blocks) < 2:
        return run(pairs)
    taken = mp.get_context("fork").Value("i", 0)

    def take() -> dict[int, list[AlignmentConstraint]]:
        done: dict[int, list[AlignmentConstraint]] = {}
        while True:
            with taken.get_lock():
                b = taken.value
                taken.value = b + 1
            if b >= len(blocks):
                return done
            done[b] = run(blocks[b])

    child = _in_child(lambda: {b: _constraint_rows(c) for b, c in take().items()})
    here = take()
    rows = child()
    out: list[AlignmentConstraint] = []
    for b, block in enumerate(blocks):
        if b in here:
            out.extend(here[b])
        elif rows is not None and b in rows:
            out.extend(_constraints_of_rows(rows[b]))
        else:  # the child failed: its blocks here
            out.extend(run(block))
    return out


def _constraint_rows(cons: list[AlignmentConstraint]) -> np.ndarray:
    """Constraints as rows (reference, query, relative 3, covariance 9, inlier fraction, searched)."""
    return np.array(
        [
            [c.reference, c.query, *c.relative, *c.covariance.ravel(), c.inlier_fraction, c.searched]
            for c in cons
        ]
    ).reshape(-1, 16)


def _constraints_of_rows(rows: np.ndarray) -> list[AlignmentConstraint]:
    """The constraints of :func:`_constraint_rows`' rows."""
    return [
        AlignmentConstraint(
            int(r[0]), int(r[1]), r[2:5].copy(), r[5:14].reshape(3, 3).copy(), float(r[14]), bool(r[15])
        )
        for r in rows
    ]


def _in_child(fn: Callable[[], T]) -> Callable[[], T | None]:
    """Start ``fn()`` in a forked process; returns a function that waits for its result (pickled;
    None when the child failed)."""
    ctx = mp.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)

    def child() -> None:
        try:
            send.send_bytes(pickle.dumps(fn()))
        finally:
            send.close()

    proc = ctx.Process(target=child, daemon=True)
    proc.start()
    send.close()

    def result() -> T | None:
        try:
            return pickle.loads(receive.recv_bytes())
        except (EOFError, OSError, pickle.UnpicklingError):
            return None
        finally:
            receive.close()
            proc.join()

    return result


def _align_refs(poses: np.ndarray, local: list[np.ndarray], pairs: np.ndarray) -> list[AlignmentConstraint]:
    """:func:`align_pairs` of ``pairs`` (sorted by reference) in one process, ``local`` the
    keyframes' points in range (:func:`_in_range`)."""
    out: list[AlignmentConstraint] = []
    queries: dict[int, np.ndarray] = {}
    refs, chunk, cells = [], [], 0
    for c in np.unique(pairs[:, 0]):
        pts = _submap(poses, local, int(c), REFERENCE_SPAN)
        if len(pts) < 30:
            continue
        ref = ReferenceSubmap(pts, RESOLUTION, INLIER_DISTANCE, ICP_MAX_DISTANCE, likelihood=False)
        refs.append(ref)
        chunk.append(int(c))
        cells += ref.shape[0] * ref.shape[1]
        if cells >= _CHUNK_CELLS:
            out.extend(_align_chunk(poses, local, pairs, chunk, refs, queries))
            refs, chunk, cells = [], [], 0
    if chunk:
        out.extend(_align_chunk(poses, local, pairs, chunk, refs, queries))
    return out


def _align_chunk(
    poses: np.ndarray,
    local: list[np.ndarray],
    pairs: np.ndarray,
    chunk: list[int],
    refs: list[ReferenceSubmap],
    queries: dict[int, np.ndarray],
) -> list[AlignmentConstraint]:
    """:func:`align_pairs` for the pairs whose reference is one of ``chunk`` (submaps ``refs``);
    ``queries`` caches the query submaps by keyframe."""
    which = {c: r for r, c in enumerate(chunk)}
    mine = pairs[np.isin(pairs[:, 0], chunk)]
    sel, parts = [], []
    for c, k in mine:
        q = queries.get(int(k))
        if q is None:
            q = queries[int(k)] = _submap(poses, local, int(k), QUERY_SPAN)
        if len(q) >= 30:
            sel.append((which[int(c)], int(c), int(k)))
            parts.append(q)
    if not sel:
        return []
    stack = _ReferenceStack(refs)
    ref = np.array([s[0] for s in sel])
    cs, ks = np.array([s[1] for s in sel]), np.array([s[2] for s in sel])
    owner = np.repeat(np.arange(len(sel)), [len(q) for q in parts])
    qpts = np.concatenate(parts)
    start = between_many(poses[cs], poses[ks])
    # the two barely overlap at the converged estimate: not worth an ICP
    keep = stack.inlier_fractions(qpts, owner, ref, start, 2.0 * INLIER_DISTANCE) >= MIN_START_OVERLAP
    renumber = np.cumsum(keep) - 1
    rows = keep[owner]
    qpts, owner = qpts[rows], renumber[owner[rows]]
    ref, cs, ks, start = ref[keep], cs[keep], ks[keep], start[keep]
    stack.prepare_icp(np.unique(ref))  # normals of the submaps still in use only
    x, cov, ok = _icp_many(stack, qpts, owner, ref, start)
    ok &= np.hypot(*(x[:, :2] - start[:, :2]).T) <= MAX_CORRECTION_XY
    ok &= np.abs(wrap(x[:, 2] - start[:, 2])) <= MAX_CORRECTION_THETA
    inliers = stack.inlier_fractions(qpts, owner, ref, x, INLIER_DISTANCE)
    ok &= np.all(np.isfinite(cov), axis=(1, 2))  # the inlier gate: _inliers_held
    return [
        AlignmentConstraint(int(cs[p]), int(ks[p]), x[p].copy(), cov[p].copy(), float(inliers[p]))
        for p in np.flatnonzero(ok)
    ]


def _reference_scans(
    poses: np.ndarray, local: list[np.ndarray], origins: list[np.ndarray], c: int, span: int
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Points of keyframes c-span..c+span (``local``: :func:`_in_range`) in keyframe c's frame, and
    per keyframe (sensor origin, end points in beam order) in that frame (the free-space test)."""
    ks, rig, sizes, pts = _stacked(poses, local, c, span)
    ends = np.split(pts, np.cumsum(sizes)[:-1])
    # the sensor origins in one transform (per origin the products of transform_points)
    sensors = rigid_points(*rig.T, np.array([origins[j] for j in ks], dtype=np.float64))
    return pts, list(zip(sensors, ends, strict=True))


def searched_constraints(
    poses: np.ndarray,
    points: list[np.ndarray],
    origins: list[np.ndarray],
    pairs: np.ndarray,
    config: LoopClosureConfig,
    processes: int = 1,
) -> list[AlignmentConstraint]:
    """Constraints of ``pairs`` (P, 2: reference c, query k) found by the closer's matcher
    (:func:`~frslam_graph.loop_closure.submap_matching.match_scan`) within ± ``SEARCH_WINDOW_XY`` /
    ``SEARCH_WINDOW_THETA`` of the estimate ``poses`` (map): the ICP's submaps, the closer's
    likelihood field, ambiguity and free-space tests (``config``), this module's inlier fraction;
    then only those that another one agrees with (:func:`agreeing`). ``origins``: per keyframe
    the sensor origin in base_link. One reference submap at a time (pairs sorted by reference);
    ``processes`` 2: shared with a forked process (:func:`_shared`, the same
    constraints)."""
    cfg = config
    local = _in_range(points, cfg.max_point_range)
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    found = _shared(pairs, lambda part: _searched(poses, local, origins, part, cfg), processes)
    return agreeing(poses, found)


def _searched(
    poses: np.ndarray,
    local: list[np.ndarray],
    origins: list[np.ndarray],
    pairs: np.ndarray,
    cfg: LoopClosureConfig,
) -> list[AlignmentConstraint]:
    """The matches of :func:`searched_constraints` for ``pairs`` (sorted by reference; ``local``:
    :func:`_in_range`) in this process, before the agreement test."""
    margin = SEARCH_WINDOW_XY + 4.0 * cfg.likelihood_sigma + 1.5
    found: list[AlignmentConstraint] = []
    queries: dict[int, np.ndarray] = {}
    ref, ref_c = None, -1
    for c, k in pairs.tolist():
        if c != ref_c:
            pts, scans = _reference_scans(poses, local, origins, c, REFERENCE_SPAN)
            ref_c = c
            ref = ReferenceSubmap(
                pts, cfg.resolution, cfg.likelihood_sigma, margin, scans, cfg.free_space_margin
            )
        q = queries.get(k)
        if q is None:
            q = queries[k] = _submap(poses, local, k, QUERY_SPAN)
        m = match_scan(ref, q, between(poses[c], poses[k]), SEARCH_WINDOW_XY, SEARCH_WINDOW_THETA, cfg)
        if m is None or m.inlier_fraction < MIN_INLIER_FRACTION or m.ambiguity > cfg.max_ambiguity:
            continue
        if not m.free_violation <= cfg.max_free_violation:  # NaN: not measured (refused)
            continue
        found.append(AlignmentConstraint(c, k, m.pose.copy(), m.covariance.copy(), m.inlier_fraction, True))
    return found


def agreeing(poses: np.ndarray, cons: list[AlignmentConstraint]) -> list[AlignmentConstraint]:
    """The constraints that another one agrees with: a constraint of another query keyframe whose
    query submap shares no keyframe with this one's (more than ``2 QUERY_SPAN`` keyframes apart),
    such that the two query poses they imply in the map keep the estimate's relative pose within
    ``AGREE_XY`` (+ ``AGREE_XY_PER_M`` per metre between them) and ``AGREE_THETA`` (the closer's
    pairwise consistency). A lone match may be an aliased place; two independent ones that agree
    are the evidence."""
    if len(cons) < 2:
        return []
    q = np.array([c.query for c in cons])
    implied = np.array([compose(poses[c.reference], c.relative) for c in cons])  # query in map
    n = len(cons)
    a, b = np.triu_indices(n, 1)
    sep = np.abs(q[a] - q[b]) > 2 * QUERY_SPAN
    a, b = a[sep], b[sep]
    est = between_many(poses[q[a]], poses[q[b]])
    d = between_many(between_many(implied[a], implied[b]), est)
    ok = (np.hypot(d[:, 0], d[:, 1]) <= AGREE_XY + AGREE_XY_PER_M * np.hypot(est[:, 0], est[:, 1])) & (
        np.abs(wrap(d[:, 2])) <= AGREE_THETA
    )
    keep = np.zeros(n, bool)
    keep[a[ok]] = keep[b[ok]] = True
    return [c for c, k in zip(cons, keep, strict=True) if k]


def constraint_factor(con: AlignmentConstraint) -> gtsam.BetweenFactorPose2:
    """The constraint as a Huber-robust between-factor (covariance floored)."""
    noise = gtsam.noiseModel.Gaussian.Covariance(con.covariance + COVARIANCE_FLOOR)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_SCALE), noise)
    return gtsam.BetweenFactorPose2(key(con.reference), key(con.query), pose2(con.relative), robust)


def dense_constraints(
    poses: np.ndarray,
    odom_poses: np.ndarray,
    points: list[np.ndarray],
    radius: float,
    max_range: float,
    per_keyframe: int = 3,
    processes: int = 1,
    origins: list[np.ndarray] | None = None,
    config: LoopClosureConfig | None = None,
) -> list[AlignmentConstraint]:
    """All constraints at the estimate ``poses`` (K, 3, map); ``odom_poses`` (K, 3) give the travel;
    ``processes``: see :func:`align_pairs`. With ``origins`` (per keyframe the sensor origin in
    base_link) the pairs of the keyframes no ICP constraint ties are searched too
    (:func:`searched_constraints`, the closer's matcher settings from ``config``), but for those
    the ICP reached (:func:`reached_pairs`)."""
    steps = np.hypot(*np.diff(odom_poses[:, :2], axis=0).T)
    travel = np.concatenate(([0.0], np.cumsum(steps)))
    window = float(np.clip(field_of_view(points) - np.deg2rad(MIN_OVERLAP_DEG), np.deg2rad(30.0), np.pi))
    pairs = candidate_pairs(poses, travel, radius, window, per_keyframe)
    reached = reached_pairs(poses, points, pairs, max_range, processes)
    cons = _inliers_held(reached)
    if origins is None or not len(pairs):
        return cons
    tied = np.zeros(len(poses), bool)
    tied[[c.reference for c in cons] + [c.query for c in cons]] = True
    # a pair the ICP reached from the estimate (converged within its gates, too few inliers) is
    # not searched: the search, started there too, finds the same basin (real logs: its matches
    # of such pairs within 5 cm / 0.8° of the ICP's) and only judges the inliers again
    code = pairs[:, 0] * len(poses) + pairs[:, 1]
    near = np.isin(code, [c.reference * len(poses) + c.query for c in reached])
    untied = pairs[(~tied[pairs[:, 0]] | ~tied[pairs[:, 1]]) & ~near]
    cfg = (config or LoopClosureConfig()).model_copy(update={"max_point_range": max_range})
    return cons + searched_constraints(poses, points, origins, untied, cfg, processes)


def align_passes(ctx: BackendContext, config: LoopClosureConfig, processes: int = 1) -> None:
    """Dense constraints between passes at the converged estimate, re-optimised (LM batch),
    ``config.final_alignment_rounds`` times; each round's constraints replace the previous
    round's; the first round also searches the keyframes its ICP does not tie
    (:func:`searched_constraints`). Logged as ``final_alignment`` per round (``searched``: how
    many of its constraints the search found)."""
    graph = ctx.graph
    odom = ctx.store.odometry()
    factors: list = []
    for round_ in range(config.final_alignment_rounds):
        t0 = time.perf_counter()
        cons = dense_constraints(
            graph.estimates(),
            odom,
            ctx.store.points,
            config.final_alignment_radius,
            config.max_point_range,
            processes=processes,
            # the search repairs what the ICP cannot reach once; the next rounds' ICP, started at
            # the re-optimised estimate, holds it (ACES: 20 searched in round 1, none left in round 2)
            origins=list(ctx.store.origins) if round_ == 0 else None,
            config=config,
        )
        new = [constraint_factor(c) for c in cons]
        graph.replace_factors([i for i in graph.factor_indices(factors) if i >= 0], new)
        factors = new
        before = graph.error()
        graph.optimize_batch(incremental=False)
        ctx.log.record(
            "final_alignment",
            f"round {round_ + 1}: {len(cons)} constraints between passes",
            constraints=len(cons),
            searched=sum(c.searched for c in cons),
            error_before=before,
            error_after=graph.error(),
            seconds=time.perf_counter() - t0,
        )
