"""ROS 1 / ROS 2 bag reader (through rosbags): LaserScan, MultiEchoLaserScan or PointCloud2 scans,
nav_msgs/Odometry or tf.

Accepts a ROS 1 ``.bag``, a rosbag2 folder (``metadata.yaml``), a bare ``.mcap`` / ``.db3`` file or
a simulator output folder (``bag/`` + ``ground_truth.tum`` + ``meta.json``). The scan topic is the
only LaserScan topic (else the only MultiEchoLaserScan topic, read at each beam's first echo,
else the only PointCloud2 topic; a topic named ``scan`` wins a tie) unless
``scan_topic`` is given; the odometry topic is the only nav_msgs/Odometry topic, or among several
the one whose name says ``odom`` (not ``ground_truth``), unless ``odom_topic`` is given. Odometry
poses are interpolated at the scan stamps (header stamps; the bag time when a header stamp is 0).
A bag without an Odometry topic whose tf carries an ``odom`` -> base transform (the common way
of older and smaller robots: ``odom`` -> ``base_link`` on ``/tf`` only) has its odometry read from
there (``odom_topic="/tf"`` asks for it). The laser's mount on the base (the odometry's child
frame, else ``base_link`` / ``base_footprint``) comes from the bag's fixed transforms
(``/tf_static``, else the first of each fixed edge on ``/tf``): it is each scan's
``sensor_offset``, and a laser mounted upside down has its beams mirrored into the base's
counter-clockwise order (:mod:`~frslam_graph.datasets.tf_frames`). A laser frame tf does not
connect to the base, or one tilted over ``TILT_WARN_DEG``, is flagged; a bag without tf has the
laser at the base, as before.

A PointCloud2 is sliced to the plane ``|z - plane_z| < plane_tol`` (sensor frame) and projected
to (x, y). LaserScan ranges that are non-finite, below ``range_min`` / <= 0, or >= ``range_max``
become ``nan`` (REP-117's ``inf`` / ``nan`` encodings are counted, a negative range is also
flagged in the warning). ROS 1 bags that rosbags' index reader rejects (the shared ``scan_tools_demo.bag``)
are read sequentially by :mod:`frslam_graph.datasets.ros1_raw`; ``reader`` forces either path.

Scans come in their publisher's order: a ROS 1 bag stores messages in bag-time order, and a bag
converted from a log with a bursty clock (the shared ``intel.bag``, whose bag times are the header
stamps) has that order differ from the order the scans were taken in; ROS 1's ``header.seq`` keeps
it. Scans are therefore yielded by increasing ``seq`` (a reorder window of ``SEQ_WINDOW``
messages; equal seqs, e.g. all 0, and ROS 2 headers keep the bag order). On ``intel.bag`` this
gives the CARMEN log's file order, scan for scan. A ROS 2 bag has no seq: when its scans are
stamped on arrival (below) nothing in it tells their order, and the reader says so
(``UNORDERED``; intel.bag converted to ROS 2 by ``rosbags-convert``: 674 scans out of the order
they were taken in, relation error 0.0356 m against 0.0165).

Odometry interpolated at a stamp is the pose at the scan's time only when the stamps are
acquisition times. A recording stamped on arrival by a busy process is not: the shared
``intel.bag`` (converted from the CARMEN log) stamps its 10 Hz ``/odom`` with a median gap of
0.9 ms (bursts), 602 of them going backwards, and its scans likewise, so the ODOM records
interpolated at the scan stamps were up to 51° off the logger's own pairing (the robot pose
written in each FLASER line) in a turn. Each stream whose stamps are bursty is therefore re-timed
from its own message count (:func:`~frslam_graph.datasets.recording.acquisition_times`: a steady
publisher stamped late, never early), the odometry in ``header.seq`` order with all its records,
and the scans are paired at their acquisition times; ``Scan.stamp`` stays the message's stamp.
Stamps without bursts (ACES, FR079, simulator output) are used as they are. On ``intel.bag`` (heading
step against the FLASER lines' poses, mean / p99 / max): 0.53° / 11.5° / 51° interpolated at the
stamps, 0.26° / 1.9° / 8.4° re-timed. Its LaserScan states 180 beams over 180° (``angle_increment``
π/179) where the CARMEN reader uses CARMEN's 1° steps; the message is read as stated (the angles
are not what separates the two readings: tools/README.md).

Both re-timings need their whole stream (its median period, its share of bursts), so one pass
reads the odometry, the scan stamps and the static tf before the first scan (a ROS 1 Odometry
message for its pose only); the scans follow in a second pass of the same open bag.

Units: seconds, metres, radians; frames: the scan in its sensor frame, odometry ``base_link`` in
``odom`` (REP-105).
"""

from __future__ import annotations

import contextlib
import heapq
import math
import struct
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
from frslam_graph.datasets.recording import PoseInterpolator, Recording, RecordingStats, acquisition_times
from frslam_graph.datasets.ros1_raw import CUT, Ros1RawBag
from frslam_graph.datasets.scan import Scan
from frslam_graph.datasets.tf_frames import (
    TF_TYPES,
    FrameTree,
    Mount,
    frame_name,
    is_odom_frame,
    planar_mount,
)

