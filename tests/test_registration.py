"""Our MFR registration (``register(plan, grid)``, method "mfr"), its result type and CLI.

Maps are made here from a known distortion D of a synthetic asymmetric plan: the rooms of a
connected subset are rasterised (free inside, a one-cell occupied ring on their boundary, door
openings free, unknown elsewhere), or simulated with the LiDAR simulator's ``partial_map`` (walls
0.12 m thick, noise). The truth is D; IoU_a is the paper's eq. 9 over all rooms.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import shapely
from shapely.geometry import box

from frslam_graph.errors import ConfigError
from frslam_graph.floorplan import Door, FloorPlan, Room
from frslam_graph.occupancy import OccupancyGrid
from frslam_graph.raster import RasterFrame, rasterise_plan
from frslam_graph.registration import Registration, matrix_from_params, params_from_matrix, register
from frslam_graph.registration.evaluation import iou_a
from frslam_graph.registration.subsets import adjacency_masks, connected_subsets, mask_ids

U = 40.0  # plan units per metre of the synthetic plan
EXPLORED = ["living", "kitchen", "bath", "corridor", "bed2"]


def synthetic_plan() -> FloorPlan:
    """Seven rooms, no symmetry, doors between them (plan units, y up)."""
    spec = {
        "living": ("living_room", (0, 0, 6, 4)),
        "kitchen": ("kitchen", (6, 0, 9, 2.5)),
        "bath": ("bathroom", (6, 2.5, 9, 4)),
        "corridor": ("corridor", (0, 4, 3, 5.5)),
        "bed1": ("bedroom", (0, 5.5, 3, 9)),
        "bed2": ("bedroom", (3, 4, 7, 8)),
        "closet": ("closet", (7, 4, 9, 5.5)),
    }
    rooms = [Room(k, t, box(*(np.array(b) * U))) for k, (t, b) in spec.items()]
    links = [
        ("living", "kitchen", (6, 0.8), (6, 1.6)),
        ("kitchen", "bath", (7, 2.5), (7.8, 2.5)),
        ("living", "corridor", (1, 4), (2, 4)),
        ("corridor", "bed1", (1, 5.5), (2, 5.5)),
        ("corridor", "bed2", (3, 4.3), (3, 5.2)),
        ("bed2", "closet", (7, 4.5), (7, 5.2)),
    ]
    doors = [
        Door(f"d{i}", tuple(np.array(a) * U), tuple(np.array(b) * U), (r1, r2))
        for i, (r1, r2, a, b) in enumerate(links)
    ]
    return FloorPlan(rooms, doors, units="px", name="synthetic")


def ring_map(plan: FloorPlan, truth: np.ndarray, rooms: list[str], res: float = 0.05):
    """Occupancy grid of ``rooms`` of the house ``truth · plan``: free inside, a one-cell occupied
    ring on each room's boundary (open at doors), unknown elsewhere."""
    house = plan.transformed(truth, units="m")
    frame = RasterFrame.around(house.subset(rooms).bounds, res, margin=0.6)
    lab = rasterise_plan(house, frame, rooms=rooms, labels=True)
    pad = np.pad(lab, 1)
    ring = np.zeros(lab.shape, bool)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ring |= pad[1 + dr : 1 + dr + lab.shape[0], 1 + dc : 1 + dc + lab.shape[1]] != lab
    occ = (lab > 0) & ring
    doors = np.zeros(lab.shape, np.uint8)
    for d in house.doors:
        if any(r in rooms for r in d.rooms):
            a, b = frame.to_pixel(np.array([d.a, d.b])) - 0.5
            cv2.line(doors, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), 1, 3)
    occ &= ~doors.astype(bool)
    free = (lab > 0) & ~occ
    return OccupancyGrid.from_masks(free, occ, res, (frame.origin[0], frame.origin[1], 0.0))


def truth_matrix(flipped: bool, rotation_deg: float, t=(3.0, -2.0)) -> np.ndarray:
    return matrix_from_params(flipped, math.radians(rotation_deg), 0.025 * 1.1, 0.025 * 0.92, *t)


def rot_error_deg(reg: Registration, truth: np.ndarray) -> float:
    t_rot = math.degrees(params_from_matrix(truth)[1])
    return abs((reg.rotation_deg - t_rot + 180.0) % 360.0 - 180.0)


@pytest.fixture(scope="module")
def plan() -> FloorPlan:
    return synthetic_plan()


# ----------------------------------------------------------------------------------- result type
@pytest.mark.parametrize("flipped", [False, True])
@pytest.mark.parametrize("rotation", [0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi, 0.7, -2.9])
def test_matrix_params_round_trip(flipped, rotation):
    m = matrix_from_params(flipped, rotation, 0.03, 0.045, 1.5, -2.0)
    f, r, sx, sy, tx, ty = params_from_matrix(m)
    assert f == flipped
    assert abs((r - rotation + math.pi) % (2 * math.pi) - math.pi) < 1e-12
    assert (sx, sy, tx, ty) == pytest.approx((0.03, 0.045, 1.5, -2.0), abs=1e-12)
    # the documented factorisation T · R · diag(1, ±1) · diag(sx, sy)
    c, s = math.cos(rotation), math.sin(rotation)
    lin = np.array([[c, -s], [s, c]]) @ np.diag([1.0, -1.0 if flipped else 1.0]) @ np.diag([0.03, 0.045])
    assert np.allclose(m[:2, :2], lin)


