"""Deferred steps (FRSlam.defer): a hook's work split over the following scans, one step per
scan, in order, deterministic; the floor-plan updater's relocalisations use them."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_world import ROOM_LOOP, drifting_odometry, room_world, route, scans_along

from frslam_graph.backend.deferred import DeferredSteps
from frslam_graph.config import FRSlamConfig
from frslam_graph.odometry import worker as odometry_worker
from frslam_graph.offline import process
from frslam_graph.plan_updates.updater import FloorPlanUpdater
from frslam_graph.registration import Registration
from frslam_graph.slam import FRSlam

ROOM_CFG = {"odometry": {"max_range": 10.0}}


@pytest.fixture(scope="module")
def room():
    truth = route(ROOM_LOOP)
    ranges, amin, inc = scans_along(room_world(), truth)
    return truth[:200], ranges[:200], amin, inc, drifting_odometry(truth)[:200]


class StepHook:
    """At keyframes 3 and 4 defers a job of three steps; records (job, step, scan count)."""

    def __init__(self):
        self.done: list[tuple[int, int, int]] = []

    def job(self, ctx, k):
        for step in range(3):
            self.done.append((k, step, len(ctx.store.scans)))
            if step < 2:
                yield

    def on_keyframe(self, ctx, kf):
        if kf.index in (3, 4):
            ctx.deferred.defer(self.job(ctx, kf.index))

    def on_finish(self, ctx):
        pass


def feed(slam, room, n):
    truth, ranges, amin, inc, wheel = room
    for i in range(n):
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, wheel[i])


def test_one_deferred_step_per_scan_in_order_without_loop_closure_work(room):
    hook = StepHook()
    slam = FRSlam({**ROOM_CFG, "loop_closure": {"enabled": True}}, update_strategy=hook)
    lc_scans = []
    on_scan = slam.loop_closer.on_scan
    slam.loop_closer.on_scan = lambda s: lc_scans.append(len(s.store.scans)) or on_scan(s)
    feed(slam, room, 150)
    assert len(hook.done) == 6 and slam.context.deferred.pending == 0
    assert [(k, s) for k, s, _ in hook.done] == [(3, 0), (3, 1), (3, 2), (4, 0), (4, 1), (4, 2)]
    scans = [n for _, _, n in hook.done]
    # each step on its own scan, after the keyframe that deferred it; job 4 after job 3
    assert scans == sorted(scans) and len(set(scans)) == 6
    kf3 = slam.keyframe(3).scan_index
    assert scans[0] == kf3 + 2  # the next scan (len(slam) counts the scan being added)
    assert not set(scans) & set(lc_scans)  # a scan that ran a step did no loop-closure work
    assert lc_scans  # ... the others did


def test_pending_steps_run_in_finish_process_and_on_request(room):
    truth, ranges, amin, inc, wheel = room
    hook = StepHook()
    slam = FRSlam(ROOM_CFG, update_strategy=hook)
    feed(slam, room, 200)
    # stop right after keyframe 4 deferred its job: nothing is lost
    hook2 = StepHook()
    slam2 = FRSlam(ROOM_CFG, update_strategy=hook2)
    feed(slam2, room, slam.keyframe(4).scan_index + 1)
    assert slam2.context.deferred.pending >= 1
    slam2.context.deferred.run_all()
    assert slam2.context.deferred.pending == 0 and len(hook2.done) == 6
    hook3 = StepHook()
    slam3 = FRSlam(ROOM_CFG, update_strategy=hook3)
    feed(slam3, room, slam.keyframe(4).scan_index + 1)
    slam3.finish()
    assert len(hook3.done) == 6
    from frslam_graph.datasets import Scan

    angles = amin + inc * np.arange(len(ranges[0]))
    scans = [
        Scan(float(truth[i, 0]), ranges[i], angles, tuple(wheel[i]), 10.0)
        for i in range(slam.keyframe(4).scan_index + 1)
    ]
    hook4 = StepHook()
    process(FRSlam(ROOM_CFG, update_strategy=hook4), scans, batch=False, parallel=False)
    assert [(k, s) for k, s, _ in hook4.done] == [(3, 0), (3, 1), (3, 2), (4, 0), (4, 1), (4, 2)]


# --------------------------------------------------------------------- floor-plan updater


@pytest.fixture(scope="module")
def house(five_room_sim):
    return five_room_sim


def run_plan(house, spread: bool, parallel: bool = False):
    plan, run, m = house
    # the registration in its keyframe's step (background_registration_s 0): these tests follow
    # the relocalisations' steps
    cfg = FRSlamConfig().with_updates(
        loop_closure={"enabled": False},
        updates={"spread_over_scans": spread, "background_registration_s": 0.0},
    )
    upd = FloorPlanUpdater(
        plan, cfg.updates, register_fn=lambda p, g: Registration.from_matrix(m, score=0.9, ambiguity=0.2)
    )
    slam = FRSlam(cfg, update_strategy=upd)
    added = []  # (keyframe's scan index, scan count when the prior went in)
    add = slam.context.add_prior
    slam.context.add_prior = lambda kf, *a, **k: (
        added.append((slam.keyframe(kf).scan_index, len(slam), k.get("extra_iterations"))) or add(kf, *a, **k)
    )
    res = process(slam, run.scans, parallel=parallel)
    return upd, slam, res, added


def test_relocalisation_priors_go_in_on_later_scans_with_the_same_decisions(house):
    upd_now, _, res_now, added_now = run_plan(house, spread=False)
    upd, slam, res, added = run_plan(house, spread=True)
    # without spreading every prior goes in on its keyframe's scan (len(slam) counts that scan)
    assert all(n == i + 1 for i, n, _ in added_now)
    # spread: the relocalisation on the next scan that is not a keyframe, the prior on the one
    # after, then one relinearising iteration per such scan (extra_iterations 0 here); the last
    # one maybe in process()'s end
    reloc = [(i, n - 1) for i, n, it in added[1:]]  # (keyframe's scan, scan of the prior)
    assert len(reloc) >= 5 and all(it == 0 for _, _, it in added[1:])
    assert all(j > i for i, j in reloc[:-1])
    # ... unless the next relocalisation comes first (a turn: a keyframe at every scan), which
    # runs what is pending before it
    kf_scans = {k.scan_index for k in slam.keyframes()}
    regular = [j == [s for s in range(i + 1, len(slam)) if s not in kf_scans][1] for i, j in reloc[:-1]]
    assert sum(regular) >= 0.7 * len(regular), regular
    # the same decisions on the same keyframes (nothing else changed the graph in between here)
    assert [(e.kind, e.keyframe) for e in upd.log] == [(e.kind, e.keyframe) for e in upd_now.log]
    assert slam.context.deferred.pending == 0
    # the trajectory barely differs (settled a few scans later)
    err = np.abs(res.trajectory[:, 1:3] - res_now.trajectory[:, 1:3]).max()
    assert err < 0.02, err
    # deterministic: the schedule depends on the scans only
    _, _, again, _ = run_plan(house, spread=True)
    np.testing.assert_array_equal(again.trajectory, res.trajectory)


@pytest.mark.skipif(
    not odometry_worker.available(FRSlamConfig().odometry),
    reason="the odometry worker needs Linux fork, two cores and a non-daemonic process",
)
def test_spread_steps_give_the_same_run_with_the_odometry_worker(house):
    _, _, seq, _ = run_plan(house, spread=True, parallel=False)
    upd, _, par, _ = run_plan(house, spread=True, parallel=True)
    assert par.parallel
    np.testing.assert_array_equal(par.trajectory, seq.trajectory)
    assert any(e.kind == "prior_added" for e in upd.log)


def test_defer_takes_a_generator_not_a_function(room):
    slam = FRSlam(ROOM_CFG)

    def job():
        yield

    with pytest.raises(TypeError, match="generator"):
        slam.context.deferred.defer(job)  # the function, not its generator
    slam.context.deferred.defer(job())
    assert slam.context.deferred.pending == 1


class CostedHook:
    """At keyframes 3 and 4 defers a job whose steps announce their estimated cost (ms)."""

    COSTS = (3.0, 8.0, 1.0)

    def __init__(self):
        self.done: list[tuple[int, int, int]] = []

    def job(self, ctx, k):
        for step, cost in enumerate(self.COSTS):
            self.done.append((k, step, len(ctx.store.scans)))
            yield cost

    def on_keyframe(self, ctx, kf):
        if kf.index in (3, 4):
            ctx.deferred.defer(self.job(ctx, kf.index))

    def on_finish(self, ctx):
        pass


def test_loop_closure_gets_the_rest_of_the_budget_a_costed_step_leaves(room):
    hook = CostedHook()
    slam = FRSlam({**ROOM_CFG, "loop_closure": {"enabled": True, "budget_ms": 8.0}}, update_strategy=hook)
    budgets: dict[int, float | None] = {}  # scan count -> budget given to the loop closer
    on_scan = slam.loop_closer.on_scan
    slam.loop_closer.on_scan = lambda s, b=None: budgets.__setitem__(len(s.store.scans), b) or on_scan(s, b)
    feed(slam, room, 150)
    assert [(k, s) for k, s, _ in hook.done] == [(3, 0), (3, 1), (3, 2), (4, 0), (4, 1), (4, 2)]
    scans = [n for _, _, n in hook.done]
    assert len(set(scans)) == 6  # one step per scan; job 3's end is glue: job 4 follows at once
    assert [budgets.get(n, "none") for n in scans] == [5.0, "none", 7.0, 5.0, "none", 7.0]
    others = [b for n, b in budgets.items() if n not in scans]
    assert others and all(b is None for b in others)  # scans without a step: the whole budget


def test_relocalisation_steps_announce_their_costs(house, monkeypatch):
    # every step of the updater's deferred work gives a finite estimate, so the loop closer keeps
    # the rest of those scans' budgets instead of starving while the plan is worked on
    spent: list[float] = []
    step = DeferredSteps.step

    def record(self):
        out = step(self)
        if out is not None:
            spent.append(out)
        return out

    monkeypatch.setattr(DeferredSteps, "step", record)
    _, slam, _, added = run_plan(house, spread=True)
    assert len(added) >= 5 and len(spent) >= 3 * len(added)
    assert all(0.0 < s < FRSlamConfig().loop_closure.budget_ms for s in spent), sorted(set(spent))
