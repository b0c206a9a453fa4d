"""Every shared real log with the default configuration: accuracy, speed, memory (Markdown tables).

Each log runs as ``frslam run`` does it (:func:`frslam_graph.datasets.open_recording`,
:func:`frslam_graph.offline.run_recording` with the odometry in a worker process, then
:func:`~frslam_graph.offline.write_outputs` into a folder), each in its own subprocess, so its
peak RSS is that log's. One row per log:

- relation error of Kümmerle et al. 2009 (``<log>.relations``; ``intel.bag`` is scored with
  ``intel.relations``, its ``/scan`` stamps being the CARMEN stamps): translation mean ± std and
  max (m), rotation mean ± std and max (deg), relations matched / total;
- endpoints on walls: ``metrics.json["map"]["endpoints_on_wall"]`` when the library writes it,
  else "n/a";
- × real time of the whole run: log duration / wall time of ``run_recording`` (reading the log,
  odometry, backend, final batch; not ``write_outputs``);
- per-scan latency median / p99 / max (ms, ``metrics.json["latency_ms"]``: with the odometry
  worker the sum of both stages' wall times per scan), and the same in CPU time of the threads
  that did each scan's work (``latency_cpu_ms``: what a scan takes on a core of its own, the
  streaming ``add_scan`` latency on a quiet machine; the wall figure also holds the waits of two
  processes and the reader's thread sharing two cores);
- peak memory (MB), backend + odometry worker + forked: ``ru_maxrss`` of the run's process (the
  backend, reading the log, the final batch and ``write_outputs``); the odometry worker's peak RSS
  (``VmHWM``; forked at the start, so it counts the pages it shares with the backend, ~100 MB of
  the imported libraries: an upper bound); and the largest private memory (``smaps_rollup``
  Private) of the final alignment's forked halves, which share the backend's pages copy-on-write
  (their RSS counts all of them: ``RUSAGE_CHILDREN``'s ``ru_maxrss``, the figure given as the
  worker's before session 8, was one of them, ~ the backend's size at the end). Sampled every
  0.5 s by :class:`MemorySampler`, which also keeps ``peak_tree_mb``: the largest sum of the
  backend's RSS and the children's private memory (each shared page counted once), what the
  run held at once;
- loop closures accepted (``decisions["loop_closure"]``);
- baseline measured in the same sweep, each in its own subprocess: bare KISS-ICP
  (``kiss_icp.kiss_icp.KissICP``, its default config except ``max_range`` = the log's,
  ``deskew`` off and frslam's thread count; the scans as 3D points with z = 0; no graph, no loop
  closure), its relation error and × real time (reading the log included, as for frslam), and
  frslam's wall time over the baseline's.

A second table gives the published figures (Hess et al., ICRA 2016, Table I, whose Graph Mapping
column quotes Kümmerle et al. 2009) next to the relation error of the wheel odometry as logged
over all relations (no scan matching at all).

``--long``: a synthetic recording of about ``--long-hours`` (default 2 h) from the project's
simulator (the five-room plan, 720 beams, 10 Hz; route length = hours × 3600 × 0.41 m/s, the
simulator's mean speed there), scored by ATE RMSE (SE(2)-aligned) against its ground truth, with
peak RSS and × real time. Simulating takes a few minutes; the run (~74,000 scans, a 2-h route
through the same five rooms, so the graph densifies) took over an hour on a shared two-core machine
(2026-12-02): off by default.

``--workers N`` runs the tasks concurrently through Dask distributed (a ``LocalCluster`` of N
single-threaded worker processes, or ``--scheduler ADDRESS``); each task still starts its own
subprocess. The pipeline is deterministic: accuracy figures equal the sequential ones, timing does
not (two runs share the machine's cores, each with its odometry worker: × real time is lower than
a run alone).

``--config FILE`` runs frslam with that configuration instead of the default (the baselines keep
theirs): a candidate default is judged on every log, the same way as the default.

    .venv/bin/python tools/bench_slam.py --workers 2 [--logs aces intel fr079 intel.bag]
        [--long] [--out DIR] [--csv FILE] [--no-baseline] [--config FILE]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/_sweep.py, also when loaded by a test
from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402
from _sweep import Sweep, SweepError  # noqa: E402

# Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM" (ICRA 2016), Table I, as quoted in
# ../shared/data/README.md (Intel, FR079). ACES: the README gives "about 0.04 m for both" and asks
# to check the paper; 0.0375 m is the figure the project has used as its target. Not re-checked.
PUBLISHED = {
    "aces": ("0.0375 m (as quoted by the project; not checked against the paper)", "≈ 0.04 m"),
    "intel": ("0.0229 ± 0.0239 m / 0.453 ± 1.335°", "0.031 ± 0.026 m / 1.3 ± 4.7°"),
    "fr079": ("0.0452 ± 0.0354 m / 0.538 ± 0.718°", "0.056 ± 0.042 m / 0.6 ± 0.6°"),
}
PUBLISHED["intel.bag"] = PUBLISHED["intel"]
LONG_SPEED = 0.41  # m/s: the simulator's mean speed on the five-room plan at max_speed 0.5


# ---------------------------------------------------------------- child processes (one task each)
def _peak_rss_mb() -> float:
    """Peak RSS of this process, MB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def _proc_kb(path: str, keys: tuple[str, ...]) -> dict[str, int]:
    """``key: value kB`` lines of a /proc file (kB); empty once the process is gone."""
    out: dict[str, int] = {}
    try:
        with open(path) as f:
            for line in f:
                k, _, v = line.partition(":")
                if k in keys:
                    out[k] = int(v.split()[0])
    except (FileNotFoundError, ProcessLookupError, ValueError):
        return {}
    return out


