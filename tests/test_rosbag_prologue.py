"""The bag reader's prologue: odometry, scan stamps and fixed tf read in one pass of an open bag.

Before the first scan the reader needs every odometry record and every scan stamp (the re-timing
of a bursty stream takes its median period: :func:`~frslam_graph.datasets.recording.acquisition_times`).
It reads them, and the static tf, in one pass over the bag it opened to list the topics, then
streams the scans in a second pass: two passes and one open (the shared intel.bag: 1.6 s to the
first scan instead of 2.6 s of CPU). An Odometry message is read for its pose only, exactly as
rosbags would decode it.
"""

from __future__ import annotations

import math
import struct

import pytest
from frslam_graph.datasets import open_recording
from frslam_graph.datasets.ros1_raw import Ros1RawBag
from frslam_graph.datasets.rosbag import OdometryPose, ros1_odometry_pose
from rosbags.rosbag1 import Reader
from rosbags.rosbag1 import Writer as Writer1
from test_rosbag import ODOM, Msgs, check_standard, read_all, standard_messages, write_bag
from test_rosbag_tf import laser_bag, quat


def count_calls(monkeypatch, cls, name: str) -> list[int]:
    """A counter of the calls of ``cls.name`` (a method or a generator method)."""
    calls = [0]
    original = getattr(cls, name)

    def counted(self, *args, **kwargs):
        calls[0] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, counted)
    return calls


def test_a_bag_is_opened_once_and_read_in_two_passes(tmp_path, monkeypatch):
    bag = laser_bag(tmp_path, "m.bag", (0.2, 0.1, 0.0), quat(yaw=0.3))
    opens = count_calls(monkeypatch, Reader, "open")
    passes = count_calls(monkeypatch, Reader, "messages")
    rec = open_recording(bag)
    scans, _ = read_all(rec)
    assert len(scans) == 5 and scans[0].odom is not None
    assert scans[0].sensor_offset == pytest.approx((0.2, 0.1, 0.3))  # the static tf was read
    # the topics, then odometry + scan stamps + static tf, then the scans (main: 5 opens, 4 passes)
    assert (opens[0], passes[0]) == (1, 2)
    assert rec.source._idle is None  # the bag is closed once the scans are through
    read_all(rec)  # again: the prologue is kept, the bag opened for the scans only
    assert (opens[0], passes[0]) == (2, 3)


def test_the_sequential_reader_walks_the_bag_three_times(tmp_path, monkeypatch):
    bag = write_bag(tmp_path / "s.bag", standard_messages(), compression="BZ2")
    walks = count_calls(monkeypatch, Ros1RawBag, "_walk")
    rec = open_recording(bag, reader="sequential")
    scans, _ = read_all(rec)
    check_standard(scans)
    assert walks[0] == 3  # the message counts, the prologue, the scans (main: 4)


def test_a_pass_inside_another_opens_its_own_reader(tmp_path):
    rec = open_recording(write_bag(tmp_path / "a.bag", standard_messages()))
    outer = rec.source.messages({"/scan"})
    first = next(outer)
    inner = [m[0] for m in rec.source.messages({"/odom"})]
    assert len(inner) == 31 and first[0] == "/scan"
    assert [m[0] for m in outer] == ["/scan"] * 4
    rec.source.close()


def odometry_bytes(frame: str = "odom", child: str = "base_link", seq: int = 7) -> bytes:
    m = Msgs(True)
    msg = m.odom(100.25, 1.5, -2.25, 0.75)
    msg.header.seq, msg.header.frame_id, msg.child_frame_id = seq, frame, child
    return bytes(m.serialize(msg, ODOM))


def rosbags_pose(ts, raw: bytes) -> OdometryPose:
    return OdometryPose.of(ts.deserialize_ros1(raw, ODOM))


def outcome(decode, raw: bytes):
    try:
        return decode(raw)
    except Exception:
        return "error"


