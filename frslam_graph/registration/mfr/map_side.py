"""MFR step 1, the map side: the partial occupancy map prepared for registration.

Observed footprint = free ∪ occupied with holes filled, main connected component, except
unobserved regions that could hold a room (:data:`CORE_RADIUS_M`): the block a corridor ring goes
round is unexplored, neither footprint nor outside (``unexplored``); free space with
small obstacles filled; its signed distance field (full resolution); the "wall-side" free cells
(free next to a wall) and doorway-like exits (free running into unobserved space, 0.4–2.5 m wide);
up to two wall directions (peaks of the histogram of 4 × gradient angle, so walls at 90° agree);
area moments and bounding boxes per direction.

Frame and units: the *grid frame* of the known-area crop (origin = corner of its cell (0, 0), axes
along the grid), metres; ``MapObservation.to_map`` maps it to ``map``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from frslam_graph.raster import RasterFrame
from frslam_graph.registration.mfr.geometry import ANGLE_SAMPLES, dominant_angles, regular_subsample
from frslam_graph.registration.refine import DistanceField
from frslam_graph.se2 import rot

CORE_RADIUS_M = 1.0  # an enclosed unobserved region holding a disc this wide (radius, m) is not footprint


@dataclass
class MapObservation:
    """The map, prepared for registration (grid frame of the known-area crop, metres)."""

    to_map: np.ndarray
    frame: RasterFrame
    footprint: np.ndarray
    free: np.ndarray
    field: DistanceField
    angles: list[float]  # wall directions (radians), strongest first
    area: float
    centroid: np.ndarray
    cov: np.ndarray
    bboxes: list[np.ndarray]  # per angle: x0, y0, x1, y1 in the frame rotated by -angle
    coarse_frame: RasterFrame
    coarse_footprint: np.ndarray
    coarse_footprint_u8: np.ndarray
    footprint_u8: np.ndarray
    edge_dt: np.ndarray  # metres to the nearest wall-side free cell (full resolution)
    edge_points: np.ndarray  # (K, 2) a subsample of those cells' centres, metres
    exit_points: np.ndarray  # (J, 2) free cells next to unobserved space outside the footprint
    unexplored: np.ndarray  # bool: enclosed unobserved regions left out of the footprint
    footprint_cells: int  # np.count_nonzero(footprint)
    any_unexplored: bool  # unexplored.any()


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every region not connected to the image border filled."""
    h, w = mask.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = mask
    ff = pad.copy()
    flood = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(ff, flood, (0, 0), 2)
    return ff[1:-1, 1:-1] != 2


