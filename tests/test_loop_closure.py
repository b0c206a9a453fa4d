"""Loop closure: matcher accuracy and ambiguity, drift corrected on a loop, wrong closures held
off by verification and the robust kernel, config switch."""

from __future__ import annotations

import dataclasses
import weakref

import gtsam
import numpy as np
import pytest
from synthetic_world import ROOM_LOOP, box, cast, corridor_world, room_world, route, scans_along, to_points

from frslam_graph.backend.graph import key
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError
from frslam_graph.loop_closure import closer as closer_module
from frslam_graph.loop_closure.closer import LoopCloser, LoopClosure
from frslam_graph.loop_closure.submap_matching import ReferenceSubmap, match_scan, transform_points
from frslam_graph.odometry.motion_model import between, compose
from frslam_graph.slam import FRSlam

CFG = {"odometry": {"max_range": 10.0}}


def _points(world, pose, seed=0):
    r, amin, inc = cast(world, np.asarray(pose, float), rng=np.random.default_rng(seed))
    return to_points(r, amin, inc)


def _reference(world, pose, cfg=None):
    cfg = cfg or FRSlamConfig().loop_closure
    pts = _points(world, pose, 1)  # in the frame of pose: the sensor sits at the origin
    return ReferenceSubmap(pts, cfg.resolution, cfg.likelihood_sigma, 6.0, [(np.zeros(2), pts)])


# ------------------------------------------------------------------------------------ matcher
def test_match_scan_recovers_the_relative_pose():
    world = room_world()
    a, b = np.array([4.0, 2.0, 0.3]), np.array([5.1, 2.6, 0.55])
    ref = _reference(world, a)
    truth = between(a, b)
    # the prediction is off by 0.8 m and 12 degrees: the grid search must find it
    guess = truth + np.array([0.6, -0.5, np.deg2rad(12.0)])
    m = match_scan(ref, _points(world, b, 2), guess, 1.5, np.deg2rad(20.0))
    assert m is not None
    err = between(truth, m.pose)
    assert np.hypot(err[0], err[1]) < 0.03 and abs(err[2]) < np.deg2rad(0.5)
    assert m.inlier_fraction > 0.75 and m.ambiguity < 0.8  # some of b is occluded from a
    w = np.linalg.eigvalsh(m.covariance)
    assert w.min() > 0 and np.sqrt(w.max()) < 0.05


def test_corridor_match_is_ambiguous_or_unsupported():
    # a featureless corridor: sliding along it fits equally well -> ambiguous, not accepted
    world = corridor_world(60.0, 2.0)
    cfg = FRSlamConfig().loop_closure
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.4, 0.1, 0.05])
    m = match_scan(_reference(world, a), _points(world, b, 3), between(a, b), 2.0, np.deg2rad(10.0), cfg)
    assert m is not None
    assert m.ambiguity > cfg.max_ambiguity


def test_similar_but_different_place_is_rejected():
    # two rooms of the same size but with different furniture: the walls alone do not match
    room_a = np.vstack([box(0, 0, 8, 6), box(2.0, 2.0, 2.6, 2.6), box(5.5, 3.5, 6.5, 4.2)])
    room_b = np.vstack([box(0, 0, 8, 6), box(5.0, 1.0, 5.6, 1.6), box(1.5, 4.0, 2.5, 4.7)])
    cfg = FRSlamConfig().loop_closure
    pose = np.array([4.0, 3.0, 0.0])
    ref = _reference(room_a, pose)
    m = match_scan(ref, _points(room_b, pose, 4), np.zeros(3), 2.0, np.deg2rad(30.0), cfg)
    assert m is not None and m.inlier_fraction > cfg.min_inlier_fraction  # the walls do fit
    assert m.free_violation > cfg.max_free_violation  # but b's furniture stands in a's free space
    # ... while the same room matches
    same = match_scan(ref, _points(room_a, pose, 5), np.zeros(3), 2.0, np.deg2rad(30.0), cfg)
    assert same.inlier_fraction >= cfg.min_inlier_fraction and same.ambiguity <= cfg.max_ambiguity
    assert same.free_violation < 0.02


# ------------------------------------------------------------------------------ full pipeline
def _inject_drift(slam: FRSlam, heading_per_m: float, scale: float) -> None:
    """Odometry between-factors get a heading bias per metre and a scale error (scans stay true)."""
    process = slam.odometry.process

    def drifting(*args, **kwargs):
        res = process(*args, **kwargs)
        if res is not None and res.between is not None:
            b = np.asarray(res.between, float)
            d = float(np.hypot(b[0], b[1]))
            bad = np.array([b[0] * (1 + scale), b[1] * (1 + scale), b[2] + heading_per_m * d])
            res = dataclasses.replace(res, between=bad)
        return res

    slam.odometry.process = drifting


@pytest.fixture(scope="module")
def two_laps():
    world = room_world()
    truth = route(ROOM_LOOP + ROOM_LOOP[1:] + ROOM_LOOP[1:2])  # about 2.3 laps of the room
    ranges, amin, inc = scans_along(world, truth)
    return truth, ranges, amin, inc


def _run(data, loop: bool):
    truth, ranges, amin, inc = data
    cfg = dict(CFG, loop_closure={"enabled": loop})
    slam = FRSlam(cfg)
    _inject_drift(slam, np.deg2rad(0.5), 0.02)
    for i in range(len(truth)):
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, None)
    slam.finish()
    err = _errors(slam, truth)
    return slam, float(np.sqrt(np.mean(err**2))), float(err[-1])


def _errors(slam: FRSlam, truth: np.ndarray) -> np.ndarray:
    """Position errors; without wheel odometry map starts at the first scan, so map -> world."""
    est = slam.trajectory()[:, 1:]
    world = np.array([compose(truth[0, 1:], p) for p in est])
    return np.hypot(*(world[:, :2] - truth[:, 1:3]).T)


@pytest.fixture(scope="module")
def runs(two_laps):
    return _run(two_laps, loop=False), _run(two_laps, loop=True)


def test_loop_closure_corrects_drift(runs):
    (_, ate_off, end_off), (slam, ate_on, end_on) = runs
    closures = [e for e in slam.log if e.kind == "loop_closure"]
    assert closures, "no loop closure on a route that revisits the room twice"
    assert ate_off > 0.5  # the injected drift is substantial
    assert ate_on < 0.2 * ate_off and end_on < 0.2 * end_off
    assert ate_on < 0.25  # a 2 % scale error is not observable by closures
    st = slam.loop_closer.stats
    assert st.accepted == len(slam.loop_closer.closures) == len(closures)
    # every closure is a factor of the batch graph between the two keyframes
    pairs = {(c.reference, c.query) for c in slam.loop_closer.closures}
    graph_pairs = {
        (int(gtsam.Symbol(f.keys()[0]).index()), int(gtsam.Symbol(f.keys()[1]).index()))
        for f in slam.graph._factors
        if isinstance(f, gtsam.BetweenFactorPose2)
    }
    assert pairs <= graph_pairs


def test_disabled_gives_no_closures(runs):
    (slam_off, _, _), _ = runs
    assert slam_off.loop_closer is None
    assert not [e for e in slam_off.log if e.kind.startswith("loop")]


