"""Loop closure on the real CARMEN logs: relation error (ACES) and speed (Markdown table).

For each log the streaming backend runs twice in the same process, timed alike: with loop
closure (the default config) and without (the baseline: odometry + graph only). Reported:

- ACES: relation-based error (Kümmerle et al. 2009, ``aces.relations``), mean ± std of the
  translation (m) and rotation (deg) errors, next to the published figures;
- every log: offline throughput as a multiple of the log's real time (incl. the final LM batch),
  per-scan latency of ``FRSlam.add`` (median, p99, max; wall clock and process CPU time, the latter
  robust to a machine shared with other jobs), loop closures accepted / candidates matched and
  the loop closer's CPU time per keyframe.

Loop-closure work is spread over the scans within ``loop_closure.budget_ms`` (estimated ms per
``add``; ``--budget-ms`` overrides it). ``--synchronous`` adds a run doing all of a keyframe's
loop-closure work inside its own ``add`` (the behaviour before the anytime scheduler).

Intel and FR079 have no relations in the shared data: they are timed only.

With relations, a row "wheel odometry as logged" (no scan matching at all) and a reference check
follow: about half of ACES's short reference relations differ from the logged wheel odometry by a
non-zero multiple of 5 cm along the heading (our estimate almost never does), the rest equal it.
The reference was made on a 5 cm grid seeded with the odometry, so its short relations carry up
to ±2.5 cm of quantisation, and the raw wheel odometry scores 0.037 m on them, about what
Cartographer reports over all relations: the published 0.0375 m is at the reference's own noise.

    .venv/bin/python tools/bench_aces.py [--logs aces intel fr079] [--no-baseline]
        [--budget-ms 8] [--synchronous]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from frslam_graph.datasets import open_recording

from frslam_graph.config import FRSlamConfig
from frslam_graph.metrics import load_relations, relation_error, relative_poses
from frslam_graph.pipeline import FRSlam

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "carmen"
LOGS = {"aces": "aces.clf.bz2", "intel": "intel.clf.bz2", "fr079": "fr079.clf.bz2"}
# Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM" (ICRA 2016), Table I (Graph Mapping:
# Kümmerle et al. 2009), as quoted in ../shared/data/README.md and the project issue.
PUBLISHED = {
    "aces": "Cartographer 0.0375 m (issue 5 target); Graph Mapping ≈ 0.04 m",
    "intel": "Cartographer 0.0229 ± 0.0239 m / 0.453 ± 1.335°; Graph Mapping 0.031 ± 0.026 m / 1.3 ± 4.7°",
    "fr079": "Cartographer 0.0452 ± 0.0354 m / 0.538 ± 0.718°; Graph Mapping 0.056 ± 0.042 m / 0.6 ± 0.6°",
}


def run(scans: list, loop_closure: bool, budget_ms: float | None = None, synchronous: bool = False) -> dict:
    lc_cfg: dict = {"enabled": loop_closure}
    if budget_ms is not None:
        lc_cfg["budget_ms"] = budget_ms
    if synchronous:  # everything in the keyframe's own add
        lc_cfg["budget_ms"] = lc_cfg["keyframe_budget_ms"] = 1e9
    cfg = FRSlamConfig().with_updates(loop_closure=lc_cfg)
    slam = FRSlam(cfg)
    n = len(scans)
    lat, cpu = np.empty(n), np.empty(n)
    t_start, c_start = time.perf_counter(), time.process_time()
    for i, scan in enumerate(scans):
        t0, c0 = time.perf_counter(), time.process_time()
        slam.add(scan)
        lat[i], cpu[i] = time.perf_counter() - t0, time.process_time() - c0
    slam.finish()
    wall, cpu_total = time.perf_counter() - t_start, time.process_time() - c_start
    duration = scans[-1].stamp - scans[0].stamp
    out = {
        "slam": slam,
        "trajectory": slam.trajectory(),
        "xrt": duration / wall,
        "xrt_cpu": duration / cpu_total,
        "lat": lat,
        "cpu": cpu,
        "keyframes": len(slam.keyframes()),
    }
    lc = slam.loop_closer
    if lc is not None:
        out["closures"] = lc.stats.accepted
        out["pruned"] = lc.stats.pruned
        out["attempts"] = lc.stats.attempts
        out["lc_ms_per_kf"] = 1e3 * lc.stats.cpu_seconds / max(lc.stats.keyframes, 1)
    return out


SHORT_S = 2.0  # relations spanning less than this (s): local accuracy, no loop closure involved
GRID = 0.05  # the step of the reference's along-heading quantisation (m), see reference_check


def fmt_rel(traj: np.ndarray, relations: Path) -> tuple[str, str, str]:
    """Relation error (all), rotation error (all) and translation error on the short relations."""
    rel = load_relations(relations)
    r = relation_error(traj, rel)
    s = relation_error(traj, rel[rel[:, 1] - rel[:, 0] < SHORT_S])
    return (
        f"{r.trans_mean:.4f} ± {r.trans_std:.4f}",
        f"{r.rot_mean:.3f} ± {r.rot_std:.3f}",
        f"{s.trans_mean:.4f}",
    )


def wheel_trajectory(scans: list) -> np.ndarray:
    """The log's own wheel odometry at the scan stamps, (N, 4): no scan matching at all."""
    return np.array([[s.stamp, *s.odom] for s in scans if s.odom is not None])


