"""The relation-based error of Kümmerle et al. (2009) ("On measuring the accuracy of SLAM
algorithms", Autonomous Robots).

Reference relations are (K, 5) ``t1, t2, x, y, yaw``: the pose at ``t2`` in the frame of the pose
at ``t1`` (metres, radians). For each relation the estimated relative pose is
``δ* = x(t1)⁻¹ ⊕ x(t2)``, with each stamp matched to the nearest trajectory pose within
``tolerance`` seconds; the error is ``δ ⊖ δ*``: translational ``|t - t*|`` (m) and rotational
``|wrap(θ - θ*)|`` (deg). We report mean ± std of both (the figures of Kümmerle et al. and of Hess
et al. 2016) and the mean squares, and count relations that found no pose.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from frslam_graph.errors import TrajectoryError
from frslam_graph.evaluation.trajectory import as_trajectory, interpolate_trajectory, nearest_pose
from frslam_graph.se2 import wrap_atan2


# ---------------------------------------------------------------------------- relation metric
@dataclass(frozen=True)
class RelationResult:
    """Relation-based error (Kümmerle et al. 2009) of a trajectory."""

    trans_mean: float  # m, mean of |t - t*|
    trans_std: float  # m
    rot_mean: float  # deg, mean of |wrap(θ - θ*)|
    rot_std: float  # deg
    trans_sq_mean: float  # m², mean of |t - t*|²
    rot_sq_mean: float  # deg², mean of wrap(θ - θ*)²
    matched: int  # relations evaluated
    unmatched: int  # relations with a stamp that found no pose within the tolerance
    trans_errors: np.ndarray  # (matched,) m
    rot_errors: np.ndarray  # (matched,) deg

    def __str__(self) -> str:
        return (
            f"{self.trans_mean:.4f} ± {self.trans_std:.4f} m, {self.rot_mean:.3f} ± {self.rot_std:.3f} deg "
            f"over {self.matched} relations ({self.unmatched} unmatched)"
        )


def relative_poses(
    trajectory: np.ndarray,
    t1: np.ndarray,
    t2: np.ndarray,
    tolerance: float = 0.01,
    interpolate: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Relative poses ``x(t1)⁻¹ ⊕ x(t2)`` of ``trajectory`` (N, 4), (K, 3): x, y (m, in the frame
    of the pose at t1) and θ(t2) - θ(t1) (rad, not wrapped); and which of the K pairs found poses.

    Each stamp takes the nearest pose within ``tolerance`` seconds, or with ``interpolate``
    (seconds) the pose interpolated between poses at most that far apart (as
    :func:`relation_error`). Rows of pairs without poses are NaN.
    """
    traj = as_trajectory(trajectory)
    if len(traj) == 0:
        raise TrajectoryError("empty trajectory", where="trajectory")
    traj = traj[np.argsort(traj[:, 0], kind="stable")]
    if interpolate is not None:
        xi, ok_i = interpolate_trajectory(traj, t1, interpolate)
        xj, ok_j = interpolate_trajectory(traj, t2, interpolate)
    else:
        i, ok_i = nearest_pose(traj[:, 0], t1, tolerance)
        j, ok_j = nearest_pose(traj[:, 0], t2, tolerance)
        xi, xj = traj[i], traj[j]
    ok = ok_i & ok_j
    c, s = np.cos(xi[:, 3]), np.sin(xi[:, 3])
    dx, dy = xj[:, 1] - xi[:, 1], xj[:, 2] - xi[:, 2]
    out = np.column_stack((c * dx + s * dy, -s * dx + c * dy, xj[:, 3] - xi[:, 3]))
    out[~ok] = np.nan
    return out, ok


def relation_error(
    trajectory: np.ndarray,
    relations: np.ndarray,
    tolerance: float = 0.01,
    interpolate: float | None = None,
) -> RelationResult:
    """Relation-based error of ``trajectory`` (N, 4) against ``relations`` (K, 5) ``t1, t2, x, y,
    yaw`` (:func:`~frslam_graph.evaluation.trajectory_io.load_relations` reads a relations file).

    Each relation stamp takes the nearest pose within ``tolerance`` seconds; with ``interpolate``
    (seconds) a keyframe trajectory is instead interpolated at the stamps, between poses at most
    that far apart. Relations left without a pose are counted in ``unmatched``.
    """
    traj = as_trajectory(trajectory)
    if isinstance(relations, str | os.PathLike):
        raise TrajectoryError(
            "expected a (K, 5) array t1, t2, x, y, yaw, not a path "
            "(frslam_graph.evaluation.trajectory_io.load_relations reads a relations file)",
            where="relations",
        )
    rel = np.asarray(relations, dtype=np.float64)
    if rel.ndim != 2 or rel.shape[1] != 5:
        raise TrajectoryError(
            f"expected (K, 5) relations t1, t2, x, y, yaw; got shape {rel.shape}", where="relations"
        )
    if len(traj) == 0:
        raise TrajectoryError("empty trajectory", where="trajectory")
    est, ok = relative_poses(traj, rel[:, 0], rel[:, 1], tolerance, interpolate)
    est, r = est[ok], rel[ok]
    t_err = np.hypot(r[:, 2] - est[:, 0], r[:, 3] - est[:, 1])
    d_th = r[:, 4] - est[:, 2]
    r_err = np.degrees(np.abs(wrap_atan2(d_th)))
    n = int(ok.sum())

    def stat(f, a):
        return float(f(a)) if n else float("nan")

    return RelationResult(
        trans_mean=stat(np.mean, t_err),
        trans_std=stat(np.std, t_err),
        rot_mean=stat(np.mean, r_err),
        rot_std=stat(np.std, r_err),
        trans_sq_mean=stat(np.mean, t_err**2),
        rot_sq_mean=stat(np.mean, r_err**2),
        matched=n,
        unmatched=int(len(rel) - n),
        trans_errors=t_err,
        rot_errors=r_err,
    )
