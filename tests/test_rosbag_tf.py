"""A bag's tf: the laser's mount on the robot (offset, yaw, upside down), odometry given as tf only; multi-echo scans."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from frslam_graph.datasets import open_recording
from frslam_graph.datasets.rosbag import RosBag
from frslam_graph.datasets.tf_frames import FrameTree, planar_mount, transform_matrix
from rosbags.typesys import get_types_from_msg
from test_rosbag import LASER, ODOM, Msgs, read_all, write_bag

from frslam_graph.cli import main
from frslam_graph.errors import OptionError

TF = "tf2_msgs/msg/TFMessage"
MULTI = "sensor_msgs/msg/MultiEchoLaserScan"
OLD_TF = "tf/msg/tfMessage"  # ROS 1 before tf2 (2010-era bags)
TF_TYPES = {
    **get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF),  # not in the Noetic store
    **get_types_from_msg("geometry_msgs/TransformStamped[] transforms", OLD_TF),
}


def missing_tf_types(ros1: bool) -> dict:
    """The tf message types the test typestore of ``ros1`` lacks."""
    have = Msgs(ros1).ts.fielddefs
    return {k: v for k, v in TF_TYPES.items() if k not in have}


def msgs(ros1: bool) -> Msgs:
    m = Msgs(ros1)
    m.ts.register(missing_tf_types(ros1))
    return m


def quat(roll=0.0, pitch=0.0, yaw=0.0):
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def transform(m: Msgs, stamp, parent, child, xyz=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0)):
    T = m.T
    return T["geometry_msgs/msg/TransformStamped"](
        header=m.header(stamp, parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def tf_msg(m: Msgs, *transforms, tf_type=TF):
    return m.T[tf_type](transforms=list(transforms))


RANGES = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]


def laser_bag(
    tmp_path,
    name,
    mount_xyz,
    mount_q,
    *,
    ros1=True,
    odom="topic",
    static_on="/tf_static",
    laser_frame="laser",
    tf_type=TF,
):
    """5 scans (frame ``laser_frame``) at 10 Hz, odometry 1 m/s along x turning 0.5 rad/s as an
    Odometry topic (``odom="topic"``) or tf only (``"tf"``: odom -> base_footprint), and the mount
    base_footprint -> base_link (0.1 m up) -> laser on ``static_on``."""
    m = msgs(ros1)
    out = []
    mount = [
        transform(m, 99.9, "base_footprint", "base_link", (0.0, 0.0, 0.1)),
        transform(m, 99.9, "base_link", "laser", mount_xyz, mount_q),
    ]
    if static_on:
        out.append((static_on, tf_type, 99.9, tf_msg(m, *mount, tf_type=tf_type)))
    for k in range(31):
        t = 99.98 + 0.02 * k
        x, yaw = t - 100.0, 0.5 * (t - 100.0)
        if odom == "topic":
            msg = m.odom(t, x, 0.0, yaw)
            msg.child_frame_id = "base_footprint"
            out.append(("/odom", ODOM, t, msg))
        else:
            q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
            odom_tf = transform(m, t, "odom", "base_footprint", (x, 0.0, 0.0), q)
            out.append(("/tf", tf_type, t, tf_msg(m, odom_tf, tf_type=tf_type)))
    for i in range(5):
        t = 100.0 + 0.1 * i
        scan = m.scan(t, RANGES, angle_min=-1.0, inc=0.25)
        scan.header.frame_id = laser_frame
        out.append(("/scan", LASER, t + 0.001, scan))
    out.sort(key=lambda x: x[2])
    return write_bag(tmp_path / name, out, ros1=ros1, extra_types=missing_tf_types(ros1))


def body_points(scan) -> np.ndarray:
    """The scan's end points in the base frame, through its sensor offset."""
    x, y, yaw = scan.sensor_offset
    c, s = math.cos(yaw), math.sin(yaw)
    p = scan.points
    return np.column_stack((x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]))


def expected_body_points(mount_xy, mount_yaw, mirrored=False) -> np.ndarray:
    a = -1.0 + 0.25 * np.arange(len(RANGES))
    a = -a if mirrored else a
    r = np.array(RANGES)
    return np.column_stack((mount_xy[0] + r * np.cos(a + mount_yaw), mount_xy[1] + r * np.sin(a + mount_yaw)))