from frslam_graph.errors import OptionError, RecordingError
from frslam_graph.limits import short_repr

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
MULTI_ECHO = "sensor_msgs/msg/MultiEchoLaserScan"  # Cartographer's 2D bags: the first echo is the scan
SCAN_TYPES = (LASER_SCAN, MULTI_ECHO, POINT_CLOUD2)  # auto-detection prefers them in this order
ODOMETRY = "nav_msgs/msg/Odometry"
BURSTY = "{what} topic stamped on arrival in bursts (odometry paired at estimated acquisition times)"
UNORDERED = (
    "scan topic stamped on arrival without header.seq (ROS 2): scans taken in bag order, which a "
    "bursty clock may have changed from the order they were taken in (a ROS 1 bag keeps header.seq)"
)
TILT_WARN_DEG = 5.0  # a laser tilted more than this from level is flagged (its scan is used as if level)
TF_SEARCH_MESSAGES = 2000  # tf messages read for an odom -> base transform when there is no Odometry topic
SEQ_WINDOW = 256  # messages held to put scans back in header.seq order (Intel: displaced by <= 14)
_PC2_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


Decoders = dict[str, Callable[[bytes], Any]] | None  # message type -> decoder of its ROS 1 bytes


class OdometryPose(NamedTuple):
    """What the reader uses of a nav_msgs/Odometry: ``header.seq`` (None in ROS 2), header stamp
    (ns, 0 when unset), the child frame, and the pose: x, y (m) and yaw (rad) in the odometry frame."""

    seq: int | None
    stamp_ns: int
    child_frame_id: str
    x: float
    y: float
    yaw: float

    @classmethod
    def of(cls, msg: Any) -> OdometryPose:
        """The fields of a decoded Odometry message."""
        st, p = msg.header.stamp, msg.pose.pose.position
        ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
        return cls(_seq(msg), ns, msg.child_frame_id, p.x, p.y, _yaw(msg.pose.pose.orientation))


# header seq, stamp sec (int32, as rosbags reads it), nanosec, frame_id length
_ODOM_HEAD = struct.Struct("<IiII")
_U32 = struct.Struct("<I")
_POSE = struct.Struct("<7d")  # position x, y, z; orientation x, y, z, w
_ODOM_TAIL = 8 * (36 + 6 + 36)  # pose covariance, twist, twist covariance: bytes after the pose


def ros1_odometry_pose(raw: bytes) -> OdometryPose:
    """:class:`OdometryPose` of a ROS 1 (Noetic) nav_msgs/Odometry from its bytes, without building
    the message (a tenth of the CPU); raises where rosbags' ``deserialize_ros1`` raises: a
    string running past the end or not UTF-8, a message shorter or longer than its fields."""
    seq, sec, nsec, n = _ODOM_HEAD.unpack_from(raw, 0)
    start = _ODOM_HEAD.size
    (m,) = _U32.unpack_from(raw, start + n)
    end = start + n + 4 + m
    if end > len(raw):
        raise ValueError("nav_msgs/msg/Odometry: a string runs past the end of the message")
    bytes(raw[start : start + n]).decode()  # frame_id: decoded only to fail as rosbags would
    child = bytes(raw[start + n + 4 : end]).decode()
    x, y, _z, qx, qy, qz, qw = _POSE.unpack_from(raw, end)
    if end + _POSE.size + _ODOM_TAIL != len(raw):
        raise ValueError("ROS1 message size mismatch for 'nav_msgs/msg/Odometry'")
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return OdometryPose(seq, sec * 1_000_000_000 + nsec, child, x, y, yaw)


def bag_path(path: Path) -> Path | None:
    """The bag inside ``path`` (file, rosbag2 folder or simulator folder), or None if none is."""
    if path.is_file() and path.suffix.lower() in (".bag", ".mcap", ".db3"):
        return path
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        if (path / "bag" / "metadata.yaml").is_file():
            return path / "bag"
    return None


class _AnySource:
    """rosbags: its indexed ROS 1 reader, or AnyReader for ROS 2 (folder, .mcap, .db3).

    ROS 1 messages are decoded with the Noetic typestore, adding the bag's own definitions only
    for types it lacks: some recorders stored definitions without their dependencies (the demo
    bag's LaserScan definition has no Header), on which AnyReader gives up.
    """

    def __init__(self, path: Path):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path = path
        self.ros1 = path.suffix.lower() == ".bag"
        self.problems: dict[str, int] = {}
        self.first_problem: dict[str, str] = {}
        self._topics: dict[str, tuple[str, int]] = {}
        self._idle: Any = None  # an open reader between two passes (its index read once)
        if self.ros1:
            self.typestore = get_typestore(Stores.ROS1_NOETIC)
        else:
            self._default = get_typestore(Stores.ROS2_HUMBLE)
        reader = self._open()
        reader.open()
        try:
            for c in reader.connections:
                self._count(c.topic, c.msgtype, c.msgcount)
                if self.ros1 and c.msgtype not in self.typestore.fielddefs and c.msgdef.data:
                    self.typestore.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        except BaseException:
            reader.close()
            raise
        self._idle = reader

    def _count(self, topic: str, msgtype: str, n: int) -> None:
        msgtype, total = self._topics.get(topic, (msgtype, 0))
        self._topics[topic] = (msgtype, total + n)

    def _open(self):
        if self.ros1:
            from rosbags.rosbag1 import Reader

            return Reader(self.path)
        from rosbags.highlevel import AnyReader

        return AnyReader([self.path], default_typestore=self._default)

    def topics(self) -> dict[str, tuple[str, int]]:
        return dict(self._topics)

    def messages(
        self, topics: set[str], ros1_decoders: Decoders = None
    ) -> Iterator[tuple[str, str, int, Any]]:
        """(topic, type, bag time ns, message or the Exception decoding it) in bag order; a ROS 1
        message whose type ``ros1_decoders`` names is decoded by it. The open reader of the
        previous pass is taken when free (a pass inside another opens its own), and left open for
        the next one."""
        reader, self._idle = self._idle, None
        if reader is None:
            reader = self._open()
            reader.open()
        decoders = (ros1_decoders or {}) if self.ros1 else {}
        try:
            conns = [c for c in reader.connections if c.topic in topics]
            for c, t, raw in reader.messages(connections=conns):
                try:
                    if c.msgtype in decoders:
                        msg = decoders[c.msgtype](raw)
                    elif self.ros1:
                        msg = self.typestore.deserialize_ros1(raw, c.msgtype)
                    else:
                        msg = reader.deserialize(raw, c.msgtype)
                except Exception as exc:  # corrupt message: reported by the caller
                    msg = exc
                yield c.topic, c.msgtype, t, msg
        finally:
            if self._idle is None:
                self._idle = reader
            else:
                reader.close()

    def close(self) -> None:
        """Close the reader kept open between passes (the next pass opens one again)."""
        reader, self._idle = self._idle, None
        if reader is not None:
            reader.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()


