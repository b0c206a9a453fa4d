"""A sequential reader of the ROS 1 bag format (v2.0) for bags rosbags' index reader rejects.

rosbags' ``Reader`` trusts the index records (``op=0x04``) and asserts their data length equals
``count * 12``; some recorders wrote another length there (the shared ``scan_tools_demo.bag``
declares ``count * 20`` but holds ``count * 12`` bytes), so it raises before reading anything.
This module ignores the index: it walks the top-level records from the start of the file, reads
each chunk (``op=0x05``; none, bz2 or lz4) one at a time and yields the connection (``op=0x07``)
and message-data (``op=0x02``) records inside, so memory stays at one chunk. An index-data record
is skipped by its entry count (12 bytes per entry in version 1) rather than its declared length.
Messages are decoded with rosbags' typestore (``deserialize_ros1``), using the definitions the
bag carries for types the store does not know.

Record layout: ``<u32 header_len><header: repeated <u32 len>name=value><u32 data_len><data>``.
"""

from __future__ import annotations

import bz2
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from frslam_graph.errors import RecordingError

MAGIC = b"#ROSBAG V2.0\n"
OP_MSG, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7


@dataclass(frozen=True)
class RawConnection:
    """One connection: id, topic, message type (``pkg/msg/Name``) and its definition text."""

    conn: int
    topic: str
    msgtype: str
    msgdef: str


def _fields(buf: bytes, where: str, path: Path) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    i = 0
    while i < len(buf):
        if i + 4 > len(buf):
            raise RecordingError("record header field cut short", source=path, where=where)
        (n,) = struct.unpack_from("<I", buf, i)
        field = buf[i + 4 : i + 4 + n]
        if len(field) != n or b"=" not in field:
            raise RecordingError("malformed record header field", source=path, where=where)
        key, value = field.split(b"=", 1)
        out[key.decode("latin-1")] = value
        i += 4 + n
    return out


def _u32(h: dict[str, bytes], key: str) -> int:
    return struct.unpack("<I", h[key][:4])[0]


def _time_ns(value: bytes) -> int:
    sec, nsec = struct.unpack("<II", value[:8])
    return sec * 1_000_000_000 + nsec


#: the problem recorded when the file ends inside a record (a bag cut short)
CUT = "bag cut in the middle of a record (rest ignored)"


