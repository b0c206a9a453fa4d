"""FloorPlan model: our JSON format, validation with file + field in every error, transforms."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from shapely.geometry import box

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan import Door, FloorPlan, Room, normalise_room_type


def two_rooms() -> dict:
    return {
        "format": "frslam-floorplan",
        "version": 1,
        "units": "px",
        "rooms": [
            {"id": "a", "type": "Living Room", "polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]},
            {"id": "b", "type": "toilet", "polygon": [[4, 0], [6, 0], [6, 3], [4, 3]]},
        ],
        "doors": [{"id": "d0", "segment": [[4, 1], [4, 2]], "rooms": ["a", "b"]}],
        "walls": [[0, 0, 6, 0]],
    }


def write(tmp_path, data, name="plan.json"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


def test_load_normalises_types_and_links_doors(tmp_path):
    plan = FloorPlan.load(write(tmp_path, two_rooms()))
    assert [r.type for r in plan.rooms] == ["living_room", "restroom"]
    assert plan.adjacency() == {"a": {"b"}, "b": {"a"}}
    assert plan.bounds == (0.0, 0.0, 6.0, 3.0)
    assert plan.area == pytest.approx(18.0)
    assert plan.walls.shape == (1, 4)
    assert plan.name == "plan"


def test_link_doors_from_geometry():
    d = two_rooms()
    d["doors"][0]["rooms"] = []
    plan = FloorPlan.from_dict(d)
    assert plan.adjacency() == {"a": set(), "b": set()}
    assert plan.link_doors(0.1).adjacency() == {"a": {"b"}, "b": {"a"}}


@pytest.mark.parametrize(
    ("label", "expected"),
    [
        ("Living Room", "living_room"),
        ("WC", "restroom"),
        ("hallway", "corridor"),
        ("xyz", "unknown"),
        ("washing_room", "washing_room"),
        ("Bedroom", "bedroom"),
    ],
)
def test_normalise_room_type(label, expected):
    assert normalise_room_type(label) == expected


def test_transformed_applies_affine_and_flip():
    plan = FloorPlan.from_dict(two_rooms())
    m = np.array([[0.0, -2.0, 1.0], [1.0, 0.0, 2.0], [0, 0, 1]])  # rotate 90°, scale x2 along old y
    t = plan.transformed(m, units="m")
    assert t.units == "m" and t.metres_per_unit == 1.0
    assert t.rooms[0].area == pytest.approx(2 * plan.rooms[0].area)
    assert t.doors[0].a == pytest.approx((1 - 2 * 1, 2 + 4))
    flipped = plan.transformed(np.diag([1.0, -1.0, 1.0]))
    assert all(r.polygon.is_valid for r in flipped.rooms)
    assert flipped.bounds == (0.0, -3.0, 6.0, 0.0)


def test_subset_keeps_touching_doors():
    plan = FloorPlan.from_dict(two_rooms())
    sub = plan.subset(["a"])
    assert sub.room_ids == ["a"] and sub.doors[0].rooms == ("a",)
    with pytest.raises(KeyError):
        plan.subset(["zz"])


coord = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@st.composite
def plans(draw):
    n = draw(st.integers(1, 5))
    rooms = []
    for i in range(n):
        x, y = draw(coord), draw(coord)
        w, h = draw(st.floats(0.1, 100)), draw(st.floats(0.1, 100))
        rtype = draw(st.sampled_from(["bedroom", "kitchen", "corridor", "unknown"]))
        rooms.append(Room(f"r{i}", rtype, box(x, y, x + w, y + h)))
    doors = [
        Door(
            f"d{j}",
            (draw(coord), draw(coord)),
            (draw(coord), draw(coord)),
            tuple(draw(st.lists(st.sampled_from([r.id for r in rooms]), max_size=2, unique=True))),
        )
        for j in range(draw(st.integers(0, 3)))
    ]
    mpu = draw(st.one_of(st.none(), st.floats(1e-3, 10)))
    return FloorPlan(rooms, doors, None, "px", mpu, "h")


@settings(max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture], deadline=None)
@given(plan=plans())
def test_json_round_trip(tmp_path, plan):
    path = plan.save(tmp_path / "rt.json")
    back = FloorPlan.load(path)
    assert back.room_ids == plan.room_ids
    assert [r.type for r in back.rooms] == [r.type for r in plan.rooms]
    for a, b in zip(plan.rooms, back.rooms, strict=True):
        assert a.polygon.equals_exact(b.polygon, 1e-9)
    assert [(d.a, d.b, d.rooms) for d in back.doors] == [(d.a, d.b, d.rooms) for d in plan.doors]
    assert back.metres_per_unit == plan.metres_per_unit and back.units == plan.units


def _mutate(path, value):
    d = two_rooms()
    target = d
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return d


@pytest.mark.parametrize(
    ("data", "field", "words"),
    [
        ("{ not json", "line 1", "malformed JSON"),
        ("", None, "empty"),
        ("[1, 2]", None, "JSON object"),
        (_mutate(["rooms"], KeyError), "rooms", "missing"),
        (_mutate(["rooms"], []), "rooms", "at least one room"),
        (_mutate(["rooms", 0, "polygon"], KeyError), "rooms[0].polygon", "missing"),
        (_mutate(["rooms", 0, "polygon"], [[0, 0], [1, 1]]), "rooms[0].polygon", "at least 3"),
        (
            _mutate(["rooms", 0, "polygon"], [[0, 0], [2, 2], [2, 0], [0, 2]]),
            "rooms[0].polygon",
            "Self-intersection",
        ),
        (
            _mutate(["rooms", 1, "polygon"], [[0, 0], [1e9, 0], [1e9, 1], [0, 1]]),
            "rooms[1].polygon",
            "absurd",
        ),
        (_mutate(["rooms", 1, "polygon"], [[0, 0], ["a", 0], [1, 1]]), "rooms[1].polygon", "number pairs"),
        (_mutate(["rooms", 1, "id"], "a"), "rooms[1].id", "duplicate"),
        (_mutate(["doors", 0, "rooms"], ["a", "zz"]), "doors[0].rooms", "unknown room"),
        (_mutate(["doors", 0, "segment"], [[0, 0]]), "doors[0].segment", "at least 2"),
        (_mutate(["walls"], [[0, 0, 1]]), "walls", "x1, y1, x2, y2"),
        (_mutate(["version"], 7), "version", "unsupported"),
        (_mutate(["metres_per_unit"], -1), "metres_per_unit", "positive"),
        (_mutate(["rooms", 0, "polygon"], [[0, 0], [float("nan"), 0], [1, 1]]), "rooms[0].polygon", "finite"),
    ],
)
def test_bad_json_names_file_and_field(tmp_path, data, field, words):
    path = write(tmp_path, data)
    with pytest.raises(FloorPlanError) as exc:
        FloorPlan.load(path)
    msg = str(exc.value)
    assert str(path) in msg
    if field:
        assert field in msg
    assert words.lower() in msg.lower()


def test_missing_file_and_unknown_suffix(tmp_path):
    with pytest.raises(FloorPlanError, match="not found"):
        FloorPlan.load(tmp_path / "nope.json")
    p = tmp_path / "plan.xyz"
    p.write_text("x")
    with pytest.raises(FloorPlanError, match="unknown floor-plan file type"):
        FloorPlan.load(p)


def test_binary_garbage_json(tmp_path):
    p = tmp_path / "bin.json"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(FloorPlanError, match=str(p)):
        FloorPlan.load(p)


def test_load_can_be_told_the_reader(tmp_path):
    """FloorPlan.load picks the reader from the suffix, or takes the one named (io.READERS)."""
    import shutil
    from pathlib import Path

    src = Path(__file__).parent / "data" / "r2v" / "000209a30b61b563f93faf6a6466ffab_0001.txt"
    odd = tmp_path / "plan.r2v"
    shutil.copy(src, odd)
    with pytest.raises(FloorPlanError, match="unknown floor-plan file type '.r2v'"):
        FloorPlan.load(odd)
    told = FloorPlan.load(odd, reader="r2v")
    plain = FloorPlan.load(src)
    assert [r.polygon.wkb for r in told.rooms] == [r.polygon.wkb for r in plain.rooms]
    with pytest.raises(FloorPlanError, match="unknown floor-plan reader 'svg'"):
        FloorPlan.load(src, reader="svg")
