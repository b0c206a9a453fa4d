"""Timeline of one real log's run (as ``tools/bench_slam.py`` runs it): when the backend and its
odometry worker compute, when each waits for the other, and the serial tail after the last scan.

Wraps the library's functions (nothing in the library changes): the worker's loop (forked with
the wrapper) records per chunk the wall time blocked in its inbox (no scans to do: the backend is
behind) and its thread CPU; the backend records the wall time blocked in the outbox (no result:
the worker is behind), its main thread's CPU, and the phases after the stream (the closer's queue,
the final batch, the final alignment). Waits are wall seconds a process sat idle on a queue; on
a loaded machine a wait can also be the other process starved of its core, so read them with the
CPU columns. Prints one JSON object (``--json FILE`` too, and FILE.scans.json: the per-scan CPU).

    FRSLAM_SHARED_DATA=/work/shared/data nice -n 10 .venv/bin/python tools/dev_timeline.py fr079
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402


def _patched_serve(original_serve, path: str):
    """The worker loop with each chunk's inbox wait, compute (wall, thread CPU) and outbox put
    recorded; written to ``path`` when the loop ends (in the forked child)."""
    from frslam_graph.odometry import worker as w

    def serve(config, inbox, outbox, parent, poll_s=1.0):
        rows: list[list[float]] = []
        per_scan: list[float] = []  # thread CPU s of each scan's odometry (prepare there included)

        class Inbox:
            def get(self):
                t0 = time.perf_counter()
                item = inbox.get()
                rows.append([t0, time.perf_counter(), time.thread_time(), 0 if item is None else len(item)])
                return item

        class Outbox:
            def put(self, item):
                if item[0] == "done":
                    Path(path).write_text(
                        json.dumps({"chunks": rows, "per_scan": per_scan, "cpu_end": time.process_time()})
                    )
                if item[0] == "results":
                    rows[-1].extend([time.perf_counter(), time.thread_time()])
                    per_scan.extend([r[3] for r in item[1]])
                outbox.put(item)

        return original_serve(config, Inbox(), Outbox(), parent, poll_s)

    w._serve = serve


def main() -> None:
    from frslam_graph.datasets import open_recording

    from frslam_graph import slam as slam_mod
    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.loop_closure import closer as closer_mod
    from frslam_graph.odometry import worker as w
    from frslam_graph.offline import run_recording

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", choices=sorted(LOGS))
    ap.add_argument("--json", type=Path, help="write the timeline here too")
    args = ap.parse_args()
    recording, relations = (DATA / p for p in LOGS[args.log])

    child_path = os.path.join(tempfile.mkdtemp(prefix="frslam_timeline_"), "worker.json")
    _patched_serve(w._serve, child_path)
    recv: list[tuple[float, float, float]] = []  # (wall before, wall after, thread CPU after)
    receive = w.OdometryWorker._receive

    def timed_receive(self):
        t0 = time.perf_counter()
        out = receive(self)
        recv.append((t0, time.perf_counter(), time.thread_time()))
        return out

    w.OdometryWorker._receive = timed_receive
    backend_scan: list[float] = []  # backend thread CPU s between two results (all its work per scan)
    prep_here: list[float] = []  # of it, the prepare run here for later chunks (CPU s)
    prepared: list[int] = []  # scans prepared here, in the worker
    sends: list[float] = []  # backend CPU s (from the run's start) when each of the first chunks was sent
    run_gen = w.OdometryWorker.run

    def timed_run(self, items, prepare=None):
        def timed_prepare(points):
            c0 = time.thread_time()
            out = prepare(points)
            prep_here.append(time.thread_time() - c0)
            return out

        c = time.thread_time()
        put = self._inbox.put

        def timed_put(chunk):
            if len(sends) < self.window:  # the first window: sent before any result is taken
                sends.append(time.thread_time() - c)
            put(chunk)

        self._inbox.put = timed_put
        for out in run_gen(self, items, None if prepare is None else timed_prepare):
            yield out
            now = time.thread_time()
            backend_scan.append(now - c)
            c = now
        prepared[:] = [self.prepared_here, self.prepared_there]

    w.OdometryWorker.run = timed_run
    phases: dict[str, list[float]] = {}

    def timed(owner, name, label):
        fn = getattr(owner, name)

        def wrapper(*a, **k):
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                phases.setdefault(label, []).append([t0, time.perf_counter() - t0, time.process_time() - c0])

        setattr(owner, name, wrapper)

    timed(closer_mod.LoopCloser, "on_finish", "closer queue (on_finish)")
    timed(slam_mod, "align_passes", "final alignment")
    timed(slam_mod.FRSlam, "finish", "finish (all)")

    rec = open_recording(recording)
    t_start, c_start = time.perf_counter(), time.process_time()
    run = run_recording(rec)
    t_end, c_end = time.perf_counter(), time.process_time()
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    child = json.loads(Path(child_path).read_text())
    res = run.result
    rel = relation_error(res.trajectory, load_relations(relations))

    chunks = child["chunks"]  # [get start, get end, cpu at get end, n, put wall, cpu at put]
    first_result = recv[0][1] if recv else t_end
    last_result = recv[-2][1] if len(recv) > 1 else t_end  # the last receive is the "done"
    worker_idle = sum(c[1] - c[0] for c in chunks)
    worker_idle_stream = sum(c[1] - c[0] for c in chunks[1:] if c[3])
    worker_cpu = sum(c[5] - c[2] for c in chunks if len(c) > 4)
    backend_wait = sum(r[1] - r[0] for r in recv[:-1])
    backend_wait_first = recv[0][1] - recv[0][0] if recv else 0.0
    fin = phases.get("finish (all)", [[t_end, 0, 0]])[0]
    out = {
        "log": args.log,
        "trans_m": rel.trans_mean,
        "rot_deg": rel.rot_mean,
        "wall_s": t_end - t_start,
        "xrt": res.duration / (t_end - t_start),
        "backend_cpu_s": c_end - c_start,
        "children_cpu_s": kids.ru_utime + kids.ru_stime,
        "worker_odometry_cpu_s": worker_cpu,
        "worker_process_cpu_s": child["cpu_end"],
        "to_first_result_s": first_result - t_start,
        "stream_s": last_result - first_result,
        "after_last_result_s": t_end - last_result,
        "backend_waits_for_worker_s": backend_wait,
        "of_it_first_result_s": backend_wait_first,
        "worker_waits_for_backend_s": worker_idle,
        "of_it_during_stream_s": worker_idle_stream,
        "worker_done_before_backend_s": t_end - (chunks[-1][1] if chunks else t_end),
        "finish_wall_s": fin[1],
        "finish_cpu_s": fin[2],
        "phases": {
            k: [[round(x - t_start, 3) if i == 0 else round(x, 3) for i, x in enumerate(v)] for v in vs]
            for k, vs in phases.items()
        },
        "loop_closure": asdict(run.slam.loop_closer.stats) if run.slam.loop_closer else {},
        # wall s each process waited, binned by when the wait began: tenths of the whole run
        "backend_wait_by_tenth": _bins([(r[0] - t_start, r[1] - r[0]) for r in recv[:-1]], t_end - t_start),
        "worker_wait_by_tenth": _bins([(c[0] - t_start, c[1] - c[0]) for c in chunks], t_end - t_start),
    }
    out["backend_stream_cpu_s"] = sum(backend_scan)
    out["prepare_here_cpu_s"] = sum(prep_here)
    out["worker_per_scan_cpu_s"] = sum(child["per_scan"])
    out["prepared_here_there"] = prepared
    out["simulated"] = simulate(child["per_scan"], backend_scan, sends)
    for window in (4, 64):
        out[f"simulated_end_window{window}_s"] = simulate(child["per_scan"], backend_scan, sends, 16, window)[
            "end_s"
        ]
    if args.json:
        args.json.with_suffix(".scans.json").write_text(
            json.dumps({"worker": child["per_scan"], "backend": backend_scan, "sends": sends})
        )
    text = json.dumps(out, default=float)
    if args.json:
        args.json.write_text(text)
    print(text)


def simulate(
    worker: list[float], backend: list[float], sends: list[float], chunk: int = 16, window: int = 16
) -> dict[str, float]:
    """A two-stage pipeline on these per-scan CPU seconds, each stage on a core of its own, as
    ``OdometryWorker.run`` sends chunks (``window`` chunks in flight, results a chunk at a time);
    the backend's seconds of a scan include the prepare it ran for later chunks. ``sends``: the
    backend's CPU s when it sent each of its first chunks (reading the log, a bag's prologue): the
    first ``window`` chunks leave then (later ones once the backend took chunk c - window), and
    the first scan's backend seconds count from the last of them. Returns the stream's end, the
    worker's end, and the idle seconds of each stage: the worker before its first chunk, with the
    window full, the backend after the worker's end; the backend's idle per tenth of the chunks."""
    n = min(len(worker), len(backend))
    backend = list(backend[:n])
    first = min(window, len(sends))
    lead = sends[first - 1] if first else 0.0
    backend[0] -= lead
    chunks = [(a, min(a + chunk, n)) for a in range(0, n, chunk)]
    consumed = [0.0] * len(chunks)
    worker_free = backend_free = 0.0
    worker_idle = [0.0] * len(chunks)
    backend_idle = [0.0] * len(chunks)
    for c, (a, b) in enumerate(chunks):
        sent = (sends[min(c, first - 1)] if first else 0.0) if c < window else consumed[c - window]
        start = max(worker_free, sent)
        worker_idle[c] = start - worker_free
        worker_free = start + sum(worker[a:b])
        t = max(backend_free, worker_free, lead)
        backend_idle[c] = t - backend_free
        backend_free = consumed[c] = t + sum(backend[a:b])
    tenth = [sum(backend_idle[q * len(chunks) // 10 : (q + 1) * len(chunks) // 10]) for q in range(10)]
    return {
        "end_s": backend_free,
        "worker_end_s": worker_free,
        "worker_idle_first_s": worker_idle[0] if chunks else 0.0,
        "worker_idle_window_full_s": sum(worker_idle[1:]),
        "backend_after_worker_s": backend_free - worker_free,
        "backend_idle_s": sum(backend_idle),
        "backend_idle_by_tenth_s": [round(x, 2) for x in tenth],
    }


def _bins(events: list[tuple[float, float]], span: float, n: int = 10) -> list[float]:
    bins = [0.0] * n
    for t, d in events:
        bins[min(n - 1, max(0, int(n * t / span)))] += d
    return [round(b, 2) for b in bins]


if __name__ == "__main__":
    main()
