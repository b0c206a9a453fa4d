"""The online loop closer's fragility (issue 19): real logs under a family of nearby configurations.

Small changes that leave the odometry almost unchanged (the wheel model's floor or fraction, the
keyframe spacing) change which candidates the closer tries when; a robust closer keeps every loop
under all of them. Each (log, variant) runs as ``tools/dev_speed.py`` runs a log
(:func:`~frslam_graph.offline.run_recording`, odometry in a worker process), one at a time, each in
its own subprocess, and leaves in ``--out``/``LOG_VARIANT``: ``summary.json`` (relation error
mean / std / max, closures accepted / pending / pruned, CPU s), ``log.jsonl`` (the decisions) and
``keyframes.csv`` (index, stamp, final map pose: the loop decisions name keyframes) and
``trajectory.tum``. A run whose
``summary.json`` exists is not run again (``--force``: it is). Prints the Markdown table.

    .venv/bin/python tools/fragility.py --out /tmp/frag                      # aces fr079, whole family
    .venv/bin/python tools/fragility.py --out /tmp/frag --logs intel --variants default frac2
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from _paths import LOGS  # noqa: E402
from _paths import SHARED_DATA as DATA  # noqa: E402
from _variants import variants_main  # noqa: E402

#: nearby configurations (overrides of the default): the wheel model around its default (8 %/m,
#: 8 mm floor; session 6 measured these), and the former fraction with the current floor
VARIANTS: dict[str, dict] = {
    "default": {},
    "floor6": {"odometry": {"wheel_sigma_floor_xy": 0.006}},
    "floor10": {"odometry": {"wheel_sigma_floor_xy": 0.010}},
    "frac2": {"odometry": {"wheel_dist_frac": 0.02}},
    # not in the default family: keyframe spacing (the loop closer plans every other keyframe)
    "kfdist25": {"odometry": {"keyframe_distance": 0.25}},
    "kfangle12": {"odometry": {"keyframe_angle_deg": 12.0}},
}
FAMILY = ["default", "floor6", "floor10", "frac2"]


def run_one(log: str, variant: str, out: Path) -> dict:
    """Run ``log`` under ``variant`` in this process; write the run's files into ``out``."""
    import numpy as np
    from frslam_graph.datasets import open_recording

    from frslam_graph.evaluation.relations import relation_error
    from frslam_graph.evaluation.trajectory_io import load_relations, save_tum
    from frslam_graph.offline import run_recording

    recording, relations = (DATA / p for p in LOGS[log])
    out.mkdir(parents=True, exist_ok=True)
    c0 = time.process_time()
    run = run_recording(open_recording(recording), config=VARIANTS[variant])
    cpu = time.process_time() - c0
    rel = relation_error(run.result.trajectory, load_relations(relations))
    with open(out / "log.jsonl", "w") as f:
        for e in run.slam.log:
            row = {"stamp": e.stamp, "kind": e.kind, "message": e.message, "keyframe": e.keyframe}
            f.write(json.dumps({**row, "data": e.data}, default=float) + "\n")
    save_tum(out / "trajectory.tum", run.result.trajectory)
    kfs = run.slam.keyframes()
    np.savetxt(
        out / "keyframes.csv",
        np.array([[k.index, k.stamp, *k.pose_map] for k in kfs]),
        delimiter=",",
        header="index,stamp,x,y,theta",
        fmt=["%d", "%.6f", "%.4f", "%.4f", "%.5f"],
    )
    counts = {
        k: sum(1 for e in run.slam.log if e.kind == k)
        for k in ("loop_closure", "loop_pending", "loop_removed")
    }
    lc = run.slam.loop_closer
    summary = {
        "log": log,
        "variant": variant,
        "trans_mean": rel.trans_mean,
        "trans_std": rel.trans_std,
        "trans_max": float(rel.trans_errors.max()),
        "rot_mean": rel.rot_mean,
        "accepted": len(lc.closures) if lc is not None else 0,
        **counts,
        "attempts": lc.stats.attempts if lc is not None else 0,
        "cpu_backend_s": round(cpu, 1),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def table(rows: list[dict]) -> str:
    lines = [
        "| log | variant | trans mean ± std, max (m) | rot mean (deg) | closures in graph / logged, pending, removed | matches | backend CPU s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['log']} | {r['variant']} | {r['trans_mean']:.4f} ± {r['trans_std']:.4f}, {r['trans_max']:.3f} "
            f"| {r['rot_mean']:.3f} | {r['accepted']} / {r['loop_closure']}, {r['loop_pending']}, {r['loop_removed']} "
            f"| {r['attempts']} | {r['cpu_backend_s']} |"
        )
    return "\n".join(lines)


def main() -> None:
    variants_main(__doc__, __file__, list(LOGS), list(VARIANTS), ["aces", "fr079"], FAMILY, run_one, table)


if __name__ == "__main__":
    main()
