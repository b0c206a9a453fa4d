"""What the slow scans of a streaming run are made of: per scan, the CPU of the odometry and of
each backend stage (issue 19: per-scan CPU p99 <= 20 ms, no scan over 200 ms).

    .venv/bin/python tools/dev_tail.py fr079 --json /tmp/tail_fr079.json   # as `frslam run`
    .venv/bin/python tools/dev_tail.py fr079_250 --serial                   # odometry split too
    .venv/bin/python tools/dev_tail.py simA0 --plan                         # a simulated house, its plan
    .venv/bin/python tools/dev_tail.py intel --floor-plan $D/floorplans/ipa/lab_intel.png
    .venv/bin/python tools/dev_tail.py aces --config /tmp/budget5.yaml      # another configuration (real logs)

The run is ``run_recording`` as ``tools/bench_slam.py`` runs it (odometry in its worker unless
``--serial``). Library functions are wrapped here (nothing in the library changes) and charged
their *exclusive* CPU time of the backend's main thread (``time.thread_time``: the reader's
read-ahead thread is left out, as in ``metrics.json``'s ``latency_cpu_ms``); a scan's odometry
CPU is its ``cpu_latencies`` entry minus the backend's part. Unlike ``tools/dev_stages.py`` the
graph's iSAM2 updates are charged to what asked for them (keyframe insertion, a closure's factor,
a settle iteration). Prints the per-scan CPU median / p99 / max and, for the scans over
``--over`` ms, the top 1 % and the slowest, their stages; ``--json`` keeps every scan's stages.

``simA0`` .. ``simB2``: house 0-2 of ``tools/bench_backend.py``'s section 2 in regime A or B (its
simulated run: 200 m, the house's seed), streamed through ``process`` as that benchmark does; with
``--plan`` the house's own floor plan (``FRSlam(floor_plan=plan)``), whose update strategy's stages
are charged too ("plan: ..."), and the scans where a deferred-steps drain (``run_all``) or a
re-anchoring of the priors ran are marked (their inclusive CPU).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _paths import SHARED_DATA as DATA  # noqa: E402
from dev_stages import LOGS, Stages, wrap_odometry


def _wrap_job_steps(st: Stages, closer_cls: Any, out: list) -> None:
    """Time each step of the loop closer's jobs (``LoopCloser._job``, the matching and the graph
    updates it drives): (cost the step announced in ms, its thread CPU in ms, the stage that took
    most of it) appended to ``out``; the job's own code is charged as "closer: job glue"."""

    def on_step(args: tuple) -> Callable[[float], None]:
        announced = args[0]._next_cost  # what the previous yield said this step costs
        before = dict(st._scan)

        def done(spent: float) -> None:
            delta = {k: v - before.get(k, 0.0) for k, v in st._scan.items()}
            out.append((announced, 1e3 * spent, max(delta, key=delta.get)))

        return done

    st.wrap_gen(closer_cls, "_job", "closer: job glue", on_step)


def steps_summary(steps: list) -> None:
    """Per kind of step (the stage that took most of it): announced against measured CPU."""
    if not steps:
        return
    print(
        "loop-closer steps by their main stage: n, announced ms median, CPU ms median / p99 / max, CPU/announced median / p90"
    )
    kinds = sorted({s[2] for s in steps})
    for kind in sorted(kinds, key=lambda k: -sum(s[1] for s in steps if s[2] == k)):
        a = np.array([s[0] for s in steps if s[2] == kind])
        c = np.array([s[1] for s in steps if s[2] == kind])
        r = c[a > 0] / a[a > 0]
        ratio = f"{np.median(r):.1f} / {np.percentile(r, 90):.1f}" if len(r) else "-"
        print(
            f"  {kind}: {len(c)}, {np.median(a):.2f}, {np.median(c):.2f} / {np.percentile(c, 99):.1f} / "
            f"{c.max():.0f}, {ratio}"
        )


SIM = {f"sim{r}{k}": (r, k) for r in "AB" for k in range(3)}


def simulated(name: str, with_plan: bool) -> tuple[Any, Any, Any]:
    """(FRSlam, scans, ground truth) of house ``k`` of ``bench_backend``'s section 2 in regime
    ``r`` (``SIM[name]``), with the house's plan when ``with_plan``."""
    import bench_backend as bb
    from frslam_graph.datasets.simulator import SimulationOptions, simulate_run

    from frslam_graph.config import FRSlamConfig
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.slam import FRSlam

    regime, k = SIM[name]
    spec = bb.REGIMES[regime]
    plan = FloorPlan.load(bb.candidate_plans()[k])
    opts = SimulationOptions(length=200.0, beams=720, scan_rate=10.0, max_speed=1.0, **spec["sim"])
    run = simulate_run(plan, seed=k, options=opts)
    cfg = FRSlamConfig().with_updates(**spec["cfg"]) if spec["cfg"] else FRSlamConfig()
    return FRSlam(cfg, floor_plan=plan if with_plan else None), run.scans, run.ground_truth