class Ros1RawBag:
    """Sequential access to a ROS 1 bag without its index.

    ``problems`` counts what was repaired or skipped (e.g. index records with a wrong length, a
    bag cut in the middle of a record) with ``first_problem`` the byte offset of the first one.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError("no such file", source=self.path)
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise RecordingError("not a ROS 1 bag (missing '#ROSBAG V2.0' header)", source=self.path)
        self.problems: Counter = Counter()  # of the latest pass over the file
        self.first_problem: dict[str, str] = {}
        self._def_problems: list[tuple[str, str]] = []
        self.connections: dict[int, RawConnection] = {}
        self.counts: Counter = Counter()  # conn id -> messages
        for kind, conn, _t, _data in self._walk(decode_messages=False):
            if kind == OP_MSG:
                self.counts[conn] += 1
        self.typestore = get_typestore(Stores.ROS1_NOETIC)
        for c in self.connections.values():
            if c.msgtype not in self.typestore.fielddefs and c.msgdef:
                try:
                    self.typestore.register(get_types_from_msg(c.msgdef, c.msgtype))
                except Exception as exc:  # rosbags raises several types on a bad definition
                    self._def_problems.append(
                        (f"unusable definition of {c.msgtype} ({exc})", f"topic {c.topic}")
                    )

    def _problem(self, what: str, where: str) -> None:
        self.problems[what] += 1
        self.first_problem.setdefault(what, where)

    def topics(self) -> dict[str, tuple[str, int]]:
        """Topic -> (message type, message count)."""
        out: dict[str, tuple[str, int]] = {}
        for c in self.connections.values():
            msgtype, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (msgtype, n + self.counts[c.conn])
        return out

    def messages(self, topics: set[str]) -> Iterator[tuple[RawConnection, int, bytes]]:
        """(connection, bag time ns, raw bytes) of the messages on ``topics``, in file order."""
        for kind, conn, t, data in self._walk(decode_messages=True):
            if kind == OP_MSG:
                c = self.connections.get(conn)
                if c is None:
                    self._problem("messages on an undeclared connection", f"connection {conn}")
                elif c.topic in topics:
                    yield c, t, data

    def deserialize(self, raw: bytes, msgtype: str) -> object:
        return self.typestore.deserialize_ros1(raw, msgtype)

    # ---------------------------------------------------------------- record walking
    def _read_record(self, f: BinaryIO, offset: int) -> tuple[dict[str, bytes], int, int] | None:
        """Header fields, data offset and data length of the record at ``offset`` (None at EOF)."""
        head = f.read(4)
        if not head:
            return None
        where = f"byte {offset}"
        if len(head) < 4:
            raise EOFError(where)
        (hlen,) = struct.unpack("<I", head)
        hbuf = f.read(hlen)
        dlen_b = f.read(4)
        if len(hbuf) < hlen or len(dlen_b) < 4:
            raise EOFError(where)
        h = _fields(hbuf, where, self.path)
        if "op" not in h:
            raise RecordingError("record without an 'op' field", source=self.path, where=where)
        (dlen,) = struct.unpack("<I", dlen_b)
        return h, offset + 4 + hlen + 4, dlen

    def _walk(self, decode_messages: bool) -> Iterator[tuple[int, int, int, bytes]]:
        """Yield (op, conn, time_ns, data) for connection and message records, chunk by chunk."""
        self.problems.clear()
        self.first_problem.clear()
        for what, where in self._def_problems:
            self._problem(what, where)
        with open(self.path, "rb") as f:
            f.seek(len(MAGIC))
            offset = len(MAGIC)
            size = self.path.stat().st_size
            while offset < size:
                try:
                    rec = self._read_record(f, offset)
                except EOFError as exc:
                    self._problem(CUT, str(exc))
                    return
                if rec is None:
                    return
                h, data_at, dlen = rec
                op = h["op"][0]
                if op == OP_INDEX and "count" in h and "ver" in h and _u32(h, "ver") == 1:
                    real = 12 * _u32(h, "count")
                    if real != dlen:
                        self._problem("index records with a wrong data length (repaired)", f"byte {offset}")
                    dlen = real
                if data_at + dlen > size:
                    self._problem(CUT, f"byte {offset}")
                    return
                if op == OP_CHUNK:
                    data = f.read(dlen)
                    try:
                        body = self._decompress(h, data, offset)
                    except RecordingError as exc:
                        self._problem(f"unreadable chunk ({exc.message})", f"byte {offset}")
                    else:
                        yield from self._chunk_records(body, offset, decode_messages)
                elif op == OP_CONNECTION:
                    self._connection(h, f.read(dlen), offset)
                elif op == OP_MSG and "conn" in h:  # a message outside any chunk
                    data = f.read(dlen) if decode_messages else b""
                    yield OP_MSG, _u32(h, "conn"), _time_ns(h["time"]) if "time" in h else 0, data
                else:
                    f.seek(dlen, 1)
                offset = data_at + dlen
                f.seek(offset)

    def _decompress(self, h: dict[str, bytes], data: bytes, offset: int) -> bytes:
        kind = h.get("compression", b"none").decode("latin-1")
        if kind == "none":
            return data
        try:
            if kind == "bz2":
                return bz2.decompress(data)
            if kind == "lz4":
                import lz4.frame

                return lz4.frame.decompress(data)
        except Exception as exc:  # corrupt compressed chunk
            raise RecordingError(f"{kind} chunk does not decompress: {exc}") from None
        raise RecordingError(f"unknown chunk compression {kind!r}")

    def _connection(self, h: dict[str, bytes], data: bytes, offset: int) -> None:
        conn = _u32(h, "conn")
        if conn in self.connections:
            return
        fields = _fields(data, f"byte {offset}", self.path)
        topic = h.get("topic", fields.get("topic", b"")).decode("utf-8", "replace")
        msgtype = fields.get("type", b"").decode("utf-8", "replace")
        parts = msgtype.split("/")  # ROS 1 names sensor_msgs/LaserScan; rosbags sensor_msgs/msg/LaserScan
        msgtype = f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype
        msgdef = fields.get("message_definition", b"").decode("utf-8", "replace")
        self.connections[conn] = RawConnection(conn, topic, msgtype, msgdef)

    def _chunk_records(
        self, body: bytes, chunk_at: int, decode: bool
    ) -> Iterator[tuple[int, int, int, bytes]]:
        i = 0
        while i < len(body):
            where = f"byte {chunk_at} (chunk) + {i}"
            if i + 4 > len(body):
                self._problem("chunk cut in the middle of a record", where)
                return
            (hlen,) = struct.unpack_from("<I", body, i)
            if i + 8 + hlen > len(body):
                self._problem("chunk cut in the middle of a record", where)
                return
            h = _fields(body[i + 4 : i + 4 + hlen], where, self.path)
            (dlen,) = struct.unpack_from("<I", body, i + 4 + hlen)
            start = i + 8 + hlen
            if start + dlen > len(body):
                self._problem("chunk cut in the middle of a record", where)
                return
            op = h.get("op", b"\0")[0]
            if op == OP_CONNECTION:
                self._connection(h, body[start : start + dlen], chunk_at)
            elif op == OP_MSG:
                conn = _u32(h, "conn")
                t = _time_ns(h["time"]) if "time" in h else 0
                yield OP_MSG, conn, t, (body[start : start + dlen] if decode else b"")
            i = start + dlen
