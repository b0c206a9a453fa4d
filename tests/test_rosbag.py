"""ROS 1 / ROS 2 bag reader: LaserScan, PointCloud2, Odometry, topic choice, the sequential fallback, bad bags."""

from __future__ import annotations

import math
import shutil
import struct
import warnings

import numpy as np
import pytest
from frslam_graph.datasets import RecordingWarning, open_recording
from frslam_graph.datasets.rosbag import RosBag
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from frslam_graph.errors import RecordingError

LASER = "sensor_msgs/msg/LaserScan"
CLOUD = "sensor_msgs/msg/PointCloud2"
ODOM = "nav_msgs/msg/Odometry"
NS = 1_000_000_000


class Msgs:
    """Message factories for one typestore (ROS 1 headers have ``seq``, ROS 2 ones do not)."""

    def __init__(self, ros1: bool):
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.T = self.ts.types

    def header(self, stamp: float, frame="laser"):
        t = self.T["builtin_interfaces/msg/Time"](sec=int(stamp), nanosec=int(round((stamp % 1) * 1e9)))
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=t, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=t, frame_id=frame)

    def scan(self, stamp, ranges, angle_min=-1.0, inc=0.5, rmin=0.1, rmax=10.0):
        r = np.asarray(ranges, dtype=np.float32)
        return self.T[LASER](
            header=self.header(stamp),
            angle_min=angle_min,
            angle_max=angle_min + inc * (len(r) - 1),
            angle_increment=inc,
            time_increment=0.0,
            scan_time=0.1,
            range_min=rmin,
            range_max=rmax,
            ranges=r,
            intensities=np.zeros(0, dtype=np.float32),
        )

    def odom(self, stamp, x, y, yaw):
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        )
        twist = T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        )
        return T[ODOM](
            header=self.header(stamp, "odom"),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )

    def cloud(self, stamp, xyz, pad=4):
        """PointCloud2 with float32 x, y, z and ``pad`` bytes of another field (intensity) after them."""
        T = self.T
        xyz = np.asarray(xyz, dtype=np.float32)
        step = 12 + pad
        buf = np.zeros((len(xyz), step), dtype=np.uint8)
        buf[:, :12] = xyz.view(np.uint8).reshape(len(xyz), 12)
        fields = [
            T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
            for i, n in enumerate("xyz")
        ]
        fields.append(T["sensor_msgs/msg/PointField"](name="intensity", offset=12, datatype=7, count=1))
        return T[CLOUD](
            header=self.header(stamp),
            height=1,
            width=len(xyz),
            fields=fields,
            is_bigendian=False,
            point_step=step,
            row_step=step * len(xyz),
            data=buf.reshape(-1),
            is_dense=True,
        )

    def serialize(self, msg, msgtype):
        return self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)


def write_bag(path, messages, ros1=True, storage=StoragePlugin.SQLITE3, extra_types=None, compression=None):
    """``messages``: list of (topic, msgtype, bag_time_s, msg). Returns the bag path."""
    m = Msgs(ros1)
    if extra_types:
        m.ts.register(extra_types)
    writer = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=storage)
    if compression:
        writer.set_compression(getattr(Writer1.CompressionFormat, compression))
    with writer:
        conns = {}
        for topic, msgtype, t, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=m.ts)
            writer.write(conns[topic], int(round(t * NS)), m.serialize(msg, msgtype))
    return path


def standard_messages(ros1=True, n=5):
    """n scans at 10 Hz from t = 100 s, odometry at 50 Hz moving 1 m/s along x, turning 0.5 rad/s."""
    m = Msgs(ros1)
    out = []
    for k in range(int(n * 5) + 6):
        t = 99.98 + 0.02 * k
        out.append(("/odom", ODOM, t, m.odom(t, t - 100.0, 0.0, 0.5 * (t - 100.0))))
    for i in range(n):
        t = 100.0 + 0.1 * i
        ranges = [1.0 + i, float("nan"), float("inf"), -1.0, 0.05, 10.0, 12.0, 2.0]
        out.append(("/scan", LASER, t + 0.001, m.scan(t, ranges)))
    out.sort(key=lambda x: x[2])
    return out


