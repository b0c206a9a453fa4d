"""Room-segmentation image + map YAML -> FloorPlan in metres (PRBonn IPB floor, 12 rooms)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan import FloorPlan
from frslam_graph.floorplan.roomseg import from_room_segmentation, load_room_segmentation

PRBONN = Path(__file__).parent / "data" / "prbonn"
RES = 0.05


@pytest.mark.parametrize("stem", ["FMap", "GMap"])
def test_twelve_rooms_whose_areas_match_the_label_pixels(stem):
    png, yaml = PRBONN / f"{stem}RoomSeg.png", PRBONN / f"{stem}.yaml"
    plan = from_room_segmentation(png, yaml)
    labels = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert plan.units == "m" and plan.metres_per_unit == 1.0 and plan.name == f"{stem}RoomSeg"
    assert plan.room_ids == [f"room_{v}" for v in range(1, 13)]
    assert {r.type for r in plan.rooms} == {"unknown"}
    for room in plan.rooms:
        pixels = int((labels == int(room.id.split("_")[1])).sum())
        assert room.area == pytest.approx(pixels * RES**2, rel=0.03), room.id
        assert room.polygon.is_valid
    # simplified: far fewer corners than boundary pixels
    assert max(len(r.polygon.exterior.coords) for r in plan.rooms) < 120


def test_map_frame_row_zero_is_the_top():
    plan = from_room_segmentation(PRBONN / "GMapRoomSeg.png", PRBONN / "GMap.yaml")
    labels = cv2.imread(str(PRBONN / "GMapRoomSeg.png"), cv2.IMREAD_GRAYSCALE)
    h = labels.shape[0]
    ox, oy = -13.90309, -10.82778  # GMap.yaml origin
    # the centre of a pixel of room 3 maps into room_3's polygon
    rows, cols = np.nonzero(labels == 3)
    r, c = rows[len(rows) // 2], cols[len(cols) // 2]
    x, y = ox + (c + 0.5) * RES, oy + (h - r - 0.5) * RES
    assert plan.room("room_3").polygon.buffer(0.03).contains(Point(x, y))
    x0, y0, x1, y1 = plan.bounds
    assert x0 >= ox - 1e-9 and y0 >= oy - 1e-9
    assert x1 <= ox + labels.shape[1] * RES + 1e-9 and y1 <= oy + h * RES + 1e-9


def test_doors_where_rooms_touch():
    plan = from_room_segmentation(PRBONN / "FMapRoomSeg.png", PRBONN / "FMap.yaml")
    assert len(plan.doors) >= 8
    for door in plan.doors:
        assert len(door.rooms) == 2 and 0.3 <= door.width <= 3.0
    # room 11 is the corridor: most rooms open onto it
    assert len(plan.adjacency()["room_11"]) >= 6


def test_dispatch_yaml_beside_and_json_round_trip(tmp_path):
    via_load = FloorPlan.load(PRBONN / "FMapRoomSeg.png", yaml=PRBONN / "FMap.yaml")
    beside = load_room_segmentation(PRBONN / "FMapRoomSeg.png")  # finds FMap.yaml
    assert via_load.room_ids == beside.room_ids
    out = beside.save(tmp_path / "prbonn.json")
    back = FloorPlan.load(out)
    assert back.room_ids == beside.room_ids and back.units == "m" and back.metres_per_unit == 1.0
    for a, b in zip(beside.rooms, back.rooms, strict=True):
        assert a.polygon.equals_exact(b.polygon, 1e-9) and len(a.polygon.interiors) == len(
            b.polygon.interiors
        )
    assert [d.rooms for d in back.doors] == [d.rooms for d in beside.doors]


def test_yaw_and_options(tmp_path):
    yaml = tmp_path / "rot.yaml"
    yaml.write_text("resolution: 0.1\norigin: [1.0, 2.0, 1.5707963267948966]\n")
    seg = np.full((20, 30), 255, np.uint8)
    seg[2:12, 3:8] = 7  # 10 rows x 5 cols
    png = tmp_path / "seg.png"
    cv2.imwrite(str(png), seg)
    plan = from_room_segmentation(png, yaml, room_type="Office", simplify=0.0)
    (room,) = plan.rooms
    assert room.id == "room_7" and room.type == "office" and room.area == pytest.approx(50 * 0.01)
    # in the unrotated map frame the room spans x 0.3..0.8, y 0.8..1.8 (row 0 is the top);
    # the origin's yaw turns that by +90 deg, (x, y) -> (-y, x), then shifts by (1, 2)
    x0, y0, x1, y1 = room.polygon.bounds
    assert (x0, x1, y0, y1) == pytest.approx((1.0 - 1.8, 1.0 - 0.8, 2.3, 2.8))


def _bad(tmp_path: Path, name: str, content: bytes | str) -> Path:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return path


def test_bad_images(tmp_path):
    yaml = PRBONN / "GMap.yaml"
    cases = {
        _bad(tmp_path, "text.png", "not an image at all"): "not a readable image",
        _bad(tmp_path, "empty.png", b""): "empty",
        tmp_path / "missing.png": "not found",
    }
    colour = np.zeros((272, 604, 3), np.uint8)
    colour[..., 2] = 3
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    cases[tmp_path / "colour.png"] = "channels differ"
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((272, 604), 255, np.uint8))
    cases[tmp_path / "blank.png"] = "no room labels"
    cv2.imwrite(str(tmp_path / "small.png"), np.full((10, 10), 1, np.uint8))
    cases[tmp_path / "small.png"] = "10x10 px but the map image GMap.png"
    for png, what in cases.items():
        with pytest.raises(FloorPlanError) as err:
            from_room_segmentation(png, yaml)
        assert str(png) in str(err.value) and what in str(err.value), str(err.value)


def test_bad_yaml(tmp_path):
    png = PRBONN / "FMapRoomSeg.png"
    cases = {
        _bad(tmp_path, "nores.yaml", "image: x.pgm\norigin: [0, 0, 0]\n"): "resolution: missing",
        _bad(tmp_path, "neg.yaml", "resolution: -1\norigin: [0, 0, 0]\n"): "resolution: expected a positive",
        _bad(tmp_path, "noorigin.yaml", "resolution: 0.05\n"): "origin: missing",
        _bad(tmp_path, "origin.yaml", "resolution: 0.05\norigin: [0, a]\n"): "origin: expected [x, y, yaw]",
        _bad(tmp_path, "broken.yaml", "resolution: [0.05\norigin: [0, 0, 0]\n"): "malformed YAML",
        _bad(tmp_path, "empty.yaml", ""): "empty",
        _bad(tmp_path, "list.yaml", "- 1\n- 2\n"): "expected a YAML mapping",
        tmp_path / "missing.yaml": "not found",
    }
    for yaml, what in cases.items():
        with pytest.raises(FloorPlanError) as err:
            from_room_segmentation(png, yaml)
        assert str(yaml) in str(err.value) and what in str(err.value), str(err.value)
    with pytest.raises(FloorPlanError, match="no map YAML beside"):
        shutil.copy(png, tmp_path / "LonelyRoomSeg.png")
        load_room_segmentation(tmp_path / "LonelyRoomSeg.png")


def test_yaml_whose_map_image_is_missing_still_places_the_segmentation(tmp_path):
    """The map image is not needed to place a segmentation (resolution + origin are), so a
    YAML pointing at a missing image is accepted; the shape check runs when it exists."""
    yaml = _bad(tmp_path, "FMap.yaml", (PRBONN / "FMap.yaml").read_text())
    assert not (tmp_path / "FMap.pgm").exists()
    plan = from_room_segmentation(PRBONN / "FMapRoomSeg.png", yaml)
    assert len(plan.rooms) == 12


def test_shared_prbonn_segmentations(shared_data):
    for stem in ("FMap", "GMap"):
        plan = FloorPlan.from_room_segmentation(
            shared_data / "prbonn" / f"{stem}RoomSeg.png", shared_data / "prbonn" / f"{stem}.yaml"
        )
        assert len(plan.rooms) == 12


def test_small_holes_can_be_filled():
    png, yaml = PRBONN / "GMapRoomSeg.png", PRBONN / "GMap.yaml"
    exact = from_room_segmentation(png, yaml)
    filled = from_room_segmentation(png, yaml, fill_holes_below=1.0)
    assert sum(len(r.polygon.interiors) for r in exact.rooms) > 50
    for a, b in zip(exact.rooms, filled.rooms, strict=True):
        assert all(Polygon(h).area >= 1.0 for h in b.polygon.interiors)
        assert b.area >= a.area
