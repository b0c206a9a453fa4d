"""Scan-to-plan relocalisation: pose recovery, ambiguity, corridor degeneracy, clutter."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import box as sbox
from synthetic_world import box, cast

from frslam_graph.errors import FloorPlanError, FrslamError
from frslam_graph.floorplan import Door, FloorPlan, Room
from frslam_graph.localisation.relocalisation import PlanField, Relocaliser, relocalise, subsample

H = 0.06  # half wall thickness used by the simulated walls and the relocaliser


def scan_points(world, pose, rng, max_range=10.0, noise=0.01):
    r, amin, inc = cast(world, np.asarray(pose, float), 720, max_range, noise, rng)
    ang = amin + inc * np.arange(720)
    ok = np.isfinite(r)
    return np.column_stack((r * np.cos(ang), r * np.sin(ang)))[ok]


def two_rooms():
    plan = FloorPlan(
        rooms=[Room("a", "living_room", sbox(0, 0, 6, 4)), Room("b", "bedroom", sbox(6, 0, 10, 4))],
        doors=[Door("d", (6.0, 1.5), (6.0, 2.5), ("a", "b"))],
        units="m",
    )
    world = np.array(
        [
            [H, H, 6 - H, H],
            [H, H, H, 4 - H],
            [H, 4 - H, 6 - H, 4 - H],
            [6 - H, H, 6 - H, 1.5],
            [6 - H, 2.5, 6 - H, 4 - H],
            [6 + H, H, 10 - H, H],
            [10 - H, H, 10 - H, 4 - H],
            [6 + H, 4 - H, 10 - H, 4 - H],
            [6 + H, H, 6 + H, 1.5],
            [6 + H, 2.5, 6 + H, 4 - H],
            [6 - H, 1.5, 6 + H, 1.5],
            [6 - H, 2.5, 6 + H, 2.5],
        ]
    )
    return plan, world


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_field_signs_and_door_opening():
    plan, _ = two_rooms()
    f = PlanField.from_plan(plan, resolution=0.02, wall_offset=H)
    d = f.lookup(np.array([[3.0, 2.0], [H, 2.0], [0.0, 2.0], [6.0, 2.0], [6.0, 3.5], [-3.0, 2.0]]))[:, 0]
    assert d[0] == pytest.approx(2.0 - H, abs=0.02)  # room centre: distance to the nearest wall
    assert abs(d[1]) < 0.02  # on the wall surface
    assert d[2] < 0  # inside the outer wall
    assert d[3] > 0.3  # the door opening is free space
    assert d[4] < 0  # the wall beside the door
    assert d[5] == -1.0  # off the raster


def _open_plan(walls_between: bool) -> FloorPlan:
    """Living (0..6) and kitchen (6..10) sharing the boundary x = 6; the plan's walls run around
    the outline, and along x = 6 only when ``walls_between``."""
    walls = [[0, 0, 10, 0], [10, 0, 10, 4], [10, 4, 0, 4], [0, 4, 0, 0]]
    if walls_between:
        walls.append([6, 0, 6, 4])
    return FloorPlan(
        rooms=[Room("a", "living_room", sbox(0, 0, 6, 4)), Room("b", "kitchen", sbox(6, 0, 10, 4))],
        doors=[],
        walls=np.array(walls, float),
        units="m",
    )


def test_field_leaves_boundaries_without_a_plan_wall_open():
    """An open-plan boundary (no plan wall along it) is free space in the field, as in the real
    building; with a wall along it, the field has a wall band there. Plans without walls keep
    every room boundary as a wall."""
    probe = np.array([[6.0, 2.0], [6.0, 0.7], [6.0, 3.3], [6.0, 0.02]])
    open_ = PlanField.from_plan(_open_plan(False), resolution=0.02, wall_offset=H).lookup(probe)[:, 0]
    assert np.all(open_[:3] > 0.5)  # across the open boundary, far from any wall
    assert open_[3] < 0.0  # the outer wall is never opened
    walled = PlanField.from_plan(_open_plan(True), resolution=0.02, wall_offset=H).lookup(probe)[:, 0]
    assert np.all(walled[:3] < 0.0)
    no_walls = _open_plan(False)
    no_walls = FloorPlan(rooms=no_walls.rooms, doors=[], units="m")
    assert np.all(PlanField.from_plan(no_walls, resolution=0.02, wall_offset=H).lookup(probe)[:3, 0] < 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_known_offset(seed):
    plan, world = two_rooms()
    rng = np.random.default_rng(seed)
    reloc = Relocaliser(plan)
    for _ in range(5):
        truth = np.array([rng.uniform(1, 5), rng.uniform(1, 3), rng.uniform(-3, 3)])
        pts = scan_points(world, truth, rng)
        prior = truth + np.array([0.4, -0.3, np.deg2rad(8.0)]) * rng.choice([-1, 1], 3)
        res = reloc.relocalise(pts, prior)
        assert res.ok, res.reason
        assert np.hypot(*(res.pose[:2] - truth[:2])) < 0.02
        assert abs(wrap(res.pose[2] - truth[2])) < np.deg2rad(0.5)
        assert res.score > 0.9
        assert res.ambiguity < 0.5
        # the covariance is honest about the error and not absurdly large
        assert np.all(res.std[:2] < 0.1) and res.std[2] < np.deg2rad(2)
        assert np.all(np.abs(res.pose - truth)[:2] < 4 * res.std[:2])


def test_prior_outside_window_is_not_found():
    plan, world = two_rooms()
    rng = np.random.default_rng(5)
    truth = np.array([3.0, 2.0, 0.3])
    pts = scan_points(world, truth, rng)
    res = relocalise(pts, plan, truth + [1.5, 0.0, 0.0], window_xy=0.3)
    assert np.hypot(*(res.pose[:2] - truth[:2])) > 0.5  # the search stays in its window


def test_symmetric_square_room_is_ambiguous():
    plan = FloorPlan(rooms=[Room("a", "bedroom", sbox(0, 0, 6, 6))], units="m")
    world = box(H, H, 6 - H, 6 - H)
    rng = np.random.default_rng(0)
    truth = np.array([3.0, 3.0, 0.2])
    pts = scan_points(world, truth, rng)
    reloc = Relocaliser(plan)
    res = reloc.relocalise(pts, truth + [0.05, 0.0, 0.02], window_xy=0.5, window_theta=np.pi)
    assert res.ambiguity > 0.9
    assert res.runner_up is not None
    # the competitor is a 90/180/270 degree turn of the winner
    dth = abs(wrap(res.runner_up[2] - res.pose[2]))
    assert min(abs(dth - np.pi / 2), abs(dth - np.pi)) < np.deg2rad(2)
    # the same room seen off-centre, with a small window: unique
    truth = np.array([2.0, 2.5, 0.2])
    pts = scan_points(world, truth, rng)
    res = reloc.relocalise(pts, truth + [0.1, 0.0, 0.02])
    assert res.ambiguity < 0.5
    assert np.hypot(*(res.pose[:2] - truth[:2])) < 0.02


def test_corridor_degeneracy_in_covariance():
    plan = FloorPlan(rooms=[Room("c", "corridor", sbox(0, 0, 30, 2))], units="m")
    world = box(H, H, 30 - H, 2 - H)
    rng = np.random.default_rng(1)
    truth = np.array([15.0, 1.0, 0.1])
    pts = scan_points(world, truth, rng, max_range=8.0)  # the corridor's ends are out of range
    prior = truth + [0.3, 0.1, 0.05]
    res = Relocaliser(plan).relocalise(pts, prior)
    assert res.ok
    sx, sy, _ = res.std
    assert sx > 1.0  # along the corridor: unobservable
    assert sy < 0.05  # across: well observed
    assert sx > 20 * sy
    assert abs(res.pose[1] - truth[1]) < 0.02
    assert abs(wrap(res.pose[2] - truth[2])) < np.deg2rad(0.5)
    assert abs(res.pose[0] - prior[0]) < 0.2  # the flat direction stays at the prior


def test_clutter_is_tolerated():
    plan = FloorPlan(rooms=[Room("a", "bedroom", sbox(0, 0, 6, 4))], units="m")
    clutter = np.vstack(
        [box(1, 1, 1.6, 1.5), box(4, 2.5, 4.3, 3.5), box(2.5, 0.5, 3, 0.8), box(0.5, 3, 1.2, 3.4)]
    )
    world = np.vstack([box(H, H, 6 - H, 4 - H), clutter])
    rng = np.random.default_rng(2)
    reloc = Relocaliser(plan)
    scores = []
    for _ in range(6):
        truth = np.array([rng.uniform(2, 4), rng.uniform(1.6, 2.4), rng.uniform(-3, 3)])
        pts = scan_points(world, truth, rng)
        res = reloc.relocalise(pts, truth + [0.3, -0.2, 0.1])
        assert res.ok
        assert np.hypot(*(res.pose[:2] - truth[:2])) < 0.03
        assert abs(wrap(res.pose[2] - truth[2])) < np.deg2rad(0.7)
        scores.append(res.score)
    assert min(scores) < 0.98  # the clutter points are counted as outliers


def test_other_building_scores_low():
    plan, world = two_rooms()
    other = FloorPlan(rooms=[Room("x", "bedroom", sbox(0, 0, 3, 9))], units="m")
    rng = np.random.default_rng(3)
    truth = np.array([3.0, 2.0, 0.0])
    pts = scan_points(world, truth, rng)
    good = relocalise(pts, plan, truth)
    bad = relocalise(pts, other, np.array([1.5, 4.5, 0.0]))
    assert good.score > 0.9
    assert bad.score < 0.5


def test_too_few_points_and_bad_prior():
    plan, _ = two_rooms()
    reloc = Relocaliser(plan)
    res = reloc.relocalise(np.array([[1.0, 0.0], [np.nan, 1.0]]), np.zeros(3))
    assert not res.ok and "too few" in res.reason
    assert np.all(res.std > 1.0)
    with pytest.raises(FrslamError, match="prior"):
        reloc.relocalise(np.ones((50, 2)), np.array([0.0, np.nan, 0.0]))


def test_subsample_limits_and_spreads():
    ang = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    pts = np.column_stack((3 * np.cos(ang), 3 * np.sin(ang)))
    pts[::7] = np.nan
    sub = subsample(pts, 0.15, 50)
    assert len(sub) == 50 and np.all(np.isfinite(sub))
    a = np.sort(np.arctan2(sub[:, 1], sub[:, 0]))
    assert np.max(np.diff(a)) < 0.3  # spread around the whole circle


def test_plan_must_be_metric_and_large_plans_get_coarser():
    px = FloorPlan(rooms=[Room("a", "bedroom", sbox(0, 0, 600, 400))], units="px")
    with pytest.raises(FloorPlanError, match="not metres"):
        Relocaliser(px)
    big = FloorPlan(rooms=[Room("a", "office", sbox(0, 0, 200, 150))], units="m")
    f = PlanField.from_plan(big, resolution=0.025, max_pixels=1_000_000)
    assert f.frame.height * f.frame.width <= 1_100_000
    assert f.frame.resolution > 0.1


def test_competitors_are_greedy_separated_candidates():
    rel = Relocaliser(two_rooms()[0])  # separation 0.3 m or 8 deg
    poses = np.array(
        [
            [0.0, 0.0, 0.0],  # the winner
            [0.1, 0.0, 0.0],  # too close to the winner
            [1.0, 0.0, 0.0],  # taken
            [1.1, 0.1, 0.0],  # too close to the one taken
            [0.0, 0.0, np.deg2rad(10.0)],  # turned: taken
            [0.0, 0.0, 2 * np.pi - 0.01],  # the winner's heading, wrapped: too close
            [-2.0, 0.0, 0.0],  # would be the third
        ]
    )
    assert rel._spread(poses, 3) == [2, 4, 6]
    assert rel._spread(poses, 1) == [2]
    assert rel._spread(poses[:2], 3) == []


def test_a_plan_drawn_off_the_building_widens_the_covariance_to_its_errors():
    """A plan drawn 4 % too long moves every relocalisation on it by up to 0.4 m whatever the
    number of scan points: the plain covariance is 10-20 sigmas off, the one with the plan's
    drawing error (``drawn_off``) covers it; the pose, score and ambiguity stay the same."""
    from shapely import affinity

    plan, world = two_rooms()
    s = 1.04
    drawn = FloorPlan(
        rooms=[Room(r.id, r.type, affinity.scale(r.polygon, s, 1.0, origin=(0, 0))) for r in plan.rooms],
        doors=[Door(d.id, (d.a[0] * s, d.a[1]), (d.b[0] * s, d.b[1]), d.rooms) for d in plan.doors],
        units="m",
    )
    rng = np.random.default_rng(3)
    exact = Relocaliser(drawn)
    off = exact.drawn_off(0.12)
    assert exact.drawn_off(0.0) is exact and off.field is exact.field
    worst_exact, worst_off = 0.0, 0.0
    for _ in range(8):
        truth = np.array([rng.uniform(1, 9), rng.uniform(1, 3), rng.uniform(-3, 3)])
        pts = scan_points(world, truth, rng)
        a, b = exact.relocalise(pts, truth), off.relocalise(pts, truth)
        assert a.ok and b.ok
        np.testing.assert_array_equal(a.pose, b.pose)
        assert (a.score, a.ambiguity) == (b.score, b.ambiguity)
        err = np.abs(a.pose[:2] - truth[:2])
        worst_exact = max(worst_exact, float(np.max(err / a.std[:2])))
        worst_off = max(worst_off, float(np.max(err / b.std[:2])))
        assert np.all(b.std >= a.std)
    assert worst_exact > 8.0
    assert worst_off < 3.0


def test_an_accepted_plan_drawn_off_relocalises_with_its_drawing_error():
    from frslam_graph.plan_updates.accepted import AcceptedPlan

    plan, _ = two_rooms()
    rel = Relocaliser(plan)
    assert AcceptedPlan(0, None, plan, rel, map_fit=0.5).relocaliser is rel
    acc = AcceptedPlan(0, None, plan, rel, map_fit=0.5, drawing_tol=0.3)
    assert acc.relocaliser.drawing_sigma == pytest.approx(0.15) and acc.relocaliser.field is rel.field
