"""``frslam register PLAN MAP.yaml --out DIR``: register a floor plan to an occupancy map.

MAP is a map_server YAML, or a map image without one (``MAP.png --resolution R``, R metres per
pixel, read as map_server reads it: top row highest y, dark occupied, light free).

Writes into DIR: ``registered_plan.json`` (the plan in map metres, our JSON format),
``overlay.png`` (the map in grey, the registered rooms coloured; matched rooms outlined) and
``report.json`` (the registration: matrix plan -> map, flip, rotation, scales, score, ambiguity,
covariance, matched rooms, timing). A failed match still writes the report (``ok: false`` and the
reason) and the overlay, with the refused placement's rooms dashed when there was one (MFR's "no
match": a plan drawn differently from the building can be right and still refused), and exits
with code 1. A doubtful match (the registration's ``verdict`` is ``"doubtful"``: the paper mode's
low score or near-tie of two flips/rotations) is handled the same way: one line says why, the
overlay dashes its placement, ``registered_plan.json`` is not written, exit code 1. Bad input
files exit with code 2 and a one-line message. The
report is written last and lists the outputs; they replace a previous registration's as a whole.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.markup import escape

from frslam_graph.cli.app import app, console
from frslam_graph.cli.summary import print_written

#: what register writes (a previous registration's files of these names are replaced)
OUTPUTS = ("registered_plan.json", "overlay.png", "report.json")


def refused_placement(reg) -> bool:
    """A failed registration that still places the plan (MFR's "no match": the best placement,
    refused by its checks), as opposed to one that never got a placement (too few rooms, no
    subset fits, a degenerate fit): its matrix is drawn in the overlay for a user to judge."""
    return not reg.ok and reg.placed


def _frame(grid, plan_m) -> tuple[float, float, float, float] | None:
    """(xmin, xmax, ymin, ymax) of what the overlay shows: the map's known cells and the placed
    plan's rooms (a metre around each), not the map image's unknown border."""
    from frslam_graph.floorplan.render import known_bounds

    boxes = [b for b in [known_bounds(grid)] if b is not None]
    if plan_m is not None and plan_m.rooms:
        x0, y0, x1, y1 = np.array([r.polygon.bounds for r in plan_m.rooms]).T
        boxes.append((x0.min() - 1.0, x1.max() + 1.0, y0.min() - 1.0, y1.max() + 1.0))
    if not boxes:
        return None
    box = np.array(boxes)
    return float(box[:, 0].min()), float(box[:, 1].max()), float(box[:, 2].min()), float(box[:, 3].max())


def _overlay(grid, plan_m, reg, out: Path, title: str) -> None:
    """Map (free white, occupied black, unknown grey) with the registered rooms on top (a refused
    or doubtful placement: dashed outlines, no fill)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon as MplPolygon

    from frslam_graph.atomic import save_figure

    img = np.full(grid.shape, 0.6)
    img[grid.free_mask()] = 1.0
    img[grid.occupied_mask()] = 0.0
    x0, y0, yaw = grid.origin
    h, w = grid.shape
    res = grid.resolution
    frame = _frame(grid, plan_m)
    ratio = h / max(w, 1) if frame is None else (frame[3] - frame[2]) / (frame[1] - frame[0])
    fig, ax = plt.subplots(figsize=(9, min(max(9 * ratio, 3.0), 18.0)), dpi=100)
    if yaw == 0.0:
        ax.imshow(
            img, origin="lower", cmap="gray", vmin=0, vmax=1, extent=(x0, x0 + w * res, y0, y0 + h * res)
        )
    else:  # rotated grid: draw cell centres
        rr, cc = np.mgrid[0:h, 0:w]
        xy = grid.cell_to_world(np.column_stack([cc.ravel() + 0.5, rr.ravel() + 0.5]))
        ax.scatter(xy[:, 0], xy[:, 1], c=img.ravel(), cmap="gray", vmin=0, vmax=1, s=1, marker="s")
    cmap = plt.get_cmap("tab20")
    accepted = reg.verdict == "registered"
    matched = set(reg.rooms)
    for i, room in enumerate(plan_m.rooms if plan_m is not None else []):
        xy = np.asarray(room.polygon.exterior.coords)
        colour = cmap(i % 20)
        if not accepted:
            ax.add_patch(MplPolygon(xy, closed=True, fill=False, edgecolor=colour, lw=1.4, ls="--"))
        else:
            ax.add_patch(MplPolygon(xy, closed=True, facecolor=(*colour[:3], 0.3), edgecolor=colour, lw=1.0))
        if accepted and room.id in matched:
            ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, lw=2.2)
        cx, cy = room.polygon.representative_point().coords[0]
        ax.text(cx, cy, f"{room.id}\n{room.type}", fontsize=6, ha="center", va="center")
    for d in plan_m.doors if plan_m is not None else []:
        ax.plot([d.a[0], d.b[0]], [d.a[1], d.b[1]], "-", color="tab:green", lw=2)
    ax.set_aspect("equal")
    if frame is not None:
        ax.set_xlim(frame[0], frame[1])
        ax.set_ylim(frame[2], frame[3])
    else:
        ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, out)
    plt.close(fig)


