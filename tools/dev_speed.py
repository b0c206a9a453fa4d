"""One real log through ``run_recording`` (as ``tools/bench_slam.py`` runs it): relation error,
CPU seconds of the backend and of its odometry worker (their system CPU and minor page faults
too; "worker" = the children: odometry worker and final alignment halves), and the loop
closer's counts, as one JSON line. CPU seconds and counts compare runs on a loaded machine, where wall times do not.

    .venv/bin/python tools/dev_speed.py fr079            # aces, intel, fr079, intel.bag
    .venv/bin/python tools/dev_speed.py fr079 --profile /tmp/fr079.prof   # + cProfile of the run (CPU clock)
"""

from __future__ import annotations

import argparse
import cProfile
import json
import resource
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402


def main() -> None:
    from frslam_graph.datasets import open_recording

    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.offline import run_recording

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", choices=sorted(LOGS))
    ap.add_argument("--profile", type=Path, help="write a cProfile of run_recording here")
    args = ap.parse_args()
    recording, relations = (DATA / p for p in LOGS[args.log])
    rec = open_recording(recording)
    prof = cProfile.Profile(time.process_time) if args.profile else None
    t0, c0 = time.perf_counter(), time.process_time()
    if prof is not None:
        prof.enable()
    run = run_recording(rec)
    if prof is not None:
        prof.disable()
        prof.dump_stats(args.profile)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    me = resource.getrusage(resource.RUSAGE_SELF)
    res = run.result
    rel = relation_error(res.trajectory, load_relations(relations))
    lat = res.latencies * 1e3
    stats = asdict(run.slam.loop_closer.stats) if run.slam.loop_closer is not None else {}
    row = {
        "log": args.log,
        "trans_m": rel.trans_mean,
        "rot_deg": rel.rot_mean,
        "wall_s": round(wall, 2),
        "xrt": round(res.duration / wall, 2),
        "cpu_backend_s": round(cpu, 2),
        "cpu_worker_s": round(kids.ru_utime + kids.ru_stime, 2),
        # system CPU and minor page faults (fresh pages the kernel zero-fills: session 10)
        "sys_backend_s": round(me.ru_stime, 2),
        "sys_worker_s": round(kids.ru_stime, 2),
        "faults_backend": me.ru_minflt,
        "faults_worker": kids.ru_minflt,
        "latency_ms": [round(float(np.percentile(lat, q)), 1) for q in (50, 99, 100)],
        "loop_closure": stats,
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()
