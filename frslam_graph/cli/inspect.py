"""``frslam inspect RECORDING``: read a recording in full and print its counts, beams and throughput."""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from frslam_graph.cli.app import app, console
from frslam_graph.cli.recording_options import (
    Laser,
    Odom,
    OdomTopic,
    PlaneTol,
    ScanTopic,
    open_recording_with,
)


@app.command("inspect")
def inspect(
    recording: Annotated[
        Path, typer.Argument(help="CARMEN log, ROS 1/2 bag, simulator output or PCD/PLY folder.")
    ],
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    laser: Laser = None,
    odom: Odom = None,
    plane_tol: PlaneTol = None,
) -> None:
    """Read RECORDING once and print record counts, duration, beams, invalid beams and scans per second."""
    from frslam_graph.datasets import RecordingWarning

    t0 = time.perf_counter()
    rec = open_recording_with(
        recording, scan_topic=scan_topic, odom_topic=odom_topic, laser=laser, odom=odom, plane_tol=plane_tol
    )
    t_open = time.perf_counter() - t0
    beams: list[int] = []
    with_odom = 0
    caught: list[str] = []
    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    )
    with warnings.catch_warnings(record=True) as got, progress:
        warnings.simplefilter("always", RecordingWarning)
        task = progress.add_task(f"reading {rec.name}", total=len(rec))
        t1 = time.perf_counter()
        for i, scan in enumerate(rec, 1):
            beams.append(scan.ranges.size)
            with_odom += scan.odom is not None
            if i % 200 == 0:
                progress.update(task, completed=i)
        t_read = time.perf_counter() - t1
        progress.update(task, completed=len(beams))
        caught = [str(w.message) for w in got if issubclass(w.category, RecordingWarning)]
    s = rec.stats
    n = len(beams)
    table = Table(title=f"{recording}", show_header=False)
    table.add_row(
        "reader", f"{type(rec).__name__}" + (f" ({rec.reader_used})" if hasattr(rec, "reader_used") else "")
    )
    if hasattr(rec, "scan_topic"):
        frames = getattr(rec, "odom_frames", None)
        odom_from = f"{rec.odom_topic} ({frames[0]} -> {frames[1]})" if frames else f"{rec.odom_topic}"
        table.add_row("topics", escape(f"scan {rec.scan_topic} [{rec.scan_type}], odometry {odom_from}"))
    for frame, mount in getattr(rec, "mounts", {}).items():
        table.add_row(
            "laser mount",
            escape(
                f"{frame} on {rec.base_frame}: x {mount.x:.3f} m, y {mount.y:.3f} m, yaw {math.degrees(mount.yaw):.1f} deg"
                + (", upside down (scan mirrored)" if mount.mirrored else "")
            ),
        )
    table.add_row("records", ", ".join(f"{k} {v:,}" for k, v in sorted(s.records.items())))
    table.add_row("scans", f"{n:,} read of {len(rec):,} found")
    table.add_row("duration", f"{s.duration:.1f} s")
    if n:
        b = np.array(beams)
        table.add_row(
            "beams per scan",
            f"{b.min()}" if b.min() == b.max() else f"{b.min()}–{b.max()} (median {int(np.median(b))})",
        )
        table.add_row(
            "invalid beams",
            f"{s.invalid_beams:,} of {s.beams:,} ({100.0 * s.invalid_beams / max(s.beams, 1):.2f} %)",
        )
    if hasattr(rec, "max_range_source"):
        table.add_row("max range", f"{rec.max_range:g} m ({rec.max_range_source})")
    table.add_row(
        "odometry",
        f"{with_odom:,} scans with a pose; {len(rec.odometry()):,} odometry records (increasing stamps)"
        + (f"; scan poses: {rec.odom_reason}" if hasattr(rec, "odom_reason") else ""),
    )
    gt_path = getattr(rec, "ground_truth_path", None)
    if gt_path is not None:
        table.add_row("ground truth", f"{len(rec.ground_truth()):,} poses in {gt_path.name}")
    rate = n / t_read if t_read > 0 else float("inf")
    realtime = f", {s.duration / t_read:.0f}× real time" if t_read > 0 and s.duration > 0 else ""
    table.add_row(
        "throughput", f"{rate:,.0f} scans/s ({t_read:.2f} s reading + {t_open:.2f} s opening{realtime})"
    )
    for msg in caught:
        table.add_row("[yellow]warning[/]", escape(msg))
    console.print(table)
