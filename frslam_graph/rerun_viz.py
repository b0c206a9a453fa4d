"""A rerun recording (``.rrd``, viewable with ``rerun FILE.rrd``) of finished runs: for each run its
keyframe scans in the map frame and the robot's pose over time, the trajectory, the LiDAR map,
the registered floor plan and the decision log.

rerun-sdk is optional (``pip install 'frslam[viz]'``); :func:`require_rerun` says how to get it.
Timelines: ``scan`` (the scan's index in the recording) and ``time`` (seconds since its first scan).
Entities: ``world/<run>/scan``, ``world/<run>/robot``, ``world/<run>/trajectory``,
``world/<run>/map``, ``world/<run>/plan/rooms``, ``world/<run>/plan/doors``,
``world/<run>/decisions``.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from frslam_graph.atomic import TEMP_PREFIX
from frslam_graph.errors import FrslamError

if TYPE_CHECKING:
    from frslam_graph.offline import RunOutput

#: how to install the optional dependency
INSTALL = "pip install 'frslam[viz]' (or: pip install rerun-sdk)"
#: the map is drawn as its occupied cells' centres at this resolution, metres
MAP_RESOLUTION = 0.05

_COLOURS = {"scan": (255, 140, 0), "robot": (220, 20, 60), "trajectory": (30, 100, 220), "map": (90, 90, 90)}
_PLAN = (46, 139, 87)


def require_rerun(option: str = "--viz") -> ModuleType:
    """The ``rerun`` module, or a FrslamError naming ``option`` and the install command."""
    try:
        import rerun
    except ImportError:
        raise FrslamError(f"needs rerun-sdk, which is not installed: {INSTALL}", where=option) from None
    return rerun


def _entity(name: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in name) or "run"


def _log_run(rr: ModuleType, rec, name: str, run: RunOutput) -> None:
    """One run's entities under ``world/<name>``."""
    base = f"world/{_entity(name)}"
    res, slam = run.result, run.slam
    traj = res.trajectory
    if not len(traj):
        return
    t0 = float(traj[0, 0])
    rec.log(
        f"{base}/trajectory", rr.LineStrips2D([traj[:, 1:3]], colors=[_COLOURS["trajectory"]]), static=True
    )
    if len(res.keyframes):
        grid = slam.occupancy_grid(MAP_RESOLUTION)
        rows, cols = np.nonzero(grid.occupied_mask())
        cells = grid.cell_to_world(np.column_stack([cols + 0.5, rows + 0.5]))
        rec.log(
            f"{base}/map",
            rr.Points2D(cells, radii=0.5 * grid.resolution, colors=[_COLOURS["map"]]),
            static=True,
        )
    plan = slam.registered_plan()
    if plan is not None:
        outlines = [np.asarray(room.polygon.exterior.coords)[:, :2] for room in plan.rooms]
        labels = [f"{room.id} ({room.type})" for room in plan.rooms]
        rec.log(f"{base}/plan/rooms", rr.LineStrips2D(outlines, colors=[_PLAN], labels=labels), static=True)
        if plan.doors:
            doors = [np.array([d.a, d.b], dtype=np.float64) for d in plan.doors]
            rec.log(f"{base}/plan/doors", rr.LineStrips2D(doors, colors=[(255, 215, 0)]), static=True)
    # keyframe scans at their final estimates, on the scan / time timelines
    first_row = {}
    for i, stamp in enumerate(traj[:, 0]):
        first_row.setdefault(float(stamp), i)
    points, _origins = slam.keyframe_scans()
    poses = slam.graph.estimates() if len(points) else np.zeros((0, 3))
    stamps = res.keyframes[:, 0] if len(res.keyframes) == len(points) else np.full(len(points), np.nan)
    for pose, pts, stamp in zip(np.asarray(poses).reshape(-1, 3), points, stamps, strict=True):
        scan = first_row.get(float(stamp))
        if scan is None:
            continue
        rec.set_time("scan", sequence=scan)
        rec.set_time("time", duration=float(stamp) - t0)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        in_map = np.column_stack([pose[0] + c * p[:, 0] - s * p[:, 1], pose[1] + s * p[:, 0] + c * p[:, 1]])
        rec.log(f"{base}/scan", rr.Points2D(in_map, radii=0.03, colors=[_COLOURS["scan"]]))
        rec.log(
            f"{base}/robot",
            rr.Arrows2D(origins=[pose[:2]], vectors=[[0.5 * c, 0.5 * s]], colors=[_COLOURS["robot"]]),
        )
    for ev in res.log:
        scan = first_row.get(float(ev.stamp))
        if scan is not None:
            rec.set_time("scan", sequence=scan)
        rec.set_time("time", duration=float(ev.stamp) - t0)
        rec.log(f"{base}/decisions", rr.TextLog(f"{ev.kind}: {ev.message}", level="INFO"))


def write_rerun(path: str | Path, runs: dict[str, RunOutput], application: str = "frslam") -> Path:
    """Write the runs (name: finished run) as one rerun recording at ``path``, atomically."""
    rr = require_rerun()
    path = Path(path)
    tmp = path.parent / f"{TEMP_PREFIX}{secrets.token_hex(4)}-{path.name}"
    rec = rr.RecordingStream(application)
    try:
        rec.save(tmp)
        for name, run in runs.items():
            _log_run(rr, rec, name, run)
        rec.flush()
        rec.disconnect()
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
