"""LiDAR occupancy map: walls survive grazing free space, bounded no-return clearing, no clearing
behind a depth discontinuity, and the end-point share measure."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_world import box, cast, room_world, to_points

from frslam_graph.backend.mapping import (
    NO_RETURN_RANGE,
    OccupancyMapper,
    endpoint_share,
    free_polygon,
    occupancy_grid,
    scan_points_in_map,
)
from frslam_graph.odometry.motion_model import compose

RES = 0.05


def _scans(world: np.ndarray, poses: np.ndarray, n_beams: int = 720, max_range: float = 30.0):
    """End points (base_link) of noise-free scans from ``poses`` (K, 3)."""
    out = []
    for p in poses:
        r, amin, inc = cast(world, p, n_beams=n_beams, max_range=max_range, noise=0.0)
        out.append(to_points(r, amin, inc))
    return out


def _value_at(grid, xy) -> np.ndarray:
    """Cell values at map points (N, 2); -1 (unknown) off the grid."""
    cr = np.floor(grid.world_to_cell(np.asarray(xy, float))).astype(int)
    inside = (cr[:, 0] >= 0) & (cr[:, 0] < grid.width) & (cr[:, 1] >= 0) & (cr[:, 1] < grid.height)
    out = np.full(len(cr), -1, np.int8)
    out[inside] = grid.data[cr[inside, 1], cr[inside, 0]]
    return out


def test_a_wall_hit_by_a_few_scans_survives_many_grazing_scans():
    # corridor 2 m wide; 3 scans see the upper wall head-on at x = 5, then 30 scans from 11-17 m
    # down the corridor see it at 4-6 degrees (their free space runs along it)
    world = np.array([[-15.0, 0.0, 15.0, 0.0], [-15.0, 2.02, 15.0, 2.02], [15.0, 0.0, 15.0, 2.02]])
    close = np.array([[5.0, 1.0, 0.0]] * 3)
    far = np.column_stack((np.linspace(-12.0, -6.0, 30), np.full(30, 1.0), np.zeros(30)))
    poses = np.vstack((close, far))
    grid = occupancy_grid(poses, _scans(world, poses), resolution=RES)
    wall = np.column_stack((np.arange(4.0, 6.0, RES) + RES / 2, np.full(40, 2.02)))
    assert np.mean(_value_at(grid, wall) == 100) > 0.95
    pts = scan_points_in_map(close, _scans(world, close))
    on_wall = pts[(np.abs(pts[:, 1] - 2.02) < 0.01) & (pts[:, 0] > 4.0) & (pts[:, 0] < 6.0)]
    assert endpoint_share(grid, on_wall) > 0.99
    # the corridor between the walls is free
    mid = np.column_stack((np.arange(-5.0, 5.0, 0.5), np.full(20, 1.0)))
    assert np.all(_value_at(grid, mid) == 0)


def test_beams_without_a_return_clear_only_up_to_the_bound():
    # a wall 2 m ahead with a 1.6 m opening and nothing behind it within range: the beams through
    # the opening have no return (absent from the points: a gap in the beam angles)
    world = np.array([[2.02, -4.0, 2.02, -0.8], [2.02, 0.8, 2.02, 4.0]])
    scans = _scans(world, np.zeros((1, 3)), n_beams=720, max_range=10.0)
    grid = occupancy_grid(np.zeros((1, 3)), scans, resolution=RES)
    through = np.array([[2.0, 0.0], [2.5, 0.1], [2.9, -0.1], [2.6, 0.3]])  # < bound, no return
    assert np.all(_value_at(grid, through) == 0)
    free = np.argwhere(grid.data == 0)
    centres = (free[:, ::-1] + 0.5) * RES + grid.origin[:2]
    beyond = centres[:, 0] > 2.02 + RES  # only beams without a return reach there
    assert np.hypot(*centres[beyond].T).max() < NO_RETURN_RANGE + RES
    assert np.hypot(*centres[beyond].T).max() > NO_RETURN_RANGE - 2 * RES
    # the walls are occupied, the cells in front of them free
    wall = np.column_stack((np.full(8, 2.02), [-1.9, -1.5, -1.2, -0.9, 0.9, 1.2, 1.5, 1.9]))
    assert np.all(_value_at(grid, wall) == 100)
    assert np.all(_value_at(grid, [[1.5, 0.0], [1.0, 1.0], [1.8, -1.5]]) == 0)


def test_a_depth_discontinuity_does_not_clear_behind_the_near_object():
    # 4-degree beams; a 1 m panel 1.5 m ahead in front of a wall 6 m ahead
    near_y = (-0.53, 0.47)
    world = np.array([[1.5, near_y[0], 1.5, near_y[1]], [6.0, -6.0, 6.0, 6.0]])
    scans = _scans(world, np.zeros((1, 3)), n_beams=90)
    grid = occupancy_grid(np.zeros((1, 3)), scans, resolution=RES)
    free = np.argwhere(grid.data == 0)
    c = (free[:, ::-1] + 0.5) * RES + grid.origin[:2]
    r, a = np.hypot(*c.T), np.arctan2(c[:, 1], c[:, 0])
    margin = 1.5 * RES / r  # one and a half cells inside the shadow's edges
    lo, hi = np.arctan2(near_y[0], 1.5), np.arctan2(near_y[1], 1.5)
    shadow = (a > lo + margin) & (a < hi - margin) & (c[:, 0] > 1.5 + 2 * RES)
    assert not shadow.any(), f"{shadow.sum()} free cells behind the panel"
    # and in the open either side the space up to the far wall is free
    assert np.all(_value_at(grid, [[4.0, 3.0], [4.0, -3.0], [1.0, 0.0]]) == 0)


def test_free_polygon_keeps_a_margin_from_the_surface_and_shortens_wedges():
    ang = np.deg2rad(np.arange(-10.0, 10.5, 1.0))
    # a wall 2 m ahead, seen head-on: each beam stops 0.1 m / cos(angle) before it
    ends = np.column_stack((np.full(ang.size, 2.0), 2.0 * np.tan(ang)))
    poly = free_polygon(np.zeros(2), ends, 0.1)
    assert len(poly) == 1 + 3 * ang.size - 2
    np.testing.assert_allclose(poly[1::3, 0], 1.9, atol=1e-9)  # beam vertices 0.1 m off the wall
    # the same wall seen at 10-20 deg incidence: the beams stop 0.1 m off the wall too
    ends = np.column_stack((2.0 / np.tan(np.deg2rad(10) + ang / 2 + 0.1), np.full(ang.size, 2.0)))
    ends = ends[np.argsort(np.arctan2(ends[:, 1], ends[:, 0]))]
    poly = free_polygon(np.zeros(2), ends, 0.1)
    assert np.all(poly[1:, 1] < 1.9 + 1e-6) and np.any(poly[1:, 1] > 1.85)
    # a step of two increments: one beam without a return between, cleared to the bound
    ang = np.deg2rad([0.0, 1.0, 2.0, 4.0, 5.0])
    ends = 2.0 * np.column_stack((np.cos(ang), np.sin(ang)))
    poly = free_polygon(np.zeros(2), ends, 0.1, no_return_range=5.0)
    assert len(poly) == 1 + 3 * 6 - 2
    assert np.isclose(np.hypot(*poly.T).max(), 5.0)
    # far and near neighbours: the wedge between them goes only as far as the near one
    ends = np.array([[4.0, 0.0], [4.0 * np.cos(0.02), 4.0 * np.sin(0.02)], [np.cos(0.04), np.sin(0.04)]])
    poly = free_polygon(np.zeros(2), ends, 0.01)
    assert np.hypot(*poly[-3:-1].T).max() < 1.0
    # a backwards step joins nothing: the wedge collapses to the sensor
    poly = free_polygon(np.zeros(2), ends[[0, 2, 1]], 0.01)
    assert np.sum(np.hypot(*poly.T) < 1e-12) >= 3


def test_endpoint_share_is_one_on_a_perfect_map_and_drops_with_pose_errors():
    world = room_world()
    rng = np.random.default_rng(4)
    poses = np.column_stack((rng.uniform(1.0, 11.0, 25), rng.uniform(1.0, 7.0, 25), rng.uniform(-3, 3, 25)))
    inside = ~np.any(
        [
            (poses[:, 0] > b[0] - 0.3)
            & (poses[:, 0] < b[2] + 0.3)
            & (poses[:, 1] > b[1] - 0.3)
            & (poses[:, 1] < b[3] + 0.3)
            for b in ((3.0, 3.0, 3.4, 3.4), (8.0, 4.5, 8.5, 5.0), (5.5, 6.8, 7.5, 8.0), (9.0, 2.6, 9.4, 3.2))
        ],
        axis=0,
    )
    poses = poses[inside]
    scans = _scans(world, poses, max_range=10.0)
    grid = occupancy_grid(poses, scans, resolution=RES)
    assert endpoint_share(grid, scan_points_in_map(poses, scans)) == 1.0
    # pose errors of 0.15 m / 1.5 deg: the end points leave the walls of the true map ...
    noise = np.column_stack(
        (rng.normal(0, 0.15, (len(poses), 2)), rng.normal(0, np.deg2rad(1.5), len(poses)))
    )
    bad = np.array([compose(p, n) for p, n in zip(poses, noise, strict=True)])
    assert endpoint_share(grid, scan_points_in_map(bad, scans)) < 0.6
    # in the map built at the wrong poses each scan's own hits mostly survive (a hit outweighs
    # ~40 misses): the share only dips there; it measures consistency, not accuracy
    bad_grid = occupancy_grid(bad, scans, resolution=RES)
    assert endpoint_share(bad_grid, scan_points_in_map(bad, scans)) < 1.0
    assert np.isnan(endpoint_share(grid, np.zeros((0, 2))))
    assert endpoint_share(grid, [[100.0, 100.0]]) == 0.0  # off the grid


def test_incremental_map_stays_exact_with_no_return_beams_and_discontinuities():
    world = np.vstack((box(0, 0, 12, 8)[:3], np.array([[3.0, 3.0, 3.0, 4.0]])))  # open side, a panel
    poses = np.column_stack((np.linspace(1.0, 10.0, 12), np.full(12, 2.0), np.linspace(0, 2, 12)))
    scans = _scans(world, poses, n_beams=180, max_range=8.0)
    m = OccupancyMapper(RES)
    m.update(poses[:8], scans[:8])
    moved = poses.copy()
    moved[2:6] = [compose(np.array([0.2, -0.1, 0.03]), p) for p in poses[2:6]]
    m.update(moved, scans)
    one_shot = OccupancyMapper(RES)
    one_shot.update(moved, scans)
    np.testing.assert_array_equal(m.arrays()[0], one_shot.arrays()[0])


@pytest.mark.parametrize("n_beams", [180, 361])
def test_wall_cells_of_a_room_stay_occupied(n_beams):
    """Every wall the scans see stays a wall: the end points of all scans lie on the map's walls."""
    world = room_world()
    poses = np.column_stack((np.linspace(1.5, 10.5, 40), np.full(40, 1.5), np.zeros(40)))
    scans = _scans(world, poses, n_beams=n_beams, max_range=10.0)
    grid = occupancy_grid(poses, scans, resolution=RES)
    assert endpoint_share(grid, scan_points_in_map(poses, scans)) > 0.99


