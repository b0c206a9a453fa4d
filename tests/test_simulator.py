"""Simulator: distortion, true house, exact ray casting, route, odometry, partial map, bag output."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import shapely
from frslam_graph.datasets.simulator import (
    Distortion,
    House,
    Lidar,
    OdometryNoise,
    RayCaster,
    RouteParams,
    SimulationOptions,
    cast_naive,
    cast_sweep,
    explored_fraction,
    five_room_plan,
    partial_map,
    plan_route,
    simulate,
    simulate_run,
    wheel_odometry,
)

from frslam_graph.errors import ConfigError, FloorPlanError
from frslam_graph.floorplan import FloorPlan

FAST = dict(beams=181, scan_rate=5.0, odom_rate=20.0, length=8.0, map_noise=False)


@pytest.fixture(scope="module")
def plan() -> FloorPlan:
    return five_room_plan()


@pytest.fixture(scope="module")
def house(plan: FloorPlan) -> House:
    d = Distortion(0.05, (0.9, 1.1), True, math.radians(30.0), (3.0, -2.0))
    return House.from_plan(plan, d, clutter=4, rng=np.random.default_rng(1))


@pytest.fixture(scope="module")
def short_run(plan: FloorPlan):
    return simulate_run(plan, seed=7, options=SimulationOptions(**FAST))


# ----------------------------------------------------------------------------- distortion
def test_distortion_matrix_form_and_inverse():
    d = Distortion(0.04, (0.8, 1.25), True, 1.1, (2.5, -7.0))
    c, s = math.cos(1.1), math.sin(1.1)
    t = np.array([[1, 0, 2.5], [0, 1, -7.0], [0, 0, 1]])
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    f = np.diag([1.0, -1.0, 1.0])
    sc = np.diag([0.04 * 0.8, 0.04 * 1.25, 1.0])
    np.testing.assert_allclose(d.matrix, t @ r @ f @ sc, atol=1e-15)
    pts = np.random.default_rng(0).uniform(-100, 100, (20, 2))
    back = np.c_[d.apply(pts), np.ones(20)] @ d.inverse.T
    np.testing.assert_allclose(back[:, :2], pts, atol=1e-9)
    assert np.linalg.det(d.matrix[:2, :2]) < 0  # flipped
    assert Distortion.from_dict(json.loads(json.dumps(d.to_dict()))) == d


def test_distortion_random_ranges(plan):
    rng = np.random.default_rng(3)
    flips = 0
    for _ in range(200):
        d = Distortion.random(rng, rotation="step90", plan_bounds=plan.bounds)
        k = d.rotation / (math.pi / 2)
        assert abs(k - round(k)) < 1e-12
        ratio = d.aspect[1] / d.aspect[0]
        assert 0.7 - 1e-12 <= ratio <= 1.3 + 1e-12
        minx, miny, maxx, maxy = plan.bounds
        diag = math.hypot(maxx - minx, maxy - miny) * d.metres_per_unit
        assert 10.0 <= diag <= 25.0
        flips += d.flip
    assert 60 < flips < 140
    anys = [Distortion.random(rng, rotation="any", plan_bounds=plan.bounds).rotation for _ in range(50)]
    assert any(abs(a / (math.pi / 2) - round(a / (math.pi / 2))) > 0.05 for a in anys)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(metres_per_unit=0.0),
        dict(metres_per_unit=float("nan")),
        dict(metres_per_unit=1.0, aspect=(1.0, -1.0)),
        dict(metres_per_unit=1.0, translation=(0.0,)),
        dict(metres_per_unit=1.0, rotation=float("inf")),
    ],
)
def test_distortion_bad_values(kwargs):
    with pytest.raises(ConfigError, match="distortion"):
        Distortion(**kwargs)


def test_distortion_random_bad_options():
    rng = np.random.default_rng(0)
    with pytest.raises(ConfigError, match="rotation"):
        Distortion.random(rng, rotation="diagonal", metres_per_unit=1.0)
    with pytest.raises(ConfigError, match="metres_per_unit"):
        Distortion.random(rng)


# ----------------------------------------------------------------------------- house
def test_house_geometry(house, plan):
    assert house.plan.units == "m"
    # rooms are the plan's rooms under the distortion
    for r_plan, r_house in zip(plan.rooms, house.plan.rooms, strict=True):
        expected = shapely.affinity.affine_transform(
            r_plan.polygon, [*house.distortion.matrix[:2, :2].ravel(), *house.distortion.matrix[:2, 2]]
        )
        assert r_house.polygon.symmetric_difference(expected).area < 1e-9
    # walls and free space do not overlap; the entrance (one room) is closed, interior doors open
    assert house.walls.intersection(house.free_space).area < 1e-6
    assert "entrance" in house.closed_doors and set(house.open_doors) == {"d0", "d1", "d2", "d3", "d4"}
    assert len(house.obstacles) == 4
    for o in house.obstacles:
        assert not o.intersects(house.walls)
    assert house.segments.shape[1] == 4 and len(house.segments) > 20
    # a room boundary shared by two rooms becomes a wall of the given thickness
    assert house.free_space.area < house.plan.area
    back = House.from_dict(json.loads(json.dumps(house.to_dict())))
    np.testing.assert_array_equal(back.segments, house.segments)
    assert back.distortion == house.distortion


def test_house_closed_door_blocks(plan):
    d = Distortion(0.05)
    h = House.from_plan(plan, d, closed_doors=["d2"])
    assert "bathroom" not in h.reachable("living")
    assert h.adjacency()["bathroom"] == set()
    with pytest.raises(ConfigError, match="closed_doors"):
        House.from_plan(plan, d, closed_doors=["nope"])
    with pytest.raises(ConfigError, match="wall_thickness"):
        House.from_plan(plan, d, wall_thickness=-1.0)


def test_house_opens_boundaries_without_plan_walls(plan):
    """Plans with walls: a shared boundary no wall runs along is left open (open-plan rooms)."""
    from dataclasses import replace

    rings = [np.asarray(r.polygon.exterior.coords) for r in plan.rooms]
    walls = np.vstack([np.hstack((c[:-1], c[1:])) for c in rings])
    # drop the living/kitchen wall (x = 120, y in 0..80) and its door
    keep = ~(
        (np.abs(walls[:, 0] - 120) < 1e-9)
        & (np.abs(walls[:, 2] - 120) < 1e-9)
        & (walls[:, 1] < 81)
        & (walls[:, 3] < 81)
    )
    open_plan = replace(plan, walls=walls[keep], doors=[d for d in plan.doors if d.id != "d0"])
    d = Distortion(0.05)
    h = House.from_plan(open_plan, d)
    assert ("living", "kitchen") in h.open_boundaries
    assert "kitchen" in h.adjacency()["living"]
    line = shapely.LineString([(6.0, 0.3), (6.0, 3.7)])  # the missing wall, metres
    assert not line.intersects(h.walls)
    # without the plan's walls every boundary is a wall
    h2 = House.from_plan(replace(open_plan, walls=None), d)
    assert h2.open_boundaries == () and line.intersects(h2.walls)
    assert "kitchen" not in h2.adjacency()["living"]


def test_house_from_bad_dict():
    with pytest.raises(FloorPlanError, match="format"):
        House.from_dict({"format": "other"})


# ----------------------------------------------------------------------------- lidar
def _brute_force(segments, pose, angle):
    """One ray against every segment, plain Python."""
    ox, oy = pose[0], pose[1]
    dx, dy = math.cos(pose[2] + angle), math.sin(pose[2] + angle)
    best = math.inf
    for x1, y1, x2, y2 in segments:
        ex, ey = x2 - x1, y2 - y1
        den = dx * ey - dy * ex
        if den == 0:
            continue
        r = ((x1 - ox) * ey - (y1 - oy) * ex) / den
        t = ((x1 - ox) * dy - (y1 - oy) * dx) / den
        if -1e-9 <= t <= 1 + 1e-9 and r > 0:
            best = min(best, r)
    return best


def test_ray_casters_exact_against_brute_force(house):
    rng = np.random.default_rng(5)
    lidar = Lidar(beams=720, max_range=30.0)
    free = house.free_space
    minx, miny, maxx, maxy = free.bounds
    poses = []
    while len(poses) < 12:
        x, y = rng.uniform(minx, maxx), rng.uniform(miny, maxy)
        if free.contains(shapely.Point(x, y)):
            poses.append((x, y, rng.uniform(-math.pi, math.pi)))
    poses = np.array(poses)
    angles = lidar.angles
    results = {m: RayCaster(house.segments, method=m).cast(poses, angles, 30.0) for m in ("sweep", "naive")}
    try:
        results["open3d"] = RayCaster(house.segments, method="open3d").cast(poses, angles, 30.0)
    except ConfigError:
        pass
    for i in range(len(poses)):
        for b in rng.choice(len(angles), 25, replace=False):
            ref = _brute_force(house.segments, poses[i], angles[b])
            for name, r in results.items():
                assert math.isfinite(r[i, b]), name  # inside a closed house every beam hits
                assert abs(r[i, b] - ref) < 1e-6, (name, i, b)
    for name, r in results.items():
        assert np.abs(r - results["naive"]).max() < 1e-6, name


def test_ray_cast_known_answer_and_max_range():
    # 4 x 4 m box, sensor at the centre looking along +x
    seg = np.array([[-2, -2, 2, -2], [2, -2, 2, 2], [2, 2, -2, 2], [-2, 2, -2, -2]], float)
    angles = np.array([-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4, math.pi / 2])
    for r in (cast_sweep(seg, np.zeros(3), angles, 30.0), cast_naive(seg, np.zeros(3), angles, 30.0)):
        np.testing.assert_allclose(r[0], [2, 2 * math.sqrt(2), 2, 2 * math.sqrt(2), 2], atol=1e-12)
    short = cast_sweep(seg, np.zeros(3), angles, 2.5)
    assert np.isinf(short[0, 1]) and np.isinf(short[0, 3]) and short[0, 2] == pytest.approx(2.0)
    # a full 360° scanner with beams on both sides of the wrap-around
    lid = Lidar(beams=360, fov=2 * math.pi, max_range=10.0)
    r = lid.cast(seg, np.array([[0.5, 0.3, 3.0]]))
    ref = np.array([_brute_force(seg, (0.5, 0.3, 3.0), a) for a in lid.angles])
    np.testing.assert_allclose(r[0], ref, atol=1e-9)


def test_lidar_noise_dropout_and_bad_params(house):
    lid = Lidar(beams=300, range_noise=0.02, dropout=0.1)
    poses = np.array([house.free_space.representative_point().coords[0] + (0.0,)])
    exact, meas = lid.measure(house.segments, np.repeat(poses, 40, axis=0), np.random.default_rng(0))
    drop = np.isnan(meas).mean()
    assert 0.07 < drop < 0.13
    ok = np.isfinite(meas)
    assert 0.015 < np.std(meas[ok] - exact[ok]) < 0.025
    for kwargs in (
        dict(beams=1),
        dict(fov=0.0),
        dict(max_range=-1.0),
        dict(dropout=1.0),
        dict(min_range=40.0),
    ):
        with pytest.raises(ConfigError, match="lidar"):
            Lidar(**kwargs)
    with pytest.raises(ConfigError, match="segments"):
        cast_sweep(np.zeros((3, 3)), np.zeros(3), lid.angles, 10.0)
    with pytest.raises(ConfigError, match="method"):
        RayCaster(house.segments, method="gpu")


# ----------------------------------------------------------------------------- route
def test_route_never_collides_and_respects_limits(house):
    params = RouteParams(max_speed=0.6, max_turn_rate=0.9)
    route = plan_route(house, np.random.default_rng(2), length=40.0, params=params)
    assert route.length >= 35.0
    assert route.min_clearance(house) >= params.robot_radius
    v, w = route.speeds()
    assert v.max() <= 0.6 + 1e-6 and np.abs(w).max() <= 0.9 + 1e-6
    assert 0.2 < v.mean() <= 0.6
    # every reachable room is visited
    assert set(route.rooms) == set(house.reachable(route.rooms[0]))
    # poses are sampled at increasing stamps and the sampler interpolates them
    mid = route.sample(route.stamps[[10, 11]])
    np.testing.assert_allclose(mid, route.poses[[10, 11]], atol=1e-12)


def test_driver_follows_a_path_that_turns_back():
    """A path that goes out and comes back the same way (a U-turn) is driven to its end."""
    from frslam_graph.datasets.simulator.route import _drive, _resample

    # the start of a real route (R2V plan 5, seed 1) on which the robot once froze in place
    path = _resample(
        np.array([[0.1559, 0.9085], [0.2711, 0.7462], [-0.1686, 1.1309], [-1.6175, 1.6784]]), 0.02
    )
    params = RouteParams()
    poses = _drive(path, params)
    assert np.hypot(*(poses[-1, :2] - path[-1])) < 0.03
    assert len(poses) * params.dt < 30.0  # about 2 m of driving, not stuck turning in place


def test_route_given_rooms_and_errors(house):
    route = plan_route(house, np.random.default_rng(0), rooms=["kitchen", "living", "bathroom"])
    assert route.rooms == ["kitchen", "living", "bathroom"]
    rooms_at_end = house.room_at(route.poses[[0, -1], :2])
    assert rooms_at_end == ["kitchen", "bathroom"]
    with pytest.raises(ConfigError, match="route.rooms"):
        plan_route(house, np.random.default_rng(0), rooms=["kitchen", "attic"])
    closed = House.from_plan(five_room_plan(), Distortion(0.05), closed_doors=["d2"])
    with pytest.raises(ConfigError, match="cannot be reached"):
        plan_route(closed, np.random.default_rng(0), rooms=["living", "bathroom"])
    with pytest.raises(ConfigError, match="route.length"):
        plan_route(house, np.random.default_rng(0), length=-5.0)


# ----------------------------------------------------------------------------- odometry
def test_odometry_drift_statistics():
    n = 201  # 10 m straight along x in 5 cm steps
    stamps = np.arange(n) * 0.1
    true = np.column_stack((np.linspace(0, 10, n), np.zeros(n), np.zeros(n)))
    noise = OdometryNoise(
        scale_error=0.03,
        turn_scale_error=0.0,
        dist_noise=0.02,
        heading_noise=math.radians(1.0),
        turn_noise=0.0,
    )
    rng = np.random.default_rng(0)
    finals = np.array([wheel_odometry(stamps, true, noise, rng).poses[-1] for _ in range(400)])
    # systematic scale: 3 % of 10 m; random distance walk: 0.02 * sqrt(10) m
    assert np.mean(finals[:, 0]) == pytest.approx(10.3, abs=0.02)
    heading_std = np.std(finals[:, 2])
    assert heading_std == pytest.approx(math.radians(1.0) * math.sqrt(10.0), rel=0.15)
    # along-track spread: distance walk plus the cosine of the heading error (second order)
    assert np.std(finals[:, 0]) == pytest.approx(0.02 * math.sqrt(10.0), rel=0.2)
    # rate independence: 4x finer sampling gives the same spread
    n4 = 4 * (n - 1) + 1
    true4 = np.column_stack((np.linspace(0, 10, n4), np.zeros(n4), np.zeros(n4)))
    finals4 = np.array(
        [wheel_odometry(np.arange(n4) * 0.025, true4, noise, rng).poses[-1] for _ in range(400)]
    )
    assert np.std(finals4[:, 2]) == pytest.approx(heading_std, rel=0.2)


def test_odometry_starts_at_true_pose_and_is_exact_without_noise(short_run):
    route = short_run.route
    stamps = route.stamps[::10]
    true = route.sample(stamps)
    odo = wheel_odometry(stamps, true, OdometryNoise.none(), np.random.default_rng(0))
    np.testing.assert_allclose(odo.poses, true, atol=1e-9)
    noisy = wheel_odometry(stamps, true, OdometryNoise(), np.random.default_rng(0))
    np.testing.assert_array_equal(noisy.poses[0], true[0])
    assert np.abs(noisy.poses[-1, :2] - true[-1, :2]).max() > 1e-4
    with pytest.raises(ConfigError, match="odometry.rate"):
        OdometryNoise(rate=0.0)


# ----------------------------------------------------------------------------- partial map
@pytest.mark.parametrize("completeness", [0.25, 0.5, 0.75, 1.0])
def test_partial_map_completeness_and_frame(house, completeness):
    rng = np.random.default_rng(int(completeness * 100))
    grid, rooms = partial_map(house, completeness, rng, noise=False)
    frac = explored_fraction(house, rooms)
    areas = house.room_areas
    total = sum(areas.values())
    # the closest connected set: adding or removing any single frontier room is not better
    adj = house.adjacency()
    assert len(set(rooms)) == len(rooms)
    assert set(rooms) <= set(house.reachable(rooms[0]))
    frontier = {nb for r in rooms for nb in adj[r]} - set(rooms)
    for cand in frontier:
        assert abs(frac + areas[cand] / total - completeness) >= abs(frac - completeness) - 1e-12
    if completeness == 1.0:
        assert frac == pytest.approx(1.0)
    # map frame = house frame: free cells lie in the explored rooms' free space
    free_xy = grid.cell_to_world(np.argwhere(grid.free_mask())[:, ::-1] + 0.5)
    explored = shapely.union_all([house.plan.room(r).polygon for r in rooms]).buffer(0.05)
    assert shapely.contains_xy(explored, free_xy[:, 0], free_xy[:, 1]).all()
    assert shapely.contains_xy(house.free_space.buffer(0.04), free_xy[:, 0], free_xy[:, 1]).all()
    occ_xy = grid.cell_to_world(np.argwhere(grid.occupied_mask())[:, ::-1] + 0.5)
    solid = shapely.union_all([house.walls, *house.obstacles])
    assert (shapely.distance(shapely.points(occ_xy), solid) < 0.08).all()
    free_area = grid.free_mask().sum() * grid.resolution**2
    expected = sum(house.room_free[r].area for r in rooms)
    assert free_area == pytest.approx(expected, rel=0.06)


def test_partial_map_sees_through_open_doors(house):
    clean, rooms = partial_map(house, 0.3, np.random.default_rng(1), noise=False, start_room="kitchen")
    seen, rooms2 = partial_map(
        house, 0.3, np.random.default_rng(1), noise=False, start_room="kitchen", see_through_doors=True
    )
    assert rooms == rooms2 == ["kitchen"]
    extra = seen.free_mask().sum() - clean.free_mask().sum()
    assert extra > 200  # the living room is partly visible through door d0
    xy = seen.cell_to_world(np.argwhere(seen.free_mask())[:, ::-1] + 0.5)
    inside = house.room_at(xy)
    assert set(inside) - {None} == {"kitchen", "living"}
    living = np.array([r == "living" for r in inside])
    assert 0 < living.sum() < 0.9 * house.room_free["living"].area / seen.resolution**2


def test_partial_map_noise_and_errors(house):
    clean, rooms = partial_map(house, 0.5, np.random.default_rng(4), noise=False, start_room="living")
    noisy, rooms2 = partial_map(house, 0.5, np.random.default_rng(4), noise=True, start_room="living")
    assert rooms == rooms2 and rooms[0] == "living"
    assert not np.array_equal(clean.data, noisy.data)
    assert abs(int(noisy.free_mask().sum()) - int(clean.free_mask().sum())) < 0.01 * clean.free_mask().sum()
    with pytest.raises(ConfigError, match="completeness"):
        partial_map(house, 0.0, np.random.default_rng(0))
    with pytest.raises(ConfigError, match="start_room"):
        partial_map(house, 0.5, np.random.default_rng(0), start_room="attic")


# ----------------------------------------------------------------------------- runs and files
def test_run_consistency_and_determinism(plan, short_run):
    run = short_run
    n = len(run)
    assert run.ranges.shape == (n, 181) and run.ground_truth.shape == (n, 4)
    np.testing.assert_array_equal(np.diff(run.stamps_ns), 200_000_000)
    np.testing.assert_allclose(np.diff(run.stamps), 0.2, atol=1e-6)  # float64 at epoch: ~0.2 µs
    # the scans are the ray caster's answer at the true poses (plus noise)
    again = RayCaster(run.house.segments, method="sweep").cast(run.true_poses, run.lidar.angles, 30.0)
    np.testing.assert_allclose(run.exact_ranges, again, atol=1e-6)
    ok = np.isfinite(run.ranges)
    assert np.abs(run.ranges[ok] - run.exact_ranges[ok]).max() < 0.1
    scan = run.scans[3]
    assert scan.odom == tuple(run.odom_poses[3]) and scan.stamp == run.stamps[3]
    # odom frame starts at the first true pose
    np.testing.assert_allclose(run.odom_poses[0], run.true_poses[0], atol=1e-12)
    same = simulate_run(plan, seed=7, options=SimulationOptions(**FAST))
    np.testing.assert_array_equal(same.ranges, run.ranges)
    np.testing.assert_array_equal(same.odom_poses, run.odom_poses)
    np.testing.assert_array_equal(same.grid.data, run.grid.data)
    other = simulate_run(plan, seed=8, options=SimulationOptions(**FAST))
    assert other.distortion != run.distortion


def test_simulate_writes_bag_readable_with_rosbags(plan, tmp_path):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    res = simulate(plan, tmp_path / "sim", seed=3, options=SimulationOptions(**FAST), keep_run=True)
    run = res.run
    for p in (res.bag, res.ground_truth, res.house, res.meta, res.map_yaml, res.plan):
        assert p.exists()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    gt, scans, odom = [], [], []
    with Reader(res.bag) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        for conn, t, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == "/ground_truth":
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                assert ns == t and msg.header.frame_id == "map"
                gt.append((ns, p.x, p.y, 2.0 * math.atan2(q.z, q.w)))
            elif conn.topic == "/scan":
                scans.append(msg.ranges)
                assert msg.header.frame_id == "laser" and len(msg.ranges) == 181
            elif conn.topic == "/odom":
                assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
                odom.append((msg.pose.pose.position.x, msg.pose.pose.position.y))
    assert counts["/scan"] == counts["/ground_truth"] == len(run) == res.scans
    assert counts["/odom"] == res.odometry
    gt = np.array(gt)
    np.testing.assert_array_equal(gt[:, 0].astype(np.int64), run.stamps_ns)
    np.testing.assert_array_equal(gt[:, 1:3], run.true_poses[:, :2])  # exact round trip
    np.testing.assert_allclose(gt[:, 3], run.true_poses[:, 2], atol=1e-14)
    np.testing.assert_array_equal(np.array(scans), run.ranges.astype(np.float32))
    np.testing.assert_array_equal(np.array(odom), run.odometry.poses[:, :2])
    tum = np.loadtxt(res.ground_truth)
    np.testing.assert_array_equal(tum[:, 1:3], run.true_poses[:, :2])
    meta = json.loads(res.meta.read_text())
    assert meta["seed"] == 3 and meta["counts"]["scans"] == len(run)
    house = House.load(res.house)
    np.testing.assert_allclose(house.distortion.matrix, run.distortion.matrix)
    from frslam_graph.occupancy import OccupancyGrid

    grid = OccupancyGrid.load(res.map_yaml)
    np.testing.assert_array_equal(grid.data, run.grid.data)
    assert FloorPlan.load(res.plan).room_ids == plan.room_ids
    # an existing output is not overwritten silently
    with pytest.raises(ConfigError, match="overwrite"):
        simulate(plan, tmp_path / "sim", seed=3, options=SimulationOptions(**FAST))
    simulate(plan, tmp_path / "sim", seed=4, options=SimulationOptions(**FAST), overwrite=True)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(beams=1), "simulation.beams"),
        (dict(fov_deg=400.0), "simulation.fov_deg"),
        (dict(rotation="diagonal"), "simulation.rotation"),
        (dict(min_range=50.0), "min_range"),
        (dict(scan_rate=-1.0), "simulation.scan_rate"),
        (dict(colour="red"), "simulation.colour"),
        (dict(clutter=-2), "simulation.clutter"),
    ],
)
def test_bad_options_raise_config_error(kwargs, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        SimulationOptions(**kwargs)


def test_bad_simulation_inputs(plan):
    with pytest.raises(ConfigError, match="closed_doors"):
        simulate_run(plan, 0, SimulationOptions(closed_doors=9, **FAST))
    with pytest.raises(ConfigError, match="closed_door_ids"):
        simulate_run(plan, 0, SimulationOptions(closed_door_ids=["zz"], **FAST))
    with pytest.raises(ConfigError, match="seed"):
        simulate_run(plan, -1, SimulationOptions(**FAST))
    with pytest.raises(ConfigError, match="route.rooms"):
        simulate_run(plan, 0, SimulationOptions(rooms=["attic"], **FAST))


def test_r2v_plan_simulates_and_reads_back(shared_data, tmp_path):
    """Acceptance: a shared R2V plan, simulated and read back through the bag reader."""
    from frslam_graph.datasets import open_recording

    path = sorted((shared_data / "floorplans" / "r2v").glob("*.txt"))[2]
    plan = FloorPlan.load(path)
    opts = SimulationOptions(**{**FAST, "range_noise": 0.0})
    res = simulate(plan, tmp_path / "r2v", seed=1, options=opts, keep_run=True)
    run = res.run
    assert run.route.min_clearance(run.house) >= run.route.params.robot_radius
    rec = open_recording(tmp_path / "r2v")
    assert len(rec) == len(run)
    gt = rec.ground_truth()
    np.testing.assert_array_equal(gt[:, 1:3], run.true_poses[:, :2])
    np.testing.assert_allclose(gt[:, 0], run.stamps, atol=1e-9)
    caster = RayCaster(run.house.segments, method="sweep")
    for i, scan in enumerate(rec):
        # noise-free scans are the ray caster's ranges at the true pose (float32 in the bag)
        exact = caster.cast(run.true_poses[i], scan.angles, run.lidar.max_range)[0]
        np.testing.assert_array_equal(np.isfinite(scan.ranges), np.isfinite(exact))
        ok = np.isfinite(exact)
        assert ok.all()  # a closed house: every beam hits within 30 m
        # float32 ranges; the reader's angles come from float32 angle_min / angle_increment
        np.testing.assert_allclose(scan.ranges, run.exact_ranges[i].astype(np.float32), rtol=0, atol=0)
        np.testing.assert_allclose(scan.ranges[ok], exact[ok], atol=1e-4)
        np.testing.assert_allclose(scan.odom, run.odom_poses[i], atol=1e-6)


def test_cli_simulate(plan, tmp_path):
    from frslam_graph.cli import main

    plan_path = plan.save(tmp_path / "plan.json")
    out = tmp_path / "out"
    args = ["simulate", str(plan_path), "--out", str(out), "--seed", "5", "--beams", "91"]
    args += ["--scan-rate", "5", "--length", "5", "--rooms", "living,kitchen", "--clutter", "2"]
    assert main(args) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert (
        meta["seed"] == 5 and meta["lidar"]["beams"] == 91 and meta["route"]["rooms"] == ["living", "kitchen"]
    )
    assert (out / "bag" / "metadata.yaml").is_file() and (out / "map.pgm").is_file()
    assert main(args) == 2  # existing output without --overwrite
    assert main([*args, "--overwrite", "--fov", "400"]) == 2  # bad option -> one-line error
    assert main([*args, "--overwrite"]) == 0


def test_r2v_houses_are_closed(shared_data):
    """No beam from inside a house built from a real plan escapes it (outer walls never cut)."""
    files = sorted((shared_data / "floorplans" / "r2v").glob("*.txt"))[:12]
    lid = Lidar(beams=360, fov=2 * math.pi, max_range=60.0)
    for k, path in enumerate(files):
        plan = FloorPlan.load(path)
        rng = np.random.default_rng(k)
        d = Distortion.random(rng, rotation="any", plan_bounds=plan.bounds)
        house = House.from_plan(plan, d, clutter=2, rng=rng)
        minx, miny, maxx, maxy = house.free_space.bounds
        pts = rng.uniform((minx, miny), (maxx, maxy), size=(400, 2))
        pts = pts[shapely.contains_xy(house.free_space, pts[:, 0], pts[:, 1])][:25]
        poses = np.column_stack((pts, rng.uniform(-math.pi, math.pi, len(pts))))
        ranges = RayCaster(house.segments, method="sweep").cast(poses, lid.angles, lid.max_range)
        assert np.isfinite(ranges).all(), (path.name, int((~np.isfinite(ranges)).sum()))


def test_plan_scale_is_kept_when_known(plan):
    from dataclasses import replace

    metric = replace(plan, metres_per_unit=0.06)
    run = simulate_run(metric, seed=2, options=SimulationOptions(**FAST))
    assert run.distortion.metres_per_unit == 0.06
    run = simulate_run(metric, seed=2, options=SimulationOptions(metres_per_unit=0.08, **FAST))
    assert run.distortion.metres_per_unit == 0.08
    minx, miny, maxx, maxy = plan.bounds
    diag = math.hypot(maxx - minx, maxy - miny)
    run = simulate_run(plan, seed=2, options=SimulationOptions(house_diagonal=(12.0, 12.0), **FAST))
    assert run.distortion.metres_per_unit * diag == pytest.approx(12.0)


def test_room_segmentation_plan_doors_pass_thick_walls(shared_data):
    """Plans from real maps have thick walls between rooms: doors still connect the rooms."""
    prb = shared_data / "prbonn"
    plan = FloorPlan.from_room_segmentation(prb / "FMapRoomSeg.png", prb / "FMap.yaml")
    house = House.from_plan(plan, Distortion(1.0))
    assert len(house.open_doors) == len(plan.doors)
    route = plan_route(house, np.random.default_rng(0), start_room="room_11")
    assert len(set(route.rooms)) >= 10
    assert route.min_clearance(house) >= route.params.robot_radius
