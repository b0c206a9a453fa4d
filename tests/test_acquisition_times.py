"""Odometry paired with scans at their acquisition times when a recording stamps messages on arrival.

The Intel recording (``intel.clf``, ``intel.bag``) stamps ODOM (10 Hz) and laser (5 Hz) messages
when the logger received them, in bursts (ODOM's median gap 0.9 ms). Interpolating the ODOM records
at the scan stamps then pairs a scan with the wrong wheel pose (up to 50° off in a turn). The
logger's own pairing (the robot pose written in each FLASER line: the ODOM record received just
before the scan) is the reference: `tests/data/intel_turns.clf.bz2` is 30 s of that log while
turning (its ODOM / FLASER records 444-893, CARMEN's header kept: 152 scans, 298 ODOM).
"""

from __future__ import annotations

import bz2
import warnings

import numpy as np
import pytest
from frslam_graph.datasets import RecordingWarning, open_recording
from frslam_graph.datasets.recording import PoseInterpolator, acquisition_times, stream_period

from tests.test_rosbag import LASER, ODOM, Msgs, write_bag


def _yaw_steps(poses) -> np.ndarray:
    """|heading change| between consecutive poses, degrees."""
    p = np.asarray(poses, dtype=np.float64)
    return np.degrees(np.angle(np.exp(1j * np.diff(p[:, 2]))))


def _disagreement(poses, reference) -> float:
    """Mean |difference| of the heading steps of two pose sequences (deg)."""
    return float(np.mean(np.abs(_yaw_steps(poses) - _yaw_steps(reference))))


def _bursty(n: int, period: float, rng: np.random.Generator, drop: float = 0.0):
    """True times of a steady stream (some dropped) and arrival stamps: bursts released together."""
    true = np.arange(n) * period
    true = true[rng.random(n) >= drop]
    release = np.cumsum(rng.exponential(0.6, size=n))  # the receiver's bursts, 0.6 s apart on average
    arrival = release[np.searchsorted(release, true)] + rng.uniform(0.0, 0.002, true.size)
    return true, arrival


def test_a_bursty_stream_is_retimed_to_its_steady_clock():
    rng = np.random.default_rng(1)
    true, arrival = _bursty(600, 0.1, rng, drop=0.02)
    late = arrival - true
    assert np.median(late) > 0.3  # stamps late by 3+ periods at median, their steps off by 0.1 s
    est = acquisition_times(arrival)
    assert est is not None
    assert np.all(est <= arrival)
    err = est - true
    assert np.median(np.abs(err)) < 0.05  # 0.04 s (a drop reads as a slower clock: 2 % here)
    assert np.median(np.abs(np.diff(err))) < 0.005 < np.median(np.abs(np.diff(late)))  # the steps
    assert stream_period(arrival) == pytest.approx(0.1, rel=0.05)


def test_steady_or_varying_stamps_are_kept():
    rng = np.random.default_rng(2)
    stamps = np.arange(500) * 0.05 + rng.normal(0.0, 0.002, 500)  # 20 Hz, 2 ms jitter
    stamps = np.delete(stamps, [40, 41, 200])  # drops do not make a stream bursty
    assert acquisition_times(stamps) is None
    varying = np.cumsum(rng.uniform(0.5, 1.9, 500) * 0.17)  # ACES: a varying rate, not bursts
    assert acquisition_times(varying) is None
    assert acquisition_times(np.array([0.0, 0.1])) is None


def test_carmen_odom_records_follow_the_laser_lines_pairing(test_data):
    path = test_data / "intel_turns.clf.bz2"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        laser = [s.odom for s in open_recording(path)]  # the logger's pairing
        rec = open_recording(path, odom="odom")
        paired = [s.odom for s in rec]
        at_stamps = PoseInterpolator(rec.odometry(), 0.5)
        before = [at_stamps(s.stamp) for s in rec]  # what the reader did before
    assert _disagreement(before, laser) > 1.0  # 1.35° a scan
    assert _disagreement(paired, laser) < 0.3  # 0.20°
    assert np.mean(np.hypot(*(np.array(paired)[:, :2] - np.array(laser)[:, :2]).T)) < 0.004


