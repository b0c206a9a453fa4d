"""Progress of a run: a bar with ETA on a terminal, a plain line at every tenth when not."""

from __future__ import annotations

import io

from rich.console import Console

from frslam_graph.cli import main
from frslam_graph.cli.progress import ScanProgress, status


class FakeClock:
    """A clock that moves only when told: 0.125 s per scan here (8 scans/s whatever the load)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_plain_progress_is_a_line_at_every_tenth():
    out = io.StringIO()
    clock = FakeClock()
    with ScanProgress(Console(file=out, force_terminal=False, width=200), clock=clock) as progress:
        tick = progress.task("with priors", 50)
        for i in range(1, 51):
            clock.now += 0.125
            tick(i)
    lines = out.getvalue().splitlines()
    assert [line.split(" %")[0] for line in lines] == [f"with priors: {p}" for p in range(10, 101, 10)]
    assert lines[0] == "with priors: 10 % (5/50 scans, 8 scans/s, about 6 s left)"
    assert lines[-1] == "with priors: 100 % (50/50 scans, 8 scans/s)"


def test_plain_progress_of_few_scans_prints_once_per_scan():
    out = io.StringIO()
    clock = FakeClock()
    with ScanProgress(Console(file=out, force_terminal=False, width=200), clock=clock) as progress:
        tick = progress.task("run", 4)
        for i in range(1, 5):
            clock.now += 0.5
            tick(i)
    assert [line.split(" (")[0] for line in out.getvalue().splitlines()] == [
        "run: 25 %",
        "run: 50 %",
        "run: 75 %",
        "run: 100 %",
    ]


def test_a_terminal_gets_a_bar_with_eta():
    out = io.StringIO()
    with ScanProgress(Console(file=out, force_terminal=True, width=120)) as progress:
        assert progress.terminal
        tick = progress.task("no priors", 30)
        for i in range(1, 31):
            tick(i)
    text = out.getvalue()
    assert "no priors" in text and "30/30" in text and "ETA" in text and "━" in text
    assert "% (" not in text  # no plain lines


def test_run_piped_prints_plain_progress_lines(test_data, tmp_path, capsys):
    assert main(["run", str(test_data / "intel_head.clf.bz2"), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    lines = [x for x in out.splitlines() if x.startswith("no priors: ")]
    assert len(lines) == 10 and lines[-1].startswith("no priors: 100 % (64/64 scans")


def test_a_step_without_a_count_is_one_line_when_not_a_terminal():
    out = io.StringIO()
    with status("simulating the run", Console(file=out, force_terminal=False)):
        pass
    assert out.getvalue() == "simulating the run ...\n"
