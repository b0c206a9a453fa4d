"""Trajectories as arrays: an (N, 4) ``stamp, x, y, theta`` array (seconds, metres, radians;
``base_link`` in ``map``), checked, and its poses found or interpolated at given stamps."""

from __future__ import annotations

import numpy as np

from frslam_graph.errors import TrajectoryError
from frslam_graph.se2 import interpolate_poses


def as_trajectory(trajectory: np.ndarray, what: str = "trajectory") -> np.ndarray:
    """Check an (N, 4) ``stamp, x, y, theta`` array; TrajectoryError when it is not one."""
    traj = np.asarray(trajectory, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 4:
        raise TrajectoryError(
            f"expected an (N, 4) array stamp, x, y, theta; got shape {traj.shape}", where=what
        )
    if not np.isfinite(traj).all():
        raise TrajectoryError("non-finite values", where=what)
    return traj


def nearest_pose(stamps: np.ndarray, query: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest of the sorted ``stamps`` for each query, and whether it is within tolerance."""
    query = np.asarray(query, dtype=np.float64)
    if len(stamps) == 1:
        idx = np.zeros(len(query), dtype=np.intp)
    else:
        hi = np.clip(np.searchsorted(stamps, query), 1, len(stamps) - 1)
        lo = hi - 1
        idx = np.where(query - stamps[lo] <= stamps[hi] - query, lo, hi)
    ok = np.abs(stamps[idx] - query) <= tolerance
    return idx, ok


def interpolate_trajectory(
    traj: np.ndarray, stamps: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a sorted (N, 4) trajectory at ``stamps`` by linear interpolation (heading unwrapped).

    Returns ((K, 4) poses, (K,) ok); ok is False outside the trajectory or where the two poses
    around a stamp are more than ``max_gap`` seconds apart.
    """
    t = traj[:, 0]
    stamps = np.asarray(stamps, dtype=np.float64)
    hi = np.clip(np.searchsorted(t, stamps, side="left"), 1, max(len(t) - 1, 1))
    lo = hi - 1
    inside = (stamps >= t[0]) & (stamps <= t[-1])
    if len(t) > 1:
        ok = inside & ((t[hi] - t[lo] <= max_gap) | (stamps == t[lo]) | (stamps == t[hi]))
    else:
        ok = inside
    out = np.column_stack((stamps, interpolate_poses(t, traj[:, 1:4], stamps)))
    return out, ok
