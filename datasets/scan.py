"""The one record every reader yields: a planar laser scan in the sensor frame.

Units: seconds, metres, radians. ``ranges[i]`` is measured along ``angles[i]`` (counter-clockwise
from the sensor's x axis, REP-103). Invalid beams are ``nan`` in ``ranges`` (and absent from
``points``). ``odom`` is the wheel-odometry pose (x, y, theta) of ``base_link`` in ``odom`` at
``stamp``, or ``None`` when the recording has none. ``sensor_offset`` is the laser's pose in
``base_link`` (x, y, yaw).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True)
class Scan:
    stamp: float
    ranges: np.ndarray  # (N,) float64, nan = no return
    angles: np.ndarray  # (N,) float64
    odom: tuple[float, float, float] | None = None
    max_range: float = float("inf")
    sensor_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _points: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def points(self) -> np.ndarray:
        """(M, 2) end points of the valid beams in the sensor frame, metres."""
        if self._points is not None:
            return self._points
        r = self.ranges
        ok = np.isfinite(r) & (r > 0.0) & (r < self.max_range)
        return np.column_stack((r[ok] * np.cos(self.angles[ok]), r[ok] * np.sin(self.angles[ok])))

    @classmethod
    def from_points(
        cls,
        stamp: float,
        points: np.ndarray,
        odom: tuple[float, float, float] | None = None,
        max_range: float = float("inf"),
        sensor_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> Scan:
        """A scan given as planar points (from a sliced point cloud); ranges/angles are derived."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ranges = np.hypot(pts[:, 0], pts[:, 1])
        angles = np.arctan2(pts[:, 1], pts[:, 0])
        return cls(stamp, ranges, angles, odom, max_range, sensor_offset, pts)
