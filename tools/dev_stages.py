"""Where one real log's CPU seconds go, stage by stage, and which stages make the slow scans.

    .venv/bin/python tools/dev_stages.py fr079                 # as `frslam run`: odometry in a worker
    .venv/bin/python tools/dev_stages.py fr079 --serial        # everything here: the worker's stages too
    .venv/bin/python tools/dev_stages.py intel --json /tmp/intel_stages.json
    .venv/bin/python tools/dev_stages.py fr079 --faults        # minor page faults per stage instead

Each stage is a function of the library wrapped here (nothing in the library changes) and charged
its *exclusive* process CPU time (time.process_time, minus the wrapped calls inside it), so the
rows add up to the process's CPU. Offline (default) the odometry runs in a forked worker: its CPU
is one figure (``RUSAGE_CHILDREN``, with the final alignment's forked half); ``--serial`` runs it
here, which splits it into stages and gives the per-scan CPU of a streaming ``add_scan``
(odometry + backend). The per-scan table shows the stages of the scans above the 99th
percentile and of the ten slowest. CPU, not wall: comparable on a loaded machine.
"""

from __future__ import annotations

import argparse
import functools
import json
import resource
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _paths import LOGS as SHARED_LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402

TESTS = Path(__file__).resolve().parents[1] / "tests" / "data"
LOGS = {
    **SHARED_LOGS,
    # 250 scans of FR079 in the repository: a check of this script in seconds
    "fr079_250": (TESTS / "fr079_250.clf.bz2", TESTS / "fr079_250.relations"),
}


class Stages:
    """Exclusive CPU seconds per stage label; per-scan deltas between :meth:`mark` calls."""

    def __init__(self, clock: Any = time.process_time) -> None:
        """``clock``: seconds of CPU (``time.process_time``; ``time.thread_time`` to leave other
        threads' work, such as the reader's read-ahead, out)."""
        self.clock = clock
        self.total: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[list[Any]] = []  # [label, start, child seconds]
        self._scan: dict[str, float] = {}
        self.per_scan: list[dict[str, float]] = []

    def _charge(self, label: str, seconds: float) -> None:
        self.total[label] = self.total.get(label, 0.0) + seconds
        self._scan[label] = self._scan.get(label, 0.0) + seconds

    def wrap(self, owner: Any, name: str, label: str) -> None:
        """Replace ``owner.name`` (a function or method) by a timed one."""
        fn = getattr(owner, name)
        if isinstance(fn, staticmethod):  # pragma: no cover - accessed through the class already
            fn = fn.__func__

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            frame = [label, self.clock(), 0.0]
            self._stack.append(frame)
            try:
                return fn(*args, **kwargs)
            finally:
                self._stack.pop()
                spent = self.clock() - frame[1]
                self._charge(label, spent - frame[2])
                self.calls[label] = self.calls.get(label, 0) + 1
                if self._stack:
                    self._stack[-1][2] += spent

        if isinstance(owner.__dict__.get(name), staticmethod):
            setattr(owner, name, staticmethod(timed))
        else:
            setattr(owner, name, timed)

    def wrap_gen(
        self,
        owner: Any,
        name: str,
        label: str,
        on_step: Callable[[tuple], Callable[[float], None]] | None = None,
    ) -> None:
        """Replace the generator function ``owner.name`` by one whose steps are timed.
        ``on_step(args)``, called before each step with the call's arguments, returns what is
        called after it with the step's seconds (its own stages' included)."""
        fn = getattr(owner, name)
        st = self

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            gen = fn(*args, **kwargs)
            value = None
            while True:
                done = on_step(args) if on_step is not None else None
                frame = [label, st.clock(), 0.0]
                st._stack.append(frame)
                try:
                    item = gen.send(value)
                except StopIteration as stop:
                    return stop.value
                finally:
                    st._stack.pop()
                    spent = st.clock() - frame[1]
                    st._charge(label, spent - frame[2])
                    if st._stack:
                        st._stack[-1][2] += spent
                    if done is not None:
                        done(spent)
                value = yield item

        setattr(owner, name, timed)

    def mark(self) -> None:
        """End of one scan: keep its stage seconds."""
        self.per_scan.append(self._scan)
        self._scan = {}


def wrap_odometry(st: Stages, body_points_label: str = "reader: body points") -> None:
    """Wrap the scan odometry's stages (in this process) and the reader's body points."""
    from frslam_graph import offline
    from frslam_graph.odometry import scan_odometry

    so = scan_odometry.ScanOdometry
    st.wrap(so, "prepare", "odometry: prepare (voxels, geometry)")
    st.wrap(so, "process", "odometry: process (EKF, keyframes)")
    st.wrap(so, "_align", "odometry: KISS-ICP register")
    st.wrap(so, "_refine", "odometry: point-to-line refinement")
    st.wrap(so, "_local_map", "odometry: local map rebuild")
    st.wrap(so, "_commit", "odometry: commit (KISS-ICP map update)")
    st.wrap(offline, "body_points", body_points_label)