def read_all(rec):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        scans = list(rec)
    return scans, [str(w.message) for w in got if issubclass(w.category, RecordingWarning)]


def check_standard(scans):
    assert len(scans) == 5
    assert [s.stamp for s in scans] == pytest.approx([100.0, 100.1, 100.2, 100.3, 100.4], abs=1e-6)
    s = scans[1]
    assert s.angles == pytest.approx(-1.0 + 0.5 * np.arange(8))
    # nan, inf, negative, below range_min, == range_max, > range_max -> nan
    assert np.isnan(s.ranges).tolist() == [False, True, True, True, True, True, True, False]
    assert s.ranges[0] == pytest.approx(2.0) and s.max_range == pytest.approx(10.0)
    x, y, yaw = s.odom
    assert x == pytest.approx(0.1, abs=1e-6) and y == 0.0 and yaw == pytest.approx(0.05, abs=1e-6)


@pytest.mark.parametrize("reader", ["auto", "sequential"])
@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_ros1_laser_scan_and_odometry(tmp_path, reader, compression):
    bag = write_bag(tmp_path / "a.bag", standard_messages(), compression=compression)
    rec = open_recording(bag, reader=reader)
    assert isinstance(rec, RosBag) and rec.reader_used == ("rosbags" if reader == "auto" else "sequential")
    assert (rec.scan_topic, rec.odom_topic, len(rec)) == ("/scan", "/odom", 5)
    scans, warns = read_all(rec)
    check_standard(scans)
    assert rec.stats.invalid_beams == 5 * 6
    assert len(warns) == 1 and "5 scans with negative ranges" in warns[0] and "/scan message 0" in warns[0]
    assert rec.odometry().shape == (31, 4)


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_ros2_folder_and_bare_storage_file(tmp_path, storage):
    bag = write_bag(tmp_path / "b", standard_messages(ros1=False), ros1=False, storage=storage)
    scans, _ = read_all(open_recording(bag))
    check_standard(scans)
    (storage_file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    scans, _ = read_all(open_recording(storage_file))
    check_standard(scans)


def test_simulator_output_folder(tmp_path):
    """Simulator layout: bag/ (rosbag2) with /scan, /odom and /ground_truth, plus ground_truth.tum."""
    from frslam_graph.evaluation.trajectory_io import save_tum

    m = Msgs(False)
    msgs = standard_messages(ros1=False)
    gt = np.array([[100.0 + 0.1 * i, 0.1 * i + 0.5, 0.0, 0.0] for i in range(5)])
    msgs += [("/ground_truth", ODOM, t, m.odom(t, x, y, th)) for t, x, y, th in gt]
    msgs.sort(key=lambda x: x[2])
    out = tmp_path / "sim"
    out.mkdir()
    write_bag(out / "bag", msgs, ros1=False)
    save_tum(out / "ground_truth.tum", gt)
    (out / "meta.json").write_text("{}")
    rec = open_recording(out)
    assert rec.odom_topic == "/odom"
    scans, _ = read_all(rec)
    check_standard(scans)
    assert np.allclose(rec.ground_truth(), gt, atol=1e-9)
    assert len(open_recording(out, odom_topic="/ground_truth").odometry()) == 5


def test_pointcloud2_sliced_to_plane(tmp_path):
    m = Msgs(True)
    xyz = np.array(
        [
            [1.0, 0.0, 0.0],
            [0.0, 2.0, 0.04],
            [3.0, 3.0, 0.5],
            [-1.0, -1.0, -0.2],
            [np.nan, 1.0, 0.0],
            [4.0, 0.0, -0.01],
        ]
    )
    bag = write_bag(
        tmp_path / "c.bag",
        [("/points", CLOUD, 1.0, m.cloud(1.0, xyz)), ("/points", CLOUD, 2.0, m.cloud(2.0, xyz[:3]))],
    )
    rec = open_recording(bag)
    assert rec.scan_type == CLOUD
    scans, warns = read_all(rec)
    assert scans[0].points == pytest.approx(np.array([[1.0, 0.0], [0.0, 2.0], [4.0, 0.0]]), abs=1e-6)
    assert scans[0].ranges == pytest.approx([1.0, 2.0, 4.0], abs=1e-6)
    assert scans[1].points.shape == (2, 2)
    assert "non-finite points" in warns[0]
    thick, _ = read_all(open_recording(bag, plane_tol=0.3))
    assert thick[0].points.shape == (4, 2)
    raised, _ = read_all(open_recording(bag, plane_z=0.5, plane_tol=0.1))
    assert raised[0].points == pytest.approx(np.array([[3.0, 3.0]]), abs=1e-6)


def test_topic_choice_and_errors(tmp_path):
    m = Msgs(True)
    msgs = standard_messages()
    msgs += [
        ("/scan_rear", LASER, 100.05, m.scan(100.05, [1.0] * 8)),
        ("/wheel", ODOM, 100.0, m.odom(100.0, 5, 5, 0)),
    ]
    bag = write_bag(tmp_path / "d.bag", msgs)
    rec = open_recording(bag)  # '/scan' wins the tie by name; '/odom' the odometry one
    assert (rec.scan_topic, rec.odom_topic) == ("/scan", "/odom")
    rear = open_recording(bag, scan_topic="/scan_rear", odom_topic="/wheel")
    (scan,), _ = read_all(rear)
    assert scan.odom == pytest.approx((5.0, 5.0, 0.0))
    assert open_recording(bag, odom_topic="").odom_topic is None
    with pytest.raises(RecordingError, match=r"d.bag: no topic '/nope' \(topics: /odom"):
        open_recording(bag, scan_topic="/nope")
    with pytest.raises(
        RecordingError, match="topic /odom has type nav_msgs/msg/Odometry; expected LaserScan"
    ):
        open_recording(bag, scan_topic="/odom")
    msgs2 = [("/a", LASER, 1.0, m.scan(1.0, [1.0])), ("/b", LASER, 1.0, m.scan(1.0, [1.0]))]
    with pytest.raises(RecordingError, match=r"several sensor_msgs/msg/LaserScan topics \(/a, /b\)"):
        open_recording(write_bag(tmp_path / "e.bag", msgs2))


def test_unknown_message_types_and_empty_bags(tmp_path):
    from rosbags.typesys import get_types_from_msg

    extra = get_types_from_msg("float64 level\nstring note", "my_pkg/msg/Battery")
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(extra)
    battery = ts.types["my_pkg/msg/Battery"](level=0.5, note="ok")
    msgs = [*standard_messages(), ("/battery", "my_pkg/msg/Battery", 100.0, battery)]
    bag = write_bag(tmp_path / "f.bag", msgs, extra_types=extra)
    for reader in ("auto", "sequential"):
        rec = open_recording(bag, reader=reader)
        assert rec.topics["/battery"][0] == "my_pkg/msg/Battery"
        scans, _ = read_all(rec)
        check_standard(scans)  # other types are listed, not in the way
    only = write_bag(
        tmp_path / "g.bag", [("/battery", "my_pkg/msg/Battery", 1.0, battery)], extra_types=extra
    )
    with pytest.raises(
        RecordingError,
        match=r"g.bag: no LaserScan, MultiEchoLaserScan or PointCloud2 messages \(topics: /battery",
    ):
        open_recording(only)
    empty = write_bag(tmp_path / "h.bag", [])
    with pytest.raises(
        RecordingError,
        match=r"h.bag: no LaserScan, MultiEchoLaserScan or PointCloud2 messages \(topics: none\)",
    ):
        open_recording(empty)
    empty2 = write_bag(tmp_path / "h2", [], ros1=False)
    with pytest.raises(RecordingError, match="no LaserScan, MultiEchoLaserScan or PointCloud2 messages"):
        open_recording(empty2)
    with pytest.raises(RecordingError, match="missing.bag: no such file"):
        open_recording(tmp_path / "missing.bag")
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(RecordingError, match="junk.bag: not a ROS 1 bag"):
        open_recording(tmp_path / "junk.bag")


def test_stamps_going_backwards_in_a_bag(tmp_path):
    m = Msgs(True)
    stamps = [1.0, 2.0, 1.5, 3.0]
    msgs = [("/scan", LASER, 10.0 + i, m.scan(t, [1.0] * 4)) for i, t in enumerate(stamps)]
    bag = write_bag(tmp_path / "i.bag", msgs)
    kept, warns = read_all(open_recording(bag))
    assert [s.stamp for s in kept] == stamps
    assert "1 scans stamped before an earlier scan (kept in bag order) (first at /scan message 2)" in warns[0]
    skipped, _ = read_all(open_recording(bag, backwards="skip"))
    assert [s.stamp for s in skipped] == [1.0, 2.0, 3.0]
    with pytest.raises(RecordingError, match="i.bag: /scan message 2: stamp 1.500000"):
        list(open_recording(bag, backwards="error"))


def patch_index_lengths(path, entry_bytes=20):
    """Rewrite every index-data record's data length as count * entry_bytes (like scan_tools_demo.bag)."""
    b = bytearray(path.read_bytes())
    pos = 13
    patched = 0
    while pos < len(b):
        (hlen,) = struct.unpack_from("<I", b, pos)
        header = bytes(b[pos + 4 : pos + 4 + hlen])
        dpos = pos + 4 + hlen
        (dlen,) = struct.unpack_from("<I", b, dpos)
        if b"op=\x04" in header:
            count = struct.unpack_from("<I", header, header.index(b"count=") + 6)[0]
            struct.pack_into("<I", b, dpos, count * entry_bytes)
            patched += 1
            dlen = count * 12  # what the record really holds (version 1 entries)
        pos = dpos + 4 + dlen
    path.write_bytes(bytes(b))
    return patched


def test_bag_with_odd_index_records_falls_back_to_sequential_reading(tmp_path):
    bag = write_bag(tmp_path / "j.bag", standard_messages())
    assert patch_index_lengths(bag) == 2
    with pytest.raises(RecordingError, match="rosbags cannot read it"):
        open_recording(bag, reader="rosbags")
    rec = open_recording(bag)
    assert rec.reader_used == "sequential" and rec.fallback_reason
    scans, warns = read_all(rec)
    check_standard(scans)
    assert "2 index records with a wrong data length (repaired)" in warns[0]


def test_bag_cut_short_keeps_the_complete_chunks(tmp_path):
    m = Msgs(True)
    path = tmp_path / "k.bag"
    writer = Writer1(path)
    writer.chunk_threshold = 2000  # several chunks
    with writer:
        conn = writer.add_connection("/scan", LASER, typestore=m.ts)
        for i in range(40):
            writer.write(conn, (10 + i) * NS, m.ts.serialize_ros1(m.scan(10.0 + i, [1.0] * 100), LASER))
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    rec = open_recording(cut)
    assert rec.reader_used == "sequential"
    scans, warns = read_all(rec)
    assert 5 < len(scans) == len(rec) < 40
    assert [s.stamp for s in scans] == pytest.approx(10.0 + np.arange(len(scans)))
    assert "bag cut in the middle of a record" in warns[0] and "byte" in warns[0]


def test_shared_demo_bag(shared_data, tmp_path):
    path = shared_data / "bags" / "scan_tools_demo.bag"
    rec = open_recording(path)
    assert rec.reader_used == "sequential" and len(rec) == 360
    scans, _ = read_all(rec)
    assert len(scans) == 360
    assert {s.ranges.size for s in scans} == {681}
    assert scans[0].angles[0] == pytest.approx(-2.086, abs=1e-3) and scans[0].angles[-1] == pytest.approx(
        2.086, abs=1e-3
    )
    assert scans[0].max_range == pytest.approx(5.6)
    assert 35.0 < scans[-1].stamp - scans[0].stamp < 37.0
    assert all(s.odom is None for s in scans)
    assert np.all(np.diff([s.stamp for s in scans]) > 0)
    # the same messages through rosbags once the index records are repaired
    fixed = tmp_path / "fixed.bag"
    shutil.copy(path, fixed)
    fixed.chmod(0o644)
    assert patch_index_lengths(fixed, entry_bytes=12) == 2
    ref = open_recording(fixed, reader="rosbags")
    ref_scans, _ = read_all(ref)
    assert len(ref_scans) == 360
    for a, b in zip(scans, ref_scans, strict=True):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.ranges, b.ranges)