def instrument_plan(st: Stages, facts: dict[str, Any]) -> None:
    """Wrap the floor-plan update strategy's stages; ``facts["inclusive"]`` gets, per scan, the
    inclusive CPU (s) of the deferred-steps drains and of the priors' re-anchorings."""
    import functools

    from frslam_graph import registration
    from frslam_graph.backend import deferred, graph, mapping
    from frslam_graph.localisation import relocalisation
    from frslam_graph.plan_updates import evidence, judge, priors, refiner, updater

    fu = updater.FloorPlanUpdater
    st.wrap(fu, "on_keyframe", "plan: updater glue")
    st.wrap(fu, "_attempt_on", "plan: registration attempt glue")
    st.wrap(fu, "_recheck", "plan: recheck of the accepted")
    st.wrap(registration, "register", "plan: MFR registration")
    st.wrap(mapping.OccupancyMapper, "update", "plan: occupancy map")
    st.wrap(mapping, "occupancy_grid", "plan: occupancy map")
    st.wrap(judge.RegistrationJudge, "judge", "plan: judge")
    st.wrap(relocalisation.Relocaliser, "relocalise", "plan: relocalise")
    st.wrap(relocalisation.Relocaliser, "__init__", "plan: relocaliser build")
    st.wrap(priors.PriorManager, "offer", "plan: prior gate + add")
    st.wrap(priors.PriorManager, "check", "plan: priors check")
    st.wrap(priors.PriorManager, "reanchor", "plan: re-anchor glue")
    st.wrap(refiner.PlanRefiner, "scale", "plan: scale refinement")
    st.wrap(refiner.PlanRefiner, "start", "plan: start alignment")
    st.wrap(refiner, "fit_plan_scale", "plan: scale fit")
    st.wrap(evidence.ScanEvidence, "fit", "plan: scan evidence")
    pg = graph.PoseGraph
    st.wrap(pg, "add_prior", "graph: prior add (iSAM2)")
    st.wrap(pg, "remove_priors", "graph: prior removal (iSAM2)")
    st.wrap(pg, "marginal_covariance", "graph: marginal covariance")
    inclusive: dict[str, float] = {}
    facts["inclusive_now"] = inclusive

    def incl(owner: Any, name: str, label: str) -> None:
        fn = getattr(owner, name)

        @functools.wraps(fn)
        def timed(*a: Any, **k: Any) -> Any:
            c0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                inclusive[label] = inclusive.get(label, 0.0) + time.thread_time() - c0

        setattr(owner, name, timed)

    incl(deferred.DeferredSteps, "run_all", "deferred run_all")
    incl(priors.PriorManager, "reanchor", "re-anchoring")
    incl(fu, "_attempt_on", "registration attempt")