def instrument(st: Stages) -> None:
    """Wrap the library's stages (coarse: one row per stage a reader can act on)."""
    from frslam_graph import offline, slam
    from frslam_graph.backend import context, graph, mapping
    from frslam_graph.loop_closure import closer, final_alignment, submap_matching

    wrap_odometry(st)
    st.wrap(slam.FRSlam, "_record", "backend: per-scan glue")
    pg = graph.PoseGraph
    st.wrap(pg, "_isam_update", "graph: iSAM2 update")
    st.wrap(pg, "_refresh_estimates", "graph: estimates refresh")
    st.wrap(pg, "optimize_batch", "graph: LM batch")
    st.wrap(graph._InflightBatch, "iterate", "graph: LM batch")
    st.wrap(pg, "_rebuild", "graph: iSAM2 rebuild")
    st.wrap(pg, "error", "graph: error()")
    lc = closer.LoopCloser
    st.wrap(lc, "on_keyframe", "closer: glue")
    st.wrap(lc, "on_scan", "closer: glue")
    st.wrap(lc, "on_finish", "closer: glue")
    st.wrap(lc, "_plan", "closer: plan (candidates)")
    st.wrap(lc, "_submap", "closer: submap points")
    st.wrap(lc, "_residual_chi2", "closer: prune residuals")
    sm = submap_matching
    st.wrap(sm.ReferenceSubmap, "__init__", "matcher: reference field build")
    st.wrap(sm.ReferenceSubmap, "dilated", "matcher: field dilation")
    st.wrap_gen(sm, "_grid_search", "matcher: correlative search")
    st.wrap(sm, "_score_poses", "matcher: correlative search")
    st.wrap(sm, "icp_point_to_line", "matcher: ICP")
    st.wrap_gen(sm, "icp_point_to_line_many", "matcher: ICP")  # the matcher's peaks in lockstep
    st.wrap(sm.ReferenceSubmap, "_normals_quality", "matcher: normals + k-d tree")
    st.wrap(sm.ReferenceSubmap, "free_violation", "matcher: free space")
    st.wrap(sm.ReferenceSubmap, "inlier_fraction", "matcher: inliers")
    fa = final_alignment
    st.wrap(fa, "candidate_pairs", "final: pairs")
    st.wrap(fa, "align_pairs", "final: ICP of pairs (this process's half)")
    st.wrap(fa, "searched_constraints", "final: searched constraints")
    st.wrap(fa, "align_passes", "final: glue")
    st.wrap(slam.FRSlam, "finish", "finish: glue")
    st.wrap(context.BackendContext, "occupancy_grid", "outputs: occupancy grid")
    st.wrap(mapping, "scans_endpoint_share", "outputs: endpoint share")
    st.wrap(offline, "_run_metrics", "outputs: metrics")


def thread_faults() -> float:
    """Minor page faults of the calling thread so far (a :class:`Stages` clock for ``--faults``:
    fresh pages the kernel zero-fills, each a fault; the reader's read-ahead thread left out)."""
    return float(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt)