def test_header_stamps_match_a_tum_file_exactly(tmp_path):
    """Absolute stamps (about 1.7e9 s) survive bag -> float seconds as a '%.9f' TUM line would."""
    from frslam_graph.evaluation.trajectory_io import load_tum, save_tum

    m = Msgs(False)
    ns = [1_700_000_000_123_456_789 + k * 33_333_333 for k in range(20)]
    msgs = []
    for n in ns:
        scan = m.scan(0.0, [1.0] * 4)
        scan.header.stamp.sec, scan.header.stamp.nanosec = n // NS, n % NS
        msgs.append(("/scan", LASER, n / NS, scan))
    bag = write_bag(tmp_path / "s", msgs, ros1=False)
    stamps = np.array([s.stamp for s in open_recording(bag)])
    save_tum(tmp_path / "gt.tum", np.column_stack([[n / NS for n in ns], np.zeros((20, 3))]))
    np.testing.assert_array_equal(stamps, load_tum(tmp_path / "gt.tum")[:, 0])
    assert stamps[0] == float("1700000000.123456789")


def test_inspect_command_on_a_bag(tmp_path, capsys):
    from frslam_graph.cli import main

    bag = write_bag(tmp_path / "a.bag", standard_messages())
    assert main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "RosBag" in out and "/scan" in out and "5 read of 5 found" in out and "scans/s" in out
    assert main(["inspect", str(bag), "--laser", "rear"]) == 2  # a CARMEN option on a bag