def instrument(st: Stages, serial: bool) -> dict[str, Any]:
    """Wrap the backend's stages (and the odometry's with ``serial``); returns a dict the
    per-scan wrapper fills with each scan's facts (keyframe, closer steps and cost)."""
    from frslam_graph import slam
    from frslam_graph.backend import graph
    from frslam_graph.loop_closure import closer, submap_matching

    if serial:
        wrap_odometry(st, "odometry: body points")
    pg = graph.PoseGraph
    st.wrap(pg, "add_first", "graph: keyframe insert (iSAM2)")
    st.wrap(pg, "add_keyframe", "graph: keyframe insert (iSAM2)")
    st.wrap(pg, "_refresh_estimates", "graph: estimates refresh")
    st.wrap_gen(pg, "settle_steps", "graph: settle iteration (iSAM2)")
    st.wrap(pg, "add_factor", "graph: closure factor (iSAM2)")
    st.wrap(pg, "remove_factors", "graph: closure removal (iSAM2)")
    st.wrap_gen(pg, "optimize_batch_steps", "graph: LM batch setup")
    st.wrap(graph._InflightBatch, "iterate", "graph: LM iteration")
    st.wrap(pg, "_finish_inflight", "graph: LM batch end")
    st.wrap(pg, "_rebuild", "graph: iSAM2 rebuild")
    st.wrap(pg, "error", "graph: error()")
    lc = closer.LoopCloser
    for name in ("on_keyframe", "on_scan", "on_finish", "_work"):
        st.wrap(lc, name, "closer: glue")
    st.wrap(lc, "_plan", "closer: plan")
    st.wrap(lc, "_graph_distances", "closer: plan, graph distances")
    if hasattr(lc, "_descriptor"):  # place recognition (session 18's s18-place)
        st.wrap(lc, "_descriptor", "closer: place descriptor")
        st.wrap(lc, "_place_distances", "closer: plan, place ranking")
    st.wrap(lc, "_query_points", "closer: query submap")
    st.wrap_gen(lc, "_reference", "closer: reference submap points")
    facts: dict[str, Any] = {"rows": [], "steps": [], "inclusive": []}
    _wrap_job_steps(st, lc, facts["steps"])
    st.wrap_gen(lc, "_add", "closer: add closures glue")
    st.wrap_gen(lc, "_prune", "closer: prune glue")
    st.wrap_gen(lc, "_remove", "closer: prune glue")
    st.wrap(lc, "_residual_chi2", "closer: prune residuals")
    sm = submap_matching
    st.wrap_gen(sm, "match_scan_steps", "matcher: glue")
    closer.match_scan_steps = sm.match_scan_steps
    st.wrap(sm.ReferenceSubmap, "__init__", "matcher: reference field build")
    st.wrap(sm.ReferenceSubmap, "dilated", "matcher: field dilation")
    st.wrap_gen(sm, "_grid_search", "matcher: correlative search")
    st.wrap(sm, "_score_poses", "matcher: correlative fine level")
    st.wrap(sm.ReferenceSubmap, "prepare_icp", "matcher: normals + k-d tree")
    near = sm.ReferenceSubmap.nearest.fget

    class _Holder:
        fget = near

    st.wrap(_Holder, "fget", "matcher: nearest-point map")
    sm.ReferenceSubmap.nearest = property(_Holder.fget)
    st.wrap_gen(sm, "icp_point_to_line_many", "matcher: ICP")
    st.wrap(sm.ReferenceSubmap, "free_violation", "matcher: free space")
    st.wrap(sm.ReferenceSubmap, "inlier_fraction", "matcher: inliers")

    record = slam.FRSlam._record

    def record_and_mark(self: Any, res: Any, *a: Any, **k: Any) -> Any:
        c0 = time.thread_time()
        frame = ["backend: per-scan glue", c0, 0.0]
        st._stack.append(frame)
        try:
            return record(self, res, *a, **k)
        finally:
            st._stack.pop()
            spent = time.thread_time() - c0
            st._charge(frame[0], spent - frame[2])
            closer_ = self.loop_closer
            facts["rows"].append(
                (
                    bool(res.is_keyframe),
                    len(self.context.graph),
                    closer_.steps_last_call if closer_ else 0,
                    closer_.cost_last_call if closer_ else 0.0,
                    spent,
                )
            )
            if closer_ is not None:  # a call that did no work leaves these from the last one
                closer_.steps_last_call, closer_.cost_last_call = 0, 0.0
            now = facts.get("inclusive_now")
            if now is not None:
                facts["inclusive"].append(dict(now))
                now.clear()
            st.mark()

    slam.FRSlam._record = record_and_mark
    return facts


