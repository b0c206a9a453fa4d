"""Latency and accuracy of scan-to-plan relocalisation (720-beam scans, two-room plan).

Prints a Markdown table: median / p90 latency and error of :class:`Relocaliser` (correlative
branch-and-bound-lite search + LM), next to a baseline timed in the same run: an exhaustive
search over the fine grid of the same window (no pruning) followed by the same refinement.

    python tools/bench_relocalisation.py --trials 40
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synthetic_world import cast  # noqa: E402
from test_relocalisation import two_rooms  # noqa: E402

from frslam_graph.localisation.relocalisation import Relocaliser, subsample  # noqa: E402


def exhaustive(reloc: Relocaliser, points: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Baseline: every pose of the fine grid (window ±0.75 m / ±15°, 0.05 m / 1°), then LM."""
    p = reloc.params
    pts = subsample(points, p.voxel, p.max_points)
    search = pts[np.linspace(0, len(pts) - 1, min(len(pts), p.search_points)).round().astype(np.intp)]
    xs = prior[0] + np.arange(-0.75, 0.7501, 0.05)
    ys = prior[1] + np.arange(-0.75, 0.7501, 0.05)
    ths = prior[2] + np.deg2rad(np.arange(-15, 15.01, 1.0))
    poses = np.stack(np.meshgrid(xs, ys, ths, indexing="ij"), -1).reshape(-1, 3)
    costs = np.concatenate(
        [reloc._pose_costs(search, poses[i : i + 2048], p.truncation) for i in range(0, len(poses), 2048)]
    )
    return reloc._refine(pts, poses[int(np.argmin(costs))])[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=40)
    args = ap.parse_args()
    plan, world = two_rooms()
    reloc = Relocaliser(plan)
    rng = np.random.default_rng(0)
    cases = []
    for _ in range(args.trials):
        truth = np.array([rng.uniform(1, 9), rng.uniform(1, 3), rng.uniform(-np.pi, np.pi)])
        r, amin, inc = cast(world, truth, 720, 10.0, 0.01, rng)
        ang = amin + inc * np.arange(720)
        ok = np.isfinite(r)
        pts = np.column_stack((r * np.cos(ang), r * np.sin(ang)))[ok]
        prior = truth + np.array(
            [rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), np.deg2rad(rng.uniform(-10, 10))]
        )
        cases.append((pts, prior, truth))
    rows = {}
    for name, fn in (
        ("Relocaliser (BnB-lite + LM)", lambda pts, prior: reloc.relocalise(pts, prior).pose),
        ("baseline: exhaustive fine grid + LM", lambda pts, prior: exhaustive(reloc, pts, prior)),
    ):
        ts, cpu, errs = [], [], []
        for pts, prior, truth in cases:
            t0, c0 = time.perf_counter(), time.process_time()
            pose = fn(pts, prior)
            ts.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            errs.append(np.hypot(*(pose[:2] - truth[:2])))
        rows[name] = (
            np.median(ts) * 1e3,
            np.percentile(ts, 90) * 1e3,
            np.median(cpu) * 1e3,
            np.median(errs),
            np.max(errs),
        )
    base = rows["baseline: exhaustive fine grid + LM"][0]
    print(f"{args.trials} scans of 720 beams, prior off by up to 0.5 m / 10 deg")
    print("| method | median ms | p90 ms | median CPU ms | speed-up | median error m | max error m |")
    print("|---|---|---|---|---|---|---|")
    for name, (med, p90, cmed, emed, emax) in rows.items():
        print(
            f"| {name} | {med:.2f} | {p90:.2f} | {cmed:.2f} | {base / med:.1f}x | {emed:.4f} | {emax:.4f} |"
        )


if __name__ == "__main__":
    main()