def test_the_registration_map_lets_free_space_win_over_a_stray_hit():
    """A chair leg hit by 2 scans, crossed by the free space of 20 others: the map a user loads
    keeps it (hits outweigh misses), the map the floor-plan registration reads (rooms against
    free space, ``FREE_SPACE_WEIGHTS``) clears it."""
    from frslam_graph.backend.mapping import FREE_SPACE_WEIGHTS

    world = np.array(
        [[-5.0, -3.0, 5.0, -3.0], [5.0, -3.0, 5.0, 3.0], [5.0, 3.0, -5.0, 3.0], [-5.0, 3.0, -5.0, -3.0]]
    )
    leg = np.array(
        [[0.0, 0.0, 0.06, 0.0], [0.06, 0.0, 0.06, 0.06], [0.06, 0.06, 0.0, 0.06], [0.0, 0.06, 0.0, 0.0]]
    )
    seen = np.array([[-2.0, 0.03, 0.0]] * 2)  # the leg is there
    later = np.column_stack((np.full(20, -2.0), np.linspace(-0.5, 0.5, 20), np.zeros(20)))  # gone
    poses = np.vstack((seen, later))
    scans = _scans(np.vstack((world, leg)), seen) + _scans(world, later)
    at_leg = np.array([[0.03, 0.03]])
    keep = occupancy_grid(poses, scans, resolution=RES)
    clear = occupancy_grid(poses, scans, resolution=RES, **FREE_SPACE_WEIGHTS)
    assert _value_at(keep, at_leg)[0] == 100 and _value_at(clear, at_leg)[0] == 0