class _RawSource:
    """Our sequential ROS 1 reader, for bags whose index rosbags rejects."""

    ros1 = True

    def __init__(self, path: Path):
        self.bag = Ros1RawBag(path)
        self.problems = self.bag.problems
        self.first_problem = self.bag.first_problem

    def topics(self) -> dict[str, tuple[str, int]]:
        return self.bag.topics()

    def messages(
        self, topics: set[str], ros1_decoders: Decoders = None
    ) -> Iterator[tuple[str, str, int, Any]]:
        decoders = ros1_decoders or {}
        for c, t, raw in self.bag.messages(topics):
            msgtype = c.msgtype
            try:
                msg = decoders[msgtype](raw) if msgtype in decoders else self.bag.deserialize(raw, msgtype)
            except Exception as exc:  # corrupt message or unknown type: reported by the caller
                msg = exc
            yield c.topic, msgtype, t, msg

    def close(self) -> None:
        """Nothing held open between passes."""


def _stamp(msg: Any, bag_ns: int) -> float:
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return (ns if ns > 0 else bag_ns) / 1_000_000_000  # int / int: correctly rounded


def _seq(msg: Any) -> int | None:
    return getattr(getattr(msg, "header", None), "seq", None)


def header_seq(item: tuple) -> int | None:
    """ROS 1 ``header.seq`` of a (topic, type, bag time, message, ...) item; None without one."""
    return _seq(item[3])


def in_seq_order(
    messages: Iterator[tuple], window: int = SEQ_WINDOW, seq_of: Callable[[tuple], int | None] = header_seq
) -> Iterator[tuple[bool, tuple]]:
    """``messages`` sorted by their ROS 1 ``header.seq`` (``seq_of``) within a window; yields
    (moved, message).

    ``moved`` is True for a message yielded after one that came later in the bag. Messages
    without a seq (ROS 2, undecodable) take the seq of the message before them, ties keep the
    bag order, and a seq that falls back by more than ``window`` starts a new run (a restarted
    publisher), so a bag with all seqs 0 or in order comes out unchanged.
    """
    heap: list[tuple[int, int, int, tuple]] = []
    run, last_seq, latest = 0, -1, -1

    def pop() -> tuple[bool, tuple]:
        nonlocal latest
        _run, _seq, i, item = heapq.heappop(heap)
        moved, latest = i < latest, max(latest, i)
        return moved, item

    for i, item in enumerate(messages):
        seq = seq_of(item)
        seq = last_seq if seq is None else int(seq)
        if seq < last_seq - window:
            run += 1
        last_seq = seq
        heapq.heappush(heap, (run, seq, i, item))
        if len(heap) > window:
            yield pop()
    while heap:
        yield pop()


def _first(item: tuple) -> Any:
    return item[0]


def _seq_items(seq: array) -> Iterator[tuple[int | None, int]]:
    """(header.seq or None, position) of each entry of a column of seqs (-1: none)."""
    return ((None if s < 0 else s, i) for i, s in enumerate(seq))


