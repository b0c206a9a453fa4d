"""Open boundaries between rooms (``frslam_graph.floorplan.openings``), metres."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Polygon

from frslam_graph.floorplan import FloorPlan, Room
from frslam_graph.floorplan.openings import open_boundaries

OUTER = np.array([[0, 0, 6, 0], [6, 0, 6, 6], [6, 6, 0, 6], [0, 6, 0, 0]], float)


def _two_rooms(gap: float, walls: np.ndarray) -> FloorPlan:
    """A 6 x 6 m square split along its diagonal into two rooms, ``gap`` metres apart."""
    n = np.array([-1.0, 1.0]) / np.sqrt(2.0) * gap  # normal of the diagonal, towards room b
    a = Room("a", "living", Polygon([(0, 0), (6, 0), (6, 6)]))
    b = Room("b", "kitchen", Polygon([(0, 0) + n, (6, 6) + n, (0, 6) + n]))
    return FloorPlan(rooms=[a, b], walls=walls, units="m", metres_per_unit=1.0)


@pytest.mark.parametrize("gap", [0.0, 1e-9, 0.004, 0.015])
def test_diagonal_boundary_without_a_wall_is_open_even_with_a_hairline_crack(gap):
    """Two rooms share a diagonal boundary no wall runs along: it is open, also when the rooms,
    once transformed, do not touch exactly (a crack narrower than 2 cm) -- without closing the
    crack, eroding the rooms' union cut the boundary out and the relocaliser drew a wall across
    an open living-kitchen that the simulator's house (built with the exact matrix) left open."""
    openings, pairs = open_boundaries(_two_rooms(gap, OUTER), wall_thickness=0.12)
    assert pairs == [("a", "b")]
    assert sum(o.area for o in openings) > 0.8 * 0.22 * 6.0 * np.sqrt(2.0) * 0.8


def test_diagonal_boundary_with_a_wall_or_far_apart_stays_closed():
    diagonal = np.array([[0, 0, 6, 6]], float)
    assert open_boundaries(_two_rooms(0.004, np.vstack((OUTER, diagonal))), 0.12) == ([], [])
    assert open_boundaries(_two_rooms(0.5, OUTER), 0.12) == ([], [])  # a real gap: not neighbours
