"""Backend speed and odometry accuracy on a synthetic ray-cast recording (Markdown table).

Recording: the 12 × 8 m room of ``tests/synthetic_world.py`` driven around ``--laps`` times at
0.5 m/s, 10 Hz, 720-beam scans (1 cm range noise, 10 m range), wheel odometry with 2 % scale
error and 1°/m heading drift. Measured, as medians over ``--runs``:

- streaming: per-scan latency of ``FRSlam.add_scan`` (median, p99; wall clock and process CPU
  time, the latter robust to a machine shared with other jobs), with and without wheel odometry;
  baseline timed in the same run: bare ``KissICP.register_frame`` on the same scans;
- offline: ``FRSlam.process`` (incl. the final LM batch) as a multiple of real time;
- accuracy: end-point drift (% of path) of the odometry and ATE RMSE of the trajectory;
- mapping: time of ``occupancy_grid()`` over all keyframes.

Loop closure (when the config has it) is off unless ``--loop-closure``: this measures the core.

    /work/venv/bin/python tools/bench_backend.py [--laps 4] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from frslam_graph.datasets import Scan  # noqa: E402
from synthetic_world import ROOM_LOOP, drifting_odometry, room_world, route, scans_along  # noqa: E402

from frslam_graph.config import FRSlamConfig  # noqa: E402
from frslam_graph.motion_model import between  # noqa: E402
from frslam_graph.pipeline import FRSlam  # noqa: E402


def make_recording(laps: int):
    truth = route(ROOM_LOOP * laps)
    ranges, amin, inc = scans_along(room_world(), truth, max_range=10.0)
    wheel = drifting_odometry(truth, scale=0.02, heading_per_m=np.deg2rad(1.0))
    return truth, ranges, amin, inc, wheel


def streaming(rec, cfg, use_wheel: bool):
    truth, ranges, amin, inc, wheel = rec
    slam = FRSlam(cfg)
    lat = np.empty(len(truth))
    cpu = np.empty(len(truth))
    for i in range(len(truth)):
        t0, c0 = time.perf_counter(), time.process_time()
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, wheel[i] if use_wheel else None)
        lat[i], cpu[i] = time.perf_counter() - t0, time.process_time() - c0
    return slam, lat, cpu


def bare_kiss(rec, cfg):
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig
    from kiss_icp.kiss_icp import KissICP

    o = cfg.odometry
    icp = KissICP(
        KISSConfig(
            data=DataConfig(max_range=o.max_range, min_range=o.min_range, deskew=False),
            mapping=MappingConfig(voxel_size=o.voxel_size),
            registration=RegistrationConfig(max_num_threads=o.num_threads),
            adaptive_threshold=AdaptiveThresholdConfig(initial_threshold=o.initial_threshold),
        )
    )
    truth, ranges, amin, inc, _ = rec
    ang = amin + inc * np.arange(len(ranges[0]))
    lat = np.empty(len(truth))
    cpu = np.empty(len(truth))
    ts = np.zeros(0)
    for i, r in enumerate(ranges):
        t0, c0 = time.perf_counter(), time.process_time()
        ok = np.isfinite(r)
        pts = np.column_stack((r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok]), np.zeros(ok.sum())))
        icp.register_frame(pts, ts)
        lat[i], cpu[i] = time.perf_counter() - t0, time.process_time() - c0
    return lat, cpu


def accuracy(slam, truth):
    traj = slam.trajectory()
    odo = slam.odometry_trajectory()
    path = float(np.sum(np.hypot(*np.diff(truth[:, 1:3], axis=0).T)))
    rel_t = between(truth[0, 1:], truth[-1, 1:])
    rel_o = between(odo[0, 1:], odo[-1, 1:])
    drift = float(np.hypot(*(rel_t[:2] - rel_o[:2]))) / path
    # align the start (the run without wheel odometry starts its odom frame at the origin)
    from frslam_graph.motion_model import compose, compose_many, inverse

    align = compose(truth[0, 1:], inverse(traj[0, 1:]))
    est = compose_many(align, traj[:, 1:])
    ate = float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[:, 1:3]) ** 2, axis=1))))
    return drift, ate, path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--laps", type=int, default=4)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--loop-closure", action="store_true", help="keep loop closure on (if configured)")
    args = ap.parse_args()
    cfg_dict = {"odometry": {"max_range": 10.0}}
    if "loop_closure" in FRSlamConfig.model_fields and not args.loop_closure:
        cfg_dict["loop_closure"] = {"enabled": False}
    cfg = FRSlamConfig.from_dict(cfg_dict)
    rec = make_recording(args.laps)
    truth = rec[0]
    duration = float(truth[-1, 0] - truth[0, 0])

    rows: dict[str, list[float]] = {}

    def put(name, value):
        rows.setdefault(name, []).append(value)

    for _ in range(args.runs):
        base, base_cpu = bare_kiss(rec, cfg)
        put("bare KissICP.register_frame median ms", 1e3 * np.median(base))
        put("bare KissICP.register_frame p99 ms", 1e3 * np.percentile(base, 99))
        put("bare KissICP.register_frame CPU median ms", 1e3 * np.median(base_cpu))
        for use_wheel, tag in ((True, "wheel+ICP"), (False, "ICP only")):
            slam, lat, cpu = streaming(rec, cfg, use_wheel)
            put(f"add_scan ({tag}) median ms", 1e3 * np.median(lat))
            put(f"add_scan ({tag}) p99 ms", 1e3 * np.percentile(lat, 99))
            put(f"add_scan ({tag}) CPU median ms", 1e3 * np.median(cpu))
            put(f"add_scan ({tag}) CPU p99 ms", 1e3 * np.percentile(cpu, 99))
            put(f"add_scan ({tag}) CPU median / bare KISS-ICP", float(np.median(cpu) / np.median(base_cpu)))
            drift, ate, path = accuracy(slam, truth)
            put(f"odometry drift ({tag}) % of path", 100 * drift)
            put(f"trajectory ATE RMSE ({tag}) m", ate)
            if use_wheel:
                t0 = time.perf_counter()
                slam.occupancy_grid(0.05)
                put(f"occupancy_grid over {len(slam.keyframes())} keyframes s", time.perf_counter() - t0)
                wheel_rel = between(rec[4][0], rec[4][-1])
                true_rel = between(truth[0, 1:], truth[-1, 1:])
                put("wheel odometry drift % of path", 100 * np.hypot(*(wheel_rel[:2] - true_rel[:2])) / path)
        angles = rec[2] + rec[3] * np.arange(len(rec[1][0]))
        scans = [
            Scan(float(truth[i, 0]), rec[1][i], angles, tuple(rec[4][i]), 10.0) for i in range(len(truth))
        ]
        res = FRSlam(cfg).process(scans)
        put("offline process() x real time", res.realtime_factor)

    print(
        f"Synthetic room, {args.laps} laps: {len(truth)} scans x 720 beams, {path:.1f} m, "
        f"{duration:.0f} s; loop closure {'on' if args.loop_closure else 'off'}; medians over {args.runs} runs\n"
    )
    print("| metric | value |\n|---|---|")
    for name, vals in rows.items():
        print(f"| {name} | {statistics.median(vals):.3f} |")


if __name__ == "__main__":
    main()