def test_planar_mount_of_a_level_and_an_upside_down_laser():
    class Tr:
        def __init__(self, xyz, q):
            self.translation = type("V", (), dict(zip("xyz", xyz, strict=True)))
            self.rotation = type("Q", (), dict(zip("xyzw", q, strict=True)))

    level = planar_mount(transform_matrix(Tr((0.2, -0.1, 0.3), quat(yaw=0.5))))
    assert (level.x, level.y, level.yaw, level.mirrored) == pytest.approx((0.2, -0.1, 0.5, False))
    assert level.tilt_deg == pytest.approx(0.0, abs=1e-6)
    # upside down as roll pi or as pitch pi: the same mirrored scan, yaw from the laser's x axis
    rolled = planar_mount(transform_matrix(Tr((0.0, 0.0, 0.0), quat(roll=math.pi, yaw=0.5))))
    assert (
        rolled.mirrored and rolled.yaw == pytest.approx(0.5) and rolled.tilt_deg == pytest.approx(0, abs=1e-6)
    )
    pitched = planar_mount(transform_matrix(Tr((0.0, 0.0, 0.0), quat(pitch=math.pi))))
    assert pitched.mirrored and abs(pitched.yaw) == pytest.approx(math.pi)
    tilted = planar_mount(transform_matrix(Tr((0.0, 0.0, 0.0), quat(pitch=0.3))))
    assert not tilted.mirrored and tilted.tilt_deg == pytest.approx(math.degrees(0.3))
    assert transform_matrix(Tr((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))) is None