def test_wrong_closure_cannot_bend_the_map(runs, two_laps):
    _, (slam, ate_on, _) = runs
    truth = two_laps[0]
    closer = slam.loop_closer
    good = closer.closures[-1]
    # a closure 3 m and 40 degrees off (e.g. a similar room elsewhere) under the robust kernel
    wrong_rel = compose(good.relative, np.array([3.0, -1.0, np.deg2rad(40.0)]))
    wrong = LoopClosure(good.reference, good.query, wrong_rel, good.covariance, good.match, np.zeros(3))
    slam.graph.add_factor(closer._factor(wrong, robust=True))
    slam.finish()
    err = _errors(slam, truth)
    assert np.sqrt(np.mean(err**2)) < max(2.0 * ate_on, 0.15)


def test_large_correction_waits_for_a_consistent_second_closure():
    closer = LoopCloser()
    est = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [10.0, 0.0, 0.0], [13.0, 0.0, 0.0], [13.5, 0.0, 0.0]])
    closer._travel = [0.0, 3.0, 10.0, 13.0, 13.5]
    m = None
    # keyframes 2 and 3 (3 m apart) are really at 0 and 3: both closures imply the same shift
    a = LoopClosure(0, 2, np.zeros(3), np.eye(3) * 1e-4, m, np.array([-10.0, 0.0, 0.0]))
    b = LoopClosure(1, 3, np.zeros(3), np.eye(3) * 1e-4, m, np.array([-10.0, 0.0, 0.0]))
    closer._pending.append(a)
    assert closer._consistent_pending(b, est) is a
    # a closure implying a different shift is not confirmed by it
    c = LoopClosure(1, 3, np.array([2.0, 0.0, 0.3]), np.eye(3) * 1e-4, m, np.zeros(3))
    assert closer._consistent_pending(c, est) is None


def test_a_closure_is_not_confirmed_by_one_from_a_query_submap_it_shares():
    """Two closures whose query keyframes lie 0.5 m of travel apart (under QUERY_TRAVEL) match
    nearly the same query points: they agree because they are the same match (FR079 with beams
    capped at 8 m: keyframes 1,198 and 1,200, 0.65 m apart, both 3 m along a corridor), so the
    second does not confirm the first; one from 3 m of travel away does."""
    closer = LoopCloser()
    est = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [10.0, 0.0, 0.0], [13.0, 0.0, 0.0], [13.5, 0.0, 0.0]])
    closer._travel = [0.0, 3.0, 10.0, 13.0, 13.5]
    shift = np.array([-10.0, 0.0, 0.0])
    a = LoopClosure(0, 3, np.array([3.0, 0.0, 0.0]), np.eye(3) * 1e-4, None, shift)
    near = LoopClosure(0, 4, np.array([3.5, 0.0, 0.0]), np.eye(3) * 1e-4, None, shift)
    far = LoopClosure(0, 2, np.zeros(3), np.eye(3) * 1e-4, None, shift)
    closer._pending.append(a)
    assert closer._consistent_pending(near, est) is None
    assert closer._consistent_pending(far, est) is a


def test_loop_closure_config_is_validated():
    cfg = FRSlamConfig()
    assert cfg.loop_closure.enabled
    with pytest.raises(ConfigError) as exc:
        FRSlamConfig.from_dict({"loop_closure": {"min_inlier_fraction": 1.5}})
    assert exc.value.where == "loop_closure.min_inlier_fraction"
    with pytest.raises(ConfigError):
        FRSlamConfig.from_dict({"loop_closure": {"no_such_field": 1}})


def test_correlative_scores_are_the_per_offset_means():
    """_grid_search gathers each point's window of offsets as one block; the scores equal the
    per-pose, per-offset look-ups written out (float32 means of the same values in the same
    order), and _score_poses those of single poses, off the grid included (the zero corner)."""
    from frslam_graph.loop_closure import submap_matching as sm
    from frslam_graph.steps import run_steps

    world = room_world()
    pts = to_points(*cast(world, np.array([2.0, 1.5, 0.3]), n_beams=360, max_range=15.0)[:3])
    ref = ReferenceSubmap(pts, 0.05, 0.1, 5.9)
    query = pts[::3] + 0.01
    rng = np.random.default_rng(2)
    for centre in (np.zeros(3), np.array([0.3, -0.2, 0.1]), np.array([9.0, 0.0, 0.0])):
        poses, scores = run_steps(sm._grid_search(ref, query, centre, 2.0, 0.3, 0.6, 0.05, 5.0, 300_000))
        cells = sm._dilation_cells(0.05, 0.6, 0.05, 5.0)
        field = ref.dilated(cells).reshape(ref.shape)
        h, w = ref.shape
        lim = int(np.ceil(2.0 / 0.6)) * 12
        for k in rng.choice(len(poses), 40, replace=False):
            c, s_ = np.cos(poses[k, 2]), np.sin(poses[k, 2])
            # the point's cell at the window's centre, then the offset (as the search steps)
            px = c * query[:, 0] - s_ * query[:, 1] + centre[0]
            py = s_ * query[:, 0] + c * query[:, 1] + centre[1]
            bx = np.floor((px - ref.origin[0]) / 0.05).astype(np.int64)
            by = np.floor((py - ref.origin[1]) / 0.05).astype(np.int64)
            out = (bx < lim) | (bx >= w - lim) | (by < lim) | (by >= h - lim)
            bx[out], by[out] = lim, lim
            ox = int(round((poses[k, 0] - centre[0]) / 0.05))
            oy = int(round((poses[k, 1] - centre[1]) / 0.05))
            assert scores[k] == field[by + oy, bx + ox].mean(dtype=np.float32)
        some = poses[rng.choice(len(poses), 30)] + rng.normal(0.0, 0.2, (30, 3))
        some[:3, :2] += 50.0  # off the grid: the corner cell, zero
        got = sm._score_poses(ref, query, some, 3)
        f3 = ref.dilated(3).reshape(ref.shape)
        for k, p in enumerate(some):
            c, s_ = np.cos(p[2]), np.sin(p[2])
            px = c * query[:, 0] - s_ * query[:, 1] + p[0]
            py = s_ * query[:, 0] + c * query[:, 1] + p[1]
            ix = np.floor((px - ref.origin[0]) / 0.05).astype(np.int64)
            iy = np.floor((py - ref.origin[1]) / 0.05).astype(np.int64)
            bad = (ix < 0) | (ix >= w) | (iy < 0) | (iy >= h)
            ix[bad], iy[bad] = 0, 0
            assert got[k] == f3[iy, ix].mean(dtype=np.float32)


def test_transform_points_matches_compose():
    pose = np.array([1.0, -2.0, 0.7])
    pts = np.array([[0.5, 0.2], [-1.0, 3.0]])
    out = transform_points(pose, pts)
    for p, o in zip(pts, out, strict=True):
        np.testing.assert_allclose(compose(pose, np.array([*p, 0.0]))[:2], o)
    assert key(3) == gtsam.symbol("x", 3)


