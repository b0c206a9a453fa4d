"""The wheel-to-scan time offset (odometry/time_offset.py): estimated from the heading steps,
applied only where its confidence interval excludes 0."""

from __future__ import annotations

import numpy as np
import pytest
from frslam_graph.datasets import open_recording
from synthetic_world import room_world, scans_along, to_points

from frslam_graph.config import OdometryConfig
from frslam_graph.odometry import time_offset
from frslam_graph.odometry.scan_odometry import ScanOdometry
from frslam_graph.se2 import between, wrap
from frslam_graph.slam import body_points

CFG = OdometryConfig(max_range=10.0)
RATE = 10.0  # Hz
N = 700  # scans: 28 blocks of the estimate's uncertainty


def _pose(t: np.ndarray) -> np.ndarray:
    """(N, 3) a robot circling (r 1.5 m, 40 s a lap) around the room's middle while its heading
    swings ±0.8 rad every 6 s: the turn rate changes by up to 0.08 rad/s between 10 Hz scans."""
    a = 2.0 * np.pi * t / 40.0
    th = a + 0.8 * np.sin(2.0 * np.pi * t / 6.0)
    return np.column_stack((6.0 + 1.5 * np.cos(a), 4.0 + 1.5 * np.sin(a), wrap(th)))


def _wheels(t: np.ndarray, seed: int = 3) -> np.ndarray:
    """Wheel poses at ``t``: 2 % scale error and 0.3° of white heading noise per step (the noise
    that biases a least-squares fit of the offset: it enters the rate change and the residual)."""
    truth = _pose(t)
    rng = np.random.default_rng(seed)
    out = np.zeros_like(truth)
    out[0] = truth[0]
    for i in range(1, len(t)):
        u = between(truth[i - 1], truth[i])
        u[:2] *= 1.02
        u[2] += rng.normal(0.0, np.deg2rad(0.3))
        c, s = np.cos(out[i - 1, 2]), np.sin(out[i - 1, 2])
        out[i] = (
            out[i - 1, 0] + c * u[0] - s * u[1],
            out[i - 1, 1] + s * u[0] + c * u[1],
            out[i - 1, 2] + u[2],
        )
    out[:, 2] = wrap(out[:, 2])
    return out


@pytest.fixture(scope="module")
def swing():
    """Stamps, scan points at the stamps' true poses, true poses."""
    stamps = np.arange(N) / RATE
    truth = _pose(stamps)
    ranges, amin, inc = scans_along(room_world(), np.column_stack((stamps, truth)))
    return stamps, [to_points(r, amin, inc) for r in ranges], truth


def _run(stamps, points, wheels) -> tuple[ScanOdometry, np.ndarray]:
    odo = ScanOdometry(CFG)
    poses = np.array([odo.process(t, p, w).pose for t, p, w in zip(stamps, points, wheels, strict=True)])
    return odo, poses


def _heading_step_error(poses: np.ndarray, truth: np.ndarray) -> float:
    """Mean absolute error of the heading steps (deg)."""
    return float(np.rad2deg(np.mean(np.abs(wrap(np.diff(poses[:, 2]) - np.diff(truth[:, 2]))))))


@pytest.mark.parametrize("lag", [-0.1, -0.05])
def test_a_known_lag_is_found_and_the_wheel_poses_retimed(swing, lag):
    """Each scan shows the robot the wheels put ``lag`` s after the scan's stamp (FR079: -0.13 s,
    the scan taken before its stamp). The estimate finds it within 0.015 s, its confidence
    interval excludes 0 so it is applied, and the wheel steps re-timed by it follow the true
    steps (the odometry's seeds) more closely."""
    stamps, points, truth = swing
    wheels = _wheels(stamps - lag)  # the pose logged at t is the robot at t - lag
    odo, _ = _run(stamps, points, wheels)
    st = odo.stats
    assert abs(st.time_offset - lag) < 0.015
    assert st.time_offset_applied == st.time_offset
    assert abs(st.time_offset) > 4.0 * st.time_offset_sigma
    retimed = np.array(
        [wheels[0]]
        + [odo._toff.retime(wheels[i], between(wheels[i - 1], wheels[i]), 1.0 / RATE) for i in range(1, N)]
    )
    assert _heading_step_error(retimed, truth) < 0.75 * _heading_step_error(wheels, truth)


@pytest.mark.parametrize(("lag", "found"), [(0.0, False), (0.06, True)])
def test_without_a_negative_lag_nothing_is_retimed(swing, lag, found, monkeypatch):
    """Wheel poses of the scans' own instants, with white heading noise per step: least squares
    would find a spurious negative offset (-0.02 s on the simulator); the instrumented estimate
    stays within its confidence interval of 0. A positive lag (ACES's laser lines copy an older
    wheel pose) is found but not applied: the wheel pose of the scan's instant is not logged yet.
    Either way nothing is re-timed: the odometry is the same, bit for bit, as one that never
    estimates an offset."""
    stamps, points, _ = swing
    wheels = _wheels(stamps - lag)
    odo, poses = _run(stamps, points, wheels)
    st = odo.stats
    assert st.time_offset_applied == 0.0
    assert abs(st.time_offset - lag) < 0.015
    assert (abs(st.time_offset) > 4.0 * st.time_offset_sigma) == found
    monkeypatch.setattr(time_offset, "MIN_BLOCKS", 10**9)  # never applied
    _, as_logged = _run(stamps, points, wheels)
    np.testing.assert_array_equal(poses, as_logged)


def test_least_squares_would_be_biased(swing):
    """Why the regressor is instrumented: on the same steps (truth as the scan-matched heading),
    the plain least-squares offset is pulled negative by the wheels' step noise, the instrumented
    one is not."""
    stamps, _, truth = swing
    wheels = _wheels(stamps)
    r = wrap(np.diff(wheels[:, 2])) * RATE
    y = wrap(np.diff(truth[:, 2]) - np.diff(wheels[:, 2]))
    x, z, yy = r[2:-1] - r[1:-2], r[3:] - r[:-3], y[2:-1]
    ls, iv = (x @ yy) / (x @ x), (z @ yy) / (z @ x)
    assert ls < -0.01 and abs(iv) < 0.5 * abs(ls)
    est = time_offset.WheelTimeOffset()
    for rate, res in zip(r, y, strict=True):
        est.add(rate, res)
    assert est.blocks == (len(r) - 3) // time_offset.BLOCK
    assert est.estimate == pytest.approx((z @ yy) / (z @ x), abs=0.01)


def test_fr079_excerpt_shows_its_lag(test_data):
    """FR079's first 250 scans (its laser lines carry the wheel pose of their stamp; the scan was
    taken earlier): -0.17 ± 0.02 s already, not yet applied (9 blocks, fewer than MIN_BLOCKS;
    the whole log: -0.143 ± 0.002 s, applied)."""
    odo = ScanOdometry(OdometryConfig())
    for s in open_recording(test_data / "fr079_250.clf.bz2"):
        odo.process(s.stamp, body_points(s.points, s.sensor_offset)[0], s.odom)
    st = odo.stats
    assert -0.22 < st.time_offset < -0.1
    assert abs(st.time_offset) > 4.0 * st.time_offset_sigma
    assert st.time_offset_applied == 0.0
