"""The end of a command's output: every file it wrote (as the output manifests list them), and
whether the floor plan was accepted and when."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rich.markup import escape
from rich.table import Table

from frslam_graph.cli.app import console


def _size(path: Path) -> str:
    if path.is_dir():
        n = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    elif path.exists():
        n = path.stat().st_size
    else:
        return "–"
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return ""


def print_written(paths: Iterable[Path], base: Path, plan: str | None = None) -> None:
    """A table of the files written in ``base`` (the command's ``--out``; paths relative to it)
    with their sizes, a line for each written elsewhere (``--viz FILE``), then ``plan`` (the
    floor plan's fate: :func:`plan_status`) if given."""
    table = Table(title=escape(f"written to {base}"), title_justify="left")
    table.add_column("file", overflow="fold")
    table.add_column("size", justify="right", no_wrap=True)
    elsewhere = []
    for path in paths:
        if not path.is_relative_to(base):
            elsewhere.append(path)
            continue
        table.add_row(escape(str(path.relative_to(base)) + ("/" if path.is_dir() else "")), _size(path))
    console.print(table)
    for path in elsewhere:
        console.print(f"also written: {escape(str(path))} ({_size(path)})", highlight=False, soft_wrap=True)
    if plan:
        console.print(plan, highlight=False, soft_wrap=True)


def plan_status(metrics: dict[str, Any], label: str = "") -> str | None:
    """One line saying whether a run's floor plan was accepted and when (from its ``metrics``:
    ``plan_accepted`` and the ``register`` decisions); None for a run without a plan."""
    if not metrics.get("floor_plan"):
        return None
    who = f"floor plan{f' ({label})' if label else ''}"
    tried = metrics.get("decisions", {}).get("register", 0)
    acc = metrics.get("plan_accepted")
    if acc is None:
        return (
            f"{who}: [bold yellow]never accepted[/] ({tried} registration{'s' * (tried != 1)} tried; "
            "the reasons are in log.jsonl)"
        )
    where = ""
    if acc.get("distance_m") is not None and acc.get("plan_seen") is not None:
        where = f", {acc['distance_m']:.0f} m driven, {acc['plan_seen']:.0%} of the plan's rooms seen"
    end = " on the complete map at the end of the run" if acc.get("at_end") else ""
    return (
        f"{who}: [bold green]accepted[/]{end} at scan {acc['scan']:,} of {metrics.get('scans', 0):,}, "
        f"{acc['time_s']:.1f} s into the recording{where} "
        f"(registration {acc['registrations_tried']} of {tried} tried)"
    )
