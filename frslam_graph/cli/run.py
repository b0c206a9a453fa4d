"""``frslam run`` and ``frslam compare``: process a recording with / without floor-plan priors.

Inputs and the output folder are checked before the run; the outputs replace a previous run's
in the folder as a whole, ``metrics.json`` last (:mod:`frslam_graph.atomic`). A ground truth or
relations file that does not match the recording is reported (exit 2) after the outputs are
written: the mismatch shows only once the recording has been read, and the run is kept.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.table import Table

from frslam_graph.cli.app import app, console
from frslam_graph.cli.progress import ScanProgress
from frslam_graph.cli.recording_options import (
    Laser,
    Odom,
    OdomTopic,
    PlaneTol,
    ScanTopic,
    open_recording_with,
)
from frslam_graph.cli.summary import plan_status, print_written

#: options of both run and compare
Sequential = Annotated[
    bool,
    typer.Option(
        "--sequential",
        help="Run the scan odometry in this process (default: in a second process where possible; "
        "same results, about 1.5x as fast on two cores).",
    ),
]
Viz = Annotated[
    Path | None,
    typer.Option(
        "--viz",
        help="Also write a rerun recording (FILE.rrd: scans, map, trajectory, registered plan; "
        "view it with 'rerun FILE.rrd'). Needs rerun-sdk: pip install 'frslam\\[viz]'.",
    ),
]

if TYPE_CHECKING:
    import numpy as np

    from frslam_graph.atomic import Outputs
    from frslam_graph.offline import RunOutput


def _run_one(rec, plan, config, label: str, progress: ScanProgress, sequential: bool = False):
    """One run over ``rec``; RecordingError naming it when it gave no scan at all (every record
    skipped: nothing to write, rather than empty outputs and exit 0)."""
    import warnings

    from frslam_graph.errors import RecordingError
    from frslam_graph.offline import run_recording

    tick = progress.task(label, len(rec))
    with warnings.catch_warnings(record=True) as caught:  # the reader's, said after the run
        result = run_recording(
            rec, floor_plan=plan, config=config, progress=tick, parallel=False if sequential else None
        )
    if len(result.result.trajectory) == 0:  # the error says what the warnings would have
        stats = result.recording_stats
        why = stats.summary() if stats is not None else ""
        raise RecordingError(f"no usable scan{f' ({why})' if why else ''}", source=getattr(rec, "path", None))
    for w in caught:
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return result


def _inputs(
    recording: Path,
    config: Path | None,
    ground_truth: Path | None,
    relations: Path | None,
    reader_options: dict[str, Any],
):
    """Open and check every input before the run (which may take long): the recording (with the
    reader options given: topics, laser, odometry), the configuration, the ground truth
    (``--ground-truth`` or the recording's own) and the relations. A bad one is reported now, not
    after the run with its outputs lost. Returns (recording, config, ground truth, relations,
    sources: how to name the ground truth / relations)."""
    from frslam_graph.config import FRSlamConfig
    from frslam_graph.evaluation.trajectory_io import load_relations, load_tum

    rec = open_recording_with(recording, **reader_options)
    cfg = FRSlamConfig.load(config) if config is not None else None
    sources = {"relations": f"--relations {relations}"}
    if ground_truth is not None:
        gt = load_tum(ground_truth)
        sources["ground_truth"] = f"--ground-truth {ground_truth}"
    elif getattr(rec, "ground_truth_path", None) is not None:
        gt = rec.ground_truth()
        sources["ground_truth"] = f"ground truth {rec.ground_truth_path}"
    else:
        gt = None
    rel = load_relations(relations) if relations is not None else None
    return rec, cfg, gt, rel, sources


def _check_evaluation(metrics: dict, sources: dict[str, str], out: Path) -> None:
    """TrajectoryError naming the ground truth / relations file that did not match the run."""
    from frslam_graph.errors import TrajectoryError

    for what, message in metrics.get("evaluation_errors", {}).items():
        message = message if len(message) <= 100 else message[:97] + "..."  # evo's own words, capped
        raise TrajectoryError(
            f"does not match the recording ({message}); the run's other outputs are in {out}",
            source=sources[what],
        )


def _trajectory_figure(
    trajectories: dict[str, np.ndarray], gt: np.ndarray | None, result: RunOutput, title: str = ""
) -> Callable[[Path], object]:
    """A writer of the trajectory plot over ``result``'s map and registered plan."""
    from frslam_graph.viz import save_trajectory_png

    grid = result.slam.occupancy_grid(0.05) if len(result.result.keyframes) else None
    plan = result.slam.registered_plan()
    refused = result.slam.refused_plan()
    return lambda path: save_trajectory_png(
        path, trajectories, gt, grid=grid, plan=plan, title=title, refused_plan=refused
    )


def _compare_figure(
    trajectories: dict[str, np.ndarray], gt: np.ndarray | None, result: RunOutput
) -> Callable[[Path], object]:
    """A writer of compare.png: the overview over ``result``'s map and plan, and with a ground
    truth each run coloured by its error and the errors over the distance travelled."""
    from frslam_graph.viz import save_compare_png

    grid = result.slam.occupancy_grid(0.05) if len(result.result.keyframes) else None
    plan = result.slam.registered_plan()
    return lambda path: save_compare_png(path, trajectories, gt, grid=grid, plan=plan)


def _check_viz(outputs: Outputs, viz: Path | None) -> None:
    """Before the run: rerun-sdk is installed and ``--viz`` can be written (a ``.rrd``)."""
    if viz is not None:
        from frslam_graph.rerun_viz import require_rerun

        require_rerun("--viz")
        outputs.file(viz, (".rrd",), option="--viz")


def _write_viz(outputs: Outputs, viz: Path | None, runs: dict[str, RunOutput]) -> None:
    if viz is not None:
        from frslam_graph.rerun_viz import write_rerun

        outputs.write(viz, lambda path: write_rerun(path, runs))


def _load_plan(path: Path | None):
    if path is None:
        return None
    from frslam_graph.floorplan import FloorPlan

    return FloorPlan.load(path)


@app.command()
def run(
    recording: Path = typer.Argument(
        ..., help="CARMEN log, ROS 1/2 bag, PCD/PLY folder or simulator output."
    ),
    floor_plan: Path | None = typer.Option(
        None, "--floor-plan", "-p", help="Floor plan: .json, R2V .txt or a plan image."
    ),
    no_priors: bool = typer.Option(
        False, "--no-priors", help="Ignore the floor plan: odometry + graph only."
    ),
    config: Path | None = typer.Option(None, "--config", "-c", help="FRSlamConfig YAML/JSON."),
    ground_truth: Path | None = typer.Option(None, "--ground-truth", help="TUM ground truth for ATE/RPE."),
    relations: Path | None = typer.Option(None, "--relations", help="Relations file (Kümmerle et al.)."),
    out: Path = typer.Option(Path("out/run"), "--out", "-o", help="Output folder."),
    sequential: Sequential = False,
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    laser: Laser = None,
    odom: Odom = None,
    plane_tol: PlaneTol = None,
    viz: Viz = None,
) -> None:
    """Run the SLAM backend over a recording; write trajectory, map, registered plan, metrics, plots."""
    from frslam_graph.atomic import Outputs
    from frslam_graph.offline import RUN_OUTPUTS, write_outputs

    with Outputs() as outputs:
        folder = outputs.folder(out, "metrics.json", RUN_OUTPUTS)
        _check_viz(outputs, viz)
        plan = None if no_priors else _load_plan(floor_plan)
        reader_options = dict(
            scan_topic=scan_topic, odom_topic=odom_topic, laser=laser, odom=odom, plane_tol=plane_tol
        )
        rec, cfg, gt, rel, sources = _inputs(recording, config, ground_truth, relations, reader_options)
        with ScanProgress() as progress:
            label = "with priors" if plan is not None else "no priors"
            result = _run_one(rec, plan, cfg, label, progress, sequential)
        figure = _trajectory_figure({"estimate": result.result.trajectory}, gt, result)
        write_outputs(result, folder, gt, rel, figures={"trajectory.png": figure})
        _write_viz(outputs, viz, {"run": result})
    _print_metrics({"run": result.metrics})
    print_written(outputs.files(), out, plan_status(result.metrics))
    _check_evaluation(result.metrics, sources, out)


@app.command()
def compare(
    recording: Path = typer.Argument(..., help="Recording to process twice."),
    floor_plan: Path = typer.Option(
        ..., "--floor-plan", "-p", help="Floor plan of the building: .json, R2V .txt or a plan image."
    ),
    ground_truth: Path | None = typer.Option(None, "--ground-truth", help="TUM ground truth (ATE/RPE)."),
    relations: Path | None = typer.Option(None, "--relations", help="Relations file (Kümmerle et al.)."),
    config: Path | None = typer.Option(None, "--config", "-c", help="FRSlamConfig YAML/JSON."),
    out: Path = typer.Option(Path("out/compare"), "--out", "-o", help="Output folder."),
    sequential: Sequential = False,
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    laser: Laser = None,
    odom: Odom = None,
    plane_tol: PlaneTol = None,
    viz: Viz = None,
) -> None:
    """Run with and without floor-plan priors and print the errors side by side."""
    from frslam_graph.atomic import Outputs
    from frslam_graph.offline import RUN_OUTPUTS, write_outputs

    with Outputs() as outputs:
        top = outputs.folder(out, "compare.json", ("compare.png",))
        runs = {name: outputs.folder(out / name, "metrics.json", RUN_OUTPUTS) for name in RUN_FOLDERS}
        _check_viz(outputs, viz)
        plan = _load_plan(floor_plan)
        reader_options = dict(
            scan_topic=scan_topic, odom_topic=odom_topic, laser=laser, odom=odom, plane_tol=plane_tol
        )
        rec, cfg, gt, rel, sources = _inputs(recording, config, ground_truth, relations, reader_options)
        with ScanProgress() as progress:
            without = _run_one(rec, None, cfg, "without priors", progress, sequential)
            write_outputs(without, runs["without_priors"], gt, rel)  # kept whatever the second run does
            with_ = _run_one(rec, plan, cfg, "with priors", progress, sequential)
        write_outputs(with_, runs["with_priors"], gt, rel)
        trajectories = {"without priors": without.result.trajectory, "with priors": with_.result.trajectory}
        summary = {"without priors": without.metrics, "with priors": with_.metrics}
        with top:
            top.write("compare.png", _compare_figure(trajectories, gt, with_))
            top.commit({k: _summary(v) for k, v in summary.items()})
        _write_viz(outputs, viz, {"without priors": without, "with priors": with_})
    _print_metrics(summary)
    print_written(outputs.files(), out, plan_status(with_.metrics, "with priors"))
    _check_evaluation(with_.metrics, sources, out)


#: compare's run folders inside its output folder
RUN_FOLDERS = ("without_priors", "with_priors")


def _summary(m: dict) -> dict:
    from frslam_graph.offline import _jsonable

    keep = (
        "scans",
        "keyframes",
        "realtime_factor",
        "latency_ms",
        "decisions",
        "priors",
        "plan_accepted",
        "ate",
        "ate_unaligned",
        "rpe_1m",
        "relations",
    )
    out = {k: m[k] for k in keep if k in m}
    if "relations" in out:
        r = out["relations"]
        out["relations"] = {
            k: getattr(r, k)
            for k in ("trans_mean", "trans_std", "rot_mean", "rot_std", "matched", "unmatched")
        }
    return _jsonable(out)


def _print_metrics(runs: dict[str, dict]) -> None:
    table = Table(title="frslam results")
    table.add_column("metric")
    for name in runs:
        table.add_column(name, justify="right")

    def row(label: str, fn) -> None:
        vals = []
        for m in runs.values():
            try:
                vals.append(fn(m))
            except (KeyError, AttributeError, TypeError):
                vals.append("–")
        if any(v != "–" for v in vals):
            table.add_row(label, *vals)

    row("scans / keyframes", lambda m: f"{m['scans']} / {m['keyframes']}")
    row("ATE RMSE \\[m] (SE(2)-aligned)", lambda m: f"{m['ate'].rmse:.3f}")
    row("ATE RMSE \\[m] (no alignment)", lambda m: f"{m['ate_unaligned'].rmse:.3f}")
    row("ATE max \\[m]", lambda m: f"{m['ate'].max:.3f}")
    row("RPE 1 m trans \\[m]", lambda m: f"{m['rpe_1m']['trans_m'].rmse:.3f}")
    row("RPE 1 m rot \\[deg]", lambda m: f"{m['rpe_1m']['rot_deg'].rmse:.2f}")
    row(
        "relations trans \\[m]", lambda m: f"{m['relations'].trans_mean:.4f} ± {m['relations'].trans_std:.4f}"
    )
    row("relations rot \\[deg]", lambda m: f"{m['relations'].rot_mean:.3f} ± {m['relations'].rot_std:.3f}")
    row("relations matched / unmatched", lambda m: f"{m['relations'].matched} / {m['relations'].unmatched}")
    row(
        "priors at the end / added / rejected",
        lambda m: "{final} / {added} / {rejected}".format(**m["priors"]),
    )
    row(
        "priors removed as wrong / re-anchored",
        lambda m: "{removed_wrong} / {re_anchored}".format(**m["priors"]),
    )
    row(
        "loop closures accepted / rejected",
        lambda m: f"{m['decisions'].get('loop_closure', 0)} / {m['decisions'].get('loop_rejected', 0)}",
    )
    row(
        "latency median / p99 \\[ms]",
        lambda m: f"{m['latency_ms']['median']:.2f} / {m['latency_ms']['p99']:.2f}",
    )
    row("× real time", lambda m: f"{m['realtime_factor']:.1f}")
    console.print(table)
