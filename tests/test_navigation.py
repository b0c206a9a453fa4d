"""Navigation on a registered plan: paths through doors, never through walls, clear failures."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from frslam_graph.datasets.simulator import five_room_plan
from shapely.geometry import LineString, Point
from shapely.geometry import box as sbox

from frslam_graph.cli import main
from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan import Door, FloorPlan, Room
from frslam_graph.navigation import NavigationMap, plan_path, room_graph, unvisited_rooms
from frslam_graph.occupancy import OccupancyGrid
from frslam_graph.raster import rasterise_plan

SCALE = np.diag([0.05, 0.05, 1.0])  # five-room plan: 200 x 160 units -> 10 x 8 m


@pytest.fixture(scope="module")
def flat():
    return five_room_plan().transformed(SCALE, units="m")


def door_segments(plan):
    return [LineString([d.a, d.b]) for d in plan.doors]


def test_room_graph(flat):
    g = room_graph(flat)
    assert g["bathroom"] == {"corridor"}
    assert g["living"] == {"kitchen", "corridor", "bedroom"}


def test_path_goes_through_doors_and_keeps_clearance(flat):
    path = plan_path(flat, (2.0, 2.0), "bathroom", clearance=0.25)
    assert path.ok, path.reason
    assert path.rooms == ("living", "corridor", "bathroom")
    assert np.allclose(path.points[0], (2.0, 2.0))
    assert flat.room("bathroom").polygon.contains(Point(path.points[-1]))
    # shorter than any detour, longer than the straight line
    straight = np.hypot(*(path.points[-1] - path.points[0]))
    assert straight <= path.length < 2.0 * straight
    # every room change happens in a door opening; every point keeps its distance from walls
    walls = shapely.union_all([r.polygon.exterior for r in flat.rooms]).difference(
        shapely.union_all([s.buffer(0.02) for s in door_segments(flat)])
    )
    d = np.array([walls.distance(Point(p)) for p in path.points[1:-1]])
    assert d.min() >= 0.25 - 0.05 - 0.06  # clearance, less a cell and the half wall
    seg = LineString(path.points)
    assert not seg.crosses(walls) and seg.intersection(walls).is_empty


def test_path_to_a_point_and_a_neighbouring_room(flat):
    p = plan_path(flat, (2.0, 2.0), (9.0, 7.0))
    assert p.ok and p.rooms[-1] == "bathroom"
    assert np.allclose(p.points[-1], (9.0, 7.0))
    q = plan_path(flat, (2.0, 2.0), "kitchen")
    assert q.ok and q.rooms == ("living", "kitchen")


def test_no_path_through_walls():
    # two rooms sharing a wall, no door: unreachable, with a reason naming the rooms
    plan = FloorPlan(
        rooms=[Room("a", "bedroom", sbox(0, 0, 4, 4)), Room("b", "kitchen", sbox(4, 0, 8, 4))], units="m"
    )
    p = plan_path(plan, (1.0, 1.0), "b")
    assert not p.ok
    assert "'b'" in p.reason and "no chain of doors" in p.reason
    assert len(p.points) == 0 and p.length == float("inf")
    # with a door it works, and the path goes through it
    door = Door("d", (4.0, 1.5), (4.0, 2.5), ("a", "b"))
    plan2 = FloorPlan(rooms=plan.rooms, doors=[door], units="m")
    p2 = plan_path(plan2, (1.0, 1.0), "b")
    assert p2.ok and p2.rooms == ("a", "b")
    crossing = [pt for pt in p2.points if abs(pt[0] - 4.0) < 0.05]
    assert crossing and all(1.5 <= pt[1] <= 2.5 for pt in crossing)
    # a door narrower than the robot: unreachable, and the reason says so
    p3 = plan_path(plan2, (1.0, 1.0), "b", clearance=0.6)
    assert not p3.ok and "narrow" in p3.reason


def test_bad_start_goal_and_unknown_room(flat):
    assert not plan_path(flat, (-5.0, -5.0), "kitchen").ok
    bad = plan_path(flat, (2.0, 2.0), (50.0, 2.0))
    assert not bad.ok and "not in the plan's free space" in bad.reason
    with pytest.raises(FloorPlanError, match="unknown room 'garage'"):
        plan_path(flat, (2.0, 2.0), "garage")
    with pytest.raises(FloorPlanError, match="not metres"):
        plan_path(five_room_plan(), (2.0, 2.0), "kitchen")


def test_unvisited_rooms(flat):
    nav = NavigationMap.from_plan(flat)
    assert nav.room_at((2.0, 2.0)) == "living" and nav.room_at((50.0, 0.0)) is None
    grid = OccupancyGrid(np.full((170, 210), -1, np.int8), 0.05, (-0.25, -0.25, 0.0))
    seen = rasterise_plan(flat, grid.frame, rooms=["living", "corridor"]) > 0
    data = grid.data.copy()
    data[seen] = 0
    grid = OccupancyGrid(data, 0.05, grid.origin)
    assert unvisited_rooms(flat, grid) == ["kitchen", "bedroom", "bathroom"]


def test_cli_navigate(flat, tmp_path):
    plan_file = flat.save(tmp_path / "plan.json")
    out = tmp_path / "path.png"
    assert main(["navigate", str(plan_file), "--from", "2", "2", "--to", "bathroom", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    assert main(["navigate", str(plan_file), "--from", "2", "2", "--to", "9,7", "--out", str(out)]) == 0
    rc = main(
        [
            "navigate",
            str(plan_file),
            "--from",
            "2",
            "2",
            "--to",
            "bathroom",
            "--clearance",
            "0.6",
            "--out",
            str(out),
        ]
    )
    assert rc == 2
    assert main(["navigate", str(plan_file), "--from", "2", "2", "--to", "garage", "--out", str(out)]) == 2
