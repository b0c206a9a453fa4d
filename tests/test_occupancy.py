"""OccupancyGrid: map_server YAML + image, conventions (row 0 = lowest y), bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

from frslam_graph.errors import MapError
from frslam_graph.occupancy import OccupancyGrid

BUNDLED = __import__("pathlib").Path(__file__).resolve().parents[1] / "frslam_graph" / "data" / "prbonn"


def test_bundled_gmap_loads_and_round_trips(tmp_path):
    g = OccupancyGrid.load(BUNDLED / "GMap.yaml")
    assert g.shape == (272, 604) and g.resolution == 0.05
    assert g.origin == pytest.approx((-13.90309, -10.82778, 0.0))
    assert g.free_mask().sum() > 100_000 and g.occupied_mask().sum() > 5_000
    back = OccupancyGrid.load(g.save(tmp_path / "out" / "m.yaml"))
    np.testing.assert_array_equal(back.data, g.data)
    assert back.origin == g.origin and back.resolution == g.resolution
    back_png = OccupancyGrid.load(g.save(tmp_path / "png.yaml", image_format="png"))
    np.testing.assert_array_equal(back_png.data, g.data)


def test_shared_fmap_loads(shared_data):
    f = OccupancyGrid.load(shared_data / "prbonn" / "FMap.yaml")
    g = OccupancyGrid.load(shared_data / "prbonn" / "GMap.yaml")
    assert f.shape == (279, 521)
    # same world frame: the known areas overlap substantially
    assert abs(f.origin[0] - g.origin[0]) < 0.1


def _write_map(tmp_path, img: np.ndarray, **meta) -> object:
    import cv2

    cv2.imwrite(str(tmp_path / "m.pgm"), img)
    fields = {
        "image": "m.pgm",
        "resolution": 0.1,
        "origin": [1.0, 2.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    } | meta
    lines = [f"{k}: {v}" for k, v in fields.items() if v is not None]
    (tmp_path / "m.yaml").write_text("\n".join(lines) + "\n")
    return tmp_path / "m.yaml"


def test_row_zero_is_lowest_y_and_thresholds(tmp_path):
    img = np.full((4, 3), 205, np.uint8)
    img[0, 0] = 0  # top-left in the image = highest y -> last row of data
    img[3, 2] = 254  # bottom-right -> row 0
    g = OccupancyGrid.load(_write_map(tmp_path, img))
    assert g.data[3, 0] == 100 and g.data[0, 2] == 0 and g.data[1, 1] == -1
    # cell (col 2, row 0) centre in map metres
    np.testing.assert_allclose(g.cell_to_world([[2.5, 0.5]]), [[1.25, 2.05]])
    np.testing.assert_allclose(g.world_to_cell([[1.25, 2.05]]), [[2.5, 0.5]])
    neg = OccupancyGrid.load(_write_map(tmp_path, img, negate=1))
    assert neg.data[3, 0] == 0 and neg.data[0, 2] == 100


def test_yaw_origin_round_trip():
    g = OccupancyGrid(np.zeros((5, 5), np.int8), 0.5, (1.0, -2.0, 0.7))
    pts = np.array([[0.3, 0.2], [3.0, 1.5]])
    np.testing.assert_allclose(g.world_to_cell(g.cell_to_world(pts)), pts)


def test_crop_to_known_keeps_world_position():
    data = np.full((20, 30), -1, np.int8)
    data[5:8, 10:14] = 0
    g = OccupancyGrid(data, 0.1, (0.0, 0.0, 0.0))
    c = g.crop_to_known(margin_cells=1)
    assert c.shape == (5, 6)
    assert c.origin[:2] == pytest.approx((0.9, 0.4))


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("", "empty"),
        ("image: [unclosed", "malformed YAML"),
        ("resolution: 0.05\norigin: [0, 0, 0]\n", "image: missing"),
        ("image: m.pgm\norigin: [0, 0, 0]\n", "resolution: missing"),
        ("image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "does not exist"),
        ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", "positive"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0]\nfree_thresh: 0.9\n", "free_thresh"),
        ("image: m.pgm\nresolution: 0.05\norigin: 7\n", "origin"),
        ("image: notimage.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "not a readable image"),
        ("image: empty.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "empty file"),
    ],
)
def test_bad_maps_name_file_and_field(tmp_path, content, words):
    import cv2

    cv2.imwrite(str(tmp_path / "m.pgm"), np.zeros((3, 3), np.uint8))
    (tmp_path / "notimage.pgm").write_text("this is text, not an image")
    (tmp_path / "empty.pgm").write_bytes(b"")
    y = tmp_path / "bad.yaml"
    y.write_text(content)
    with pytest.raises(MapError) as exc:
        OccupancyGrid.load(y)
    assert str(y) in str(exc.value)
    assert words.lower() in str(exc.value).lower()


def test_missing_yaml_and_bad_arrays(tmp_path):
    with pytest.raises(MapError, match="not found"):
        OccupancyGrid.load(tmp_path / "none.yaml")
    with pytest.raises(MapError, match="resolution"):
        OccupancyGrid(np.zeros((2, 2), np.int8), 0.0)
    with pytest.raises(MapError, match="2D"):
        OccupancyGrid(np.zeros((0, 2), np.int8), 0.1)
    with pytest.raises(MapError, match="-1"):
        OccupancyGrid(np.full((2, 2), 120), 0.1)
