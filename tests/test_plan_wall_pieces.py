"""The judge's per-piece check of a registered plan's walls (plan_checks.wall_pieces_seen_through)
and the relocaliser that ignores the disagreeing pieces (Relocaliser.ignoring): a plan drawn
differently from the building in one place loses that wall piece, not the registration."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import box

from frslam_graph.floorplan import Door, FloorPlan, Room
from frslam_graph.localisation.relocalisation import IGNORED, Relocaliser
from frslam_graph.occupancy import OccupancyGrid
from frslam_graph.plan_checks import wall_pieces_seen_through, walls_through_free_space

RES = 0.05


def _plan() -> FloorPlan:
    """Two 4 x 4 m rooms side by side (metres), a wall at x = 4 with a door at y = 0.5-1.3."""
    rooms = [Room("a", "office", box(0, 0, 4, 4)), Room("b", "office", box(4, 0, 8, 4))]
    return FloorPlan(rooms=rooms, doors=[Door("d", (4.0, 0.5), (4.0, 1.3), ("a", "b"))], units="m")


def _building(open_from: float) -> OccupancyGrid:
    """The map of the building: the outer walls and the wall at x = 4 occupied, the rooms free,
    but the wall at x = 4 absent above y = ``open_from`` (the robot saw through it)."""
    h, w = int(5.0 / RES), int(9.0 / RES)
    data = np.full((h, w), -1, np.int8)
    grid = OccupancyGrid(data, RES, (-0.5, -0.5, 0.0))
    rr, cc = np.mgrid[0:h, 0:w]
    xy = grid.cell_to_world(np.column_stack((cc.ravel() + 0.5, rr.ravel() + 0.5))).reshape(h, w, 2)
    x, y = xy[..., 0], xy[..., 1]
    inside = (x > 0) & (x < 8) & (y > 0) & (y < 4)
    outer = ~inside & (x > -0.1) & (x < 8.1) & (y > -0.1) & (y < 4.1)
    wall = (np.abs(x - 4.0) < 0.06) & (y < open_from) & ~((y > 0.5) & (y < 1.3))
    data[inside] = 0
    data[outer | wall] = 100
    return OccupancyGrid(data, RES, (-0.5, -0.5, 0.0))


def _scan_in_room_b() -> tuple[np.ndarray, np.ndarray]:
    """A scan from (6, 2) in room b of :func:`_plan` (base_link points, its pose): the room's four
    walls, a quarter of the points on the wall at x = 4."""
    t = np.linspace(0.0, 4.0, 80, endpoint=False)
    walls = np.vstack(
        (
            np.c_[np.full(80, 4.0), t],
            np.c_[np.full(80, 8.0), t],
            np.c_[4.0 + t, np.zeros(80)],
            np.c_[4.0 + t, np.full(80, 4.0)],
        )
    )
    return walls - np.array([6.0, 2.0]), np.array([6.0, 2.0, 0.0])


def test_only_the_wall_piece_seen_through_is_dropped_and_ignored():
    rel = Relocaliser(_plan())
    grid = _building(open_from=3.0)
    assert walls_through_free_space(rel, grid, 0.2) > 0.1  # the whole-plan check refuses
    pts, dropped, rest = wall_pieces_seen_through(rel, grid, 0.2, 0.1)
    assert len(pts) and np.all(np.abs(pts[:, 0] - 4.0) < 0.2) and pts[:, 1].min() >= 3.0 - 1e-9
    assert 0.1 < dropped < 0.5 and rest <= 0.1
    part = rel.ignoring(pts, 0.3)
    assert walls_through_free_space(part, grid, 0.2) <= 0.1
    # no information about the dropped piece: a point on it is an outlier; the rest unchanged
    on_piece, on_wall = np.array([[4.0, 3.5]]), np.array([[4.0, 2.0], [0.0, 2.0], [6.0, 0.0]])
    assert part.field.lookup(on_piece)[0, 0] == IGNORED and rel.fit_points(on_piece, 0.1) == 1.0
    assert part.fit_points(on_piece, 0.1) == 0.0 and part.fit_points(on_wall, 0.1) == 1.0
    assert rel.ignored is None and part.ignored is not None


def test_a_plan_that_agrees_with_the_building_drops_no_piece():
    rel = Relocaliser(_plan())
    pts, dropped, rest = wall_pieces_seen_through(rel, _building(open_from=9.0), 0.2, 0.1)
    assert len(pts) == 0 and dropped == 0.0 and rest == 0.0
    assert rel.ignoring(pts, 0.3) is rel


def _thick_walled(gap: float) -> tuple[FloorPlan, OccupancyGrid, OccupancyGrid]:
    """Two 4 x 4 m rooms drawn ``gap`` m apart (a wall as thick as an image plan draws it, no
    door), and two maps of the building: one with that wall (occupied), one where the robot has
    seen straight through it (free everywhere inside the outer walls)."""
    rooms = [Room("a", "office", box(0, 0, 4, 4)), Room("b", "office", box(4 + gap, 0, 8 + gap, 4))]
    plan = FloorPlan(rooms=rooms, doors=[], units="m")
    h, w = int(5.0 / RES), int((9.0 + gap) / RES)
    rr, cc = np.mgrid[0:h, 0:w]
    proto = OccupancyGrid(np.zeros((h, w), np.int8), RES, (-0.5, -0.5, 0.0))
    xy = proto.cell_to_world(np.column_stack((cc.ravel() + 0.5, rr.ravel() + 0.5))).reshape(h, w, 2)
    x, y = xy[..., 0], xy[..., 1]
    inside = (x > 0) & (x < 8 + gap) & (y > 0) & (y < 4)
    outer = ~inside & (x > -0.1) & (x < 8.1 + gap) & (y > -0.1) & (y < 4.1)
    maps = []
    for wall in ((x > 4.0) & (x < 4.0 + gap), np.zeros_like(inside)):
        data = np.full((h, w), -1, np.int8)
        data[inside] = 0
        data[outer | wall] = 100
        maps.append(OccupancyGrid(data, RES, (-0.5, -0.5, 0.0)))
    return plan, maps[0], maps[1]


def test_thick_interior_walls_are_judged_too():
    """A wall drawn 0.3 m thick between two rooms is an interior wall: seen straight through, the
    check sees it (before, every wall thicker than about 0.2 m counted as an outer wall and was
    never tested: on the Intel plan 0.5-4.5 m of its walls were, and the share seen through
    jumped between 0.2 and 0.7 on maps a few metres apart)."""
    plan, built, open_ = _thick_walled(0.3)
    rel = Relocaliser(plan)
    assert walls_through_free_space(rel, built, 0.2) <= 0.1
    assert walls_through_free_space(rel, open_, 0.2) > 0.9
    pts, dropped, _ = wall_pieces_seen_through(rel, open_, 0.2, 0.1)
    assert dropped > 0.9 and np.all((pts[:, 0] > 3.8) & (pts[:, 0] < 4.5))
    # the outer walls (outside behind them) are never tested: the map sees nothing beyond them
    assert walls_through_free_space(Relocaliser(plan.subset(["a"])), open_, 0.2) == 0.0


def test_the_ignored_surroundings_count_neither_way():
    """Map points and scan points around an ignored wall piece (the plan is drawn differently
    there) are left out of the shares: the rest of the plan fits as well as it does (before, they
    counted as misfits: a drawn-off plan's map fit fell below min_map_fit and a scan standing near
    such a piece failed the relocalisation score)."""
    rel = Relocaliser(_plan())
    grid = _building(open_from=3.0)
    pts, _, _ = wall_pieces_seen_through(rel, grid, 0.2, 0.1)
    part = rel.ignoring(pts, 0.3)
    on_piece, on_wall = np.array([[4.0, 3.5]]), np.array([[4.0, 2.0], [0.0, 2.0], [6.0, 0.0]])
    assert part.fit_points(np.vstack((on_piece, on_wall)), 0.1) == 1.0
    assert rel.fit_points(np.vstack((on_piece, on_wall + 1.0)), 0.1) == 0.25
    scan, pose = _scan_in_room_b()
    full = rel.relocalise(scan, pose)
    wide = rel.ignoring(np.c_[np.full(41, 4.0), np.linspace(0.0, 4.0, 41)], 0.3)
    ignored = wide.relocalise(scan, pose)
    assert full.score > 0.9 and ignored.ok and ignored.score > 0.9


def test_evaluate_reports_a_pose_as_relocalise_does_around_ignored_pieces():
    """The start alignment moves a plan when the first scan's soft score at the relocalised pose
    beats the score at the anchor (``evaluate``). Around ignored wall pieces ``relocalise``
    reported its scores over the informed points, ``evaluate`` over all: at the very same pose
    the "gain" was 0.06-0.07 on the Intel plan, so the plan was moved at every check (intel.bag:
    1 deg back and forth five times, each re-anchoring every prior)."""
    rel = Relocaliser(_plan())
    scan, pose = _scan_in_room_b()
    part = rel.ignoring(np.c_[np.full(41, 4.0), np.linspace(0.0, 4.0, 41)], 0.3)
    for r in (rel, part):
        found = r.relocalise(scan, pose)
        score, soft = r.evaluate(scan, found.pose)
        assert soft == pytest.approx(found.soft_score, abs=1e-12)
        assert score == pytest.approx(found.score, abs=1e-12)
    # the ignored quarter counts neither way: the rest fits as well as the whole plan does
    assert part.evaluate(scan, pose)[1] >= rel.evaluate(scan, pose)[1] - 0.01