def _straight_line_with_pending_closure(closer: LoopCloser) -> np.ndarray:
    """41 keyframes along x, 0.5 m apart, and a pending closure of keyframe 39 on old keyframe
    2; returns the estimates (41, 3)."""
    n = 41
    for k in range(n):
        closer._append_motion(np.array([0.5 * k, 0.0, 0.0]))
    closer._pending.append(LoopClosure(2, 39, np.zeros(3), np.eye(3) * 1e-4, None, np.zeros(3)))
    return np.column_stack((0.5 * np.arange(n), np.zeros(n), np.zeros(n)))


def test_pending_closure_predicts_where_to_look_next():
    closer = LoopCloser()
    # 40 keyframes along x, 0.5 m apart; keyframe 39 (at 19.5 m) matched old keyframe 2 at a
    # 10 m correction: keyframe 40 should be looked for near old keyframe 3 (1 m further on)
    est = _straight_line_with_pending_closure(closer)
    c, win_xy, win_th, centre = closer._hypothesis(est, 40)
    cfg = closer.config
    assert c == 3 and win_xy == cfg.hypothesis_window_xy
    assert win_th == pytest.approx(np.deg2rad(cfg.hypothesis_window_theta_deg))
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.0], atol=1e-9)
    # too old a pending closure predicts nothing
    assert closer._hypothesis(est, 40 + closer.config.pending_keyframes + 2) is None


# ------------------------------------------------------------------- bounded work per add_scan
def _fake_job(costs: list[float], log: list[int]):
    """A job whose steps announce ``costs`` (ms) and record their index when they run."""

    def job(slam, job):
        for k, cost in enumerate(costs):
            yield cost
            log.append(k)
        return []

    return job


def _calls(closer: LoopCloser, n_calls: int, log: list[int]) -> list[list[int]]:
    """Steps run by each of n_calls calls of the per-scan hook."""
    out = []
    for _ in range(n_calls):
        before = len(log)
        closer.on_scan(None)
        out.append(log[before:])
    return out


def test_work_per_scan_is_packed_into_the_budget():
    cfg = FRSlamConfig.from_dict({"loop_closure": {"budget_ms": 8.0}}).loop_closure
    closer = LoopCloser(cfg)
    log: list[int] = []
    closer._job = _fake_job([3.0, 3.0, 3.0, 20.0, 1.0, 1.0, 7.0], log)
    closer._jobs.append(None)
    # the job's first (glue) step costs nothing; then estimated costs are added while they fit in
    # 8 ms; the 20 ms step (e.g. an LM batch) runs alone, as the first step of a call
    assert _calls(closer, 5, log) == [[0, 1], [2], [3], [4, 5], [6]]
    assert closer.idle
    assert closer.steps_last_call == 1 and closer.cost_last_call == pytest.approx(7.0)


def test_a_slow_scanner_gets_the_budget_per_0_3_s_of_its_period():
    """Keyframes come with travel and turning, not with scans: at 0.6 s per scan the per-scan
    budget is that of two 0.3 s scans (8 -> 16 ms); at 0.3 s or faster it stays per scan."""
    cfg = FRSlamConfig.from_dict({"loop_closure": {"budget_ms": 8.0}}).loop_closure
    closer = LoopCloser(cfg)
    log: list[int] = []
    closer._job = _fake_job([3.0] * 10, log)
    closer._jobs.append(None)
    closer.set_scan_period(0.1)
    assert _calls(closer, 1, log) == [[0, 1]]  # 3 + 3 <= 8
    closer.set_scan_period(0.6)
    assert closer.budget_scale == pytest.approx(2.0)
    assert _calls(closer, 1, log) == [[2, 3, 4, 5, 6]]  # 5 x 3 <= 16
    closer.set_scan_period(float("nan"))
    assert closer.budget_scale == 1.0


def test_wall_clock_cap_uses_the_injected_clock():
    now = [0.0]
    cfg = FRSlamConfig.from_dict({"loop_closure": {"budget_ms": 1000.0, "wall_budget_ms": 12.0}})
    closer = LoopCloser(cfg.loop_closure, clock=lambda: now[0])
    log: list[int] = []

    def job(slam, job):  # every step takes 5 ms by the injected clock
        for k in range(8):
            yield 0.5
            now[0] += 0.005
            log.append(k)
        return []

    closer._job = job
    closer._jobs.append(None)
    # a step starts while less than 12 ms have passed in the call: at 0, 5 and 10 ms -> three
    # steps per call, whatever their estimated cost
    assert _calls(closer, 3, log) == [[0, 1, 2], [3, 4, 5], [6, 7]]


def test_matching_is_spread_over_scans_and_still_closes_the_loop(two_laps, monkeypatch):
    """With a tight budget no add_scan builds more than one reference submap or runs more than
    one peak's share of the ICP iterations (the peaks are refined in lockstep, their iterations
    spread over one step per peak; before: all candidates of a keyframe in its add_scan), and
    the loop still closes."""
    import frslam_graph.loop_closure.submap_matching as matching

    counts = {"icp": 0, "submaps": 0}
    icp, submap_init = matching.icp_point_to_line_many, ReferenceSubmap.__init__

    def counting_icp(*a, **k):  # counts the ICP's iterations (its generator's steps)
        steps = icp(*a, **k)
        while True:
            counts["icp"] += 1
            try:
                step = next(steps)
            except StopIteration as stop:
                return stop.value
            yield step

    def counting_init(self, *a, **k):
        counts["submaps"] += 1
        submap_init(self, *a, **k)

    monkeypatch.setattr(matching, "icp_point_to_line_many", counting_icp)
    monkeypatch.setattr(ReferenceSubmap, "__init__", counting_init)
    truth, ranges, amin, inc = two_laps
    # the odometry's refinement builds a local map (a ReferenceSubmap) every scan: off here
    odometry = dict(CFG["odometry"], local_map_scans=0)
    slam = FRSlam(dict(CFG, odometry=odometry, loop_closure={"budget_ms": 2.0}))
    _inject_drift(slam, np.deg2rad(0.5), 0.02)
    per_scan = []
    for i in range(len(truth)):
        before = dict(counts)
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, None)
        per_scan.append((counts["icp"] - before["icp"], counts["submaps"] - before["submaps"]))
        closer = slam.loop_closer
        assert closer.steps_last_call <= 1 or closer.cost_last_call <= 2.0
    per_scan = np.array(per_scan)
    assert per_scan.sum(axis=0).min() > 0  # matching did happen
    # one peak's share of the iterations at most: all of them when one peak is refined
    assert per_scan[:, 0].max() <= matching.ICP_ITERATIONS and per_scan[:, 1].max() <= 1
    assert not (per_scan[:, 0] & per_scan[:, 1]).any()  # never a submap build and an ICP together
    slam.finish()
    assert slam.loop_closer.idle  # finish() runs the queued work
    err = _errors(slam, truth)
    assert slam.loop_closer.stats.accepted > 0
    assert np.sqrt(np.mean(err**2)) < 0.25


