"""``frslam relations TRAJ RELATIONS``: the relation-based error of Kümmerle et al. (2009)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from frslam_graph.cli.app import app, console


@app.command("relations")
def relations(
    trajectory: Annotated[
        Path,
        typer.Argument(
            help="Trajectory as TUM (stamp x y z qx qy qz qw), or a recording whose odometry is evaluated."
        ),
    ],
    relations_file: Annotated[
        Path, typer.Argument(metavar="RELATIONS", help="Relations file: t1 t2 x y z roll pitch yaw.")
    ],
    tolerance: Annotated[
        float, typer.Option(help="Seconds between a relation stamp and the nearest pose.")
    ] = 0.01,
    interpolate: Annotated[
        float | None,
        typer.Option(
            help="Interpolate a keyframe trajectory at the relation stamps (max gap between poses, s)."
        ),
    ] = None,
) -> None:
    """Print the mean ± std translational (m) and rotational (deg) relation error of a trajectory."""
    from frslam_graph.cli.option_errors import option_text
    from frslam_graph.datasets import RecordingWarning, open_recording
    from frslam_graph.datasets.carmen import is_carmen
    from frslam_graph.datasets.rosbag import bag_path
    from frslam_graph.errors import TrajectoryError
    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations, load_tum

    for flag, value in (("--tolerance", tolerance), ("--interpolate", interpolate)):
        if value is not None and not 0.0 <= value < np.inf:  # before reading anything
            raise TrajectoryError(
                "expected a finite number of seconds, 0 or more", source=option_text(flag, value)
            )
    if trajectory.is_dir() or is_carmen(trajectory) or bag_path(trajectory) is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RecordingWarning)
            rows = [(s.stamp, *s.odom) for s in open_recording(trajectory) if s.odom is not None]
        if not rows:
            raise TrajectoryError("the recording has no odometry to evaluate", source=trajectory)
        traj = np.array(rows, dtype=np.float64)
        what = "odometry of the recording"
    else:
        traj = load_tum(trajectory)
        what = "trajectory"
    res = relation_error(traj, load_relations(relations_file), tolerance, interpolate)
    if res.matched == 0:  # no error to report: another recording's relations, or a tolerance too tight
        raise TrajectoryError(
            f"none of its {res.unmatched:,} relations matches a pose of {trajectory} within "
            + (
                f"--interpolate {interpolate:g} s"
                if interpolate is not None
                else f"--tolerance {tolerance:g} s"
            )
            + " (relations of another recording?)",
            source=relations_file,
        )
    console.print(f"{trajectory} ({what}, {len(traj):,} poses) against {relations_file}:")
    console.print(
        f"  translational error {res.trans_mean:.4f} ± {res.trans_std:.4f} m (mean of squares {res.trans_sq_mean:.4f} m²)"
    )
    console.print(
        f"  rotational error    {res.rot_mean:.3f} ± {res.rot_std:.3f} deg (mean of squares {res.rot_sq_mean:.3f} deg²)"
    )
    how = (
        f"interpolated, gaps <= {interpolate:g} s"
        if interpolate is not None
        else f"tolerance {tolerance:g} s"
    )
    console.print(f"  relations: {res.matched:,} matched, {res.unmatched:,} unmatched ({how})")