def _check_seed_rooms(plan, plan_path: Path, seed_rooms: list[str]) -> None:
    """FloorPlanError naming ``--seed-room`` and the plan's rooms for an id the plan lacks."""
    from frslam_graph.errors import FloorPlanError
    from frslam_graph.limits import short_repr

    ids = [r.id for r in plan.rooms]
    for room in seed_rooms:
        if room not in ids:
            listed = ", ".join(ids[:30]) + (f", ... ({len(ids)} in all)" if len(ids) > 30 else "")
            raise FloorPlanError(
                f"no such room in the plan (its rooms: {listed or 'none'})",
                source=plan_path,
                where=f"--seed-room {short_repr(room)}",
            )


@app.command("register")
def register_cmd(
    plan_path: Path = typer.Argument(
        ..., metavar="PLAN", help="Floor plan: .json, R2V .txt, room-seg .png or a plan image."
    ),
    map_yaml: Path = typer.Argument(
        ..., metavar="MAP.yaml", help="Occupancy map: map_server YAML, or an image with --resolution."
    ),
    resolution: float | None = typer.Option(
        None, "--resolution", help="Metres per pixel of a map image without a YAML (not for a YAML map)."
    ),
    out: Path = typer.Option(Path("register_out"), "--out", "-o", help="Output directory."),
    method: str = typer.Option("mfr", "--method", "-m", help="mfr (ours) or paper (paper-faithful)."),
    plan_yaml: Path | None = typer.Option(
        None, "--plan-yaml", help="map_server YAML of a room-segmentation PNG plan (default: beside it)."
    ),
    seed_room: list[str] = typer.Option(
        [], "--seed-room", help="Room id the robot is in (repeatable): the matched rooms contain one of them."
    ),
) -> None:
    """Register a floor plan (unknown scale, aspect, rotation, flip) to a partial occupancy map."""
    from frslam_graph.atomic import Outputs
    from frslam_graph.cli.option_errors import named_options
    from frslam_graph.cli.plan import _load
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.registration import register

    with Outputs() as outputs:
        folder = outputs.folder(out, "report.json", OUTPUTS)
        plan, _ = _load(plan_path, plan_yaml)
        _check_seed_rooms(plan, plan_path, seed_room)
        with named_options({"resolution": ("--resolution", resolution)} if resolution is not None else {}):
            grid = OccupancyGrid.load(map_yaml, resolution=resolution)
        options = {"seed_rooms": list(seed_room)} if seed_room else {}
        with named_options({"method": ("--method", method)}):
            reg = register(plan, grid, method=method, **options)
        report = {
            "plan": str(plan_path),
            "map": str(map_yaml),
            "n_rooms": len(plan.rooms),
            "registration": reg.to_dict(),
        }
        refused = refused_placement(reg)
        plan_m = reg.apply(plan) if reg.ok or refused else None
        placement = (
            f"score {reg.score:.3f}, ambiguity {reg.ambiguity:.2f}, flip {reg.flipped}, "
            f"rot {reg.rotation_deg:.2f} deg, scale {reg.scale[0]:.4g}/{reg.scale[1]:.4g} m/unit"
        )
        if reg.verdict == "registered":
            status = placement
        elif reg.verdict == "doubtful":
            status = "DOUBTFUL: " + reg.doubt.replace("; ", "\n") + f"\nplacement (dashed): {placement}"
        else:
            status = f"FAILED: {reg.reason}" + (
                f"\nrefused placement (dashed): {placement}" if refused else ""
            )
        title = f"{plan_path.name} -> {map_yaml.name} [{reg.method}] " + status
        with folder:
            if reg.verdict == "registered":
                folder.write("registered_plan.json", plan_m.save)
            folder.write("overlay.png", lambda p: _overlay(grid, plan_m, reg, p, title))
            folder.commit(report)
    if reg.verdict == "registered":
        console.print(
            f"registered {len(reg.rooms)}/{len(plan.rooms)} rooms: flip {reg.flipped}, rotation "
            f"{reg.rotation_deg:.2f} deg, scale {reg.scale[0]:.5g} x {reg.scale[1]:.5g} m/unit, translation "
            f"({reg.translation[0]:.3f}, {reg.translation[1]:.3f}) m, score {reg.score:.3f}, ambiguity "
            f"{reg.ambiguity:.2f}, {reg.time_s * 1e3:.1f} ms",
            highlight=False,
            soft_wrap=True,
        )
        print_written(outputs.files(), out, "floor plan: [bold green]registered[/] to the map")
    elif reg.verdict == "doubtful":
        print_written(outputs.files(), out)
        console.print(
            f"[bold yellow]doubtful match, not accepted:[/] {escape(reg.doubt)} (placement: flip {reg.flipped}, "
            f"rotation {reg.rotation_deg:.2f} deg, scale {reg.scale[0]:.5g} x {reg.scale[1]:.5g} m/unit, translation "
            f"({reg.translation[0]:.3f}, {reg.translation[1]:.3f}) m; dashed in overlay.png)",
            highlight=False,
            soft_wrap=True,
        )
        raise typer.Exit(1)
    else:
        print_written(outputs.files(), out)
        console.print(f"[bold red]no registration:[/] {escape(reg.reason)}", highlight=False, soft_wrap=True)
        raise typer.Exit(1)
