"""Registration of the floor plan off the scan that triggered it (``updates.background_registration_s``):
the triggering scan returns while the registration is still running, and when its verdict is
applied depends on the recording's stamps only, never on how fast the registration ran."""

from __future__ import annotations

import threading
import time

import numpy as np

from frslam_graph.config import FRSlamConfig
from frslam_graph.offline import process
from frslam_graph.plan_updates.updater import FloorPlanUpdater
from frslam_graph.registration import Registration
from frslam_graph.slam import FRSlam

CFG = FRSlamConfig().with_updates(loop_closure={"enabled": False}, updates={"final_refine": False})
# only a deadlock guard for the failing case: a passing run never waits this long
GUARD_S = 30.0


def _updater(plan, register, lag: float) -> FloorPlanUpdater:
    return FloorPlanUpdater(plan, CFG.updates.model_copy(update={"background_registration_s": lag}), register)


def test_the_triggering_scan_returns_while_the_registration_runs(five_room_sim):
    plan, run, m = five_room_sim
    release, done = threading.Event(), []

    def register(plan_, grid):
        released = release.wait(GUARD_S)  # held until the test has seen add() return
        done.append(released)
        return Registration.from_matrix(m, score=0.9, ambiguity=0.2, method="fake")

    upd = _updater(plan, register, 1.0)
    slam = FRSlam(config=CFG, update_strategy=upd)
    returned_while_running = None
    for scan in run.scans:
        slam.add(scan)
        if upd.schedule.attempts == 1 and returned_while_running is None:
            returned_while_running = not done  # add() came back, the registration is held
            release.set()
    slam.finish()
    assert returned_while_running is True
    assert done and all(done), "a registration ran inside add() (it waited for the test in vain)"
    reg = upd.events("register")
    assert reg and reg[0].accepted and len(upd.events("prior_added")) > 0


class _Watch:
    """The updater as a hook, noting the keyframe (and its stamp) after which each register
    event first appeared in the log."""

    def __init__(self, upd: FloorPlanUpdater) -> None:
        self.upd, self.applied, self.seen = upd, [], []

    def on_keyframe(self, ctx, keyframe):
        self.seen.append((keyframe.index, float(keyframe.stamp)))
        n = len(self.upd.events("register"))
        self.upd.on_keyframe(ctx, keyframe)
        self.applied += [(keyframe.index, float(keyframe.stamp))] * (len(self.upd.events("register")) - n)

    def on_finish(self, ctx):
        self.upd.on_finish(ctx)


def _run(plan, run, register, lag: float):
    watch = _Watch(_updater(plan, register, lag))
    slam = FRSlam(config=CFG, update_strategy=watch)
    res = process(slam, run.scans, parallel=False)
    events = [(e.stamp, e.kind, e.keyframe, e.message) for e in res.log]
    return watch, res, events


def _source(m, pause_s: float = 0.0):
    def register(plan_, grid):
        time.sleep(pause_s)  # a slow registration (wall time only: the results must not see it)
        return Registration.from_matrix(m, score=0.9, ambiguity=0.2, method="fake")

    return register


def test_when_a_verdict_is_applied_does_not_depend_on_how_fast_it_ran(five_room_sim):
    plan, run, m = five_room_sim
    _, fast, ev_fast = _run(plan, run, _source(m), 1.0)
    _, slow, ev_slow = _run(plan, run, _source(m, 0.3), 1.0)
    assert ev_fast == ev_slow
    assert np.array_equal(fast.trajectory, slow.trajectory)


def test_the_verdict_is_the_one_made_in_the_step_applied_later(five_room_sim):
    """With a lag, the registration is made on the same map at the same keyframe as in the step
    (same trigger, same verdict), applied at the first keyframe the lag later, and the run's
    priors are as many."""
    plan, run, m = five_room_sim
    now, _, _ = _run(plan, run, _source(m), 0.0)
    later, _, _ = _run(plan, run, _source(m), 2.0)
    first_now, first_later = now.upd.events("register")[0], later.upd.events("register")[0]
    assert first_now.keyframe == first_later.keyframe and first_now.accepted and first_later.accepted
    assert first_now.data["score"] == first_later.data["score"]
    assert now.applied[0][0] == first_now.keyframe  # in the step of its keyframe
    due = first_later.stamp + 2.0
    assert later.applied[0] == next(k for k in later.seen if k[1] >= due)  # the first keyframe that late
    n_now, n_later = len(now.upd.events("prior_added")), len(later.upd.events("prior_added"))
    assert n_later >= 0.8 * n_now > 0