def test_frame_tree_composes_through_a_common_ancestor_and_survives_a_cycle():
    tree = FrameTree()
    shift = np.eye(4)
    shift[:3, 3] = (1.0, 0.0, 0.0)
    turn = np.eye(4)
    turn[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    assert tree.add("/base_link", "laser_mount", shift) and tree.add("laser_mount", "laser", turn)
    assert tree.add("base_link", "camera", shift)
    assert not tree.add("other", "laser", shift)  # one parent a frame: the first wins
    got = tree.pose("camera", "laser")  # camera and laser share base_link
    assert got[:3, 3] == pytest.approx((0.0, 0.0, 0.0)) and got[:2, :2] == pytest.approx(turn[:2, :2])
    assert tree.base_of("laser") == "base_link" and tree.pose("base_link", "nowhere") is None
    tree.add("laser", "base_link", shift)  # ignored: base_link has no parent yet, so this closes a cycle
    assert tree.chain("laser") == ["laser", "laser_mount", "base_link"]


@pytest.mark.parametrize("ros1", [True, False])
def test_the_laser_mount_on_tf_static_is_the_scans_sensor_offset(tmp_path, ros1):
    bag = laser_bag(tmp_path, "m.bag" if ros1 else "m", (0.3, 0.05, 0.2), quat(yaw=math.pi / 2), ros1=ros1)
    rec = open_recording(bag)
    scans, warns = read_all(rec)
    assert not warns and len(scans) == 5
    assert rec.base_frame == "base_footprint"
    for s in scans:
        assert s.sensor_offset == pytest.approx((0.3, 0.05, math.pi / 2))
    assert body_points(scans[0]) == pytest.approx(expected_body_points((0.3, 0.05), math.pi / 2))


def test_an_upside_down_laser_is_mirrored_into_the_base_frame(tmp_path):
    bag = laser_bag(tmp_path, "u.bag", (0.2, 0.0, 0.3), quat(roll=math.pi))
    rec = open_recording(bag)
    scans, warns = read_all(rec)
    assert not warns and rec.mounts["laser"].mirrored
    s = scans[0]
    assert np.all(np.diff(s.angles) > 0)  # still counter-clockwise, beams reversed
    # the same end points as the beams taken clockwise, last beam first
    assert body_points(s) == pytest.approx(expected_body_points((0.2, 0.0), 0.0, mirrored=True)[::-1])


@pytest.mark.parametrize("ros1", [True, False])
def test_odometry_given_as_tf_only_is_read_from_tf(tmp_path, ros1):
    bag = "{}.bag" if ros1 else "{}"
    with_topic = open_recording(laser_bag(tmp_path, bag.format("o"), (0.0, 0.0, 0.0), quat(), ros1=ros1))
    tf_only = open_recording(
        laser_bag(tmp_path, bag.format("t"), (0.0, 0.0, 0.0), quat(), odom="tf", ros1=ros1)
    )
    assert (tf_only.odom_topic, tf_only.odom_frames, tf_only.base_frame) == (
        "/tf",
        ("odom", "base_footprint"),
        "base_footprint",
    )
    a, _ = read_all(with_topic)
    b, warns = read_all(tf_only)
    assert not warns
    assert np.array([s.odom for s in b]) == pytest.approx(np.array([s.odom for s in a]))
    assert b[2].odom == pytest.approx((0.2, 0.0, 0.1), abs=1e-6)
    assert tf_only.odometry().shape == with_topic.odometry().shape == (31, 4)
    # '' still means none
    assert (
        open_recording(
            laser_bag(tmp_path, bag.format("n"), (0.0, 0.0, 0.0), quat(), odom="tf", ros1=ros1), odom_topic=""
        ).odom_topic
        is None
    )


@pytest.mark.parametrize("tf_type", [TF, OLD_TF])
def test_a_mount_published_on_tf_is_found_there(tmp_path, tf_type):
    """Bags older than /tf_static publish the fixed transforms on /tf with the odometry (before tf2
    as tf/tfMessage)."""
    bag = laser_bag(
        tmp_path, "d.bag", (-0.1, 0.0, 0.2), quat(yaw=0.2), odom="tf", static_on="/tf", tf_type=tf_type
    )
    rec = open_recording(bag)
    scans, warns = read_all(rec)
    assert not warns and scans[0].sensor_offset == pytest.approx((-0.1, 0.0, 0.2))
    assert rec.odom_frames == ("odom", "base_footprint") and scans[2].odom == pytest.approx(
        (0.2, 0.0, 0.1), abs=1e-6
    )


def test_a_laser_frame_tf_does_not_reach_is_flagged_and_taken_at_the_base(tmp_path):
    bag = laser_bag(tmp_path, "x.bag", (0.3, 0.0, 0.2), quat(), laser_frame="front_laser")
    scans, warns = read_all(open_recording(bag))
    assert scans[0].sensor_offset == (0.0, 0.0, 0.0)
    assert len(warns) == 1
    assert "5 no tf transform from base_footprint to the laser frame front_laser" in warns[0]


def test_a_tilted_laser_is_flagged(tmp_path):
    bag = laser_bag(tmp_path, "p.bag", (0.3, 0.0, 0.2), quat(pitch=0.35))
    scans, warns = read_all(open_recording(bag))
    assert len(warns) == 1 and "laser frame laser tilted 20 deg from level on base_footprint" in warns[0]


def test_a_tf_topic_without_odometry_named_as_odom_topic_is_refused(tmp_path, capsys):
    bag = laser_bag(tmp_path, "s.bag", (0.0, 0.0, 0.0), quat())
    with pytest.raises(OptionError) as err:
        open_recording(bag, odom_topic="/tf_static")
    assert err.value.option == "odom_topic" and "no odom -> base transform" in str(err.value)
    assert main(["run", str(bag), "--odom-topic", "/tf_static", "--out", str(tmp_path / "o")]) == 2
    out = capsys.readouterr().err.strip()
    assert "Traceback" not in out and len(out.splitlines()) == 1
    assert "--odom-topic /tf_static: a tf topic without an odom -> base transform" in out
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_intel_bag_odometry_from_tf_is_its_odom_topic(shared_data):
    """The shared intel.bag publishes its odometry on /odom and on /tf alike."""
    path = shared_data / "bags" / "intel.bag"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topic, tf = RosBag(path), RosBag(path, odom_topic="/tf")
    assert tf.odom_frames == ("odom", "base_link")
    np.testing.assert_array_equal(tf.odometry(), topic.odometry())
    assert tf._odom_track.shape == topic._odom_track.shape
    np.testing.assert_array_equal(tf._odom_track, topic._odom_track)


def test_a_run_on_a_bag_with_an_offset_upside_down_laser_and_tf_odometry_follows_the_base(tmp_path, capsys):
    """End to end: the robot's odometry only on /tf, its laser 0.3 m ahead of the base, upside down
    and turned 90 deg; the trajectory written is the base's, on the true route."""
    from frslam_graph.evaluation.trajectory_io import load_tum
    from tests import synthetic_world as sw

    m = msgs(True)
    truth = sw.route([(1.5, 1.5), (6.0, 1.5), (6.0, 4.0)], speed=0.6, rate=5.0)[:40]
    world = sw.room_world()
    mount = np.array([0.3, 0.0, math.pi / 2])
    n = 360
    out = [
        (
            "/tf_static",
            TF,
            99.0,
            tf_msg(
                m,
                transform(
                    m, 99.0, "base_link", "laser", (0.3, 0.0, 0.4), quat(roll=math.pi, yaw=math.pi / 2)
                ),
            ),
        )
    ]
    for t, x, y, th in truth:
        stamp = 100.0 + t
        c, s = math.cos(th), math.sin(th)
        plane = np.array([x + c * mount[0] - s * mount[1], y + s * mount[0] + c * mount[1], th + mount[2]])
        ranges, amin, inc = sw.cast(world, plane, n_beams=n, max_range=20.0)
        own = ranges[(n - np.arange(n)) % n]  # upside down: its beam at a sees the plane's -a
        scan = m.scan(stamp, np.nan_to_num(own, nan=np.inf), angle_min=amin, inc=inc, rmax=20.0)
        q = (0.0, 0.0, math.sin(th / 2), math.cos(th / 2))
        odom = transform(m, stamp - 0.001, "odom", "base_link", (x, y, 0.0), q)
        out += [("/scan", LASER, stamp, scan), ("/tf", TF, stamp - 0.001, tf_msg(m, odom))]
    out.sort(key=lambda r: r[2])
    bag = write_bag(tmp_path / "mounted.bag", out, extra_types=missing_tf_types(True))
    run = tmp_path / "run"
    assert main(["run", str(bag), "--out", str(run)]) == 0, capsys.readouterr().err
    est = load_tum(run / "trajectory.tum")
    assert len(est) == len(truth)
    err = np.hypot(est[:, 1] - truth[:, 1], est[:, 2] - truth[:, 2])
    assert err.max() < 0.05


def multi_echo(m: Msgs, stamp, echoes, angle_min=-1.0, inc=0.5):
    T = m.T
    return T["sensor_msgs/msg/MultiEchoLaserScan"](
        header=m.header(stamp),
        angle_min=angle_min,
        angle_max=angle_min + inc * (len(echoes) - 1),
        angle_increment=inc,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.1,
        range_max=10.0,
        ranges=[T["sensor_msgs/msg/LaserEcho"](echoes=np.asarray(e, dtype=np.float32)) for e in echoes],
        intensities=[
            T["sensor_msgs/msg/LaserEcho"](echoes=np.zeros(len(e), dtype=np.float32)) for e in echoes
        ],
    )


@pytest.mark.parametrize(("ros1", "reader"), [(True, "auto"), (True, "sequential"), (False, "auto")])
def test_a_multi_echo_scan_is_read_at_each_beams_first_echo(tmp_path, ros1, reader):
    """Cartographer's 2D bags record sensor_msgs/MultiEchoLaserScan (a list of echoes a beam)."""
    m = Msgs(ros1)
    echoes = [[1.0, 1.5], [], [2.0], [12.0, 3.0], [float("inf")]]
    msgs = [
        ("/horizontal_laser_2d", MULTI, 100.0 + 0.1 * i, multi_echo(m, 100.0 + 0.1 * i, echoes))
        for i in range(3)
    ]
    bag = write_bag(tmp_path / ("e.bag" if ros1 else "e"), msgs, ros1=ros1)
    rec = open_recording(bag, reader=reader)
    assert (rec.scan_topic, rec.scan_type) == ("/horizontal_laser_2d", MULTI)
    scans, _ = read_all(rec)
    assert len(scans) == 3
    s = scans[0]
    # first echoes 1.0, none, 2.0, 12.0 (beyond range_max), inf: the valid ones are 1.0 and 2.0
    assert np.isnan(s.ranges).tolist() == [False, True, False, True, True]
    assert s.ranges[[0, 2]] == pytest.approx([1.0, 2.0]) and s.angles == pytest.approx(
        [-1.0, -0.5, 0.0, 0.5, 1.0]
    )


def test_an_odometry_frame_tf_does_not_know_takes_the_mount_on_tfs_base(tmp_path):
    """The odometry says base_link, tf says robot/base_link -> laser: the mount is tf's, flagged."""
    m = msgs(True)
    mount = transform(m, 99.9, "robot/base_link", "laser", (0.25, 0.0, 0.2), quat(yaw=0.1))
    out = [("/tf_static", TF, 99.9, tf_msg(m, mount))]
    out += [("/odom", ODOM, 99.99 + 0.02 * k, m.odom(99.99 + 0.02 * k, 0.0, 0.0, 0.0)) for k in range(10)]
    out += [("/scan", LASER, 100.0 + 0.05 * i, m.scan(100.0 + 0.05 * i, RANGES)) for i in range(3)]
    out.sort(key=lambda r: r[2])
    scans, warns = read_all(
        open_recording(write_bag(tmp_path / "r.bag", out, extra_types=missing_tf_types(True)))
    )
    assert scans[0].sensor_offset == pytest.approx((0.25, 0.0, 0.1))
    assert len(warns) == 1
    assert "3 the odometry's frame base_link is not connected to tf's robot/base_link" in warns[0]