def observe_map(
    grid,
    *,
    min_area_m2: float = 2.0,
    obstacle_m2: float = 0.5,
    coarse_px: int = 80,
    max_edge_points: int = 400,
    min_exit_m: float = 0.4,
    max_exit_m: float = 2.5,
    max_resolution: float = 0.5,
) -> MapObservation | str:
    """Prepare ``grid`` (an OccupancyGrid); returns a failure reason string when unusable."""
    known_all = ~grid.unknown_mask()
    if not known_all.any():
        return "map has no observed cells (all unknown)"
    if grid.resolution > max_resolution:
        return f"map resolution {grid.resolution:g} m per cell is too coarse (at most {max_resolution:g} m)"
    g = grid.crop_to_known(margin_cells=4)
    res = g.resolution
    free = g.free_mask()
    occ = g.occupied_mask()
    if not free.any():
        return "map has no free cells"
    known = free | occ
    filled = _fill_holes(known.astype(np.uint8))
    unexplored = _unexplored_cores(filled & ~known, CORE_RADIUS_M / res)
    filled &= ~unexplored
    n, labels = cv2.connectedComponents(filled.view(np.uint8), connectivity=8)
    if n <= 1:
        return "map has no observed area"
    main = 1 if n == 2 else 1 + int(np.argmax(np.bincount(labels.ravel(), minlength=n)[1:]))
    footprint = labels == main
    footprint_cells = int(np.count_nonzero(footprint))
    area = float(footprint_cells) * res * res
    if area < min_area_m2:
        return f"observed area too small ({area:.2f} m² < {min_area_m2} m²)"
    free = free & footprint
    # small obstacles (furniture, people) inside free space are not walls
    nonfree = (~free & footprint).view(np.uint8)
    m, lab2 = cv2.connectedComponents(nonfree, connectivity=8)
    small = np.zeros(m, bool)
    small[1:] = component_stats(lab2, nonfree, m)[0] * res * res < obstacle_m2
    # keep components that touch the footprint's outside (outer walls) even when small
    small &= ~_touching(footprint, lab2, m)
    if small.any():  # one lookup of the components kept (most maps: none)
        free = free | small[lab2]
    field_ = DistanceField.from_masks(free, res, (0.0, 0.0))
    # free cells on a wall (not on a frontier to unknown): the map's room structure
    walls_in = (footprint & ~free).view(np.uint8)
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
    edge = free & cv2.dilate(walls_in, cross).view(bool)
    edge_dt = cv2.distanceTransform((~edge).view(np.uint8), cv2.DIST_L2, 3)
    edge_dt *= np.float32(res)
    at = np.flatnonzero(edge)  # np.nonzero's cells, row-major
    if len(at) < 10:
        return "map shows no walls next to free space: nothing to match"
    stride = max(1, len(at) // max_edge_points)
    er, ec = np.divmod(at[::stride], edge.shape[1])
    edge_points = (np.column_stack([ec, er]).astype(np.float64) + 0.5) * res
    # exits: where free space runs out of the observed area (open doorways, open-plan boundaries)
    outside = (~footprint).view(np.uint8)
    exits = (free & cv2.dilate(outside, cross).view(bool)).view(np.uint8)
    # doorway-like exits: 0.4 to 2.5 m across (single missing wall cells are noise; big ragged
    # openings are gaps in what the sensor saw, not doors); one point (centroid) per doorway
    m, lab3 = cv2.connectedComponents(exits, connectivity=8)
    _, width, height, cen3 = component_stats(lab3, exits, m, boxes=True)
    span = np.maximum(width, height) * res
    door_like = (span >= min_exit_m) & (span <= max_exit_m)
    exit_points = (cen3[door_like] + 0.5) * res

    # dominant wall direction from the free-space edges
    # σ 2 cells: less aliasing (the free space as float32: the distance field's ``known``)
    fimg = cv2.GaussianBlur(field_.known, (9, 9), 2.0)
    gx = cv2.Sobel(fimg, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(fimg, cv2.CV_32F, 0, 1, ksize=3)
    at = np.flatnonzero((np.abs(gx) + np.abs(gy)) > 0.05)  # the edge cells, row-major
    # plenty: a regular subsample keeps the histogram; then dominant_angles' own, taken here so
    # that only the cells it keeps are gathered
    at = regular_subsample(regular_subsample(at, 30000), ANGLE_SAMPLES)
    vectors = np.column_stack([gx.ravel().take(at), gy.ravel().take(at)]).astype(np.float64)
    angles = dominant_angles(vectors) if len(at) else [0.0]

    footprint_u8 = footprint.view(np.uint8)  # bool is one byte of 0 / 1
    mom = cv2.moments(footprint_u8, binaryImage=True)
    m00 = max(mom["m00"], 1.0)
    centroid = np.array([(mom["m10"] / m00 + 0.5) * res, (mom["m01"] / m00 + 0.5) * res])
    cov = np.array([[mom["mu20"], mom["mu11"]], [mom["mu11"], mom["mu02"]]]) / m00 * res * res
    cov += np.eye(2) * res * res / 12.0
    contours, _ = cv2.findContours(footprint_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    pts = (np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64) + 0.5) * res
    half = 0.5 * res
    bboxes = []
    for angle in angles:
        pa = pts @ rot(-angle).T
        bboxes.append(
            np.array(
                [pa[:, 0].min() - half, pa[:, 1].min() - half, pa[:, 0].max() + half, pa[:, 1].max() + half]
            )
        )

    h, w = footprint.shape
    k = max(1, int(math.ceil(max(h, w) / coarse_px)))
    hc, wc = max(1, h // k), max(1, w // k)
    coarse = _coarse_cover(footprint, k, hc, wc)
    coarse_frame = RasterFrame(res * k, (0.0, 0.0), (hc, wc))
    return MapObservation(
        to_map=g.map_from_grid(),
        frame=RasterFrame(res, (0.0, 0.0), (h, w)),
        footprint=footprint,
        free=free,
        field=field_,
        angles=angles,
        area=area,
        centroid=centroid,
        cov=cov,
        bboxes=bboxes,
        coarse_frame=coarse_frame,
        coarse_footprint=coarse,
        coarse_footprint_u8=coarse.astype(np.uint8),
        footprint_u8=footprint_u8.copy(),
        edge_dt=edge_dt,
        edge_points=edge_points,
        exit_points=exit_points,
        unexplored=unexplored,
        footprint_cells=footprint_cells,
        any_unexplored=bool(unexplored.any()),
    )


def _unexplored_cores(pockets: np.ndarray, radius_px: float) -> np.ndarray:
    """The unobserved regions enclosed by the observed area (``pockets``, bool) that hold a disc
    of ``radius_px`` cells: rooms the robot has not entered, the core of a building a corridor
    goes round. The smaller ones (behind furniture, inside thick walls) stay footprint.

    Computed on the pockets' bounding box and a ring of one cell (no pocket there): OpenCV's
    3 x 3 distance transform sums integer weights along 8-paths, so a pocket cell's distance to
    the nearest other cell is the same as on the whole image (a cell beyond the ring is no
    nearer than the ring cell it projects onto); a pocket holds the disc when one of its cells
    lies that deep (its maximum depth does)."""
    rows = np.flatnonzero(pockets.any(axis=1))
    out = np.zeros(pockets.shape, bool)
    if len(rows) == 0:
        return out
    cols = np.flatnonzero(pockets.any(axis=0))
    h, w = pockets.shape
    r0, r1 = max(0, rows[0] - 1), min(h, rows[-1] + 2)
    c0, c1 = max(0, cols[0] - 1), min(w, cols[-1] + 2)
    p8 = np.ascontiguousarray(pockets[r0:r1, c0:c1]).view(np.uint8)
    n, labels = cv2.connectedComponents(p8, connectivity=4)
    core = np.zeros(n, bool)  # per pocket: a cell at least radius_px deep
    core[labels[cv2.distanceTransform(p8, cv2.DIST_L2, 3) >= radius_px]] = True
    core[0] = False
    if core.any():
        out[r0:r1, c0:c1] = core[labels]
    return out


def _ring(mask: np.ndarray) -> np.ndarray:
    """One-pixel ring just outside ``mask`` (counts as observed: walls end there)."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask


def _touching(footprint: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool per component of ``labels``: it touches the footprint's border ring (label 0,
    the background, counts as touching)."""
    ring = _ring(footprint)
    border = cv2.dilate(ring.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    touching = np.zeros(n, bool)
    touching[labels[border]] = True
    touching[0] = True
    return touching


def component_stats(
    labels: np.ndarray, mask: np.ndarray, n: int, boxes: bool = False
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Of the components 1..n-1 of ``labels`` (cv2.connectedComponents of ``mask``, uint8 0 / 1):
    (n - 1,) areas (int64 pixel counts) and, with ``boxes``, bounding-box widths and heights
    (pixels) and (n - 1, 2) centroids (x, y; pixels): cv2.connectedComponentsWithStats' areas,
    ``CC_STAT_WIDTH``, ``CC_STAT_HEIGHT`` and centroids (the integer coordinate sums over the
    area, in double), from the mask's pixels only (that call costs ~0.4 ms a map in its stats)."""
    at = np.flatnonzero(mask.view(bool))  # a bool view: numpy's fast path (8x a uint8's)
    lab = labels.ravel().take(at)
    area = np.bincount(lab, minlength=n)[1:]
    if not boxes:
        return area, None, None, None
    ys, xs = np.divmod(at, mask.shape[1])
    lo = np.full((2, n), np.iinfo(np.intp).max, np.intp)
    hi = np.full((2, n), -1, np.intp)
    for k, c in enumerate((xs, ys)):
        np.minimum.at(lo[k], lab, c)
        np.maximum.at(hi[k], lab, c)
    size = hi[:, 1:] - lo[:, 1:] + 1
    sums = np.stack(
        [np.bincount(lab, weights=c.astype(np.float64), minlength=n)[1:] for c in (xs, ys)], axis=1
    )
    return area, size[0], size[1], sums / area.astype(np.float64)[:, None]


def _coarse_cover(footprint: np.ndarray, k: int, hc: int, wc: int) -> np.ndarray:
    """(hc, wc) bool: blocks of k x k cells at least half footprint (the mean of the block's cells
    >= 0.5), from the footprint's integral image (exact integer counts)."""
    h, w = footprint.shape
    if hc * k > h or wc * k > w:  # a map thinner than a block: the block mean as it was
        return footprint[: hc * k, : wc * k].reshape(hc, k, wc, k).mean(axis=(1, 3)) >= 0.5
    ii = cv2.integral(footprint.view(np.uint8))  # (h + 1, w + 1) int32
    s = ii[::k, ::k][: hc + 1, : wc + 1]
    counts = s[1:, 1:] - s[:-1, 1:] - s[1:, :-1] + s[:-1, :-1]
    return 2 * counts >= k * k