def test_registration_result_helpers(plan):
    m = matrix_from_params(True, 0.3, 0.02, 0.03, 1.0, 2.0)
    reg = Registration.from_matrix(m, score=0.9, ambiguity=0.2, rooms=("living",), method="mfr")
    assert reg.ok and reg.flipped and reg.rotation_deg == pytest.approx(math.degrees(0.3))
    assert reg.scale == pytest.approx((0.02, 0.03)) and reg.translation == pytest.approx((1.0, 2.0))
    d = json.loads(json.dumps(reg.to_dict()))
    assert np.allclose(d["matrix"], m) and d["rooms"] == ["living"]
    placed = reg.apply(plan)
    assert placed.units == "m"
    corner = np.asarray(plan.room("living").polygon.exterior.coords)[:1]
    assert np.allclose(
        np.asarray(placed.room("living").polygon.exterior.coords)[:1], reg.transform_points(corner)
    )
    bad = Registration.failure("empty map", "mfr", 0.01)
    assert not bad.ok and bad.reason == "empty map" and np.array_equal(bad.matrix, np.eye(3))
    assert json.loads(json.dumps(bad.to_dict()))["ok"] is False


# ---------------------------------------------------------------------------------------- subsets
def test_connected_subsets_of_a_path():
    # rooms 0 - 1 - 2 - 3 in a row: 10 connected subsets (4 + 3 + 2 + 1)
    adj = np.array([0b0010, 0b0101, 0b1010, 0b0100], dtype=np.uint64)
    masks = connected_subsets(adj)
    assert sorted(int(m) for m in masks) == sorted([1, 2, 4, 8, 3, 6, 12, 7, 14, 15])
    with_seed = connected_subsets(adj, seeds=np.array([0]))
    assert all(int(m) & 1 for m in with_seed) and len(with_seed) == 4
    assert mask_ids(np.uint64(0b0101), ["a", "b", "c", "d"]) == ("a", "c")


def test_connected_subsets_match_brute_force():
    rng = np.random.default_rng(4)
    n = 10
    edges = [(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.3]
    adj = np.zeros(n, np.uint64)
    for i, j in edges:
        adj[i] |= np.uint64(1 << j)
        adj[j] |= np.uint64(1 << i)

    def connected(mask: int) -> bool:
        members = [i for i in range(n) if mask >> i & 1]
        seen, todo = {members[0]}, [members[0]]
        while todo:
            k = todo.pop()
            for j in range(n):
                if int(adj[k]) >> j & 1 and mask >> j & 1 and j not in seen:
                    seen.add(j)
                    todo.append(j)
        return len(seen) == len(members)

    brute = {m for m in range(1, 1 << n) if connected(m)}
    assert {int(m) for m in connected_subsets(adj)} == brute


def test_room_moments_match_shapely():
    from shapely.geometry import Polygon

    from frslam_graph.registration.refine import ring_edges
    from frslam_graph.registration.subsets import polygon_moments, rings_moments

    poly = Polygon([(0, 0), (7, 0), (7, 3), (4, 3), (4, 5), (0, 5)], [[(1, 1), (2, 1), (2, 2), (1, 2)]])
    m = polygon_moments(poly)
    assert m[0] == pytest.approx(poly.area)
    assert (m[1] / m[0], m[2] / m[0]) == pytest.approx(poly.centroid.coords[0])
    oriented = shapely.orient_polygons(poly)
    rings = [np.asarray(oriented.exterior.coords)[:-1], np.asarray(oriented.interiors[0].coords)[:-1]]
    a, b, _ = ring_edges(rings)
    assert np.allclose(rings_moments(a, b, np.zeros(len(a), int), 1)[0], m)


def test_door_adjacency(plan):
    links = [tuple(plan.room_ids.index(r) for r in d.rooms) for d in plan.doors]
    adj = adjacency_masks(plan.rooms, links)
    i = plan.room_ids.index
    assert int(adj[i("corridor")]) == (1 << i("living")) | (1 << i("bed1")) | (1 << i("bed2"))
    assert not int(adj[i("living")]) & (1 << i("bath"))  # touching, but no door


# ------------------------------------------------------------------------------ known distortions
@pytest.mark.parametrize("flipped", [False, True])
@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_recovers_dihedral_cases_exactly(plan, flipped, k):
    truth = truth_matrix(flipped, 90.0 * k)
    reg = register(plan, ring_map(plan, truth, EXPLORED))
    assert reg.ok, reg.reason
    assert reg.method == "mfr"
    assert reg.flipped == flipped
    assert rot_error_deg(reg, truth) < 0.1
    _, _, sx, sy, _, _ = params_from_matrix(truth)
    assert reg.scale[0] == pytest.approx(sx, rel=0.004) and reg.scale[1] == pytest.approx(sy, rel=0.004)
    assert iou_a(plan, reg.matrix, truth) > 0.985
    assert set(reg.rooms) == set(EXPLORED)
    assert reg.score > 0.95 and 0.0 <= reg.ambiguity < 0.9
    assert reg.covariance is not None and reg.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(reg.covariance) > 0)


