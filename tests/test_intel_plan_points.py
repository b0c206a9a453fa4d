"""The hand-annotated ground truth of the Intel plan registration (``tests/data/
intel_lab_plan_points.csv``: IPA ``lab_intel.png`` pixels <-> frslam's map of the Intel log, metres)
is a consistent flipped similarity, and its plan points lie on walls of the plan image."""

from __future__ import annotations

import csv
import math

import cv2
import numpy as np
import pytest

PLAN_HEIGHT_PX = 708  # lab_intel.png is 763 x 708 px


def intel_plan_points(test_data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pixels (N, 2) col, row; plan frame (N, 2) x, y as ``FloorPlan.from_image``; map (N, 2) m)."""
    with open(test_data / "intel_lab_plan_points.csv", newline="") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    px = np.array([[float(r["plan_col"]), float(r["plan_row"])] for r in rows])
    plan = np.column_stack([px[:, 0] + 0.5, PLAN_HEIGHT_PX - px[:, 1] - 0.5])
    world = np.array([[float(r["map_x"]), float(r["map_y"])] for r in rows])
    return px, plan, world


def fit_similarity(src: np.ndarray, dst: np.ndarray, flip: bool) -> np.ndarray:
    """Least-squares similarity (3 x 3, src -> dst), mirrored about src's x axis first if ``flip``."""
    mirror = np.diag([1.0, -1.0]) if flip else np.eye(2)
    s, d = src @ mirror, dst
    sc, dc = s - s.mean(0), d - d.mean(0)
    u, sv, vt = np.linalg.svd(dc.T @ sc)
    e = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ e @ vt
    scale = float(np.sum(sv * np.diag(e)) / np.sum(sc**2))
    m = np.eye(3)
    m[:2, :2] = scale * rot @ mirror
    m[:2, 2] = d.mean(0) - m[:2, :2] @ src.mean(0)
    return m


def residuals(m: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    return np.linalg.norm(src @ m[:2, :2].T + m[:2, 2] - dst, axis=1)


def test_intel_annotation_is_a_flipped_similarity_with_a_half_metre_residual(test_data):
    _, plan, world = intel_plan_points(test_data)
    assert len(plan) >= 6
    best = {flip: residuals(fit_similarity(plan, world, flip), plan, world) for flip in (False, True)}
    rms = {flip: float(np.sqrt(np.mean(r**2))) for flip, r in best.items()}
    assert rms[True] < 0.6 and rms[False] > 5.0  # the plan is mirrored against the log's frame
    assert best[True].max() < 1.2
    m = fit_similarity(plan, world, True)
    assert abs(np.linalg.det(m[:2, :2])) ** 0.5 == pytest.approx(0.0429, abs=0.002)  # m per px
    col = m[:2, :2] @ np.diag([1.0, -1.0])  # the rotation after the mirror
    assert math.degrees(math.atan2(col[1, 0], col[0, 0])) == pytest.approx(-88.2, abs=1.0)


def test_intel_annotated_plan_points_lie_on_wall_faces(shared_data, test_data):
    img = cv2.imread(str(shared_data / "floorplans" / "ipa" / "lab_intel.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (PLAN_HEIGHT_PX, 763)
    px, _, _ = intel_plan_points(test_data)
    dark = np.argwhere(img < 100)[:, ::-1].astype(float)  # col, row
    for p in px:
        assert np.min(np.hypot(*(dark - p).T)) <= 2.0, p
