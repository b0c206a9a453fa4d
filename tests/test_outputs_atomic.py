"""Outputs written whole or not at all (issue 22): interruptions, signals, symlinks, a bad
``--out`` found before the work, a full disk, reruns into the same folder, a mismatched ground truth."""

from __future__ import annotations

import errno
import importlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from frslam_graph.atomic import TEMP_PREFIX, atomic_write
from frslam_graph.cli import main
from frslam_graph.errors import Interrupted

R2V = Path(__file__).parent / "data" / "r2v" / "000209a30b61b563f93faf6a6466ffab_0001.txt"
#: a short simulation through the CLI (a few seconds)
SIM_ARGS = ["--seed", "5", "--beams", "91", "--scan-rate", "5", "--length", "5", "--rooms", "living,kitchen"]


def one_line(err: str) -> str:
    """The only non-empty line of ``err`` (asserting there is one and no traceback)."""
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def listing(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative name: content); temporary names included."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished_run(small_log):
    """A finished run of the small log (computed once; the CLI tests reuse it)."""
    from frslam_graph.datasets import open_recording

    from frslam_graph.offline import run_recording

    return run_recording(open_recording(small_log[0]), parallel=False)


@pytest.fixture
def quick_run(finished_run, monkeypatch):
    """``frslam run`` without processing: run_recording returns the finished run; ``calls`` counts."""
    import frslam_graph.offline as offline

    calls: list[object] = []

    def fake(recording, floor_plan=None, **kw):
        calls.append(floor_plan)
        return finished_run

    monkeypatch.setattr(offline, "run_recording", fake)
    return calls


@pytest.fixture(scope="module")
def plan_json(tmp_path_factory) -> Path:
    from frslam_graph.datasets.simulator import five_room_plan

    return five_room_plan().save(tmp_path_factory.mktemp("plan") / "five.json")


def test_atomic_write_failing_midway_keeps_the_previous_file(tmp_path):
    target = tmp_path / "t.txt"
    target.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_write(target) as fh:
        fh.write("new, cut mid-")
        raise RuntimeError("killed while writing")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["t.txt"]


def test_run_interrupted_while_writing_leaves_the_previous_run_whole(
    small_log, tmp_path, quick_run, monkeypatch, capsys
):
    """A signal arriving mid-write (here raised by a writer half-way through trajectory.tum)
    leaves the previous run's outputs as they were, no half file, and one line, exit 143."""
    import frslam_graph.evaluation.trajectory_io as trajectory_io

    log, gt = small_log
    out = tmp_path / "run"
    assert main(["run", str(log), "--ground-truth", str(gt), "--out", str(out)]) == 0
    before = listing(out)
    capsys.readouterr()

    def cut_save_tum(path, trajectory):
        with atomic_write(path) as fh:
            fh.write("# stamp x y z qx qy qz qw\n1000.0 0 0 0 0 0 0 1\n")
            raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(trajectory_io, "save_tum", cut_save_tum)
    assert main(["run", str(log), "--ground-truth", str(gt), "--out", str(out)]) == 143
    assert one_line(capsys.readouterr().err) == "frslam: interrupted (SIGTERM); outputs left: none"
    assert listing(out) == before


