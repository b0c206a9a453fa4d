"""Place recognition of loop-closure candidates: the polar descriptor is rotation invariant and
gives the relative heading, tells different places apart, and takes empty or bad input."""

from __future__ import annotations

import numpy as np
from synthetic_world import box, cast, to_points

from frslam_graph.loop_closure.place import (
    DESCRIPTOR_MIN_RANGE,
    DESCRIPTOR_RANGE,
    RINGS,
    SECTORS,
    descriptor_distances,
    polar_descriptor,
)
from frslam_graph.loop_closure.submap_matching import transform_points
from frslam_graph.odometry.motion_model import between, compose


def _l_room() -> np.ndarray:
    """An L-shaped set of rooms with a few boxes: no symmetry."""
    return np.vstack(
        [
            box(0, 0, 12, 4),
            box(0, 4, 4, 10),
            box(2.0, 1.0, 2.6, 1.5),
            box(8.0, 2.5, 9.2, 3.2),
            box(1.0, 7.0, 1.6, 8.5),
        ]
    )


def _scan(world: np.ndarray, pose: np.ndarray, seed: int) -> np.ndarray:
    r, amin, inc = cast(world, np.asarray(pose, float), rng=np.random.default_rng(seed))
    return to_points(r, amin, inc)


def test_same_place_turned_is_near_and_gives_the_relative_heading():
    world = _l_room()
    cand = np.array([2.0, 2.0, 0.0])
    turned = np.array([2.0, 2.0, np.deg2rad(84.0)])  # 14 sectors turned
    d, heading = descriptor_distances(
        polar_descriptor(_scan(world, turned, 1)), polar_descriptor(_scan(world, cand, 2))[None]
    )
    assert d[0] < 0.2
    assert abs(np.rad2deg(heading[0]) - 84.0) <= 360.0 / SECTORS


def test_another_place_is_farther_than_the_same_place_a_little_off():
    world = _l_room()
    query = polar_descriptor(_scan(world, np.array([2.0, 2.0, 1.0]), 1))
    cands = np.stack(
        [
            polar_descriptor(_scan(world, np.array([2.3, 2.2, -0.5]), 2)),  # the same place, 0.36 m off
            polar_descriptor(_scan(world, np.array([10.0, 2.0, 0.0]), 3)),  # the other end of the L
            polar_descriptor(_scan(world, np.array([2.0, 8.5, 0.0]), 4)),  # the other arm
        ]
    )
    d, _ = descriptor_distances(query, cands)
    assert d[0] < d[1] and d[0] < d[2]


def test_heading_sign_is_the_query_pose_in_the_candidate_frame():
    rng = np.random.default_rng(0)
    world_pts = rng.uniform(-8.0, 8.0, (400, 2))
    cand_pose, query_pose = np.array([0.0, 0.0, 0.3]), np.array([0.0, 0.0, 0.3 - np.deg2rad(60.0)])
    in_frame = [transform_points(between(p, np.zeros(3)), world_pts) for p in (cand_pose, query_pose)]
    _, heading = descriptor_distances(polar_descriptor(in_frame[1]), polar_descriptor(in_frame[0])[None])
    rel = between(cand_pose, query_pose)[2]
    assert abs(np.rad2deg(heading[0] - rel)) <= 360.0 / SECTORS
    assert np.allclose(compose(cand_pose, between(cand_pose, query_pose)), query_pose)


def test_empty_and_bad_input():
    empty = polar_descriptor(np.zeros((0, 2)))
    assert empty.shape == (RINGS, SECTORS) and not empty.any()
    # non-finite points, points at or beyond the range and points nearer than the near cut are
    # ignored
    bad = np.array([[np.nan, 1.0], [np.inf, 0.0], [DESCRIPTOR_RANGE, 0.0], [0.0, -50.0], [1.0, 0.0]])
    assert not polar_descriptor(bad).any() and DESCRIPTOR_MIN_RANGE > 1.0
    one = polar_descriptor(np.array([[6.0, 0.1], [np.nan, np.nan], [0.5, 0.5]]))
    ring, sector = np.unravel_index(np.argmax(one), one.shape)
    assert (ring, sector) == (int(6.0 / (DESCRIPTOR_RANGE / RINGS)), SECTORS // 2)
    # an empty descriptor is at distance 1 from everything, itself included
    full = polar_descriptor(_scan(_l_room(), np.array([2.0, 2.0, 0.0]), 1))
    d, h = descriptor_distances(empty, np.stack([full, empty]))
    assert np.array_equal(d, [1.0, 1.0]) and np.array_equal(h, [0.0, 0.0])
    d, h = descriptor_distances(full, empty[None])
    assert d[0] == 1.0
    # no candidates: nothing to rank
    d, h = descriptor_distances(full, np.zeros((0, RINGS, SECTORS)))
    assert d.shape == (0,) and h.shape == (0,)
    # a descriptor is at distance 0 from itself
    d, h = descriptor_distances(full, full[None])
    assert d[0] < 1e-9 and h[0] == 0.0
