"""``frslam plan show PLAN --out plan.png`` and ``frslam plan convert IN OUT.json``.

PLAN is our JSON, a HouseExpo JSON, an R2V ``.txt``, a room-segmentation ``.png`` (its map
YAML given with ``--yaml`` or found beside it: ``X.yaml`` for ``XRoomSeg.png``) or, without a
YAML, a drawn plan image (``.png``, ``.jpg``, ``.pgm``; pixels; ``--segmentation``,
``--door-width``).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import typer

from frslam_graph.cli.app import console, plan_app

_YAML_HELP = "map_server YAML of a room-segmentation PNG (default: beside it, X.yaml for XRoomSeg.png)."
_SEG_HELP = "Plan image: rooms from this segmentation image (one colour a room), or 'auto': <stem>_gt_segmentation.png."
_DOOR_HELP = "Plan image: widest door gap in pixels (default: the width that splits the most rooms)."


def _load(path: Path, yaml: Path | None, segmentation: str | None = None, door_width: float | None = None):
    """(plan, note): the plan and a line about how it was built (R2V: labels found, strategy;
    plan image: door width, furniture removed)."""
    from frslam_graph.cli.option_errors import named_options
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.floorplan.io import IMAGE_SUFFIXES
    from frslam_graph.floorplan.plan_image import load_image_plan_detailed
    from frslam_graph.floorplan.r2v import load_r2v_detailed
    from frslam_graph.floorplan.roomseg import load_room_segmentation, yaml_beside

    suffix = path.suffix.lower()
    if suffix == ".txt" and path.is_file():
        res = load_r2v_detailed(path)
        missing = [f"{lab.type} (line {lab.line})" for lab in res.labels if lab.room is None]
        note = f"R2V: {res.n_found}/{res.n_labels} labelled rooms found, wall repair: {res.strategy}"
        if missing:
            note += "; not found: " + ", ".join(missing)
        return res.plan, note
    is_seg = suffix in (".png", ".pgm") and (yaml is not None or yaml_beside(path)[0] is not None)
    if is_seg and path.is_file():
        return load_room_segmentation(path, yaml), None
    if suffix in IMAGE_SUFFIXES:
        with named_options({"door_width": ("--door-width", door_width)} if door_width is not None else {}):
            res = load_image_plan_detailed(path, segmentation=segmentation, door_width=door_width)
        note = (
            f"plan image: door width {res.door_width:.0f} px (walls {res.wall_thickness:.0f} px), "
            f"{res.furniture_removed} furniture blobs removed, rooms from "
            + (f"the segmentation {res.segmentation}" if res.segmentation else "the free space")
        )
        return res.plan, note
    return FloorPlan.load(path), None


def _summary(plan, path: Path) -> str:
    types = Counter(r.type for r in plan.rooms)
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(types.items()))
    linked = sum(len(d.rooms) == 2 for d in plan.doors)
    x0, y0, x1, y1 = plan.bounds
    walls = 0 if plan.walls is None else len(plan.walls)
    return (
        f"{path}: {len(plan.rooms)} rooms ({kinds}); {len(plan.doors)} doors ({linked} between two rooms); "
        f"{walls} walls; units {plan.units}; bounds x {x0:.4g}..{x1:.4g}, y {y0:.4g}..{y1:.4g}"
    )


@plan_app.command("show")
def show(
    plan_path: Path = typer.Argument(
        ..., metavar="PLAN", help="Floor plan: .json, R2V .txt, room-seg .png or a plan image."
    ),
    out: Path = typer.Option(Path("plan.png"), "--out", "-o", help="PNG to write."),
    yaml: Path | None = typer.Option(None, "--yaml", help=_YAML_HELP),
    labels: bool = typer.Option(True, "--labels/--no-labels", help="Write room ids and types."),
    segmentation: str | None = typer.Option(None, "--segmentation", help=_SEG_HELP),
    door_width: float | None = typer.Option(None, "--door-width", help=_DOOR_HELP),
) -> None:
    """Render a floor plan (rooms coloured by type, doors, walls, labels) and print its summary."""
    from frslam_graph.atomic import FIGURE_SUFFIXES, Outputs
    from frslam_graph.floorplan.render import render_plan

    outputs = Outputs()
    outputs.file(out, FIGURE_SUFFIXES)
    plan, note = _load(plan_path, yaml, segmentation, door_width)
    outputs.write(out, lambda p: render_plan(plan, p, title=plan_path.name, labels=labels))
    console.print(_summary(plan, plan_path), highlight=False, soft_wrap=True)
    if note:
        console.print(note, highlight=False, soft_wrap=True)
    console.print(f"wrote {out}", highlight=False, soft_wrap=True)


@plan_app.command("convert")
def convert(
    src: Path = typer.Argument(
        ..., metavar="IN", help="Floor plan: .json, R2V .txt, room-seg .png or a plan image."
    ),
    dst: Path = typer.Argument(..., metavar="OUT.json", help="Our JSON floor-plan file to write."),
    yaml: Path | None = typer.Option(None, "--yaml", help=_YAML_HELP),
    segmentation: str | None = typer.Option(None, "--segmentation", help=_SEG_HELP),
    door_width: float | None = typer.Option(None, "--door-width", help=_DOOR_HELP),
) -> None:
    """Convert a floor plan to our JSON format (frslam-floorplan v1)."""
    from frslam_graph.atomic import Outputs

    outputs = Outputs()
    outputs.file(dst, (".json",), option="OUT.json")
    plan, note = _load(src, yaml, segmentation, door_width)
    outputs.write(dst, plan.save)
    console.print(_summary(plan, src), highlight=False, soft_wrap=True)
    if note:
        console.print(note, highlight=False, soft_wrap=True)
    console.print(f"wrote {dst}", highlight=False, soft_wrap=True)
