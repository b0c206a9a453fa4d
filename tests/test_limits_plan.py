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
