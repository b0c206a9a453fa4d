"""CARMEN log reader: record types, angles, odometry, compression, bad input, the shared logs in full."""

from __future__ import annotations

import bz2
import gzip
import math
import warnings

import numpy as np
import pytest
from frslam_graph.datasets import RecordingWarning, open_recording
from frslam_graph.datasets.carmen import CarmenLog, carmen_angle_increment

from frslam_graph.errors import RecordingError

HEADER = "# CARMEN Logfile\n# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp\n"


def flaser(ranges, stamp, robot=(0.0, 0.0, 0.0), laser=None, kind="FLASER"):
    laser = robot if laser is None else laser
    r = " ".join(f"{v}" for v in ranges)
    pose = " ".join(f"{v:.6f}" for v in (*laser, *robot))
    return f"{kind} {len(ranges)} {r} {pose} {stamp:.6f} host {stamp - 100:.6f}\n"


def odom_line(x, y, th, stamp):
    return f"ODOM {x:.6f} {y:.6f} {th:.6f} 0.0 0.0 0.0 {stamp:.6f} host {stamp - 100:.6f}\n"


def robotlaser(ranges, stamp, start=-2.0, fov=4.0, res=0.01, max_range=30.0, robot=(1.0, 2.0, 0.5), kind=1):
    r = " ".join(f"{v}" for v in ranges)
    pose = " ".join(f"{v:.6f}" for v in (*robot, *robot))
    return (
        f"ROBOTLASER{kind} 0 {start} {fov} {res} {max_range} 0.01 0 {len(ranges)} {r} 2 7 8 {pose} "
        f"0.1 0.2 0.3 0.4 0.5 {stamp:.6f} host {stamp - 100:.6f}\n"
    )


def write(tmp_path, text, name="log.clf"):
    p = tmp_path / name
    if name.endswith(".gz"):
        with gzip.open(p, "wt") as f:
            f.write(text)
    elif name.endswith(".bz2"):
        with bz2.open(p, "wt") as f:
            f.write(text)
    else:
        p.write_text(text)
    return p


def read_all(rec):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        scans = list(rec)
    return scans, [str(w.message) for w in got if issubclass(w.category, RecordingWarning)]


def simple_log(n=5):
    lines = [HEADER, "PARAM robot_frontlaser_offset 0.0 nohost 0\n"]
    for i in range(n):
        lines.append(odom_line(0.1 * i, 0.0, 0.0, 10.0 + i - 0.05))
        lines.append(flaser([1.0 + i] * 180, 10.0 + i, robot=(0.1 * i, 0.0, 0.0)))
    return "".join(lines)


def test_angle_increment_follows_carmen_convention():
    assert carmen_angle_increment(180) == pytest.approx(math.pi / 180)
    assert carmen_angle_increment(181) == pytest.approx(math.pi / 180)
    assert carmen_angle_increment(360) == pytest.approx(math.pi / 360)
    assert carmen_angle_increment(361) == pytest.approx(math.pi / 360)
    assert carmen_angle_increment(401) == pytest.approx(math.pi / 720)
    assert carmen_angle_increment(91) == pytest.approx(math.pi / 90)  # 180° over n - 1 steps


@pytest.mark.parametrize("name", ["log.clf", "log.log", "log.clf.gz", "log.clf.bz2"])
def test_flaser_scans_plain_and_compressed(tmp_path, name):
    rec = open_recording(write(tmp_path, simple_log(), name), odom="laser")  # the lines' own poses
    assert isinstance(rec, CarmenLog)
    assert len(rec) == 5
    scans, warns = read_all(rec)
    assert warns == []
    assert [s.stamp for s in scans] == pytest.approx([10.0, 11.0, 12.0, 13.0, 14.0])
    s = scans[2]
    assert s.ranges.shape == (180,) and np.allclose(s.ranges, 3.0)
    assert s.angles[0] == pytest.approx(-math.pi / 2)
    assert s.angles[-1] == pytest.approx(math.pi / 2 - math.pi / 180)
    assert s.odom == pytest.approx((0.2, 0.0, 0.0))
    assert rec.stats.records["FLASER"] == 5 and rec.stats.records["ODOM"] == 5
    assert rec.odometry().shape == (5, 4)
    # first beam points to the robot's right (-y), the middle one forward
    assert s.points[0] == pytest.approx([0.0, -3.0], abs=1e-9)
    assert s.points[90] == pytest.approx([3.0, 0.0], abs=1e-9)


