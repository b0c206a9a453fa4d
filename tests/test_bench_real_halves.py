"""The registration benchmark's measure of how far a sensor map is from one similarity of its
plan (``tools/bench_real.halves_scales``): each half of the annotated points fitted on its own."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_tool

bench_real = load_tool("bench_real")


def _points(stretch_right: float) -> tuple[np.ndarray, np.ndarray]:
    """Plan points on a 40 x 10 grid (plan units) and their map points: scaled 0.05 m/unit,
    rotated 30 deg, mirrored, with the map's right half (x > 1 m) stretched by ``stretch_right``
    about x = 1 m (a Tango map bent in one part)."""
    g = np.stack(np.meshgrid(np.arange(0.0, 40.0, 2.0), np.arange(0.0, 10.0, 2.0)), -1).reshape(-1, 2)
    m = g * np.array([1.0, -1.0]) * 0.05
    right = m[:, 0] > 1.0
    m[right] = (m[right] - [1.0, 0.0]) * (1.0 + stretch_right) + [1.0, 0.0]
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    return g, m @ np.array([[c, -s], [s, c]]).T + [3.0, -2.0]


def test_a_map_that_is_one_similarity_has_halves_of_the_same_scale():
    h1, h2 = bench_real.halves_scales(*_points(0.0))
    assert h1 == pytest.approx(0.0, abs=1e-9) and h2 == pytest.approx(0.0, abs=1e-9)


def test_a_map_stretched_in_one_half_shows_it():
    h1, h2 = bench_real.halves_scales(*_points(0.10))
    assert sorted((h1, h2)) == [pytest.approx(-0.035, abs=0.03), pytest.approx(0.06, abs=0.03)]
    assert abs(h1 - h2) > 0.07  # the stretched half's own scale against the other's