def process_memory(pid: str | int = "self") -> dict[str, float]:
    """A process's memory (MB): ``rss`` and ``hwm`` (peak RSS; both count the pages a forked
    process shares with its parent), ``pss`` (shared pages split among their sharers) and
    ``private`` (the pages no other process maps: what it adds). Empty once it is gone (Linux)."""
    roll = _proc_kb(f"/proc/{pid}/smaps_rollup", ("Rss", "Pss", "Private_Clean", "Private_Dirty"))
    if not roll:
        return {}
    status = _proc_kb(f"/proc/{pid}/status", ("VmHWM",))
    return {
        "rss": roll.get("Rss", 0) / 1024.0,
        "hwm": status.get("VmHWM", 0) / 1024.0,
        "pss": roll.get("Pss", 0) / 1024.0,
        "private": (roll.get("Private_Clean", 0) + roll.get("Private_Dirty", 0)) / 1024.0,
    }


def child_pids() -> list[str]:
    """This process's children (the odometry worker, the final alignment's forked halves)."""
    pids: list[str] = []
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/children") as f:
                pids += f.read().split()
        except FileNotFoundError:
            pass
    return pids


class MemorySampler:
    """A thread that samples this process and its children every ``period_s`` (Linux).

    ``children``: per child pid in the order first seen (the odometry worker first: forked at
    the start of the run), its largest ``hwm`` and ``private`` (MB) and ``from_scan`` (the
    caller's ``scans`` when first seen); ``tree_mb``: the largest sum of this process's RSS and
    its children's private memory (the pages they share with it counted once; reading the
    children's ``smaps_rollup`` only, ~2 ms of CPU per 400 MB, not this process's). Children that were there before it are left out. Use as a
    context manager."""

    def __init__(self, period_s: float = 0.5):
        self.period_s, self.scans, self.tree_mb = period_s, 0, 0.0
        self.children: dict[str, dict[str, float]] = {}
        self._before = set(child_pids())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def sample(self) -> None:
        """One sample now."""
        total = _proc_kb("/proc/self/status", ("VmRSS",)).get("VmRSS", 0) / 1024.0
        for pid in child_pids():
            if pid in self._before:
                continue
            m = process_memory(pid)
            if not m:
                continue
            total += m["private"]
            seen = self.children.setdefault(pid, {"from_scan": self.scans, "hwm": 0.0, "private": 0.0})
            seen["hwm"], seen["private"] = max(seen["hwm"], m["hwm"]), max(seen["private"], m["private"])
        self.tree_mb = max(self.tree_mb, total)

    def worker_mb(self) -> float:
        """The odometry worker's peak RSS (the first child seen), 0 without one."""
        return next(iter(self.children.values()), {}).get("hwm", 0.0)

    def forked_private_mb(self) -> float:
        """The largest private memory of the other children (the final alignment's halves)."""
        return max([c["private"] for c in list(self.children.values())[1:]], default=0.0)


