"""Occupancy grids: a grid over MAX_GRID_CELLS is refused before its arrays are allocated."""

from __future__ import annotations

import resource

import numpy as np
import pytest

from frslam_graph.backend.mapping import OccupancyMapper, occupancy_grid
from frslam_graph.errors import ConfigError

GIB = 1 << 30
SCAN = np.array([[10.0 * np.cos(a), 10.0 * np.sin(a)] for a in np.linspace(-1.5, 1.5, 50)])


def test_a_grid_at_a_tiny_resolution_is_refused():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(
        ConfigError, match=r"resolution: an occupancy grid of .* cells at 0\.0001 m is over the limit"
    ):
        occupancy_grid(np.zeros((1, 3)), [SCAN], resolution=1e-4)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024 < GIB // 4


def test_the_incremental_mapper_refuses_it_too():
    mapper = OccupancyMapper(1e-4)
    with pytest.raises(ConfigError, match=r"MAX_GRID_CELLS"):
        mapper.update(np.zeros((1, 3)), [SCAN], None)


def test_a_usual_resolution_is_mapped():
    grid = occupancy_grid(np.zeros((1, 3)), [SCAN], resolution=0.05)
    assert grid.data.size < 1_000_000
