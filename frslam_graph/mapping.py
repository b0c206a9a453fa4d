"""LiDAR occupancy map from keyframe scans at their current pose estimates (log-odds).

Units: metres, radians, frame ``map``. Each keyframe contributes its planar end points (in
``base_link``) and the sensor origin; free space is the polygon sensor -> end points (beam order)
filled with OpenCV at sub-cell precision in a window around the scan (no per-beam Python loop),
each cell counted at most once per scan; end cells are hits and never carved by their own scan.

:class:`OccupancyMapper` keeps per-cell hit / miss counts on a grid that grows as needed and is
*incremental*: new keyframes are added, keyframes whose pose estimate moved (after a prior or a
loop closure) are subtracted at their old pose and added at the new one (exact, counts are
integers), so repeated map requests during a run cost little. Cell log-odds =
hits · l_hit + misses · l_miss; occupied (100) above ``occupied_logodds``, free (0) below
``free_logodds``, unknown (-1) otherwise. Output follows nav_msgs/OccupancyGrid: row 0 is the
lowest y, ``origin`` the lower-left corner of cell (0, 0), yaw 0.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from frslam_graph.motion_model import compose_many, wrap

L_HIT = 0.85
L_MISS = -0.4
_SHIFT = 4
_SUB = 1 << _SHIFT
_GROW = 64  # cells of slack added when the grid grows


class OccupancyMapper:
    """Incremental hit / miss counts of keyframe scans (see module docstring)."""

    def __init__(
        self,
        resolution: float = 0.05,
        pose_tolerance_xy: float | None = None,
        pose_tolerance_theta: float = np.deg2rad(0.2),
        l_hit: float = L_HIT,
        l_miss: float = L_MISS,
        occupied_logodds: float = 0.5,
        free_logodds: float = -0.3,
    ):
        if not (np.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be positive, got {resolution!r}")
        self.resolution = float(resolution)
        self.tol_xy = 0.25 * self.resolution if pose_tolerance_xy is None else float(pose_tolerance_xy)
        self.tol_th = float(pose_tolerance_theta)
        self.l_hit, self.l_miss = l_hit, l_miss
        self.occupied_logodds, self.free_logodds = occupied_logodds, free_logodds
        self._hits = np.zeros((0, 0), np.int32)
        self._misses = np.zeros((0, 0), np.int32)
        self._c0 = np.zeros(2, np.int64)  # global cell (ix, iy) of array element [0, 0]
        self._poses: list[np.ndarray | None] = []  # pose each keyframe is inserted at

    def __len__(self) -> int:
        return sum(p is not None for p in self._poses)

    # ------------------------------------------------------------------ updates
    def update(
        self,
        poses: np.ndarray,
        scans: Sequence[np.ndarray],
        origins: Sequence[np.ndarray] | None = None,
    ) -> int:
        """Bring the counts to ``poses`` (K, 3) for keyframe scans ``scans[k]`` (M_k, 2) in base_link.

        Keyframes beyond the ones known are added; known ones are re-inserted when their pose
        moved more than the tolerance. Returns the number of scans (re-)inserted.
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if len(poses) != len(scans):
            raise ValueError(f"{len(poses)} poses for {len(scans)} scans")
        if len(poses) < len(self._poses):  # fewer keyframes than before: start again
            self.reset()
        n_old = len(self._poses)
        moved = []
        if n_old:
            old = np.array([p if p is not None else np.full(3, np.nan) for p in self._poses])
            d_xy = np.hypot(*(poses[:n_old, :2] - old[:, :2]).T)
            d_th = np.abs(wrap(poses[:n_old, 2] - old[:, 2]))
            moved = np.flatnonzero(~((d_xy <= self.tol_xy) & (d_th <= self.tol_th))).tolist()
        if n_old and len(moved) > 0.6 * n_old:
            self.reset()
            n_old, moved = 0, []
        count = 0
        for k in moved:
            o = self._origin(origins, k)
            if self._poses[k] is not None:
                self._insert(self._poses[k], scans[k], o, -1)
            self._poses[k] = None
            if self._insert(poses[k], scans[k], o, +1):
                self._poses[k] = poses[k].copy()
            count += 1
        for k in range(n_old, len(poses)):
            ok = self._insert(poses[k], scans[k], self._origin(origins, k), +1)
            self._poses.append(poses[k].copy() if ok else None)
            count += 1
        return count

    def reset(self) -> None:
        self._hits = np.zeros((0, 0), np.int32)
        self._misses = np.zeros((0, 0), np.int32)
        self._poses = []

    @staticmethod
    def _origin(origins, k) -> np.ndarray:
        return np.zeros(2) if origins is None else np.asarray(origins[k], dtype=np.float64)[:2]

    def _insert(self, pose: np.ndarray, pts: np.ndarray, origin: np.ndarray, sign: int) -> bool:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 2:
            return False
        ow = compose_many(pose, np.array([[origin[0], origin[1], 0.0]]))[0, :2]
        ew = compose_many(pose, np.column_stack((pts, np.zeros(len(pts)))))[:, :2]
        poly = np.vstack((ow, ew)) / self.resolution  # global cell units
        lo = np.floor(poly.min(axis=0)).astype(np.int64)
        hi = np.floor(poly.max(axis=0)).astype(np.int64) + 1
        self._ensure(lo, hi)
        a0 = lo - self._c0  # window in array indices
        shape = (int(hi[1] - lo[1]), int(hi[0] - lo[0]))
        mask = np.zeros(shape, dtype=np.uint8)
        pix = np.round((poly - lo - 0.5) * _SUB).astype(np.int32)  # cell centres at integer + 0.5
        cv2.fillPoly(mask, [pix.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        hit = np.floor(ew / self.resolution).astype(np.int64) - lo
        key = np.unique(hit[:, 1] * shape[1] + hit[:, 0])
        hr, hc = np.divmod(key, shape[1])
        mask[hr, hc] = 0
        ys, xs = slice(a0[1], a0[1] + shape[0]), slice(a0[0], a0[0] + shape[1])
        if sign > 0:
            self._misses[ys, xs] += mask
            self._hits[hr + a0[1], hc + a0[0]] += 1
        else:
            self._misses[ys, xs] -= mask
            self._hits[hr + a0[1], hc + a0[0]] -= 1
        return True

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the arrays so global cells [lo, hi) fit."""
        h, w = self._hits.shape
        c1 = self._c0 + np.array([w, h])
        if h and w and np.all(lo >= self._c0) and np.all(hi <= c1):
            return
        if not (h and w):
            new0, new1 = lo - _GROW, hi + _GROW
        else:
            new0 = np.minimum(self._c0, lo - _GROW)
            new1 = np.maximum(c1, hi + _GROW)
        nw, nh = (new1 - new0).tolist()
        hits = np.zeros((nh, nw), np.int32)
        misses = np.zeros((nh, nw), np.int32)
        if h and w:
            off = self._c0 - new0
            hits[off[1] : off[1] + h, off[0] : off[0] + w] = self._hits
            misses[off[1] : off[1] + h, off[0] : off[0] + w] = self._misses
        self._hits, self._misses, self._c0 = hits, misses, new0

    # ------------------------------------------------------------------ output
    def arrays(self, margin: float = 0.5) -> tuple[np.ndarray, float, tuple[float, float, float]]:
        """(data int8 (H, W), resolution, origin (x, y, 0)) cropped to the observed cells + margin."""
        seen = (self._hits > 0) | (self._misses > 0)
        if not seen.any():
            return np.full((1, 1), -1, np.int8), self.resolution, (0.0, 0.0, 0.0)
        rows = np.flatnonzero(seen.any(axis=1))
        cols = np.flatnonzero(seen.any(axis=0))
        m = int(np.ceil(margin / self.resolution))
        r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, seen.shape[0])
        c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, seen.shape[1])
        hits = self._hits[r0:r1, c0:c1]
        misses = self._misses[r0:r1, c0:c1]
        logodds = hits * self.l_hit + misses * self.l_miss
        data = np.full(hits.shape, -1, dtype=np.int8)
        data[(logodds < self.free_logodds) & (misses > 0)] = 0
        data[(logodds > self.occupied_logodds) & (hits > 0)] = 100
        origin = ((self._c0[0] + c0) * self.resolution, (self._c0[1] + r0) * self.resolution, 0.0)
        return data, self.resolution, (float(origin[0]), float(origin[1]), 0.0)

    def grid(self, margin: float = 0.5):
        """The map as :class:`frslam_graph.occupancy.OccupancyGrid`."""
        from frslam_graph.occupancy import OccupancyGrid

        data, res, origin = self.arrays(margin)
        return OccupancyGrid(data, res, origin)


def occupancy_arrays(
    poses: np.ndarray,
    scans: Sequence[np.ndarray],
    origins: Sequence[np.ndarray] | None = None,
    resolution: float = 0.05,
    margin: float = 0.5,
    **kwargs,
) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """One-shot occupancy of keyframe scans: (data int8 (H, W), resolution, origin (x, y, 0)).

    ``poses`` (K, 3): base_link in map. ``scans[k]`` (M_k, 2): end points in base_link.
    ``origins[k]``: the sensor position (x, y) in base_link (default (0, 0)).
    """
    mapper = OccupancyMapper(resolution, **kwargs)
    mapper.update(poses, scans, origins)
    return mapper.arrays(margin)


def occupancy_grid(
    poses: np.ndarray,
    scans: Sequence[np.ndarray],
    origins: Sequence[np.ndarray] | None = None,
    resolution: float = 0.05,
    **kwargs,
):
    """:func:`occupancy_arrays` wrapped in :class:`frslam_graph.occupancy.OccupancyGrid`."""
    from frslam_graph.occupancy import OccupancyGrid

    data, res, origin = occupancy_arrays(poses, scans, origins, resolution, **kwargs)
    return OccupancyGrid(data, res, origin)


__all__ = ["OccupancyMapper", "occupancy_arrays", "occupancy_grid"]