def test_compare_interrupted_in_the_second_run_names_the_first(
    small_log, tmp_path, finished_run, monkeypatch, capsys
):
    import frslam_graph.offline as offline

    def second_interrupted(recording, floor_plan=None, **kw):
        if floor_plan is not None:
            raise Interrupted(signal.SIGINT)
        return finished_run

    monkeypatch.setattr(offline, "run_recording", second_interrupted)
    log, gt = small_log
    out = tmp_path / "cmp"
    args = ["compare", str(log), "--floor-plan", str(R2V), "--ground-truth", str(gt), "--out", str(out)]
    assert main(args) == 130
    line = one_line(capsys.readouterr().err)
    assert line == f"frslam: interrupted (SIGINT); outputs left: {out / 'without_priors'}"
    assert sorted(p.name for p in out.iterdir()) == ["without_priors"]
    assert "metrics.json" in json.loads((out / "without_priors" / "metrics.json").read_text())["outputs"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_real_signal_during_simulate_leaves_the_previous_simulation(plan_json, tmp_path, sig):
    """``frslam simulate --overwrite`` in a subprocess, stopped by a real signal while it writes
    ground_truth.tum (the writer waits for the signal after a marker file): the previous
    simulation is left whole, nothing half, one line, exit 128 + signal."""
    out = tmp_path / "sim"
    assert main(["simulate", str(plan_json), "--out", str(out), *SIM_ARGS]) == 0
    before = listing(out)
    marker = tmp_path / "writing"
    script = textwrap.dedent(
        """
        import importlib, pathlib, signal, sys
        from frslam_graph.atomic import atomic_write
        from frslam_graph.cli import main

        def stuck_write_tum(path, stamps, poses):
            with atomic_write(path) as fh:
                fh.write("# half a ground truth\\n")
                fh.flush()
                pathlib.Path(sys.argv[1]).touch()
                while True:
                    signal.pause()

        sim = importlib.import_module("frslam_graph.datasets.simulator.simulate")
        sim.write_tum = stuck_write_tum
        sys.exit(main(sys.argv[2:]))
        """
    )
    args = ["simulate", str(plan_json), "--out", str(out), *SIM_ARGS, "--overwrite"]
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(marker), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 300  # only a guard against a hang, not a timing assertion
        while not marker.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the writer was never reached"
            time.sleep(0.05)
        assert any(p.name.startswith(TEMP_PREFIX) for p in out.iterdir())  # caught mid-write
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + sig
    assert one_line(err) == f"frslam: interrupted ({signal.Signals(sig).name}); outputs left: none"
    assert listing(out) == before


def test_symlink_at_an_output_is_replaced_not_followed(small_log, tmp_path, quick_run):
    log, _ = small_log
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours\n")
    out = tmp_path / "run"
    out.mkdir()
    (out / "trajectory.tum").symlink_to(victim)
    assert main(["run", str(log), "--out", str(out)]) == 0
    assert victim.read_text() == "not yours\n"
    assert not (out / "trajectory.tum").is_symlink()
    assert (out / "trajectory.tum").read_text().startswith("# stamp")
    converted = tmp_path / "plan.json"
    converted.symlink_to(victim)
    assert main(["plan", "convert", str(R2V), str(converted)]) == 0
    assert victim.read_text() == "not yours\n" and not converted.is_symlink()


def _no_call(calls: list[str], name: str):
    return lambda *a, **k: calls.append(name)


@pytest.mark.parametrize(
    "command, words",
    [
        (["run", "{log}", "--out", "{file}"], ["--out", "not a folder"]),
        (["run", "{log}", "--out", "{file}/sub"], ["--out", "is not a folder, cannot create"]),
        (["compare", "{log}", "--floor-plan", str(R2V), "--out", "{file}"], ["--out", "not a folder"]),
        (["register", str(R2V), "{map}", "--out", "{file}"], ["--out", "not a folder"]),
        (["simulate", "{plan}", "--out", "{file}"], ["--out", "not a folder"]),
        (["plan", "show", str(R2V), "--out", "{dir}/x.png"], ["--out", "is a folder"]),
        (["plan", "show", str(R2V), "--out", "{dir}/x.txt"], ["--out", "'.txt'", ".png, .pdf, .svg"]),
        (["plan", "convert", str(R2V), "{dir}/x.png"], ["OUT.json", "'.png'", ".json"]),
        (["map", "show", "{map}", "--out", "{file}/m.png"], ["--out", "is not a folder"]),
        (
            ["navigate", "{plan}", "--from", "0", "0", "--to", "kitchen", "--out", "{dir}/p.txt"],
            ["--out", "'.txt'"],
        ),
        (["demo", "--out", "{file}"], ["--out", "not a folder"]),
    ],
)
def test_bad_out_is_found_before_any_work(
    small_log, plan_json, tmp_path, monkeypatch, capsys, command, words
):
    """An output that cannot be written is one line naming the option, exit 2, before the work
    (the run, the registration, the simulation, the rendering) starts."""
    import frslam_graph.floorplan.render as render
    import frslam_graph.offline as offline
    import frslam_graph.registration as registration
    from frslam_graph.resources import bundled

    sim = importlib.import_module("frslam_graph.datasets.simulator.simulate")  # not the function
    calls: list[str] = []
    monkeypatch.setattr(offline, "run_recording", _no_call(calls, "run"))
    monkeypatch.setattr(registration, "register", _no_call(calls, "register"))
    monkeypatch.setattr(sim, "simulate_run", _no_call(calls, "simulate"))
    monkeypatch.setattr(render, "render_plan", _no_call(calls, "render"))
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    (tmp_path / "x.png").mkdir()
    fill = dict(
        log=str(small_log[0]),
        file=str(a_file),
        dir=str(tmp_path),
        map=str(bundled("prbonn/GMap.yaml")),
        plan=str(plan_json),
    )
    assert main([c.format(**fill) for c in command]) == 2
    line = one_line(capsys.readouterr().err)
    assert all(w in line for w in words), line
    assert calls == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "x.png"]


