"""MFR on maps not made by the project's simulator (issue 21): thick walls, real sensor maps.

Excerpts in ``tests/data/halmstad`` (a crop of a Halmstad apartment's layout drawing and of one
of its Tango sensor maps, with the annotated points; GPL-3.0, ``tests/data/halmstad/LICENSE``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from shapely.geometry import box

from frslam_graph.floorplan import Door, FloorPlan, Room
from frslam_graph.occupancy import OccupancyGrid
from frslam_graph.raster import RasterFrame, rasterise_plan
from frslam_graph.registration import matrix_from_params, params_from_matrix, register
from frslam_graph.registration.evaluation import iou_a
from tests.test_registration import EXPLORED, U, ring_map, synthetic_plan, truth_matrix


def _rooms_and_walls(house, frame, thickness: float, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Room labels of ``house`` (metres) on ``frame``, and its walls ``thickness`` m thick centred
    on the room boundaries, cut at the doors."""
    lab = rasterise_plan(house, frame, labels=True)
    edge = np.zeros(lab.shape, np.uint8)
    edge[:, 1:] |= (lab[:, 1:] != lab[:, :-1]).astype(np.uint8)
    edge[1:, :] |= (lab[1:, :] != lab[:-1, :]).astype(np.uint8)
    wall = cv2.distanceTransform(1 - edge, cv2.DIST_L2, 5) * res < thickness / 2.0
    cut = np.zeros(lab.shape, np.uint8)
    for d in house.doors:
        a, b = frame.to_pixel(np.array([d.a, d.b])) - 0.5
        cv2.line(
            cut, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), 1, int(thickness / res) + 3
        )
    return lab, wall & ~cut.astype(bool)


