"""``frslam simulate PLAN --out DIR --seed N [options]``: a simulated LiDAR recording on a floor plan.

Writes a ROS 2 bag (``/scan``, ``/odom``, ``/ground_truth``), ``ground_truth.tum``, the true house
and distortion (``house.json``), a partial LiDAR map (``map.yaml`` + ``map.pgm``), ``plan.json`` and
``meta.json``; see :mod:`frslam_graph.datasets.simulator.simulate`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import typer

from frslam_graph.cli.app import app, console
from frslam_graph.cli.option_errors import named_options
from frslam_graph.cli.summary import print_written


def _load_plan(path: Path):
    from frslam_graph.floorplan import FloorPlan

    return FloorPlan.load(path)


@app.command("simulate")
def simulate_cmd(
    plan_path: Path = typer.Argument(..., metavar="PLAN", help="Floor plan: our .json or an R2V .txt."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, "--seed", help="Random seed (distortion, house, route, noise)."),
    rooms: str | None = typer.Option(
        None, "--rooms", help="Comma-separated room ids to visit in order (default: every reachable room)."
    ),
    length: float = typer.Option(0.0, "--length", help="Minimum route length in metres (revisits rooms)."),
    closed_doors: int = typer.Option(0, "--closed-doors", help="Number of interior doors closed at random."),
    clutter: int = typer.Option(0, "--clutter", help="Number of furniture boxes."),
    rotation: str = typer.Option("step90", "--rotation", help="Plan->house rotation: step90, any or none."),
    aspect_max: float = typer.Option(0.3, "--aspect-max", help="Largest aspect error (0.3 = ±30 %)."),
    no_flip: bool = typer.Option(False, "--no-flip", help="Never mirror the plan."),
    metres_per_unit: float | None = typer.Option(
        None, "--metres-per-unit", help="Scale (default: a realistic house of 10–25 m diagonal)."
    ),
    beams: int = typer.Option(1081, "--beams", help="LiDAR beams."),
    fov: float = typer.Option(270.0, "--fov", help="LiDAR field of view, degrees."),
    max_range: float = typer.Option(30.0, "--max-range", help="LiDAR range, metres."),
    noise: float = typer.Option(0.01, "--noise", help="Range noise sigma, metres."),
    dropout: float = typer.Option(0.0, "--dropout", help="Probability that a beam returns nothing."),
    scan_rate: float = typer.Option(10.0, "--scan-rate", help="Scans per second."),
    odom_rate: float = typer.Option(50.0, "--odom-rate", help="Odometry messages per second."),
    odom_drift: float = typer.Option(
        0.02, "--odom-drift", help="Odometry distance error: systematic scale and random walk (0.02 = 2 %)."
    ),
    odom_heading_drift: float = typer.Option(
        1.0, "--odom-heading-drift", help="Odometry heading random walk, degrees per sqrt(metre)."
    ),
    speed: float = typer.Option(0.5, "--speed", help="Maximum speed, m/s."),
    completeness: float = typer.Option(
        0.5, "--map-completeness", help="Share of the rooms' area in the partial map (0..1]."
    ),
    see_through_doors: bool = typer.Option(
        False, "--see-through-doors", help="The partial map also holds what is seen through open doors."
    ),
    caster: str = typer.Option("auto", "--caster", help="Ray caster: auto, open3d, sweep or naive."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a previous simulation in --out."),
) -> None:
    """Simulate a LiDAR + odometry recording through a house built from a floor plan."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from frslam_graph.atomic import Outputs
    from frslam_graph.datasets.simulator.simulate import (
        OUTPUT_FILES,
        SimulationOptions,
        check_output_dir,
        simulate,
    )

    outputs = Outputs()
    folder = outputs.folder(out, "meta.json", OUTPUT_FILES)
    plan = _load_plan(plan_path)
    values: dict[str, Any] = dict(
        rooms=[r.strip() for r in rooms.split(",") if r.strip()] if rooms else None,
        length=length,
        closed_doors=closed_doors,
        clutter=clutter,
        rotation=rotation,
        aspect_max=aspect_max,
        flip_prob=0.0 if no_flip else 0.5,
        metres_per_unit=metres_per_unit,
        beams=beams,
        fov_deg=fov,
        max_range=max_range,
        range_noise=noise,
        dropout=dropout,
        scan_rate=scan_rate,
        odom_rate=odom_rate,
        odom_scale_error=odom_drift,
        odom_dist_noise=abs(odom_drift),
        odom_heading_noise_deg=odom_heading_drift,
        max_speed=speed,
        map_completeness=completeness,
        map_see_through_doors=see_through_doors,
        caster=caster,
    )
    flags = {
        "rooms": ("--rooms", rooms),
        "length": ("--length", length),
        "closed_doors": ("--closed-doors", closed_doors),
        "clutter": ("--clutter", clutter),
        "rotation": ("--rotation", rotation),
        "aspect_max": ("--aspect-max", aspect_max),
        "metres_per_unit": ("--metres-per-unit", metres_per_unit),
        "beams": ("--beams", beams),
        "fov_deg": ("--fov", fov),
        "max_range": ("--max-range", max_range),
        "range_noise": ("--noise", noise),
        "dropout": ("--dropout", dropout),
        "scan_rate": ("--scan-rate", scan_rate),
        "odom_rate": ("--odom-rate", odom_rate),
        "odom_scale_error": ("--odom-drift", odom_drift),
        "odom_dist_noise": ("--odom-drift", odom_drift),
        "odom_heading_noise_deg": ("--odom-heading-drift", odom_heading_drift),
        "max_speed": ("--speed", speed),
        "map_completeness": ("--map-completeness", completeness),
        "caster": ("--caster", caster),
        "seed": ("--seed", seed),
    }
    with named_options(flags):
        options = SimulationOptions(**values)
    check_output_dir(out, overwrite, "--overwrite")
    stages = ("house", "route", "lidar", "map", "bag")
    with (
        Progress(
            TextColumn("[bold]{task.description:<6}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        ) as progress,
        outputs,
    ):
        tasks = {s: progress.add_task(s, total=1.0) for s in stages}

        def report(stage: str, frac: float) -> None:
            for s in stages[: stages.index(stage)]:
                progress.update(tasks[s], completed=1.0)
            progress.update(tasks[stage], completed=frac)

        with named_options(flags):
            res = simulate(plan, folder, seed=seed, options=options, overwrite=overwrite, progress=report)
        for s in stages:
            progress.update(tasks[s], completed=1.0)
    d = res.distortion
    console.print(
        f"{plan_path}: {res.scans} scans, {res.odometry} odometry records, route {res.route_length:.1f} m "
        f"in {res.duration:.1f} s; map {res.map_completeness * 100:.1f} % of the rooms' area "
        f"({len(res.map_rooms)} rooms)",
        highlight=False,
        soft_wrap=True,
    )
    console.print(
        f"distortion: {d.metres_per_unit:.5g} m/unit, aspect {d.aspect[0]:.4f}/{d.aspect[1]:.4f}, "
        f"flip {d.flip}, rotation {math.degrees(d.rotation):.2f}°, translation "
        f"({d.translation[0]:.3f}, {d.translation[1]:.3f}) m",
        highlight=False,
        soft_wrap=True,
    )
    print_written(outputs.files(), out)
