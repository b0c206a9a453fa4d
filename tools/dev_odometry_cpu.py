"""The scan odometry alone over a real log: CPU seconds of ``prepare`` and of ``process``
(``time.process_time``, the mmap threshold pinned as ``run_recording`` pins it), and optionally
its CPU by stage (exclusive seconds of wrapped methods, with their calls per scan) or a cProfile;
the results of every scan saved for an identity check between two checkouts.

    .venv/bin/python tools/dev_odometry_cpu.py fr079 --out /tmp/a.npz           # CPU, results
    .venv/bin/python tools/dev_odometry_cpu.py fr079 --stages                    # CPU by stage
    .venv/bin/python tools/dev_odometry_cpu.py fr079 --profile /tmp/odo.prof     # cProfile (CPU timer)
    .venv/bin/python tools/dev_odometry_cpu.py --same /tmp/a.npz /tmp/b.npz      # bit-identical?
"""

from __future__ import annotations

import argparse
import cProfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402

#: (owner module or class path, attribute, stage label) of the wrapped calls of ``--stages``
_STAGES = [
    ("scan_odometry.ScanOdometry", "process", "process: glue"),
    ("scan_odometry.ScanOdometry", "_align", "align: glue"),
    ("scan_odometry.ScanOdometry", "_kiss_align", "KISS-ICP alignment (C++)"),
    ("scan_odometry.ScanOdometry", "_turned", "turned seeds: glue"),
    ("scan_odometry.ScanOdometry", "_refine", "refinement: glue"),
    ("scan_odometry.ScanOdometry", "_local_map", "local map: cell means + LineMap"),
    ("scan_odometry.ScanOdometry", "_commit", "commit (KISS-ICP map update)"),
    ("scan_odometry.ScanOdometry", "_clock", "scan clock"),
    ("scan_odometry.ScanOdometry", "_new_keyframe", "keyframes"),
    ("scan_odometry", "icp_point_to_line", "refinement ICP: loop"),
    ("submap_matching.LineMap", "correspondences", "refinement ICP: first k-d query"),
    ("submap_matching._NearestCandidates", "exact_nearest_offsets", "refinement ICP: nearest per iteration"),
    ("submap_matching.LineMap", "line_normals", "refinement ICP: normals"),
    ("submap_matching.LineMap", "inlier_fractions", "LineMap inlier fractions"),
    ("scan_odometry", "_inlier_fractions", "two-seed test (KISS-ICP map)"),
    ("scan_odometry.MotionEKF", "predict", "EKF"),
    ("scan_odometry.MotionEKF", "innovation", "EKF"),
    ("scan_odometry.MotionEKF", "update", "EKF"),
]


def _wrap_stages() -> tuple[dict[str, float], dict[str, int]]:
    """Wrap :data:`_STAGES` so that each charges its exclusive process CPU time; returns the
    (seconds, calls) accumulators."""
    import importlib

    seconds: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    nested: list[float] = []

    def timed(f: Callable, label: str) -> Callable:
        def g(*a, **k):
            t0 = time.process_time()
            nested.append(0.0)
            try:
                return f(*a, **k)
            finally:
                dt = time.process_time() - t0
                seconds[label] += dt - nested.pop()
                calls[label] += 1
                if nested:
                    nested[-1] += dt

        return g

    for path, attr, label in _STAGES:
        mod, _, cls = path.partition(".")
        package = "odometry" if mod == "scan_odometry" else "loop_closure"
        owner = importlib.import_module(f"frslam_graph.{package}.{mod}")
        owner = getattr(owner, cls) if cls else owner
        setattr(owner, attr, timed(getattr(owner, attr), label))
    return seconds, calls


def _same(a_path: Path, b_path: Path) -> bool:
    """Whether two ``--out`` files hold the same results bit for bit (NaN equal to NaN)."""
    a, b = np.load(a_path), np.load(b_path)
    same = True
    for key in a.files:
        eq = a[key].shape == b[key].shape and np.array_equal(a[key], b[key], equal_nan=True)
        print(key, "identical" if eq else "DIFFERENT")
        same &= eq
    print("IDENTICAL" if same else "DIFFERENT", len(a["pose"]), "scans")
    return same


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", choices=sorted(LOGS))
    ap.add_argument("--n", type=int, help="the first n scans only")
    ap.add_argument("--out", type=Path, help="save every scan's results here (.npz)")
    ap.add_argument("--stages", action="store_true", help="CPU by stage (wrapped calls)")
    ap.add_argument("--profile", type=Path, help="write a cProfile (process CPU timer) of process here")
    ap.add_argument("--same", nargs=2, type=Path, metavar=("A", "B"), help="compare two --out files")
    args = ap.parse_args()
    if args.same:
        raise SystemExit(0 if _same(*args.same) else 1)
    if args.log is None:
        ap.error("a log, or --same A B")
    from frslam_graph.datasets import open_recording

    from frslam_graph.config import FRSlamConfig
    from frslam_graph.odometry.scan_odometry import ScanOdometry
    from frslam_graph.offline import _pin_mmap_threshold, body_points

    _pin_mmap_threshold()
    scans = []
    for scan in open_recording(DATA / LOGS[args.log][0]):
        if args.n is not None and len(scans) >= args.n:
            break
        scans.append(
            (scan.stamp, np.ascontiguousarray(body_points(scan.points, scan.sensor_offset)[0]), scan.odom)
        )
    seconds, calls = _wrap_stages() if args.stages else ({}, {})
    odo = ScanOdometry(FRSlamConfig().odometry)
    c0 = time.process_time()
    prepared = [odo.prepare(points) for _, points, _ in scans]
    c1 = time.process_time()
    prof = cProfile.Profile(time.process_time) if args.profile else None
    if prof is not None:
        prof.enable()
    results = [odo.process(stamp, ps, wheel) for (stamp, _, wheel), ps in zip(scans, prepared, strict=True)]
    if prof is not None:
        prof.disable()
        prof.dump_stats(args.profile)
    c2 = time.process_time()
    n = len(scans)
    print(
        f"{args.log}: {n} scans, CPU s: prepare {c1 - c0:.2f}, process {c2 - c1:.2f} ({1e3 * (c2 - c1) / n:.3f} ms a scan)"
    )
    for label, s in sorted(seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {label:42s} {s:7.2f} s {1e3 * s / n:7.3f} ms/scan, calls/scan {calls[label] / n:.2f}")
    if args.out is not None:
        np.savez(
            args.out,
            pose=np.array([r.pose for r in results]),
            relative=np.array([r.relative for r in results]),
            covariance=np.array([r.covariance for r in results]),
            between=np.array([np.full(3, np.nan) if r.between is None else r.between for r in results]),
            flags=np.array(
                [
                    [r.keyframe, r.is_keyframe, r.degenerate, r.fallback, r.odom_jump, r.dropped]
                    + [r.n_points, r.icp_rejected, r.period]
                    for r in results
                ],
                dtype=float,
            ),
            stats=np.array([getattr(odo.stats, f) for f in odo.stats.__slots__], dtype=float),
        )


if __name__ == "__main__":
    main()
