"""Final alignment (frslam_graph.loop_closure.final_alignment): dense constraints between passes at finish()."""

from __future__ import annotations

import numpy as np
import pytest

from frslam_graph.config import LoopClosureConfig
from frslam_graph.loop_closure import final_alignment as fa
from frslam_graph.loop_closure.final_alignment import candidate_pairs, dense_constraints, field_of_view
from frslam_graph.loop_closure.submap_matching import ReferenceSubmap, icp_point_to_line
from frslam_graph.odometry.motion_model import between, compose
from tests import synthetic_world as sw


def _line(x0: float, x1: float, y: float, heading: float, n: int) -> np.ndarray:
    return np.column_stack((np.linspace(x0, x1, n), np.full(n, y), np.full(n, heading)))


def test_pairs_join_other_passes_with_overlapping_views_only():
    # pass 1 east along y = 0, pass 2 back west (opposite view), pass 3 east again along y = 0.3
    poses = np.vstack((_line(0, 12, 0.0, 0.0, 41), _line(12, 0, 0.15, np.pi, 41), _line(0, 12, 0.3, 0.0, 41)))
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))))
    pairs = candidate_pairs(poses, travel, radius=1.0, heading_window=np.deg2rad(60.0), per_keyframe=3)
    assert len(pairs) > 30
    passes = np.arange(len(poses)) // 41
    assert set(map(tuple, passes[pairs])) == {(0, 2)}  # never the same pass, never the opposite view
    d = np.hypot(*(poses[pairs[:, 0], :2] - poses[pairs[:, 1], :2]).T)
    assert d.max() <= 1.0
    # a 360° sensor sees the opposite pass too
    wide = candidate_pairs(poses, travel, radius=1.0, heading_window=np.pi, per_keyframe=3)
    assert {(0, 1), (1, 2)} <= set(map(tuple, passes[wide]))


def test_field_of_view_from_points():
    ang = np.linspace(-np.pi / 2, np.pi / 2, 181)
    half = [np.column_stack((5 * np.cos(ang), 5 * np.sin(ang)))] * 5
    assert field_of_view(half) == pytest.approx(np.pi, abs=np.deg2rad(10))
    full = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    assert field_of_view([np.column_stack((np.cos(full), np.sin(full)))] * 5) == pytest.approx(2 * np.pi)


def _two_laps() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Keyframes of two laps of a room: true poses, estimate (second lap 6 cm and 1° off), points
    and the mask of the second lap."""
    world = sw.room_world()
    truth = sw.route(sw.ROOM_LOOP + sw.ROOM_LOOP[1:], speed=0.5, rate=2.0)[:, 1:]  # two laps
    keep = [0]
    for i in range(1, len(truth)):  # keyframes every 0.3 m or 10°
        z = between(truth[keep[-1]], truth[i])
        if np.hypot(z[0], z[1]) >= 0.3 or abs(z[2]) >= np.deg2rad(10):
            keep.append(i)
    truth = truth[keep]
    rng = np.random.default_rng(3)
    points = []
    for p in truth:
        r, amin, inc = sw.cast(world, p, n_beams=360, max_range=15.0, noise=0.005, rng=rng)
        points.append(sw.to_points(r, amin, inc).astype(np.float32))
    estimate = truth.copy()
    second = np.arange(len(truth)) >= len(truth) // 2
    shift = np.array([0.06, -0.04, np.deg2rad(1.0)])
    estimate[second] = np.array([compose(shift, p) for p in truth[second]])
    return truth, estimate, points, second


def test_constraints_measure_the_true_relative_pose_of_two_passes():
    """Two laps of a room; the estimate of the second lap is off by 6 cm and 1°: every
    constraint between the laps measures the true relative pose, not the estimate's."""
    truth, estimate, points, second = _two_laps()
    cons = dense_constraints(estimate, truth, points, radius=2.0, max_range=15.0)
    across = [c for c in cons if second[c.reference] != second[c.query]]
    assert len(across) >= 10
    err = np.array([c.relative - between(truth[c.reference], truth[c.query]) for c in across])
    # the estimate was 7 cm and 1° off; the measurements are within a few mm of the truth
    assert np.hypot(err[:, 0], err[:, 1]).mean() < 0.01
    assert np.hypot(err[:, 0], err[:, 1]).max() < 0.03
    assert np.degrees(np.abs(err[:, 2])).mean() < 0.1
    assert np.degrees(np.abs(err[:, 2])).max() < 0.6
    assert min(c.inlier_fraction for c in across) >= 0.7


