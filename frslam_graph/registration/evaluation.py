"""Registration accuracy: per-room IoU and the paper's IoU_a (eq. 9).

A registration maps plan coordinates to map metres with a 3×3 affine matrix (homogeneous column
vectors). Given the true plan -> map matrix (the simulator's distortion D, or D⁻¹ when the plan
itself was distorted), every room of the plan is placed twice, once by each matrix, and the two
placements are compared by area (shapely; areas in m²):

    IoU(room) = area(A ∩ B) / area(A ∪ B),   IoU_a = Σ IoU(room) / n   (mean over ALL rooms).

A failed registration (``matrix_est is None``) scores 0 for every room, as do degenerate or
non-finite matrices. Everything is vectorised over rooms with shapely 2's array functions.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import shapely

__all__ = ["iou_a", "room_iou", "room_ious", "transform_polygons"]


def _as_matrix(matrix: Any) -> np.ndarray | None:
    if matrix is None:
        return None
    m = np.asarray(matrix, dtype=float)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    if m.shape != (3, 3):
        raise ValueError(f"expected a 3x3 (or 2x3) affine matrix, got shape {m.shape}")
    return m


def _usable(m: np.ndarray | None) -> bool:
    if m is None or not np.all(np.isfinite(m)):
        return False
    return abs(np.linalg.det(m[:2, :2])) > 1e-15


def transform_polygons(polygons: Sequence[Any] | np.ndarray, matrix: Any) -> np.ndarray:
    """Apply a 3×3 affine ``matrix`` (x' = A x + t) to shapely geometries; returns an object array."""
    m = _as_matrix(matrix)
    geoms = np.asarray(list(polygons) if not isinstance(polygons, np.ndarray) else polygons, dtype=object)
    a, t = m[:2, :2], m[:2, 2]
    return shapely.transform(geoms, lambda xy: xy @ a.T + t)


def room_iou(poly_a: Any, poly_b: Any) -> float | np.ndarray:
    """IoU of two polygons (or element-wise for two equal-length arrays of polygons).

    Empty unions give 0. Invalid inputs (e.g. collapsed by a degenerate transform) are repaired
    with ``shapely.make_valid`` before the overlay.
    """
    a = np.asarray(poly_a, dtype=object) if isinstance(poly_a, list | tuple | np.ndarray) else poly_a
    b = np.asarray(poly_b, dtype=object) if isinstance(poly_b, list | tuple | np.ndarray) else poly_b
    a = np.where(shapely.is_valid(a), a, shapely.make_valid(a))
    b = np.where(shapely.is_valid(b), b, shapely.make_valid(b))
    inter = shapely.area(shapely.intersection(a, b))
    union = shapely.area(a) + shapely.area(b) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    iou = np.clip(iou, 0.0, 1.0)
    return float(iou) if np.ndim(iou) == 0 else iou


def room_ious(plan: Any, matrix_est: Any, matrix_true: Any) -> np.ndarray:
    """IoU of every room of ``plan`` placed by ``matrix_est`` versus by ``matrix_true`` (n_rooms,)."""
    polygons = [room.polygon for room in plan.rooms]
    n = len(polygons)
    m_est, m_true = _as_matrix(matrix_est), _as_matrix(matrix_true)
    if m_true is None or not _usable(m_true):
        raise ValueError("matrix_true must be a finite, non-singular 3x3 affine matrix")
    if n == 0 or not _usable(m_est):
        return np.zeros(n)
    est = transform_polygons(polygons, m_est)
    true = transform_polygons(polygons, m_true)
    return np.atleast_1d(np.asarray(room_iou(est, true), dtype=float))


def iou_a(plan: Any, matrix_est: Any, matrix_true: Any) -> float:
    """The paper's IoU_a (eq. 9): mean over all rooms of the plan of each room's IoU.

    ``matrix_est`` None (failed registration) or degenerate -> 0.0.
    """
    ious = room_ious(plan, matrix_est, matrix_true)
    return float(ious.mean()) if ious.size else 0.0
