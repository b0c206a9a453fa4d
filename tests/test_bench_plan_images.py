"""tools/bench_plan_images.py: ground-truth rooms matched by the rooms read from a plan image,
at another pixel density too; a reading that joins two rooms matches one of them only."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import load_tool

from tests.test_plan_images import two_rooms


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_plan_images")


def plan_folder(tmp_path):
    """A plan of two rooms and its ground truth (one colour a room), as the IPA files are named."""
    folder = tmp_path / "ipa"
    folder.mkdir()
    img = two_rooms()
    cv2.imwrite(str(folder / "two.png"), img)
    seg = np.zeros((*img.shape, 3), np.uint8)
    seg[23:178, 23:138] = (0, 0, 255)
    seg[23:178, 143:278] = (0, 255, 0)
    cv2.imwrite(str(folder / "two_gt_segmentation.png"), seg)
    return folder


def test_both_rooms_matched_at_every_density(bench, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (row,) = bench.rows(plan_folder(tmp_path), [0.5, 1.0, 2.0], None, work)
    assert row["truth"] == 2 and row["rooms"] == [2, 2, 2]
    assert row["matched"] == [1.0, 1.0, 1.0]


def test_a_door_width_that_closes_no_door_matches_one_room_of_two(bench, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (row,) = bench.rows(plan_folder(tmp_path), [1.0], 5.0, work)  # the 20 px gap stays open
    assert row["rooms"] == [1] and row["matched"] == [0.5]


def test_bad_scales_are_refused_in_one_line(bench, capsys):
    assert bench.main(["--scales", "0"]) == 2
    assert capsys.readouterr().err.strip() == "--scales: expected factors between 0.1 and 8"