def test_finish_adds_the_constraints_and_rounds_zero_or_no_loop_closure_turn_it_off():
    from frslam_graph import FRSlam

    world = sw.room_world()
    truth = sw.route(sw.ROOM_LOOP + sw.ROOM_LOOP[1:], speed=0.6, rate=5.0)  # two laps
    odom = sw.drifting_odometry(truth, scale=0.02)
    scans, amin, inc = sw.scans_along(world, truth, max_range=15.0)
    events, errors = {}, {}
    for rounds in (0, 2, "off", "default"):
        lc = {"enabled": False} if rounds == "off" else {"final_alignment_rounds": rounds}
        lc = {} if rounds == "default" else lc
        slam = FRSlam({"loop_closure": lc})
        for row, o, r in zip(truth, odom, scans, strict=True):
            slam.add_scan(row[0], r, amin, inc, odom=tuple(o))
        est = slam.finish()
        events[rounds] = [e for e in slam.log if e.kind == "final_alignment"]
        errors[rounds] = np.hypot(*(est[:, 1:3] - truth[:, 1:3]).T).mean()
    assert events[0] == [] and events["off"] == []  # off, and off with loop closure
    assert len(events[2]) == 2
    # one round by default: a second one, matching again at the re-optimised estimate, moved the
    # real logs' relation errors by <= 0.0001 m for 3-6 % of their run time (tools/README.md)
    assert len(events["default"]) == 1 and errors["default"] <= errors[0] + 0.005
    assert all(e.data["constraints"] > 0 for e in events[2])
    assert errors[2] <= errors[0] + 0.005


def _align_one_by_one(poses, points, pairs, max_range):
    """The constraints of align_pairs computed pair by pair with icp_point_to_line."""
    out = []
    local = fa._in_range(points, max_range)
    for c, k in pairs[np.argsort(pairs[:, 0], kind="stable")]:
        pts = fa._submap(poses, local, int(c), fa.REFERENCE_SPAN)
        query = fa._submap(poses, local, int(k), fa.QUERY_SPAN)
        if len(pts) < 30 or len(query) < 30:
            continue
        ref = ReferenceSubmap(pts, fa.RESOLUTION, fa.INLIER_DISTANCE, fa.ICP_MAX_DISTANCE)
        start = between(poses[c], poses[k])
        if ref.inlier_fraction(query, start, 2.0 * fa.INLIER_DISTANCE) < fa.MIN_START_OVERLAP:
            continue
        res = icp_point_to_line(
            ref, query, start, fa.ICP_ITERATIONS, fa.ICP_MAX_DISTANCE, fa.ICP_KERNEL, fa.ICP_SIGMA
        )
        if res is None:
            continue
        x, cov = res
        d = between(start, x)
        if np.hypot(*(x[:2] - start[:2])) > fa.MAX_CORRECTION_XY or abs(d[2]) > fa.MAX_CORRECTION_THETA:
            continue
        inliers = ref.inlier_fraction(query, x, fa.INLIER_DISTANCE)
        if inliers >= fa.MIN_INLIER_FRACTION and np.all(np.isfinite(cov)):
            out.append((int(c), int(k), x, cov, inliers))
    return out


