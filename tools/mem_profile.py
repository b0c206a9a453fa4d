"""Memory of a run over time: one JSON line every ``--every`` scans (issue 19).

The recording runs as ``frslam run`` and ``tools/bench_slam.py`` run it (``open_recording``,
``run_recording`` with the odometry in a worker process, the final batch). Every ``--every`` scans
(before that scan's heap trim): the backend's RSS and peak RSS so far (``/proc/self/status``
VmRSS / VmHWM, MB), the odometry worker's peak RSS and private memory, the keyframes, iSAM2's
``treeNnz`` (non-zeros of its Bayes tree) and the loop closures in the graph; at the end the
peaks of the whole run as ``bench_slam.py`` reports them (``ru_maxrss`` of the backend, the
worker's peak RSS, the largest private memory of the final alignment's forked halves, the
largest sum of the backend's RSS and the children's private memory: :class:`bench_slam.MemorySampler`) and each child's figures.

``--simulate HOURS`` first writes the ``bench_slam.py --long`` recording (five-room plan, 720
beams, 10 Hz, seed 1) into RECORDING unless it is there already, in a subprocess (in this one, the
2-h simulation's 1.4 GB was the backend's peak RSS from the first sample on).

    .venv/bin/python tools/mem_profile.py /tmp/long2h --simulate 2 [--every 2000] [--limit N]
        [--set '{"loop_closure": {"closure_spacing": 1.0}}']
"""

from __future__ import annotations

import argparse
import itertools
import json
import resource
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_slam import MemorySampler, child_pids, process_memory, run_child  # noqa: E402


def _status(pid: str = "self") -> dict[str, int]:
    """VmRSS and VmHWM of a process (MB; empty once it is gone)."""
    out: dict[str, int] = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                k, v = line.split(":", 1)
                if k in ("VmRSS", "VmHWM"):
                    out[k] = round(int(v.split()[0]) / 1024)
    except FileNotFoundError:
        pass
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording")
    ap.add_argument("--every", type=int, default=2000, help="scans between two samples")
    ap.add_argument("--limit", type=int, default=None, help="the first N scans only")
    ap.add_argument("--simulate", type=float, default=None, metavar="HOURS")
    ap.add_argument("--set", default="{}", help="configuration overrides (JSON)")
    args = ap.parse_args()

    from frslam_graph.datasets import open_recording

    from frslam_graph import offline

    if args.simulate is not None and not Path(args.recording).exists():
        # in a subprocess, as bench_slam.py --long: the simulation's memory (1.4 GB for 2 h) would
        # be this process's peak RSS and the odometry worker's pages, forked from it
        sim = run_child({"kind": "simulate", "hours": args.simulate, "out": args.recording})
        if "error" in sim:
            raise SystemExit(f"simulation failed: {sim['error']}")
        print(json.dumps({"simulated": sim}), flush=True)
    built: dict[str, Any] = {}
    init = offline.FRSlam.__init__

    def keep(self, *a, **kw):  # the run's FRSlam, to read its graph while it runs
        init(self, *a, **kw)
        built["slam"] = self

    offline.FRSlam.__init__ = keep
    t0 = time.perf_counter()

    memory = MemorySampler()

    def progress(n: int) -> None:
        memory.scans = n
        if n % args.every:
            return
        slam = built["slam"]
        isam = slam.graph._isam
        me = _status()
        row = {
            "scans": n,
            "keyframes": len(slam.graph),
            "wall_s": round(time.perf_counter() - t0),
            "rss_mb": me.get("VmRSS"),
            "peak_mb": me.get("VmHWM"),
            "worker_mb": [round(process_memory(p).get("hwm", 0)) for p in child_pids()],
            "worker_private_mb": [round(process_memory(p).get("private", 0)) for p in child_pids()],
            "tree_nnz": isam.treeNnz() if isam is not None else None,
            "closures": len(slam.loop_closer.closures) if slam.loop_closer else None,
        }
        print(json.dumps(row), flush=True)

    scans = open_recording(args.recording)
    if args.limit:
        scans = itertools.islice(scans, args.limit)
    with memory:
        out = offline.run_recording(scans, config=json.loads(args.set), progress=progress)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    end = {
        "end": True,
        "scans": len(out.result.trajectory),
        "keyframes": len(out.slam.graph),
        "wall_s": round(time.perf_counter() - t0),
        "peak_backend_mb": round(peak),
        "peak_worker_mb": round(memory.worker_mb()),
        "peak_forked_private_mb": round(memory.forked_private_mb()),
        "peak_tree_mb": round(memory.tree_mb),
        "children": {pid: {k: round(v) for k, v in c.items()} for pid, c in memory.children.items()},
    }
    print(json.dumps(end), flush=True)


if __name__ == "__main__":
    main()
