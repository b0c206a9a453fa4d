"""HouseExpo-style JSON (outer contour ``verts`` + ``room_category`` boxes) -> FloorPlan in metres.

No HouseExpo house is bundled (the data set is not in ../shared/data), so the houses here are
written in its format: ``{"id", "room_num", "bbox": {"min", "max"}, "verts": [[x, y], ...],
"room_category": {"<type>": [[x1, y1, x2, y2], ...]}}``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from shapely.geometry import box

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan import FloorPlan
from frslam_graph.floorplan.houseexpo import houseexpo_type, load_houseexpo

# an L-shaped house: 10 x 4 m along the bottom, a 4 x 6 m wing on the left
HOUSE = {
    "id": "0a1b2c3d",
    "room_num": 5,
    "bbox": {"min": [0.0, 0.0], "max": [10.0, 10.0]},
    "verts": [[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]],
    "room_category": {
        "Living_Room": [[0, 0, 10, 4]],
        "Bedroom": [[0, 4, 4, 10]],
        "Toilet": [[8, 2, 10, 4]],  # inside the living-room box: stays the toilet
        "Guest_room": [[2, 8, 6, 12]],  # reaches out of the house: clipped to it
        "indoor": [[0, 0, 0, 5]],  # degenerate box: ignored
    },
}


def _write(tmp_path: Path, data, name="house.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def test_rooms_are_clipped_disjoint_and_typed(tmp_path):
    plan = load_houseexpo(_write(tmp_path, HOUSE))
    assert plan.units == "m" and plan.metres_per_unit == 1.0 and plan.name == "0a1b2c3d"
    by_type = {r.type: r for r in plan.rooms}
    assert sorted(by_type) == ["bedroom", "living_room", "restroom"] and len(plan.rooms) == 4
    assert by_type["restroom"].area == pytest.approx(4.0)
    assert by_type["living_room"].area == pytest.approx(40.0 - 4.0)  # minus the toilet
    guest = [r for r in plan.rooms if r.type == "bedroom" and r.polygon.bounds[1] >= 8 - 1e-9]
    assert len(guest) == 1 and guest[0].polygon.equals(box(2, 8, 4, 10))  # clipped to the house
    total = sum(r.area for r in plan.rooms)
    assert total == pytest.approx(64.0)  # house area: rooms tile it without overlap
    assert plan.walls is not None and plan.walls.shape == (6, 4) and plan.doors == []


def test_overlapping_boxes_kept_when_not_disjoint():
    plan = load_houseexpo(HOUSE, disjoint=False)
    living = next(r for r in plan.rooms if r.type == "living_room")
    assert living.area == pytest.approx(40.0)


def test_type_names():
    assert houseexpo_type("Living_Room") == "living_room"
    assert houseexpo_type("Hallway") == "corridor"
    assert houseexpo_type("child_room") == "bedroom"
    assert houseexpo_type("Garage") == "storage"
    assert houseexpo_type("indoor") == "unknown"
    assert houseexpo_type("Gym") == "unknown"


def test_dispatch_from_floorplan_load_and_round_trip(tmp_path):
    plan = FloorPlan.load(_write(tmp_path, HOUSE))
    assert len(plan.rooms) == 4
    back = FloorPlan.load(plan.save(tmp_path / "ours.json"))
    assert [(r.id, r.type, round(r.area, 9)) for r in back.rooms] == [
        (r.id, r.type, round(r.area, 9)) for r in plan.rooms
    ]


def test_house_without_room_boxes_is_one_room():
    plan = load_houseexpo({"verts": HOUSE["verts"]})
    assert len(plan.rooms) == 1 and plan.rooms[0].area == pytest.approx(64.0)


@pytest.mark.parametrize(
    ("data", "what"),
    [
        ({"room_category": {}}, "verts: missing"),
        ({"verts": [[0, 0], [1, 1]]}, "verts: expected at least 3"),
        ({"verts": [[0, 0], [1, "a"], [0, 1]]}, "verts: expected numbers"),
        ({"verts": [[0, 0], [1e9, 0], [0, 1]]}, "absurd"),
        ({"verts": [[0, 0], [1, 0], [2, 0]]}, "encloses no area"),
        ({"verts": HOUSE["verts"], "room_category": {"Bedroom": [[0, 0, 1]]}}, "room_category.Bedroom"),
        ({"verts": HOUSE["verts"], "room_category": [1, 2]}, "room_category: expected an object"),
    ],
)
def test_bad_houses_name_the_field(tmp_path, data, what):
    path = _write(tmp_path, data)
    with pytest.raises(FloorPlanError) as err:
        load_houseexpo(path)
    assert str(path) in str(err.value) and what in str(err.value), str(err.value)


def test_bad_files(tmp_path):
    cases = {
        _write(tmp_path, '{"verts": [[0, 0], [1, 0],\n', "broken.json"): "line 2",
        _write(tmp_path, "  ", "empty.json"): "empty",
        tmp_path / "missing.json": "not found",
        _write(tmp_path, "[1, 2]", "list.json"): "expected a JSON object",
    }
    for path, what in cases.items():
        with pytest.raises(FloorPlanError) as err:
            load_houseexpo(path)
        assert str(path) in str(err.value) and what in str(err.value), str(err.value)


def _house_file(tmp_path: Path, **change) -> Path:
    house = {
        "id": "h",
        "verts": [[0, 0], [10, 0], [10, 8], [0, 8]],
        "room_category": {"bedroom": [[1, 1, 4, 4]], "kitchen": [[6, 1, 9, 7]]},
    }
    house.update(change)
    path = tmp_path / "house.json"
    path.write_text(json.dumps(house))
    return path


def test_a_boolean_inside_a_vertex_is_refused(tmp_path):
    """[true, 0] was read as (1, 0): the check looked at the top level of the list only."""
    path = _house_file(tmp_path, verts=[[0, 0], [True, 0], [10, 8], [0, 8]])
    with pytest.raises(FloorPlanError, match=r"house\.json: verts: expected numbers \(not true / false"):
        FloorPlan.load(path)


def test_a_self_intersecting_contour_is_refused_not_repaired(tmp_path):
    """It was repaired into its largest piece (a triangle), dropping the rooms outside it."""
    path = _house_file(tmp_path, verts=[[0, 0], [10, 8], [10, 0], [0, 8]])
    with pytest.raises(
        FloorPlanError, match=r"verts: the house contour is not a simple polygon \(Self-intersection"
    ):
        FloorPlan.load(path)


def test_a_room_box_outside_the_contour_is_refused(tmp_path):
    """It was dropped without a word: a plan with one room fewer."""
    path = _house_file(tmp_path, room_category={"bedroom": [[1, 1, 4, 4]], "kitchen": [[50, 50, 60, 60]]})
    with pytest.raises(
        FloorPlanError, match=r"room_category\.kitchen\[0\]: room box .* lies outside the house contour"
    ):
        FloorPlan.load(path)


def test_a_contour_of_more_points_than_the_wall_limit_is_refused(tmp_path, monkeypatch):
    """400,000 contour points became a plan of 400,000 walls (16 s to read, minutes to use)."""
    import math

    from frslam_graph import limits

    monkeypatch.setattr(limits, "MAX_PLAN_WALLS", 100)
    ring = [
        [5 + 4 * math.cos(2 * math.pi * k / 101), 4 + 3 * math.sin(2 * math.pi * k / 101)] for k in range(101)
    ]
    with pytest.raises(FloorPlanError, match=r"verts: 101 contour points, over the limit of 100 walls"):
        FloorPlan.load(_house_file(tmp_path, verts=ring, room_category={}))
