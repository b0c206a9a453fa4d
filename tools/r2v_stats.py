"""Load every R2V plan of a folder and print the acceptance table (Markdown).

    python tools/r2v_stats.py [../shared/data/floorplans/r2v] [--workers 2] [--failures 10]

Reports how many plans load, how many give >= 2 rooms, median rooms vs median room labels per
plan, how many labelled rooms were not found, the wall-repair strategy used, failures by reason
and the median load time. Baseline in the same run: the same plans built with the repair steps
switched off (walls as drawn), so the table shows what the repair buys.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import Counter
from multiprocessing import Pool
from pathlib import Path

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan.r2v import R2VOptions, build_r2v, load_r2v_detailed, parse_r2v

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "floorplans" / "r2v"


def _one(path: str) -> dict:
    t0 = time.perf_counter()
    try:
        res = load_r2v_detailed(path)
    except FloorPlanError as exc:
        return {"path": path, "ok": False, "reason": exc.message.split(" (")[0], "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - counted as a crash, the loader must never do this
        return {"path": path, "ok": False, "reason": f"CRASH {type(exc).__name__}", "error": str(exc)}
    dt = time.perf_counter() - t0
    # baseline: no wall repair (walls as drawn, one pass)
    t1 = time.perf_counter()
    try:
        base = build_r2v(parse_r2v(path), R2VOptions(repair=False))
        base_found = base.n_found
    except FloorPlanError:
        base_found = 0
    dt_base = time.perf_counter() - t1
    missing = [f"{lab.type}@line{lab.line}" for lab in res.labels if lab.room is None]
    return {
        "path": path,
        "ok": True,
        "rooms": len(res.plan.rooms),
        "labels": res.n_labels,
        "found": res.n_found,
        "base_found": base_found,
        "missing": missing,
        "strategy": res.strategy,
        "time": dt,
        "time_base": dt_base,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", type=Path, default=DEFAULT)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--failures", type=int, default=10, help="list this many failing plans")
    args = ap.parse_args()
    files = sorted(str(p) for p in args.folder.glob("*.txt"))
    if not files:
        raise SystemExit(f"no .txt plans in {args.folder}")
    t0 = time.perf_counter()
    with Pool(args.workers) as pool:
        rows = list(pool.imap(_one, files, chunksize=8))
    wall = time.perf_counter() - t0
    ok = [r for r in rows if r["ok"]]
    n = len(rows)
    all_found = [r for r in ok if r["found"] == r["labels"]]
    base_all = [r for r in ok if r["base_found"] == r["labels"]]
    pct = lambda k: f"{100.0 * k / n:.1f} %"  # noqa: E731
    print(f"## R2V plans: {args.folder} ({n} files, {args.workers} workers, {wall:.1f} s)\n")
    print("| measure | value |")
    print("|---|---|")
    print(f"| plans | {n} |")
    print(f"| load without error | {len(ok)} ({pct(len(ok))}) |")
    print(f"| load with every labelled room found | {len(all_found)} ({pct(len(all_found))}) |")
    print(f"| baseline, no wall repair: every labelled room found | {len(base_all)} ({pct(len(base_all))}) |")
    print(
        f"| plans with >= 2 rooms | {sum(r['rooms'] >= 2 for r in ok)} ({pct(sum(r['rooms'] >= 2 for r in ok))}) |"
    )
    if ok:
        print(f"| median rooms per plan | {statistics.median(r['rooms'] for r in ok):g} |")
        print(f"| median room labels per plan | {statistics.median(r['labels'] for r in ok):g} |")
        n_lab = sum(r["labels"] for r in ok)
        n_miss = sum(r["labels"] - r["found"] for r in ok)
        n_miss_base = sum(r["labels"] - r["base_found"] for r in ok)
        print(f"| labelled rooms (all plans) | {n_lab} |")
        print(f"| labelled rooms NOT found | {n_miss} (baseline without repair: {n_miss_base}) |")
        t = statistics.median(r["time"] for r in ok)
        tb = statistics.median(r["time_base"] for r in ok)
        print(
            f"| median load time per plan | {1000 * t:.1f} ms ({t / tb:.2f} x the no-repair baseline, {1000 * tb:.1f} ms) |"
        )
    print("\n| strategy (first that enclosed every label) | plans |")
    print("|---|---|")
    for strat, k in Counter(r["strategy"] for r in ok).most_common():
        print(f"| {strat} | {k} |")
    fails = Counter(r["reason"] for r in rows if not r["ok"])
    fails.update("labelled room not found" for r in ok if r["found"] < r["labels"])
    print("\n| failure | plans |")
    print("|---|---|")
    for reason, k in fails.most_common() or [("none", 0)]:
        print(f"| {reason} | {k} |")
    bad = [r for r in rows if not r["ok"] or r["found"] < r["labels"]]
    if bad and args.failures:
        print("\nFailing plans:")
        for r in bad[: args.failures]:
            detail = r["error"] if not r["ok"] else "missing " + ", ".join(r["missing"])
            print(f"- {Path(r['path']).name}: {detail}")


if __name__ == "__main__":
    main()