def test_padded_reference_equals_the_unpadded_one():
    """The distance transform runs on an inner grid; the wide search margin is zero padding: the
    likelihood, free-space and nearest-point maps match a submap built without padding."""
    world = room_world()
    # binary-exact coordinates and resolution: both grids put every point in the same cell
    res = 1.0 / 16.0
    pts = np.round(_points(world, np.array([4.0, 3.0, 0.2]), 1) * 128.0) / 128.0
    scans = [(np.zeros(2), pts)]
    cfg = FRSlamConfig().with_updates(loop_closure={"resolution": res}).loop_closure
    wide = ReferenceSubmap(pts, res, cfg.likelihood_sigma, 6.0, scans)
    tight = ReferenceSubmap(pts, res, cfg.likelihood_sigma, 2.0, scans)
    assert wide._inner[0] > 0 and tight._inner[0] == 0  # the wide one is padded
    k = int(round((tight.origin[0] - wide.origin[0]) / res))  # wide cells before the tight grid
    h, w = tight.shape
    f_wide = wide.padded(wide.field, 0.0).reshape(wide.shape)
    np.testing.assert_array_equal(f_wide[k : k + h, k : k + w], tight.field)
    assert f_wide.sum() == pytest.approx(tight.field.sum())  # nothing outside
    free_wide = wide.free.reshape(wide.shape)[k : k + h, k : k + w]
    np.testing.assert_array_equal(free_wide, tight.free.reshape(h, w))
    near_wide = wide.padded(wide.nearest, -1).reshape(wide.shape)[k : k + h, k : k + w]
    np.testing.assert_array_equal(near_wide, tight.nearest.reshape(h, w))
    # and the matcher finds the same pose on both
    q = _points(world, np.array([4.3, 3.2, 0.25]), 2)
    a = match_scan(wide, q, np.zeros(3), 1.0, np.deg2rad(10.0), cfg)
    b = match_scan(tight, q, np.zeros(3), 1.0, np.deg2rad(10.0), cfg)
    np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)


@pytest.mark.parametrize("cells", [1, 4, 7, 200])
def test_max_filtered_field_equals_filtering_the_whole_grid(cells):
    """dilated() filters only the inner grid and `cells` around it (the rest is zero padding and
    stays zero): the same field as cv2.dilate over the whole padded grid."""
    import cv2

    world = room_world()
    pts = _points(world, np.array([4.0, 3.0, 0.2]), 1)
    ref = ReferenceSubmap(pts, 0.05, 0.1, 6.0, [(np.zeros(2), pts)])
    assert ref._inner[0] > cells or cells == 200  # padded (200: wider than the padding)
    whole = cv2.dilate(
        ref.padded(ref.field, 0.0).reshape(ref.shape), np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    ).ravel()
    np.testing.assert_array_equal(ref.dilated(cells), whole)


def _fake_slam(est: np.ndarray, priors: bool = False):
    """The part of FRSlam that LoopCloser._plan and on_keyframe read: the estimates, whether
    floor-plan priors are in the graph, the keyframes' scans (none: empty place descriptors)."""
    from types import SimpleNamespace

    n = len(est)
    return SimpleNamespace(
        graph=SimpleNamespace(estimates=lambda: est.copy(), has_priors=lambda: priors),
        keyframe_scans=lambda: ([np.zeros((0, 2), np.float32)] * n, [np.zeros(2)] * n),
    )


def test_pending_closure_check_goes_ahead_of_queued_candidates():

    from frslam_graph.loop_closure.closer import _Job

    closer = LoopCloser()
    est = _straight_line_with_pending_closure(closer)
    older = [_Job(5, 36, 2.0, 0.2), _Job(6, 38, 2.0, 0.2)]  # not matched yet
    closer._jobs.extend(older)
    closer._last_plan = 38
    closer._plan(_fake_slam(est), 40)
    first = closer._jobs[0]
    assert (first.reference, first.query) == (3, 40) and first.predicted is not None
    assert list(closer._jobs)[1:3] == older


def test_spread_work_is_deterministic(two_laps):
    """The per-scan budget is in estimated (cost-model) milliseconds, not clock time: a second run
    finds the same closures at the same scans and the same trajectory."""
    slam, _, _ = _run(two_laps, loop=True)  # not the `runs` fixture: another test alters it
    again, _, _ = _run(two_laps, loop=True)
    np.testing.assert_array_equal(again.trajectory(), slam.trajectory())
    first = [(e.stamp, e.keyframe, e.data["reference"]) for e in slam.log if e.kind == "loop_closure"]
    second = [(e.stamp, e.keyframe, e.data["reference"]) for e in again.log if e.kind == "loop_closure"]
    assert first == second and first


def test_keyframe_scans_get_the_smaller_budget():
    from types import SimpleNamespace

    cfg = FRSlamConfig.from_dict({"loop_closure": {"budget_ms": 8.0, "keyframe_budget_ms": 4.0}})
    closer = LoopCloser(cfg.loop_closure)
    log: list[int] = []
    closer._job = _fake_job([3.0] * 6, log)
    closer._jobs.append(None)
    # keyframe 0 (too early to plan): only 3 of the 4 ms fit; the next (plain) scan fits two
    closer.on_keyframe(_fake_slam(np.zeros((1, 3))), SimpleNamespace(index=0, pose_odom=np.zeros(3)))
    assert log == [0]
    assert _calls(closer, 1, log) == [[1, 2]]


@pytest.mark.parametrize("anchored", [False, True])
def test_confirmed_pair_stays_robust_once_floor_plan_priors_anchor_the_map(anchored):
    """A confirmed pair of closures enters as plain Gaussians (to pull a stiff odometry chain)
    unless floor-plan priors already anchor the graph: then it stays under the robust kernel,
    so an aliased pair cannot overrule the plan."""
    from types import SimpleNamespace

    import gtsam

    from frslam_graph.loop_closure.closer import LoopCloser, LoopClosure
    from frslam_graph.slam import FRSlam

    slam = FRSlam()
    g = slam.graph
    g.add_first(np.zeros(3))
    cov = np.diag([1e-4, 1e-4, 1e-6])
    for _ in range(6):
        g.add_keyframe(np.array([1.0, 0.0, 0.0]), cov)
    if anchored:
        g.add_prior(0, np.zeros(3), np.diag([1e-4, 1e-4, 1e-5]), source="reloc:reg0")
    match = SimpleNamespace(inlier_fraction=0.9, ambiguity=0.1, coarse_score=0.9)
    lcs = [
        LoopClosure(0, 5, np.array([5.0, 0.1, 0.0]), cov, match, np.zeros(3)),
        LoopClosure(1, 6, np.array([5.0, 0.1, 0.0]), cov, match, np.zeros(3)),
    ]
    closer = LoopCloser()
    for _ in closer._add(slam, lcs, settle=True):
        pass
    fg = g._graph()
    models = [
        fg.at(i).noiseModel() for i in range(fg.size()) if isinstance(fg.at(i), gtsam.BetweenFactorPose2)
    ]
    robust = [isinstance(m, gtsam.noiseModel.Robust) for m in models[-2:]]
    assert robust == [anchored, anchored]


# ------------------------------------------------------------ redundant regions are not searched
def _circle(closer: LoopCloser, n: int = 62) -> np.ndarray:
    """n keyframes 0.5 m apart on a circle of radius 3 m (about 38 per lap, turning 1/3 rad per
    metre); keyframe 60 is back next to keyframe 22. Returns the estimates (n, 3)."""
    th = 0.5 / 3.0 * np.arange(n)
    est = np.column_stack((3.0 * np.cos(th), 3.0 * np.sin(th), th + np.pi / 2.0))
    for p in est:
        closer._append_motion(p)
    return est