@pytest.mark.parametrize("rotation_deg", [17.0, -128.4])
def test_recovers_any_angle(plan, rotation_deg):
    truth = truth_matrix(True, rotation_deg)
    reg = register(plan, ring_map(plan, truth, EXPLORED))
    assert reg.ok, reg.reason
    assert reg.flipped and rot_error_deg(reg, truth) < 0.1
    assert iou_a(plan, reg.matrix, truth) > 0.985


def test_recovers_simulated_lidar_map(plan):
    """The simulator's partial map: 0.12 m walls, open doorways, noise."""
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    dist = Distortion(0.025, (0.95, 1.08), True, math.radians(33.0), (2.0, -1.0))
    house = House.from_plan(plan, dist)
    grid, explored = partial_map(house, 0.6, np.random.default_rng(3), start_room="living")
    reg = register(plan, grid)
    assert reg.ok, reg.reason
    assert reg.flipped and rot_error_deg(reg, dist.matrix) < 0.3
    assert iou_a(plan, reg.matrix, dist.matrix) > 0.97
    assert set(reg.rooms) == set(explored)
    # the wall offset: half the simulated wall thickness
    assert reg.details["delta_m"] == pytest.approx(0.06, abs=0.02)


def test_runner_up_placements_are_reported(plan):
    """details["alternatives"]: MFR's runner-up placements (map frame), each a different
    placement from the best and from each other, scored relative to the best."""
    from frslam_graph.registration.evaluation import iou_a as _iou

    truth = truth_matrix(False, 0.0)
    reg = register(plan, ring_map(plan, truth, EXPLORED))
    alts = reg.details["alternatives"]
    assert 1 <= len(alts) <= 2
    for a in alts:
        m = np.asarray(a["matrix"], float)
        assert m.shape == (3, 3) and 0.0 < a["relative_score"] <= 1.0 + 1e-9
        assert _iou(plan, m, truth) < 0.9  # not the true placement again
    assert reg.to_dict()["details"]["alternatives"][0]["matrix"]  # JSON-ready


# ------------------------------------------------------------------------- resolution and origin
def test_invariant_to_map_resolution(plan):
    truth = truth_matrix(False, 90.0)
    fine = register(plan, ring_map(plan, truth, EXPLORED, res=0.05))
    coarse = register(plan, ring_map(plan, truth, EXPLORED, res=0.1))
    assert fine.ok and coarse.ok
    assert coarse.flipped == fine.flipped == False  # noqa: E712
    assert rot_error_deg(coarse, truth) < 0.2
    assert iou_a(plan, coarse.matrix, truth) > 0.97
    assert iou_a(plan, coarse.matrix, fine.matrix) > 0.97


def test_invariant_to_map_origin(plan):
    """The same cells with the origin moved by ``shift``: the result moves by ``shift``."""
    truth = truth_matrix(True, 200.0)
    shift = np.array([123.4, -56.7])
    grid = ring_map(plan, truth, EXPLORED)
    moved_grid = OccupancyGrid(
        grid.data, grid.resolution, (grid.origin[0] + shift[0], grid.origin[1] + shift[1], 0.0)
    )
    base, moved = register(plan, grid), register(plan, moved_grid)
    assert base.ok and moved.ok
    assert np.allclose(moved.matrix[:2, :2], base.matrix[:2, :2], atol=1e-9)
    assert np.allclose(moved.matrix[:2, 2], base.matrix[:2, 2] + shift, atol=1e-6)
    moved_truth = truth.copy()
    moved_truth[:2, 2] += shift
    assert iou_a(plan, moved.matrix, moved_truth) > 0.985


def test_rotated_grid_origin(plan):
    """A grid whose origin has a yaw: the same cells, rotated in the map frame."""
    truth = truth_matrix(False, 0.0)
    grid = ring_map(plan, truth, EXPLORED)
    yaw = 0.4
    rotated = OccupancyGrid(grid.data, grid.resolution, (1.0, 2.0, yaw))
    a, b = register(plan, grid), register(plan, rotated)
    assert a.ok and b.ok
    expected = rotated.map_from_grid() @ np.linalg.inv(grid.map_from_grid()) @ a.matrix
    assert np.allclose(b.matrix, expected, atol=1e-6)
    assert b.rotation_deg == pytest.approx(a.rotation_deg + math.degrees(yaw), abs=1e-6)


# ----------------------------------------------------------------------------------- failures
def test_fails_on_all_unknown_map(plan):
    grid = OccupancyGrid(np.full((50, 60), -1, np.int8), 0.05)
    reg = register(plan, grid)
    assert not reg.ok and "unknown" in reg.reason