def _relation_summary(rel) -> dict[str, Any]:
    return {
        "trans_mean": rel.trans_mean,
        "trans_std": rel.trans_std,
        "trans_max": float(np.max(rel.trans_errors)) if rel.matched else math.nan,
        "rot_mean": rel.rot_mean,
        "rot_std": rel.rot_std,
        "rot_max": float(np.max(rel.rot_errors)) if rel.matched else math.nan,
        "matched": rel.matched,
        "total": rel.matched + rel.unmatched,
    }


def child_frslam(spec: dict) -> dict[str, Any]:
    """Run one recording as ``frslam run`` does; write its outputs to ``spec["out"]``."""
    from frslam_graph.datasets import open_recording

    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.offline import run_recording, write_outputs

    rec = open_recording(spec["recording"])
    relations = load_relations(spec["relations"]) if spec.get("relations") else None
    gt = rec.ground_truth() if getattr(rec, "ground_truth_path", None) is not None else None
    t0 = time.perf_counter()
    with MemorySampler() as memory:
        run = run_recording(rec, config=spec.get("config"))
    wall = time.perf_counter() - t0
    out = Path(spec["out"])
    write_outputs(run, out, gt, relations)
    metrics = json.loads((out / "metrics.json").read_text())
    res = run.result
    row: dict[str, Any] = {
        "scans": len(res.trajectory),
        "duration_s": res.duration,
        "wall_s": wall,
        "xrt": res.duration / wall,
        "latency_ms": metrics["latency_ms"],
        "latency_cpu_ms": metrics["latency_cpu_ms"],
        "endpoints_on_wall": (metrics.get("map") or {}).get("endpoints_on_wall"),
        "closures": metrics["decisions"].get("loop_closure", 0),
        "keyframes": metrics["keyframes"],
    }
    row["peak_rss_backend_mb"] = _peak_rss_mb()
    row["peak_rss_worker_mb"] = memory.worker_mb()
    row["peak_forked_private_mb"] = memory.forked_private_mb()
    row["peak_tree_mb"] = memory.tree_mb
    row["peak_rss_mb"] = (
        row["peak_rss_backend_mb"] + row["peak_rss_worker_mb"] + row["peak_forked_private_mb"]
    )
    if relations is not None:
        row["relations"] = _relation_summary(run.metrics["relations"])
    if gt is not None:
        row["ate_rmse"] = run.metrics["ate"].rmse
    return row


def child_kiss(spec: dict) -> dict[str, Any]:
    """Bare KISS-ICP on the recording's scans (z = 0), and the wheel odometry as logged."""
    from frslam_graph.datasets import open_recording
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import DataConfig, MappingConfig, RegistrationConfig
    from kiss_icp.kiss_icp import KissICP

    from frslam_graph.config import FRSlamConfig
    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.se2 import to_matrix

    rec = open_recording(spec["recording"])
    t0 = time.perf_counter()
    icp = None
    rows, wheel = [], []
    no_stamps = np.zeros(0)
    for scan in rec:
        if icp is None:  # max_range from the log: its first scan's
            max_range = scan.max_range if math.isfinite(scan.max_range) else 100.0
            icp = KissICP(
                KISSConfig(
                    data=DataConfig(max_range=max_range, deskew=False),
                    # KISS-ICP's own default (kiss_icp.config.load_config): max_range / 100
                    mapping=MappingConfig(voxel_size=max_range / 100.0),
                    registration=RegistrationConfig(max_num_threads=FRSlamConfig().odometry.num_threads),
                )
            )
            offset = to_matrix(scan.sensor_offset)
            offset_inv = np.linalg.inv(offset)
        p = scan.points
        icp.register_frame(np.column_stack((p, np.zeros(len(p)))), no_stamps)
        m = icp.last_pose
        sensor = to_matrix((m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])))
        base = offset @ sensor @ offset_inv  # base_link_0 -> base_link_k
        rows.append((scan.stamp, base[0, 2], base[1, 2], math.atan2(base[1, 0], base[0, 0])))
        if scan.odom is not None:
            wheel.append((scan.stamp, *scan.odom))
    wall = time.perf_counter() - t0
    traj = np.array(rows)
    row: dict[str, Any] = {"wall_s": wall, "xrt": float(traj[-1, 0] - traj[0, 0]) / wall}
    if spec.get("relations"):
        rel = load_relations(spec["relations"])
        row["relations"] = _relation_summary(relation_error(traj, rel))
        if wheel:
            row["wheel_relations"] = _relation_summary(relation_error(np.array(wheel), rel))
    return row


