"""Robust floor-plan priors on keyframe poses (map frame; metres, radians).

A floor-plan registration or relocalisation is a *measurement* of a keyframe's pose in ``map``
with a covariance; it may be wrong (similar rooms), so it enters the graph through an M-estimator
(Cauchy or Geman-McClure by default: Huber's linear tail still lets a gross outlier bend the
trajectory). ``kind`` selects a full ``PriorFactorPose2`` or a partial prior on the translation
(``PoseTranslationPrior2D``) or the heading (``PoseRotationPrior2D``). The kernel parameter is in
whitened units (standard deviations).
"""

from __future__ import annotations

from typing import Literal

import gtsam
import numpy as np
from frslam_graph.factors.between import pose2, regularise_covariance

from frslam_graph.errors import ConfigError, FrslamError

PriorKind = Literal["full", "translation", "rotation"]
KernelName = Literal["cauchy", "geman_mcclure", "huber", "none"]


def m_estimator(kernel: KernelName, param: float = 1.0):
    """The GTSAM M-estimator for a kernel name (None for 'none')."""
    est = gtsam.noiseModel.mEstimator
    if kernel == "cauchy":
        return est.Cauchy.Create(param)
    if kernel == "geman_mcclure":
        return est.GemanMcClure.Create(param)
    if kernel == "huber":
        return est.Huber.Create(param)
    if kernel == "none":
        return None
    raise ConfigError(
        f"unknown robust kernel {kernel!r} (expected 'cauchy', 'geman_mcclure', 'huber' or 'none')",
        where="graph.prior_kernel",
    )


def robust_noise(cov: np.ndarray, kernel: KernelName = "cauchy", param: float = 1.0):
    """``noiseModel.Robust.Create(mEstimator, Gaussian.Covariance(cov))`` (plain Gaussian for 'none')."""
    gauss = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=np.float64))
    est = m_estimator(kernel, param)
    return gauss if est is None else gtsam.noiseModel.Robust.Create(est, gauss)


def prior_covariance(
    cov: np.ndarray, kind: PriorKind = "full", floor_xy: float = 0.0, floor_theta: float = 0.0
) -> np.ndarray:
    """The (floored) covariance block a prior of this kind uses: 3×3, 2×2 (x, y) or 1×1 (theta)."""
    c = regularise_covariance(cov, floor_xy, floor_theta)
    if kind == "full":
        return c
    if kind == "translation":
        return c[:2, :2]
    if kind == "rotation":
        return c[2:, 2:]
    raise FrslamError(
        f"unknown prior kind {kind!r} (expected 'full', 'translation' or 'rotation')", where="kind"
    )


def floorplan_prior(
    key: int,
    pose: np.ndarray,
    cov: np.ndarray,
    kind: PriorKind = "full",
    kernel: KernelName = "cauchy",
    param: float = 1.0,
    floor_xy: float = 0.0,
    floor_theta: float = 0.0,
) -> gtsam.NonlinearFactor:
    """A robust prior on the Pose2 variable ``key`` at ``pose`` (x, y, theta) in map.

    ``cov`` is always the full 3×3 tangent covariance of the measurement; partial priors use its
    translation or heading block.
    """
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise FrslamError(f"prior pose must be finite (x, y, theta), got {p!r}", where="pose")
    noise = robust_noise(prior_covariance(cov, kind, floor_xy, floor_theta), kernel, param)
    if kind == "full":
        return gtsam.PriorFactorPose2(key, pose2(p), noise)
    if kind == "translation":
        return gtsam.PoseTranslationPrior2D(key, pose2(p), noise)
    return gtsam.PoseRotationPrior2D(key, pose2(p), noise)


def prior_chi2(
    pose_estimate: np.ndarray, pose: np.ndarray, cov: np.ndarray, kind: PriorKind = "full"
) -> tuple[np.ndarray, float]:
    """Residual (estimate vs measured, tangent at the measurement) and its squared Mahalanobis norm.

    This is the *Gaussian* (un-robustified) error: large values flag a prior inconsistent with
    the rest of the graph, whatever weight the kernel gave it.
    """
    e = np.asarray(gtsam.Pose2.Logmap(pose2(pose).between(pose2(pose_estimate))))
    if kind == "translation":
        # PoseTranslationPrior2D compares translations in map
        e = np.asarray(pose_estimate[:2], float) - np.asarray(pose[:2], float)
        c = np.asarray(cov)[:2, :2]
    elif kind == "rotation":
        e = e[2:]
        c = np.asarray(cov)[2:, 2:]
    else:
        c = np.asarray(cov)
    return e, float(e @ np.linalg.solve(c, e))


__all__ = ["floorplan_prior", "m_estimator", "prior_chi2", "prior_covariance", "robust_noise"]