def test_fails_on_tiny_map(plan):
    data = np.full((50, 60), -1, np.int8)
    data[10:14, 10:14] = 0
    reg = register(plan, OccupancyGrid(data, 0.05))
    assert not reg.ok and "too small" in reg.reason


def test_fails_on_map_without_walls_or_too_coarse(plan):
    reg = register(plan, OccupancyGrid(np.zeros((80, 80), np.int8), 0.05))
    assert not reg.ok and "no walls" in reg.reason
    grid = ring_map(plan, truth_matrix(False, 0.0), EXPLORED)
    reg = register(plan, OccupancyGrid(grid.data, 5.0))
    assert not reg.ok and "too coarse" in reg.reason


def test_fails_on_one_room_plan(plan):
    one = plan.subset(["living"])
    grid = ring_map(plan, truth_matrix(False, 0.0), ["living"])
    reg = register(one, grid)
    assert not reg.ok and "1 room" in reg.reason


def other_building_grid(n: int = 4):
    """Map of an n x n grid of equal 3 m square rooms (doors along x): MFR places the synthetic
    plan on it but refuses the placement."""
    rooms = [
        Room(f"g{i}{j}", "bedroom", box(i * 3.0, j * 3.0, i * 3.0 + 3.0, j * 3.0 + 3.0))
        for i in range(n)
        for j in range(n)
    ]
    doors = [
        Door(
            f"h{i}{j}",
            (i * 3.0 + 3.0, j * 3.0 + 1.0),
            (i * 3.0 + 3.0, j * 3.0 + 2.0),
            (f"g{i}{j}", f"g{i + 1}{j}"),
        )
        for i in range(n - 1)
        for j in range(n)
    ]
    return ring_map(FloorPlan(rooms, doors, units="m"), np.eye(3), [r.id for r in rooms])


def test_fails_on_another_building(plan):
    """A grid of equal square rooms cannot be explained by the synthetic plan."""
    reg = register(plan, other_building_grid())
    # its best placement puts one room on the map (a square room of the grid fits any room)
    assert not reg.ok and ("no match" in reg.reason or "under-determined" in reg.reason)
    assert 0.0 <= reg.score < 1.0
    # on a 3 x 3 grid the first screening leaves the one-room best undecided, and the search from
    # the others fits six rooms (IoU x precision x recall 0.53): accepted, but another placement
    # scores as well (ambiguity 1.00): flagged, never a confident match
    reg = register(plan, other_building_grid(3))
    assert not reg.ok or (reg.details["ambiguous"] and reg.ambiguity >= 0.99)


def test_bad_method_and_option(plan):
    grid = ring_map(plan, truth_matrix(False, 0.0), EXPLORED)
    with pytest.raises(ConfigError):
        register(plan, grid, method="nope")
    with pytest.raises(ConfigError):
        register(plan, grid, bogus=1)


def test_seed_rooms(plan):
    truth = truth_matrix(False, 90.0)
    reg = register(plan, ring_map(plan, truth, EXPLORED), seed_rooms=["kitchen"])
    assert reg.ok and "kitchen" in reg.rooms and iou_a(plan, reg.matrix, truth) > 0.985
    bad = register(plan, ring_map(plan, truth, EXPLORED), seed_rooms=["attic"])
    assert not bad.ok and "seed" in bad.reason


