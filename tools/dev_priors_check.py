"""Dev check of the floor-plan priors: simulated house through FRSlam with and without the plan.

Prints a Markdown table of ATE RMSE (SE(2)-aligned, metres) for: no plan, the right plan,
a plan of another building, and the right plan with a fraction of deliberately wrong
registrations; plus the update strategy's decisions. Issue 5 targets: 2 % odometry drift,
routes >= 200 m: ATE with priors <= 0.10 m and >= 5x lower than without; wrong building no worse
than without; 25 % wrong registrations within 10 % of the clean run.

    python tools/dev_priors_check.py --plan synthetic --length 200 --seeds 0 1
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from pathlib import Path

import numpy as np
from frslam_graph.datasets.simulator import SimulationOptions, five_room_plan, simulate_run

from frslam_graph.config import FRSlamConfig
from frslam_graph.evaluation.metrics import ate
from frslam_graph.floorplan import FloorPlan
from frslam_graph.offline import process
from frslam_graph.plan_updates.updater import FloorPlanUpdater
from frslam_graph.registration import Registration, register
from frslam_graph.slam import FRSlam

R2V = Path(__file__).resolve().parents[1] / "frslam_graph" / "data" / "r2v"


def load_plan(name: str) -> FloorPlan:
    if name == "synthetic":
        return five_room_plan()
    if name == "r2v":
        return FloorPlan.load(next(R2V.glob("*.txt")))
    return FloorPlan.load(name)


class WrongRegistrations:
    """Registration source that corrupts a fraction of the results (rotation / flip / shift)."""

    def __init__(self, fraction: float, seed: int = 0):
        self.fraction = fraction
        self.rng = np.random.default_rng(seed)
        self.marks: list[bool] = []  # per call: corrupted

    @property
    def calls(self) -> int:
        return len(self.marks)

    @property
    def corrupted(self) -> int:
        return sum(self.marks)

    def __call__(self, plan, grid):
        reg = register(plan, grid)
        if not reg.ok or self.rng.random() >= self.fraction:
            self.marks.append(False)
            return reg
        self.marks.append(True)
        m = reg.matrix.copy()
        c = m[:2, :2] @ np.array(plan.bounds).reshape(2, 2).mean(0) + m[:2, 2]  # plan centre in map
        kind = self.rng.integers(3)
        if kind == 0:  # rotate 90 / 180 degrees about the plan centre
            a = np.pi / 2 * self.rng.integers(1, 4)
            r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        elif kind == 1:  # mirror about the centre
            r = np.diag([-1.0, 1.0])
        else:  # shift by 1-3 m
            r = np.eye(2)
        t = self.rng.uniform(1.0, 3.0) * np.array([np.cos(a := self.rng.uniform(0, 6.3)), np.sin(a)])
        wrong = np.eye(3)
        wrong[:2, :2] = r
        wrong[:2, 2] = c - r @ c + (t if kind == 2 else 0.0)
        return Registration.from_matrix(
            wrong @ m, score=reg.score, ambiguity=reg.ambiguity, method="corrupted", rooms=reg.rooms
        )


def run_once(run, plan, cfg, register_fn=None):
    updater = None
    if plan is not None:
        updater = FloorPlanUpdater(plan, cfg.updates, register_fn=register_fn)
    slam = FRSlam(config=cfg, update_strategy=updater)
    t0 = time.perf_counter()
    res = process(slam, run.scans)
    wall = time.perf_counter() - t0
    stats, _ = ate(res.trajectory, run.ground_truth)
    return stats.rmse, wall, updater, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", default="synthetic", help="synthetic | r2v | path to a plan")
    ap.add_argument("--other", default=None, help="plan of another building (default: the other bundled one)")
    ap.add_argument("--length", type=float, default=200.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--wrong-frac", type=float, default=0.25)
    ap.add_argument("--beams", type=int, default=720)
    ap.add_argument("--modes", nargs="+", default=["none", "plan", "other", "wrong"])
    ap.add_argument(
        "--wheel-only",
        action="store_true",
        help="no scan matching in the odometry (motion model on the wheel odometry, ~2 %% drift)",
    )
    ap.add_argument(
        "--prior-floor",
        type=float,
        nargs=2,
        metavar=("XY_M", "THETA_DEG"),
        help="sigma floors of the floor-plan priors (graph and relocalisation), e.g. 0.005 0.1",
    )
    ap.add_argument("--no-loop-closure", action="store_true")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    plan = load_plan(args.plan)
    other = load_plan(args.other or ("r2v" if args.plan == "synthetic" else "synthetic"))
    cfg = FRSlamConfig()
    if args.wheel_only:  # fewer valid points than this -> motion-model fallback instead of ICP
        cfg = cfg.with_updates(odometry={"min_points": 10**9})
    if args.prior_floor:
        xy, th = args.prior_floor
        cfg = cfg.with_updates(
            graph={"prior_sigma_floor_xy": xy, "prior_sigma_floor_theta_deg": th},
            updates={"reloc_sigma_floor_xy": xy, "reloc_sigma_floor_theta_deg": th},
        )
    if args.no_loop_closure:
        cfg = cfg.with_updates(loop_closure={"enabled": False})
    print(
        "| seed | route m | mode | ATE RMSE m | ratio vs none | run s | registrations acc/tried | priors added/rejected/removed |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        opts = SimulationOptions(length=args.length, beams=args.beams, fov_deg=360.0, max_range=20.0)
        run = simulate_run(plan, seed=seed, options=opts)
        route_len = float(np.sum(np.hypot(*np.diff(run.true_poses[:, :2], axis=0).T)))
        base = None
        for mode in args.modes:
            p, fn = None, None
            if mode == "plan":
                p = plan
            elif mode == "other":
                p = other
            elif mode == "wrong":
                p, fn = plan, WrongRegistrations(args.wrong_frac, seed)
            rmse, wall, upd, _ = run_once(run, p, cfg, fn)
            if mode == "none":
                base = rmse
            regs = prs = ""
            if upd is not None:
                c = Counter(e.kind for e in upd.log)
                acc = sum(
                    1 for e in upd.log if e.kind in ("register", "registration_replaced") and e.accepted
                )
                regs = f"{acc}/{c['register'] + c['registration_replaced']}"
                prs = f"{c['prior_added']}/{c['prior_rejected']}/{c['prior_removed']}"
                if fn is not None:
                    regs += f" ({fn.corrupted} corrupted of {fn.calls})"
            ratio = f"{base / rmse:.1f}x" if base and mode != "none" else ""
            print(
                f"| {seed} | {route_len:.0f} | {mode} | {rmse:.3f} | {ratio} | {wall:.1f} | {regs} | {prs} |"
            )
            if args.verbose and upd is not None:
                for e in upd.log:
                    if e.kind != "relocalise":
                        print(f"    {e.stamp - run.stamps[0]:7.1f}s kf{e.keyframe} {e.kind}: {e.message}")
                print("    timings", {k: round(v, 2) for k, v in upd.timings.items()})


if __name__ == "__main__":
    main()