def wrap_property(st: Stages, cls: Any, name: str, label: str) -> None:
    """Wrap the getter of property ``cls.name`` as :meth:`Stages.wrap` wraps a method."""

    class _Holder:
        fget = getattr(cls, name).fget

    st.wrap(_Holder, "fget", label)
    setattr(cls, name, property(_Holder.fget))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", help=f"one of {', '.join(sorted(LOGS))}, or a recording's path (no relations)")
    ap.add_argument("--serial", action="store_true", help="odometry in this process (stages + streaming CPU)")
    ap.add_argument("--json", type=Path, help="write the stage table and per-scan figures here")
    ap.add_argument(
        "--faults",
        action="store_true",
        help="charge minor page faults (this thread's) instead of CPU seconds",
    )
    args = ap.parse_args()

    from frslam_graph.datasets import open_recording

    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.offline import run_recording, write_outputs

    st = Stages(clock=thread_faults if args.faults else time.process_time)
    instrument(st)
    from frslam_graph import slam
    from frslam_graph.loop_closure import submap_matching as sm

    wrap_property(st, sm.ReferenceSubmap, "nearest", "matcher: nearest-point map")
    wrap_property(st, sm.ReferenceSubmap, "free", "matcher: free-space mask")

    record = slam.FRSlam._record  # already timed: mark a scan after it

    def record_and_mark(self: Any, *a: Any, **k: Any) -> Any:
        try:
            return record(self, *a, **k)
        finally:
            st.mark()

    slam.FRSlam._record = record_and_mark
    if args.log in LOGS:
        path, rel_path = (DATA / p for p in LOGS[args.log])
    elif Path(args.log).exists():  # e.g. bench_slam.py --long's simulated recording
        path, rel_path = Path(args.log), None
    else:
        ap.error(f"log: {args.log!r} is neither one of {', '.join(sorted(LOGS))} nor a path")
    rec = open_recording(path)

    class Timed:  # the reader's iteration as a stage
        stats = property(lambda _: getattr(rec, "stats", None))

        def __iter__(self):
            it = iter(rec)
            while True:
                frame = ["reader: records -> scans", st.clock(), 0.0]
                st._stack.append(frame)
                try:
                    scan = next(it)
                except StopIteration:
                    return
                finally:
                    st._stack.pop()
                    spent = st.clock() - frame[1]
                    st._charge(frame[0], spent - frame[2])
                    if st._stack:
                        st._stack[-1][2] += spent
                yield scan

    c0, t0, f0 = time.process_time(), time.perf_counter(), thread_faults()
    run = run_recording(Timed(), parallel=False if args.serial else None)
    c_run, wall_run = time.process_time() - c0, time.perf_counter() - t0
    if args.faults:
        faults = thread_faults() - f0
        me = resource.getrusage(resource.RUSAGE_SELF)
        print(
            f"{args.log}: minor page faults of this thread in run_recording {faults / 1e6:.3f} M "
            f"(the process's {me.ru_minflt / 1e6:.3f} M, system CPU {me.ru_stime:.2f} s, peak RSS "
            f"{me.ru_maxrss / 1024:.0f} MB); run CPU {c_run:.1f} s"
        )
        print("\n| stage | faults (k) | calls |\n|---|---:|---:|")
        for label, n in sorted(st.total.items(), key=lambda kv: -kv[1]):
            if n >= 500:
                print(f"| {label} | {n / 1e3:.0f} | {st.calls.get(label, '')} |")
        print(f"| (unwrapped) | {(faults - sum(st.total.values())) / 1e3:.0f} | |")
        return
    relations = load_relations(rel_path) if rel_path is not None else None
    write_outputs(run, Path("/tmp") / f"dev_stages_{Path(args.log).name}", relations=relations)
    cpu_all = time.process_time() - c0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    child = kids.ru_utime + kids.ru_stime
    res = run.result
    rel = run.metrics.get("relations")
    rel_text = f"relations {rel.trans_mean:.4f} m / {rel.rot_mean:.3f} deg" if rel is not None else "no relations"
    print(
        f"{args.log}: {'serial' if args.serial else 'worker'}; {res.duration:.0f} s of log; run wall "
        f"{wall_run:.1f} s ({res.duration / wall_run:.1f}x RT), run CPU here {c_run:.1f} s, with "
        f"outputs {cpu_all:.1f} s; children (worker + forked alignment half) {child:.1f} s; {rel_text}"
    )
    total = sum(st.total.values())
    print("\n| stage | CPU s | share | calls |\n|---|---:|---:|---:|")
    for label, sec in sorted(st.total.items(), key=lambda kv: -kv[1]):
        print(f"| {label} | {sec:.2f} | {100 * sec / max(cpu_all, 1e-9):.1f} % | {st.calls.get(label, '')} |")
    print(f"| (unwrapped: imports, glue) | {cpu_all - total:.2f} | | |")
    # per scan: CPU of add_scan (serial) or of the backend's part (worker)
    scans = st.per_scan
    per = np.array([sum(s.values()) for s in scans]) * 1e3
    lat = res.latencies * 1e3
    print(
        f"\nper scan CPU ms (median / p99 / max): {np.median(per):.2f} / {np.percentile(per, 99):.1f} / "
        f"{per.max():.0f} ({'odometry + backend' if args.serial else 'backend only'}); "
        f"run's latency (wall) {np.median(lat):.2f} / {np.percentile(lat, 99):.1f} / {lat.max():.0f}"
    )
    top = per >= np.percentile(per, 99)
    labels = sorted({k for s in scans for k in s})
    share = {k: sum(s.get(k, 0.0) for s, t in zip(scans, top, strict=True) if t) for k in labels}
    tot = sum(share.values())
    print(
        "scans at or above p99: CPU by stage: "
        + ", ".join(
            f"{k} {100 * v / tot:.0f} %"
            for k, v in sorted(share.items(), key=lambda kv: -kv[1])
            if v > 0.02 * tot
        )
    )
    print("slowest ten scans (index: ms, stages over 10 %):")
    for i in np.argsort(per)[::-1][:10]:
        parts = ", ".join(
            f"{k} {1e3 * v:.0f}"
            for k, v in sorted(scans[i].items(), key=lambda kv: -kv[1])
            if v * 1e3 > 0.1 * per[i]
        )
        print(f"  {i}: {per[i]:.0f} ms: {parts}")
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "log": args.log,
                    "serial": args.serial,
                    "stages": st.total,
                    "cpu_run": c_run,
                    "cpu_all": cpu_all,
                    "children": child,
                    "wall_run": wall_run,
                    "per_scan_ms": per.tolist(),
                }
            )
        )


if __name__ == "__main__":
    main()