def test_scans_endpoint_share_is_the_share_of_all_end_points_in_bounded_chunks(monkeypatch):
    """The share of the keyframe scans' end points, computed a chunk of keyframes at a time: the
    same value as all end points at once (which, on a 2-h recording's 14,000 keyframes, took ~1 GB
    of temporaries at the end of the run), with no chunk much over ``ENDPOINT_CHUNK`` points."""
    from frslam_graph.backend import mapping
    from frslam_graph.occupancy import OccupancyGrid

    rng = np.random.default_rng(4)
    scans = [rng.uniform(-4.0, 4.0, (int(n), 2)).astype(np.float32) for n in rng.integers(0, 90, 60)]
    poses = np.column_stack((rng.uniform(0.0, 6.0, (60, 2)), rng.uniform(-3.0, 3.0, 60)))
    data = np.zeros((200, 200), np.int8)
    data[::9] = 100
    data[:, ::13] = 100
    grid = OccupancyGrid(data, RES, (-2.0, -2.0, 0.0))  # some end points fall off the grid
    whole = endpoint_share(grid, scan_points_in_map(poses, scans))
    asked = []
    inner = mapping.scan_points_in_map

    def counted(p, s):
        out = inner(p, s)
        asked.append((len(s), len(out)))
        return out

    monkeypatch.setattr(mapping, "scan_points_in_map", counted)
    monkeypatch.setattr(mapping, "ENDPOINT_CHUNK", 300)
    assert mapping.scans_endpoint_share(grid, poses, scans) == whole
    assert sum(k for k, _ in asked) == 60 and len(asked) > 5  # every keyframe once, in chunks
    assert max(n for _, n in asked) <= 300 + 90  # the chunk, or one keyframe's scan past it
    assert np.isnan(mapping.scans_endpoint_share(grid, poses[:2], [np.zeros((0, 2))] * 2))
    with pytest.raises(ValueError, match="2 poses for 3 scans"):
        mapping.scans_endpoint_share(grid, poses[:2], scans[:3])
