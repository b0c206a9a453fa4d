#!/usr/bin/env python3
"""MFR registration CPU on captured inputs: two source trees timed case by case, alternately.

``capture`` runs the benchmark's own case builders (``bench_real.style_rows``, or
``bench_registration``'s quick set: R2V ``r2v_cases`` and PRBonn ``prbonn_cases``) with
``frslam_graph.registration.register`` wrapped, and pickles every (plan, grid) it is called with
(one pickle keeps the plans' identity, so the plan-side memo of ``register_mfr`` hits as in the
benchmark). ``time`` starts one worker process per source tree (``--a`` / ``--b``: a folder
holding ``frslam_graph``, put first on ``PYTHONPATH``), sends them the cases one by one, A then B
on even cases and B then A on odd ones, for ``--rounds`` rounds; each worker measures the CPU
time of its ``register`` call (``time.process_time``: BLAS or OpenCV threads count) and returns
a digest of the result (every field of the Registration and its details but the times, pickled).
Prints the median CPU per registration of each tree (per-case minimum over the rounds) by group,
and how many results differ. ``profile`` runs cProfile over the cases in this process;
``stages`` times the registration's stage functions (:data:`STAGES`, inclusive process CPU)
per registration, split by whether the wide search ran.

    .venv/bin/python tools/dev_reg_cpu.py capture --set styles --out /tmp/styles.pkl
    .venv/bin/python tools/dev_reg_cpu.py capture --set quick --out /tmp/quick.pkl
    git archive main | tar -x -C /tmp/main_src   # then move datasets/ and factors/ into its frslam_graph/
    nice -n 10 .venv/bin/python tools/dev_reg_cpu.py time /tmp/styles.pkl --a /tmp/main_src --b . --rounds 2
    .venv/bin/python tools/dev_reg_cpu.py profile /tmp/styles.pkl --limit 60 --top 40
    .venv/bin/python tools/dev_reg_cpu.py stages /tmp/quick.pkl --group quick-r2v
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def capture(which: str, out: Path, n_plans: int, seed: int, max_rooms: int | None) -> int:
    """Pickle the (label, plan, grid) of every MFR registration of the benchmark set ``which``."""
    from _paths import SHARED_DATA

    import frslam_graph.registration as reg_pkg

    cases: list[tuple[str, Any, Any]] = []
    real = reg_pkg.register
    label = {"set": which}

    def record(plan, grid, *, method="mfr", **options):
        if method == "mfr" and (max_rooms is None or len(plan.rooms) <= max_rooms):
            cases.append((f"{label['set']}/{len(plan.rooms)}", plan, grid))
        return real(plan, grid, method=method, **options)

    reg_pkg.register = record
    try:
        if which == "styles":
            from bench_real import style_rows

            style_rows(SHARED_DATA, n_plans, seed, method="mfr")
        elif which == "quick":
            from bench_registration import ROTSETS, prbonn_cases, r2v_cases, select_plans

            plans, _ = select_plans(SHARED_DATA, 20, seed)
            for i, p in enumerate(plans):
                for rs in ROTSETS:
                    label["set"] = "quick-r2v"
                    r2v_cases(
                        {
                            "path": str(p),
                            "plan_index": i,
                            "rotset": rs,
                            "completeness": [25, 50, 75, 100],
                            "methods": ["mfr"],
                            "seed": seed,
                        }
                    )
            for k in range(3):
                for rs in ROTSETS:
                    label["set"] = "quick-prbonn"
                    prbonn_cases(
                        {
                            "data": str(SHARED_DATA),
                            "index": k,
                            "rotset": rs,
                            "completeness": [25, 50, 75, 100],
                            "methods": ["mfr"],
                            "seed": seed,
                        }
                    )
        else:
            raise SystemExit(f"unknown set {which!r}")
    finally:
        reg_pkg.register = real
    out.write_bytes(pickle.dumps(cases, protocol=pickle.HIGHEST_PROTOCOL))
    print(f"{len(cases)} cases -> {out}", file=sys.stderr)
    return 0


def digest(reg: Any) -> str:
    """A hash of every field of a Registration and its details but the times (pickled bytes)."""
    d = dict(vars(reg))
    d.pop("time_s", None)
    d["details"] = {k: v for k, v in reg.details.items() if not k.startswith("time_")}
    return hashlib.sha1(pickle.dumps(d, protocol=4)).hexdigest()


def worker(path: Path) -> int:
    """Serve ``run INDEX`` lines on stdin: register that case, answer ``CPU_S DIGEST``."""
    import cv2

    from frslam_graph.registration import register

    cv2.setNumThreads(1)  # as the benchmark's workers
    cases = pickle.loads(path.read_bytes())
    print(f"ready {len(cases)}", flush=True)
    for line in sys.stdin:
        i = int(line.split()[1])
        _, plan, grid = cases[i]
        c0 = time.process_time()
        reg = register(plan, grid, method="mfr")
        cpu = time.process_time() - c0
        print(f"{cpu:.6f} {digest(reg)}", flush=True)
    return 0


def _start(src: Path, path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(src.resolve()), PYTHONDONTWRITEBYTECODE="1")
    p = subprocess.Popen(
        [sys.executable, __file__, "worker", str(path)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd="/",
    )
    assert p.stdout is not None
    head = p.stdout.readline()
    if not head.startswith("ready"):
        raise SystemExit(f"worker for {src} did not start: {head!r}")
    return p


def _ask(p: subprocess.Popen, i: int) -> tuple[float, str]:
    assert p.stdin is not None and p.stdout is not None
    p.stdin.write(f"run {i}\n")
    p.stdin.flush()
    cpu, dig = p.stdout.readline().split()
    return float(cpu), dig


def time_trees(path: Path, a: Path, b: Path, rounds: int, limit: int | None, max_rooms: int) -> int:
    """Alternate the two trees case by case; print medians and the differing results."""
    path, a, b = path.resolve(), a.resolve(), b.resolve()  # the workers run in /
    cases = pickle.loads(path.read_bytes())
    labels = [c[0] for c in cases][:limit]
    n = len(labels)
    cpu = np.full((2, rounds, n), np.nan)
    digs: list[list[set[str]]] = [[set() for _ in range(n)] for _ in range(2)]
    for r in range(rounds):  # fresh workers per round: each replays the sequence (plan memo) alike
        procs = [_start(a, path), _start(b, path)]
        for i in range(n):
            for w in (0, 1) if (i + r) % 2 == 0 else (1, 0):
                c, d = _ask(procs[w], i)
                cpu[w, r, i] = c
                digs[w][i].add(d)
        for p in procs:
            p.stdin.close()
            p.wait()
        print(
            f"round {r + 1}: A {1000 * np.median(cpu[0, r]):.1f} ms, B {1000 * np.median(cpu[1, r]):.1f} ms (medians)",
            file=sys.stderr,
        )
    best = np.min(cpu, axis=1)  # per case, min over rounds
    groups: dict[str, list[int]] = {}
    for i, lab in enumerate(labels):
        s, rooms = lab.split("/")
        tag = f"{s}, plans <= {max_rooms} rooms" if int(rooms) <= max_rooms else f"{s}, > {max_rooms} rooms"
        groups.setdefault(tag, []).append(i)
    print(
        f"| {path.name}: median CPU per registration (ms) | n | A rounds | B rounds | A (min of rounds) | B | per case B/A, median | total A -> B (s) |"
    )
    print("|---|---:|---|---|---:|---:|---:|---|")
    for tag, idx in groups.items():
        ra = ", ".join(f"{1000 * np.median(cpu[0, r, idx]):.1f}" for r in range(rounds))
        rb = ", ".join(f"{1000 * np.median(cpu[1, r, idx]):.1f}" for r in range(rounds))
        print(
            f"| {tag} | {len(idx)} | {ra} | {rb} | {1000 * np.median(best[0, idx]):.1f} | "
            f"{1000 * np.median(best[1, idx]):.1f} | {np.median(best[1, idx] / best[0, idx]):.3f} | "
            f"{best[0, idx].sum():.2f} -> {best[1, idx].sum():.2f} |"
        )
    unstable = [i for i in range(n) if len(digs[0][i]) > 1 or len(digs[1][i]) > 1]
    differ = [i for i in range(n) if digs[0][i] != digs[1][i]]
    print(
        f"\nresults differing A vs B: {len(differ)} of {n} {differ[:20]}; not repeatable within a tree: {len(unstable)}"
    )
    return 1 if differ else 0


def profile(path: Path, limit: int | None, top: int, sort: str) -> int:
    """cProfile of the registrations of the first ``limit`` cases in this process."""
    import cProfile
    import pstats

    import cv2

    from frslam_graph.registration import register

    cv2.setNumThreads(1)
    cases = pickle.loads(path.read_bytes())[:limit]
    pr = cProfile.Profile(time.process_time)
    c0 = time.process_time()
    pr.enable()
    for _, plan, grid in cases:
        register(plan, grid, method="mfr")
    pr.disable()
    total = time.process_time() - c0
    print(f"{len(cases)} registrations, {total:.2f} s CPU under the profiler")
    pstats.Stats(pr).sort_stats(sort).print_stats(top)
    return 0


# (module, function) pairs timed by ``stages``: the registration's stages and their main parts
STAGES = (
    ("frslam_graph.registration.mfr.register", "observe_map"),
    ("frslam_graph.registration.mfr.register", "_prepared_entry"),
    ("frslam_graph.registration.mfr.register", "_subsets"),
    ("frslam_graph.registration.mfr.coarse", "coarse_hypotheses"),
    ("frslam_graph.registration.mfr.coarse", "local_search"),
    ("frslam_graph.registration.mfr.coarse", "coarse_scores"),
    ("frslam_graph.registration.mfr.coarse", "search"),
    ("frslam_graph.registration.mfr.coarse", "wide_search"),
    ("frslam_graph.registration.mfr.fine", "choose_distinct"),
    ("frslam_graph.registration.mfr.fine", "screen"),
    ("frslam_graph.registration.mfr.fine", "refine_from"),
    ("frslam_graph.registration.mfr.fine", "refine_from_many"),  # session 27: the fits together
    ("frslam_graph.registration.mfr.fine", "structure_key"),
    ("frslam_graph.registration.mfr.fine", "placed_rooms_iou"),
    ("frslam_graph.registration.mfr.fine", "wall_precision_recall"),
    ("frslam_graph.registration.mfr.fine", "polish_scales"),
    ("frslam_graph.registration.mfr.fine", "polish_scales_many"),
    ("frslam_graph.registration.mfr.register", "_ambiguity"),
    ("frslam_graph.registration.mfr.register", "_final"),
    ("frslam_graph.registration.mfr.register", "_drawing_gate"),
    ("frslam_graph.registration.mfr.register", "_alternatives"),
    ("frslam_graph.registration.mfr.register", "_merge"),
)


def stages(path: Path, limit: int | None, max_rooms: int, group: str | None) -> int:
    """Per-stage CPU (``time.process_time``, inclusive of what a stage calls) of the registrations
    of a capture in this process: the stage functions of :data:`STAGES` wrapped with timers
    (every module's name for them); mean and median per registration over the cases of
    ``group`` (a capture label's set, e.g. ``quick-r2v``) on plans of at most ``max_rooms``."""
    import functools
    import importlib

    import cv2

    from frslam_graph.registration import register

    cv2.setNumThreads(1)
    acc: dict[str, float] = {}
    calls: dict[str, int] = {}
    depth = {"on": {}}

    def timed(name: str, fn):
        @functools.wraps(fn)
        def run(*a, **k):
            if depth["on"].get(name):  # recursion / re-entry: the outer call times it
                return fn(*a, **k)
            depth["on"][name] = True
            c0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                acc[name] = acc.get(name, 0.0) + time.process_time() - c0
                calls[name] = calls.get(name, 0) + 1
                depth["on"][name] = False

        return run

    mods = [importlib.import_module(m) for m in {m for m, _ in STAGES}]
    for m, f in STAGES:
        orig = getattr(importlib.import_module(m), f, None)
        if orig is None:  # a stage function the tree does not have (an older one)
            continue
        w = timed(f, orig)
        for mod in mods:  # every module's reference (``from ... import`` copies)
            if getattr(mod, f, None) is orig:
                setattr(mod, f, w)
    cases = pickle.loads(path.read_bytes())[:limit]
    rows: list[dict[str, float]] = []
    for lab, plan, grid in cases:
        acc.clear()
        calls.clear()
        c0 = time.process_time()
        reg = register(plan, grid, method="mfr")
        total = time.process_time() - c0
        s, rooms = lab.split("/")
        if int(rooms) > max_rooms or (group is not None and s != group):
            continue
        row = dict(acc)
        row["total"] = total
        row["_wide"] = float(reg.details.get("wide_searched", False))
        row.update({f"#{k}": float(v) for k, v in calls.items()})
        rows.append(row)
    keys = ["total"] + [f for _, f in STAGES if any(f in r for r in rows)]
    n = len(rows)
    wide = [r for r in rows if r["_wide"]]
    print(f"{n} registrations ({len(wide)} with the wide search); CPU ms per registration, inclusive")
    print("| stage | mean | median | mean calls | mean, no wide search | mean, wide search |")
    print("|---|---:|---:|---:|---:|---:|")
    for k in keys:
        v = np.array([r.get(k, 0.0) for r in rows])
        c = np.array([r.get(f"#{k}", 0.0) for r in rows])
        nw = np.array([r.get(k, 0.0) for r in rows if not r["_wide"]])
        ww = np.array([r.get(k, 0.0) for r in wide])
        print(
            f"| {k} | {1000 * v.mean():.2f} | {1000 * np.median(v):.2f} | {c.mean():.1f} | "
            f"{1000 * nw.mean() if len(nw) else float('nan'):.2f} | {1000 * ww.mean() if len(ww) else float('nan'):.2f} |"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture", help="pickle the benchmark's registration inputs")
    c.add_argument("--set", choices=("styles", "quick"), required=True)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--style-plans", type=int, default=20)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--max-rooms", type=int, default=None, help="keep only plans of at most this many rooms")
    w = sub.add_parser("worker", help="(internal) serve registrations of a capture")
    w.add_argument("path", type=Path)
    t = sub.add_parser("time", help="alternate two source trees case by case")
    t.add_argument("path", type=Path)
    t.add_argument("--a", type=Path, required=True, help="folder holding tree A's frslam_graph (e.g. main)")
    t.add_argument("--b", type=Path, required=True, help="folder holding tree B's frslam_graph")
    t.add_argument("--rounds", type=int, default=2)
    t.add_argument("--limit", type=int, default=None, help="only the first cases")
    t.add_argument("--max-rooms", type=int, default=12, help="the groups' room bound (issue 21: 12)")
    p = sub.add_parser("profile", help="cProfile in this process")
    p.add_argument("path", type=Path)
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--top", type=int, default=40)
    p.add_argument("--sort", default="tottime")
    st = sub.add_parser("stages", help="per-stage CPU in this process (timers around the stage functions)")
    st.add_argument("path", type=Path)
    st.add_argument("--limit", type=int, default=None)
    st.add_argument("--max-rooms", type=int, default=12)
    st.add_argument("--group", default=None, help="only cases of this set label, e.g. quick-r2v")
    args = ap.parse_args(argv)
    if args.cmd == "capture":
        return capture(args.set, args.out, args.style_plans, args.seed, args.max_rooms)
    if args.cmd == "worker":
        return worker(args.path)
    if args.cmd == "time":
        return time_trees(args.path, args.a, args.b, args.rounds, args.limit, args.max_rooms)
    if args.cmd == "stages":
        return stages(args.path, args.limit, args.max_rooms, args.group)
    return profile(args.path, args.limit, args.top, args.sort)


if __name__ == "__main__":
    sys.exit(main())