# ---------------------------------------------------------------------------------------- CLI
def test_cli_register_writes_outputs(plan, tmp_path):
    from frslam_graph.cli import main

    truth = truth_matrix(True, 90.0)
    ring_map(plan, truth, EXPLORED).save(tmp_path / "map.yaml")
    plan.save(tmp_path / "plan.json")
    out = tmp_path / "out"
    assert main(["register", str(tmp_path / "plan.json"), str(tmp_path / "map.yaml"), "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["registration"]["ok"] is True
    placed = FloorPlan.load(out / "registered_plan.json")
    assert placed.units == "m"
    # the registered plan is the plan placed by the truth (rooms overlap almost exactly)
    truth_plan = plan.transformed(truth, units="m")
    for r in truth_plan.rooms:
        p = placed.room(r.id).polygon
        assert p.intersection(r.polygon).area / p.union(r.polygon).area > 0.97
    img = cv2.imread(str(out / "overlay.png"))
    assert img is not None and img.shape[0] > 100


def test_cli_register_draws_a_refused_placement_dashed_and_writes_no_plan(plan, tmp_path, capsys):
    from frslam_graph.cli import main
    from frslam_graph.cli.register import _overlay, refused_placement

    grid = other_building_grid()
    reg = register(plan, grid)
    assert not reg.ok and refused_placement(reg)  # refused, with its placement
    assert not refused_placement(Registration.failure("plan has 1 room(s)", "mfr"))
    # the overlay shows the refused rooms (it differs from the map alone)
    _overlay(grid, reg.apply(plan), reg, tmp_path / "with.png", "t")
    _overlay(grid, None, reg, tmp_path / "without.png", "t")
    assert not np.array_equal(
        cv2.imread(str(tmp_path / "with.png")), cv2.imread(str(tmp_path / "without.png"))
    )
    grid.save(tmp_path / "map.yaml")
    plan.save(tmp_path / "plan.json")
    out = tmp_path / "out"
    assert main(["register", str(tmp_path / "plan.json"), str(tmp_path / "map.yaml"), "--out", str(out)]) == 1
    assert reg.reason[:40] in capsys.readouterr().out
    assert (out / "overlay.png").is_file() and not (out / "registered_plan.json").exists()
    assert json.loads((out / "report.json").read_text())["registration"]["ok"] is False


def test_cli_register_bad_map_path(plan, tmp_path, capsys):
    from frslam_graph.cli import main

    plan.save(tmp_path / "plan.json")
    code = main(
        [
            "register",
            str(tmp_path / "plan.json"),
            str(tmp_path / "missing.yaml"),
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 2
    assert "missing.yaml" in capsys.readouterr().err
    assert not (tmp_path / "o" / "report.json").exists()


# ------------------------------------------------------------------------ open plans and angles
def open_plan(plan: FloorPlan) -> FloorPlan:
    """The synthetic plan with wall segments on every room edge except living | bath (x = 6 m,
    y 2.5..4 m): an open-plan boundary, no door."""
    segs = []
    for r in plan.rooms:
        xy = np.asarray(r.polygon.exterior.coords)
        for a, b in zip(xy[:-1], xy[1:], strict=True):
            segs.append([*a, *b])
    segs = np.array(segs)
    vertical_at_6 = np.isclose(segs[:, 0], 6 * U) & np.isclose(segs[:, 2], 6 * U)
    keep = ~(vertical_at_6 & (np.maximum(segs[:, 1], segs[:, 3]) > 2.5 * U))
    # the living room's east edge runs 0..4 m: keep its lower part (kitchen side) as a wall
    walls = np.vstack([segs[keep], [[6 * U, 0.0, 6 * U, 2.5 * U]]])
    return FloorPlan(plan.rooms, plan.doors, walls=walls, units="px", name="open")


def test_open_plan_boundary_links_rooms_and_is_not_a_wall(plan):
    from frslam_graph.registration.mfr.plan_side import prepare_plan

    pm = prepare_plan(open_plan(plan))
    i = pm.ids.index
    assert int(pm.adjacency[i("living")]) & (1 << i("bath"))
    # no wall samples on the open stretch (x = 6 m, 2.7 < y < 3.8 m)
    on_open = (
        np.isclose(pm.samples[:, 0], 6 * U, atol=1.0)
        & (pm.samples[:, 1] > 2.7 * U)
        & (pm.samples[:, 1] < 3.8 * U)
    )
    assert not on_open.any()
    # the outer walls and the walled part of the same boundary stay
    assert (np.isclose(pm.samples[:, 0], 6 * U, atol=1.0) & (pm.samples[:, 1] < 2.3 * U)).any()
    plain = prepare_plan(plan)
    assert not int(plain.adjacency[i("living")]) & (1 << i("bath"))


def test_registers_open_plan_house(plan):
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    op = open_plan(plan)
    dist = Distortion(0.025, (1.1, 0.93), False, math.radians(-71.0), (1.0, 4.0))
    house = House.from_plan(op, dist)
    grid, explored = partial_map(house, 0.5, np.random.default_rng(5), start_room="living")
    reg = register(op, grid)
    assert reg.ok, reg.reason
    assert not reg.flipped and rot_error_deg(reg, dist.matrix) < 0.3
    assert iou_a(op, reg.matrix, dist.matrix) > 0.97


def test_dominant_angles_ignore_a_few_diagonal_walls():
    from frslam_graph.registration.mfr.geometry import dominant_angles

    rng = np.random.default_rng(0)
    main = np.radians(20.0) + rng.normal(0, 0.01, 400) + rng.integers(0, 4, 400) * np.pi / 2
    diag = np.radians(65.0) + rng.normal(0, 0.01, 60)
    ang = np.concatenate([main, diag])
    vec = np.column_stack([np.cos(ang), np.sin(ang)])
    found = dominant_angles(vec)
    assert math.degrees(found[0]) == pytest.approx(20.0, abs=0.3)
    assert len(found) == 1  # the diagonal family is too weak to be a second direction


@pytest.mark.parametrize("room", ["living", "kitchen", "bath", "corridor", "bed1", "bed2", "closet"])
def test_a_map_of_one_room_is_not_refused_but_a_wrong_placement_is_flagged(plan, room):
    """A map that is one whole room (a robot that has seen its first room): the placement of one
    plan room explains every wall of it, its doors decide flip and rotation (right in 13 of 21
    such cases), and where they do not the placement is flagged ambiguous. Only one room stretched
    over a map with more structure is refused as under-determined (test_registration_real_maps)."""
    for flipped, rotation in ((False, 0.0), (True, 90.0), (False, 200.0)):
        truth = truth_matrix(flipped, rotation)
        reg = register(plan, ring_map(plan, truth, [room]))
        if not reg.ok:  # a fit on fewer than a handful of points
            assert "under-determined" in reg.reason and reg.details["n_points"] < 60
            continue
        right = reg.flipped == flipped and rot_error_deg(reg, truth) < 5.0 and reg.rooms == (room,)
        assert right or reg.details["ambiguous"]


def test_speed_helpers_match_numpy() -> None:
    """The speed-ups of session 11 give numpy's answers exactly: the stable top-k (ties by index,
    inf and NaN last), the sorted unique of uint64 masks, and the per-label pixel counts."""
    from frslam_graph.registration.mfr.coarse import smallest_stable
    from frslam_graph.registration.mfr.fine import _label_counts
    from frslam_graph.registration.subsets import _sorted_unique

    rng = np.random.default_rng(3)
    for t in range(300):
        n, k = int(rng.integers(1, 3000)), int(rng.integers(1, 400))
        a = rng.integers(0, int(rng.integers(1, 40)), n).astype(float)
        a[rng.random(n) < 0.2] = np.inf
        if t % 3 == 0:
            a[rng.random(n) < 0.2] = np.nan
        assert np.array_equal(smallest_stable(a, k), np.argsort(a, kind="stable")[:k])
        m = rng.integers(0, 1 << int(rng.integers(1, 60)), n, dtype=np.uint64)
        assert np.array_equal(_sorted_unique(m), np.unique(m))
    labels = rng.integers(0, 27, (120, 90)).astype(np.uint8)
    mask = rng.random((120, 90)) < 0.4
    assert np.array_equal(_label_counts(labels, mask, 26), np.bincount(labels[mask], minlength=27)[1:])


def test_the_plan_side_is_prepared_once_per_plan_object(plan):
    # the plan updates register one FloorPlan again and again as the map grows: its prepared
    # model is reused (read-only), and the registration is the same as from a fresh copy
    from frslam_graph.registration.mfr import register as mfr

    grid = ring_map(plan, truth_matrix(False, 30.0), EXPLORED)
    first = register(plan, grid)
    pm = mfr._prepared(plan, "doors")
    assert mfr._prepared(plan, "doors") is pm and not pm.samples.flags.writeable
    again = register(plan, grid)
    fresh = register(synthetic_plan(), grid)
    assert mfr._prepared(plan, "touch") is not pm
    for reg in (again, fresh):
        assert reg.ok == first.ok and np.array_equal(reg.matrix, first.matrix)
        assert reg.ambiguity == first.ambiguity


def test_room_counts_in_blocks_equal_the_whole_product() -> None:
    # the coarse IoU's per-room counts run in blocks of hypotheses (one BLAS thread each): the
    # same float32 counts as the one product, also across a block boundary
    from frslam_graph.registration.mfr.coarse import ONE_THREAD_MACS, room_counts

    rng = np.random.default_rng(5)
    onehot = np.eye(12, dtype=np.float32)[rng.integers(0, 12, 1200)]
    rows = ONE_THREAD_MACS // onehot.size
    for h in (1, rows, rows + 1, 5 * rows + 3):
        on = (rng.random((h, 1200)) < 0.6).astype(np.uint8)
        got = room_counts(on, onehot)
        assert got.dtype == np.float32 and np.array_equal(got, on.astype(np.float32) @ onehot)


def test_distance_field_lookups_match_the_clipped_bilinear_formula() -> None:
    # the refinement's bilinear lookups (the hot loop of every fit) give the plain formula's
    # values exactly: np.clip'd cells, the four corners, outside the grid and NaN alike
    from frslam_graph.registration.refine import DistanceField

    rng = np.random.default_rng(7)
    free = rng.random((40, 30)) < 0.6
    field = DistanceField.from_masks(free, 0.05, (-0.3, 0.2))
    x = rng.uniform(-0.6, 1.5, 500)
    y = rng.uniform(-0.2, 2.4, 500)
    x[:3] = [np.nan, -np.inf, 0.3]
    h, w = field.sdf.shape
    u = (x - field.origin[0]) * (1.0 / field.resolution) - 0.5
    v = (y - field.origin[1]) * (1.0 / field.resolution) - 0.5
    inside = (u >= 0) & (v >= 0) & (u < w - 1) & (v < h - 1)
    u, v = np.clip(u, 0, w - 1.0001), np.clip(v, 0, h - 1.0001)
    with np.errstate(invalid="ignore"):
        i0, j0 = u.astype(np.intp), v.astype(np.intp)
    ok = np.isfinite(u)
    fx, fy = u[ok] - i0[ok], v[ok] - j0[ok]
    for img, got in ((field.sdf, field.sample(x[ok], y[ok])[0]), (field.known, field.free_at(x[ok], y[ok]))):
        c00, c10 = img[j0[ok], i0[ok]], img[j0[ok], i0[ok] + 1]
        c01, c11 = img[j0[ok] + 1, i0[ok]], img[j0[ok] + 1, i0[ok] + 1]
        top, bot = c00 + fx * (c10 - c00), c01 + fx * (c11 - c01)
        want = top + fy * (bot - top)
        if img is field.known:
            want = want * inside[ok]
        assert np.array_equal(got, want)


def test_best_bounded_gives_argmax_of_the_keys_above_a_threshold() -> None:
    # the polish restarts' room IoU is computed only where the wall part's bound can still win:
    # the same restart (np.argmax's first of equal maxima) and key as ranking every one, and
    # the skipped ones are those that cannot win
    from frslam_graph.registration.mfr.fine import best_bounded

    rng = np.random.default_rng(11)
    for _ in range(400):
        n = int(rng.integers(0, 9))
        keys = np.round(rng.random(n), 1)  # ties
        bounds = keys + np.round(rng.random(n), 1) * rng.integers(0, 2, n)
        above = float(np.round(rng.random(), 1)) if rng.random() < 0.7 else 0.0
        asked: list[int] = []

        def value(i: int, keys=keys, asked=asked) -> tuple[float, int]:
            asked.append(i)
            return float(keys[i]), i

        got = best_bounded(list(bounds), value, above)
        want = int(np.argmax(keys)) if n and keys.max() > above else None
        assert (got is None) == (want is None)
        if want is not None:
            assert got == (want, (float(keys[want]), want))
        assert len(set(asked)) == len(asked) and all(bounds[i] > above for i in asked)


def test_wall_bound_is_never_below_the_structure_key() -> None:
    # the product without the IoU (<= 1) bounds the key in floating point too
    from frslam_graph.registration.mfr.fine import _wall_bound

    rng = np.random.default_rng(3)
    for _ in range(20000):
        iou, prec, rec = rng.random(3)
        door = np.float64(rng.random())
        assert float(iou * prec * rec * door) <= _wall_bound((float(prec), float(rec), door))


def test_map_side_helpers_match_their_full_canvas_formulas() -> None:
    # the coarse footprint from the integral image is the block mean's >= 0.5; the small
    # obstacles kept free are those that do not touch the footprint's border ring
    from frslam_graph.registration.mfr.map_side import _coarse_cover, _ring, _touching

    rng = np.random.default_rng(5)
    for h, w, k in ((80, 120, 3), (97, 61, 4), (7, 200, 3), (64, 64, 8)):
        fp = cv2.dilate((rng.random((h, w)) < 0.05).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        hc, wc = max(1, h // k), max(1, w // k)
        want = fp[: hc * k, : wc * k].reshape(hc, k, wc, k).mean(axis=(1, 3)) >= 0.5
        assert np.array_equal(_coarse_cover(fp, k, hc, wc), want)
        nonfree = (fp & (rng.random((h, w)) < 0.2)).astype(np.uint8)
        m, lab, _, _ = cv2.connectedComponentsWithStats(nonfree, connectivity=8)
        border = cv2.dilate(_ring(fp).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        touching = np.zeros(m, bool)
        touching[np.unique(lab[border])] = True
        touching[0] = True
        assert np.array_equal(_touching(fp, lab, m), touching)


def test_room_subsets_are_kept_with_the_prepared_plan(plan):
    # the connected subsets and their shapes per dihedral case are computed once per plan object
    # and options, read-only, equal to a fresh computation
    from frslam_graph.registration.mfr import coarse
    from frslam_graph.registration.mfr import register as mfr

    pm, derived = mfr._prepared_entry(plan, "doors")
    masks, cases = mfr._subsets(pm, derived, None, 3000)
    again = mfr._subsets(pm, derived, None, 3000)
    assert again[0] is masks and again[1] is cases and not masks.flags.writeable
    assert np.array_equal(masks, connected_subsets(pm.adjacency, max_per_level=3000))
    fresh = coarse.dihedral_cases(coarse.subset_geometry(pm, masks))
    assert len(cases) == 5 and all(u.shape[0] == 8 for u in cases)  # features, vx, vy, cx, cy per case
    assert all(np.array_equal(u, v) and not u.flags.writeable for u, v in zip(cases, fresh, strict=True))
    seeded = mfr._subsets(pm, derived, np.array([1]), 3000)[0]
    assert np.array_equal(seeded, connected_subsets(pm.adjacency, seeds=np.array([1]), max_per_level=3000))


def test_room_labels_drawn_as_uint8_equal_the_int32_labels(plan):
    # placed_rooms_iou draws the labels straight into uint8: the same pixels as the int32 canvas
    from frslam_graph.registration.mfr import register as mfr
    from frslam_graph.registration.mfr.plan_side import fill_rooms

    pm = mfr._prepared(plan, "doors")
    frame = RasterFrame(0.05, (-1.0, -3.0), (260, 300))
    for flipped, deg in ((False, 0.0), (True, 33.0), (False, 211.0)):
        m = truth_matrix(flipped, deg)
        a = fill_rooms(pm.room_rings, pm.room_holes, range(len(pm.ids)), m, frame, labels=True)
        b = fill_rooms(
            pm.room_rings, pm.room_holes, range(len(pm.ids)), m, frame, labels=True, label_dtype=np.uint8
        )
        assert a.dtype == np.int32 and b.dtype == np.uint8 and a.any() and np.array_equal(a, b)


def test_batched_trial_placements_equal_the_matrix_by_matrix_products() -> None:
    # local_search builds its 15 trials of an axis round at once: the same bits as the
    # products taken one trial at a time
    from frslam_graph.se2 import rot

    rng = np.random.default_rng(2)
    for _ in range(50):
        rm = np.eye(3)
        rm[:2, :2] = rot(rng.uniform(-np.pi, np.pi))
        m = np.eye(3)
        m[:2] = rng.normal(size=(2, 3))
        c, ext, axis = rng.normal(size=2) * 5, rng.random(2) * 10, int(rng.integers(2))
        factors, shift = (0.85, 0.92, 1.0, 1.08, 1.17), 0.08
        f = np.repeat(np.array(factors), 3)
        sh = np.tile(np.array([-shift, 0.0, shift]), len(factors))
        d = np.broadcast_to(np.eye(3), (len(f), 3, 3)).copy()
        d[:, axis, axis] = f
        d[:, axis, 2] = c[axis] * (1.0 - f) + sh * ext[axis]
        batched = rm @ d @ rm.T @ m
        one = []
        for fi in factors:
            for si in (-shift, 0.0, shift):
                di = np.eye(3)
                di[axis, axis] = fi
                di[axis, 2] = c[axis] * (1.0 - fi) + si * ext[axis]
                one.append(rm @ di @ rm.T @ m)
        assert np.array_equal(batched, np.stack(one))


def hall_plan(asymmetric: bool) -> FloorPlan:
    """A hall 2 m wide along offices on both sides: a spine with a foot at one end and a stub
    at the other (no symmetry), or a plain rectangle (symmetric under 180 deg and its mirrors)."""
    if asymmetric:
        hall = shapely.Polygon([(0, 0), (5, 0), (5, 10), (6.5, 10), (6.5, 12), (3, 12), (3, 2), (0, 2)])
    else:
        hall = box(3, 0, 5, 12)
    rooms = [Room("hall", "corridor", shapely.Polygon(np.asarray(hall.exterior.coords) * U))]
    doors = []
    for side, x0, x1, spans in (
        ("w", 0, 3, ((3, 6), (6, 9), (9, 12))),
        ("e", 5, 8, ((0, 4), (4, 7), (7, 10))),
    ):
        for i, (y0, y1) in enumerate(spans):
            rooms.append(Room(f"{side}{i}", "office", box(x0 * U, y0 * U, x1 * U, y1 * U)))
            x = (3 if side == "w" else 5) * U
            doors.append(Door(f"d{side}{i}", (x, (y0 + 1) * U), (x, (y0 + 2) * U), ("hall", f"{side}{i}")))
    return FloorPlan(rooms, doors, units="px", name="hall")


def with_furniture(grid: OccupancyGrid, seed: int, n: int = 30) -> OccupancyGrid:
    """``grid`` with ``n`` furniture edges (2 cells thick, 0.4-1 m long) in its free space: map
    walls that no plan wall explains."""
    rng = np.random.default_rng(seed)
    free, occ = grid.free_mask().copy(), grid.occupied_mask().copy()
    ys, xs = np.nonzero(free)
    for _ in range(n):
        k, length = rng.integers(len(ys)), rng.integers(8, 20)
        y, x = ys[k], xs[k]
        if rng.random() < 0.5:
            occ[y : y + 2, x : x + length] = True
        else:
            occ[y : y + length, x : x + 2] = True
    return OccupancyGrid.from_masks(free & ~occ, occ, grid.resolution, grid.origin)


@pytest.mark.parametrize("flipped, rotation", [(False, 0.0), (True, 90.0), (False, 200.0), (True, -30.0)])
def test_one_room_whose_shape_fixes_flip_and_rotation_is_not_refused(flipped, rotation):
    """A map of one hall with furniture (its placement explains 82-94 % of the map's walls):
    a hall with a foot and a stub fixes flip and rotation by its shape, as a corridor network
    does (Halmstad E5_04, tools/README.md), and its other turns score clearly lower; a plain
    rectangle does not, and stays refused as under-determined."""
    truth = truth_matrix(flipped, rotation)
    asym, rect = hall_plan(True), hall_plan(False)
    reg = register(asym, with_furniture(ring_map(asym, truth, ["hall"]), 0))
    assert reg.ok, reg.reason
    assert reg.rooms == ("hall",) and reg.flipped == flipped and rot_error_deg(reg, truth) < 2.0
    assert 0.0 < reg.ambiguity <= 0.8 and not reg.details["ambiguous"]
    reg = register(rect, with_furniture(ring_map(rect, truth, ["hall"]), 0))
    assert not reg.ok and "under-determined" in reg.reason and "a turn of it scores" in reg.reason