def test_sensor_offset_from_laser_and_robot_pose(tmp_path):
    # robot at (1, 1) facing +y; laser 0.04 m behind it (FR079's robot_frontlaser_offset -0.04)
    robot = (1.0, 1.0, math.pi / 2)
    laser = (1.0, 0.96, math.pi / 2)
    p = write(tmp_path, HEADER + flaser([2.0] * 360, 5.0, robot=robot, laser=laser))
    (scan,), _ = read_all(open_recording(p))
    assert scan.sensor_offset == pytest.approx((-0.04, 0.0, 0.0), abs=1e-6)
    assert scan.odom == pytest.approx(robot)
    assert scan.angles[1] - scan.angles[0] == pytest.approx(math.pi / 360)


def test_robotlaser1_carries_its_own_geometry(tmp_path):
    ranges = [1.0, 2.0, 35.0, 3.0]
    p = write(tmp_path, HEADER + robotlaser(ranges, 7.0))
    rec = open_recording(p)
    (scan,), _ = read_all(rec)
    assert scan.angles == pytest.approx([-2.0, -1.99, -1.98, -1.97])
    assert scan.max_range == 30.0
    assert np.isnan(scan.ranges[2]) and scan.ranges[3] == 3.0  # 35 m >= max range 30 m
    assert scan.stamp == 7.0 and scan.odom == pytest.approx((1.0, 2.0, 0.5))
    (wide,), _ = read_all(open_recording(p, max_range=40.0))  # an explicit max range wins
    assert wide.ranges[2] == 35.0 and wide.max_range == 40.0


def test_rear_lasers_selected_on_request_and_reported_otherwise(tmp_path):
    text = (
        HEADER + flaser([1.0] * 180, 1.0) + flaser([2.0] * 180, 1.5, kind="RLASER") + flaser([1.0] * 180, 2.0)
    )
    p = write(tmp_path, text)
    scans, warns = read_all(open_recording(p))
    assert len(scans) == 2
    assert len(warns) == 1 and "RLASER records not selected" in warns[0]
    rear, warns = read_all(open_recording(p, laser="rear"))
    assert len(rear) == 1 and rear[0].stamp == 1.5
    assert len(open_recording(p, laser="all")) == 3


def test_odometry_interpolated_from_odom_records(tmp_path):
    # ODOM at t = 0 .. 4 moving along x at 1 m/s and turning across +-pi; scans in between
    lines = [HEADER]
    for i in range(5):
        th = math.pi - 0.2 + 0.1 * i  # crosses +pi between i = 2 and i = 3
        lines.append(odom_line(float(i), 0.0, math.atan2(math.sin(th), math.cos(th)), float(i)))
    lines.append(flaser([1.0] * 180, 2.5, robot=(99.0, 99.0, 0.0)))
    lines.append(flaser([1.0] * 180, 9.0, robot=(99.0, 99.0, 0.0)))  # far beyond the ODOM records
    p = write(tmp_path, "".join(lines))
    scans, warns = read_all(open_recording(p, odom="odom"))
    x, y, th = scans[0].odom
    assert x == pytest.approx(2.5) and y == pytest.approx(0.0)
    assert th == pytest.approx(math.atan2(math.sin(math.pi + 0.05), math.cos(math.pi + 0.05)))
    assert scans[1].odom is None
    assert any("outside the ODOM records" in w for w in warns)
    from_laser, _ = read_all(open_recording(p, odom="laser"))
    assert from_laser[0].odom == (99.0, 99.0, 0.0)
    none, _ = read_all(open_recording(p, odom="none"))
    assert none[0].odom is None


