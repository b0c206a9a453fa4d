"""Every scan's pose in map between keyframes (KeyframeStore.scan_poses): keyframe scans at their
estimates, the map <- odom correction blended from one keyframe to the next, no step at a
keyframe; the latest scans follow the last keyframe."""

from __future__ import annotations

import numpy as np

from frslam_graph.backend.keyframes import KeyframeStore, StoredKeyframe
from frslam_graph.se2 import between, compose


def _store(odom: np.ndarray, keyframe_at: list[int]) -> KeyframeStore:
    """Scans on the odometry poses ``odom`` (N, 3), a keyframe at each index of ``keyframe_at``."""
    store = KeyframeStore()
    kf = -1
    for i, pose in enumerate(odom):
        if i in keyframe_at:
            kf += 1
            store.append(StoredKeyframe(float(i), i, pose.copy(), np.zeros((0, 2), np.float32), np.zeros(2)))
        store.scans.append(float(i), kf, between(store[kf].pose_odom, pose), pose)
    return store


def _straight(n: int) -> np.ndarray:
    return np.column_stack((0.1 * np.arange(n), np.zeros(n), np.zeros(n)))


def test_keyframe_scans_sit_at_their_estimates_and_the_correction_is_blended_between():
    odom = _straight(21)
    store = _store(odom, [0, 10, 20])
    # the graph moved the second keyframe 0.1 m sideways and turned it 2 deg, the third 0.2 m
    est = np.array([odom[0], odom[10] + [0.0, 0.1, np.deg2rad(2.0)], odom[20] + [0.0, 0.2, 0.0]])
    poses = store.scan_poses(est)
    np.testing.assert_allclose(poses[[0, 10, 20]], est, atol=1e-12)
    # half-way between keyframes 0 and 1: half-way between the pose the first keyframe implies
    # (its estimate and the odometry from it) and the one the second implies (0.041 m sideways
    # and 1 deg here, where the last keyframe's correction alone gives 0 and 0)
    via0 = compose(est[0], between(odom[0], odom[5]))
    via1 = compose(est[1], between(odom[10], odom[5]))
    np.testing.assert_allclose(poses[5, :2], (via0[:2] + via1[:2]) / 2, atol=1e-4)
    np.testing.assert_allclose(poses[5, 2], np.deg2rad(1.0), atol=1e-9)
    # no step: consecutive scans differ by about the odometry's 0.1 m, never by the corrections'
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert np.all(np.abs(steps - 0.1) < 0.02)


def test_scans_after_the_last_keyframe_follow_it_as_the_latest_pose_does():
    odom = _straight(15)
    store = _store(odom, [0, 10])
    est = np.array([odom[0], odom[10] + [0.3, -0.2, 0.1]])
    poses = store.scan_poses(est)
    for i in range(10, 15):
        np.testing.assert_allclose(poses[i], compose(est[1], store.scans.relative[i]), atol=1e-12)


def test_one_keyframe_and_no_scan():
    assert KeyframeStore().scan_poses(np.zeros((0, 3))).shape == (0, 3)
    odom = _straight(4)
    store = _store(odom, [0])
    est = np.array([[1.0, 2.0, 0.5]])
    expected = np.array([compose(est[0], store.scans.relative[i]) for i in range(4)])
    np.testing.assert_allclose(store.scan_poses(est), expected, atol=1e-12)
