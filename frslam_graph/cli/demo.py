"""``frslam demo``: the main job, end to end, on the real data bundled with the package.

1. Floor plans: a real internet apartment plan (R2V) and the room segmentation of a real office
   floor (PRBonn) are loaded and rendered.
2. Registration on real data: the PRBonn plan, distorted at random (scale, aspect, rotation,
   flip), is registered (MFR) to the real gmapping map of that floor; the error against the known
   truth is printed and the overlay written.
3. SLAM: a robot run through a true house made from the apartment plan (unknown scale, aspect,
   rotation and flip) is simulated with 2 % odometry drift; the backend runs with and without
   floor-plan priors; ATE / RPE are printed side by side and the plots written.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import typer

from frslam_graph.cli.app import app, console
from frslam_graph.cli.progress import ScanProgress, status
from frslam_graph.cli.summary import plan_status, print_written
from frslam_graph.resources import bundled

if TYPE_CHECKING:
    from frslam_graph.atomic import OutputFolder, Outputs

DEMO_PLAN = "r2v/000209a30b61b563f93faf6a6466ffab_0001.txt"
#: the SLAM runs' output folders inside the demo's folder
SLAM_RUNS = ("without_priors", "with_priors")


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", "-o", help="Folder for the demo's outputs."),
    seed: int = typer.Option(3, help="Seed of the simulated house and run."),
    length: float = typer.Option(200.0, help="Minimum length of the simulated route, metres."),
    viz: Path | None = typer.Option(
        None,
        "--viz",
        help="Also write a rerun recording of the SLAM runs (FILE.rrd; view it with 'rerun FILE.rrd'). "
        "Needs rerun-sdk: pip install 'frslam\\[viz]'.",
    ),
) -> None:
    """Run the main job on bundled real data: plans, registration on a real map, SLAM with/without priors."""
    from frslam_graph.atomic import Outputs, check_folder
    from frslam_graph.cli.option_errors import option_text
    from frslam_graph.cli.run import _check_viz
    from frslam_graph.errors import FrslamError
    from frslam_graph.offline import RUN_OUTPUTS

    if not 0.0 <= length < math.inf:  # checked before the demo's first minute of work
        raise FrslamError(
            "expected a finite length in metres, 0 or more", source=option_text("--length", length)
        )
    check_folder(out)
    with Outputs() as outputs:
        runs = {name: outputs.folder(out / name, "metrics.json", RUN_OUTPUTS) for name in SLAM_RUNS}
        _check_viz(outputs, viz)
        with_priors = _plans_demo(outputs, out, seed, length, runs, viz)
    print_written(outputs.files(), out, plan_status(with_priors, "with priors") if with_priors else None)


def _plans_demo(
    outputs: Outputs,
    out: Path,
    seed: int,
    length: float,
    runs: dict[str, OutputFolder],
    viz: Path | None = None,
) -> dict[str, Any]:
    """The demo's three parts, writing through ``outputs`` (``runs``: the SLAM runs' folders);
    the metrics of the SLAM run with priors."""
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.floorplan.render import render_plan
    from frslam_graph.occupancy import OccupancyGrid

    console.rule("[bold]1. floor plans")
    apartment = FloorPlan.load(bundled(DEMO_PLAN))
    outputs.write(out / "apartment_plan.png", lambda p: render_plan(apartment, p))
    types = ", ".join(sorted({r.type for r in apartment.rooms}))
    console.print(f"apartment (R2V): {len(apartment.rooms)} rooms ({types}), {len(apartment.doors)} doors")
    office = FloorPlan.from_room_segmentation(bundled("prbonn/FMapRoomSeg.png"), bundled("prbonn/FMap.yaml"))
    outputs.write(out / "office_plan.png", lambda p: render_plan(office, p))
    gmap = OccupancyGrid.load(bundled("prbonn/GMap.yaml"))
    console.print(
        f"office (PRBonn): {len(office.rooms)} rooms; gmapping map {gmap.height}×{gmap.width} cells"
    )

    console.rule("[bold]2. registration of a distorted plan to a real LiDAR map")
    _registration_demo(outputs, office, gmap, out, seed)

    console.rule("[bold]3. SLAM with and without floor-plan priors (simulated run in the apartment)")
    return _slam_demo(outputs, apartment, out, seed, length, runs, viz)


def _registration_demo(outputs: Outputs, office, gmap, out: Path, seed: int) -> None:
    from frslam_graph.datasets.simulator import Distortion
    from frslam_graph.floorplan.render import render_plan
    from frslam_graph.registration import register
    from frslam_graph.registration.evaluation import iou_a

    rng = np.random.default_rng(seed)
    d = Distortion.random(rng, rotation="any", metres_per_unit=1.0)
    distorted = office.transformed(d.matrix, units="unit")  # as if drawn by hand: wrong scale/aspect/angle
    truth = np.linalg.inv(d.matrix)  # distorted plan -> map
    reg = register(distorted, gmap)
    if not reg.ok:
        console.print(f"[yellow]registration failed: {reg.reason}[/]")
        return
    err_deg = abs((reg.rotation_deg - np.degrees(np.arctan2(truth[1, 0], truth[0, 0])) + 180) % 360 - 180)
    score = iou_a(distorted, reg.matrix, truth)
    outputs.write(
        out / "office_registered.png",
        lambda p: render_plan(
            distorted,
            p,
            transform=reg.matrix,
            grid=gmap,
            title=f"MFR on the real PRBonn map: IoU_a {score:.1%}",
        ),
    )
    console.print(
        f"distortion: flip={d.flip} rotation={np.degrees(d.rotation):.1f}° aspect=({d.sx:.2f}, {d.sy:.2f}); "
        f"registered in {reg.time_s * 1e3:.0f} ms: flip {'ok' if reg.flipped == d.flip else 'WRONG'}, "
        f"rotation error {err_deg:.2f}°, IoU_a {score:.1%} (score {reg.score:.2f}, ambiguity {reg.ambiguity:.2f})"
    )


def _slam_demo(
    outputs: Outputs,
    apartment,
    out: Path,
    seed: int,
    length: float,
    folders: dict[str, OutputFolder],
    viz: Path | None = None,
) -> dict[str, Any]:
    from frslam_graph.cli.run import _print_metrics, _write_viz
    from frslam_graph.datasets.simulator import SimulationOptions, simulate_run
    from frslam_graph.offline import run_recording, write_outputs
    from frslam_graph.viz import save_compare_png

    options = SimulationOptions(length=length, beams=720, fov_deg=270.0, max_range=30.0, rotation="any")
    with status("simulating the run"):
        sim = simulate_run(apartment, seed=seed, options=options)
    route_len = float(np.sum(np.hypot(*np.diff(sim.true_poses[:, :2], axis=0).T)))
    console.print(
        f"simulated {len(sim)} scans over {route_len:.0f} m ({sim.stamps[-1] - sim.stamps[0]:.0f} s)"
    )
    runs = {}
    with ScanProgress() as progress:
        for name, plan in (("without priors", None), ("with priors", apartment)):
            runs[name] = run_recording(
                sim.scans, floor_plan=plan, progress=progress.task(f"SLAM {name}", len(sim))
            )
            write_outputs(runs[name], folders[name.replace(" ", "_")], sim.ground_truth)
    with_ = runs["with priors"]
    plan_in_map = with_.slam.registered_plan()
    trajectories = {name: r.result.trajectory for name, r in runs.items()}
    grid = with_.slam.occupancy_grid(0.05)
    outputs.write(
        out / "slam_compare.png",
        lambda p: save_compare_png(
            p,
            trajectories,
            sim.ground_truth,
            grid=grid,
            plan=plan_in_map,
            title="apartment: with and without floor-plan priors",
        ),
    )
    _write_viz(outputs, viz, runs)
    _print_metrics({name: r.metrics for name, r in runs.items()})
    return with_.metrics
