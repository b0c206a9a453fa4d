"""SE(2) algebra on (x, y, theta) arrays: metres, radians.

Poses are ``(x, y, theta)``; ``(N, 3)`` arrays hold one pose per row.
"""

from __future__ import annotations

import numpy as np


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(M, 3) SE(2) poses linearly interpolated at ``query`` from ``poses`` (N, 3) at increasing
    ``stamps`` (N,): x, y linearly, the heading unwrapped then wrapped to (-pi, pi]. Queries
    outside the stamps take the end poses (``np.interp``)."""
    q = np.asarray(query, dtype=np.float64)
    heading = np.interp(q, stamps, np.unwrap(poses[:, 2]))
    return np.column_stack(
        (
            np.interp(q, stamps, poses[:, 0]),
            np.interp(q, stamps, poses[:, 1]),
            np.arctan2(np.sin(heading), np.cos(heading)),
        )
    )