def _bag_from_carmen(path, out, ros1=True):
    """A ROS 1 bag as intel.bag was made: /scan and /odom with the CARMEN stamps, ``header.seq`` in
    file order per topic, stored in stamp order (``ros1`` False: a ROS 2 bag, whose headers carry
    no seq, as ``rosbags-convert`` makes of intel.bag)."""
    m = Msgs(ros1=ros1)
    msgs, seqs = [], {"/scan": 0, "/odom": 0}
    for line in _lines(path):
        tok = line.split()
        if tok[0] == "ODOM":
            topic, stamp = "/odom", float(tok[-3])
            msg = m.odom(stamp, float(tok[1]), float(tok[2]), float(tok[3]))
        elif tok[0] == "FLASER":
            n = int(tok[1])
            topic, stamp = "/scan", float(tok[-3])
            msg = m.scan(stamp, [float(v) for v in tok[2 : 2 + n]], -np.pi / 2, np.pi / 180, 0.0, 81.9)
        else:
            continue
        if ros1:
            msg.header.seq = seqs[topic]
            seqs[topic] += 1
        msgs.append((topic, LASER if topic == "/scan" else ODOM, stamp, msg))
    msgs.sort(key=lambda x: x[2])
    return write_bag(out, msgs, ros1=ros1)


def _lines(path):
    with bz2.open(path, "rt") as f:
        yield from (line for line in f if line.strip() and not line.startswith("#"))


def test_bag_odometry_follows_the_laser_lines_pairing(test_data, tmp_path):
    path = test_data / "intel_turns.clf.bz2"
    bag = _bag_from_carmen(path, tmp_path / "intel_turns.bag")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RecordingWarning)
        laser = [s.odom for s in open_recording(path)]
        rec = open_recording(bag)
        scans = list(rec)
    assert [s.stamp for s in scans] == pytest.approx(_scan_stamps(path), abs=1e-6)  # file order
    paired = [s.odom for s in scans]
    at_stamps = PoseInterpolator(rec.odometry(), 0.5)
    before = [at_stamps(s.stamp) for s in scans]  # what the reader did before
    assert _disagreement(before, laser) > 0.5  # 0.55° a scan
    assert _disagreement(paired, laser) < 0.3
    assert any("stamped on arrival in bursts" in str(w.message) for w in caught)


def test_a_bursty_ros2_bag_says_its_scan_order_is_unknown(test_data, tmp_path):
    """Stamped on arrival, the excerpt's scans are stored out of the order they were taken in;
    a ROS 1 bag puts them back by header.seq, a ROS 2 bag has none: its bag order is yielded
    as it is (nothing in it tells the order), and the reader says so."""
    path = test_data / "intel_turns.clf.bz2"
    file_order = _scan_stamps(path)
    said = {}
    for ros1, name in ((True, "excerpt.bag"), (False, "excerpt_ros2")):
        bag = _bag_from_carmen(path, tmp_path / name, ros1=ros1)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RecordingWarning)
            stamps = [s.stamp for s in open_recording(bag)]
        said[ros1] = " ".join(str(w.message) for w in caught)
        assert sorted(stamps) == pytest.approx(sorted(file_order), abs=1e-6)  # every scan kept
        if ros1:
            assert stamps == pytest.approx(file_order, abs=1e-6)
        else:
            assert stamps != pytest.approx(file_order, abs=1e-6)  # the bag (stamp) order
    assert "stamped on arrival in bursts" in said[True] and "without header.seq" not in said[True]
    assert "stamped on arrival without header.seq (ROS 2)" in said[False]


def _scan_stamps(path):
    return [float(line.split()[-3]) for line in _lines(path) if line.startswith("FLASER")]


def test_shared_intel_bag_pairs_odometry_like_the_carmen_log(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        laser = [s.odom for s in open_recording(shared_data / "carmen" / "intel.clf.bz2")]
        paired = [s.odom for s in open_recording(shared_data / "bags" / "intel.bag")]
    assert len(paired) == len(laser) == 13631
    # interpolated at the scan stamps: 0.53° a scan, p99 11.5°, max 51°; now 0.26°, p99 1.9°
    d = np.abs(_yaw_steps(paired) - _yaw_steps(laser))
    assert d.mean() < 0.3 and np.percentile(d, 99) < 2.5
