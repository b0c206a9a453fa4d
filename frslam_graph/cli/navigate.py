"""``frslam navigate PLAN.json --from X Y --to ROOM --out path.png``: a path on a registered plan.

The plan must be in metres (a registered plan, e.g. ``registered_plan.json`` written by
``frslam run``); ``--to`` is a room id or ``X,Y`` in metres.
"""

from __future__ import annotations

from pathlib import Path

import typer

from frslam_graph.cli.app import app, console
from frslam_graph.errors import FrslamError


def _goal(text: str):
    parts = text.replace(";", ",").split(",")
    if len(parts) == 2:
        try:
            return (float(parts[0]), float(parts[1]))
        except ValueError:
            pass
    return text


@app.command("navigate")
def navigate(
    plan_path: Path = typer.Argument(..., help="Registered floor plan in metres (our JSON)."),
    start: tuple[float, float] = typer.Option(..., "--from", help="Start x y in metres (map frame)."),
    to: str = typer.Option(..., "--to", help="Goal: a room id, or X,Y in metres."),
    out: Path = typer.Option(Path("path.png"), "--out", "-o", help="PNG to write."),
    clearance: float = typer.Option(0.25, help="Minimum distance from walls (m)."),
    resolution: float = typer.Option(0.05, help="Planning grid resolution (m)."),
) -> None:
    """Plan a path through the plan's doors to a room (or point); print length and rooms."""
    from matplotlib.figure import Figure

    from frslam_graph.atomic import FIGURE_SUFFIXES, Outputs, save_figure
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.floorplan.render import draw_plan
    from frslam_graph.navigation import plan_path as plan_route
    from frslam_graph.navigation import room_graph

    outputs = Outputs()
    outputs.file(out, FIGURE_SUFFIXES)
    plan = FloorPlan.load(plan_path)
    if plan.units != "m":
        raise FrslamError(
            f"the plan is in {plan.units!r}, not metres: navigate needs a registered plan "
            "(frslam register PLAN MAP.yaml --out DIR writes DIR/registered_plan.json; "
            "frslam run --floor-plan writes one too)",
            source=plan_path,
        )
    goal = _goal(to)
    try:
        path = plan_route(plan, start, goal, grid_resolution=resolution, clearance=clearance)
    except FrslamError as exc:  # the library names its arguments: say the options instead
        option = {
            "start": f"--from {start[0]:g} {start[1]:g}",
            "goal": f"--to {to[:80]}",
            "clearance": f"--clearance {clearance:g}",
            "grid_resolution": f"--resolution {resolution:g}",
            "bounds": f"--resolution {resolution:g}",  # the plan's raster at that resolution is too large
        }.get(exc.where or "")
        if option is None:
            raise
        raise type(exc)(exc.message, source=exc.source, where=option) from None
    fig = Figure(figsize=(9, 8))
    ax = fig.add_subplot(1, 1, 1)
    draw_plan(ax, plan, alpha=0.35)
    ax.plot([start[0]], [start[1]], "go", ms=8, label="start")
    if path.ok:
        ax.plot(path.points[:, 0], path.points[:, 1], "r-", lw=2, label=f"path {path.length:.2f} m")
        ax.plot([path.points[-1, 0]], [path.points[-1, 1]], "r*", ms=12, label="goal")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{plan_path.name}: to {to}")
    fig.tight_layout()
    outputs.write(out, lambda p: save_figure(fig, p, dpi=110))
    if not path.ok:
        links = room_graph(plan)
        doors = ", ".join(f"{a}-{b}" for a in sorted(links) for b in sorted(links[a]) if a < b) or "none"
        culprit = path.info.get("culprit", "goal")
        option = f"--from {start[0]:g} {start[1]:g}" if culprit == "start" else f"--to {to[:80]}"
        raise FrslamError(
            f"no path: {path.reason} (doors: {doors}); wrote {out}", source=plan_path, where=option
        )
    console.print(
        f"path of {path.length:.2f} m through {' -> '.join(path.rooms) or 'no room'} "
        f"({len(path.points)} points); wrote {out}"
    )