def child_simulate(spec: dict) -> dict[str, Any]:
    """Write a simulated recording of about ``spec["hours"]`` on the five-room plan."""
    from frslam_graph.datasets.simulator import SimulationOptions, five_room_plan
    from frslam_graph.datasets.simulator.simulate import simulate

    opts = SimulationOptions(length=spec["hours"] * 3600.0 * LONG_SPEED, beams=720, scan_rate=10.0)
    res = simulate(five_room_plan(), spec["out"], seed=1, options=opts, overwrite=True)
    return {"scans": res.scans, "duration_s": res.duration, "route_m": res.route_length}


CHILDREN = {"frslam": child_frslam, "kiss": child_kiss, "simulate": child_simulate}


# ---------------------------------------------------------------- tasks (run by Dask or in a loop)
def run_child(spec: dict) -> dict[str, Any]:
    """Run one child of this script in a fresh subprocess; its JSON result (or an "error")."""
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
        capture_output=True,
        text=True,
        check=False,
    )
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"error": f"exit {proc.returncode}: {tail}"[:300]}
    return json.loads(lines[-1])


def run_task(task: dict) -> dict[str, Any]:
    """One task: ``{"name", "kind": "frslam"|"kiss"|"long", ...}``; returns the task with ``result``."""
    if task["kind"] == "long":  # simulate (not measured), then run like any recording
        sim = run_child({"kind": "simulate", "hours": task["hours"], "out": task["recording"]})
        if "error" in sim:
            return {**task, "result": sim}
        return {**task, "result": {**run_child({**task, "kind": "frslam"}), "simulated": sim}}
    return {**task, "result": run_child(task)}


def make_tasks(
    logs: dict[str, tuple[Path, Path | None]], out: Path, baseline: bool, config: Path | None = None
) -> list[dict]:
    """frslam tasks first (the longest), then the baselines; ``logs``: name -> (recording, relations);
    ``config``: an FRSlamConfig file for the frslam runs (None: the default)."""
    tasks = []
    for kind in ("frslam", "kiss") if baseline else ("frslam",):
        for name, (recording, relations) in logs.items():
            tasks.append(
                {
                    "name": name,
                    "kind": kind,
                    "recording": str(recording),
                    "relations": str(relations) if relations is not None else None,
                    "out": str(out / name.replace("/", "_")),
                    "config": str(config) if config is not None and kind == "frslam" else None,
                }
            )
    return tasks


def run_tasks(tasks: list[dict], workers: int = 1, scheduler: str | None = None) -> list[dict]:
    """Run the tasks one after another (``workers`` 1, no scheduler) or through Dask distributed
    (``tools/_sweep.py``); results in task order. Raises ``SweepError`` for an unreachable scheduler."""
    with Sweep(workers, scheduler) as sweep:
        return sweep.map(run_task, tasks)


# ---------------------------------------------------------------- tables
def _f(v: Any, fmt: str) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _share(v: Any) -> str:
    """A share as a percentage (a number <= 1 is a fraction, above 1 already a percentage)."""
    if v is None:
        return "n/a"
    if isinstance(v, int | float):
        return f"{100 * v if v <= 1 else v:.1f} %"
    return str(v)