def _circle_closer(closure: tuple[int, int] | None, **cfg) -> tuple[LoopCloser, np.ndarray]:
    lc = {"max_candidates": 10, "retry_keyframes": 0, "redundant_travel": 5.0, **cfg}
    closer = LoopCloser(FRSlamConfig.from_dict({"loop_closure": lc}).loop_closure)
    est = _circle(closer)
    if closure is not None:
        closer.closures.append(LoopClosure(*closure, np.zeros(3), np.eye(3) * 1e-4, None, np.zeros(3)))
        closer._last_closure = closure[1]
    return closer, est


def test_region_tied_by_a_recent_closure_is_not_searched_again():
    # keyframe 56 closed on 18 two metres ago: 60 is tied to the region of 22 (4 m of graph
    # path through the closure, below redundant_travel): nothing is searched, and in particular
    # the farther regions (26, 29: not tied) do not take the tied one's place
    closer, est = _circle_closer((18, 56))
    assert closer._candidates(est, 60) == []
    assert closer.stats.redundant == 1
    # without the rule the nearest region (keyframe 22, 0.15 m away) is the first candidate
    closer, est = _circle_closer((18, 56), redundant_travel=0.0)
    refs = [c for c, *_ in closer._candidates(est, 60)]
    assert refs[0] == 22 and {26, 29} <= set(refs) and closer.stats.redundant == 0


@pytest.mark.parametrize("closure", [(10, 48), None])
def test_region_is_searched_again_once_its_uncertainty_grew(closure):
    # the closure is 6 m of travel back (or there is none): the drift since can exceed what a
    # closure corrects, the nearest region is searched again
    closer, est = _circle_closer(closure)
    assert closer._candidates(est, 60)[0][0] == 22
    assert closer.stats.redundant == 0


def test_large_turn_since_the_closure_unties_the_region():
    # same 4 m path as above, but the heading drift allowance is exceeded by the turning
    # (the 2 m from 60 back to the closure alone turn 38 degrees)
    closer, est = _circle_closer((18, 56), redundant_turn_deg=30.0)
    assert closer._candidates(est, 60)[0][0] == 22


def test_queued_candidate_tied_by_a_later_closure_is_dropped_unmatched():
    from frslam_graph.loop_closure.closer import _Job
    from frslam_graph.steps import run_steps

    closer, est = _circle_closer(None)
    job = _Job(22, 60, 3.0, 0.2, None, len(closer.closures))  # planned before the closure below
    closer.closures.append(LoopClosure(18, 56, np.zeros(3), np.eye(3) * 1e-4, None, np.zeros(3)))
    closer._last_closure = 56
    # (no pipeline needed: the job stops before gathering any point)
    assert run_steps(closer._job(None, job)) == []
    assert closer.stats.redundant == 1 and closer.stats.attempts == 0


def test_pending_check_of_a_tied_place_is_skipped():

    closer, est = _circle_closer((18, 56))
    # an older pending closure (large correction) predicts keyframe 60 next to keyframe 22,
    # which the newer verified closure already ties to 60
    closer._pending.append(LoopClosure(0, 38, np.zeros(3), np.eye(3) * 1e-4, None, np.zeros(3)))
    assert closer._hypothesis(est, 60)[0] == 22
    closer._last_plan = 58
    closer._plan(_fake_slam(est), 60)
    assert all(j.predicted is None and j.reference != 22 for j in closer._jobs)


@pytest.mark.parametrize("priors", [False, True])
def test_redundant_travel_with_plan_applies_once_floor_plan_priors_are_in_the_graph(priors):
    # no redundancy rule without a plan; with floor-plan priors in the graph the region of
    # keyframe 22 (tied to 60 through the closure 18-56) is not searched
    closer, est = _circle_closer((18, 56), redundant_travel=0.0, redundant_travel_with_plan=5.0)
    closer._last_plan = 58
    closer._plan(_fake_slam(est, priors), 60)
    refs = [j.reference for j in closer._jobs]
    if priors:
        assert refs == [] and closer.stats.redundant == 1
    else:
        assert refs[0] == 22 and closer.stats.redundant == 0


