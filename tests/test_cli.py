"""The ``frslam`` command line: every command exists, outputs are written, bad input -> exit 2."""

from __future__ import annotations

import json

import pytest

from frslam_graph.cli import main
from frslam_graph.resources import bundled

COMMANDS = ["demo", "run", "compare", "register", "simulate", "plan", "map", "inspect", "navigate", "config"]


def test_every_command_is_registered(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    missing = [c for c in COMMANDS if f" {c} " not in text]
    assert not missing, f"commands missing from frslam --help: {missing}"


def test_map_show_writes_png(tmp_path, capsys):
    out = tmp_path / "m.png"
    assert main(["map", "show", str(bundled("prbonn/GMap.yaml")), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    assert "604" in capsys.readouterr().out


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    assert main(["map", "show", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "does not exist" in err and "Traceback" not in err
    assert main(["run", str(tmp_path / "missing.clf"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.clf" in capsys.readouterr().err


def test_run_writes_every_output(small_log, tmp_path, capsys):
    log, gt = small_log
    out = tmp_path / "run"
    assert main(["run", str(log), "--ground-truth", str(gt), "--out", str(out)]) == 0
    for name in (
        "trajectory.tum",
        "odometry.tum",
        "map.yaml",
        "map.pgm",
        "metrics.json",
        "log.jsonl",
        "trajectory.png",
    ):
        assert (out / name).exists(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["scans"] > 100
    assert metrics["ate"]["rmse"] < 0.10  # KISS-ICP in a well-constrained room
    assert "ATE RMSE" in capsys.readouterr().out
    # the loop closer's work (matches, batches, plans skipped while the queue was full)
    lc = metrics["loop_closure"]
    assert lc["attempts"] >= lc["accepted"] + lc["rejected"]
    assert {"plans_skipped", "cpu_seconds", "batches", "reasons"} <= set(lc)


def test_run_sequential_gives_the_same_trajectory(small_log, tmp_path):
    """--sequential keeps the odometry in-process; the default may run it in a worker process."""
    from frslam_graph.config import FRSlamConfig
    from frslam_graph.odometry import worker as odometry_worker

    log, _ = small_log
    a, b = tmp_path / "default", tmp_path / "seq"
    assert main(["run", str(log), "--out", str(a)]) == 0
    assert main(["run", str(log), "--sequential", "--out", str(b)]) == 0
    assert (a / "trajectory.tum").read_text() == (b / "trajectory.tum").read_text()
    worker = json.loads((a / "metrics.json").read_text())["odometry_in_worker"]
    assert worker == odometry_worker.available(FRSlamConfig().odometry)
    assert json.loads((b / "metrics.json").read_text())["odometry_in_worker"] is False


def test_compare_with_unusable_plan_still_reports_both(small_log, tmp_path, capsys):
    """A one-room plan cannot be registered: no priors, both runs reported, nothing lost."""
    log, gt = small_log
    plan = tmp_path / "one_room.json"
    plan.write_text(
        json.dumps({"rooms": [{"id": "r", "type": "office", "polygon": [[0, 0], [12, 0], [12, 8], [0, 8]]}]})
    )
    out = tmp_path / "cmp"
    assert (
        main(["compare", str(log), "--floor-plan", str(plan), "--ground-truth", str(gt), "--out", str(out)])
        == 0
    )
    summary = json.loads((out / "compare.json").read_text())
    assert set(summary) == {"without priors", "with priors", "outputs"}
    assert summary["outputs"] == ["compare.png", "compare.json"]
    assert summary["with priors"]["ate"]["rmse"] < 0.2
    assert (out / "compare.png").exists()
    assert "with priors" in capsys.readouterr().out


def test_usage_errors_exit_2_without_traceback(capsys):
    assert main(["map", "show"]) == 2
    assert main(["no-such-command"]) == 2
    err = capsys.readouterr().err
    assert "Missing argument" in err and "No such command" in err and "Traceback" not in err


def test_error_message_with_brackets_is_printed_verbatim(tmp_path, capsys):
    assert main(["map", "show", str(tmp_path / "map[1].yaml")]) == 2
    assert "map[1].yaml" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "compare"])
def test_bad_ground_truth_or_config_stops_before_the_run(small_log, tmp_path, capsys, monkeypatch, command):
    """Every input is checked before the (possibly long) run: a malformed ground truth, a
    missing one or a config with a mistyped field exits 2 naming the file and the line / field,
    without processing the recording (before, a bad --ground-truth failed after the run and its
    outputs were lost)."""
    import frslam_graph.offline as offline

    log, _ = small_log
    runs = []
    monkeypatch.setattr(offline, "run_recording", lambda *a, **k: runs.append(1))
    bad_gt = tmp_path / "bad.tum"
    bad_gt.write_text("1000.0 1 2\n")
    bad_cfg = tmp_path / "cfg.yaml"
    bad_cfg.write_text("odometry:\n  voxel_sise: 0.2\n")
    room = tmp_path / "room.json"
    room.write_text(
        json.dumps({"rooms": [{"id": "r", "type": "office", "polygon": [[0, 0], [12, 0], [12, 8], [0, 8]]}]})
    )
    plan = ["--floor-plan", str(room)] if command == "compare" else []
    cases = [
        (["--ground-truth", str(bad_gt)], ["bad.tum", "line 1", "expected 8 numbers"]),
        (["--ground-truth", str(tmp_path / "nothere.tum")], ["nothere.tum", "no such file"]),
        (["--config", str(bad_cfg)], ["cfg.yaml", "odometry.voxel_sise"]),
    ]
    for extra, words in cases:
        out = tmp_path / f"out{len(runs)}"
        assert main([command, str(log), *plan, *extra, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), err
        assert "Traceback" not in err
    assert not runs


def test_reader_warnings_are_one_line_and_kept_in_the_metrics(small_log, tmp_path, capsys):
    """A record the reader skips is reported as one 'warning:' line naming the file and line (no
    Python source line) and counted in metrics.json, so it is not lost with the terminal."""
    log, _ = small_log
    lines = log.read_text().splitlines()
    bad = tmp_path / "with_bad_record.clf"
    bad.write_text("\n".join([*lines[:50], "FLASER 180 1.0 2.0 3.0", *lines[50:]]) + "\n")
    out = tmp_path / "run"
    assert main(["run", str(bad), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    warn = [x for x in err.splitlines() if "skipped" in x]
    assert len(warn) == 1 and warn[0].startswith("warning: ") and "with_bad_record.clf:51" in warn[0]
    assert "enumerate" not in err and "RecordingWarning" not in err
    rec = json.loads((out / "metrics.json").read_text())["recording"]
    assert sum(rec["skipped"].values()) == 1
    assert list(rec["first_at"].values()) == ["with_bad_record.clf:51"]
    assert rec["beams"] == 180 * (len(lines)) and 0 <= rec["invalid_beams"] <= rec["beams"]


def test_compare_keeps_the_first_runs_outputs_when_the_second_fails(small_log, tmp_path, monkeypatch):
    """compare writes the run without priors before starting the one with them: a failure in
    the second run (here a simulated crash) does not lose the first run's outputs."""
    import frslam_graph.offline as offline

    log, gt = small_log
    room = tmp_path / "room.json"
    room.write_text(
        json.dumps({"rooms": [{"id": "r", "type": "office", "polygon": [[0, 0], [12, 0], [12, 8], [0, 8]]}]})
    )
    real = offline.run_recording

    def second_fails(recording, floor_plan=None, **kw):
        if floor_plan is not None:
            raise RuntimeError("simulated crash in the run with priors")
        return real(recording, floor_plan=floor_plan, **kw)

    monkeypatch.setattr(offline, "run_recording", second_fails)
    out = tmp_path / "cmp"
    with pytest.raises(RuntimeError, match="simulated crash"):
        main(["compare", str(log), "--floor-plan", str(room), "--ground-truth", str(gt), "--out", str(out)])
    assert (out / "without_priors" / "trajectory.tum").exists()
    assert json.loads((out / "without_priors" / "metrics.json").read_text())["ate"]["rmse"] < 0.2