@pytest.mark.parametrize("where", ["write", "fsync"])
def test_full_disk_is_one_line_naming_the_file_and_leaves_no_partial_file(
    small_log, tmp_path, quick_run, monkeypatch, capsys, where
):
    """ENOSPC half-way through writing trajectory.tum (or when flushing it to disk): one line
    naming the file, exit 2, the previous run's outputs as they were, no temporary file."""
    log, gt = small_log
    out = tmp_path / "run"
    assert main(["run", str(log), "--out", str(out)]) == 0
    before = listing(out)
    capsys.readouterr()
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    if where == "write":
        real_fdopen = os.fdopen

        class FullDisk:
            """A file that writes half of what it is given, then finds the disk full."""

            def __init__(self, fh):
                self.fh = fh

            def write(self, data):
                self.fh.write(data[: len(data) // 2])
                self.fh.flush()
                raise full

            def __getattr__(self, name):
                return getattr(self.fh, name)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                self.fh.close()

        monkeypatch.setattr(os, "fdopen", lambda *a, **k: FullDisk(real_fdopen(*a, **k)))
    else:

        def fsync(fd):
            raise full

        monkeypatch.setattr(os, "fsync", fsync)
    assert main(["run", str(log), "--out", str(out)]) == 2
    line = one_line(capsys.readouterr().err)
    assert str(out / "trajectory.tum") in line and "No space left on device" in line, line
    assert listing(out) == before


def test_rerun_into_the_same_folder_removes_the_previous_runs_files(small_log, tmp_path, quick_run):
    """A run with a plan left registered_plan.json (and an output its manifest lists); a rerun
    without priors removes them; a file of the user's, and a listed path outside, stay."""
    log, _ = small_log
    out = tmp_path / "run"
    out.mkdir()
    outside = tmp_path / "outside.txt"
    outside.write_text("keep\n")
    previous = {"outputs": ["registered_plan.json", "old_plot.png", "../outside.txt", "metrics.json"]}
    (out / "metrics.json").write_text(json.dumps(previous))
    for name in ("registered_plan.json", "old_plot.png", "notes.txt"):
        (out / name).write_text("previous run\n")
    (out / f"{TEMP_PREFIX}abcd-log.jsonl").write_text("left by a killed run\n")
    assert main(["run", str(log), "--no-priors", "--floor-plan", str(R2V), "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert sorted(p.name for p in out.iterdir()) == sorted([*metrics["outputs"], "notes.txt"])
    assert "registered_plan.json" not in metrics["outputs"] and metrics["outputs"][-1] == "metrics.json"
    assert outside.read_text() == "keep\n" and (out / "notes.txt").read_text() == "previous run\n"


def test_ground_truth_of_another_recording_is_named_and_the_outputs_kept(
    small_log, tmp_path, quick_run, capsys
):
    """The mismatch shows once the recording is read: the run's outputs are written, then one
    line naming --ground-truth and the file, exit 2."""
    from frslam_graph.evaluation.trajectory_io import load_tum, save_tum

    log, gt = small_log
    other = tmp_path / "other.tum"
    shifted = load_tum(gt)
    shifted[:, 0] += 500.0
    save_tum(other, shifted)
    out = tmp_path / "run"
    assert main(["run", str(log), "--ground-truth", str(other), "--out", str(out)]) == 2
    line = one_line(capsys.readouterr().err)
    assert line.startswith(f"error: --ground-truth {other}: does not match the recording"), line
    assert str(out) in line
    metrics = json.loads((out / "metrics.json").read_text())
    assert "ground_truth" in metrics["evaluation_errors"] and (out / "trajectory.png").is_file()


def test_run_refuses_a_simulation_without_its_completeness_marker(plan_json, tmp_path, quick_run, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(plan_json), "--out", str(out), *SIM_ARGS]) == 0
    assert json.loads((out / "meta.json").read_text())["outputs"][-1] == "meta.json"
    (out / "meta.json").unlink()  # as a simulate killed while moving its files into place leaves it
    capsys.readouterr()
    assert main(["run", str(out), "--out", str(tmp_path / "run")]) == 2
    line = one_line(capsys.readouterr().err)
    assert "without meta.json" in line and str(out) in line
    assert quick_run == []


def test_trajectory_file_is_whole_after_the_writer_fails_at_any_line(tmp_path, monkeypatch):
    """save_tum is atomic: a failure while numpy writes the rows leaves no file at all."""
    import frslam_graph.evaluation.trajectory_io as trajectory_io

    def savetxt(fh, rows, fmt):
        fh.write("1000.0 0 0 0 0 0 0 1\n")
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(np, "savetxt", savetxt)
    with pytest.raises(OSError):
        trajectory_io.save_tum(tmp_path / "t.tum", np.zeros((3, 4)))
    assert list(tmp_path.iterdir()) == []