def test_graph_distances_are_updated_incrementally_between_closures():
    rng = np.random.default_rng(3)
    closer = LoopCloser()
    for _ in range(120):
        closer._append_motion(rng.normal(size=3))
    for i in range(30, 120, 3):
        if i % 4 == 0:  # a closure now and then (sometimes of an earlier keyframe)
            q = i - i % 3
            closer.closures.append(LoopClosure(q // 3, q, np.zeros(3), np.eye(3), None, np.zeros(3)))
            closer._last_closure = max(closer._last_closure, q)
        fresh = LoopCloser()
        fresh._travel, fresh._turn, fresh.closures = closer._travel, closer._turn, closer.closures
        for a, b in zip(closer._graph_distances(i), fresh._graph_distances(i), strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)


def test_keyframe_where_the_update_strategy_touched_the_graph_gets_no_closure_work(two_laps):
    """A keyframe whose update-strategy hook added a prior (its relocalisation, prior and settle
    spent this scan's budget) only queues loop-closure candidates; the queued work goes on at
    the next scan. Keyframes the hook left alone get their keyframe budget as before."""
    from types import SimpleNamespace

    closer = LoopCloser(FRSlamConfig().loop_closure)
    log: list[int] = []
    closer._job = _fake_job([1.0] * 6, log)
    closer._jobs.append(None)
    closer.on_keyframe(
        _fake_slam(np.zeros((1, 3))), SimpleNamespace(index=0, pose_odom=np.zeros(3)), work=False
    )
    assert log == [] and closer.steps_last_call == 0 and not closer.idle
    assert _calls(closer, 1, log) and log  # the next scan works on the queue

    truth, ranges, amin, inc = two_laps
    seen: list[tuple[int, bool]] = []

    def hook(slam, kf):  # a prior on every third keyframe
        if kf.index % 3 == 0:
            slam.add_prior(kf.index, kf.pose_map, np.diag([1e-2, 1e-2, 1e-3]), source="test")

    slam = FRSlam(dict(CFG, loop_closure={"enabled": True}), update_strategy=hook)
    on_keyframe = slam.loop_closer.on_keyframe
    slam.loop_closer.on_keyframe = lambda s, kf, work=True: (
        seen.append((kf.index, work)) or on_keyframe(s, kf, work)
    )
    for i in range(80):
        slam.add_scan(truth[i, 0], ranges[i], amin, inc, None)
    assert len(seen) >= 6
    assert all(work == (k % 3 != 0) for k, work in seen)


# ------------------------------------------------ independent confirmation and pruning (ACES)
def _ret(value):
    """A step generator without steps that returns ``value``."""
    if False:  # pragma: no cover
        yield 0.0
    return value


def _line_slam(n: int = 40, step: float = 0.5) -> FRSlam:
    """A graph of n keyframes ``step`` metres apart along x (stiff odometry)."""
    slam = FRSlam()
    slam.graph.add_first(np.zeros(3))
    for _ in range(n - 1):
        slam.graph.add_keyframe(np.array([step, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-6]))
    return slam


def _weak_match_job(monkeypatch, inliers: float, pending: bool, shift: float = 18.5, **cfg):
    """Keyframe 39 (at 19.5 m) matched on old keyframe 2 (at 1 m) with ``inliers``, putting it
    ``shift`` metres behind its estimate (a large correction); with ``pending`` a closure of
    keyframe 34 (2.5 m of travel before it: another query submap) on keyframe 0 agrees with it."""
    import frslam_graph.loop_closure.closer as lcm
    from frslam_graph.loop_closure.closer import _Job
    from frslam_graph.loop_closure.submap_matching import ScanMatch
    from frslam_graph.steps import run_steps

    slam = _line_slam()
    # no pruning: the straight chain cannot fold onto itself as these closures would have it
    cfg = {"prune_chi2": 0.0, **cfg}
    closer = LoopCloser(FRSlamConfig.from_dict({"loop_closure": cfg}).loop_closure)
    for k in range(40):
        closer._append_motion(np.array([0.5 * k, 0.0, 0.0]))
    rel = np.array([18.5 - shift, 0.0, 0.0])  # keyframe 39 relative to keyframe 2
    m = ScanMatch(rel, inliers, 0.3, np.eye(3) * 1e-5, 0.9, 100)
    monkeypatch.setattr(lcm, "match_scan_steps", lambda *a, **k: _ret(m))
    closer._query = (39, np.zeros((50, 2)))
    closer._reference = lambda slam, c, i: _ret(None)
    if pending:
        corr = np.array([-shift, 0.0, 0.0])
        rel34 = np.array([17.0 - shift, 0.0, 0.0])  # keyframe 34 (at 17 m) relative to keyframe 0
        closer._pending.append(LoopClosure(0, 34, rel34, np.eye(3) * 4e-4, m, corr))
    out = run_steps(closer._job(slam, _Job(2, 39, 2.0, 0.2)))
    return closer, out


def test_weak_match_confirms_a_pending_closure_but_is_rejected_alone(monkeypatch):
    cfg = FRSlamConfig().loop_closure
    weak = 0.5 * (cfg.confirm_min_inlier_fraction + cfg.min_inlier_fraction)
    within = 0.5 * cfg.search_window_xy  # the correction: within the search window
    # alone: rejected (and not even queued as pending)
    closer, out = _weak_match_job(monkeypatch, weak, pending=False, shift=within)
    assert out == [] and not closer._pending and closer.stats.reasons == {"low_inliers": 1}
    # agreeing with a pending closure: the pair enters the graph
    closer, out = _weak_match_job(monkeypatch, weak, pending=True, shift=within)
    assert [(c.reference, c.query) for c in out] == [(0, 34), (2, 39)]
    assert len(closer.closures) == 2 and not closer._pending
    # switched off (= min_inlier_fraction): rejected even with the pending closure
    off = {"confirm_min_inlier_fraction": cfg.min_inlier_fraction}
    closer, out = _weak_match_job(monkeypatch, weak, pending=True, shift=within, **off)
    assert out == [] and closer.stats.reasons == {"low_inliers": 1}
    # below confirm_min_inlier_fraction: rejected
    low = cfg.confirm_min_inlier_fraction - 0.05
    closer, out = _weak_match_job(monkeypatch, low, pending=True, shift=within)
    assert out == [] and closer.stats.reasons == {"low_inliers": 1}


def test_weak_match_does_not_confirm_a_correction_beyond_the_search_window(monkeypatch):
    """Two neighbouring keyframes in a corridor or a row of alike rooms match the same wrong place
    alike (ACES at 850 s, FR079 at 2,040 s: 12 m and 3 m wrong pairs, each confirmed by a match of
    inlier fraction 0.50 / 0.59). Beyond the search window the prediction was not searched:
    the weak match's agreement is no evidence, and only a match acceptable alone confirms."""
    cfg = FRSlamConfig().loop_closure
    weak = 0.5 * (cfg.confirm_min_inlier_fraction + cfg.min_inlier_fraction)
    for shift in (1.5 * cfg.search_window_xy, 18.5):
        closer, out = _weak_match_job(monkeypatch, weak, pending=True, shift=shift)
        assert out == [] and closer.stats.reasons == {"low_inliers": 1}
        assert not closer.closures and len(closer._pending) == 1
        # a match acceptable alone confirms it
        closer, out = _weak_match_job(monkeypatch, 0.9, pending=True, shift=shift)
        assert [(c.reference, c.query) for c in out] == [(0, 34), (2, 39)]


def test_pending_closure_is_checked_from_the_keyframe_two_metres_back(monkeypatch):
    # a strong match with a large correction goes pending and queues (first) the check of the
    # keyframe verify_back_travel before it, where the closure puts that keyframe
    closer, out = _weak_match_job(monkeypatch, 0.9, pending=False)
    assert out == [] and len(closer._pending) == 1 and closer.stats.verifications == 1
    job = closer._jobs[0]
    # keyframe 35 (2 m before 39) is at -1 m by the closure: nearest old keyframe 0, 1 m behind it
    assert (job.reference, job.query) == (0, 35)
    np.testing.assert_allclose(job.predicted, [-1.0, 0.0, 0.0], atol=1e-6)
    assert job.radius == closer.config.hypothesis_window_xy
    closer, _ = _weak_match_job(monkeypatch, 0.9, pending=False, verify_back_travel=0.0)
    assert not closer._jobs and closer.stats.verifications == 0


def _closure_pairs(slam: FRSlam) -> set[tuple[int, int]]:
    """(reference, query) of the between-factors that skip keyframes (loop closures)."""
    pairs = {
        (int(gtsam.Symbol(f.keys()[0]).index()), int(gtsam.Symbol(f.keys()[1]).index()))
        for f in slam.graph._factors
        if isinstance(f, gtsam.BetweenFactorPose2)
    }
    return {(a, b) for a, b in pairs if b - a > 1}


@pytest.mark.parametrize("prune", [True, False])
def test_closure_the_graph_disagrees_with_is_removed(prune):
    """Two true closures are in the graph; a confirmed but aliased one (1.2 m off along the
    corridor) enters as a Gaussian: the odometry and the true closures disagree with it, so it
    is removed and the graph returns to the straight line."""
    from types import SimpleNamespace

    slam = _line_slam(12, 1.0)
    closer = LoopCloser(
        FRSlamConfig.from_dict({"loop_closure": {"prune_chi2": 200.0 if prune else 0.0}}).loop_closure
    )
    cov = np.diag([9e-4, 9e-4, 1e-4])
    match = SimpleNamespace(inlier_fraction=0.9, ambiguity=0.1, coarse_score=0.9)
    good = [LoopClosure(k, k + 10, np.array([10.0, 0.0, 0.0]), cov, match, np.zeros(3)) for k in (0, 1)]
    wrong = LoopClosure(2, 9, np.array([8.2, 0.3, 0.0]), cov, match, np.zeros(3))
    for _ in closer._add(slam, good, settle=True):
        pass
    assert closer.stats.pruned == 0  # consistent closures stay
    for _ in closer._add(slam, [wrong], settle=True):
        pass
    est = slam.graph.estimates()
    if prune:
        assert closer.closures == good and closer.stats.pruned == 1
        assert _closure_pairs(slam) == {(0, 10), (1, 11)}
        assert [e.kind for e in slam.log][-1] == "loop_removed"
        np.testing.assert_allclose(est[:, 0], np.arange(12.0), atol=0.01)
    else:
        assert len(closer.closures) == 3 and (2, 9) in _closure_pairs(slam)
        assert np.abs(est[:, 0] - np.arange(12.0)).max() > 0.1  # the aliased closure bent it


@pytest.mark.parametrize("settle_small", [0, 1])
def test_small_closure_takes_settle_small_relinearising_updates(settle_small):
    """A single closure that agrees with the estimate: its own iSAM2 update, then at most
    settle_small forced relinearisations (default 0: the keyframe updates relinearise)."""
    from types import SimpleNamespace

    slam = _line_slam(12, 1.0)
    cfg = FRSlamConfig.from_dict({"loop_closure": {"settle_small": settle_small}}).loop_closure
    closer = LoopCloser(cfg)
    match = SimpleNamespace(inlier_fraction=0.9, ambiguity=0.1, coarse_score=0.9)
    lc = LoopClosure(0, 10, np.array([10.02, 0.0, 0.0]), np.diag([9e-4, 9e-4, 1e-4]), match, np.zeros(3))
    before = slam.graph.version
    for _ in closer._add(slam, [lc], settle=False):
        pass
    assert closer.closures == [lc]
    assert slam.graph.version - before == 1 + settle_small
    assert FRSlamConfig().loop_closure.settle_small == 0


@pytest.mark.parametrize("rule", [True, False])
def test_confirmed_pair_contradicting_older_closures_is_removed_before_them(rule):
    """Robust closures every metre tie a 40 m corridor; an aliased pair (2 m short) is
    confirmed and enters as plain Gaussians. Under its pull the older closures show the large
    residuals: "worst first" alone removes many good closures; with the pair rule (default
    config) the pair goes first and every good closure stays."""
    from types import SimpleNamespace

    slam = _line_slam(40, 1.0)
    lc_cfg = {} if rule else {"prune_pair_contradictions": 1000}
    closer = LoopCloser(FRSlamConfig.from_dict({"loop_closure": lc_cfg}).loop_closure)
    cov = np.diag([9e-4, 9e-4, 1e-4])
    match = SimpleNamespace(inlier_fraction=0.9, ambiguity=0.1, coarse_score=0.9)
    good = [LoopClosure(k, k + 10, np.array([10.0, 0.0, 0.0]), cov, match, np.zeros(3)) for k in range(30)]
    for lc in good:
        for _ in closer._add(slam, [lc], settle=False):
            pass
    assert closer.stats.pruned == 0
    pair = [LoopClosure(k, k + 10, np.array([8.0, 0.0, 0.0]), cov, match, np.zeros(3)) for k in (14, 15)]
    for _ in closer._add(slam, pair, settle=True):
        pass
    removed = [e for e in slam.log if e.kind == "loop_removed"]
    kept = [lc for lc in good if any(lc is c for c in closer.closures)]
    if rule:
        assert kept == good and closer.stats.pruned == 2
        assert [(e.data["reference"], e.keyframe) for e in removed] == [(14, 24), (15, 25)]
        assert all("contradicts" in e.message and e.data["chi2"] > 0.0 for e in removed)
        np.testing.assert_allclose(slam.graph.estimates()[:, 0], np.arange(40.0), atol=0.01)
    else:
        assert len(good) - len(kept) >= 5, len(kept)


def test_an_idle_closer_plans_an_extra_candidate():
    """max_candidates_idle regions when nothing is queued (the work keeps up with the budget),
    max_candidates while older work waits."""

    closer, est = _circle_closer(None, max_candidates=2, max_candidates_idle=3, redundant_travel=0.0)
    slam = _fake_slam(est)
    closer._plan(slam, 60)
    assert len(closer._jobs) == 3  # idle
    closer._plan(slam, 61)
    assert len(closer._jobs) == 3 + 2  # three still queued
    assert all(j.query == 61 for j in list(closer._jobs)[3:])


def test_submap_is_each_keyframe_scan_moved_into_the_centre_frame():
    # _submap transforms all keyframes at once: it must equal moving each keyframe's in-range
    # points by its own relative pose, keyframe by keyframe, in order (and skip far/empty ones)
    rng = np.random.default_rng(3)
    n = 8
    est = np.column_stack((rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-3, 3, n)))
    pts = [rng.uniform(-20, 20, (int(m), 2)).astype(np.float32) for m in rng.integers(0, 60, n)]
    pts[2] = np.zeros((0, 2), np.float32)
    origins = [rng.uniform(-0.2, 0.2, 2) for _ in range(n)]

    class _Slam:
        def keyframe_scans(self):
            return list(pts), list(origins)

    closer = LoopCloser(FRSlamConfig().loop_closure)
    closer._travel = [0.0, 1.0, 2.0, 3.0, 4.0, 9.0, 6.0, 7.0]  # keyframe 5 is beyond +-3 m of 4
    got, scans = closer._submap(_Slam(), est, 4, 0, n - 1, 3.0)
    want, kept = [], []
    for k in range(n):
        if abs(closer._travel[k] - closer._travel[4]) > 3.0 or not len(pts[k]):
            continue
        p = pts[k][np.hypot(*(pts[k] - origins[k]).T) <= closer.config.max_point_range]
        rel = between(est[4], est[k])
        want.append(transform_points(rel, p))
        kept.append((transform_points(rel, origins[k][None])[0], want[-1]))
    assert len(scans) == len(kept) == 5  # keyframes 1, 3, 4, 6, 7 (2 empty; 0 and 5 too far)
    np.testing.assert_array_equal(got, np.vstack(want))
    for (o, e), (o2, e2) in zip(scans, kept, strict=True):
        np.testing.assert_array_equal(o, o2)
        np.testing.assert_array_equal(e, e2)


def test_the_rest_of_a_shared_budget_runs_only_steps_that_fit():
    cfg = FRSlamConfig.from_dict({"loop_closure": {"budget_ms": 8.0}}).loop_closure
    closer = LoopCloser(cfg)
    log: list[int] = []
    closer._job = _fake_job([3.0, 3.0, 6.0, 1.0], log)
    closer._jobs.append(None)
    out = []
    for left in (5.0, 2.0, None, 6.0):  # None: a scan of its own (the first step always runs)
        before = len(log)
        closer.on_scan(None, left)
        out.append(log[before:])
    # 5 ms left: the glue and step 0 fit, step 1 would not; 2 ms: nothing fits, the queue waits
    assert out == [[0], [], [1], [2]]
    assert not closer.idle


def test_a_full_queue_plans_no_more_candidates_but_the_pending_check():
    """While MAX_QUEUED_JOBS candidates wait (the matching fell behind the budget), a keyframe
    plans none: the queue stays short and its closures come in time; the check of a pending
    closure is queued all the same, first."""
    from frslam_graph.loop_closure.closer import MAX_QUEUED_JOBS, _Job

    closer, est = _circle_closer(None, max_candidates=2, max_candidates_idle=3, redundant_travel=0.0)
    slam = _fake_slam(est)
    full = [_Job(5, 30, 2.0, 0.2) for _ in range(MAX_QUEUED_JOBS)]
    closer._jobs.extend(full)
    closer._plan(slam, 60)
    assert list(closer._jobs) == full  # nothing planned, nor marked tried
    assert not closer._tried and closer.stats.plans_skipped == 1
    closer._jobs.pop()  # one below the cap: the keyframe plans again
    closer._plan(slam, 61)
    assert len(closer._jobs) == MAX_QUEUED_JOBS - 1 + 2

    closer = LoopCloser()
    est = _straight_line_with_pending_closure(closer)
    closer._jobs.extend(full)
    closer._last_plan = 38
    closer._plan(_fake_slam(est), 40)
    first = closer._jobs[0]
    assert (first.reference, first.query) == (3, 40) and first.predicted is not None
    assert list(closer._jobs)[1:] == full


def test_free_space_is_measured_only_for_a_match_the_closer_could_accept():
    """The free-space test (a polygon fill of every reference scan) is skipped for a match refused
    anyway, ambiguous or with too few inliers even to confirm a pending closure (most candidates
    on real logs): its free_violation is NaN and the mask is not built; an acceptable match is
    measured."""
    import math

    cfg = FRSlamConfig().loop_closure
    corridor = corridor_world(60.0, 2.0)
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.4, 0.1, 0.05])
    ref = _reference(corridor, a)
    bad = match_scan(ref, _points(corridor, b, 3), between(a, b), 2.0, np.deg2rad(10.0), cfg)
    assert bad is not None and bad.ambiguity > cfg.max_ambiguity  # refused: ambiguous
    assert bad.coarse_score >= 0.62  # (refined: not refused by the coarse score alone)
    assert math.isnan(bad.free_violation) and ref._free is None
    world = room_world()
    pose = np.array([4.0, 3.0, 0.0])
    ref = _reference(world, pose)
    good = match_scan(ref, _points(world, pose, 5), np.zeros(3), 2.0, 0.3, cfg)
    assert good.inlier_fraction >= cfg.min_inlier_fraction and good.free_violation < 0.02
    assert ref._free is not None


