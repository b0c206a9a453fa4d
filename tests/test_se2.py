"""SE(2) helpers of frslam_graph.se2 that the motion-model tests do not cover: the two angle wraps,
degrees, and the chains of increments the simulator uses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from frslam_graph.se2 import (
    between_many,
    compose,
    compose_increments,
    compose_rows,
    interpolate_poses,
    inverse,
    inverse_rows,
    relative_motion,
    wrap,
    wrap_atan2,
    wrap_deg,
)


def test_the_two_wraps_differ_only_at_the_ends_of_the_range():
    a = np.array([-3 * math.pi, -math.pi, -1.0, 0.0, 2.5, math.pi, 7.0])
    assert wrap(math.pi) == pytest.approx(-math.pi)  # [-pi, pi)
    assert wrap_atan2(math.pi) == pytest.approx(math.pi)  # (-pi, pi]
    inner = np.abs(np.abs(wrap_atan2(a)) - math.pi) > 1e-9
    np.testing.assert_allclose(wrap(a)[inner], wrap_atan2(a)[inner], atol=1e-12)
    # a scalar goes through math, an array through numpy: the same values
    assert [wrap_atan2(float(x)) for x in a] == pytest.approx(list(wrap_atan2(a)), abs=1e-15)


def test_wrap_deg_is_half_open_at_minus_180():
    assert [wrap_deg(d) for d in (-540.0, -180.0, 180.0, 190.0, 720.5)] == [180.0, 180.0, 180.0, -170.0, 0.5]


def test_increments_chain_back_to_the_poses():
    rng = np.random.default_rng(1)
    poses = np.column_stack([rng.normal(0, 3, 20), rng.normal(0, 3, 20), rng.uniform(-math.pi, math.pi, 20)])
    inc = relative_motion(poses)
    np.testing.assert_allclose(inc[:, :2], between_many(poses[:-1], poses[1:])[:, :2], atol=1e-12)
    back = compose_increments(poses[0], inc)
    np.testing.assert_allclose(back[:, :2], poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap(back[:, 2] - poses[:, 2]), 0.0, atol=1e-9)


def test_interpolated_heading_takes_the_short_way_round():
    stamps = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, math.pi - 0.1], [1.0, 2.0, -math.pi + 0.1]])
    mid = interpolate_poses(stamps, poses, np.array([0.5]))[0]
    assert mid[:2] == pytest.approx([0.5, 1.0])
    assert abs(mid[2]) == pytest.approx(math.pi)


def test_row_by_row_compose_and_inverse_equal_the_single_pose_ones():
    rng = np.random.default_rng(3)
    a = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], (20, 3))
    b = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], (20, 3))
    np.testing.assert_allclose(
        compose_rows(a, b), [compose(x, y) for x, y in zip(a, b, strict=True)], atol=1e-12
    )
    np.testing.assert_allclose(inverse_rows(a), [inverse(x) for x in a], atol=1e-12)
    np.testing.assert_allclose(compose_rows(a, inverse_rows(a)), np.zeros((20, 3)), atol=1e-12)
