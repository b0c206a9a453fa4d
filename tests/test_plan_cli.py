"""``frslam plan show`` / ``frslam plan convert`` on real excerpts, and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.image as mpimg

from frslam_graph.cli import main
from frslam_graph.floorplan import FloorPlan

DATA = Path(__file__).parent / "data"
R2V = DATA / "r2v" / "000209a30b61b563f93faf6a6466ffab_0001.txt"


def test_show_r2v_writes_png_and_summary(tmp_path, capsys):
    out = tmp_path / "plan.png"
    assert main(["plan", "show", str(R2V), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "13 rooms" in text and "bedroom 1" in text and "9/9 labelled rooms found" in text
    img = mpimg.imread(out)
    assert img.shape[0] > 400 and img.shape[1] > 400
    # rooms are filled in colour: many pixels are neither white nor grey
    rgb = img[..., :3]
    coloured = (rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.1
    assert coloured.mean() > 0.05


def test_show_room_segmentation_finds_its_yaml(tmp_path, capsys):
    out = tmp_path / "seg.png"
    assert (
        main(["plan", "show", str(DATA / "prbonn" / "GMapRoomSeg.png"), "-o", str(out), "--no-labels"]) == 0
    )
    assert "12 rooms" in capsys.readouterr().out and out.stat().st_size > 10_000


def test_convert_to_our_json_and_back(tmp_path, capsys):
    out = tmp_path / "plan.json"
    assert main(["plan", "convert", str(R2V), str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["format"] == "frslam-floorplan" and data["units"] == "px" and len(data["rooms"]) == 13
    plan = FloorPlan.load(out)
    assert {r.type for r in plan.rooms} >= {"bedroom", "living_room", "kitchen", "closet"}
    seg = tmp_path / "seg.json"
    yaml = DATA / "prbonn" / "FMap.yaml"
    assert (
        main(["plan", "convert", str(DATA / "prbonn" / "FMapRoomSeg.png"), str(seg), "--yaml", str(yaml)])
        == 0
    )
    assert FloorPlan.load(seg).units == "m"
    # and a converted plan shows
    assert main(["plan", "show", str(out), "-o", str(tmp_path / "again.png")]) == 0


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("1\t2\t3\t4\twall\t1\t1\n1\t2\tthree\n")
    assert main(["plan", "show", str(bad), "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "line 2" in err and "Traceback" not in err
    assert main(["plan", "convert", str(R2V), str(tmp_path / "out.png")]) == 2
    assert "unsupported extension '.png' (expected .json)" in capsys.readouterr().err
    assert main(["plan", "show", str(tmp_path / "nothere.json")]) == 2
    assert "not found" in capsys.readouterr().err