def summary(
    name: str,
    total: np.ndarray,
    odo: np.ndarray,
    scans: list[dict],
    rows: list,
    over: float,
    inclusive: list[dict] | None = None,
) -> None:
    """Print the spread and the stages of the slow scans (``inclusive``: per scan, the inclusive
    CPU in s of the drains and re-anchorings, :func:`instrument_plan`)."""
    kf = np.array([r[0] for r in rows])
    steps = np.array([r[2] for r in rows])
    cost = np.array([r[3] for r in rows])
    back = total - odo
    p = lambda a: f"{np.median(a):.1f} / {np.percentile(a, 99):.1f} / {a.max():.0f}"  # noqa: E731
    print(f"\n{name}: {len(total)} scans, {kf.sum()} keyframes; CPU per scan ms median / p99 / max:")
    print(f"  total {p(total)}; odometry {p(odo)}; backend {p(back)}")
    print(f"  keyframe scans: backend {p(back[kf])}; other scans: backend {p(back[~kf])}")
    labels = sorted({k for s in scans for k in s})

    def stages(mask: np.ndarray, title: str) -> None:
        n = int(mask.sum())
        if not n:
            print(f"{title}: none")
            return
        share = {k: sum(s.get(k, 0.0) for s, t in zip(scans, mask, strict=True) if t) * 1e3 for k in labels}
        if "odometry: point-to-line refinement" not in labels:  # the odometry ran in its worker: one figure
            share["odometry (worker)"] = float(odo[mask].sum())
        tot = float(total[mask].sum())
        print(
            f"{title}: {n} scans ({100 * n / len(total):.2f} %), {kf[mask].sum()} keyframes; "
            f"mean {tot / n:.1f} ms, of it (ms per scan):"
        )
        for k, v in sorted(share.items(), key=lambda kv: -kv[1]):
            if v > 0.01 * tot:
                print(f"    {k}: {v / n:.2f} ({100 * v / tot:.0f} %)")
        print(
            f"    closer steps per scan {steps[mask].mean():.1f}, announced cost {cost[mask].mean():.1f} ms "
            f"(CPU of the closer's stages {np.mean([sum(v for k, v in s.items() if k.startswith(('closer', 'matcher'))) for s, t in zip(scans, mask, strict=True) if t]) * 1e3:.1f} ms)"
        )

    stages(total > over, f"scans over {over:.0f} ms")
    stages(total >= np.percentile(total, 99), "scans at or above p99")
    print("slowest 15 (index: ms total, odometry; stages over 10 %; closer steps / announced ms):")
    for i in np.argsort(total)[::-1][:15]:
        parts = ", ".join(
            f"{k} {1e3 * v:.0f}"
            for k, v in sorted(scans[i].items(), key=lambda kv: -kv[1])
            if v * 1e3 > 0.1 * total[i]
        )
        kind = "KF" if kf[i] else "  "
        within = ", ".join(f"{k} {1e3 * v:.0f}" for k, v in (inclusive[i] if inclusive else {}).items())
        print(
            f"  {i} {kind}: {total[i]:.0f}, odo {odo[i]:.0f}; {parts}; {steps[i]} / {cost[i]:.1f} "
            f"({rows[i][1]} keyframes){'; within: ' + within if within else ''}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", choices=sorted(LOGS) + sorted(SIM))
    ap.add_argument("--serial", action="store_true", help="odometry in this process (its stages too)")
    ap.add_argument("--plan", action="store_true", help="sim*: with the house's floor plan")
    ap.add_argument("--floor-plan", type=Path, help="a real log: with this floor plan (its stages charged)")
    ap.add_argument("--over", type=float, default=20.0, help="ms; the scans over this are analysed")
    ap.add_argument("--json", type=Path, help="write every scan's stages here")
    ap.add_argument("--config", type=Path, help="FRSlamConfig YAML/JSON (default: the default configuration)")
    args = ap.parse_args()

    from frslam_graph.datasets import open_recording

    from frslam_graph.offline import run_recording

    st = Stages(clock=time.thread_time)
    facts = instrument(st, args.serial)
    parallel = False if args.serial else None
    c0 = time.process_time()
    if args.log in SIM:
        from frslam_graph.evaluation.metrics import ate
        from frslam_graph.offline import process

        if args.plan:
            instrument_plan(st, facts)
        slam, scans_in, truth = simulated(args.log, args.plan)
        res = process(slam, scans_in, parallel=parallel)
        run = type("Run", (), {"result": res, "slam": slam})
        stats, _ = ate(res.trajectory, truth)
        up = slam.update_strategy
        n_priors = len([h for h in slam.context.graph.priors() if h.source.startswith("reloc:")])
        print(
            f"{args.log}{' with its plan' if args.plan else ''}: ATE {stats.rmse:.4f} m; wall latency "
            f"max {1e3 * np.max(res.latencies):.0f} ms; priors at the end {n_priors}"
            + (
                f", registrations accepted {sum(1 for e in up.events('register') if e.data.get('accepted'))}"
                if up
                else ""
            )
        )
    else:
        path, _ = (DATA / p for p in LOGS[args.log])
        if args.floor_plan is not None:
            from frslam_graph.floorplan import FloorPlan

            instrument_plan(st, facts)
        plan = FloorPlan.load(args.floor_plan) if args.floor_plan is not None else None
        run = run_recording(open_recording(path), config=args.config, floor_plan=plan, parallel=parallel)
        res = run.result
    total = res.cpu_latencies * 1e3
    rows = facts["rows"]
    back = np.array([r[4] for r in rows]) * 1e3
    if len(back) != len(total):
        raise SystemExit(f"{len(back)} backend scans against {len(total)} latencies")
    odo = total - back
    scans = st.per_scan[: len(total)]
    lc = run.slam.loop_closer.stats if run.slam.loop_closer else None
    print(
        f"{args.log}: run CPU here {time.process_time() - c0:.1f} s; closures {lc.accepted if lc else 0}, "
        f"batches {lc.batches if lc else 0}, attempts {lc.attempts if lc else 0}"
    )
    summary(args.log, total, odo, scans, rows, args.over, facts["inclusive"][: len(total)])
    steps_summary(facts["steps"])
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "log": args.log,
                    "serial": args.serial,
                    "total_ms": total.tolist(),
                    "odometry_ms": odo.tolist(),
                    "rows": rows,
                    "steps": facts["steps"],
                    "stages": [{k: round(v * 1e3, 4) for k, v in s.items()} for s in scans],
                    "trajectory": res.trajectory.tolist(),
                }
            )
        )


if __name__ == "__main__":
    main()
