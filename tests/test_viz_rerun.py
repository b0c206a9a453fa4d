"""``--viz FILE.rrd``: a rerun recording of scans, map, trajectory and registered plan that rerun
loads; without rerun-sdk one line naming --viz and the install command."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from frslam_graph.cli import main

pytest.importorskip("rerun", reason="rerun-sdk (the dev extra) is needed for the --viz tests")

RERUN = Path(sys.executable).parent / "rerun"


def rerun_cli(*args: str, home: Path) -> subprocess.CompletedProcess:
    """The rerun command line, with its configuration in ``home`` and no usage data (CI=1)."""
    env = {
        **os.environ,
        "CI": "1",
        "HOME": str(home),
        "XDG_CONFIG_HOME": str(home),
        "XDG_DATA_HOME": str(home),
    }
    return subprocess.run([str(RERUN), *args], capture_output=True, text=True, env=env, timeout=600)


def entities(path: Path, home: Path) -> set[str]:
    verified = rerun_cli("rrd", "verify", str(path), home=home)
    assert verified.returncode == 0, verified.stderr
    printed = rerun_cli("rrd", "print", str(path), home=home)
    assert printed.returncode == 0, printed.stderr
    return {w.strip("\"',") for w in printed.stdout.split() if w.strip("\"',").startswith("/world/")}


@pytest.fixture
def plan_json(five_room_sim, tmp_path) -> Path:
    return five_room_sim[0].save(tmp_path / "five.json")


def test_run_viz_writes_a_recording_rerun_loads(small_log, plan_json, replayed, tmp_path, capsys):
    rrd = tmp_path / "run.rrd"
    argv = ["run", str(small_log[0]), "--floor-plan", str(plan_json), "--out", str(tmp_path / "o")]
    assert main([*argv, "--viz", str(rrd)]) == 0
    assert rrd.stat().st_size > 10_000
    assert str(rrd) in capsys.readouterr().out  # listed with the outputs
    found = entities(rrd, tmp_path)
    for name in ("scan", "robot", "trajectory", "map", "plan/rooms", "plan/doors", "decisions"):
        assert f"/world/run/{name}" in found, (name, found)


def test_compare_viz_holds_both_runs(small_log, plan_json, replayed, tmp_path):
    rrd = tmp_path / "cmp.rrd"
    argv = ["compare", str(small_log[0]), "--floor-plan", str(plan_json), "--out", str(tmp_path / "o")]
    assert main([*argv, "--viz", str(rrd)]) == 0
    found = entities(rrd, tmp_path)
    assert {"/world/without_priors/scan", "/world/with_priors/scan", "/world/with_priors/plan/rooms"} <= found


def test_viz_without_rerun_sdk_is_one_line_naming_the_option(small_log, tmp_path, monkeypatch, capsys):
    import frslam_graph.offline as offline

    def never(*args, **kwargs):
        raise AssertionError("the run started")

    monkeypatch.setattr(offline, "run_recording", never)
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    out = tmp_path / "o"
    assert main(["run", str(small_log[0]), "--out", str(out), "--viz", str(tmp_path / "r.rrd")]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err
        == "error: --viz: needs rerun-sdk, which is not installed: pip install 'frslam[viz]' (or: pip install rerun-sdk)"
    )
    assert not (out / "metrics.json").exists()


def test_viz_needs_an_rrd_file(small_log, tmp_path, capsys):
    assert (
        main(["run", str(small_log[0]), "--out", str(tmp_path / "o"), "--viz", str(tmp_path / "r.txt")]) == 2
    )
    err = capsys.readouterr().err
    assert "--viz" in err and "unsupported extension '.txt' (expected .rrd)" in err


def test_demo_lists_its_files_and_writes_the_viz_recording(replayed, tmp_path, capsys):
    """The demo's SLAM runs replayed (``replayed``): its plans, registration, file table and
    --viz recording are the real ones."""
    from frslam_graph.cli.demo import SLAM_RUNS

    out, rrd = tmp_path / "demo", tmp_path / "demo.rrd"
    assert main(["demo", "--out", str(out), "--length", "1", "--viz", str(rrd)]) == 0
    text = capsys.readouterr().out
    for sub in SLAM_RUNS:
        for name in json.loads((out / sub / "metrics.json").read_text())["outputs"]:
            assert f"│ {sub}/{name} " in text, name
    for name in ("apartment_plan.png", "office_plan.png", "office_registered.png", "slam_compare.png"):
        assert f"│ {name} " in text, name
    assert "floor plan (with priors): accepted at scan" in text
    assert f"also written: {rrd}" in text.replace("\n", "")
    assert {"/world/with_priors/plan/rooms", "/world/without_priors/scan"} <= entities(rrd, tmp_path)


@pytest.mark.parametrize("command", ["run", "compare", "demo"])
def test_viz_help_names_the_extra(command, capsys):
    assert main([command, "--help"]) == 0
    assert "'frslam[viz]'" in capsys.readouterr().out