@pytest.mark.parametrize("chunk_cells", [fa._CHUNK_CELLS, 20_000])
def test_pairs_matched_at_once_equal_pair_by_pair_icp(monkeypatch, chunk_cells):
    """align_pairs runs the ICP of all pairs as one vectorised computation (in chunks of reference
    submaps): the same constraints as icp_point_to_line pair by pair, in the same order."""
    monkeypatch.setattr(fa, "_CHUNK_CELLS", chunk_cells)
    truth, estimate, points, _ = _two_laps()
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))))
    pairs = candidate_pairs(estimate, travel, 2.0, np.pi, 3)
    want = _align_one_by_one(estimate, points, pairs, 15.0)
    built = []
    submap = fa._submap
    monkeypatch.setattr(fa, "_submap", lambda *a: built.append(a[2]) or submap(*a))
    got = fa.align_pairs(estimate, points, pairs, 15.0)
    # each reference and each query submap built once, however many pairs share it
    assert len(built) == len(np.unique(pairs[:, 0])) + len(np.unique(pairs[:, 1]))
    assert len(want) >= 10
    assert [(c.reference, c.query) for c in got] == [w[:2] for w in want]
    for c, (_, _, x, cov, inliers) in zip(got, want, strict=True):
        np.testing.assert_allclose(c.relative, x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(c.covariance, cov, rtol=1e-7, atol=0)
        assert c.inlier_fraction == inliers


def test_two_processes_give_the_same_constraints():
    """processes=2 matches the second half of the references in a forked process: the same
    constraints, bit for bit, in the same order."""
    truth, estimate, points, _ = _two_laps()
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))))
    pairs = candidate_pairs(estimate, travel, 2.0, np.pi, 3)
    one = fa.align_pairs(estimate, points, pairs, 15.0)
    two = fa.align_pairs(estimate, points, pairs, 15.0, processes=2)
    assert len(one) >= 10
    assert [(c.reference, c.query) for c in two] == [(c.reference, c.query) for c in one]
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a.relative, b.relative)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        assert a.inlier_fraction == b.inlier_fraction


def test_child_work_runs_in_another_process_and_a_failed_child_gives_none():
    import os

    assert fa._in_child(lambda: np.array([os.getpid()]))()[0] != os.getpid()

    def fail():
        raise RuntimeError("boom")

    assert fa._in_child(fail)() is None


def test_two_processes_share_the_blocks_as_they_come():
    """_shared: the blocks of references go to whichever process is free. This process stalls in
    its first block until the forked one has done every other block (halves split beforehand:
    the forked one would stop at its half, this one give up waiting after ~20 s and do the
    rest): the forked process did all but one block, and the constraints come in the order of
    one run."""
    import multiprocessing as mp
    import os
    import time

    pairs = np.column_stack((np.repeat(np.arange(100), 2), np.arange(200) + 200))
    me = os.getpid()
    done = mp.get_context("fork").Value("i", 0)
    stalled = [False]

    def run(part: np.ndarray) -> list[fa.AlignmentConstraint]:
        if os.getpid() == me and not stalled[0]:
            stalled[0] = True
            for _ in range(2000):  # until the other has done the rest (at most ~20 s)
                if done.value >= fa.SHARED_BLOCKS - 1:
                    break
                time.sleep(0.01)
        elif os.getpid() != me:
            with done.get_lock():
                done.value += 1
        return [
            fa.AlignmentConstraint(int(c), int(k), np.zeros(3), np.eye(3), float(os.getpid()))
            for c, k in part
        ]

    out = fa._shared(pairs, run, processes=2)
    assert [(c.reference, c.query) for c in out] == [tuple(p) for p in pairs.tolist()]
    assert done.value == fa.SHARED_BLOCKS - 1
    mine = {c.reference for c in out if c.inlier_fraction == me}
    assert 0 < len(mine) <= 100 // fa.SHARED_BLOCKS + 1