def _rel_cells(r: dict | None) -> list[str]:
    if not r:
        return ["—", "—", "—"]
    if not r["matched"]:
        return ["n/a", "n/a", f"0 / {r['total']}"]
    return [
        f"{r['trans_mean']:.4f} ± {r['trans_std']:.4f}, {_f(r['trans_max'], '.3f')}",
        f"{r['rot_mean']:.3f} ± {r['rot_std']:.3f}, {_f(r['rot_max'], '.2f')}",
        f"{r['matched']} / {r['total']}",
    ]


MAIN_HEAD = [
    "log",
    "scans",
    "trans err mean ± std, max (m)",
    "rot err mean ± std, max (deg)",
    "relations matched / total",
    "endpoints on wall",
    "× real time",
    "latency median / p99 / max (ms)",
    "CPU per scan median / p99 / max (ms)",
    "peak memory backend + worker + forked (MB)",
    "loop closures",
    "KISS-ICP trans err mean ± std (m)",
    "KISS-ICP × real time",
    "wall frslam / KISS-ICP",
]


def main_row(name: str, run: dict, base: dict | None) -> list[str]:
    """One row of the main table from a frslam result and its baseline (None = not run)."""
    if "error" in run:
        return [name, f"failed: {run['error']}"] + ["—"] * (len(MAIN_HEAD) - 2)
    cells = _rel_cells(run.get("relations"))
    if "ate_rmse" in run and not run.get("relations"):
        cells[0] = f"ATE RMSE {run['ate_rmse']:.4f} (simulated, {run['duration_s'] / 3600:.2f} h)"
    wall = run.get("endpoints_on_wall")
    row = [
        name,
        str(run["scans"]),
        *cells,
        _share(wall),
        f"{run['xrt']:.1f}",
        _lat_cell(run["latency_ms"]),
        _lat_cell(run.get("latency_cpu_ms")),
        _rss_cell(run),
        str(run["closures"]),
    ]
    if base is None or "error" in base:
        row += ["—" if base is None else f"failed: {base['error']}", "—", "—"]
    else:
        r = base.get("relations")
        row += [
            f"{r['trans_mean']:.4f} ± {r['trans_std']:.4f}" if r and r["matched"] else "—",
            f"{base['xrt']:.1f}",
            f"{run['wall_s'] / base['wall_s']:.2f}",
        ]
    return row


def _lat_cell(ms: dict | None) -> str:
    """median / p99 / max of per-scan milliseconds ("—" for a result from before they existed)."""
    return "—" if ms is None else f"{ms['median']:.2f} / {ms['p99']:.1f} / {ms['max']:.0f}"


def _rss_cell(run: dict) -> str:
    if "peak_rss_backend_mb" not in run:  # a result from before the split
        return f"{run['peak_rss_mb']:.0f}"
    cell = f"{run['peak_rss_backend_mb']:.0f} + {run['peak_rss_worker_mb']:.0f}"
    if "peak_forked_private_mb" not in run:  # a result from before session 8 (worker: any child)
        return cell
    return cell + f" + {run['peak_forked_private_mb']:.0f}"


def markdown(head: list[str], rows: list[list[str]]) -> str:
    """A Markdown table (pipes in cells escaped)."""
    esc = [[c.replace("|", "\\|") for c in r] for r in [head, *rows]]
    lines = ["| " + " | ".join(esc[0]) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in esc[1:]]
    return "\n".join(lines)


REF_HEAD = [
    "log",
    "Cartographer (Hess et al. 2016)",
    "Graph Mapping (Kümmerle et al. 2009)",
    "wheel odometry as logged",
]


def reference_rows(results: dict[str, dict[str, dict]]) -> list[list[str]]:
    rows = []
    for name, kinds in results.items():
        if name not in PUBLISHED:
            continue
        wheel = (kinds.get("kiss") or {}).get("wheel_relations")
        w = (
            f"{wheel['trans_mean']:.4f} ± {wheel['trans_std']:.4f} m / {wheel['rot_mean']:.3f} ± {wheel['rot_std']:.3f}°"
            if wheel
            else "—"
        )
        rows.append([name, *PUBLISHED[name], w])
    return rows


