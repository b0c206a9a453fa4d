"""Degraded real logs (issue 19): does the default configuration hold on logs unlike ours?

The project is judged on real logs we do not have (other CARMEN logs: MIT CSAIL, Killian Court,
Freiburg buildings). They differ from ours in ways we can imitate on ours: poor or no wheel
odometry, a lower scan rate and logger pauses, shorter beams, and a far larger odometry drift on
big loops. Each variant is a generator over :func:`frslam_graph.datasets.open_recording`'s scans
that changes them before :func:`frslam_graph.offline.run_recording` (default configuration, the
odometry in a worker process, as ``frslam run`` and ``tools/bench_slam.py`` run a log). Each
(log, variant) runs in its own subprocess and leaves ``summary.json`` (and ``trajectory.tum``,
``log.jsonl``) in ``--out``/``LOG_VARIANT``; a run whose summary exists is not run again
(``--force``: it is). Prints one Markdown table.

Relation error (Kümmerle et al. 2009): each relation stamp takes the nearest pose within 0.01 s;
variants that drop scans interpolate the trajectory between poses at most 6 s apart (a dropped
scan's stamp has no pose of its own). × real time CPU: log duration / CPU seconds of the run
(backend process + odometry worker; machine load does not enter).

    .venv/bin/python tools/degrade_logs.py --out /tmp/degrade                  # aces intel, all variants
    .venv/bin/python tools/degrade_logs.py --out /tmp/degrade --logs fr079 --variants noodom
    .venv/bin/python tools/degrade_logs.py --out /tmp/degrade --variants noise3cm noise3cm_s1 noise3cm_s2
"""

from __future__ import annotations

import json
import resource
import sys
import time
import warnings
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402
from _variants import variants_main  # noqa: E402


def stalled_odometry(scans: Iterable) -> Iterator:
    """Every scan's odometry pose replaced by the first one: the wheels report no motion."""
    first = None
    for s in scans:
        if first is None:
            first = s.odom
        yield replace(s, odom=first)


def drifting_odometry(scans: Iterable, scale: float, bias_deg_per_m: float) -> Iterator:
    """Odometry re-integrated from its own increments (robot frame) with the translation scaled
    by ``scale`` and a heading bias of ``bias_deg_per_m`` degrees per metre travelled (the
    drift of a long route with big loops, as MIT Killian Court's)."""
    prev = None
    pose = None
    bias = np.radians(bias_deg_per_m)
    for s in scans:
        if s.odom is None:
            yield s
            continue
        o = np.asarray(s.odom, dtype=np.float64)
        if prev is None:
            pose = o.copy()
        else:
            c, si = np.cos(prev[2]), np.sin(prev[2])
            dx, dy = o[0] - prev[0], o[1] - prev[1]
            lx, ly = c * dx + si * dy, -si * dx + c * dy  # increment in the previous robot frame
            dth = np.arctan2(np.sin(o[2] - prev[2]), np.cos(o[2] - prev[2]))
            lx, ly = scale * lx, scale * ly
            dth += bias * np.hypot(lx, ly)
            cp, sp = np.cos(pose[2]), np.sin(pose[2])
            pose = np.array([pose[0] + cp * lx - sp * ly, pose[1] + sp * lx + cp * ly, pose[2] + dth])
        prev = o
        yield replace(s, odom=(float(pose[0]), float(pose[1]), float(pose[2])))


def thinned(scans: Iterable, keep_every: int, pause_every_s: float, pause_s: float) -> Iterator:
    """Every ``keep_every``-th scan only, and a logger pause of ``pause_s`` seconds (no scan)
    every ``pause_every_s`` seconds of the log (0: none)."""
    t0 = None
    for i, s in enumerate(scans):
        t0 = s.stamp if t0 is None else t0
        if i % keep_every:
            continue
        if pause_every_s > 0 and (s.stamp - t0) % pause_every_s < pause_s:
            continue
        yield s


def short_beams(scans: Iterable, max_range: float) -> Iterator:
    """Beams past ``max_range`` metres become 'no return' at the sensor's (smaller) maximum, as a
    SICK in its 8 m mode logs them: the range value equals the maximum (CARMEN's convention)."""
    for s in scans:
        r = np.where(np.isfinite(s.ranges) & (s.ranges >= max_range), max_range, s.ranges)
        yield replace(s, ranges=r, max_range=min(max_range, s.max_range), _points=None)


def noisy_ranges(scans: Iterable, sigma: float, seed: int = 0) -> Iterator:
    """Each valid range gets Gaussian noise of ``sigma`` metres (seeded): a cheaper laser than the
    logs' SICKs (a Hokuyo URG's +-3 cm, an RPLidar's 1-2 % of the range)."""
    rng = np.random.default_rng(seed)
    for s in scans:
        ok = np.isfinite(s.ranges) & (s.ranges > 0.0) & (s.ranges < s.max_range)
        noisy = np.clip(s.ranges + rng.normal(0.0, sigma, len(s.ranges)), 1e-3, np.nextafter(s.max_range, 0))
        yield replace(s, ranges=np.where(ok, noisy, s.ranges), _points=None)