def test_pairs_of_a_place_passed_many_times_need_memory_for_a_chunk_only():
    """Keyframes of 60 passes of one 1 m circle all lie within the radius of each other: the pairs
    are gathered ``PAIRS_CHUNK`` keyframes at a time (all pairs at once: 4.5 million, ~300 MB of
    index arrays) and equal a direct computation."""
    import tracemalloc

    from frslam_graph.loop_closure import final_alignment as fa

    n = 1500
    t = np.arange(n) * 0.125  # 0.125 m steps on a circle of radius 0.5 m: a pass is 25 keyframes
    poses = np.column_stack((0.5 * np.cos(t / 0.5), 0.5 * np.sin(t / 0.5), t / 0.5 + np.pi / 2))
    travel = t.copy()
    tracemalloc.start()
    try:
        pairs = candidate_pairs(poses, travel, radius=2.0, heading_window=np.pi, per_keyframe=3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 40 * 2**20, f"{peak / 2**20:.0f} MB"
    # the same pairs directly: per keyframe the nearest of other passes (ties: lower index)
    want = set()
    for k in range(n):
        d = np.hypot(*(poses[:, :2] - poses[k, :2]).T)
        chosen: list[int] = []
        for c in np.lexsort((np.arange(n), d)):
            if d[c] <= 2.0 and abs(travel[c] - travel[k]) >= fa.MIN_PASS_TRAVEL:
                if all(abs(travel[c] - travel[o]) >= fa.MIN_PASS_TRAVEL for o in chosen):
                    chosen.append(int(c))
                    if len(chosen) == 3:
                        break
        want |= {(min(c, k), max(c, k)) for c in chosen}
    assert set(map(tuple, pairs.tolist())) == want


def _slipped_segment(angle_deg: float = 12.0):
    """Two laps of a room (keyframes, 360° scans); in the estimate a stretch of the second lap
    (about 3 m) is turned by ``angle_deg`` about its middle keyframe, as after an odometry slip in
    a fast spin: (truth, estimate, points, origins, mask of the stretch)."""
    truth, _, points, second = _two_laps()
    k2 = np.flatnonzero(second)
    mid = int(k2[len(k2) // 3])
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))))
    seg = second & (np.abs(travel - travel[mid]) <= 1.5)
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    p = truth[mid, :2]
    turn = np.array([*(p - np.array([[c, -s], [s, c]]) @ p), a])  # rotation about p
    estimate = truth.copy()
    estimate[seg] = np.array([compose(turn, q) for q in truth[seg]])
    return truth, estimate, points, [np.zeros(2)] * len(points), seg


def test_search_ties_a_stretch_the_icp_cannot_reach():
    """A stretch of the second lap is 12° off (beyond the ICP's 5° gate and its reach): the ICP
    alone ties none of its keyframes to the first lap; with the search (``origins`` given) they
    are tied, and every searched constraint measures the true relative pose."""
    truth, estimate, points, origins, seg = _slipped_segment(12.0)
    icp = dense_constraints(estimate, truth, points, radius=2.0, max_range=15.0)
    assert not any(seg[c.reference] or seg[c.query] for c in icp)
    cons = dense_constraints(estimate, truth, points, radius=2.0, max_range=15.0, origins=origins)
    found = [c for c in cons if c.searched]
    assert [(c.reference, c.query) for c in cons if not c.searched] == [(c.reference, c.query) for c in icp]
    assert len({c.query for c in found if seg[c.query]}) >= 3
    assert all(seg[c.reference] or seg[c.query] for c in found)
    err = np.array([c.relative - between(truth[c.reference], truth[c.query]) for c in found])
    assert np.hypot(err[:, 0], err[:, 1]).max() < 0.03
    assert np.degrees(np.abs(err[:, 2])).max() < 0.5


def test_search_skips_the_pairs_the_icp_reached(monkeypatch):
    """Six keyframes of the second lap carry clutter (1 × 0.5 m of points ahead, not in the first
    lap): their ICP converges within its gates but with too few inliers, so they are untied.
    The estimate is within the ICP's reach there: the search, which would start at the same
    place, is not given their pairs (only those the ICP could not judge)."""
    truth, estimate, points, second = _two_laps()
    k2 = np.flatnonzero(second)
    stretch = k2[len(k2) // 3 : len(k2) // 3 + 6]
    g = np.arange(0.0, 1.0, 0.05) + 0.025
    clutter = (np.stack(np.meshgrid(g + 1.0, g - 0.5), -1).reshape(-1, 2) * [1.0, 0.5]).astype(np.float32)
    points = [np.concatenate((p, clutter)) if k in stretch else p for k, p in enumerate(points)]
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))))
    pairs = candidate_pairs(estimate, travel, 2.0, np.pi, 3)
    low = {
        (c.reference, c.query)
        for c in fa.reached_pairs(estimate, points, pairs, 15.0)
        if c.inlier_fraction < 0.7
    }
    assert len({k for _, k in low} & set(stretch.tolist())) >= 4
    given = []

    def searched(poses, points_, origins, pairs_, config, processes=1):
        given.extend(map(tuple, pairs_.tolist()))
        return []

    monkeypatch.setattr(fa, "searched_constraints", searched)
    cons = dense_constraints(estimate, truth, points, 2.0, 15.0, origins=[np.zeros(2)] * len(points))
    tied = {c.reference for c in cons} | {c.query for c in cons}
    assert not {k for _, k in low} & tied  # untied: the old rule searched all their pairs
    assert not low & set(given)