@dataclass
class _OdometryColumns:
    """The odometry records of the prologue in bag order, as columns: header.seq (-1: none), the
    message's bag index, stamp / x / y / theta (s, m, rad) and the child frame (an index into
    ``frames``); ``undecodable`` maps a record's position to its message type."""

    seq: array = field(default_factory=lambda: array("q"))
    index: array = field(default_factory=lambda: array("q"))
    values: array = field(default_factory=lambda: array("d"))
    frame: array = field(default_factory=lambda: array("q"))
    frames: list[str] = field(default_factory=list)
    undecodable: dict[int, str] = field(default_factory=dict)
    _frame_at: dict[str, int] = field(default_factory=dict)

    def add(self, seq: int | None, index: int, row: tuple[float, float, float, float], frame: str) -> None:
        if frame not in self._frame_at:
            self._frame_at[frame] = len(self.frames)
            self.frames.append(frame)
        self.seq.append(-1 if seq is None else seq)
        self.index.append(index)
        self.values.extend(row)
        self.frame.append(self._frame_at[frame])

    def add_undecodable(self, index: int, msgtype: str) -> None:
        self.undecodable[len(self.seq)] = msgtype
        self.add(None, index, (math.nan,) * 4, "")


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pointcloud2_xyz(msg: Any) -> np.ndarray:
    """(N, 3) float64 x, y, z of a sensor_msgs/PointCloud2 (padding and row_step respected)."""
    fields = {f.name: f for f in msg.fields}
    if not all(k in fields for k in "xyz"):
        raise ValueError(f"PointCloud2 without x/y/z fields (has {sorted(fields)})")
    end = ">" if msg.is_bigendian else "<"
    for k in "xyz":
        if fields[k].datatype not in _PC2_TYPES:
            raise ValueError(f"PointCloud2 field {k} has unknown datatype {fields[k].datatype}")
    dt = np.dtype(
        {
            "names": list("xyz"),
            "formats": [end + _PC2_TYPES[fields[k].datatype] for k in "xyz"],
            "offsets": [fields[k].offset for k in "xyz"],
            "itemsize": int(msg.point_step),
        }
    )
    h, w, step = int(msg.height), int(msg.width), int(msg.point_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < h * int(msg.row_step) or w * step > int(msg.row_step):
        raise ValueError("PointCloud2 data shorter than height * row_step")
    rows = data[: h * int(msg.row_step)].reshape(h, int(msg.row_step))[:, : w * step]
    arr = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dt, count=h * w)
    return np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64)