def fewer_beams(scans: Iterable, keep_every: int) -> Iterator:
    """Every ``keep_every``-th beam only: a laser of coarser angular resolution."""
    for s in scans:
        yield replace(s, ranges=s.ranges[::keep_every], angles=s.angles[::keep_every], _points=None)


#: odometry counters (:class:`~frslam_graph.odometry.scan_odometry.OdometryStats`) in the table
ODOM_STATS = ("odom_jumps", "icp_rejections", "fallbacks", "degenerate_scans", "gaps")

#: name -> (scan transform, whether scans are dropped: the relations then interpolate)
VARIANTS: dict[str, tuple[Callable[[Iterable], Iterator], bool]] = {
    "default": (lambda s: iter(s), False),
    "noodom": (stalled_odometry, False),
    "drift2": (lambda s: drifting_odometry(s, 1.07, 2.0), False),
    "rate3_gaps": (lambda s: thinned(s, 3, 120.0, 5.0), True),
}
#: short-range lasers: ``rangeN`` beams past N metres no-return at an N m maximum (a SICK in its 8 m
#: mode; a TurtleBot-class laser: LDS-01 3.5 m, a 4 m cap)
for _name, _r in (("range8", 8.0), ("range4", 4.0), ("range3.5", 3.5)):
    VARIANTS[_name] = ((lambda r: lambda s: short_beams(s, r))(_r), False)
#: a cheaper laser: range noise of 3 cm (sigma), half the beams
VARIANTS["noise3cm"] = (lambda s: noisy_ranges(s, 0.03), False)
#: the same laser, other draws of its noise (``noise3cm`` is seed 0): a second and third sample of a
#: change's effect on a noisy log, where one run cannot tell a change from a changed trajectory
for _k in (1, 2):
    VARIANTS[f"noise3cm_s{_k}"] = ((lambda k: lambda s: noisy_ranges(s, 0.03, seed=k))(_k), False)
VARIANTS["half_beams"] = (lambda s: fewer_beams(s, 2), False)
ALL = ["noodom", "drift2", "rate3_gaps", "range8"]


def run_one(log: str, variant: str, out: Path) -> dict:
    """Run ``log`` under ``variant`` in this process; write the run's files into ``out``."""
    from frslam_graph.datasets import open_recording

    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations, save_tum
    from frslam_graph.offline import run_recording

    recording, relations = (DATA / p for p in LOGS[log])
    transform, drops = VARIANTS[variant]
    out.mkdir(parents=True, exist_ok=True)
    c0 = time.process_time()
    ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    rec = open_recording(recording)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run = run_recording(transform(rec))
    ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = time.process_time() - c0 + (ch1.ru_utime - ch0.ru_utime) + (ch1.ru_stime - ch0.ru_stime)
    res = run.result
    rel = relation_error(res.trajectory, load_relations(relations), interpolate=6.0 if drops else None)
    save_tum(out / "trajectory.tum", res.trajectory)
    with open(out / "log.jsonl", "w") as f:
        for e in run.slam.log:
            row = {"stamp": e.stamp, "kind": e.kind, "message": e.message, "keyframe": e.keyframe}
            f.write(json.dumps({**row, "data": e.data}, default=float) + "\n")
    kinds = Counter(e.kind for e in run.slam.log)
    lc = run.slam.loop_closer
    summary = {
        "log": log,
        "variant": variant,
        "trans_mean": rel.trans_mean,
        "trans_max": float(rel.trans_errors.max()),
        "rot_mean": rel.rot_mean,
        "matched": int(len(rel.trans_errors)),
        "relations": int(len(rel.trans_errors) + rel.unmatched),
        "scans": len(res.trajectory),
        "accepted": len(lc.closures) if lc is not None else 0,
        "kinds": dict(kinds),
        "odometry": {k: getattr(res.stats, k) for k in ODOM_STATS},
        "warnings": sorted({str(w.message)[:160] for w in caught}),
        "cpu_s": round(cpu, 1),
        "xrt_cpu": round(res.duration / cpu, 1) if cpu > 0 else None,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def table(rows: list[dict]) -> str:
    lines = [
        "| log | variant | trans mean, max (m) | rot mean (deg) | matched | closures in graph / logged, rejected | other decisions | × real time CPU |",
        "|---|---|---|---|---|---|---|---|",
    ]
    routine = {"loop_closure", "loop_rejected", "keyframe"}
    for r in rows:
        k = r["kinds"]
        other = ", ".join(f"{n} {c}" for n, c in sorted(k.items()) if n not in routine) or "-"
        odo = r.get("odometry", {})
        other += "".join(f", {n} {c}" for n, c in odo.items() if c)
        if r["warnings"]:
            other += f"; {len(r['warnings'])} warning(s)"
        lines.append(
            f"| {r['log']} | {r['variant']} | {r['trans_mean']:.4f}, {r['trans_max']:.3f} | {r['rot_mean']:.3f} "
            f"| {r['matched']} / {r['relations']} | {r['accepted']} / {k.get('loop_closure', 0)}, "
            f"{k.get('loop_rejected', 0)} | {other} | {r['xrt_cpu']} |"
        )
    return "\n".join(lines)


def main() -> None:
    variants_main(__doc__, __file__, list(LOGS), list(VARIANTS), ["intel", "aces"], ALL, run_one, table)


if __name__ == "__main__":
    main()
