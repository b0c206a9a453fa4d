"""Benchmark the simulator's ray casting (scans per second) and partial maps (ms per map).

Houses are made from shared R2V plans (``../shared/data/floorplans/r2v``; the synthetic
five-room plan when absent) with random distortions; scan poses lie along simulated routes.
Each caster casts the same poses; the naive full broadcast (every beam against every segment)
is the baseline, timed in the same run. Exactness is the largest range difference from the
naive caster over every beam (both must agree on which beams hit nothing).

    python tools/bench_simulator.py [--plans 5] [--beams 720] [--scans 400] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
from _paths import SHARED_DATA
from frslam_graph.datasets.simulator import (
    Distortion,
    House,
    Lidar,
    RayCaster,
    SimulationOptions,
    five_room_plan,
    partial_map,
    plan_route,
    simulate_run,
)

from frslam_graph.floorplan import FloorPlan

SHARED = SHARED_DATA / "floorplans" / "r2v"


def _houses(n: int, seed: int) -> list[tuple[str, House, np.ndarray]]:
    rng = np.random.default_rng(seed)
    files = sorted(SHARED.glob("*.txt")) if SHARED.is_dir() else []
    plans = []
    if files:
        for i in rng.permutation(len(files)):
            try:
                plans.append((files[i].stem, FloorPlan.load(files[i])))
            except Exception:  # a plan the loader rejects is skipped in the benchmark
                continue
            if len(plans) == n:
                break
    else:
        plans = [("synthetic-five-rooms", five_room_plan())]
    out = []
    for name, plan in plans:
        d = Distortion.random(rng, rotation="any", plan_bounds=plan.bounds)
        house = House.from_plan(plan, d, clutter=10, rng=rng)
        route = plan_route(house, rng, length=30.0)
        out.append((name, house, route.poses))
    return out


def _time(fn, repeats: int) -> tuple[float, np.ndarray]:
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plans", type=int, default=5)
    ap.add_argument("--beams", type=int, default=720)
    ap.add_argument("--fov", type=float, default=270.0, help="degrees")
    ap.add_argument("--scans", type=int, default=400, help="scans per house and run")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    lidar = Lidar(beams=args.beams, fov=math.radians(args.fov), max_range=30.0)
    houses = _houses(args.plans, args.seed)
    methods = ["naive", "sweep", "open3d"]
    rates: dict[str, list[float]] = {m: [] for m in methods}
    errors: dict[str, float] = {m: 0.0 for m in methods}
    mismatches: dict[str, int] = {m: 0 for m in methods}
    seg_counts, map_ms = [], []
    for _name, house, poses in houses:
        idx = np.linspace(0, len(poses) - 1, args.scans).astype(int)
        p = poses[idx]
        seg_counts.append(len(house.segments))
        ref = None
        for m in methods:
            try:
                caster = RayCaster(house.segments, method=m)
            except Exception:
                continue
            reps = 1 if m == "naive" else args.repeats
            caster.cast(p[:2], lidar.angles, lidar.max_range)  # warm-up
            dt, r = _time(lambda c=caster, q=p: c.cast(q, lidar.angles, lidar.max_range), reps)
            rates[m].append(len(p) / dt)
            if m == "naive":
                ref = r
            else:
                both = np.isfinite(ref) & np.isfinite(r)
                mismatches[m] += int((np.isfinite(ref) != np.isfinite(r)).sum())
                if both.any():
                    errors[m] = max(errors[m], float(np.abs(ref[both] - r[both]).max()))
        rng = np.random.default_rng(args.seed)
        partial_map(house, 0.5, rng)  # builds the per-house raster cache
        ms, _ = _time(lambda h=house, g=rng: partial_map(h, 0.5, g), 20)
        map_ms.append(ms * 1e3)

    base = statistics.median(rates["naive"])
    print(
        f"\n### Ray casting: {args.beams} beams over {args.fov:g}°, {len(houses)} houses "
        f"({min(seg_counts)}–{max(seg_counts)} segments), {args.scans} scans per house, "
        f"median of {args.repeats} runs\n"
    )
    print(
        "| caster | scans/s (median over houses) | × naive | max |error| vs naive (m) | hit/miss mismatches |"
    )
    print("|---|---:|---:|---:|---:|")
    for m in methods:
        if not rates[m]:
            print(f"| {m} | unavailable | | | |")
            continue
        r = statistics.median(rates[m])
        err = "reference" if m == "naive" else f"{errors[m]:.2e}"
        mis = "" if m == "naive" else str(mismatches[m])
        print(f"| {m} | {r:,.0f} | {r / base:.1f} | {err} | {mis} |")
    print(f"\nPartial map (completeness 0.5, 0.05 m): median {statistics.median(map_ms):.2f} ms per map")
    # End to end: a whole in-memory run (house, route, scans, odometry, partial map).
    plan = five_room_plan()
    opts = SimulationOptions(length=100.0, beams=args.beams, fov_deg=args.fov, scan_rate=10.0)
    t0 = time.perf_counter()
    run = simulate_run(plan, seed=args.seed, options=opts)
    dt = time.perf_counter() - t0
    print(
        f"simulate_run (five-room plan, {run.route.length:.0f} m route, {len(run)} scans of {args.beams} "
        f"beams): {dt:.2f} s, {len(run) / dt:,.0f} scans/s, {run.route.duration / dt:,.0f}x real time"
    )


if __name__ == "__main__":
    main()
