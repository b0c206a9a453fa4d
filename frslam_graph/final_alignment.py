"""Final alignment: dense scan-to-submap constraints between passes at the end of a run.

Loop closure (:mod:`frslam_graph.loop_closure`) adds a closure now and then while the robot
drives, searching widely because the estimate may have drifted. Once the graph has converged
(:meth:`FRSlam.finish`), every keyframe's estimate is within centimetres of the truth, so
every place the robot passed more than once can be tied cheaply: for each keyframe, the
keyframes of *other passes* near it (``map`` positions within ``final_alignment_radius``,
headings whose fields of view overlap) are matched by point-to-line ICP, started at the
current estimate, of the keyframe's query submap (itself and its neighbours) onto the other's
reference submap. A match that converges with most points on the reference and moves the
estimate by little is a between-factor under a Huber kernel; the graph is re-optimised (LM
batch) and the constraints are computed again at the new estimate (``final_alignment_rounds``).
This is the dense constraint set offline mappers end with (Cartographer's final optimisation,
Karto's and GraphMapping's scan matching against all near poses). It runs only with loop
closure on (``loop_closure.enabled``): these are loop closures too.

Frames: keyframe points are (M, 2) in ``base_link``; poses are ``base_link`` in ``map``
(x, y, theta; metres, radians). The constraint ``relative`` is x_reference⁻¹ ⊕ x_query with
its 3×3 covariance in GTSAM's Pose2 tangent (body frame of the query).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from frslam_graph.factors.between import pose2
from frslam_graph.graph import key
from frslam_graph.motion_model import between, wrap
from frslam_graph.submap_matching import (
    ReferenceSubmap,
    icp_point_to_line,
    transform_points,
    voxel_downsample,
)

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


@dataclass(frozen=True, slots=True)
class AlignmentConstraint:
    """x_reference⁻¹ ⊕ x_query measured by ICP, with its covariance and inlier fraction."""

    reference: int
    query: int
    relative: np.ndarray
    covariance: np.ndarray
    inlier_fraction: float


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


def _submap(poses: np.ndarray, points: list[np.ndarray], i: int, span: int, max_range: float) -> np.ndarray:
    """Points of keyframes i-span..i+span in keyframe i's frame (voxel-thinned)."""
    lo, hi = max(0, i - span), min(len(points) - 1, i + span)
    parts = []
    for j in range(lo, hi + 1):
        p = np.asarray(points[j], dtype=np.float64)
        p = p[np.hypot(p[:, 0], p[:, 1]) <= max_range]
        parts.append(transform_points(between(poses[i], poses[j]), p))
    pts = np.concatenate(parts) if parts else np.zeros((0, 2))
    return voxel_downsample(pts, RESOLUTION)


def align_pairs(
    poses: np.ndarray, points: list[np.ndarray], pairs: np.ndarray, max_range: float
) -> list[AlignmentConstraint]:
    """ICP of each pair's query submap onto its reference submap, from the current estimate."""
    out: list[AlignmentConstraint] = []
    if len(pairs) == 0:
        return out
    order = np.argsort(pairs[:, 0], kind="stable")  # reference submaps are built once each
    ref_index, ref = -1, None
    for c, k in pairs[order]:
        if c != ref_index:
            ref_index = int(c)
            pts = _submap(poses, points, ref_index, REFERENCE_SPAN, max_range)
            ref = (
                ReferenceSubmap(pts, RESOLUTION, INLIER_DISTANCE, ICP_MAX_DISTANCE)
                if len(pts) >= 30
                else None
            )
        if ref is None:
            continue
        query = _submap(poses, points, int(k), QUERY_SPAN, max_range)
        if len(query) < 30:
            continue
        start = between(poses[c], poses[k])
        if ref.inlier_fraction(query, start, 2.0 * INLIER_DISTANCE) < MIN_START_OVERLAP:
            continue  # the two barely overlap at the converged estimate: not worth an ICP
        res = icp_point_to_line(ref, query, start, ICP_ITERATIONS, ICP_MAX_DISTANCE, ICP_KERNEL, ICP_SIGMA)
        if res is None:
            continue
        x, cov = res
        if (
            np.hypot(*(x[:2] - start[:2])) > MAX_CORRECTION_XY
            or abs(wrap(x[2] - start[2])) > MAX_CORRECTION_THETA
        ):
            continue
        inliers = ref.inlier_fraction(query, x, INLIER_DISTANCE)
        if inliers < MIN_INLIER_FRACTION or not np.all(np.isfinite(cov)):
            continue
        out.append(AlignmentConstraint(int(c), int(k), x, cov, inliers))
    return out


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
) -> list[AlignmentConstraint]:
    """All constraints at the estimate ``poses`` (K, 3, map); ``odom_poses`` (K, 3) give the travel."""
    steps = np.hypot(*np.diff(odom_poses[:, :2], axis=0).T)
    travel = np.concatenate(([0.0], np.cumsum(steps)))
    window = float(np.clip(field_of_view(points) - np.deg2rad(MIN_OVERLAP_DEG), np.deg2rad(30.0), np.pi))
    pairs = candidate_pairs(poses, travel, radius, window, per_keyframe)
    return align_pairs(poses, points, pairs, max_range)
