"""Odometry between-factors for the Pose2 graph and Gaussian noise-model helpers.

Covariances are 3×3 over GTSAM's Pose2 tangent (body frame of the measured relative pose):
(x, y) in metres, theta in radians. Floors are standard deviations added in quadrature to the
diagonal so a (near) singular covariance from an over-confident front end still gives a
well-posed factor.
"""

from __future__ import annotations

import gtsam
import numpy as np

from frslam_graph.errors import FrslamError


def regularise_covariance(cov: np.ndarray, floor_xy: float = 0.0, floor_theta: float = 0.0) -> np.ndarray:
    """Symmetric positive-definite copy of ``cov`` with floors (std devs) added to the diagonal."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        raise FrslamError(f"covariance must be a finite 3×3 matrix, got shape {c.shape}", where="covariance")
    c = 0.5 * (c + c.T) + np.diag([floor_xy**2, floor_xy**2, floor_theta**2])
    w, v = np.linalg.eigh(c)
    if w[0] <= 0.0:
        w = np.maximum(w, max(1e-12, 1e-9 * float(w[-1])))
        c = (v * w) @ v.T
    return c


def gaussian_noise(
    cov: np.ndarray, floor_xy: float = 0.0, floor_theta: float = 0.0
) -> gtsam.noiseModel.Gaussian:
    """``noiseModel.Gaussian.Covariance`` of a regularised 3×3 covariance."""
    return gtsam.noiseModel.Gaussian.Covariance(regularise_covariance(cov, floor_xy, floor_theta))


def pose2(p: np.ndarray | tuple[float, float, float]) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def between_factor(
    key_i: int,
    key_j: int,
    relative: np.ndarray,
    cov: np.ndarray,
    floor_xy: float = 0.0,
    floor_theta: float = 0.0,
) -> gtsam.BetweenFactorPose2:
    """Pose2 between-factor x_i⁻¹ ⊕ x_j = relative, with a (floored) Gaussian covariance."""
    rel = np.asarray(relative, dtype=np.float64).reshape(-1)
    if rel.shape != (3,) or not np.all(np.isfinite(rel)):
        raise FrslamError(f"relative pose must be finite (x, y, theta), got {rel!r}", where="relative")
    return gtsam.BetweenFactorPose2(key_i, key_j, pose2(rel), gaussian_noise(cov, floor_xy, floor_theta))


__all__ = ["between_factor", "gaussian_noise", "pose2", "regularise_covariance"]
