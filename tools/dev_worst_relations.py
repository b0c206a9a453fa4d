"""The worst relations of a run, the loop closures around them, and how far the reference
relations themselves agree (issue 19: where a log's maximum comes from).

    .venv/bin/python tools/dev_worst_relations.py worst RUN RELATIONS [--k 10]
    .venv/bin/python tools/dev_worst_relations.py near RUN RELATIONS --from 2060 --to 2095
    .venv/bin/python tools/dev_worst_relations.py keyframes intel.bag /tmp/kf_bag.csv
    .venv/bin/python tools/dev_worst_relations.py keyframes intel /tmp/kf_hb.csv --variant half_beams
    .venv/bin/python tools/dev_worst_relations.py closures RUN /tmp/kf_bag.csv REFERENCE.tum --from 2040 --to 2120
    .venv/bin/python tools/dev_worst_relations.py triangles RELATIONS [--k 5]

``RUN``: an output folder of ``frslam run`` / ``bench_slam.py --out`` (``trajectory.tum``,
``log.jsonl``). Times after ``--from`` / ``--to`` are seconds from the run's first pose.
``worst``: the relations with the largest translation error (stamps, span, estimate and truth
in the frame of the pose at t1). ``near``: every relation with a stamp in the window.
``keyframes``: the keyframes (index, stamp) of a log's odometry alone (the same as a run's: the
odometry does not depend on the backend; ``--variant``: of a degraded log). ``closures``: each
accepted or pending closure whose query lies in the window, its measured relative pose against
``REFERENCE`` (e.g. another run of the same recording that fits the relations) at the two
keyframes' stamps (``meas-ref``) and the run's own final one (``final-ref``); also each match
rejected as ``contradicted`` and each pending closure so dropped, with the closure in the graph
that contradicted it (``by``) and their disagreement (``off``: m, deg). ``triangles``: every
relation (a, c) that two others (a, b), (b, c) compose (either direction), and how far the
composition is from it: the noise of the reference itself, a floor under any trajectory's error
on those relations.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402


def relation_errors(traj: np.ndarray, rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per relation: translation error (m), rotation error (deg), estimated relative pose (K, 3);
    NaN where a stamp found no pose within 0.01 s (as ``bench_slam.py``)."""
    from frslam_graph.evaluation.relations import relative_poses
    from frslam_graph.se2 import wrap_atan2

    est, _ = relative_poses(traj, rel[:, 0], rel[:, 1], 0.01)
    t = np.hypot(rel[:, 2] - est[:, 0], rel[:, 3] - est[:, 1])
    r = np.degrees(np.abs(wrap_atan2(rel[:, 4] - est[:, 2])))
    return t, r, est


def _load(run: Path, relations: Path) -> tuple[np.ndarray, np.ndarray]:
    from frslam_graph.evaluation.trajectory_io import load_relations, load_tum

    return load_tum(run / "trajectory.tum"), load_relations(relations)


def worst(run: Path, relations: Path, k: int) -> None:
    traj, rel = _load(run, relations)
    t, r, est = relation_errors(traj, rel)
    t0 = traj[0, 0]
    print(f"mean {np.nanmean(t):.4f} m, max {np.nanmax(t):.4f} m, rot {np.nanmean(r):.3f} deg (t0 {t0:.3f})")
    for j in np.argsort(-np.nan_to_num(t))[:k]:
        print(
            f"{j:5d} {rel[j, 0] - t0:9.2f} -> {rel[j, 1] - t0:9.2f} s (span {rel[j, 1] - rel[j, 0]:7.1f} s)"
            f" err {t[j]:.3f} m {r[j]:.2f} deg  est {est[j].round(3)} true {rel[j, 2:].round(3)}"
        )


def near(run: Path, relations: Path, a: float, b: float) -> None:
    traj, rel = _load(run, relations)
    t, r, est = relation_errors(traj, rel)
    t0 = traj[0, 0]
    s1, s2 = rel[:, 0] - t0, rel[:, 1] - t0
    m = ((s1 >= a) & (s1 <= b)) | ((s2 >= a) & (s2 <= b))
    for j in np.flatnonzero(m)[np.argsort(rel[m, 0], kind="stable")]:
        d = rel[j, 2:4] - est[j, :2]
        print(f"{j:5d} {s1[j]:9.2f} -> {s2[j]:9.2f} err {t[j]:.3f} m {r[j]:.2f} deg  d {d.round(3)}")


def keyframes(log: str, out: Path, variant: str | None = None) -> None:
    from frslam_graph.datasets import open_recording

    from frslam_graph.config import FRSlamConfig
    from frslam_graph.odometry.scan_odometry import ScanOdometry
    from frslam_graph.offline import body_points

    odo = ScanOdometry(FRSlamConfig().odometry)
    rows = []
    scans = open_recording(DATA / LOGS[log][0])
    if variant is not None:  # a degraded log of tools/degrade_logs.py
        from degrade_logs import VARIANTS

        scans = VARIANTS[variant][0](scans)
    for s in scans:
        res = odo.process(s.stamp, body_points(s.points, s.sensor_offset)[0], s.odom)
        if res.is_keyframe:
            rows.append((res.keyframe, s.stamp))
    np.savetxt(out, np.array(rows), fmt=["%d", "%.6f"], delimiter=",", header="index,stamp")
    print(f"{len(rows)} keyframes -> {out}")