def test_the_odometry_pose_of_ros1_bytes_is_what_rosbags_decodes():
    ts = Msgs(True).ts
    raw = odometry_bytes()
    pose = ros1_odometry_pose(raw)
    assert pose == rosbags_pose(ts, raw)
    assert (pose.seq, pose.stamp_ns, pose.child_frame_id) == (7, 100_250_000_000, "base_link")
    assert (pose.x, pose.y, pose.yaw) == pytest.approx((1.5, -2.25, 0.75))
    assert math.isfinite(pose.yaw)
    # damaged messages fail where rosbags fails, and only there
    frame_len_at, child_len_at = 12, 16 + len("odom")
    damaged = [raw[:n] for n in range(len(raw))] + [raw + b"\0" * n for n in (1, 8)]
    for at in (frame_len_at, child_len_at):
        for length in (0, 3, 5, 9, 10_000, 2**32 - 1):
            damaged.append(raw[:at] + struct.pack("<I", length) + raw[at + 4 :])
    damaged.append(odometry_bytes(frame="odöm"))  # valid: non-ASCII UTF-8
    bad_utf8 = bytearray(raw)
    bad_utf8[16] = 0xFF  # in frame_id
    damaged.append(bytes(bad_utf8))
    bad_utf8 = bytearray(raw)
    bad_utf8[child_len_at + 4] = 0xC3  # a cut two-byte sequence in child_frame_id
    damaged.append(bytes(bad_utf8))
    damaged.append(odometry_bytes(frame="", child=""))
    for bad in damaged:
        assert outcome(ros1_odometry_pose, bad) == outcome(lambda b: rosbags_pose(ts, b), bad), bad.hex()
    assert sum(outcome(ros1_odometry_pose, bad) == "error" for bad in damaged) > len(raw)


@pytest.mark.parametrize("reader", ["auto", "sequential"])
def test_damaged_odometry_and_scans_are_skipped_and_reported_as_before(tmp_path, reader):
    """An undecodable, a non-finite and a repeated odometry record, an undecodable scan: each
    skipped and named (the prologue keeps them apart from the records it uses)."""
    m = Msgs(True)
    messages = standard_messages()
    odom = [i for i, (topic, *_rest) in enumerate(messages) if topic == "/odom"]
    scans = [i for i, (topic, *_rest) in enumerate(messages) if topic == "/scan"]
    raw = [(topic, msgtype, t, bytes(m.serialize(msg, msgtype))) for topic, msgtype, t, msg in messages]
    topic, msgtype, t, data = raw[odom[3]]
    raw[odom[3]] = (topic, msgtype, t, data[:-8])
    topic, msgtype, t, msg = messages[odom[5]]
    msg.pose.pose.position.x = math.nan
    raw[odom[5]] = (topic, msgtype, t, bytes(m.serialize(msg, msgtype)))
    topic, msgtype, t, msg = messages[odom[7]]
    msg.header.stamp = messages[odom[6]][3].header.stamp
    raw[odom[7]] = (topic, msgtype, t, bytes(m.serialize(msg, msgtype)))
    topic, msgtype, t, data = raw[scans[2]]
    raw[scans[2]] = (topic, msgtype, t, data[:-3])
    path = tmp_path / "damaged.bag"
    with Writer1(path) as writer:
        conns = {}
        for topic, msgtype, t, data in raw:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=m.ts)
            writer.write(conns[topic], int(round(t * 1e9)), data)
    rec = open_recording(path, reader=reader)
    scans_read, warns = read_all(rec)
    assert len(scans_read) == 4 and all(s.odom is not None for s in scans_read)
    assert rec.odometry().shape == (28, 4)
    assert len(warns) == 1
    for part in (
        "1 skipped: undecodable nav_msgs/msg/Odometry messages (first at /odom message 3)",
        "1 skipped: odometry messages with non-finite values (first at /odom message 5)",
        "1 skipped: odometry messages not after the previous one (first at /odom message 7)",
        "1 skipped: undecodable sensor_msgs/msg/LaserScan messages (first at /scan message 2)",
    ):
        assert part in warns[0], warns[0]