def test_search_in_two_processes_gives_the_same_constraints():
    """searched_constraints with processes=2 matches the pairs of the second half of the
    references in a forked process: the same constraints, bit for bit, in the same order."""
    truth, estimate, points, origins, seg = _slipped_segment(12.0)
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))))
    pairs = candidate_pairs(estimate, travel, 2.0, np.pi, 3)
    pairs = pairs[seg[pairs[:, 0]] | seg[pairs[:, 1]]]
    cfg = LoopClosureConfig()
    one = fa.searched_constraints(estimate, points, origins, pairs, cfg)
    two = fa.searched_constraints(estimate, points, origins, pairs, cfg, processes=2)
    assert len(one) >= 3
    assert [(c.reference, c.query, c.searched) for c in two] == [(c.reference, c.query, True) for c in one]
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a.relative, b.relative)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        assert a.inlier_fraction == b.inlier_fraction


def test_a_searched_constraint_counts_only_when_another_agrees():
    """agreeing(): two constraints of keyframes whose query submaps share no keyframe and whose
    implied poses keep the estimate's relative pose are kept; a lone one, one that disagrees
    (another correction), and one of a neighbouring keyframe (shared submap) are not."""
    poses = _line(0, 10, 0.0, 0.0, 21)
    truth = poses.copy()
    truth[10:] = np.array([compose(np.array([0.2, 0.1, np.deg2rad(8.0)]), q) for q in poses[10:]])

    def con(c: int, k: int, pose_k: np.ndarray) -> fa.AlignmentConstraint:
        return fa.AlignmentConstraint(c, k, between(poses[c], pose_k), np.eye(3) * 1e-4, 0.9, True)

    a, b = con(0, 14, truth[14]), con(1, 18, truth[18])
    assert fa.agreeing(poses, [a]) == []
    assert fa.agreeing(poses, [a, b]) == [a, b]
    other = con(2, 19, compose(np.array([-0.3, 0.0, np.deg2rad(-6.0)]), poses[19]))
    assert fa.agreeing(poses, [a, other]) == []
    assert fa.agreeing(poses, [a, b, other]) == [a, b]
    near = con(3, 15, truth[15])  # its query submap shares keyframes with a's
    assert fa.agreeing(poses, [a, near]) == []


def test_submaps_take_the_stored_float32_points_without_a_float64_copy():
    """The points within range stay float32 (the store's dtype: half the memory of the float64
    copy of every keyframe's points each round held) and give the same submaps bit for bit."""
    rng = np.random.default_rng(4)
    points = [rng.uniform(-12.0, 12.0, (700, 2)).astype(np.float32) for _ in range(12)]
    poses = np.column_stack(
        (np.cumsum(rng.uniform(0.2, 0.4, 12)), rng.normal(0, 0.1, 12), rng.normal(0, 0.3, 12))
    )
    local = fa._in_range(points, 10.0)
    assert all(p.dtype == np.float32 for p in local)
    wide = [p.astype(np.float64) for p in points]
    want = [p[np.hypot(p[:, 0], p[:, 1]) <= 10.0] for p in wide]  # the float64 copies of before
    for i in range(12):
        for span in (fa.QUERY_SPAN, fa.REFERENCE_SPAN):
            got = fa._submap(poses, local, i, span)
            assert got.dtype == np.float64
            np.testing.assert_array_equal(got, fa._submap(poses, want, i, span))
