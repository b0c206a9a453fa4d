"""Diagnostic (issue 21 d4): do the floor-plan priors pull the Intel trajectory where the plan is
drawn differently from the building? The registration is forced: the hand-annotated similarity
(``tests/data/intel_lab_plan_points.csv``; flipped, -88.2 deg, 0.0429 m/px, 0.50 m RMS, about 1 m
off at the central block) or a given 3 x 3 plan -> map matrix is returned by every attempt, and
the judge's map checks (min_map_fit, max_walls_in_free_space, min_scan_fit) are off, so it is
accepted at the first attempt and relocalisation priors are offered along the whole run. What
keeps a prior of the wrongly drawn part out is then only the chi² gate and the Cauchy kernel.

    .venv/bin/python tools/intel_forced_plan.py --out /tmp/forced            # ~10 min
    .venv/bin/python tools/intel_forced_plan.py --matrix reg.json --out ...   # a registration's matrix

Writes the run's outputs (metrics.json with the relation error, trajectory.png with the plan) and
prints the prior counts and the relation error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from _paths import REPO as ROOT  # noqa: E402
from _paths import SHARED_DATA  # noqa: E402

sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    from frslam_graph.datasets import open_recording
    from test_intel_plan_points import fit_similarity, intel_plan_points

    import frslam_graph as fr
    from frslam_graph.cli.run import _trajectory_figure
    from frslam_graph.evaluation.trajectory_io import load_relations
    from frslam_graph.offline import RunOutput, process, write_outputs
    from frslam_graph.plan_updates.updater import FloorPlanUpdater
    from frslam_graph.registration import Registration
    from frslam_graph.slam import FRSlam

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data",
        type=Path,
        default=SHARED_DATA,
    )
    ap.add_argument("--matrix", type=Path, default=None, help="JSON with a 'matrix' (plan -> map)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    _, plan_xy, map_xy = intel_plan_points(ROOT / "tests" / "data")
    matrix = fit_similarity(plan_xy, map_xy, True)
    if args.matrix is not None:
        matrix = np.asarray(json.loads(args.matrix.read_text())["matrix"], float)
    plan = fr.FloorPlan.load(args.data / "floorplans" / "ipa" / "lab_intel.png")
    cfg = fr.FRSlamConfig().with_updates(
        updates={"min_map_fit": 0.0, "max_walls_in_free_space": 1.0, "min_scan_fit": 0.0}
    )

    def forced(plan_, grid):
        return Registration.from_matrix(matrix, score=0.9, ambiguity=0.2, method="forced")

    upd = FloorPlanUpdater(plan, cfg.updates, register_fn=forced)
    slam = FRSlam(config=cfg, update_strategy=upd)
    res = process(slam, open_recording(args.data / "carmen" / "intel.clf.bz2"), batch=True)
    run = RunOutput(slam, res)
    rel = load_relations(args.data / "carmen" / "intel.relations")
    fig = _trajectory_figure({"frslam": res.trajectory}, None, run, title="forced plan")
    write_outputs(run, args.out, relations=rel, figures={"trajectory.png": fig})
    m = json.loads((args.out / "metrics.json").read_text())
    rel_err = {k: m["relations"][k] for k in ("trans_mean", "trans_std", "rot_mean", "rot_std", "matched")}
    print(json.dumps({"priors": m["priors"], "plan_accepted": m["plan_accepted"], "relations": rel_err}))


if __name__ == "__main__":
    main()