def _moving_log(copied: bool, backwards: bool = False) -> str:
    """ODOM at 10 Hz of a robot driving along x at 1 m/s and turning at 1 rad/s; a scan every
    0.25 s whose robot pose is the last ODOM record (``copied``, as ACES and Intel log it) or the
    pose at the scan's stamp (as FR079's logger interpolates it); ``backwards``: one scan stamped
    before its predecessor (Intel)."""
    lines, last = [HEADER], None
    for k in range(41):
        t = 10.0 + 0.1 * k
        lines.append(odom_line(t - 10.0, 0.0, math.atan2(math.sin(t), math.cos(t)), t))
        last = (t - 10.0, 0.0, math.atan2(math.sin(t), math.cos(t)))
        if k % 5 == 2:
            ts = t + 0.05
            if backwards and k == 22:
                ts = t - 0.6
            robot = last if copied else (ts - 10.0, 0.0, math.atan2(math.sin(ts), math.cos(ts)))
            lines.append(flaser([1.0] * 180, ts, robot=robot))
    return "".join(lines)


def test_copied_laser_poses_are_replaced_by_odom_interpolated_at_the_stamps(tmp_path):
    """A laser line that copies the last ODOM record carries a pose up to one ODOM period old
    (ACES: 5-12 deg while turning): with trustworthy stamps the ODOM records are interpolated at
    the scan's stamp instead; the choice and its reason are reported."""
    rec = open_recording(write(tmp_path, _moving_log(copied=True)), odom="auto")
    assert rec.odom_source == "odom" and "interpolated" in rec.odom_reason
    scans, _ = read_all(rec)
    for s in scans:
        assert s.odom[0] == pytest.approx(s.stamp - 10.0, abs=1e-6)
        assert s.odom[2] == pytest.approx(math.atan2(math.sin(s.stamp), math.cos(s.stamp)), abs=1e-6)
    default, _ = read_all(open_recording(write(tmp_path, _moving_log(copied=True))))
    assert [d.odom for d in default] == [d.odom for d in scans]  # "auto" is the default
    copied, _ = read_all(open_recording(write(tmp_path, _moving_log(copied=True)), odom="laser"))
    assert copied[1].odom[0] == pytest.approx(copied[1].stamp - 10.0 - 0.05, abs=1e-6)


def test_laser_poses_kept_when_stamps_go_backwards_or_the_logger_interpolated(tmp_path):
    """Stamps that go backwards cannot place a scan between ODOM records (Intel: by up to 0.9 s;
    its file order is the better clock): the copied pose stays. A pose the logger interpolated
    (FR079) stays too."""
    jittery = open_recording(write(tmp_path, _moving_log(copied=True, backwards=True), "j.clf"), odom="auto")
    assert jittery.odom_source == "laser" and "earlier than an earlier one" in jittery.odom_reason
    scans, _ = read_all(jittery)
    assert scans[4].stamp < scans[3].stamp
    assert scans[4].odom[0] == pytest.approx(2.2, abs=1e-6)  # the last ODOM record before it
    fresh = open_recording(write(tmp_path, _moving_log(copied=False), "f.clf"), odom="auto")
    assert fresh.odom_source == "laser" and "interpolated by the logger" in fresh.odom_reason


def test_invalid_ranges_become_nan_and_are_counted(tmp_path):
    ranges = ["1.0", "nan", "inf", "-1.0", "0.0", "80.0", "81.83", "2.0"]
    p = write(tmp_path, HEADER + flaser(ranges, 1.0))
    rec = open_recording(p)
    (scan,), warns = read_all(rec)
    assert np.isnan(scan.ranges).tolist() == [False, True, True, True, True, True, True, False]
    assert rec.stats.invalid_beams == 6 and rec.stats.beams == 8
    assert len(scan.points) == 2
    assert len(warns) == 1 and "NaN/inf/negative" in warns[0] and "log.clf:3" in warns[0]


def test_saturation_value_detected_as_max_range(tmp_path):
    rng = np.random.default_rng(0)
    lines = [HEADER]
    for i in range(20):
        r = np.round(rng.uniform(1, 40, 180), 2)
        r[::10] = 50.0  # the ACES log's "no return"
        lines.append(flaser(r.tolist(), float(i)))
    rec = open_recording(write(tmp_path, "".join(lines)))
    assert rec.max_range == 50.0 and "saturation" in rec.max_range_source
    scans, _ = read_all(rec)
    assert rec.stats.invalid_beams == 20 * 18
    assert open_recording(write(tmp_path, "".join(lines)), max_range=60.0).max_range == 60.0