def test_peaks_refined_in_lockstep_equal_each_refined_alone():
    """icp_point_to_line_many from several starts (one far enough to give up, others that
    converge early) gives each start's result of icp_point_to_line from it alone, to the last
    bit, with one k-d tree query per iteration for all the starts still iterating (before: one
    per start and iteration)."""
    from scipy.spatial import cKDTree

    from frslam_graph.loop_closure.submap_matching import icp_point_to_line, icp_point_to_line_many
    from frslam_graph.steps import run_steps

    world = room_world()
    a, b = np.array([4.0, 2.0, 0.3]), np.array([4.6, 2.3, 0.4])
    ref = _reference(world, a)
    ref.prepare_icp()
    query = _points(world, b, 2)[::3]
    truth = between(a, b)
    starts = np.array(
        [truth, truth + (0.12, -0.08, 0.03), truth + (-0.2, 0.15, -0.05), truth + (40.0, 0.0, 0.0)]
    )
    alone = [icp_point_to_line(ref, query, s, 10, 0.5, 0.05, 0.05) for s in starts]
    assert alone[-1] is None and all(r is not None for r in alone[:-1])
    queries = []
    tree_query = cKDTree.query

    class CountingTree(cKDTree):
        def query(self, x, *args, **kwargs):
            queries.append(len(x))
            return tree_query(self, x, *args, **kwargs)

    ref._tree = CountingTree(ref.points)
    together = run_steps(icp_point_to_line_many(ref, query, starts, 10, 0.5, 0.05, 0.05))
    for r, s in zip(together, alone, strict=True):
        assert (r is None) == (s is None)
        if s is not None:
            assert np.array_equal(r[0], s[0]) and np.array_equal(r[1], s[1])
    # one query per iteration, of the starts still iterating (the far one gave up at once, the
    # others converged before the tenth iteration)
    assert queries[:2] == [4 * len(query), 3 * len(query)] and len(queries) < 10
    assert queries == sorted(queries, reverse=True)


