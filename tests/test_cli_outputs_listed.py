"""Every file a command wrote is listed at its end (from the output manifests), with whether the
floor plan was accepted and when; ``metrics.json`` carries the acceptance (``plan_accepted``)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from frslam_graph.backend.decisions import DecisionEvent
from frslam_graph.cli import main
from frslam_graph.cli.summary import plan_status
from frslam_graph.offline import plan_acceptance
from tests.test_outputs_atomic import SIM_ARGS
from tests.test_registration import EXPLORED, ring_map, synthetic_plan, truth_matrix


@pytest.fixture(scope="module")
def plan_json(tmp_path_factory) -> Path:
    from frslam_graph.datasets.simulator import five_room_plan

    return five_room_plan().save(tmp_path_factory.mktemp("plan") / "five.json")


def listed(out: Path, manifest: str) -> list[str]:
    return json.loads((out / manifest).read_text())["outputs"]


def test_plan_acceptance_is_the_first_accepted_registration():
    stamps = 100.0 + 0.25 * np.arange(12)
    log = [
        DecisionEvent(101.0, "register", "too little map", 1, {"accepted": False}),
        DecisionEvent(101.5, "prior_added", "prior", 2, {}),
        DecisionEvent(
            102.0, "register", "accepted", 3, {"accepted": True, "distance_m": 4.0, "plan_seen": 0.4}
        ),
        DecisionEvent(102.5, "register", "agrees; refined", 4, {"accepted": False}),
        DecisionEvent(102.75, "registration_replaced", "replaces", 5, {"accepted": True}),
    ]
    result = SimpleNamespace(trajectory=np.column_stack([stamps, np.zeros((12, 3))]), log=log)
    assert plan_acceptance(result) == {
        "scan": 8,
        "stamp": 102.0,
        "time_s": 2.0,
        "keyframe": 3,
        "registrations_tried": 2,
        "distance_m": 4.0,
        "plan_seen": 0.4,
        "at_end": False,
    }
    assert plan_acceptance(SimpleNamespace(trajectory=result.trajectory, log=log[:2])) is None


def test_plan_status_says_never_accepted_and_nothing_without_a_plan():
    never = plan_status({"floor_plan": True, "plan_accepted": None, "decisions": {"register": 3}})
    assert "never accepted" in never and "3 registrations tried" in never
    assert plan_status({"floor_plan": False, "plan_accepted": None}) is None


def test_plan_status_says_how_far_the_robot_drove_and_how_much_it_had_seen():
    acc = {"scan": 8, "time_s": 2.0, "registrations_tried": 2, "distance_m": 41.4, "plan_seen": 0.62}
    line = plan_status({"floor_plan": True, "plan_accepted": acc, "scans": 12, "decisions": {"register": 3}})
    assert "41 m driven, 62% of the plan's rooms seen" in line and "end of the run" not in line
    at_end = plan_status({"floor_plan": True, "plan_accepted": {**acc, "at_end": True}, "scans": 12})
    assert "on the complete map at the end of the run" in at_end


def test_run_lists_every_file_and_when_the_plan_was_accepted(
    small_log, plan_json, tmp_path, replayed, capsys
):
    out = tmp_path / "run"
    assert main(["run", str(small_log[0]), "--floor-plan", str(plan_json), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    names = listed(out, "metrics.json")
    assert "registered_plan.json" in names and "trajectory.png" in names
    for name in names:
        assert f"│ {name} " in text, name
    acc = json.loads((out / "metrics.json").read_text())["plan_accepted"]
    assert acc["scan"] > 0 and acc["time_s"] > 0 and acc["registrations_tried"] >= 1
    assert f"floor plan: accepted at scan {acc['scan']:,} of " in text
    assert f"{acc['time_s']:.1f} s into the recording" in text


def test_compare_lists_both_runs_files(small_log, plan_json, tmp_path, replayed, capsys):
    out = tmp_path / "cmp"
    assert main(["compare", str(small_log[0]), "--floor-plan", str(plan_json), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for sub in ("without_priors", "with_priors"):
        for name in listed(out / sub, "metrics.json"):
            assert f"│ {sub}/{name} " in text, name
    for name in listed(out, "compare.json"):
        assert f"│ {name} " in text, name
    summary = json.loads((out / "compare.json").read_text())
    assert summary["with priors"]["plan_accepted"]["scan"] > 0
    assert "floor plan (with priors): accepted at scan" in text


def test_register_lists_its_files(tmp_path, capsys):
    plan = synthetic_plan()
    ring_map(plan, truth_matrix(True, 90.0), EXPLORED).save(tmp_path / "map.yaml")
    plan.save(tmp_path / "plan.json")
    out = tmp_path / "reg"
    assert main(["register", str(tmp_path / "plan.json"), str(tmp_path / "map.yaml"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert listed(out, "report.json") == ["overlay.png", "registered_plan.json", "report.json"]
    for name in listed(out, "report.json"):
        assert f"│ {name} " in text, name
    assert "floor plan: registered" in text


def test_simulate_lists_its_files(plan_json, tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(plan_json), "--out", str(out), *SIM_ARGS]) == 0
    text = capsys.readouterr().out
    names = listed(out, "meta.json")
    assert "bag" in names and "ground_truth.tum" in names
    for name in names:
        shown = f"{name}/" if (out / name).is_dir() else name
        assert f"│ {shown} " in text, name
