"""The streaming API's contract (issue 22): bad arguments are refused naming the argument, one
thread at a time, equal stamps keep every scan, non-finite config values refused."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from synthetic_world import ROOM_LOOP, drifting_odometry, room_world, route, scans_along

from frslam_graph.backend.context import BackendContext
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, FloorPlanError, FrslamError
from frslam_graph.floorplan.model import FloorPlan
from frslam_graph.slam import FRSlam

CFG = {"odometry": {"max_range": 10.0}, "loop_closure": {"enabled": False}}
ROOM = {"rooms": [{"id": "r", "type": "office", "polygon": [[0, 0], [12, 0], [12, 8], [0, 8]]}]}


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, list[np.ndarray], float, float, np.ndarray]:
    truth = route(ROOM_LOOP)[:80]
    ranges, amin, inc = scans_along(room_world(), truth)
    return truth, ranges, amin, inc, drifting_odometry(truth)


@pytest.fixture()
def slam(room) -> FRSlam:
    """An FRSlam with one scan in (the bad call must not be its first)."""
    truth, ranges, amin, inc, wheel = room
    s = FRSlam(CFG)
    s.add_scan(truth[0, 0], ranges[0], amin, inc, wheel[0])
    return s


NAN = float("nan")


@pytest.mark.parametrize(
    ("change", "where"),
    [
        ({"ranges": "abc"}, "ranges"),
        ({"ranges": ["a", "b"]}, "ranges"),
        ({"ranges": None}, "ranges"),
        ({"ranges": np.ones((2, 720))}, "ranges"),
        ({"stamp": NAN}, "stamp"),
        ({"stamp": "x"}, "stamp"),
        ({"stamp": None}, "stamp"),
        ({"angle_min": "x"}, "angle_min"),
        ({"angle_increment": "x"}, "angle_increment"),
        ({"angle_increment": 0.0}, "angle_increment"),
        ({"odom": (1.0, 2.0)}, "odom"),
        ({"odom": "abc"}, "odom"),
        ({"odom": np.zeros((3, 3))}, "odom"),
        ({"sensor_offset": (1.0, 2.0)}, "sensor_offset"),
        ({"sensor_offset": (0.0, 0.0, NAN)}, "sensor_offset"),
        ({"sensor_offset": "abc"}, "sensor_offset"),
        ({"sensor_offset": None}, "sensor_offset"),
        ({"range_max": "x"}, "range_max"),
        ({"range_max": NAN}, "range_max"),
        ({"range_max": -1.0}, "range_max"),
    ],
)
def test_bad_add_scan_arguments_are_refused_naming_the_argument(slam, room, change, where):
    """Before, most of these raised a bare numpy ValueError / IndexError / TypeError, and a NaN
    sensor offset or range_max was taken (a scan with NaN points or none)."""
    truth, ranges, amin, inc, wheel = room
    args: dict[str, Any] = {
        "stamp": truth[1, 0],
        "ranges": ranges[1],
        "angle_min": amin,
        "angle_increment": inc,
        "odom": wheel[1],
        "range_max": None,
        "sensor_offset": (0.0, 0.0, 0.0),
    }
    args.update(change)
    with pytest.raises(FrslamError) as exc:
        slam.add_scan(**args)
    assert exc.value.where == where, str(exc.value)
    assert len(slam) == 1  # nothing recorded


@pytest.mark.parametrize(
    ("points", "odom"),
    [(np.zeros((6, 3)), None), (np.zeros((5, 3)), None), ("abc", None), (np.zeros((4, 2)), "x")],
)
def test_bad_add_points_arguments_are_refused(slam, room, points, odom):
    """(6, 3) points were silently read as 9 (x, y) pairs."""
    with pytest.raises(FrslamError) as exc:
        slam.add_points(room[0][1, 0], points, odom)
    assert exc.value.where == ("points" if odom is None else "odom")
    assert len(slam) == 1


def test_valid_inputs_still_pass(slam, room):
    """Empty scans, wheel odometry with a NaN (no wheel reading), range_max inf, lists: taken."""
    truth, ranges, amin, inc, wheel = room
    slam.add_scan(truth[1, 0], [], amin, inc)
    slam.add_scan(truth[2, 0], list(ranges[2]), amin, inc, (NAN, 0.0, 0.0), range_max=float("inf"))
    slam.add_points(truth[3, 0], np.zeros((0, 2)))
    slam.add_points(truth[4, 0], np.zeros(0), odom=list(wheel[4]), sensor_offset=[0.1, 0.0, 0.0])
    assert len(slam) == 5


def test_floor_plan_path_is_loaded(tmp_path):
    """A path is loaded with FloorPlan.load (as ``config`` takes a path); before, it was kept as
    a string and every registration failed with a logged AttributeError."""
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(ROOM))
    for given in (path, str(path)):
        s = FRSlam(CFG, floor_plan=given)
        assert isinstance(s.floor_plan, FloorPlan)
        assert isinstance(s.update_strategy.plan, FloorPlan)


def test_floor_plan_of_another_type_or_missing_file_is_refused(tmp_path):
    with pytest.raises(FloorPlanError) as exc:
        FRSlam(CFG, floor_plan={"rooms": []})
    assert exc.value.where == "floor_plan" and "FloorPlan" in str(exc.value)
    with pytest.raises(FloorPlanError, match="nothere.json"):
        FRSlam(CFG, floor_plan=tmp_path / "nothere.json")


def test_equal_stamps_keep_every_scan(room):
    """64 scans with one stamp: every scan kept, none counted as dropped (the tester saw 63 of
    64 dropped without a warning; the odometry now takes scans in arrival order)."""
    truth, ranges, amin, inc, wheel = room
    s = FRSlam(CFG)
    for i in range(64):
        s.add_scan(5.0, ranges[i], amin, inc, wheel[i])
    traj = s.trajectory()
    assert traj.shape == (64, 4) and np.all(traj[:, 0] == 5.0)
    assert np.all(np.isfinite(traj))
    assert s.stats.scans == 64 and s.stats.dropped_scans == 0
    assert s.stats.out_of_order == 63  # counted, not dropped
    assert "dropped_scans" not in [e.kind for e in s.log]


def test_concurrent_add_scan_is_refused(room, monkeypatch):
    """FRSlam is single-threaded: a second thread's call while one runs raises instead of
    corrupting the trajectory. Deterministic: the first call is held inside its odometry step."""
    truth, ranges, amin, inc, wheel = room
    s = FRSlam(CFG)
    entered, release = threading.Event(), threading.Event()
    real = s.odometry.process

    def held(*args: Any, **kwargs: Any) -> Any:
        entered.set()
        assert release.wait(60)
        return real(*args, **kwargs)

    monkeypatch.setattr(s.odometry, "process", held)
    errors: list[BaseException] = []

    def first() -> None:
        try:
            s.add_scan(truth[0, 0], ranges[0], amin, inc, wheel[0])
        except BaseException as exc:  # reported to the main thread
            errors.append(exc)

    t = threading.Thread(target=first)
    t.start()
    try:
        assert entered.wait(60)
        with pytest.raises(FrslamError, match="not thread-safe: add_scan called from two threads"):
            s.add_scan(truth[1, 0], ranges[1], amin, inc, wheel[1])
        with pytest.raises(FrslamError, match="not thread-safe: finish"):
            s.finish()
    finally:
        release.set()
        t.join()
    assert not errors and len(s) == 1
    monkeypatch.undo()
    s.add_scan(truth[1, 0], ranges[1], amin, inc, wheel[1])  # free again once the first returned
    assert len(s) == 2


def test_hooks_may_call_back_on_the_same_thread(room):
    """The lock is per thread: an update strategy adding a prior inside add_scan is fine."""
    truth, ranges, amin, inc, wheel = room
    added = []

    def hook(slam: BackendContext, kf: Any) -> None:
        if kf.index == 1:
            added.append(slam.add_prior(kf.index, kf.pose_map, np.eye(3) * 0.01))

    s = FRSlam(CFG, update_strategy=hook)
    for i in range(30):
        s.add_scan(truth[i, 0], ranges[i], amin, inc, wheel[i])
    assert len(added) == 1


@pytest.mark.parametrize("value", [float("inf"), float("nan"), float("-inf")])
def test_non_finite_config_values_are_refused(value):
    with pytest.raises(ConfigError) as exc:
        FRSlamConfig.from_dict({"odometry": {"max_range": value}})
    assert exc.value.where == "odometry.max_range" and "finite" in str(exc.value)
    with pytest.raises(ConfigError, match="loop_closure.budget_ms"):
        FRSlamConfig.from_dict({"loop_closure": {"budget_ms": value}})


def test_cli_config_with_inf_exits_2_in_one_line(small_log, tmp_path: Path, capsys):
    """``max_range: .inf`` aborted the odometry worker, and --sequential the process (exit 134,
    Sophus SO3::exp nan); now refused before the run."""
    from frslam_graph.cli import main

    log, _ = small_log
    bad = tmp_path / "bad.yaml"
    bad.write_text("odometry:\n  max_range: .inf\n")
    for extra in ([], ["--sequential"]):
        assert main(["run", str(log), "--config", str(bad), "--out", str(tmp_path / "o"), *extra]) == 2
        err = capsys.readouterr().err
        assert "bad.yaml" in err and "odometry.max_range" in err and "finite" in err, err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_cli_version(capsys):
    from importlib.metadata import version

    from frslam_graph.cli import main

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"frslam {version('frslam')}"


@pytest.mark.parametrize(
    ("change", "where"),
    [
        ({"ranges": [True, False] * 360}, "ranges"),
        ({"ranges": ["1.0"] * 720}, "ranges"),
        ({"ranges": np.ones(720, dtype=bool)}, "ranges"),
        ({"odom": ("1", "2", "3")}, "odom"),
    ],
)
def test_booleans_and_number_strings_are_not_ranges(slam, room, change, where):
    """numpy read [True, False] as 1 / 0 and "1.0" as 1.0: a scan of made-up ranges."""
    truth, ranges, amin, inc, wheel = room
    args: dict[str, Any] = {
        "stamp": truth[1, 0],
        "ranges": ranges[1],
        "angle_min": amin,
        "angle_increment": inc,
    }
    args["odom"] = wheel[1]
    args.update(change)
    with pytest.raises(FrslamError, match=f"{where} must be"):
        slam.add_scan(**args)


def test_a_huge_bad_value_is_quoted_short():
    """A 50 MB string given as the stamp was quoted whole in the message (and the line)."""
    s = FRSlam(CFG)
    with pytest.raises(FrslamError) as err:
        s.add_scan("1" * 5_000_000, np.ones(10), 0.0, 0.1)
    assert len(str(err.value)) < 200
    with pytest.raises(FrslamError) as err:
        s.add_scan(0.0, np.ones(10), 0.0, 0.1, range_max=[1.0] * 1_000_000)
    assert len(str(err.value)) < 200