def test_cut_mid_line_is_skipped_with_file_and_line(tmp_path):
    text = simple_log(3) + flaser([1.0] * 180, 20.0)[:300]  # no newline: the log was cut
    rec = open_recording(write(tmp_path, text))
    assert len(rec) == 3
    scans, warns = read_all(rec)
    assert len(scans) == 3
    assert len(warns) == 1 and "cut short at end of file" in warns[0] and "log.clf:10" in warns[0]
    assert rec.stats.skipped["laser record cut short at end of file"] == 1


def test_truncated_compressed_stream_keeps_what_was_read(tmp_path):
    full = write(tmp_path, simple_log(200), "full.clf.gz").read_bytes()
    p = tmp_path / "cut.clf.gz"
    p.write_bytes(full[: len(full) // 2])
    rec = open_recording(p)
    scans, warns = read_all(rec)
    assert 0 < len(scans) == len(rec) < 200
    assert [s.stamp for s in scans] == pytest.approx(10.0 + np.arange(len(scans)))
    assert len(warns) == 1 and "rest of file unreadable" in warns[0] and "cut.clf.gz:" in warns[0]
    # bzip2 decodes whole 900 kB blocks: a small log cut in its only block has nothing left
    full = write(tmp_path, simple_log(200), "full.clf.bz2").read_bytes()
    p = tmp_path / "cut.clf.bz2"
    p.write_bytes(full[: len(full) // 2])
    with pytest.raises(RecordingError, match=r"cut.clf.bz2: no FLASER.*rest of file unreadable"):
        open_recording(p)


def test_wrong_field_count_and_non_numeric_field_skipped(tmp_path):
    bad_count = flaser([1.0] * 180, 3.0).replace("FLASER 180", "FLASER 181")
    bad_value = flaser([1.0] * 180, 4.0).replace(" 1.0 ", " 1.0x ", 1)
    text = HEADER + flaser([1.0] * 180, 1.0) + bad_count + bad_value + flaser([1.0] * 180, 5.0)
    rec = open_recording(write(tmp_path, text))
    scans, warns = read_all(rec)
    assert [s.stamp for s in scans] == [1.0, 5.0]
    assert rec.stats.skipped["malformed laser record (expected 192 fields, found 191)"] == 1
    assert rec.stats.skipped["laser record with a non-numeric field"] == 1
    assert "log.clf:4" in warns[0] and "log.clf:5" in warns[0]


def test_unknown_record_type_counted_known_ones_silent(tmp_path):
    text = simple_log(2) + "SYNC tag 1.0 host 0\nBOGUS 1 2 3 4.0 host 0\nTRUEPOS 1 2 3 4 5 6 4.0 host 0\n"
    rec = open_recording(write(tmp_path, text))
    scans, warns = read_all(rec)
    assert len(scans) == 2
    assert rec.stats.skipped == {"unknown record type 'BOGUS'": 1}
    assert len(warns) == 1 and "BOGUS" in warns[0] and "log.clf:9" in warns[0]


def test_stamps_going_backwards_keep_skip_error(tmp_path):
    stamps = [1.0, 2.0, 1.5, 3.0, 2.5, 4.0]
    p = write(tmp_path, HEADER + "".join(flaser([1.0] * 180, t) for t in stamps))
    kept, warns = read_all(open_recording(p))
    assert [s.stamp for s in kept] == stamps
    assert (
        "2 scans stamped before an earlier scan (kept in file order)" in warns[0] and "log.clf:5" in warns[0]
    )
    skipped, warns = read_all(open_recording(p, backwards="skip"))
    assert [s.stamp for s in skipped] == [1.0, 2.0, 3.0, 4.0]
    assert "2 skipped" in warns[0]
    with pytest.raises(RecordingError, match=r"log.clf: line 5: stamp 1.500000"):
        list(open_recording(p, backwards="error"))


def test_missing_empty_and_scanless_logs_rejected(tmp_path):
    with pytest.raises(RecordingError, match="nope.clf: no such file"):
        open_recording(tmp_path / "nope.clf")
    with pytest.raises(RecordingError, match="empty.clf: no FLASER/ROBOTLASER1 laser records"):
        open_recording(write(tmp_path, "", "empty.clf"))
    with pytest.raises(RecordingError, match="ODOM 1"):
        open_recording(write(tmp_path, HEADER + odom_line(0, 0, 0, 1.0), "odom_only.clf"))
    with pytest.raises(RecordingError, match="takes no option"):
        open_recording(write(tmp_path, simple_log(), "x.clf"), scan_topic="/scan")


def test_intel_excerpt(test_data):
    """First 200 lines of the Intel Research Lab log (Radish, CC-BY)."""
    path = test_data / "intel_head.clf.bz2"
    with bz2.open(path, "rt") as f:
        text = f.read().splitlines()
    n_flaser = sum(line.startswith("FLASER ") for line in text)
    n_odom = sum(line.startswith("ODOM ") for line in text)
    rec = open_recording(path)
    scans, warns = read_all(rec)
    assert len(rec) == len(scans) == n_flaser > 50
    assert rec.stats.records["ODOM"] == n_odom
    assert all(s.ranges.size == 180 for s in scans)
    assert scans[0].stamp == pytest.approx(976052857.3375, abs=1e-3)
    assert scans[0].ranges[0] == pytest.approx(1.07)


def test_inspect_command(test_data, capsys):
    from frslam_graph.cli import main

    assert main(["inspect", str(test_data / "intel_head.clf.bz2")]) == 0
    out = capsys.readouterr().out
    assert "FLASER" in out and "scans/s" in out and "180" in out


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, beams",
    [("intel", 180), ("fr079", 360), ("aces", 180)],
)
def test_shared_logs_read_in_full(shared_data, name, beams):
    path = shared_data / "carmen" / f"{name}.clf.bz2"
    with bz2.open(path, "rt", encoding="latin-1") as f:
        counts = {"FLASER": 0, "ODOM": 0}
        for line in f:
            key = line.split(" ", 1)[0]
            if key in counts:
                counts[key] += 1
    rec = open_recording(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        n = sum(1 for s in rec if s.ranges.size == beams and s.odom is not None)
    assert n == len(rec) == counts["FLASER"]
    assert rec.stats.records["ODOM"] == counts["ODOM"]
    assert sum(rec.stats.skipped.values()) == 0
    if name == "intel":
        assert n == 13631


def test_intel_excerpt_backwards_stamps_all_kept_by_the_backend(test_data):
    """The Intel log stamps scans in bursts, some before their predecessor (its line 90 is the
    first): the backend keeps every scan, one pose per scan at its own stamp, in file order."""
    from frslam_graph.offline import process
    from frslam_graph.slam import FRSlam

    rec = open_recording(test_data / "intel_head.clf.bz2")
    scans, _ = read_all(rec)
    stamps = np.array([s.stamp for s in scans])
    assert np.count_nonzero(np.diff(stamps) < 0) >= 1
    traj = process(FRSlam(), scans, parallel=False).trajectory
    np.testing.assert_array_equal(traj[:, 0], stamps)
    assert np.all(np.isfinite(traj[:, 1:]))


def test_fr079_excerpt_laser_offset_and_no_return_beams(test_data):
    """First 20 FLASER lines of the FR079 log: its laser sits 0.04 m behind the robot's centre
    (the laser pose of each line, PARAM robot_frontlaser_offset -0.04) and 81.91 m readings mean
    "no return" (above PARAM robot_front_laser_max 80.99): they become nan, never wall points."""
    path = test_data / "fr079_head.clf.bz2"
    rec = open_recording(path)
    scans, _ = read_all(rec)
    assert len(scans) == 20 and all(s.ranges.size == 360 for s in scans)
    assert rec.max_range == pytest.approx(80.99)
    for s in scans:
        assert s.sensor_offset[0] == pytest.approx(-0.04, abs=2e-3)
        assert abs(s.sensor_offset[1]) < 2e-3 and abs(s.sensor_offset[2]) < 1e-6
    with bz2.open(path, "rt") as f:
        raw = [line.split() for line in f if line.startswith("FLASER ")]
    no_return = np.array([np.array(t[2:362], dtype=float) >= 81.9 for t in raw])
    assert no_return.sum() >= 10
    ranges = np.array([s.ranges for s in scans])
    assert np.all(np.isnan(ranges[no_return])) and np.all(np.isfinite(ranges[~no_return]))
    assert all(np.hypot(*s.points.T).max() < 80.0 for s in scans)