def closures(run: Path, kf_csv: Path, reference: Path, a: float, b: float) -> None:
    from frslam_graph.evaluation.trajectory_io import load_tum
    from frslam_graph.se2 import between

    stamp = {int(k): t for k, t in np.loadtxt(kf_csv, delimiter=",", ndmin=2)[:, :2]}
    ref, own = load_tum(reference), load_tum(run / "trajectory.tum")
    t0 = own[0, 0]

    def pose(tr: np.ndarray, t: float) -> np.ndarray:
        j = int(np.argmin(np.abs(tr[:, 0] - t)))
        return tr[j, 1:]

    events = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    pending: dict[tuple[int, int], dict] = {}
    for e in events:
        kind, d = e["kind"], e["data"]
        if kind == "loop_pending":
            pending[e["keyframe"], d["reference"]] = d
        if kind == "loop_rejected" and e["message"].endswith("contradicted"):
            # a rejected match, or a pending closure dropped (its match as logged when it waited)
            kind = "contradicted" if "relative" in d else "dropped"
            d = {**pending.get((e["keyframe"], d["reference"]), {}), **d}
        elif kind not in ("loop_closure", "loop_pending"):
            continue
        q, c = e["keyframe"], d["reference"]
        if not a <= stamp[q] - t0 <= b:
            continue
        truth = between(pose(ref, stamp[c]), pose(ref, stamp[q]))
        err = between(truth, np.array(d["relative"]))
        fin = between(truth, between(pose(own, stamp[c]), pose(own, stamp[q])))
        corr = f"{np.hypot(*d['correction'][:2]):.2f} m" if "correction" in d else "-"  # not for a rejection
        print(
            f"{e['stamp'] - t0:8.2f} {kind:12s} {q} ({stamp[q] - t0:7.1f} s) on {c} ({stamp[c] - t0:7.1f} s)"
            f" correction {corr}, meas-ref {np.hypot(err[0], err[1]):.3f} m"
            f" {np.degrees(err[2]):+.2f} deg, final-ref {np.hypot(fin[0], fin[1]):.3f} m,"
            f" inliers {d['inliers']} ambiguity {d['ambiguity']} {d.get('found_by', '')}"
            + ("" if d.get("robust") is None else f" robust {d['robust']}")
            + ("" if "by" not in d else f" by {d['by'][0]} on {d['by'][1]}, off {d['off']}")
        )


def triangles(relations: Path, k: int) -> None:
    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.se2 import between, compose

    rel = load_relations(relations)
    edge: dict[tuple[float, float], np.ndarray] = {}
    adj: dict[float, set[float]] = defaultdict(set)
    for r in rel:
        a, c = round(r[0], 3), round(r[1], 3)
        edge[a, c], edge[c, a] = r[2:], between(r[2:], np.zeros(3))
        adj[a].add(c)
        adj[c].add(a)
    out = []
    for j, r in enumerate(rel):
        a, c = round(r[0], 3), round(r[1], 3)
        for b in adj[a] & adj[c]:
            d = between(r[2:], compose(edge[a, b], edge[b, c]))
            out.append((float(np.hypot(d[0], d[1])), float(abs(np.degrees(d[2]))), a, b, c, j))
    out.sort(reverse=True)
    ds = np.array([o[0] for o in out])
    print(
        f"{len(out)} triangles: discrepancy median {np.median(ds):.3f} m, p90 {np.percentile(ds, 90):.3f} m,"
        f" max {ds.max():.3f} m"
    )
    for o in out[:k]:
        print(f"  {o[2]:.3f} -> {o[4]:.3f} via {o[3]:.3f}: {o[0]:.3f} m {o[1]:.2f} deg (relation {o[5]})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=["worst", "near", "keyframes", "closures", "triangles"])
    ap.add_argument("args", nargs="+")
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--from", dest="a", type=float, default=-np.inf)
    ap.add_argument("--to", dest="b", type=float, default=np.inf)
    ap.add_argument("--variant", help="keyframes: of this degraded log (tools/degrade_logs.py)")
    o = ap.parse_args()
    p = [Path(x) for x in o.args]
    if o.what == "worst":
        worst(p[0], p[1], o.k)
    elif o.what == "near":
        near(p[0], p[1], o.a, o.b)
    elif o.what == "keyframes":
        keyframes(o.args[0], p[1], o.variant)
    elif o.what == "closures":
        closures(p[0], p[1], p[2], o.a, o.b)
    else:
        triangles(p[0], o.k)


if __name__ == "__main__":
    main()
