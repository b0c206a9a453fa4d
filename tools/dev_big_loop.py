"""One big corridor loop with a large odometry drift: does the loop closer close it, and where
did it look? (issue 19: a Killian-Court-sized drift; session 17.)

    .venv/bin/python tools/dev_big_loop.py --bias 0.4 --scale 0.03
    .venv/bin/python tools/dev_big_loop.py --bias 0.4 --config '{"loop_closure": {"max_candidates": 6}}'

A 40 x 24 m rectangle of 2.5-m corridors with 26 small boxes on the walls (irregular, seeded),
driven once round and 12 m on at 1 m/s (5 Hz, 720 beams, 10 m range: 733 scans). The odometry
between-factors get a heading bias (deg per m) and a scale error, the scans stay true, as
``tests/test_loop_closure.py`` drifts its loops. Prints the end and RMS position error, each
closure and pending closure with its error against the truth (relative pose of the two
keyframes), and the candidate searches of the keyframes back at the start (``--after`` s) whose
reference is in the start corridor: how far the true pose lay from the search centre.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synthetic_world import corridor_loop, route, scans_along  # noqa: E402

from frslam_graph.loop_closure import closer as closer_module  # noqa: E402
from frslam_graph.se2 import between, compose, wrap  # noqa: E402
from frslam_graph.slam import FRSlam  # noqa: E402

WIDTH, HEIGHT, CORRIDOR = 40.0, 24.0, 2.5  # m
RATE = 5.0  # Hz


def big_loop_world(seed: int = 3) -> np.ndarray:
    """Wall segments (K, 4: x0, y0, x1, y1) of the corridor rectangle and its 26 wall boxes."""
    return corridor_loop(WIDTH, HEIGHT, 26, seed, CORRIDOR)


def inject_drift(slam: FRSlam, heading_deg_per_m: float, scale: float) -> None:
    """Odometry between-factors get a heading bias per metre and a scale error (scans stay true)."""
    process = slam.odometry.process
    bias = np.deg2rad(heading_deg_per_m)

    def drifting(*args, **kwargs):
        res = process(*args, **kwargs)
        if res is not None and res.between is not None:
            b = np.asarray(res.between, float)
            d = float(np.hypot(b[0], b[1]))
            res = dataclasses.replace(
                res, between=np.array([b[0] * (1 + scale), b[1] * (1 + scale), b[2] + bias * d])
            )
        return res

    slam.odometry.process = drifting


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bias", type=float, default=0.4, help="deg of heading per m travelled")
    ap.add_argument("--scale", type=float, default=0.03, help="translation scale error (0.03 = 3 %%)")
    ap.add_argument("--config", default="{}", help="FRSlam config overrides (JSON)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the wall boxes (another world)")
    ap.add_argument("--after", type=float, default=120.0, help="s; searches of keyframes after this")
    args = ap.parse_args()

    truth = route(
        [(2.0, 0.0), (WIDTH, 0.0), (WIDTH, HEIGHT), (0.0, HEIGHT), (0.0, 0.0), (14.0, 0.0)],
        speed=1.0,
        rate=RATE,
    )
    ranges, amin, inc = scans_along(big_loop_world(args.seed), truth, max_range=10.0)
    slam = FRSlam({"odometry": {"max_range": 10.0}, **json.loads(args.config)})
    inject_drift(slam, args.bias, args.scale)

    # record each candidate search: (job, search centre, guess) -- the library is not changed
    searches: list[tuple] = []
    search_window = closer_module.LoopCloser._search_window

    def recorded(self, job, guess):
        centre, win = search_window(self, job, guess)
        searches.append((job, np.array(centre, float), win))
        return centre, win

    closer_module.LoopCloser._search_window = recorded
    c0 = time.process_time()
    for i in range(len(truth)):
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, None)
    slam.finish()
    cpu = time.process_time() - c0
    closer_module.LoopCloser._search_window = search_window

    est = slam.trajectory()[:, 1:]
    world = np.array([compose(truth[0, 1:], p) for p in est])
    err = np.hypot(*(world[:, :2] - truth[:, 1:3]).T)
    kfs = slam.context.keyframes()

    def true_pose(k: int) -> np.ndarray:
        return truth[int(round(kfs[k].stamp * RATE)), 1:]

    kinds: dict[str, int] = {}
    for e in slam.log:
        kinds[e.kind] = kinds.get(e.kind, 0) + 1
    print(
        f"seed {args.seed}, bias {args.bias} deg/m, scale {args.scale}: {len(truth)} scans, error RMS {np.sqrt(np.mean(err**2)):.2f} m, "
        f"end {err[-1]:.2f} m, max {err.max():.2f} m; closures in the graph {len(slam.loop_closer.closures)}; "
        f"{ {k: v for k, v in kinds.items() if k.startswith('loop')} }; CPU {cpu:.0f} s"
    )
    for e in slam.log:
        if e.kind in ("loop_pending", "loop_closure", "loop_removed"):
            q, c = e.keyframe, e.data["reference"]
            line = f"  {e.kind} {q} ({kfs[q].stamp:.1f} s) on {c} ({kfs[c].stamp:.1f} s)"
            if "relative" in e.data:
                d = between(between(true_pose(c), true_pose(q)), np.asarray(e.data["relative"]))
                line += f": correction {np.round(e.data['correction'], 2).tolist()}, off the truth {np.hypot(d[0], d[1]):.2f} m / {np.rad2deg(wrap(d[2])):.0f} deg"
            print(line)
    print(f"searches of keyframes after {args.after} s on the start corridor (x < 16 m, y < 2 m):")
    for job, centre, win in searches:
        tq, tc = kfs[job.query].stamp, kfs[job.reference].stamp
        p = true_pose(job.reference)
        if tq < args.after or p[0] > 16.0 or abs(p[1]) > 2.0:
            continue
        t = between(p, true_pose(job.query))
        off = np.hypot(*(t[:2] - centre[:2]))
        print(
            f"  {job.query} ({tq:.1f} s) vs {job.reference} ({tc:.1f} s): radius {job.radius:.1f} m, "
            f"{'pending check' if job.predicted is not None else 'candidate'}, centre {np.round(centre, 1).tolist()} +- {win:.1f} m; "
            f"truth {np.round(t, 1).tolist()}: {off:.1f} m / {np.rad2deg(wrap(t[2] - centre[2])):.0f} deg from the centre"
        )


if __name__ == "__main__":
    main()