class RosBag(Recording):
    """A ROS 1 / ROS 2 bag (or simulator output folder) as a stream of :class:`Scan`.

    Args:
        path: ``.bag``, rosbag2 folder, ``.mcap``, ``.db3`` or simulator output folder.
        scan_topic, odom_topic: topics to use (auto-detected when None; ``odom_topic=""`` = none).
        plane_z, plane_tol: slice of a PointCloud2 kept as the 2D scan, metres (sensor frame).
        reader: ``"auto"`` (rosbags, falling back to the sequential ROS 1 reader when rosbags
            rejects the bag), ``"rosbags"`` or ``"sequential"`` (ROS 1 only).
        backwards: scans stamped before an earlier scan are ``"keep"`` (flagged), ``"skip"`` or
            ``"error"``.
        odom_tolerance: seconds a scan may lie outside the odometry records and still get a pose.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        plane_z: float = 0.0,
        plane_tol: float = 0.05,
        reader: Literal["auto", "rosbags", "sequential"] = "auto",
        backwards: Literal["keep", "skip", "error"] = "keep",
        odom_tolerance: float = 0.5,
    ):
        super().__init__(path)
        bag = bag_path(self.path)
        if bag is None:
            if not self.path.exists():
                raise RecordingError("no such file or folder", source=self.path)
            raise RecordingError(
                "not a bag (.bag, .mcap, .db3, a folder with metadata.yaml or with bag/metadata.yaml)",
                source=self.path,
            )
        self.bag = bag
        self.plane_z, self.plane_tol = float(plane_z), float(plane_tol)
        self.backwards = backwards
        self.odom_tolerance = float(odom_tolerance)
        self.reader_used, self.fallback_reason = self._open(reader)
        self.topics = self.source.topics()
        self.scan_topic, self.scan_type = self._pick_scan_topic(scan_topic)
        self.tf_topics = sorted(t for t, (m, n) in self.topics.items() if m in TF_TYPES and n > 0)
        self.odom_frames: tuple[str, str] | None = None  # (odom, base) when odometry comes from tf
        self.odom_topic = self._pick_odom_topic(odom_topic)
        self.base_frame: str | None = self.odom_frames[1] if self.odom_frames else None
        self._tree: FrameTree | None = None
        self.mounts: dict[str, Mount] = {}  # laser frame -> its mount, as the scans met them
        self._mount_problems: dict[str, str] = {}
        self._tf_walked = False
        self._len = self.topics[self.scan_topic][1]
        if self._len == 0:
            raise RecordingError(f"topic {self.scan_topic} has no messages", source=self.bag)
        self._odom: np.ndarray | None = None
        self._odom_track = np.zeros((0, 4))  # records or their acquisition times: what scans pair with
        self._odom_stats = RecordingStats()
        self._acquired: np.ndarray | None = None  # the scans' acquisition times (see _prologue)
        self._unordered = False  # stamped on arrival without header.seq: order unknown (_prologue)

    def _open(self, reader: str) -> tuple[str, str]:
        is_ros1 = self.bag.suffix.lower() == ".bag"
        if reader == "sequential":
            if not is_ros1:
                raise RecordingError("the sequential reader reads ROS 1 .bag files only", source=self.bag)
            self.source = _RawSource(self.bag)
            return "sequential", ""
        if reader not in ("auto", "rosbags"):
            raise RecordingError(f"reader must be 'auto', 'rosbags' or 'sequential', got {reader!r}")
        try:
            self.source = _AnySource(self.bag)
            return "rosbags", ""
        except Exception as exc:  # rosbags raises AssertionError, ReaderError, ... on odd bags
            reason = f"{type(exc).__name__}: {exc}".strip(": ")
            if reader == "rosbags" or not is_ros1:
                raise RecordingError(
                    f"rosbags cannot read it, the bag may be damaged or cut short ({reason})", source=self.bag
                ) from None
        self.source = _RawSource(self.bag)
        return "sequential", reason

    def _pick_scan_topic(self, wanted: str | None) -> tuple[str, str]:
        listing = ", ".join(f"{t} [{m}]" for t, (m, _n) in sorted(self.topics.items())) or "none"
        choices = sorted(t for t, (m, _n) in self.topics.items() if m in SCAN_TYPES)

        def bad(message: str, problem: str) -> OptionError:
            return OptionError(
                message, self.bag, option="scan_topic", value=wanted, choices=choices, problem=problem
            )

        if wanted is not None:
            if wanted not in self.topics:
                raise bad(f"no topic {short_repr(wanted)} (topics: {listing})", "no such topic")
            msgtype = self.topics[wanted][0]
            if msgtype not in SCAN_TYPES:
                raise bad(
                    f"topic {wanted} has type {msgtype}; expected LaserScan, MultiEchoLaserScan or PointCloud2",
                    f"has type {msgtype}, not LaserScan, MultiEchoLaserScan or PointCloud2",
                )
            return wanted, msgtype
        for msgtype in SCAN_TYPES:
            cands = [t for t, (m, n) in self.topics.items() if m == msgtype and n > 0]
            if len(cands) > 1:
                named = [t for t in cands if t.rstrip("/").rsplit("/", 1)[-1] in ("scan", "points")]
                if len(named) != 1:
                    raise bad(
                        f"several {msgtype} topics ({', '.join(sorted(cands))}): choose one with scan_topic=",
                        f"several {msgtype} topics: choose one",
                    )
                cands = named
            if cands:
                return cands[0], msgtype
        cut = getattr(self.source, "first_problem", {}).get(CUT)
        if cut is not None:
            size = self.bag.stat().st_size
            raise RecordingError(
                f"truncated: the file ({size:,} bytes) ends in the middle of the record at {cut}, before "
                f"any complete LaserScan, MultiEchoLaserScan or PointCloud2 message (topics read: {listing})",
                source=self.bag,
            )
        raise RecordingError(
            f"no LaserScan, MultiEchoLaserScan or PointCloud2 messages (topics: {listing})", source=self.bag
        )

    def _pick_odom_topic(self, wanted: str | None) -> str | None:
        """The Odometry topic, or a tf topic carrying an ``odom`` -> base transform when the bag has
        no Odometry topic (:attr:`odom_frames` then names the two frames); None for none."""
        if wanted == "":
            return None
        dynamic_tf = [t for t in self.tf_topics if not t.rstrip("/").endswith("tf_static")]
        choices = [
            *sorted(t for t, (m, _n) in self.topics.items() if m == ODOMETRY),
            *dynamic_tf,
            "'' (none)",
        ]

        def bad(message: str, problem: str) -> OptionError:
            return OptionError(
                message, self.bag, option="odom_topic", value=wanted, choices=choices, problem=problem
            )

        if wanted is not None:
            if wanted not in self.topics:
                raise bad(f"no topic {short_repr(wanted)}", "no such topic")
            msgtype = self.topics[wanted][0]
            if msgtype in TF_TYPES:
                self.odom_frames = self._tf_odometry_edge(wanted)
                if self.odom_frames is None:
                    raise bad(
                        f"tf topic {wanted} carries no odom -> base transform",
                        "a tf topic without an odom -> base transform",
                    )
                return wanted
            if msgtype != ODOMETRY:
                raise bad(
                    f"topic {wanted} has type {msgtype}; expected {ODOMETRY} or a tf topic",
                    f"has type {msgtype}, not {ODOMETRY} or tf",
                )
            return wanted
        cands = [t for t, (m, _n) in self.topics.items() if m == ODOMETRY]
        if len(cands) > 1:
            cands = [t for t in cands if "odom" in t.lower() and "truth" not in t.lower()]
            if len(cands) != 1:
                raise bad(
                    "several Odometry topics and none clearly wheel odometry: choose one with odom_topic=",
                    "several Odometry topics and none clearly wheel odometry: choose one",
                )
        if cands:
            return cands[0]
        for topic in dynamic_tf:
            self.odom_frames = self._tf_odometry_edge(topic)
            if self.odom_frames is not None:
                return topic
        return None

    def _tf_odometry_edge(self, topic: str, limit: int = TF_SEARCH_MESSAGES) -> tuple[str, str] | None:
        """(odom frame, base frame) of the first odometry transform on tf ``topic`` (an ``*odom*``
        parent, a child that is no odom, map or world frame), looked for in its first ``limit``
        messages; None when there is none."""
        for k, (_topic, _type, _t, msg) in enumerate(self.source.messages({topic})):
            if k >= limit:
                break
            for tr in getattr(msg, "transforms", ()):
                parent, child = frame_name(tr.header.frame_id), frame_name(tr.child_frame_id)
                leaf = child.rsplit("/", 1)[-1]
                if is_odom_frame(parent) and not is_odom_frame(child) and leaf not in ("map", "world"):
                    return parent, child
        return None

    def __len__(self) -> int:
        return self._len

    @property
    def ground_truth_path(self) -> Path | None:
        """``ground_truth.tum`` next to the bag of a simulator output folder, if present."""
        p = self.bag.parent / "ground_truth.tum" if self.bag.name == "bag" else None
        return p if p is not None and p.is_file() else None

    def ground_truth(self) -> np.ndarray:
        """(N, 4) ``stamp, x, y, theta`` from a simulator folder's ``ground_truth.tum``; an error
        when the folder lacks ``meta.json``, its completeness marker (an interrupted simulation)."""
        from frslam_graph.evaluation.trajectory_io import load_tum

        path = self.ground_truth_path
        if path is None:
            raise RecordingError("no ground_truth.tum next to the bag", source=self.path)
        if not (path.parent / "meta.json").is_file():
            raise RecordingError(
                "simulator output without meta.json, its completeness marker (an interrupted "
                "frslam simulate?): simulate again",
                source=path.parent,
            )
        return load_tum(path)

    def odometry(self) -> np.ndarray:
        """(M, 4) ``stamp, x, y, theta`` of the odometry topic (increasing stamps; others dropped)."""
        if self._odom is None:
            self._prologue()
        return self._odom.copy()

    def _prologue(self) -> None:
        """One pass over the odometry, scan and static tf topics: the odometry records and the
        track scans pair with (:meth:`_odometry_tables`), the scans' acquisition times
        (:meth:`_scan_acquisition`) and the fixed transforms (:meth:`_frame_tree`). Both estimates
        need their whole stream (its median period and share of bursts), hence a pass before the
        first scan; it keeps a few numbers per message (``array`` columns, 56 bytes an odometry
        record, 16 a scan), and reads a ROS 1 Odometry message for its pose only
        (:func:`ros1_odometry_pose`)."""
        if self.odom_topic is None:
            self._odom, self._odom_track, self._acquired = np.zeros((0, 4)), np.zeros((0, 4)), None
            return
        odom = _OdometryColumns()
        scan_seq, scan_stamp = array("q"), array("d")  # header.seq (-1: none), stamp (NaN: undecodable)
        static = self._static_tf_topics() if self._tree is None else set()
        if static:  # the fixed transforms (:meth:`_frame_tree`) in the same pass
            self._tree = FrameTree()
        k = -1
        topics = {self.odom_topic, self.scan_topic} | static
        for topic, msgtype, t, msg in self.source.messages(topics, {ODOMETRY: ros1_odometry_pose}):
            if topic == self.scan_topic:
                seq = _seq(msg)
                scan_seq.append(-1 if seq is None else seq)
                scan_stamp.append(math.nan if isinstance(msg, Exception) else _stamp(msg, t))
                continue
            if topic in static and not isinstance(msg, Exception):
                self._tree.add_message(msg)
            if topic != self.odom_topic:
                continue
            k += 1
            if isinstance(msg, Exception):
                odom.add_undecodable(k, msgtype)
            elif self.odom_frames is None:
                o = msg if isinstance(msg, OdometryPose) else OdometryPose.of(msg)
                stamp = (o.stamp_ns if o.stamp_ns > 0 else t) / 1_000_000_000
                odom.add(o.seq, k, (stamp, o.x, o.y, o.yaw), o.child_frame_id)
            else:
                parent, child = self.odom_frames
                for tr in getattr(msg, "transforms", ()):
                    if frame_name(tr.header.frame_id) == parent and frame_name(tr.child_frame_id) == child:
                        p, q = tr.transform.translation, tr.transform.rotation
                        odom.add(_seq(tr), k, (_stamp(tr, t), p.x, p.y, _yaw(q)), "")
        self._odom, self._odom_track = self._odometry_tables(odom)
        self._acquired = self._scan_acquisition(scan_seq, scan_stamp) if self._odom.shape[0] else None
        # stamped on arrival and no header.seq (ROS 2 headers have none): the bag order is the only
        # order left, and a bursty clock's delays may have put scans out of the order they were
        # taken in (intel.bag converted to ROS 2: 674 scans displaced by up to 14 places, relation
        # error 0.0165 -> 0.0356 m); said, since nothing in the bag can tell
        self._unordered = self._acquired is not None and all(q < 0 for q in scan_seq)

    def _odometry_tables(self, odom: _OdometryColumns) -> tuple[np.ndarray, np.ndarray]:
        """The odometry records (bag order, increasing stamps), and the track scans are paired
        with: the same records, or all of them in ``header.seq`` order at their acquisition times
        (:func:`acquisition_times`) when their stamps are arrival times of a bursty stream."""
        values = np.frombuffer(odom.values, dtype=np.float64).reshape(-1, 4)  # stamp, x, y, theta
        finite = np.isfinite(values).all(axis=1)
        picked = []  # the rows used, in header.seq order
        stats = self._odom_stats
        for _moved, (_s, i) in in_seq_order(_seq_items(odom.seq), seq_of=_first):
            where = f"{self.odom_topic} message {odom.index[i]}"
            if i in odom.undecodable:
                stats.skip(f"undecodable {odom.undecodable[i]} messages", where)
                continue
            if self.odom_frames is None and self.base_frame is None:
                self.base_frame = frame_name(odom.frames[odom.frame[i]]) or None
            if not finite[i]:
                stats.skip("odometry messages with non-finite values", where)
                continue
            picked.append(i)
        index = np.frombuffer(odom.index, dtype=np.int64)[picked].astype(np.float64)
        seq_rows = np.column_stack((index, values[picked])).reshape(-1, 5)  # bag index, stamp, x, y, theta
        # bag (stamp) order, not seq order: a table interpolated at stamps; on intel.bag it is
        # closer to the CARMEN lines' robot poses (p99 0.12 m) than the seq-ordered records (0.23 m)
        records = seq_rows[np.argsort(seq_rows[:, 0], kind="stable")]
        keep = np.ones(len(records), dtype=bool)
        keep[1:] = records[1:, 1] > np.maximum.accumulate(records[:, 1])[:-1]
        acquired = acquisition_times(seq_rows[:, 1])
        if acquired is None:
            for k in records[~keep, 0]:
                where = f"{self.odom_topic} message {int(k)}"
                stats.skip("odometry messages not after the previous one", where)
            return records[keep, 1:], records[keep, 1:]
        stats.flag(BURSTY.format(what="odometry"), f"{self.odom_topic} message 0")
        track = np.column_stack((acquired, seq_rows[:, 2:]))
        ok = np.ones(len(track), dtype=bool)  # the bound may tie or step back: keep it increasing
        ok[1:] = track[1:, 0] > np.maximum.accumulate(track[:, 0])[:-1]
        return records[keep, 1:], track[ok]

    @staticmethod
    def _scan_acquisition(seq: array, stamp: array) -> np.ndarray | None:
        """Acquisition times of the scan messages in the order :meth:`_scans` takes them (NaN for
        an undecodable one), or None when their stamps follow a steady clock. ``seq``, ``stamp``:
        each scan message's header.seq (-1: none) and stamp (NaN: undecodable) in bag order."""
        order = [i for _moved, (_s, i) in in_seq_order(_seq_items(seq), seq_of=_first)]
        stamps = np.frombuffer(stamp, dtype=np.float64)[order]
        good = np.isfinite(stamps)
        acquired = acquisition_times(stamps[good])
        if acquired is None:
            return None
        stamps[good] = acquired
        return stamps

    def _scans(self, stats: RecordingStats) -> Iterator[Scan]:
        odom = self.odometry()
        odom_at = PoseInterpolator(self._odom_track, self.odom_tolerance)
        for reason, n in self._odom_stats.skipped.items():
            stats.skipped[reason] += n
            stats.first.setdefault(reason, self._odom_stats.first[reason])
        for reason, n in self._odom_stats.problems.items():
            stats.problems[reason] += n
            stats.first.setdefault(reason, self._odom_stats.first[reason])
        acquired = self._acquired
        angles_cache: dict[tuple[int, float, float], np.ndarray] = {}
        last_stamp = -math.inf
        reordered = False
        scans = in_seq_order(self.source.messages({self.scan_topic}))
        for i, (moved, (topic, msgtype, t, msg)) in enumerate(scans):
            where = f"{topic} message {i}"
            if moved:
                reordered = True
                stats.flag("scans stored out of header.seq order (yielded in seq order)", where)
            stats.records[msgtype] += 1
            if isinstance(msg, Exception):
                stats.skip(f"undecodable {msgtype} messages", where)
                continue
            stamp = _stamp(msg, t)
            if stamp < last_stamp:
                if self.backwards == "error":
                    raise RecordingError(
                        f"stamp {stamp:.6f} earlier than an earlier scan's {last_stamp:.6f}",
                        source=self.bag,
                        where=where,
                    )
                if self.backwards == "skip":
                    stats.skip("scans stamped before an earlier scan", where)
                    continue
                order = "header.seq order" if reordered else "bag order"
                stats.flag(f"scans stamped before an earlier scan (kept in {order})", where)
            last_stamp = max(last_stamp, stamp)
            pose = None
            if odom.shape[0]:
                pose = odom_at(stamp if acquired is None else acquired[i])
                if acquired is not None and i == 0:
                    stats.flag(BURSTY.format(what="scan"), where)
                    if self._unordered:
                        stats.flag(UNORDERED, where)
                if pose is None:
                    stats.flag("scans outside the odometry records (odom None)", where)
            mount = self._mount(frame_name(msg.header.frame_id), stats, where)
            if msgtype in (LASER_SCAN, MULTI_ECHO):
                scan = self._laser_scan(msg, msgtype, stamp, pose, mount, angles_cache, stats, where)
            else:
                scan = self._cloud_scan(msg, stamp, pose, mount, stats, where)
            if scan is not None:
                yield scan
        self.source.close()
        for reason, n in self.source.problems.items():
            stats.problems[reason] += n
            stats.first.setdefault(reason, self.source.first_problem.get(reason, "?"))

    def _mount(self, frame: str, stats: RecordingStats, where: str) -> Mount:
        """The mount of the laser frame ``frame`` on the robot base (found once per frame); a scan
        whose mount is unknown or tilted is flagged."""
        if frame not in self.mounts:
            self.mounts[frame], self._mount_problems[frame] = self._find_mount(frame)
        problem = self._mount_problems[frame]
        if problem:
            stats.flag(problem, where)
        return self.mounts[frame]

    def _find_mount(self, frame: str) -> tuple[Mount, str]:
        """``frame``'s mount on the base frame (the odometry's child frame, else ``base_link`` /
        ``base_footprint`` above it) from the bag's fixed transforms, and what went wrong ('' if
        nothing). A bag without tf, a laser frame that is the base, or no base frame at all (no
        odometry, no base above the laser): the laser is the base, as it is for the trajectory."""
        if not self.tf_topics or not frame or frame == self.base_frame:
            return Mount(), ""
        tree = self._frame_tree()
        base = self.base_frame or tree.base_of(frame)
        found = tree.pose(base, frame) if base else None
        if found is None and not self._tf_walked:
            found, base = self._walk_dynamic_tf(tree, frame)
        if base is None:
            return Mount(), ""
        note = ""
        other = tree.base_of(frame)
        if found is None and other is not None and other != base:  # odometry and tf name the base apart
            found = tree.pose(other, frame)
            note = (
                f"the odometry's frame {base} is not connected to tf's {other}: laser mount taken on {other}"
            )
        if found is None:
            return Mount(), f"no tf transform from {base} to the laser frame {frame} (laser taken at {base})"
        mount = planar_mount(found)
        if mount.tilt_deg > TILT_WARN_DEG:
            tilt = (
                f"laser frame {frame} tilted {mount.tilt_deg:.0f} deg from level on {other if note else base}"
            )
            note = "; ".join(filter(None, (note, tilt + " (used as if level)")))
        return mount, note

    def _frame_tree(self) -> FrameTree:
        """The fixed transforms of the static tf topics (read once: by :meth:`_prologue` in a bag
        with odometry)."""
        if self._tree is None:
            self._tree = FrameTree()
            static = self._static_tf_topics()
            if static:
                for _topic, _type, _t, msg in self.source.messages(static):
                    if not isinstance(msg, Exception):
                        self._tree.add_message(msg)
        return self._tree

    def _static_tf_topics(self) -> set[str]:
        return {t for t in self.tf_topics if t.rstrip("/").endswith("tf_static")}

    def _walk_dynamic_tf(self, tree: FrameTree, frame: str) -> tuple[np.ndarray | None, str | None]:
        """Add the first transform of each fixed-looking edge of the dynamic tf topics (not the
        odometry's, not the map's) until ``frame`` connects to the base; its pose and the base."""
        self._tf_walked = True

        def moving(parent: str, child: str) -> bool:
            return any(is_odom_frame(f) or f.rsplit("/", 1)[-1] in ("map", "world") for f in (parent, child))

        dynamic = {t for t in self.tf_topics if not t.rstrip("/").endswith("tf_static")}
        base = self.base_frame
        for _topic, _type, _t, msg in self.source.messages(dynamic) if dynamic else ():
            if isinstance(msg, Exception) or not tree.add_message(msg, skip=moving):
                continue
            base = self.base_frame or tree.base_of(frame)
            found = tree.pose(base, frame) if base else None
            if found is not None:
                return found, base
        return None, base

    def _laser_scan(
        self, msg, msgtype: str, stamp, pose, mount: Mount, cache, stats: RecordingStats, where: str
    ) -> Scan | None:
        if msgtype == MULTI_ECHO:  # each beam's first echo, as Cartographer takes it
            ranges = np.array(
                [e.echoes[0] if len(e.echoes) else np.nan for e in msg.ranges], dtype=np.float64
            )
        else:
            ranges = np.asarray(msg.ranges, dtype=np.float64)
        a0, inc = float(msg.angle_min), float(msg.angle_increment)
        if ranges.size == 0 or not (math.isfinite(a0) and math.isfinite(inc)):
            stats.skip(f"{msgtype.rsplit('/', 1)[-1]} messages with no beams or non-finite angles", where)
            return None
        rmax = float(msg.range_max) if math.isfinite(msg.range_max) and msg.range_max > 0 else math.inf
        rmin = float(msg.range_min) if math.isfinite(msg.range_min) else 0.0
        # REP-117: +inf = no return, -inf = too close, nan = no valid reading; all legal, all
        # nan here and counted in stats.invalid_beams. A finite negative range is not legal.
        if np.any(ranges < 0.0):
            stats.flag("scans with negative ranges (set to nan)", where)
        invalid = ~(ranges > 0.0) | (ranges < rmin) | (ranges >= rmax) | ~np.isfinite(ranges)
        if invalid.any():
            ranges[invalid] = np.nan
        key = (ranges.size, a0, inc, mount.mirrored)
        angles = cache.get(key)
        if angles is None:
            angles = a0 + inc * np.arange(ranges.size, dtype=np.float64)
            if mount.mirrored:  # upside down: beam a lies at -a; reversed, the angles increase again
                angles = -angles[::-1].copy()
            angles.flags.writeable = False
            cache[key] = angles
        if mount.mirrored:
            ranges = ranges[::-1].copy()
        return Scan(stamp, ranges, angles, pose, rmax, mount.offset)

    def _cloud_scan(self, msg, stamp, pose, mount: Mount, stats: RecordingStats, where: str) -> Scan | None:
        try:
            xyz = pointcloud2_xyz(msg)
        except ValueError as exc:
            stats.skip(f"unusable PointCloud2 messages ({exc})", where)
            return None
        finite = np.isfinite(xyz).all(axis=1)
        if not finite.all():
            stats.flag("clouds with non-finite points (dropped)", where)
        keep = finite & (np.abs(xyz[:, 2] - self.plane_z) < self.plane_tol)
        xy = xyz[keep, :2]
        if mount.mirrored:
            xy = xy * np.array([1.0, -1.0])
        return Scan.from_points(stamp, xy, pose, sensor_offset=mount.offset)