def tables(results: dict[str, dict[str, dict]]) -> str:
    """Both tables from ``results[name][kind]`` (kind "frslam" / "kiss")."""
    rows = [main_row(n, k["frslam"], k.get("kiss")) for n, k in results.items() if "frslam" in k]
    text = markdown(MAIN_HEAD, rows)
    ref = reference_rows(results)
    if ref:
        text += "\n\nPublished relation errors (mean ± std, translation / rotation):\n\n" + markdown(
            REF_HEAD, ref
        )
    return text


def write_csv(path: Path, results: dict[str, dict[str, dict]]) -> None:
    flat = []
    for name, kinds in results.items():
        for kind, res in kinds.items():
            row = {"log": name, "kind": kind}
            for k, v in res.items():
                if isinstance(v, dict):
                    row.update({f"{k}.{kk}": vv for kk, vv in v.items()})
                else:
                    row[k] = v
            flat.append(row)
    keys = sorted({k for r in flat for k in r}, key=lambda k: (k not in ("log", "kind"), k))
    with Path(path).open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(flat)


def collect(done: list[dict]) -> dict[str, dict[str, dict]]:
    """``results[name][kind]`` in task order ("long" rows are frslam rows)."""
    results: dict[str, dict[str, dict]] = {}
    for t in done:
        kind = "frslam" if t["kind"] == "long" else t["kind"]
        results.setdefault(t["name"], {})[kind] = t["result"]
    return results


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=list(LOGS), choices=list(LOGS))
    ap.add_argument("--workers", type=int, default=1, help="concurrent tasks through Dask (1: a plain loop)")
    ap.add_argument(
        "--scheduler", default=None, help="address of an existing Dask scheduler (tcp://host:8786) instead"
    )
    ap.add_argument("--out", type=Path, default=None, help="keep each run's outputs here")
    ap.add_argument("--csv", type=Path, default=None, help="also write every figure as CSV")
    ap.add_argument("--no-baseline", action="store_true", help="skip the KISS-ICP / wheel-odometry runs")
    ap.add_argument("--long", action="store_true", help="add the simulated long recording (an hour or more)")
    ap.add_argument("--long-hours", type=float, default=2.0)
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="FRSlamConfig YAML/JSON for the frslam runs (default: the default configuration); "
        "to compare a candidate default on every log",
    )
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:  # one task, in its own process: print its JSON result
        import warnings

        warnings.simplefilter("ignore")  # readers warn about the logs' known oddities
        spec = json.loads(args.child)
        print(json.dumps(CHILDREN[spec["kind"]](spec), default=float))
        return

    if args.config is not None:
        from frslam_graph.config import FRSlamConfig
        from frslam_graph.errors import FrslamError

        try:
            FRSlamConfig.load(args.config)
        except FrslamError as exc:
            print(f"error: --config: {exc}", file=sys.stderr)
            sys.exit(2)
    tmp = None
    out = args.out
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_slam_")
        out = Path(tmp.name)
    logs = {}
    for name in args.logs:
        rec, rel = (DATA / p for p in LOGS[name])
        if not rec.exists():
            print(f"skipping {name}: {rec} not found", file=sys.stderr)
            continue
        logs[name] = (rec, rel if rel.exists() else None)
    tasks = make_tasks(logs, out, baseline=not args.no_baseline, config=args.config)
    if args.long:
        name = f"simulated {args.long_hours:g} h"
        rec = out / "simulated"
        tasks.insert(
            0,
            {
                "name": name,
                "kind": "long",
                "hours": args.long_hours,
                "recording": str(rec),
                "relations": None,
                "out": str(out / "simulated_run"),
                "config": str(args.config) if args.config is not None else None,
            },
        )
    t0 = time.perf_counter()
    try:
        results = collect(run_tasks(tasks, args.workers, args.scheduler))
    except SweepError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(tables(results))
    print(f"\n{len(tasks)} tasks, {args.workers} worker(s), {time.perf_counter() - t0:.0f} s in all.")
    if args.csv is not None:
        write_csv(args.csv, results)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