def thick_wall_map(
    plan, truth: np.ndarray, rooms: list[str], thickness: float, res: float = 0.05, outside=None
):
    """Occupancy grid of ``rooms`` of ``truth · plan`` with walls ``thickness`` m thick centred on
    the room boundaries (as buildings and their plans are drawn): free space stops at the wall
    face, the face is seen two cells deep, door openings cut through the walls.

    ``outside``: a box (x0, y0, x1, y1, plan units) of free space outside the building seen
    through the explored rooms' wall along it (a glazed wall, an open terrace): no plan room
    holds it, and its far sides run into unknown space."""
    house = plan.transformed(truth, units="m")
    frame = RasterFrame.around(house.subset(rooms).bounds, res, margin=4.0 if outside else 1.0)
    lab, wall = _rooms_and_walls(house, frame, thickness, res)
    ids = [r.id for r in house.rooms]
    explored = np.isin(lab, [ids.index(r) + 1 for r in rooms])
    free = explored & ~wall
    beyond = np.zeros(lab.shape, bool)
    if outside is not None:
        x0, y0, x1, y1 = outside
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float) @ truth[:2, :2].T + truth[:2, 2]
        box_px = np.zeros(lab.shape, np.uint8)
        cv2.fillPoly(box_px, [np.round(frame.to_pixel(corners) - 0.5).astype(np.int32).reshape(-1, 1, 2)], 1)
        beyond = box_px.astype(bool) & (lab == 0)
        k = np.ones((int(thickness / res) + 3,) * 2, np.uint8)
        through = wall & cv2.dilate(beyond.astype(np.uint8), k).astype(bool)  # the wall between
        free |= beyond | (through & cv2.dilate(explored.astype(np.uint8), k).astype(bool))
    seen = cv2.dilate(free.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    occ = seen & ~free & (wall | (lab == 0))
    occ &= ~cv2.dilate(beyond.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return OccupancyGrid.from_masks(free, occ, res, (frame.origin[0], frame.origin[1], 0.0))


@pytest.mark.parametrize("flipped, rotation", [(False, 90.0), (True, 180.0)])
def test_thick_walls_register_and_are_accepted(flipped, rotation):
    # walls 0.35 m thick: the plan's room boundaries (wall centres) lie 0.175 m beyond the map's
    # wall faces, outside the observed area; precision and recall at the fitted wall offset
    # accept the right placement (without: precision ~0, "no match")
    plan = synthetic_plan()
    truth = truth_matrix(flipped, rotation)
    grid = thick_wall_map(plan, truth, EXPLORED, thickness=0.35)
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    f, rot, *_ = params_from_matrix(truth)
    assert reg.flipped == f
    assert abs((reg.rotation_deg - math.degrees(rot) + 180.0) % 360.0 - 180.0) < 2.0
    assert iou_a(plan, reg.matrix, truth) > 0.9
    assert reg.details["precision"] > 0.6 and reg.details["recall"] > 0.6
    assert 0.1 < reg.details["delta_m"] < 0.25


@pytest.mark.parametrize("flipped, rotation", [(False, 90.0), (True, 270.0), (True, 180.0)])
def test_footprint_beyond_the_plan_rooms_registers_at_the_true_scale(flipped, rotation):
    # thick walls and free space outside the building seen through the living room's west wall
    # (as PRBonn's gmapping map sees beyond its corridor's end): the plan's rooms (to the wall
    # centres) cover ~85 % of the footprint. The moment-fitted scales are ~20 % too large and that
    # placement passed the gate (scale +23 %, IoU_a 0.49 at 90 and 270 degrees without the wide
    # scale search, ``wide_seeds=0``); the search from the best placement's own rotation finds
    # the truth, which the gate's measure ranks first
    plan = synthetic_plan()
    truth = truth_matrix(flipped, rotation)
    grid = thick_wall_map(plan, truth, EXPLORED, thickness=0.25, outside=(-3.0 * U, 0.5 * U, 0.0, 3.5 * U))
    known = ~grid.unknown_mask()
    house = plan.transformed(truth, units="m")
    frame = RasterFrame(grid.resolution, tuple(grid.origin[:2]), grid.data.shape)
    in_rooms = rasterise_plan(house, frame, labels=True) > 0
    assert 0.8 < np.count_nonzero(known & in_rooms) / np.count_nonzero(known) < 0.9
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    f, rot, sx, sy, _, _ = params_from_matrix(truth)
    ef, erot, esx, esy, _, _ = params_from_matrix(reg.matrix)
    assert ef == f and abs((math.degrees(erot - rot) + 180.0) % 360.0 - 180.0) < 1.0
    assert abs(math.sqrt(esx * esy / (sx * sy)) - 1.0) < 0.02
    assert iou_a(plan, reg.matrix, truth) > 0.9


def test_wide_search_reaches_scales_a_third_off():
    # the refinement's basin is about +-5 % in scale; the wide search starts from a placement
    # 25-35 % off along both map axes and shifted, and returns one inside that basin, which the
    # screening refinement takes to the truth
    from frslam_graph.registration.mfr import coarse, fine
    from frslam_graph.registration.mfr.map_side import observe_map
    from frslam_graph.registration.mfr.plan_side import prepare_plan
    from frslam_graph.registration.mfr.register import DEFAULTS

    plan = synthetic_plan()
    truth = truth_matrix(False, 90.0)
    grid = thick_wall_map(plan, truth, EXPLORED, thickness=0.2)
    obs = observe_map(grid)
    pm = prepare_plan(plan)
    true_g = np.linalg.inv(obs.to_map) @ truth  # plan -> the grid frame of the crop
    off = np.diag([0.75, 1.35, 1.0])
    off[:2, 2] = obs.centroid - off[:2, :2] @ obs.centroid + (0.4, -0.3)
    seed = coarse.Hypothesis(0, 0, False, off @ true_g, 0.0)
    found = coarse.wide_search(pm, obs, [seed], dict(DEFAULTS), 0.15, 1)
    assert len(found) == 1
    _, _, tsx, tsy, _, _ = params_from_matrix(true_g)

    def errors(m: np.ndarray) -> tuple[float, float, float]:
        _, _, esx, esy, _, _ = params_from_matrix(m)
        corners = np.array([[0.0, 0.0], [9.0 * U, 0.0], [0.0, 9.0 * U], [9.0 * U, 9.0 * U]])
        d = corners @ (m - true_g)[:2, :2].T + (m - true_g)[:2, 2]
        return abs(esx / tsx - 1.0), abs(esy / tsy - 1.0), float(np.max(np.hypot(d[:, 0], d[:, 1])))

    ex, ey, shift = errors(found[0].matrix)
    assert ex < 0.05 and ey < 0.05 and shift < 0.5
    fine.screen(pm, obs, found, dict(DEFAULTS), 0.15)
    ex, ey, shift = errors(found[0].refined.matrix)
    assert ex < 0.02 and ey < 0.02 and shift < 0.15


@pytest.mark.parametrize(
    "plan_file, rotation, seed, style, completeness",
    [
        ("00988a5263f5", "step90", 1, "thick", 75),
        ("06d8961ed28b", "step90", 0, "tango", 100),
    ],
)
def test_independent_map_styles_pick_the_right_screened_placement(
    test_data, plan_file, rotation, seed, style, completeness
):
    # maps drawn by tools/bench_real.py's map makers (not the simulator's): the coarse grid's key
    # ranked a placement shifted by a room above the right one (IoU_a 0.38 / failure without
    # fine.structure_key); the gate's own measure ranks the right one first
    from conftest import load_tool
    from frslam_graph.datasets.simulator import Distortion, House

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    path = next((test_data / "r2v").glob(plan_file[:12] + "*.txt"))
    plan = FloorPlan.load(path)
    dist = Distortion.random(np.random.default_rng([seed, 7]), rotation=rotation, plan_bounds=plan.bounds)
    house = House.from_plan(plan, dist)
    grid, _, _ = bench.styled_map(
        house, style, completeness / 100, np.random.default_rng([seed, completeness, len(style)])
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert iou_a(plan, reg.matrix, dist.matrix) > 0.75


def test_annotation_similarity_recovers_a_flip():
    from conftest import load_tool

    bench = load_tool("bench_real")
    rng = np.random.default_rng(0)
    src = rng.uniform(0, 100, size=(8, 2))
    truth = np.array([[0.0, 0.5, 3.0], [0.5, 0.0, -1.0], [0.0, 0.0, 1.0]])  # a flip, 0.5 per unit
    dst = src @ truth[:2, :2].T + truth[:2, 2] + rng.normal(0, 0.2, size=(8, 2))
    m, res = bench.fit_similarity(src, dst)
    assert params_from_matrix(m)[0] and np.allclose(m[:2, :2], truth[:2, :2], atol=0.01)
    assert np.allclose(m[:2, 2], truth[:2, 2], atol=0.5)
    assert 0.1 < res < 0.4


def test_halmstad_apartment_sensor_map_registers_within_the_annotation_residual(test_data):
    # a real Tango map against the apartment's layout drawing (excerpts, a few kB): the layout's
    # door gaps are drawn wider than the default door width, so without widening it the plan
    # reads as one room and registration is impossible
    from conftest import load_tool

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    folder = test_data / "halmstad"
    plan = FloorPlan.load(folder / "HIH_layout_crop.png")
    assert len(plan.rooms) >= 3
    row = _registered_against_points(
        bench, plan, folder / "HIH_03_crop.png", folder / "HIH_03_to_layout_crop.csv", 5
    )
    assert row["flip_ok"] and row["rot_err_deg"] < 2.0
    assert abs(row["scale_err"]) < 0.02
    assert row["err_ratio"] < 2.0


def _registered_against_points(bench, plan, map_png, points_csv, skiprows: int) -> dict:
    """MFR of ``plan`` on the Halmstad sensor map ``map_png`` (0.05 m a pixel), accepted, scored
    against the annotated points (``tools/bench_real.py``'s row: flip, rotation, scale, points)."""
    res = 0.05
    grid = OccupancyGrid.from_image(map_png, res)
    pts = np.loadtxt(points_csv, delimiter=",", comments="#", skiprows=skiprows, ndmin=2)
    map_pts = np.column_stack([pts[:, 0] + 0.5, pts[:, 1]]) * res
    plan_pts = np.column_stack([pts[:, 2] + 0.5, pts[:, 3]])
    truth, residual = bench.fit_similarity(plan_pts, map_pts)
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    return bench.point_rows(reg, truth, plan_pts, map_pts, residual)


def _styled(test_data, stem: str, rotation: str, style: str, share: float, dist_seed, map_seed):
    """(plan, grid, truth) of a map drawn by one of tools/bench_real.py's map makers."""
    from conftest import load_tool
    from frslam_graph.datasets.simulator import Distortion, House

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    plan = FloorPlan.load(next((test_data / "r2v").glob(stem + "*.txt")))
    dist = Distortion.random(np.random.default_rng(dist_seed), rotation=rotation, plan_bounds=plan.bounds)
    grid, _, _ = bench.styled_map(House.from_plan(plan, dist), style, share, np.random.default_rng(map_seed))
    return plan, grid, dist.matrix


@pytest.mark.parametrize(
    "stem, index, rotation, style, completeness",
    [
        # every one of the three screened placements put one plan room over the whole map (57 % of
        # its walls explained, flip and rotation wrong): refused as under-determined. The right
        # placement of six rooms ranked fourth on the coarse key and screens best (IoU_a 0.96)
        ("005dca1a716b", 11, "any", "thick", 100),
        # the same, and the placement of several rooms the next three hold is 6 % off in scale
        # (IoU_a 0.57): the one-room search from it reaches the right one (IoU_a 0.97)
        ("000966a2577f", 7, "any", "tango", 75),
    ],
)
def test_one_room_screened_placements_do_not_hide_several_rooms_ranked_lower(
    test_data, stem, index, rotation, style, completeness
):
    # thick / tango maps (tools/bench_real.py `--parts styles`, plan `index`) of R2V flats
    rs, si = ("step90", "any").index(rotation), ("thick", "tango").index(style)
    plan, grid, truth = _styled(
        test_data,
        stem,
        rotation,
        style,
        completeness / 100,
        [0, index, rs, 21],
        [0, index, rs, completeness, si, 21],
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert len(reg.rooms) >= 2 and iou_a(plan, reg.matrix, truth) > 0.9
    # the one-room placements score nearly as well: the answer stays flagged for the caller
    assert reg.details["ambiguous"]


@pytest.mark.parametrize(
    "plan_id, index",
    [
        # a thick map of 75 % of an R2V flat (`--parts styles`, plan 12, any rotation): the three
        # best distinct placements on the coarse key are flipped or turned by 180 deg, the best
        # of them screened at 0.55 with its runner-up at 0.81 of it, and was accepted unflagged
        # (IoU_a 0.18). The right one ranked sixth and screens at 0.74 (IoU_a 0.98): a best not
        # clearly best (by the drawing gate's margin) has the next three screened too
        ("0582497ea7d9", 12),
        # plan 18, rooms seen in part: the screening refinement stopped with the scales 5 % / 6 %
        # off (IoU_a 0.76); restarted with both scales 5 % apart the refinement reaches the right
        # basin (IoU_a 0.96)
        ("07594d09a107", 18),
    ],
    ids=["right-placement-ranked-sixth-is-screened", "scales-polished-from-restarts"],
)
def test_thick_maps_of_three_quarters_of_a_flat_are_registered_right(test_data, plan_id, index):
    plan, grid, truth = _styled(
        test_data, plan_id, "any", "thick", 0.75, [0, index, 1, 21], [0, index, 1, 75, 0, 21]
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert iou_a(plan, reg.matrix, truth) > 0.9


@pytest.mark.parametrize(
    "index, style, completeness",
    [
        (6, "simulator", 50),  # refused; the further search accepted two rooms, not flagged (0.77)
        (9, "thick", 100),  # refused; the further search accepted nine rooms, not flagged (0.79)
        (10, "thick", 100),  # accepted, not flagged (0.82); its first screening left it at 0.88
    ],
)
def test_another_building_found_by_a_further_search_stays_doubtful(test_data, index, style, completeness):
    # plan i against a map of plan i + 1 (tools/bench_real.py `--parts other`): the screening of
    # more placements and the wide search from an ambiguous best find placements of another
    # building that beat the first ones; the answer is at least as doubtful as the first
    # screening left it (refused or flagged ambiguous, never accepted unflagged)
    from conftest import load_tool
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    stems = {6: "07e11ad2b598", 7: "000966a2577f", 9: "0520b01e0db1", 10: "02ee23df7042", 11: "005dca1a716b"}
    plan = FloorPlan.load(next((test_data / "r2v").glob(stems[index] + "*.txt")))
    other = FloorPlan.load(next((test_data / "r2v").glob(stems[index + 1] + "*.txt")))
    dist = Distortion.random(
        np.random.default_rng([0, index, 5]), rotation="step90", plan_bounds=other.bounds
    )
    house = House.from_plan(other, dist)
    rng = np.random.default_rng([0, index, completeness, len(style)])
    if style == "simulator":
        grid, _ = partial_map(house, completeness / 100, rng)
    else:
        grid, _, _ = bench.styled_map(house, style, completeness / 100, rng)
    reg = register(plan, grid)
    assert not reg.ok or reg.details["ambiguous"]


def test_one_room_stretched_over_the_map_does_not_stop_the_search(test_data):
    # a tango-style map of 75 % of an R2V flat: one plan room stretched over the map (12 boundary
    # points fitted, IoU_a 0.01) outranked the screened placement of six rooms (IoU_a 0.67); the
    # wide search did not run (that placement passed the gate's score) and the answer was refused
    # as under-determined. Searched from the best placement of several rooms, the right one
    # (IoU_a 0.94, 97 % of the map's walls explained) is found and accepted
    plan, grid, truth = _styled(
        test_data, "06fa9896fe36", "step90", "tango", 0.75, [0, 4, 0, 21], [0, 4, 0, 75, 1, 21]
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert len(reg.rooms) >= 2 and iou_a(plan, reg.matrix, truth) > 0.9


def test_few_rooms_of_another_building_do_not_displace_a_one_room_placement(test_data):
    # plan 0520b01e against a simulator map of another flat (tools/bench_real.py's `--parts other`,
    # case 9 at 100 %): the best screened placement puts one room on the map (refused). A variant
    # of the search that also started from the best rotations' moment fits stretched three rooms
    # over the map (IoU 0.98, 52 % of its walls explained) and accepted them, not flagged; from
    # the best placement of several rooms and its turns it stays refused
    from conftest import load_tool
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    from frslam_graph.floorplan import FloorPlan

    load_tool("bench_real")
    plan = FloorPlan.load(next((test_data / "r2v").glob("0520b01e0db1*.txt")))
    other = FloorPlan.load(next((test_data / "r2v").glob("02ee23df7042*.txt")))
    dist = Distortion.random(np.random.default_rng([0, 9, 5]), rotation="step90", plan_bounds=other.bounds)
    grid, _ = partial_map(
        House.from_plan(other, dist), 1.0, np.random.default_rng([0, 9, 100, len("simulator")])
    )
    reg = register(plan, grid)
    assert not reg.ok or reg.details["ambiguous"]


def test_turned_seeds_keep_the_plan_scales_and_the_footprint_centroid(test_data):
    from frslam_graph.registration.mfr.coarse import Hypothesis, turned_seeds
    from frslam_graph.registration.mfr.map_side import observe_map

    obs = observe_map(OccupancyGrid.from_image(test_data / "halmstad" / "HIH_03_crop.png", 0.05))
    m = np.array([[0.03, -0.01, 2.0], [0.01, 0.05, 1.0], [0.0, 0.0, 1.0]])
    seeds = turned_seeds(Hypothesis(3, 0, False, m, 0.0, 0), obs)
    assert len(seeds) == 7
    c = np.append(obs.centroid, 1.0)
    p = np.linalg.solve(m, c)  # the plan point on the footprint's centroid stays there
    cols = np.linalg.norm(m[:2, :2], axis=0)
    signs = set()
    for s in seeds:
        assert np.allclose(s.matrix @ p, c)
        assert np.allclose(np.linalg.norm(s.matrix[:2, :2], axis=0), cols)  # the plan axes' scales
        signs.add((round(float(np.linalg.det(s.matrix[:2, :2])) / np.linalg.det(m[:2, :2])), s.flipped))
        assert not np.allclose(s.matrix, m)
    assert {d for d, _ in signs} == {1, -1}
    assert len({tuple(np.round(s.matrix[:2, :2].ravel(), 9)) for s in seeds}) == 7


@pytest.mark.parametrize("name", ["E5_05", "E5_11"])
def test_halmstad_office_maps_reached_from_the_best_placement_turned(shared_data, name):
    # Tango maps of corridors and parts of rooms: the moment fit of the right (dihedral case,
    # wall direction) is 20-40 % off per axis (E5_05: x0.58 / x0.82) or that case has no
    # hypothesis at all (E5_11), and the wide search from it settles on a wrong placement; the
    # best placement's scales, turned to the right case, lead there
    from conftest import load_tool

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    folder = shared_data / "halmstad" / "E5"
    plan = FloorPlan.load(folder / "layout" / "E5_layout.png")
    res = 0.05
    grid = OccupancyGrid.from_image(folder / "sensor_maps" / f"{name}.png", res)
    pts = np.loadtxt(folder / "annotations" / f"{name}_to_layout.csv", delimiter=",", skiprows=1, ndmin=2)
    map_pts = np.column_stack([pts[:, 0] + 0.5, pts[:, 1]]) * res
    plan_pts = np.column_stack([pts[:, 2] + 0.5, pts[:, 3]])
    truth, residual = bench.fit_similarity(plan_pts, map_pts)
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    row = bench.point_rows(reg, truth, plan_pts, map_pts, residual)
    assert row["flip_ok"] and row["rot_err_deg"] < 2.0 and row["err_ratio"] < 2.0


def _halmstad_row(shared_data, building: str, name: str) -> dict:
    """``tools/bench_real.py``'s row of one Halmstad sensor map registered on its layout."""
    from conftest import load_tool

    from frslam_graph.floorplan import FloorPlan

    folder = shared_data / "halmstad" / building
    plan = FloorPlan.load(folder / "layout" / f"{building}_layout.png")
    return _registered_against_points(
        load_tool("bench_real"),
        plan,
        folder / "sensor_maps" / f"{name}.png",
        folder / "annotations" / f"{name}_to_layout.csv",
        1,
    )


def test_halmstad_corridor_network_fixes_flip_and_rotation_alone(shared_data):
    # E5_04: the Tango map is the office's corridor network, which the layout draws as one room
    # (r7, an asymmetric hall with a foot and a stub); its placement explains 52 % of the map's
    # walls (the rest: furniture and glimpses into offices) and was refused as under-determined.
    # Its seven other turns score at most 0.43 of it: flip and rotation are right, accepted
    row = _halmstad_row(shared_data, "E5", "E5_04")
    assert row["flip_ok"] and row["rot_err_deg"] < 2.0 and row["err_ratio"] < 2.0


def test_halmstad_apartment_placement_polished_past_its_mirror_image(shared_data):
    # HIH_02: the apartment's layout is nearly mirror-symmetric, and the screened placement of
    # the mirror image scored 0.27 against 0.24 for the right one (both a few per cent off in
    # scale); polished alike from restarts, the right one scores best and is accepted
    row = _halmstad_row(shared_data, "HIH", "HIH_02")
    assert row["flip_ok"] and row["rot_err_deg"] < 2.0


def test_restarts_leave_a_doubtful_match_doubtful(test_data):
    # plan 07e11ad2 against a thick-style map of another flat (tools/bench_real.py's `--parts
    # other`, case 6 at 100 %, drawn with another seed): flagged ambiguous (0.903) as screened;
    # without the floor the restarts polish the best further than its runner-ups and the
    # ambiguity falls to 0.857, under the flag (the case of session 12, a tango map, no longer
    # shows it since the map makers draw their walls centred on the plan's boundaries).
    # Polishing must not make a doubtful answer look sure
    from conftest import load_tool
    from frslam_graph.datasets.simulator import Distortion, House

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    plan = FloorPlan.load(next((test_data / "r2v").glob("07e11ad2b598*.txt")))
    other = FloorPlan.load(next((test_data / "r2v").glob("000966a2577f*.txt")))
    dist = Distortion.random(np.random.default_rng([0, 6, 5, 2]), rotation="step90", plan_bounds=other.bounds)
    grid, _, _ = bench.styled_map(
        House.from_plan(other, dist), "thick", 1.0, np.random.default_rng([0, 6, 100, len("thick"), 2])
    )
    reg = register(plan, grid)
    assert not reg.ok or reg.details["ambiguous"]


def office_row_plan(n: int = 6) -> FloorPlan:
    """A corridor (2 m deep) along a row of ``n`` offices (3.5 x 4 m), a door from each (plan
    units: ``U`` a metre): as the Halmstad E5 layout, many walls across the row."""
    rooms = [Room("corridor", "corridor", box(0, 0, n * 3.5 * U, 2 * U))]
    doors = []
    for i in range(n):
        rooms.append(Room(f"o{i}", "office", box(i * 3.5 * U, 2 * U, (i + 1) * 3.5 * U, 6 * U)))
        a, b = ((i * 3.5 + 1.0) * U, 2 * U), ((i * 3.5 + 2.0) * U, 2 * U)
        doors.append(Door(f"d{i}", a, b, ("corridor", f"o{i}")))
    return FloorPlan(rooms, doors, units="px", name="office_row")


def seen_through_map(plan, truth: np.ndarray, beyond: float, thickness: float = 0.15, res: float = 0.05):
    """Occupancy grid of ``truth · plan`` (every room explored) whose inner walls (``thickness``
    m, centred on the room boundaries, cut at the doors) are seen, but whose outer walls are not:
    the free space runs past them into unknown space up to ``beyond`` metres, by a smooth
    random amount (a Tango map seeing through windows: a ragged free edge, no wall)."""
    house = plan.transformed(truth, units="m")
    frame = RasterFrame.around(house.bounds, res, margin=1.0 + beyond)
    lab, wall = _rooms_and_walls(house, frame, thickness, res)
    inside = lab > 0
    noise = cv2.GaussianBlur(
        np.random.default_rng(0).uniform(0, 1, lab.shape).astype(np.float32), (0, 0), 8.0
    )
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    dist = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5) * res
    outer = ~inside & (dist < beyond * noise)
    near_out = cv2.dilate(outer.astype(np.uint8), np.ones((int(thickness / res) + 3,) * 2, np.uint8)).astype(
        bool
    )
    free = (inside & ~wall) | outer | (wall & near_out)
    seen = cv2.dilate(free.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    occ = seen & ~free & wall & ~near_out
    return OccupancyGrid.from_masks(free, occ, res, (frame.origin[0], frame.origin[1], 0.0))


@pytest.mark.parametrize("flipped, rotation", [(False, 0.0), (True, 90.0), (False, 200.0)])
def test_free_space_past_the_outer_walls_does_not_stretch_the_row_of_rooms(flipped, rotation):
    # the outer walls unseen, free space up to 0.6 m past them: the plan's outer boundary samples
    # lie in free space and pull outwards, the inner walls alone hold the scale along the row.
    # Fitted one-sided (the plan's samples on the map's free-space edge) the row came out 2.1-2.3 %
    # too long; the answer is fitted two-sided (the map's wall cells pull onto the plan's walls)
    from frslam_graph.registration.mfr import fine
    from frslam_graph.registration.mfr.map_side import observe_map
    from frslam_graph.registration.mfr.plan_side import prepare_plan
    from frslam_graph.registration.mfr.register import DEFAULTS

    plan = office_row_plan()
    truth = matrix_from_params(flipped, math.radians(rotation), 0.025, 0.025, 3.0, -2.0)
    grid = seen_through_map(plan, truth, beyond=0.6)
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    f, rot, sx, _, _, _ = params_from_matrix(truth)
    ef, erot, esx, _, _, _ = params_from_matrix(reg.matrix)
    assert ef == f and abs((math.degrees(erot - rot) + 180.0) % 360.0 - 180.0) < 1.0
    assert abs(esx / sx - 1.0) < 0.01  # along the row (plan x)
    # the one-sided fit from the same screened start: too long
    obs, pm, opts = observe_map(grid), prepare_plan(plan), dict(DEFAULTS)
    true_g = np.linalg.inv(obs.to_map) @ truth
    screened = fine.refine_from(
        pm, obs, true_g, 0.06, opts, scales=(0.15,), spacing_px=4.0, max_points=300, iterations=6
    )
    _, _, gsx, _, _, _ = params_from_matrix(true_g)
    one = params_from_matrix(fine.refine_final(pm, obs, screened, opts).matrix)[2] / gsx - 1.0
    two = params_from_matrix(fine.refine_final(pm, obs, screened, opts, walls=True).matrix)[2] / gsx - 1.0
    assert one > 0.015 and abs(two) < 0.01


@pytest.mark.parametrize("name", ["E5_05", "E5_14"])
def test_halmstad_office_maps_fitted_two_sided_keep_the_scale(shared_data, name):
    # Tango maps of the E5 offices: fitted one-sided the scale came out +3.7 % (E5_05) and +2.9 %
    # (E5_14) off the annotated similarity (free space past doorways and outer walls pulls the
    # plan's walls outwards); fitted two-sided within 2 %
    from conftest import load_tool

    from frslam_graph.floorplan import FloorPlan

    bench = load_tool("bench_real")
    folder = shared_data / "halmstad" / "E5"
    plan = FloorPlan.load(folder / "layout" / "E5_layout.png")
    row = _registered_against_points(
        bench,
        plan,
        folder / "sensor_maps" / f"{name}.png",
        folder / "annotations" / f"{name}_to_layout.csv",
        1,
    )
    assert row["flip_ok"] and row["rot_err_deg"] < 2.0
    assert abs(row["scale_err"]) < 0.02 and row["err_ratio"] < 2.0


def _count_two_sided(monkeypatch) -> list[float]:
    """Patch MFR's final fit to log its two-sided fits (the map's resolution, one per fit)."""
    from frslam_graph.registration.mfr import fine

    calls: list[float] = []
    final = fine.refine_final

    def counting(pm, obs, screened, opts, *, walls=False):
        if walls:
            calls.append(obs.frame.resolution)
        return final(pm, obs, screened, opts, walls=walls)

    monkeypatch.setattr(fine, "refine_final", counting)
    return calls


@pytest.mark.parametrize("flipped, k", [(False, 0), (True, 3)])
def test_walls_seen_where_the_plan_draws_them_keep_the_one_sided_answer(monkeypatch, flipped, k):
    # every wall seen, none beyond the plan's: the one-sided fit's wall offset is a wall's
    # half-thickness (>= 0), nothing pulled it outwards; the answer is that fit, not the two-sided
    # one (which cost the simulator's regime-B runs with plans: house 00dd 0.018 -> 0.028 m ATE)
    plan = synthetic_plan()
    calls = _count_two_sided(monkeypatch)
    reg = register(plan, ring_map(plan, truth_matrix(flipped, 90.0 * k), EXPLORED))
    assert reg.ok, reg.reason
    assert reg.details["delta_m"] > -0.025
    assert calls == []


def test_free_space_past_the_drawn_walls_takes_the_two_sided_scales(monkeypatch):
    # the outer walls unseen and free space past them: the one-sided fit puts the plan's walls
    # inside the free space (wall offset below minus half a cell) and comes out too long; the
    # answer takes the scales of the two-sided fit and keeps the one-sided rotation and flip
    from frslam_graph.registration.mfr import fine

    plan = office_row_plan()
    truth = matrix_from_params(False, math.radians(200.0), 0.025, 0.025, 3.0, -2.0)
    grid = seen_through_map(plan, truth, beyond=0.6)
    calls = _count_two_sided(monkeypatch)
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert len(calls) == 1
    final = fine.refine_final
    monkeypatch.setattr(
        fine, "refine_final", lambda pm, obs, s, opts, walls=False: s if walls else final(pm, obs, s, opts)
    )
    one = register(plan, grid)  # the one-sided answer (main's before the gate)
    f1, rot1, sx1, _, _, _ = params_from_matrix(one.matrix)
    f2, rot2, sx2, _, _, _ = params_from_matrix(reg.matrix)
    assert f1 == f2 and abs(rot1 - rot2) < 1e-9
    assert sx1 / 0.025 - 1.0 > 0.015 and abs(sx2 / 0.025 - 1.0) < 0.01


@pytest.mark.parametrize(
    "stem, seed, index, rotation, completeness, least_iou_a",
    [
        # `--parts styles --seed 1`, plan 9 (any rotation), thick maps of 50 % and 75 %: one plan
        # room stretched over the map screened best (refused as under-determined, flip and
        # rotation wrong); the placement of two rooms screened at 0.94 of it, right (IoU_a 0.99
        # and 0.73)
        ("03a5b967452e", 1, 9, "any", 50, 0.9),
        ("03a5b967452e", 1, 9, "any", 75, 0.7),
    ],
)
def test_one_room_best_answers_with_the_placement_of_several_rooms_flagged(
    test_data, stem, seed, index, rotation, completeness, least_iou_a
):
    rs = ("step90", "any").index(rotation)
    plan, grid, truth = _styled(
        test_data,
        stem,
        rotation,
        "thick",
        completeness / 100,
        [seed, index, rs, 21],
        [seed, index, rs, completeness, 0, 21],
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert len(reg.rooms) >= 2 and iou_a(plan, reg.matrix, truth) > least_iou_a
    # the one-room placement scores above it: the answer is flagged, the placement an alternative
    assert reg.details["ambiguous"]
    assert reg.details["alternatives"] and reg.details["alternatives"][0]["relative_score"] > 1.0


def test_a_best_explaining_few_map_walls_is_searched_and_polished(test_data):
    # `--parts styles --seed 1`, plan 2 (90-degree steps), a thick map of 75 %: every coarse
    # placement is the same one (ambiguity 0), covering the footprint (coarse IoU 0.854, above
    # `search_below_iou`) but explaining 54 % of the map's walls: screened a scale step off
    # (IoU_a 0.70). Searched and polished like a poor coverage it reaches IoU_a 0.98
    plan, grid, truth = _styled(
        test_data, "054a4f90a419", "step90", "thick", 0.75, [1, 2, 0, 21], [1, 2, 0, 75, 0, 21]
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert iou_a(plan, reg.matrix, truth) > 0.9 and reg.details["recall"] > 0.9


def test_polish_ranks_its_restarts_by_the_gates_measure(test_data):
    # `--parts styles` (seed 0), plan 14 (90-degree steps), a thick map of 50 %: polished, the
    # restart a wall off ranked best on the coarse key (0.64, the gate's measure 0.45) over the
    # one near the truth (coarse key 0.33, the gate's measure 0.69) and was kept (IoU_a 0.43,
    # accepted unflagged); ranked by the gate's measure the polish reaches IoU_a 0.87
    plan, grid, truth = _styled(
        test_data, "01e84a78bcf0", "step90", "thick", 0.5, [0, 14, 0, 21], [0, 14, 0, 50, 0, 21]
    )
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert iou_a(plan, reg.matrix, truth) > 0.8
