"""LiDAR map preprocessing of the FR-SLAM paper (Section III-A, eqs. 2–4), vectorised with OpenCV.

Steps on the map_server grey image I (free 254, unknown 205, occupied 0):

1. binarise, eq. (2): B = [I >= θ] (θ in grey levels; the default 250 keeps free cells only);
2. remove small connected components, eq. (3): keep components with area >= α (α in m²);
3. fit polygons to the outer contours (the paper's "polygon fitting"; here ``cv2.approxPolyDP``
   with tolerance ``epsilon`` in metres, which smooths ragged LiDAR borders);
4. flood-fill the inside of each fitted polygon (``cv2.drawContours(..., FILLED)``), which also
   closes interior walls and obstacles;
5. crop to the bounding box of the filled mask.

Frames: the mask keeps the grid's convention (row 0 = lowest y). ``offset`` = (col, row) of
``mask[0, 0]`` in the grid; ``pixel_to_map`` maps mask pixel coordinates (corner-based: pixel
(c, r) spans [c, c+1) × [r, r+1)) to map metres, including the grid's origin and yaw.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from frslam_graph.se2 import to_matrix

__all__ = ["PreprocessedMap", "grey_image", "preprocess_image", "preprocess_map"]

FREE_GREY, UNKNOWN_GREY, OCCUPIED_GREY = 254, 205, 0


@dataclass(frozen=True)
class PreprocessedMap:
    """Filled, cropped LiDAR map mask (uint8 0/1, row 0 = lowest y) and where it sits in the map."""

    mask: np.ndarray
    offset: tuple[int, int]  # (col, row) of mask[0, 0] in the grid
    resolution: float  # metres per cell
    origin: tuple[float, float, float]  # grid origin (x, y, yaw) in the map frame
    polygons: list[np.ndarray] = field(default_factory=list)  # fitted outer polygons, (K, 2) mask px

    @property
    def empty(self) -> bool:
        return self.mask.size == 0 or not self.mask.any()

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape  # type: ignore[return-value]

    @property
    def pixel_to_map(self) -> np.ndarray:
        """3×3 affine: mask pixel coordinates (col, row), corner-based -> map metres."""
        res = self.resolution
        rot = to_matrix(self.origin)
        scale = np.array(
            [[res, 0.0, res * self.offset[0]], [0.0, res, res * self.offset[1]], [0.0, 0.0, 1.0]]
        )
        return rot @ scale

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the cropped box in metres (the paper's H2, V2)."""
        h, w = self.mask.shape
        return w * self.resolution, h * self.resolution


def grey_image(grid: Any) -> np.ndarray:
    """map_server grey image of an OccupancyGrid (uint8, row 0 = lowest y): free 254, unknown 205,
    occupied 0, intermediate probabilities p in (0, 100) as 254·(1 − p/100)."""
    data = np.asarray(grid.data)
    known = data >= 0
    grey = np.full(data.shape, UNKNOWN_GREY, dtype=np.uint8)
    p = np.clip(data.astype(np.float32), 0.0, 100.0)
    grey[known] = np.round(FREE_GREY * (1.0 - p[known] / 100.0)).astype(np.uint8)
    return grey


def preprocess_image(
    grey: np.ndarray, theta: int = 250, alpha_px: float = 100.0, epsilon_px: float = 2.0
) -> tuple[np.ndarray, tuple[int, int], list[np.ndarray]]:
    """Eqs. (2)–(4) on a grey image. Returns (cropped filled mask uint8, (col0, row0), polygons).

    ``alpha_px``: minimum component area in pixels; ``epsilon_px``: approxPolyDP tolerance.
    An image with nothing left returns a (0, 0) mask.
    """
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.size == 0:
        return np.zeros((0, 0), np.uint8), (0, 0), []
    binary = (grey >= theta).astype(np.uint8)  # eq. (2)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= alpha_px  # eq. (3)
    keep[0] = False
    if not keep.any():
        return np.zeros((0, 0), np.uint8), (0, 0), []
    kept = keep[labels].astype(np.uint8)
    contours, _ = cv2.findContours(kept, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    fitted = [cv2.approxPolyDP(c, epsilon_px, True) if epsilon_px > 0 else c for c in contours]
    filled = np.zeros_like(kept)
    cv2.drawContours(filled, fitted, -1, 1, thickness=cv2.FILLED)  # flood fill of the insides
    filled |= kept  # approxPolyDP may cut a sliver off a component; never lose free cells
    rows = np.flatnonzero(filled.any(axis=1))
    cols = np.flatnonzero(filled.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    polygons = [f.reshape(-1, 2).astype(float) - (c0, r0) for f in fitted]
    return np.ascontiguousarray(filled[r0:r1, c0:c1]), (int(c0), int(r0)), polygons


def preprocess_map(grid: Any, theta: int = 250, alpha: float = 0.25, epsilon: float = 0.1) -> PreprocessedMap:
    """The paper's LiDAR map preprocessing on an OccupancyGrid.

    theta: grey threshold (0..255, eq. 2); alpha: minimum component area in m² (eq. 3);
    epsilon: polygon-fit tolerance in metres. Returns an empty :class:`PreprocessedMap`
    (``.empty``) when nothing survives (no free cells, all unknown).
    """
    res = float(grid.resolution)
    mask, offset, polygons = preprocess_image(
        grey_image(grid), theta=theta, alpha_px=alpha / res**2, epsilon_px=epsilon / res
    )
    origin = tuple(float(v) for v in grid.origin)
    if len(origin) == 2:
        origin = (*origin, 0.0)
    return PreprocessedMap(mask, offset, res, origin, polygons)  # type: ignore[arg-type]
