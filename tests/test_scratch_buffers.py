"""The correlative search's large temporaries live in per-thread scratch buffers (no page faults
of freshly mapped blocks): the same numbers as computing them anew, and a buffer reused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from frslam_graph.loop_closure import submap_matching as sm


def _room(rng: np.random.Generator) -> np.ndarray:
    """Noisy walls of a 6 m × 4 m room with a pillar (m)."""
    t = np.linspace(0.0, 1.0, 400)
    walls = [
        np.column_stack((6.0 * t, np.zeros_like(t))),
        np.column_stack((6.0 * t, np.full_like(t, 4.0))),
        np.column_stack((np.zeros_like(t), 4.0 * t)),
        np.column_stack((np.full_like(t, 6.0), 4.0 * t)),
        np.column_stack((2.0 + 0.3 * t, np.full_like(t, 2.0))),
    ]
    return np.concatenate(walls) + rng.normal(0.0, 0.01, (5 * len(t), 2))


def _score_poses_anew(
    ref: sm.ReferenceSubmap, query: np.ndarray, poses: np.ndarray, cells: int
) -> np.ndarray:
    """_score_poses as it was written before the scratch buffers (every array allocated)."""
    field = ref.dilated(cells)
    h, w = ref.shape
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    px = c * query[None, :, 0] - s * query[None, :, 1] + poses[:, 0:1]
    py = s * query[None, :, 0] + c * query[None, :, 1] + poses[:, 1:2]
    bx = np.floor((px - ref.origin[0]) / ref.resolution).astype(np.int64)
    by = np.floor((py - ref.origin[1]) / ref.resolution).astype(np.int64)
    out = (bx < 0) | (bx >= w) | (by < 0) | (by >= h)
    flat = by * w + bx
    flat[out] = 0
    return np.take(field, flat).mean(axis=1)


def test_scores_fields_and_search_are_those_computed_anew():
    rng = np.random.default_rng(3)
    pts = _room(rng)
    ref = sm.ReferenceSubmap(pts, 0.05, 0.05, 2.5, likelihood=True)
    # the field as the distance transform gives it, without scratch buffers
    pad, hi_, wi = ref._inner
    free = np.full((hi_, wi), 255, np.uint8)
    ij = np.floor((ref.points - ref.origin) / 0.05).astype(int)
    free[ij[:, 1] - pad, ij[:, 0] - pad] = 0
    dist, _ = cv2.distanceTransformWithLabels(
        free, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    field = np.zeros(ref.shape, np.float32)
    field[pad : pad + hi_, pad : pad + wi] = np.exp(-0.5 * np.square(dist * 0.05 / 0.05))
    np.testing.assert_array_equal(ref.padded(ref.field, 0.0).reshape(ref.shape), field)
    cells = 3
    r0, c0 = max(pad - cells, 0), max(pad - cells, 0)
    r1, c1 = min(pad + hi_ + cells, ref.shape[0]), min(pad + wi + cells, ref.shape[1])
    kernel = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    dilated = np.zeros(ref.shape, np.float32)
    dilated[r0:r1, c0:c1] = cv2.dilate(np.ascontiguousarray(field[r0:r1, c0:c1]), kernel)
    np.testing.assert_array_equal(ref.dilated(cells), dilated.ravel())
    query = sm.transform_points(np.array([0.1, -0.05, 0.03]), pts[::7])
    for n_poses in (40, 300, 40):  # a smaller call after a larger one reuses the grown buffer
        poses = np.column_stack((rng.uniform(-0.5, 0.5, (n_poses, 2)), rng.uniform(-0.3, 0.3, n_poses)))
        np.testing.assert_array_equal(
            sm._score_poses(ref, query, poses, cells), _score_poses_anew(ref, query, poses, cells)
        )
    match = sm.match_scan(ref, query, np.zeros(3), 0.5, np.deg2rad(10.0))
    assert match is not None and match.inlier_fraction > 0.9
    np.testing.assert_allclose(match.pose, [-0.1, 0.05, -0.03], atol=0.02)


def test_a_slot_is_one_buffer_grown_to_the_largest_request():
    a = sm._scratch(7, (100, 50), np.float64)
    b = sm._scratch(7, (10, 5), np.float32)
    assert np.shares_memory(a, b) and b.shape == (10, 5) and b.dtype == np.float32 and b.flags.c_contiguous
    c = sm._scratch(7, (400, 50), np.float64)  # larger: a new buffer, kept for the next calls
    assert c.shape == (400, 50) and np.shares_memory(c, sm._scratch(7, (100, 50), np.float64))


def _nearest_from_full_grids(ref: sm.ReferenceSubmap, labels: np.ndarray) -> np.ndarray:
    """The nearest-point map as it was computed before its scratch buffers (a full-grid owner
    table, the labels' look-up table by label - 1, clipped)."""
    h, w = ref.shape
    pad, hi_, wi = ref._inner
    nearest = np.full((h, w), -1, np.int32)
    owner = np.full(h * w, -1, np.int32)
    owner[ref._cells] = np.arange(len(ref.points), dtype=np.int32)
    owner = owner.reshape(h, w)[pad : pad + hi_, pad : pad + wi].ravel()
    inner = np.take(owner[np.flatnonzero(ref._occupied)], labels.ravel() - 1, mode="clip")
    nearest[pad : pad + hi_, pad : pad + wi] = inner.reshape(hi_, wi)
    return nearest.ravel()


@pytest.mark.parametrize("margin", [0.3, 2.5, 6.0])
def test_the_nearest_point_map_is_the_one_of_the_full_grid_owner_table(margin):
    """The nearest-point map of the ICP's inlier tests, built on the inner grid in scratch
    buffers: the same map as the full-grid owner table gave, a submap after another (the
    buffers hold the previous one's numbers), with or without a zero margin around the inner grid."""
    rng = np.random.default_rng(7)
    for scale in (1.0, 0.6, 1.3):
        pts = scale * _room(rng) + rng.uniform(-1.0, 1.0, 2)
        ref = sm.ReferenceSubmap(pts, 0.05, 0.1, margin, likelihood=False)
        labels = ref._labels.copy()
        np.testing.assert_array_equal(ref.padded(ref.nearest, -1), _nearest_from_full_grids(ref, labels))
