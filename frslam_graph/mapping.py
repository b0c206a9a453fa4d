"""LiDAR occupancy map from keyframe scans at their current pose estimates (log-odds).

Units: metres, radians, frame ``map``. Each keyframe contributes its planar end points (in
``base_link``) and the sensor origin; free space is the polygon sensor -> end points (beam order)
filled with OpenCV at sub-cell precision in a window around the scan (no per-beam Python loop),
each cell counted at most once per scan; end cells are hits and never carved by their own scan. Cells end up occupied (100) when their log-odds exceed ``occupied_logodds``, free (0)
when below ``free_logodds``, unknown (-1) otherwise. The output follows nav_msgs/OccupancyGrid:
row 0 is the lowest y, ``origin`` the lower-left corner of cell (0, 0), yaw 0.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from frslam_graph.motion_model import compose_many

L_HIT = 0.85
L_MISS = -0.4
_SHIFT = 4
_SUB = 1 << _SHIFT


def occupancy_arrays(
    poses: np.ndarray,
    scans: Sequence[np.ndarray],
    origins: Sequence[np.ndarray] | None = None,
    resolution: float = 0.05,
    margin: float = 0.5,
    occupied_logodds: float = 0.5,
    free_logodds: float = -0.3,
    l_hit: float = L_HIT,
    l_miss: float = L_MISS,
    clamp: float = 5.0,
) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """Occupancy of keyframe scans: (data int8 (H, W), resolution, origin (x, y, 0)).

    ``poses`` (K, 3): base_link in map. ``scans[k]`` (M_k, 2): end points in base_link.
    ``origins[k]``: the sensor position (x, y) in base_link (default (0, 0)).
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(scans):
        raise ValueError(f"{len(poses)} poses for {len(scans)} scans")
    ends_w, orig_w = [], []
    for k, (pose, pts) in enumerate(zip(poses, scans, strict=True)):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        o = np.zeros(2) if origins is None else np.asarray(origins[k], float)[:2]
        ow = compose_many(pose, np.array([[o[0], o[1], 0.0]]))[0, :2]
        ew = compose_many(pose, np.column_stack((pts, np.zeros(len(pts)))))[:, :2]
        ends_w.append(ew)
        orig_w.append(ow)
    allpts = np.vstack([*ends_w, np.array(orig_w).reshape(-1, 2)]) if ends_w else np.zeros((0, 2))
    if len(allpts) == 0:
        return np.full((1, 1), -1, np.int8), float(resolution), (0.0, 0.0, 0.0)
    lo = np.floor((allpts.min(axis=0) - margin) / resolution) * resolution
    hi = allpts.max(axis=0) + margin
    w, h = (np.ceil((hi - lo) / resolution).astype(int) + 1).tolist()
    logodds = np.zeros((h, w), dtype=np.float64)
    flat = logodds.reshape(-1)
    for ew, ow in zip(ends_w, orig_w, strict=True):
        if len(ew) < 2:
            continue
        # free space: the polygon sensor -> end points (beam order), filled with sub-cell precision
        poly = np.vstack((ow, ew))
        c = (poly - lo) / resolution
        c0 = np.floor(c.min(axis=0)).astype(int)
        c1 = np.ceil(c.max(axis=0)).astype(int) + 1
        c0 = np.maximum(c0, 0)
        c1 = np.minimum(c1, [w, h])
        mask = np.zeros((c1[1] - c0[1], c1[0] - c0[0]), dtype=np.uint8)
        pix = np.round((c - c0 - 0.5) * _SUB).astype(np.int32)  # cell centres at integer + 0.5
        cv2.fillPoly(mask, [pix.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        hit_cells = np.unique(_flat_cells(ew, lo, resolution, w, h))
        hr, hc = np.divmod(hit_cells, w)
        inside = (hr >= c0[1]) & (hr < c1[1]) & (hc >= c0[0]) & (hc < c1[0])
        mask[hr[inside] - c0[1], hc[inside] - c0[0]] = 0
        view = logodds[c0[1] : c1[1], c0[0] : c1[0]]
        view += l_miss * mask
        flat[hit_cells] += l_hit
        np.clip(view, -clamp, clamp, out=view)
    np.clip(logodds, -clamp, clamp, out=logodds)
    logodds = flat
    grid = np.full(h * w, -1, dtype=np.int8)
    grid[logodds < free_logodds] = 0
    grid[logodds > occupied_logodds] = 100
    return grid.reshape(h, w), float(resolution), (float(lo[0]), float(lo[1]), 0.0)


def _flat_cells(xy: np.ndarray, lo: np.ndarray, res: float, w: int, h: int) -> np.ndarray:
    c = np.floor((xy - lo) / res).astype(np.int64)
    c[:, 0] = np.clip(c[:, 0], 0, w - 1)
    c[:, 1] = np.clip(c[:, 1], 0, h - 1)
    return c[:, 1] * w + c[:, 0]


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


__all__ = ["occupancy_arrays", "occupancy_grid"]
