"""Occupancy maps from images without a YAML (``OccupancyGrid.from_image``, ``load(png,
resolution=...)``, ``frslam register PLAN MAP.png --resolution R``), read as ROS map_server."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from frslam_graph.cli import main
from frslam_graph.errors import MapError
from frslam_graph.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid


def test_map_server_thresholds_and_negate(tmp_path):
    # p = (255 - v) / 255: occupied above 0.65 (v <= 89), free below 0.196 (v >= 206)
    values = np.array([[0, 89, 90, 128, 205, 206, 254, 255]], np.uint8)
    path = tmp_path / "row.png"
    cv2.imwrite(str(path), values)
    grid = OccupancyGrid.from_image(path, 0.05)
    assert grid.data[0].tolist() == [OCCUPIED, OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, FREE, FREE, FREE]
    neg = OccupancyGrid.from_image(path, 0.05, negate=True)
    # negated: p = v / 255, free below 0.196 (v <= 49), occupied above 0.65 (v >= 166)
    assert neg.data[0].tolist() == [FREE, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED, OCCUPIED, OCCUPIED, OCCUPIED]
    strict = OccupancyGrid.from_image(path, 0.05, occupied_thresh=0.99, free_thresh=0.001)
    assert strict.data[0].tolist() == [OCCUPIED, *[UNKNOWN] * 6, FREE]
    with pytest.raises(MapError, match="free_thresh"):
        OccupancyGrid.from_image(path, 0.05, occupied_thresh=0.1, free_thresh=0.5)


def test_top_row_of_the_image_is_the_highest_y(tmp_path):
    img = np.full((40, 30), 254, np.uint8)
    img[0:2, 10:12] = 0  # a mark at the top of the image
    path = tmp_path / "mark.png"
    cv2.imwrite(str(path), img)
    grid = OccupancyGrid.from_image(path, 0.1, origin=(1.0, 2.0, 0.0))
    rows, cols = np.nonzero(grid.occupied_mask())
    assert set(rows.tolist()) == {38, 39}  # row 0 = lowest y, as nav_msgs
    xy = grid.cell_to_world(np.column_stack([cols + 0.5, rows + 0.5]))
    assert xy[:, 1].max() == pytest.approx(2.0 + 4.0 - 0.05)  # the top edge of the map
    assert xy[:, 0].min() == pytest.approx(1.0 + 1.05)
    assert grid.source == str(path) and grid.resolution == 0.1


def test_load_dispatches_images_and_agrees_with_a_yaml(tmp_path):
    img = np.full((20, 30), 205, np.uint8)
    img[5:15, 5:25] = 254
    img[5, 5:25] = 0
    cv2.imwrite(str(tmp_path / "m.pgm"), img)
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.05\norigin: [-1.0, 0.5, 0.0]\n")
    via_yaml = OccupancyGrid.load(tmp_path / "m.yaml")
    via_image = OccupancyGrid.load(tmp_path / "m.pgm", resolution=0.05, origin=(-1.0, 0.5, 0.0))
    assert np.array_equal(via_yaml.data, via_image.data) and via_yaml.origin == via_image.origin
    with pytest.raises(MapError, match="needs its resolution"):
        OccupancyGrid.load(tmp_path / "m.pgm")
    with pytest.raises(MapError, match="states its own resolution"):
        OccupancyGrid.load(tmp_path / "m.yaml", resolution=0.05)
    with pytest.raises(MapError, match="resolution: must be a positive"):
        OccupancyGrid.from_image(tmp_path / "m.pgm", 0.0)


def test_bad_map_images_name_the_file(tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_text("hello")
    (tmp_path / "huge.pgm").write_bytes(b"P5\n25000 25000\n255\n" + b"\0" * 16)
    cases = {"empty.png": "empty", "text.png": "not a readable image", "huge.pgm": "25000x25000 px"}
    for name, what in cases.items():
        with pytest.raises(MapError) as err:
            OccupancyGrid.from_image(tmp_path / name, 0.05)
        assert str(tmp_path / name) in str(err.value) and what in str(err.value), str(err.value)


def building(scale: float) -> np.ndarray:
    """An L-shaped flat of three rooms of different sizes with door gaps, drawn ``scale`` px per
    unit: grey outside, white rooms, black walls."""
    s = scale
    img = np.full((int(130 * s), int(170 * s)), 128, np.uint8)
    pts = (np.array([[10, 10], [160, 10], [160, 70], [90, 70], [90, 120], [10, 120]]) * s).astype(np.int32)
    cv2.fillPoly(img, [pts], 255)
    cv2.polylines(img, [pts], True, 0, max(1, int(round(1.5 * s))))
    t = max(1, int(round(1.5 * s)))
    cv2.line(img, (int(90 * s), int(10 * s)), (int(90 * s), int(70 * s)), 0, t)  # left | right
    cv2.line(img, (int(10 * s), int(70 * s)), (int(90 * s), int(70 * s)), 0, t)  # top | bottom
    img[int(30 * s) : int(40 * s), int(88 * s) : int(92 * s) + 1] = 255  # door left-right
    img[int(68 * s) : int(72 * s) + 1, int(40 * s) : int(50 * s)] = 255  # door top-bottom
    return img


def test_cli_register_a_plan_image_on_a_map_image(tmp_path, capsys):
    plan = tmp_path / "plan.png"
    cv2.imwrite(str(plan), building(2.0))
    map_png = tmp_path / "map.png"
    cv2.imwrite(str(map_png), building(3.0))
    out = tmp_path / "reg"
    assert main(["register", str(plan), str(map_png), "--resolution", "0.05", "-o", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())["registration"]
    assert report["ok"] and not report["flipped"]  # same axis convention: no flip
    # 3 px of the map per 2 px of the plan, 0.05 m per map pixel
    assert np.mean(report["scale"]) == pytest.approx(0.075, rel=0.05)
    capsys.readouterr()
    assert main(["register", str(plan), str(map_png), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(map_png) in err and "--resolution" in err and len(err.strip().splitlines()) == 1


def test_a_damaged_png_says_one_line_libpng_says_nothing(tmp_path, capfd):
    """libpng printed 'libpng error: PNG input buffer is incomplete' before our line."""
    ok, buf = cv2.imencode(".png", (np.random.default_rng(0).random((200, 200)) * 255).astype(np.uint8))
    png = tmp_path / "cut.png"
    png.write_bytes(buf.tobytes()[: len(buf) // 2])
    assert main(["map", "show", str(png), "--resolution", "0.05", "--out", str(tmp_path / "o.png")]) == 2
    err = capfd.readouterr().err
    assert "libpng" not in err and len(err.strip().splitlines()) == 1 and "cut.png" in err, err


def test_a_device_as_a_map_image_is_refused(tmp_path):
    (tmp_path / "z.pgm").symlink_to("/dev/zero")
    with pytest.raises(MapError, match="not a regular file"):
        OccupancyGrid.load(tmp_path / "z.pgm", resolution=0.05)
