"""The wheel-to-scan time offset the odometry learns (ScanOdometry._retime / _learn_offset)."""

from __future__ import annotations

import numpy as np
import pytest
from frslam_graph.datasets import open_recording

from frslam_graph.config import OdometryConfig
from frslam_graph.evaluation.relations import relation_error
from frslam_graph.evaluation.trajectory_io import load_relations
from frslam_graph.odometry.scan_odometry import ScanOdometry
from frslam_graph.slam import body_points


@pytest.fixture(scope="module")
def fr079_250(test_data):
    scans = []
    for s in open_recording(test_data / "fr079_250.clf.bz2"):
        pts, _ = body_points(s.points, s.sensor_offset)
        scans.append((s.stamp, pts, s.odom))
    return scans, load_relations(test_data / "fr079_250.relations")


def _run(scans, learn: bool) -> tuple[np.ndarray, float]:
    odo = ScanOdometry(OdometryConfig())
    if not learn:
        odo._learn_offset = lambda *args: None  # the offset stays 0: the wheel poses as logged
    rows = [(stamp, *odo.process(stamp, pts, odom).pose) for stamp, pts, odom in scans]
    return np.array(rows), odo._offset


@pytest.mark.parametrize("k", [1, 2, 3])
def test_fr079_wheel_poses_lead_the_scans_by_a_tenth_of_a_second(fr079_250, k):
    """FR079's logger pairs each scan with the wheel pose at the scan's stamp, but the scan was
    taken ~0.1 s earlier (the whole log's scan-matched heading steps agree best with the wheel
    poses 0.10-0.12 s before theirs): the odometry finds the same offset at every scan rate."""
    scans, _ = fr079_250
    _, offset = _run(scans[::k], learn=True)
    assert -0.15 < offset < -0.08


def test_retimed_wheel_poses_keep_the_heading_at_half_the_scan_rate(fr079_250):
    """Every second scan of FR079's first 250: the wheel increments, 0.42 s apart, carry
    offset x (change of turn rate) in heading, which KISS-ICP keeps from its seed; re-timed, the
    relations' rotation error is 0.72 -> 0.41 deg (all scans: 0.22 / 0.24)."""
    scans, rel = fr079_250
    thin = scans[::2]
    as_logged = relation_error(_run(thin, learn=False)[0], rel, interpolate=6.0)
    retimed = relation_error(_run(thin, learn=True)[0], rel, interpolate=6.0)
    assert retimed.matched == as_logged.matched == 51
    assert retimed.rot_mean < 0.7 * as_logged.rot_mean
    assert retimed.trans_mean < as_logged.trans_mean
