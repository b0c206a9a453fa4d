"""Progress of the long steps (a SLAM run over a recording): a bar with rate and ETA when stdout
is a terminal, plain lines at every tenth of the work when it is not (a log file, a pipe, CI).

    with ScanProgress() as progress:
        tick = progress.task("with priors", total=len(recording))
        run_recording(recording, progress=tick)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from frslam_graph.cli.app import console as default_console

#: a plain progress line at every this share of the work
PLAIN_STEP = 0.1
#: the bar is redrawn every this many scans (and at the last)
BAR_EVERY = 25


def _eta(seconds: float) -> str:
    if seconds < 1:
        return "under 1 s"
    seconds = round(seconds)
    return f"about {seconds // 60}:{seconds % 60:02d}" if seconds >= 60 else f"about {seconds} s"


class ScanProgress:
    """Tasks counting scans: ``task(label, total)`` returns the callback ``tick(i)`` (i scans done).

    On a terminal a rich bar per task (scans done, scans/s, time remaining); otherwise one line per
    :data:`PLAIN_STEP` of each task: ``label: 30 % (90/300 scans, 45 scans/s, about 5 s left)``.
    """

    def __init__(self, console: Console | None = None, clock: Callable[[], float] = time.perf_counter):
        """``clock`` (seconds) measures the scans per second and the time left; injectable for tests."""
        self.console = console or default_console
        self.clock = clock
        self.terminal = self.console.is_terminal
        self._bar: Progress | None = None

    def __enter__(self) -> ScanProgress:
        if self.terminal:
            self._bar = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=self.console,
                transient=False,
            )
            self._bar.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)
            self._bar = None

    def task(self, label: str, total: int) -> Callable[[int], None]:
        """The callback ``tick(i)`` reporting ``i`` of ``total`` scans done."""
        t0 = self.clock()
        total = max(int(total), 0)

        def rate(i: int) -> float:
            dt = self.clock() - t0
            return i / dt if dt > 0 else 0.0

        if self._bar is not None:
            bar, task = self._bar, self._bar.add_task(label, total=total, rate="")

            def tick_bar(i: int) -> None:
                if i % BAR_EVERY == 0 or i >= total:
                    r = rate(i)
                    bar.update(task, completed=i, rate=f"{r:.0f} scans/s" if r > 0 else "")

            return tick_bar

        next_share = [PLAIN_STEP]

        def tick_plain(i: int) -> None:
            if total <= 0 or i / total + 1e-9 < next_share[0]:
                return
            share = i / total
            while next_share[0] <= share + 1e-9:
                next_share[0] += PLAIN_STEP
            r = rate(i)
            left = f", {_eta((total - i) / r)} left" if r > 0 and i < total else ""
            self.console.print(
                f"{label}: {100 * share:.0f} % ({i:,}/{total:,} scans, {r:.0f} scans/s{left})",
                highlight=False,
                soft_wrap=True,
            )

        return tick_plain


def status(text: str, console: Console | None = None) -> AbstractContextManager:
    """A step without a count: a spinner with ``text`` on a terminal, one line ``text ...`` when not."""
    console = console or default_console
    if console.is_terminal:
        return console.status(text)
    console.print(f"{text} ...", highlight=False, soft_wrap=True)
    return nullcontext()