def _fields(fields: dict[str, bytes]) -> bytes:
    return b"".join(struct.pack("<I", len(k) + 1 + len(v)) + k.encode() + b"=" + v for k, v in fields.items())


def _record(fields: dict[str, bytes], data: bytes) -> bytes:
    header = _fields(fields)
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(data)) + data


def test_unindexed_bag_with_messages_outside_chunks(tmp_path):
    """A bag whose recorder died: no index (index_pos = 0), records written without chunks."""
    m = Msgs(True)
    conn = _record(
        {"op": b"\x07", "conn": struct.pack("<I", 0), "topic": b"/scan"},
        _fields({"topic": b"/scan", "type": b"sensor_msgs/LaserScan", "md5sum": b"*"}),
    )
    msgs = b"".join(
        _record(
            {"op": b"\x02", "conn": struct.pack("<I", 0), "time": struct.pack("<II", 10 + i, 0)},
            m.ts.serialize_ros1(m.scan(10.0 + i, [1.0, 2.0, 3.0]), LASER),
        )
        for i in range(3)
    )
    header = _record(
        {"op": b"\x03", "index_pos": struct.pack("<Q", 0), "conn_count": b"\0" * 4, "chunk_count": b"\0" * 4},
        b" " * 16,
    )
    path = tmp_path / "unindexed.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + header + conn + msgs)
    rec = open_recording(path)
    assert rec.reader_used == "sequential" and len(rec) == 3
    scans, _ = read_all(rec)
    assert [s.stamp for s in scans] == [10.0, 11.0, 12.0]
    assert scans[2].ranges.tolist() == [1.0, 2.0, 3.0]
