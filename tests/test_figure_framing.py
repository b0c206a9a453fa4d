"""Figures of a map framed on what there is to see: a sensor map's image (Halmstad's Tango maps:
a 25 m map in an 80 m image) is mostly unknown border, which ``map show`` and ``register``'s
overlay drew in full, the map a small patch in a grey square."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import box

from frslam_graph.floorplan import FloorPlan, Room
from frslam_graph.floorplan.render import known_bounds
from frslam_graph.occupancy import OccupancyGrid


def _bordered(origin=(0.0, 0.0, 0.0)) -> OccupancyGrid:
    """A 20 x 20 m grid (0.05 m) whose known cells are rows 100-199, cols 40-139: a 5 x 5 m room."""
    data = np.full((400, 400), -1, np.int8)
    data[100:200, 40:140] = 0
    data[100, 40:140] = data[199, 40:140] = 100
    return OccupancyGrid(data, 0.05, origin)


def test_known_bounds_are_the_known_cells_widened_by_the_margin():
    assert known_bounds(_bordered(), margin=1.0) == pytest.approx((1.0, 8.0, 4.0, 11.0))
    assert known_bounds(_bordered((-3.0, 2.0, 0.0)), margin=0.0) == pytest.approx((-1.0, 4.0, 7.0, 12.0))
    # a grid turned by 90 deg: its columns run along y
    turned = known_bounds(_bordered((0.0, 0.0, np.pi / 2)), margin=0.0)
    assert turned == pytest.approx((-10.0, -5.0, 2.0, 7.0))
    empty = OccupancyGrid(np.full((50, 50), -1, np.int8), 0.05, (0.0, 0.0, 0.0))
    assert known_bounds(empty) is None


def _axes_of(monkeypatch, module) -> list:
    """The axes of the figures ``module`` saves (save_figure replaced by a recorder)."""
    seen: list = []

    def record(fig, out, **_k):
        seen.extend(fig.axes)
        return out

    monkeypatch.setattr(module, "save_figure", record)
    return seen


def test_map_png_is_framed_on_the_known_cells(tmp_path, monkeypatch):
    from frslam_graph import viz

    axes = _axes_of(monkeypatch, viz)
    viz.save_grid_png(_bordered(), tmp_path / "map.png")
    (ax,) = axes
    assert ax.get_xlim() == pytest.approx((1.0, 8.0))
    assert ax.get_ylim() == pytest.approx((4.0, 11.0))


def test_register_overlay_is_framed_on_the_map_and_the_placed_plan(tmp_path, monkeypatch):
    from frslam_graph import atomic
    from frslam_graph.cli.register import _overlay
    from frslam_graph.registration import Registration

    axes = _axes_of(monkeypatch, atomic)
    # a room placed partly beyond the map's known cells: the frame takes both
    plan_m = FloorPlan(rooms=[Room("r1", "room", box(6.0, 5.0, 12.0, 9.0))], doors=[])
    reg = Registration.from_matrix(np.eye(3), score=0.9, ambiguity=0.1, rooms=("r1",), method="mfr")
    _overlay(_bordered(), plan_m, reg, tmp_path / "overlay.png", "t")
    (ax,) = axes
    assert ax.get_xlim() == pytest.approx((1.0, 13.0))
    assert ax.get_ylim() == pytest.approx((4.0, 11.0))