def _on_grid(d: np.ndarray) -> tuple[float, float]:
    """Fractions of ``d`` within 5 mm of 0 and of a non-zero multiple of GRID."""
    k = np.round(d / GRID)
    on = np.abs(d - GRID * k) < 0.005
    return float(np.mean(on & (k == 0))), float(np.mean(on & (k != 0)))


def reference_check(scans: list, relations: Path, estimate: np.ndarray) -> str:
    """How the short reference relations relate to the logged wheel odometry (a Markdown line).

    The along-heading difference ``d`` between a reference relation and the wheel odometry over
    the same stamps is either ~0 (the reference *is* the wheel odometry) or close to a non-zero
    multiple of 5 cm: the reference was made by a matcher on a 5 cm grid seeded with the wheel
    odometry. Its translations thus carry a quantisation error of up to ±2.5 cm, which bounds how
    low any continuous estimate's relation error can go on these relations. ``estimate`` (our
    trajectory) is the control: its differences from the wheel odometry are continuous.
    """
    rel = load_relations(relations)
    rel = rel[rel[:, 1] - rel[:, 0] < SHORT_S]
    wheel, ok = relative_poses(wheel_trajectory(scans), rel[:, 0], rel[:, 1])
    est, ok_e = relative_poses(estimate, rel[:, 0], rel[:, 1])
    ok &= ok_e
    same, stepped = _on_grid(rel[ok, 2] - wheel[ok, 0])  # along the heading: x in the first pose's frame
    c_same, c_stepped = _on_grid(est[ok, 0] - wheel[ok, 0])
    return (
        f"Reference check ({int(ok.sum())} relations < {SHORT_S:g} s), along the heading: "
        f"{100 * same:.0f} % of the reference relations equal the logged wheel odometry within "
        f"5 mm and {100 * stepped:.0f} % differ from it by a non-zero multiple of {100 * GRID:g} cm "
        f"(within 5 mm); for our estimate the same fractions are {100 * c_same:.0f} % and "
        f"{100 * c_stepped:.1f} %. The reference is quantised on a {100 * GRID:g} cm grid."
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=list(LOGS), choices=list(LOGS))
    ap.add_argument("--no-baseline", action="store_true", help="skip the run without loop closure")
    ap.add_argument("--budget-ms", type=float, default=None, help="loop_closure.budget_ms (default: config)")
    ap.add_argument(
        "--synchronous",
        action="store_true",
        help="add a run with all loop-closure work inside the keyframe's add (unbounded budget)",
    )
    args = ap.parse_args()

    rows, notes = [], []
    for name in args.logs:
        path = DATA / LOGS[name]
        if not path.exists():
            print(f"skipping {name}: {path} not found")
            continue
        scans = list(open_recording(path))
        relations = DATA / f"{name}.relations"
        run(scans[:500], True)  # warm-up (untimed): the first run in a process is slower
        budget = FRSlamConfig().loop_closure.budget_ms if args.budget_ms is None else args.budget_ms
        kf_budget = FRSlamConfig().loop_closure.keyframe_budget_ms
        variants = [
            (
                f"loop closure, budget {budget:g} ms ({min(budget, kf_budget):g} on keyframes)",
                True,
                budget,
                False,
            )
        ]
        if args.synchronous:
            variants.append(("loop closure, synchronous", True, None, True))
        if not args.no_baseline:
            variants.append(("no loop closure", False, None, False))
        first_traj = None
        for label, on, budget_ms, sync in variants:
            res = run(scans, on, budget_ms, sync)
            if first_traj is None:
                first_traj = res["trajectory"]
            trans = rot = short = "—"
            if relations.exists():
                trans, rot, short = fmt_rel(res["trajectory"], relations)
            rows.append(
                [
                    name,
                    label,
                    str(len(scans)),
                    str(res["keyframes"]),
                    trans,
                    rot,
                    short,
                    f"{res['xrt']:.1f} ({res['xrt_cpu']:.1f})",
                    f"{1e3 * np.median(res['lat']):.2f} / {1e3 * np.percentile(res['lat'], 99):.1f}"
                    f" / {1e3 * res['lat'].max():.0f}",
                    f"{1e3 * np.median(res['cpu']):.2f} / {1e3 * np.percentile(res['cpu'], 99):.1f}",
                    f"{res['closures']} / {res['pruned']} / {res['attempts']}" if on else "—",
                    f"{res['lc_ms_per_kf']:.1f}" if on else "—",
                ]
            )
        if relations.exists():  # the floor the reference allows: the log's own odometry
            trans, rot, short = fmt_rel(wheel_trajectory(scans), relations)
            rows.append(
                [name, "wheel odometry as logged", str(len(scans)), "—", trans, rot, short] + ["—"] * 5
            )
            notes.append(reference_check(scans, relations, first_traj))
    head = [
        "log",
        "run",
        "scans",
        "keyframes",
        "relation error trans (m)",
        "rot (deg)",
        f"trans, relations < {SHORT_S:g} s",
        "× real time wall (CPU)",
        "latency wall median / p99 / max (ms)",
        "CPU median / p99 (ms)",
        "closures accepted / later pruned / matched",
        "LC CPU ms / keyframe",
    ]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print()
    for n in notes:
        print(n)
        print()
    print("Published relation errors (mean ± std), Hess et al. ICRA 2016 Table I:")
    for name in args.logs:
        print(f"- {name}: {PUBLISHED[name]}")


if __name__ == "__main__":
    main()
