"""Offline processing of a recording: run the backend, write its outputs, evaluate.

:func:`process` is the offline loop: every scan of a recording through an
:class:`~frslam_graph.slam.FRSlam`, the scan odometry in a worker process one stage ahead
(:mod:`frslam_graph.odometry.worker`) where possible, then the final batch. ``run_recording`` drives :class:`~frslam_graph.slam.FRSlam` over every scan of a recording
(optionally with a floor plan, whose registrations / relocalisations become priors) and
``write_outputs`` saves what a user needs: the trajectory (TUM, ``map`` frame), the LiDAR map
(map_server YAML + PGM), the registered plan (JSON, map metres), the decision log (JSON lines)
and a metrics JSON, written last with the list of outputs (the folder's completeness marker;
a rerun into the folder replaces the previous run's outputs as a whole, see
:class:`~frslam_graph.atomic.OutputFolder`). ``evaluate`` compares a trajectory with ground truth (evo ATE / RPE) or with
the relations of Kümmerle et al. Nothing here prints; progress goes through a callback.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph import stream_input
from frslam_graph.atomic import OutputFolder
from frslam_graph.backend.decisions import PRIOR_REMOVAL_CAUSES, DecisionEvent
from frslam_graph.backend.keyframes import Rows
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, TrajectoryError
from frslam_graph.libc import libc_function
from frslam_graph.odometry import worker as odometry_worker
from frslam_graph.odometry.scan_odometry import OdometryStats
from frslam_graph.slam import FRSlam, body_points

if TYPE_CHECKING:
    from frslam_graph.occupancy import OccupancyGrid

#: what a run writes into its folder (a previous run's files of these names are removed)
RUN_OUTPUTS = (
    "trajectory.tum",
    "odometry.tum",
    "map.yaml",
    "map.pgm",
    "registered_plan.json",
    "log.jsonl",
    "trajectory.png",
    "metrics.json",
)


@dataclass(slots=True)
class SlamResult:
    """Output of :func:`process`."""

    trajectory: np.ndarray  # (N, 4) stamp, x, y, theta in map
    keyframes: np.ndarray  # (K, 4) stamp, x, y, theta in map
    odometry: np.ndarray  # (N, 4) stamp, x, y, theta in odom
    map_to_odom: np.ndarray  # (3,)
    stats: OdometryStats
    log: Sequence[DecisionEvent]
    latencies: np.ndarray  # (N,) seconds per scan (add_scan; parallel: odometry + backend stage)
    wall_time: float  # seconds for the whole run (incl. the batch)
    duration: float  # recording time span, seconds
    parallel: bool = False  # odometry ran in a worker process (latencies: sum of both stages)
    # (N,) CPU seconds per scan of the threads that did its work (odometry + backend stage): the
    # latency on a core of its own, whatever else loads the machine
    cpu_latencies: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def realtime_factor(self) -> float:
        return self.duration / self.wall_time if self.wall_time > 0 else float("inf")


def process(
    slam: FRSlam, recording: Iterable[Any], batch: bool = True, parallel: bool | None = None
) -> SlamResult:
    """Run ``slam`` over every Scan of a recording (offline); LM batch at the end when ``batch``.

    ``parallel``: run the scan odometry in a worker process, one stage ahead of the backend
    (:mod:`frslam_graph.odometry.worker`; same results, about 1.5x the throughput on two
    cores). None = whenever possible: a fresh instance (no scans yet) where
    :func:`~frslam_graph.odometry.worker.available` holds. Afterwards ``slam`` takes no more
    scans (its own odometry did not run). ``SlamResult.latencies`` are then the sum of both
    stages' seconds per scan (what ``add_scan`` would take); ``cpu_latencies`` the same in CPU
    seconds of the threads that did the work.
    """
    with slam.guard("process"):
        can = (
            not len(slam) and not slam.odometry_in_worker and odometry_worker.available(slam.config.odometry)
        )
        if parallel and not can:
            raise ConfigError(
                "process(parallel=True) needs a fresh FRSlam, Linux fork, two cores, a non-daemonic "
                "process and odometry.num_threads 1",
                where="parallel",
            )
        parallel = can if parallel is None else parallel
        lat = Rows(2)  # wall, CPU seconds per scan
        t_start = time.perf_counter()
        first = last = None
        with contextlib.ExitStack() as stack:
            if parallel:
                worker = stack.enter_context(odometry_worker.OdometryWorker(slam.config.odometry))
                slam.odometry_in_worker = True
                staged = _odometry_in_worker(slam, recording, worker)
            else:
                staged = _odometry_here(slam, recording)
            for stamp, res, pts, off, odometry_s, odometry_cpu in staged:
                t0, c0 = time.perf_counter(), time.thread_time()
                slam.add_odometry(res, pts, off)
                lat.append((odometry_s + time.perf_counter() - t0, odometry_cpu + time.thread_time() - c0))
                first = stamp if first is None else first
                last = stamp
            if parallel:
                slam.odometry.stats = worker.stats
        slam.context.deferred.run_all()  # the last keyframes' steps (also without the batch)
        if batch:
            slam.finish()
        wall = time.perf_counter() - t_start
        return SlamResult(
            slam.trajectory(),
            slam.keyframe_array(),
            slam.odometry_trajectory(),
            np.asarray(slam.map_to_odom()),
            slam.stats,
            slam.log,
            lat.array[:, 0].copy(),
            wall,
            float(last - first) if first is not None else 0.0,
            bool(parallel),
            lat.array[:, 1].copy(),
        )


def _odometry_here(slam: FRSlam, recording: Iterable[Any]) -> Iterator[tuple]:
    """(stamp, odometry result, base_link points, sensor offset, seconds, CPU seconds) per scan,
    in-process."""
    for scan in recording:
        slam.check_own_odometry()
        t0, c0 = time.perf_counter(), time.thread_time()
        stamp = stream_input.finite_number(scan.stamp, "stamp")
        pts, off = body_points(scan.points, scan.sensor_offset)
        res = slam.odometry.process(stamp, pts, scan.odom)
        yield scan.stamp, res, pts, off, time.perf_counter() - t0, time.thread_time() - c0


def _odometry_in_worker(slam: FRSlam, recording: Iterable[Any], worker) -> Iterator[tuple]:
    """The same from an :class:`~frslam_graph.odometry.worker.OdometryWorker`; the stateless
    part of the odometry (prepare) runs in whichever stage is the lighter one."""

    def inputs():
        for scan in recording:  # the stamp is checked in the worker (raised in order)
            pts, off = body_points(scan.points, scan.sensor_offset)
            yield scan.stamp, pts, scan.odom, off

    for (stamp, pts, _, off), res, seconds, cpu_seconds in worker.run(inputs(), slam.odometry.prepare):
        yield stamp, res, pts, off, seconds, cpu_seconds


#: scans between two returns of freed heap memory to the system during :func:`run_recording`
TRIM_EVERY_SCANS = 200
#: bytes; blocks from this size up are mapped and unmapped one by one (glibc's M_MMAP_THRESHOLD,
#: pinned by :func:`_pin_mmap_threshold`)
MMAP_THRESHOLD = 256 * 1024
#: bytes of free memory at the top of the heap that ``free`` leaves mapped (glibc's
#: M_TRIM_THRESHOLD, set with the pin). At 512 kB the top of the heap was given back and mapped
#: again all the time, the kernel zero-filling each page anew: the odometry took 728,000 page
#: faults on FR079 (1.1 s of system CPU of ~20 s), 5,600 at 4 MB. :data:`TRIM_EVERY_SCANS` trims
#: the heap anyway.
TRIM_THRESHOLD = 4 * 1024 * 1024
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt(3) parameters (malloc.h)


def _pin_mmap_threshold() -> bool:
    """Pin glibc's mmap threshold at :data:`MMAP_THRESHOLD` for this process (and the odometry
    worker forked from it); False without glibc.

    glibc raises its threshold to the size of the largest mapped block freed so far (up to
    32 MB): afterwards iSAM2's and numpy's temporaries of that size come from the heap, and the
    heap grew between two trims by what they left behind (on the long simulated recording,
    peak RSS - trimmed RSS: 35 MB at 4,000 scans, 119 MB at 16,000). Pinned, such blocks go back
    to the system when freed: 11 and 29 MB. The trim threshold goes with it
    (:data:`TRIM_THRESHOLD`). It moves no live object: results are unchanged."""
    mallopt = libc_function("mallopt", [ctypes.c_int, ctypes.c_int], ctypes.c_int)
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )


def _heap_trimmer() -> Callable[[], object] | None:
    """glibc's ``malloc_trim(0)``, or None without glibc.

    glibc keeps memory freed in the middle of its heap (and, once a large numpy temporary was
    freed, serves arrays up to that size from the heap instead of ``mmap``: its dynamic mmap
    threshold, mallopt(3)). On Intel the backend held ~80 MB of freed memory (RSS 288 MB at
    2,000 scans, 207 MB after a trim; 318 / 237 MB at 6,000). Trimming every few hundred scans
    gives it back; it moves no live object, so results are unchanged."""
    trim = libc_function("malloc_trim", [ctypes.c_size_t], ctypes.c_int)
    return None if trim is None else lambda: trim(0)


@dataclass
class RunOutput:
    """A finished run: the backend (for further queries), its result, and where files went."""

    slam: FRSlam
    result: SlamResult
    files: dict[str, Path] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    #: what the reader saw (records skipped or flagged and where; None for a plain iterable)
    recording_stats: Any = None


def run_recording(
    recording,
    floor_plan=None,
    config: FRSlamConfig | dict | str | Path | None = None,
    progress: Callable[[int], None] | None = None,
    parallel: bool | None = None,
) -> RunOutput:
    """Run FRSlam over ``recording`` (an iterable of Scan); ``floor_plan`` None = no priors.

    ``progress(i)`` is called after each scan is read. ``parallel``: odometry in a worker process
    (same results; None = where possible, see :func:`process`). Every
    :data:`TRIM_EVERY_SCANS` scans the heap memory freed meanwhile goes back to the system
    (:func:`_heap_trimmer`), and large blocks go back as soon as they are freed (the process's
    mmap threshold is pinned: :func:`_pin_mmap_threshold`). Scans are streamed: none is kept
    after the backend took it.
    """
    slam = FRSlam(config=config, floor_plan=floor_plan)
    _pin_mmap_threshold()
    trim = _heap_trimmer()

    def scans():
        for i, scan in enumerate(recording):
            yield scan
            if progress is not None:
                progress(i + 1)
            if trim is not None and (i + 1) % TRIM_EVERY_SCANS == 0:
                trim()

    result = process(slam, scans(), batch=True, parallel=parallel)
    return RunOutput(slam, result, recording_stats=getattr(recording, "stats", None))


def _jsonable(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        return _jsonable(asdict(value))
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def write_outputs(
    run: RunOutput,
    out: Path | OutputFolder,
    ground_truth: np.ndarray | None = None,
    relations: np.ndarray | None = None,
    figures: dict[str, Callable[[Path], object]] | None = None,
) -> RunOutput:
    """Write trajectory, map, registered plan, decision log, ``figures`` (name: ``writer(path)``)
    and metrics into ``out`` (a folder, or an OutputFolder the caller declared), replacing a
    previous run's outputs as a whole; ``metrics.json`` is written last.

    A ground truth or relations that do not match the trajectory (another recording) do not
    stop the writing: ``metrics["evaluation_errors"]`` names the problem.
    """
    from frslam_graph.atomic import atomic_write
    from frslam_graph.evaluation.trajectory_io import save_tum

    folder = out if isinstance(out, OutputFolder) else OutputFolder(out, "metrics.json", RUN_OUTPUTS)
    res = run.result
    grid = run.slam.occupancy_grid(0.05) if len(res.keyframes) else None
    metrics = _run_metrics(run, grid, ground_truth, relations)
    with folder:
        files = {
            "trajectory": folder.write("trajectory.tum", lambda p: save_tum(p, res.trajectory)),
            "odometry": folder.write("odometry.tum", lambda p: save_tum(p, res.odometry)),
        }
        if grid is not None:
            files["map"] = folder.write("map.yaml", grid.save)
        plan_in_map = run.slam.registered_plan()
        if plan_in_map is not None:
            files["registered_plan"] = folder.write("registered_plan.json", plan_in_map.save)

        def write_log(path: Path) -> None:
            with atomic_write(path) as fh:
                fh.writelines(json.dumps(_jsonable(ev)) + "\n" for ev in res.log)

        files["log"] = folder.write("log.jsonl", write_log)
        for name, writer in (figures or {}).items():
            files[name] = folder.write(name, writer)
        folder.commit(_jsonable(metrics))
    files["metrics"] = folder.folder / "metrics.json"
    run.files, run.metrics = files, metrics
    return run


def _spread(seconds: np.ndarray) -> dict[str, float]:
    """Median, 99th percentile and maximum (ms) of per-scan seconds (zeros for no scan)."""
    ms = seconds * 1e3 if len(seconds) else np.zeros(1)
    return {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


def _run_metrics(
    run: RunOutput, grid: OccupancyGrid | None, ground_truth: np.ndarray | None, relations: np.ndarray | None
) -> dict[str, Any]:
    """The content of ``metrics.json``: counts, timing, decisions, priors, map (``grid``, None
    without keyframes), evaluation."""
    res = run.result
    map_metrics = _map_metrics(run.slam, grid) if grid is not None else {}
    kinds: dict[str, int] = {}
    removed = dict.fromkeys(PRIOR_REMOVAL_CAUSES, 0)
    for ev in res.log:
        kinds[ev.kind] = kinds.get(ev.kind, 0) + 1
        if ev.kind == "prior_removed":
            removed[ev.data["cause"]] += 1
    metrics: dict[str, Any] = {
        "scans": len(res.trajectory),
        "keyframes": len(res.keyframes),
        "duration_s": res.duration,
        "wall_time_s": res.wall_time,
        "realtime_factor": res.realtime_factor,
        # with the odometry in a worker process a latency is the sum of both stages' times
        "odometry_in_worker": res.parallel,
        "latency_ms": _spread(res.latencies),
        # the same in CPU time of the threads that did each scan's work: the latency on a core of
        # its own, whatever else loads the machine
        "latency_cpu_ms": _spread(res.cpu_latencies),
        "map_to_odom": res.map_to_odom,
        "odometry_stats": res.stats,
        "decisions": kinds,
        # floor-plan priors: in the graph at the end; removed as wrong (proven wrong, or their
        # plan retracted) or re-anchored (their plan refined or replaced: relocalised on it)
        "priors": {
            "final": len(run.slam.graph.priors()),
            "added": kinds.get("prior_added", 0),
            "rejected": kinds.get("prior_rejected", 0),
            "removed_wrong": removed["wrong"],
            "re_anchored": removed["re-anchored"],
        },
        "floor_plan": run.slam.floor_plan is not None,
        # when the floor plan was first accepted (None: never, or no plan)
        "plan_accepted": plan_acceptance(res),
    }
    if map_metrics:
        metrics["map"] = map_metrics
    if run.slam.loop_closer is not None:  # the work done (matches, batches, plans skipped) and its time
        metrics["loop_closure"] = run.slam.loop_closer.stats
    st = run.recording_stats
    if st is not None:  # records the reader skipped or flagged: kept with the results
        metrics["recording"] = {
            "skipped": dict(st.skipped),
            "flagged": dict(st.problems),
            "first_at": dict(st.first),
            "invalid_beams": int(st.invalid_beams),
            "beams": int(st.beams),
        }
    errors: dict[str, str] = {}
    for what, gt, rel in (("ground_truth", ground_truth, None), ("relations", None, relations)):
        try:
            metrics.update(evaluate(res.trajectory, gt, rel))
        except TrajectoryError as exc:  # another recording's: the run's outputs are still written
            errors[what] = exc.message
    if errors:
        metrics["evaluation_errors"] = errors
    return metrics


def plan_acceptance(result: SlamResult) -> dict[str, Any] | None:
    """When the floor plan was first accepted, from the decision log: the first accepted
    registration's scan index (into the trajectory), stamp, seconds since the first scan and
    keyframe, how many registrations had been tried by then, the distance travelled (m) and the
    share of the registered plan's room area the map had seen (0..1) then, and whether it came
    only at the end of the run (on the complete map); None when none was accepted."""
    tried = 0
    for ev in result.log:
        if ev.kind != "register":
            continue
        tried += 1
        if not ev.data.get("accepted"):
            continue
        stamps = result.trajectory[:, 0]
        exact = np.flatnonzero(stamps == ev.stamp)
        scan = int(exact[0]) if exact.size else int(np.argmin(np.abs(stamps - ev.stamp)))
        return {
            "scan": scan,
            "stamp": ev.stamp,
            "time_s": ev.stamp - float(stamps[0]),
            "keyframe": ev.keyframe,
            "registrations_tried": tried,
            "distance_m": ev.data.get("distance_m"),
            "plan_seen": ev.data.get("plan_seen"),
            "at_end": ev.message.startswith("end of the run"),
        }
    return None


def _map_metrics(slam: FRSlam, grid) -> dict[str, Any]:
    """The written map against the keyframe scans at the final estimates: share of end points on
    or next to (8-neighbourhood) an occupied cell, and the occupied / free cell counts."""
    from frslam_graph.backend.mapping import scans_endpoint_share

    pts, _ = slam.keyframe_scans()
    return {
        "endpoints_on_wall": scans_endpoint_share(grid, slam.graph.estimates(), pts),
        "occupied_cells": int(grid.occupied_mask().sum()),
        "free_cells": int(grid.free_mask().sum()),
    }


def evaluate(
    trajectory: np.ndarray,
    ground_truth: np.ndarray | None = None,
    relations: np.ndarray | None = None,
    max_dt: float = 0.02,
) -> dict[str, Any]:
    """ATE (SE(2)-aligned) / RPE against ground truth and/or the relation error; {} without either."""
    from frslam_graph.evaluation.metrics import ate, rpe
    from frslam_graph.evaluation.relations import relation_error

    out: dict[str, Any] = {}
    if ground_truth is not None:
        stats, align = ate(trajectory, ground_truth, max_dt=max_dt)
        out["ate"] = stats
        out["ate_alignment"] = align
        # ATE without alignment: meaningful once the map frame is the floor plan's frame
        out["ate_unaligned"], _ = ate(trajectory, ground_truth, align=False, max_dt=max_dt)
        try:
            t_err, r_err = rpe(trajectory, ground_truth, delta=1.0, unit="meters", max_dt=max_dt)
            out["rpe_1m"] = {"trans_m": t_err, "rot_deg": r_err}
        except TrajectoryError as exc:  # too short a trajectory for 1 m pairs
            out["rpe_1m"] = {"error": str(exc)}
    if relations is not None:
        out["relations"] = relation_error(trajectory, relations)
    return out