def test_lockstep_peaks_equal_each_alone_on_real_submaps(test_data):
    """The same on real scans (FR079's first scans, at their wheel odometry): a reference submap
    and a query of other scans, starts scattered around their offset (some giving up, some
    running all its iterations): each start's pose and covariance are icp_point_to_line's to the
    last bit."""
    from frslam_graph.datasets import open_recording

    from frslam_graph.loop_closure.submap_matching import icp_point_to_line, icp_point_to_line_many
    from frslam_graph.slam import body_points
    from frslam_graph.steps import run_steps

    pts, poses = [], []
    for scan in open_recording(test_data / "fr079_250.clf.bz2"):
        pts.append(body_points(scan.points, scan.sensor_offset)[0])
        poses.append(np.asarray(scan.odom, dtype=float))
        if len(pts) == 60:
            break
    rng = np.random.default_rng(3)
    ref = ReferenceSubmap(
        np.vstack([transform_points(between(poses[10], poses[k]), pts[k]) for k in range(20)]), 0.05, 0.1, 2.0
    )
    ref.prepare_icp()
    rel = between(poses[10], poses[40])
    query = np.vstack([transform_points(between(poses[40], poses[k]), pts[k]) for k in range(36, 44)])
    query = query[:: max(1, len(query) // 400)]
    starts = rel + rng.normal(0.0, [0.25, 0.25, 0.08], (6, 3))
    starts[-1, :2] += 30.0  # no correspondences: gives up
    alone = [icp_point_to_line(ref, query, s, 10, 0.5, 0.05, 0.05) for s in starts]
    together = run_steps(icp_point_to_line_many(ref, query, starts, 10, 0.5, 0.05, 0.05))
    assert alone[-1] is None and sum(r is not None for r in alone) >= 3
    for r, s in zip(together, alone, strict=True):
        assert (r is None) == (s is None)
        if s is not None:
            assert np.array_equal(r[0], s[0]) and np.array_equal(r[1], s[1])


def test_submaps_a_closure_made_stale_are_freed_one_per_later_build():
    """A confirmed pair or a pruned closure makes every reference submap stale. They are not
    all freed in that step (24 submaps' arrays cost 15-20 ms of CPU to unmap at once): one goes
    per submap built afterwards, never more than SUBMAPS_KEPT held, and none is used again."""

    class Sub:  # stands in for a ReferenceSubmap (only its lifetime matters)
        def release(self) -> None:
            pass

    def build(c: int) -> None:  # as LoopCloser._reference: room made, then the new submap kept
        lc._make_room()
        lc._keep_submap(c, Sub())

    kept = closer_module.SUBMAPS_KEPT
    lc = LoopCloser()
    subs = [Sub() for _ in range(kept)]
    for c, s in enumerate(subs):
        lc._make_room()
        lc._keep_submap(c, s)
    alive = [weakref.ref(s) for s in subs]
    del subs, s
    lc._drop_submaps()
    assert not lc._submaps  # no stale submap is looked up again
    assert sum(r() is not None for r in alive) == kept  # none freed in the closure's step
    for n in range(1, kept + 1):
        build(100 + n)
        assert sum(r() is not None for r in alive) == kept - n  # one per build
        assert len(lc._submaps) + len(lc._stale_submaps) <= kept
    build(200)  # then the least recently used, as before
    assert len(lc._submaps) == kept and 101 not in lc._submaps
