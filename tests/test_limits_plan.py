"""Floor plans: size limits checked before parsing, JSON numbers strict (no booleans, no strings)."""

from __future__ import annotations

import json

import pytest

from frslam_graph import limits
from frslam_graph.cli import main
from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan import FloorPlan


def plan(polygon: list) -> dict:
    return {
        "format": "frslam-floorplan",
        "version": 1,
        "units": "px",
        "rooms": [{"id": "a", "type": "kitchen", "polygon": polygon}],
    }


def write(tmp_path, data, name="plan.json"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


@pytest.mark.parametrize(
    ("vertex", "shown"),
    [([True, False], "[True, False]"), (["107.0", 0], "['107.0', 0]")],
    ids=["bool", "string"],
)
def test_a_vertex_must_hold_json_numbers(tmp_path, vertex, shown):
    path = write(tmp_path, plan([vertex, [4, 0], [4, 3], [0, 3]]))
    with pytest.raises(
        FloorPlanError, match=r"plan\.json: rooms\[0\]\.polygon\[0\]: expected \[x, y\] number pairs"
    ) as err:
        FloorPlan.load(path)
    assert shown in str(err.value)


def test_numbers_are_still_read(tmp_path):
    loaded = FloorPlan.load(write(tmp_path, plan([[0, 0], [4.5, 0], [4.5, 3], [0, 3]])))
    assert loaded.rooms[0].area == pytest.approx(13.5)


def test_a_plan_over_the_size_limit_is_refused_before_parsing(tmp_path, monkeypatch):
    monkeypatch.setattr(limits, "MAX_PLAN_BYTES", 1000)
    path = write(tmp_path, plan([[0, 0], [4, 0], [4, 3], [0, 3]] * 50))
    with pytest.raises(
        FloorPlanError, match=r"plan\.json: file of \d[\d,]* bytes is over the limit of 1,000 bytes"
    ):
        FloorPlan.load(path)


def test_an_r2v_file_with_too_many_walls_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(limits, "MAX_PLAN_WALLS", 100)
    path = tmp_path / "walls.txt"
    path.write_text("".join(f"{i} 0 {i} 10 wall 1 1\n" for i in range(101)))
    with pytest.raises(FloorPlanError, match=r"walls\.txt: line 101: more than 100 walls"):
        FloorPlan.load(path)


def test_an_r2v_file_over_the_size_limit_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(limits, "MAX_PLAN_BYTES", 1000)
    path = tmp_path / "big.txt"
    path.write_text("0 0 1 1 wall 1 1\n" * 100)
    with pytest.raises(FloorPlanError, match=r"big\.txt: R2V file of 1,700 bytes is over the limit"):
        FloorPlan.load(path)


def test_plan_cli_with_a_boolean_vertex_exits_2_with_one_line(tmp_path, capsys):
    path = write(tmp_path, plan([[True, False], [4, 0], [4, 3], [0, 3]]))
    assert main(["plan", "show", str(path), "--out", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert "plan.json" in err and "expected [x, y] number pairs" in err and len(err.splitlines()) == 1


def test_rooms_over_the_limit_are_refused_before_they_are_built(tmp_path, monkeypatch):
    """60,000 small rooms (9 MB of JSON) took over 30 s to convert and minutes to draw."""
    monkeypatch.setattr(limits, "MAX_PLAN_ROOMS", 50)
    rooms = [
        {"id": f"r{i}", "polygon": [[3 * i, 0], [3 * i + 2, 0], [3 * i + 2, 2], [3 * i, 2]]}
        for i in range(51)
    ]
    path = write(tmp_path, {"rooms": rooms})
    with pytest.raises(
        FloorPlanError, match=r"plan\.json: rooms: 51 rooms, over the limit of 50 \(MAX_PLAN_ROOMS"
    ):
        FloorPlan.load(path)
    FloorPlan.load(write(tmp_path, {"rooms": rooms[:50]}))  # at the limit: read


def test_r2v_doors_count_with_the_walls(tmp_path, monkeypatch):
    """100,000 random R2V walls (under the old limit of 200,000) grew to 2 GB; the default limit
    is now 2,000 walls and doors (real plans: at most 75 walls)."""
    assert limits.MAX_PLAN_WALLS <= 2_000
    monkeypatch.setattr(limits, "MAX_PLAN_WALLS", 10)
    path = tmp_path / "doors.txt"
    path.write_text(
        "".join(f"{i} 0 {i} 10 wall 1 1\n" for i in range(6))
        + "".join(f"{i} 0 {i} 1 door 1 1\n" for i in range(6))
    )
    with pytest.raises(FloorPlanError, match=r"doors\.txt: line 11: more than 10 walls and doors"):
        FloorPlan.load(path)


def test_room_labels_over_the_limit_are_refused(tmp_path, monkeypatch):
    import numpy as np

    from frslam_graph.floorplan.roomseg import rooms_from_labels

    monkeypatch.setattr(limits, "MAX_PLAN_ROOMS", 3)
    lab = np.arange(16, dtype=np.int32).reshape(4, 4)
    with pytest.raises(FloorPlanError, match=r"seg\.png: 15 room labels, over the limit of 3 rooms"):
        rooms_from_labels(lab, np.arange(1, 16), [1, 0, 0, 1, 0, 0], source="seg.png")
