"""Dev diagnosis (session 13): every registration of one simulated house's plan run, with the
one-sided and the current MFR answer (``two``; at fed0866 the full two-sided fit) on the same
map, against the simulator's truth; ``d1`` is the one-sided fit's wall offset (m).

    python tools/dev_regime_regs.py --house 00dd --regime B --answer one|two [--out X.json]

The run uses the answer ``--answer``; at every registration both answers are computed on the same
grid (MFR is deterministic) and compared with the truth for the map as it is then: the SE(2)
aligning the keyframes' estimates to their true poses (least squares), composed with the house's
distortion (plan -> house metres). Errors: RMS over the plan's room corners (m), scale ratios.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_backend as bb  # noqa: E402
from _fit_capture import CAPTURE, MODE  # noqa: E402  (installs the capturing final fit)
from frslam_graph.datasets.simulator import SimulationOptions, simulate_run  # noqa: E402

from frslam_graph.config import FRSlamConfig  # noqa: E402
from frslam_graph.evaluation.metrics import ate  # noqa: E402
from frslam_graph.floorplan import FloorPlan  # noqa: E402
from frslam_graph.offline import process  # noqa: E402
from frslam_graph.plan_updates.updater import FloorPlanUpdater  # noqa: E402
from frslam_graph.registration import register  # noqa: E402
from frslam_graph.slam import FRSlam  # noqa: E402


def rigid_align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 rigid (no scale) least-squares map of src (N,2) onto dst (N,2)."""
    ms, md = src.mean(0), dst.mean(0)
    h = (src - ms).T @ (dst - md)
    u, _, vt = np.linalg.svd(h)
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    m = np.eye(3)
    m[:2, :2] = r
    m[:2, 2] = md - r @ ms
    return m


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--house", default="00dd")
    ap.add_argument("--regime", default="B")
    ap.add_argument("--answer", choices=["one", "two"], default="two")
    ap.add_argument("--out")
    ap.add_argument("--dump", help="pickle every registration's (plan, grid, truth) here")
    args = ap.parse_args()
    cands = bb.candidate_plans()
    k = next(i for i, p in enumerate(cands) if p.stem.startswith(args.house))
    plan = FloorPlan.load(cands[k])
    spec = bb.REGIMES[args.regime]
    opts = SimulationOptions(length=200.0, beams=720, scan_rate=10.0, max_speed=1.0, **spec["sim"])
    run = simulate_run(plan, seed=k, options=opts)
    cfg = FRSlamConfig().with_updates(**spec["cfg"]) if spec["cfg"] else FRSlamConfig()
    dist = run.house.distortion.matrix
    corners = np.concatenate([np.asarray(r.polygon.exterior.coords)[:-1] for r in plan.rooms])
    truth_by_stamp = {round(float(s), 6): p for s, p in zip(run.stamps, run.true_poses, strict=True)}
    records: list[dict] = []
    dumps: list = []

    def err(m_reg: np.ndarray, m_true: np.ndarray) -> dict:
        a = corners @ m_reg[:2, :2].T + m_reg[:2, 2]
        b = corners @ m_true[:2, :2].T + m_true[:2, 2]
        d = np.hypot(*(a - b).T)
        s_reg = np.linalg.svd(m_reg[:2, :2], compute_uv=False)
        s_true = np.linalg.svd(m_true[:2, :2], compute_uv=False)
        return {
            "rms_m": float(np.sqrt(np.mean(d**2))),
            "max_m": float(d.max()),
            "scale_ratio": (s_reg / s_true).tolist(),
            "det_sign_ok": bool(
                np.sign(np.linalg.det(m_reg[:2, :2])) == np.sign(np.linalg.det(m_true[:2, :2]))
            ),
        }

    class Updater(FloorPlanUpdater):
        def _attempt_on(self, view, keyframe, keep, *a):
            est = view.graph.estimates()
            n = len(est)
            stamps = [round(float(view.keyframe(i).stamp), 6) for i in range(n)]
            tru = np.array([truth_by_stamp[s] for s in stamps])
            # map <- house: align the estimates' positions to the truth's
            m_align = rigid_align(tru[:, :2], est[:, :2])
            m_true = m_align @ dist
            traj_err = np.hypot(*((tru[:, :2] @ m_align[:2, :2].T + m_align[:2, 2]) - est[:, :2]).T)
            rec = {
                "kf": int(keyframe.index),
                "stamp": float(keyframe.stamp),
                "local": keep is not None,
                "map_rms_after_align_m": float(np.sqrt(np.mean(traj_err**2))),
                "map_max_after_align_m": float(traj_err.max()),
            }
            self._diag = rec
            self._diag_true = m_true
            return super()._attempt_on(view, keyframe, keep, *a)

    def reg_fn(p, grid):
        rec, m_true = upd._diag, upd._diag_true
        out = {}
        for ans in ("one", "two"):
            MODE["answer"] = ans
            t = time.process_time()
            CAPTURE.clear()
            r = register(p, grid)
            if "one" in CAPTURE:
                rec[f"d1_{ans}"] = CAPTURE["one"].delta
            if "two" in CAPTURE:
                rec[f"d2_{ans}"] = CAPTURE["two"].delta
            out[ans] = r
            rec[f"cpu_{ans}_s"] = time.process_time() - t
            rec[f"ok_{ans}"] = bool(r.ok)
            if r.ok:
                rec[f"err_{ans}"] = err(r.matrix, m_true)
                rec[f"scale_{ans}"] = [float(v) for v in r.scale]
                rec[f"score_{ans}"] = float(r.score)
                rec[f"amb_{ans}"] = float(r.ambiguity)
        MODE["answer"] = args.answer
        rec["grid_shape"] = list(grid.data.shape) if hasattr(grid, "data") else None
        records.append(rec)
        if args.dump:
            dumps.append((rec["kf"], grid, m_true))
        return out[args.answer]

    upd = Updater(plan, cfg.updates, register_fn=reg_fn)
    slam = FRSlam(cfg, update_strategy=upd)
    t0 = time.process_time()
    res = process(slam, run.scans, parallel=False)
    stats, _ = ate(res.trajectory, run.ground_truth)
    # the decisions, with the registration events' verdicts
    events = [
        {"kind": e.kind, "kf": e.keyframe, "accepted": e.accepted, "msg": e.message[:160]}
        for e in upd.log
        if e.kind in ("register", "registration_replaced", "registration_retracted", "plan_refined")
        or e.kind.startswith("prior_")
    ]
    print(
        f"house {cands[k].stem} regime {args.regime} answer {args.answer}: ATE {stats.rmse:.4f} m, "
        f"cpu {time.process_time() - t0:.0f} s, registrations {len(records)}"
    )
    for r in records:
        line = f"kf {r['kf']:4d} local={int(r['local'])} map_rms {r['map_rms_after_align_m']:.3f}"
        for ans in ("one", "two"):
            if r.get(f"ok_{ans}"):
                e = r[f"err_{ans}"]
                line += f" | {ans}: d1 {r.get('d1_' + ans, float('nan')):+.3f} rms {e['rms_m']:.3f} max {e['max_m']:.3f} sc {e['scale_ratio'][0]:.4f},{e['scale_ratio'][1]:.4f}"
            else:
                line += f" | {ans}: refused"
        print(line)
    from collections import Counter  # noqa: PLC0415

    print(Counter((e["kind"], e["accepted"]) for e in events))
    if args.dump:
        import pickle  # noqa: PLC0415

        Path(args.dump).write_bytes(pickle.dumps({"plan": cands[k], "regs": dumps}))
    if args.out:
        Path(args.out).write_text(
            json.dumps({"ate": float(stats.rmse), "records": records, "events": events}, indent=1)
        )


if __name__ == "__main__":
    main()
