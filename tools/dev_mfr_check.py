#!/usr/bin/env python3
"""Quick development check of our MFR registration on shared R2V plans with simulated partial maps.

Protocol of the registration benchmark (same as ``tools/bench_registration.py``, smaller and ours only): per plan
and rotation set one random distortion (``Distortion.random``), per completeness one partial map
from the simulator; IoU_a over all rooms. Prints a Markdown table (flip / rotation accuracy,
mean IoU_a, median time), the failure reasons, and optionally every case as CSV.

    python tools/dev_mfr_check.py --plans 60 --completeness 25 50 75 100 --csv /tmp/mfr.csv
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from collections import Counter, defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from _paths import SHARED_DATA as DATA  # noqa: E402

ROTSETS = ("step90", "any")


def _init() -> None:
    import cv2

    cv2.setNumThreads(1)


def run_plan(args: tuple) -> list[dict]:
    path, index, rotsets, comps, seed, method, options = args
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.registration import register
    from frslam_graph.registration.evaluation import iou_a
    from frslam_graph.registration.result import params_from_matrix

    try:
        plan = FloorPlan.load(path)
    except Exception as exc:  # noqa: BLE001 - a dev tool: count and move on
        return [{"case": Path(path).stem, "skip": f"load: {exc}"}]
    if len(plan.rooms) < 2:
        return [{"case": Path(path).stem, "skip": "one room"}]
    rows = []
    for rotset in rotsets:
        rng = np.random.default_rng([seed, index, ROTSETS.index(rotset)])
        dist = Distortion.random(rng, rotation=rotset, plan_bounds=plan.bounds)
        house = House.from_plan(plan, dist)
        t_flip, t_rot, *_ = params_from_matrix(dist.matrix)
        for comp in comps:
            rng_m = np.random.default_rng([seed, index, ROTSETS.index(rotset), comp])
            grid, explored = partial_map(house, comp / 100.0, rng_m, resolution=0.05)
            t0, c0 = time.perf_counter(), time.process_time()
            reg = register(plan, grid, method=method, **options)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            row = {
                "case": Path(path).stem,
                "index": index,
                "rooms": len(plan.rooms),
                "rotset": rotset,
                "comp": comp,
                "explored": len(explored),
                "ok": reg.ok,
                "reason": reg.reason,
                "wall_ms": wall * 1e3,
                "cpu_ms": cpu * 1e3,
                "score": reg.score,
                "ambiguity": reg.ambiguity,
            }
            if reg.ok:
                drot = (reg.rotation_deg - math.degrees(t_rot) + 180.0) % 360.0 - 180.0
                row.update(
                    flip_ok=reg.flipped == t_flip,
                    rot_ok=abs(drot) < 5.0,
                    rot_err=abs(drot),
                    iou_a=iou_a(plan, reg.matrix, dist.matrix),
                    delta=reg.details.get("delta_m", float("nan")),
                    fit=reg.details.get("fit", float("nan")),
                )
            else:
                row.update(flip_ok=False, rot_ok=False, rot_err=float("nan"), iou_a=0.0)
            rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plans", type=int, default=50)
    ap.add_argument("--offset", type=int, default=0)
    ap.add_argument("--completeness", type=int, nargs="+", default=[25, 50, 75, 100])
    ap.add_argument("--rotsets", nargs="+", default=list(ROTSETS), choices=ROTSETS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--method", default="mfr")
    ap.add_argument("--max-rooms", type=int, default=0, help="skip plans with more rooms (0: no limit)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--csv", type=Path)
    ap.add_argument(
        "--option", action="append", default=[], help="KEY=VALUE passed to register (python literal)"
    )
    args = ap.parse_args()
    import ast

    options = {}
    for kv in args.option:
        k, v = kv.split("=", 1)
        options[k] = ast.literal_eval(v)
    files = sorted((DATA / "floorplans" / "r2v").glob("*.txt"))
    order = np.random.default_rng(args.seed).permutation(len(files))
    picked = [files[i] for i in order[args.offset : args.offset + args.plans]]
    tasks = [
        (str(p), args.offset + i, args.rotsets, args.completeness, args.seed, args.method, options)
        for i, p in enumerate(picked)
    ]
    rows: list[dict] = []
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers, initializer=_init) as ex:
            for r in ex.map(run_plan, tasks):
                rows += r
    else:
        _init()
        for t in tasks:
            rows += run_plan(t)
    skipped = [r for r in rows if "skip" in r]
    rows = [r for r in rows if "skip" not in r]
    if args.max_rooms:
        rows = [r for r in rows if r["rooms"] <= args.max_rooms]
    groups = defaultdict(list)
    for r in rows:
        groups[(r["rotset"], r["comp"])].append(r)
    print(
        f"plans: {len(picked)} ({len(skipped)} skipped), cases: {len(rows)}, method: {args.method} {options}\n"
    )
    print(
        "| rotation | completeness | n | flip | rotation | IoU_a mean | IoU_a median | failed | median ms (wall / cpu) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for (rs, comp), g in sorted(groups.items()):
        flip = np.mean([r["flip_ok"] for r in g]) * 100
        rot = np.mean([r["rot_ok"] for r in g]) * 100
        iou = np.array([r["iou_a"] for r in g]) * 100
        fails = sum(not r["ok"] for r in g)
        wall = np.median([r["wall_ms"] for r in g])
        cpu = np.median([r["cpu_ms"] for r in g])
        print(
            f"| {rs} | {comp} % | {len(g)} | {flip:.1f} | {rot:.1f} | {iou.mean():.2f} | {np.median(iou):.2f} "
            f"| {fails} | {wall:.1f} / {cpu:.1f} |"
        )
    reasons = Counter(r["reason"].split(":")[0] for r in rows if not r["ok"])
    if reasons:
        print("\nfailures:", dict(reasons))
    wrong = [r for r in rows if r["ok"] and (not r["flip_ok"] or not r["rot_ok"])]
    if wrong:
        flagged = np.mean([r["ambiguity"] >= 0.9 for r in wrong]) * 100
        right = [r for r in rows if r["ok"] and r["flip_ok"] and r["rot_ok"]]
        print(
            f"\nwrong matches: {len(wrong)}, flagged ambiguous (>= 0.9): {flagged:.0f} %; "
            f"right ones flagged: {np.mean([r['ambiguity'] >= 0.9 for r in right]) * 100:.0f} %"
        )
    if args.csv:
        keys = sorted({k for r in rows for k in r})
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
