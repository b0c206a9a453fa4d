"""Bad inputs through the CLI: does every one get one line naming the file / option, exit 2?

Issue 22's target, checked on a set of bad inputs made here (not the files of ``tests/``): every
input kind the CLI and the library read (CARMEN .clf/.gz/.bz2, ROS 1 bags, ROS 2 db3 / mcap,
PCD/PLY folders, map_server maps, JSON / R2V / HouseExpo / room-segmentation / image plans,
configuration, relations, TUM ground truth, CLI options, outputs, the streaming API), of the
classes of the issue (empty, truncated, binary junk, huge headers, decompression bombs, YAML alias
bombs, wrong types, NaN / inf, duplicates, symlinks and read-only / existing outputs, ...).

Each case runs in its own subprocess (``frslam ...``, or ``python -c`` for the streaming API)
under ``/usr/bin/time -v`` (peak RSS of the largest process) with a 30 s timeout and a 2 GB RSS
guard (polled with psutil; a case over it is killed and fails). A case passes when:

- ``error`` cases: exit 2, stderr exactly one line, no traceback, the line names the file or
  option given in the case (``names``), within 30 s and 1 GB;
- ``warn`` cases (input readable in part, e.g. a log cut mid-line): exit 0 or 2, no traceback,
  the file named on stderr;
- ``ok`` cases (valid but tricky, e.g. a symlink planted at an output): exit 0 and the case's
  own check (the link's target untouched).

    .venv/bin/python tools/bad_inputs.py                  # all cases, 2 at a time
    .venv/bin/python tools/bad_inputs.py --only carmen --jobs 1 --keep /tmp/cases
    .venv/bin/python tools/bad_inputs.py --kill 5         # the kill test instead (see kill_test)

``--kill N`` runs the kill test: ``frslam run`` on a small recording and ``frslam simulate`` are
killed (SIGKILL, SIGTERM, SIGINT) N times each at random moments; after each, every output in the
folder must be absent or complete (``metrics.json`` / ``meta.json`` written last lists them; a
TUM file parses with every row of 8 numbers; no temporary file left behind except after SIGKILL,
where a stale ``.frslam-tmp`` file is allowed but the outputs must still be whole).
"""

from __future__ import annotations

import argparse
import bz2
import gzip
import json
import os
import random
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import psutil
from _paths import REPO, SHARED_DATA  # noqa: E402

sys.path.insert(0, str(REPO))
PY = sys.executable
FRSLAM = [PY, "-c", "import sys; from frslam_graph.cli import main; sys.exit(main())"]
TIMEOUT_S = 30.0
RSS_TARGET_MB = 1024.0
RSS_GUARD_MB = 2048.0
SHARED = SHARED_DATA


@dataclass
class Case:
    name: str
    kind: str  # input kind (carmen, ros1, ...)
    klass: str  # class of badness (empty, truncated, junk, bomb, ...)
    make: Callable[[Path], tuple[list[str], str]]  # folder -> (argv after frslam, token to name)
    expect: str = "error"  # error | warn | ok
    check: Callable[[Path], str | None] | None = None  # ok cases: None = fine, else what is wrong
    api: bool = False  # argv is Python code for the streaming API


@dataclass
class Outcome:
    case: Case
    code: int | None
    line: str
    one_line: bool
    traceback: bool
    names: bool
    rss_mb: float
    seconds: float
    killed: str = ""
    problem: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.problem


CASES: list[Case] = []


def case(kind: str, klass: str, expect: str = "error", check=None, api: bool = False):
    def deco(fn):
        CASES.append(Case(fn.__name__, kind, klass, fn, expect, check, api))
        return fn

    return deco


# ---------------------------------------------------------------- valid material to spoil
def carmen_text(n: int = 40, beams: int = 90, stamp0: float = 100.0, dt: float = 0.2) -> str:
    """A small CARMEN log: a robot in a 6 x 4 m room, FLASER lines (and ODOM)."""
    lines = []
    for i in range(n):
        t = stamp0 + dt * i
        x, y, th = 0.05 * i, 0.0, 0.01 * i
        ang = np.linspace(-np.pi / 2, np.pi / 2, beams)
        r = np.minimum(
            np.abs(3.0 / np.maximum(np.abs(np.cos(ang + th)), 1e-3)),
            2.0 / np.maximum(np.abs(np.sin(ang + th)), 1e-3),
        )
        r = np.minimum(r, 7.9)
        rs = " ".join(f"{v:.3f}" for v in r)
        lines.append(f"ODOM {x:.4f} {y:.4f} {th:.4f} 0.1 0 0 {t - 0.05:.6f} host {t - 0.05:.6f}")
        lines.append(
            f"FLASER {beams} {rs} {x:.4f} {y:.4f} {th:.4f} {x:.4f} {y:.4f} {th:.4f} {t:.6f} host {t:.6f}"
        )
    return "\n".join(lines) + "\n"


def small_log(d: Path) -> Path:
    p = d / "small.clf"
    if not p.exists():
        p.write_text(carmen_text())
    return p


def tum_text(n: int = 40, stamp0: float = 100.0, dt: float = 0.2) -> str:
    return "".join(
        f"{stamp0 + dt * i:.6f} {0.05 * i:.4f} 0 0 0 0 {np.sin(0.005 * i):.6f} {np.cos(0.005 * i):.6f}\n"
        for i in range(n)
    )


def metric_plan(d: Path) -> Path:
    """The five-room plan in metres (as ``frslam register`` writes one), for ``navigate``."""
    from frslam_graph.datasets.simulator import five_room_plan

    p = d / "metric_plan.json"
    if not p.exists():
        five_room_plan().transformed(np.diag([0.05, 0.05, 1.0]), units="m").save(p)
    return p


def good_plan(d: Path) -> Path:
    from frslam_graph.datasets.simulator import five_room_plan

    p = d / "good_plan.json"
    if not p.exists():
        five_room_plan().save(p)
    return p


def write(p: Path, data: bytes | str) -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    p.write_bytes(data)
    return p


def junk(n: int, seed: int = 1) -> bytes:
    return random.Random(seed).randbytes(n)


def png_header_only(width: int, height: int, bit_depth: int = 8, color: int = 0) -> bytes:
    """A PNG whose IHDR claims width x height, with a tiny (wrong) IDAT."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\x00" * 1000))
        + chunk(b"IEND", b"")
    )


def png_bomb(side: int) -> bytes:
    """A valid PNG of side x side zero pixels whose data compresses to a few hundred kB."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    comp = zlib.compressobj(9)
    row = b"\x00" * (side + 1)
    body = b"".join(comp.compress(row) for _ in range(side)) + comp.flush()
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body) + chunk(b"IEND", b"")


def image(p: Path, arr: np.ndarray) -> Path:
    import cv2

    p.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(p), arr)
    return p


def map_yaml(d: Path, body: str, img: str = "m.pgm", make_image: bool = True) -> Path:
    if make_image:
        a = np.full((60, 80), 254, np.uint8)
        a[0, :] = a[-1, :] = a[:, 0] = a[:, -1] = 0
        image(d / img, a)
    return write(d / "m.yaml", body)


MAP_OK = "image: m.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"


def alias_bomb(levels: int = 12, fan: int = 10) -> str:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * fan) + "]")
    return "\n".join(lines)


def roomseg(d: Path, labels: np.ndarray, yaml_body: str | None = None) -> tuple[Path, Path]:
    png = image(d / "segRoomSeg.png", labels)
    y = write(
        d / "seg.yaml",
        yaml_body
        or "image: seg.png\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
    )
    return png, y


def plan_image(d: Path, arr: np.ndarray, name: str = "plan.png") -> Path:
    return image(d / name, arr)


def drawn_plan() -> np.ndarray:
    a = np.full((200, 300), 255, np.uint8)
    a[20:25, 20:280] = a[175:180, 20:280] = 0
    a[20:180, 20:25] = a[20:180, 275:280] = a[20:180, 148:153] = 0
    a[90:110, 148:153] = 255
    return a


def bag_messages(n: int = 5):
    from tests.test_rosbag import standard_messages

    return standard_messages(ros1=True, n=n)


def ros1_bag(p: Path, n: int = 20) -> Path:
    from tests.test_rosbag import standard_messages, write_bag

    if not p.exists():
        write_bag(p, standard_messages(ros1=True, n=n), ros1=True)
    return p


def ros2_bag(folder: Path, storage: str = "sqlite3", n: int = 20) -> Path:
    from rosbags.rosbag2 import StoragePlugin

    from tests.test_rosbag import standard_messages, write_bag

    plug = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    if not folder.exists():
        write_bag(folder, standard_messages(ros1=False, n=n), ros1=False, storage=plug)
    return folder


def storage_file(folder: Path) -> Path:
    return next(p for p in folder.iterdir() if p.suffix in (".db3", ".mcap"))


def nested_json(depth: int) -> str:
    return "[" * depth + "]" * depth


def run_rec(d: Path, rec: Path | str) -> list[str]:
    """``frslam run`` on a recording (content problems: ``inspect`` reports them in its table)."""
    return ["run", str(rec), "--out", str(d / "o"), "--sequential"]


# ---------------------------------------------------------------- CARMEN
@case("carmen", "empty")
def carmen_empty(d):
    return ["inspect", str(write(d / "e.clf", ""))], "e.clf"


@case("carmen", "junk")
def carmen_binary_junk(d):
    return ["inspect", str(write(d / "junk.clf", junk(200_000)))], "junk.clf"


@case("carmen", "junk")
def carmen_text_junk(d):
    return ["inspect", str(write(d / "words.log", "hello world\n" * 1000))], "words.log"


@case("carmen", "truncated", expect="warn")
def carmen_cut_mid_line(d):
    t = carmen_text()
    return ["inspect", str(write(d / "cut.clf", t[: len(t) // 2 + 7]))], "cut.clf"


@case("carmen", "truncated", expect="warn")
def carmen_gz_truncated(d):
    data = gzip.compress(carmen_text(200).encode())
    return ["inspect", str(write(d / "cut.clf.gz", data[: len(data) // 2]))], "cut.clf.gz"


@case("carmen", "truncated", expect="warn")
def carmen_bz2_truncated(d):
    data = bz2.compress(carmen_text(400).encode())
    return ["inspect", str(write(d / "cut.clf.bz2", data[: len(data) // 2]))], "cut.clf.bz2"


@case("carmen", "truncated")
def carmen_gz_header_only(d):
    data = gzip.compress(carmen_text().encode())
    return ["inspect", str(write(d / "hdr.clf.gz", data[:12]))], "hdr.clf.gz"


@case("carmen", "junk")
def carmen_gz_not_gzip(d):
    return ["inspect", str(write(d / "plain.clf.gz", carmen_text()))], "plain.clf.gz"


@case("carmen", "junk")
def carmen_bz2_is_gzip(d):
    return [
        "inspect",
        str(write(d / "wrong.clf.bz2", gzip.compress(carmen_text().encode()))),
    ], "wrong.clf.bz2"


@case("carmen", "bomb")
def carmen_bz2_bomb_newlines(d):
    comp = bz2.BZ2Compressor(9)
    chunk = b"\n" * (1 << 20)
    data = b"".join(comp.compress(chunk) for _ in range(1024)) + comp.flush()
    return ["inspect", str(write(d / "nl.clf.bz2", data))], "nl.clf.bz2"


@case("carmen", "bomb")
def carmen_gz_bomb_one_line(d):
    comp = zlib.compressobj(9, zlib.DEFLATED, 31)
    chunk = b"A" * (1 << 20)
    data = b"".join(comp.compress(chunk) for _ in range(1024)) + comp.flush()
    return ["inspect", str(write(d / "line.clf.gz", data))], "line.clf.gz"


@case("carmen", "bomb")
def carmen_gz_bomb_valid_lines(d):
    """A real-looking FLASER line repeated: compresses over 100x (refused as a bomb or read)."""
    line = carmen_text(1).splitlines()[1] + "\n"
    comp = zlib.compressobj(9, zlib.DEFLATED, 31)
    data = b"".join(comp.compress(line.encode() * 10_000) for _ in range(100)) + comp.flush()
    return ["inspect", str(write(d / "rep.clf.gz", data))], "rep.clf.gz"


@case("carmen", "huge header")
def carmen_huge_beam_count(d):
    return [
        "inspect",
        str(write(d / "n.clf", "FLASER 1000000000 1 2 3 0 0 0 0 0 0 100.0 h 100.0\n" * 3)),
    ], "n.clf"


@case("carmen", "huge header")
def carmen_negative_beam_count(d):
    return [
        "inspect",
        str(write(d / "neg.clf", "FLASER -5 1 2 3 0 0 0 0 0 0 100.0 h 100.0\n" * 3)),
    ], "neg.clf"


@case("carmen", "huge header")
def carmen_long_line(d):
    return ["inspect", str(write(d / "long.clf", "FLASER 3 " + "1.0 " * 600_000 + "\n"))], "long.clf"


@case("carmen", "wrong type")
def carmen_words_for_numbers(d):
    t = carmen_text(5).replace("FLASER 90 ", "FLASER ninety ")
    return ["inspect", str(write(d / "w.clf", t))], "w.clf"


@case("carmen", "nan/inf")
def carmen_nan_pose(d):
    lines = carmen_text(10).splitlines()
    lines = [
        re.sub(r" (\S+) (\S+) (\S+) (\S+) (\S+) (\S+) (\S+) host", r" nan nan nan nan nan nan \7 host", x)
        if x.startswith("FLASER")
        else x
        for x in lines
    ]
    return run_rec(d, write(d / "nanpose.clf", "\n".join(lines) + "\n")), "nanpose.clf"


@case("carmen", "nan/inf")
def carmen_inf_stamps(d):
    lines = [re.sub(r"\d+\.\d+ host \d+\.\d+$", "inf host inf", x) for x in carmen_text(10).splitlines()]
    return run_rec(d, write(d / "infstamp.clf", "\n".join(lines) + "\n")), "infstamp.clf"


@case("carmen", "nan/inf", expect="warn")
def carmen_nan_ranges(d):
    lines = carmen_text(10).splitlines()
    lines = [x.replace(" 2.000 ", " nan ").replace("7.900", "inf") for x in lines]
    return ["inspect", str(write(d / "nanr.clf", "\n".join(lines) + "\n"))], "nanr.clf"


@case("carmen", "duplicates", expect="warn")
def carmen_equal_stamps(d):
    lines = [
        re.sub(r"\d+\.\d+ host \d+\.\d+$", "100.000000 host 100.000000", x)
        for x in carmen_text(30).splitlines()
    ]
    return ["inspect", str(write(d / "same.clf", "\n".join(lines) + "\n"))], "same.clf"


@case("carmen", "device")
def carmen_dev_zero(d):
    (d / "zero.clf").symlink_to("/dev/zero")
    return ["inspect", str(d / "zero.clf")], "zero.clf"


@case("carmen", "device")
def carmen_dev_urandom_gz(d):
    (d / "rnd.clf.gz").symlink_to("/dev/urandom")
    return ["inspect", str(d / "rnd.clf.gz")], "rnd.clf.gz"


@case("carmen", "missing")
def carmen_missing(d):
    return ["inspect", str(d / "nope.clf")], "nope.clf"


@case("carmen", "wrong type")
def carmen_directory(d):
    (d / "dir.clf").mkdir()
    return ["inspect", str(d / "dir.clf")], "dir.clf"


@case("carmen", "junk")
def carmen_run_junk(d):
    return ["run", str(write(d / "junk2.clf", junk(50_000, 7))), "--out", str(d / "o")], "junk2.clf"


@case("carmen", "truncated", expect="ok")
def carmen_run_one_scan(d):
    t = carmen_text(1)
    return ["run", str(write(d / "one.clf", t)), "--out", str(d / "o")], "one.clf"


# ---------------------------------------------------------------- ROS 1 bag
@case("ros1", "empty")
def ros1_empty(d):
    return ["inspect", str(write(d / "e.bag", ""))], "e.bag"


@case("ros1", "junk")
def ros1_junk(d):
    return ["inspect", str(write(d / "j.bag", junk(100_000)))], "j.bag"


@case("ros1", "junk")
def ros1_magic_then_junk(d):
    return ["inspect", str(write(d / "mj.bag", b"#ROSBAG V2.0\n" + junk(100_000)))], "mj.bag"


@case("ros1", "truncated", expect="warn")
def ros1_cut_half(d):
    src = ros1_bag(d / "full.bag", 200).read_bytes()
    return ["inspect", str(write(d / "half.bag", src[: len(src) // 2]))], "half.bag"


@case("ros1", "truncated")
def ros1_header_only(d):
    src = ros1_bag(d / "full.bag").read_bytes()
    return ["inspect", str(write(d / "hdr.bag", src[:4200]))], "hdr.bag"


@case("ros1", "truncated", expect="warn")
def ros1_shared_cut(d):
    src = (SHARED / "bags" / "scan_tools_demo.bag").read_bytes()
    return ["inspect", str(write(d / "demo_cut.bag", src[: int(len(src) * 0.6)]))], "demo_cut.bag"


@case("ros1", "huge header")
def ros1_huge_header_len(d):
    src = bytearray(ros1_bag(d / "full.bag").read_bytes())
    src[13:17] = struct.pack("<I", 0x7FFFFFF0)  # bag header record's header length
    return ["inspect", str(write(d / "hh.bag", bytes(src)))], "hh.bag"


@case("ros1", "huge header", expect="warn")
def ros1_huge_data_len(d):
    src = bytearray(ros1_bag(d / "full.bag").read_bytes())
    hlen = struct.unpack("<I", src[13:17])[0]
    off = 17 + hlen
    src[off : off + 4] = struct.pack("<I", 0x7FFFFFF0)
    return ["inspect", str(write(d / "hd.bag", bytes(src)))], "hd.bag"


@case("ros1", "wrong type")
def ros1_no_scans(d):
    from tests.test_rosbag import standard_messages, write_bag

    msgs = [m for m in standard_messages(ros1=True, n=5) if m[0] == "/odom"]
    return ["inspect", str(write_bag(d / "odom.bag", msgs, ros1=True))], "odom.bag"


@case("options", "wrong option")
def ros1_bad_topic(d):
    return ["inspect", str(ros1_bag(d / "full.bag")), "--scan-topic", "/nope"], "--scan-topic"


@case("options", "wrong option")
def ros1_odom_topic_is_scan(d):
    return ["inspect", str(ros1_bag(d / "full.bag")), "--odom-topic", "/scan"], "--odom-topic"


@case("options", "wrong option")
def ros1_laser_on_bag(d):
    return ["inspect", str(ros1_bag(d / "full.bag")), "--laser", "rear"], "--laser"


# ---------------------------------------------------------------- ROS 2
@case("ros2", "empty")
def db3_empty(d):
    return ["inspect", str(write(d / "e.db3", ""))], "e.db3"


@case("ros2", "junk")
def db3_junk(d):
    return ["inspect", str(write(d / "j.db3", junk(100_000)))], "j.db3"


@case("ros2", "truncated")
def db3_cut(d):
    src = storage_file(ros2_bag(d / "b2", n=200)).read_bytes()
    return ["inspect", str(write(d / "cut.db3", src[: len(src) // 2]))], "cut.db3"


@case("ros2", "wrong type")
def db3_other_schema(d):
    import sqlite3

    p = d / "other.db3"
    con = sqlite3.connect(p)
    con.execute("create table t (a int)")
    con.commit()
    con.close()
    return ["inspect", str(p)], "other.db3"


@case("ros2", "empty")
def mcap_empty(d):
    return ["inspect", str(write(d / "e.mcap", ""))], "e.mcap"


@case("ros2", "junk")
def mcap_junk(d):
    return ["inspect", str(write(d / "j.mcap", b"\x89MCAP0\r\n" + junk(100_000)))], "j.mcap"


@case("ros2", "truncated", expect="warn")
def mcap_cut(d):
    src = storage_file(ros2_bag(d / "m2", "mcap", n=200)).read_bytes()
    return ["inspect", str(write(d / "cut.mcap", src[: len(src) // 2]))], "cut.mcap"


@case("ros2", "junk")
def ros2_metadata_junk(d):
    f = d / "mj"
    write(f / "metadata.yaml", junk(5000))
    return ["inspect", str(f)], "mj"


@case("ros2", "bomb")
def ros2_metadata_alias_bomb(d):
    f = d / "mb"
    write(f / "metadata.yaml", alias_bomb())
    return ["inspect", str(f)], "mb"


@case("ros2", "missing")
def ros2_metadata_without_storage(d):
    src = ros2_bag(d / "b2")
    f = d / "nostore"
    write(f / "metadata.yaml", (src / "metadata.yaml").read_text())
    return ["inspect", str(f)], "nostore"


# ---------------------------------------------------------------- point clouds
PCD_HEAD = "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n"


def pcd_folder(d: Path, name: str, data: bytes | str) -> Path:
    f = d / name
    write(f / "000001.pcd", data)
    return f


@case("pcd", "huge header")
def pcd_claims_billion_points(d):
    return [
        "inspect",
        str(pcd_folder(d, "big", PCD_HEAD.format(n=1_000_000_000, kind="binary") + "\0" * 120)),
    ], "000001.pcd"


@case("pcd", "truncated")
def pcd_ascii_truncated(d):
    body = PCD_HEAD.format(n=500, kind="ascii") + "1 2 0\n3 4 0\n"
    return ["inspect", str(pcd_folder(d, "trunc", body))], "000001.pcd"


@case("pcd", "truncated")
def pcd_binary_truncated(d):
    body = PCD_HEAD.format(n=500, kind="binary").encode() + np.ones((20, 3), np.float32).tobytes()
    return ["inspect", str(pcd_folder(d, "btrunc", body))], "000001.pcd"


@case("pcd", "empty")
def pcd_empty_file(d):
    return run_rec(d, str(pcd_folder(d, "emp", ""))), "000001.pcd"


@case("pcd", "junk")
def pcd_junk(d):
    return run_rec(d, str(pcd_folder(d, "jk", junk(20_000)))), "000001.pcd"


@case("pcd", "nan/inf", expect="warn")
def pcd_nan_points(d):
    body = PCD_HEAD.format(n=4, kind="ascii") + "nan nan nan\ninf 1 0\n1 2 0\n3 4 0\n"
    return ["inspect", str(pcd_folder(d, "nanp", body))], "nanp"


@case("pcd", "wrong type")
def pcd_no_xyz_fields(d):
    body = PCD_HEAD.format(n=2, kind="ascii").replace("FIELDS x y z", "FIELDS a b c") + "1 2 0\n3 4 0\n"
    return run_rec(d, str(pcd_folder(d, "noxyz", body))), "000001.pcd"


@case("pcd", "huge header")
def pcd_binary_compressed_huge(d):
    head = PCD_HEAD.format(n=2, kind="binary_compressed").encode()
    body = head + struct.pack("<II", 100, 0x7FFFFFF0) + junk(100)
    return run_rec(d, str(pcd_folder(d, "bc", body))), "000001.pcd"


@case("pcd", "huge header")
def ply_claims_billion_vertices(d):
    f = d / "ply"
    write(
        f / "a.ply",
        "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        + "\0" * 120,
    )
    return ["inspect", str(f)], "a.ply"


@case("pcd", "wrong type")
def pcd_words(d):
    body = PCD_HEAD.format(n=2, kind="ascii") + "one two three\nfour five six\n"
    return run_rec(d, str(pcd_folder(d, "words", body))), "000001.pcd"


# ---------------------------------------------------------------- maps (map_server)
def map_show(d: Path, y: Path) -> list[str]:
    return ["map", "show", str(y), "--out", str(d / "o.png")]


@case("map", "missing")
def map_image_missing(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "gone.pgm"), make_image=False)), "gone.pgm"


@case("map", "empty")
def map_yaml_empty(d):
    return map_show(d, write(d / "m.yaml", "")), "m.yaml"


@case("map", "junk")
def map_yaml_binary(d):
    return map_show(d, write(d / "m.yaml", junk(4000))), "m.yaml"


@case("map", "bomb")
def map_yaml_alias_bomb(d):
    return map_show(
        d, map_yaml(d, MAP_OK.replace("origin: [0.0, 0.0, 0.0]", "origin: *a11") + alias_bomb() + "\n")
    ), "m.yaml"


@case("map", "duplicates")
def map_yaml_duplicate_key(d):
    return map_show(d, map_yaml(d, MAP_OK + "resolution: 5.0\n")), "m.yaml"


@case("map", "nan/inf")
def map_resolution_nan(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("0.05", ".nan"))), "m.yaml"


@case("map", "nan/inf")
def map_resolution_huge(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("0.05", "1e300"))), "m.yaml"


@case("map", "wrong type")
def map_resolution_bool(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("0.05", "true"))), "m.yaml"


@case("map", "wrong type")
def map_resolution_string(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("0.05", "'0.05'"))), "m.yaml"


@case("map", "wrong type")
def map_origin_short(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("[0.0, 0.0, 0.0]", "[0.0]"))), "m.yaml"


@case("map", "nan/inf")
def map_origin_inf(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("[0.0, 0.0, 0.0]", "[.inf, 0.0, 0.0]"))), "m.yaml"


@case("map", "wrong type")
def map_thresholds_swapped(d):
    return map_show(d, map_yaml(d, MAP_OK.replace("0.65", "1.5"))), "m.yaml"


@case("map", "huge header")
def map_png_header_20000(d):
    write(d / "big.png", png_header_only(20000, 20000))
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "big.png"), make_image=False)), "big.png"


@case("map", "bomb")
def map_png_bomb_15000(d):
    write(d / "bomb.png", png_bomb(15000))
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "bomb.png"), make_image=False)), "bomb.png"


@case("map", "huge header")
def map_pgm_header_100000(d):
    write(d / "big.pgm", b"P5\n100000 100000\n255\n" + b"\0" * 1000)
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "big.pgm"), make_image=False)), "big.pgm"


@case("map", "truncated")
def map_pgm_truncated(d):
    write(d / "t.pgm", b"P5\n800 600\n255\n" + b"\xfe" * 1000)
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "t.pgm"), make_image=False)), "t.pgm"


@case("map", "truncated")
def map_png_truncated(d):
    import cv2

    ok, buf = cv2.imencode(".png", (np.random.default_rng(0).random((300, 300)) * 255).astype(np.uint8))
    write(d / "t.png", buf.tobytes()[: len(buf) // 2])
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "t.png"), make_image=False)), "t.png"


@case("map", "junk")
def map_image_junk(d):
    write(d / "j.png", junk(5000))
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "j.png"), make_image=False)), "j.png"


@case("map", "wrong type")
def map_image_is_dir(d):
    (d / "dir.png").mkdir()
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "dir.png"), make_image=False)), "dir.png"


@case("map", "device")
def map_image_dev_zero(d):
    (d / "z.pgm").symlink_to("/dev/zero")
    return map_show(d, map_yaml(d, MAP_OK.replace("m.pgm", "z.pgm"), make_image=False)), "z.pgm"


@case("map", "bomb")
def map_yaml_nested_deep(d):
    return map_show(d, write(d / "m.yaml", "origin: " + nested_json(100_000) + "\n")), "m.yaml"


@case("map", "wrong type")
def map_yaml_python_tag(d):
    return map_show(d, map_yaml(d, MAP_OK + "x: !!python/object/apply:os.system ['true']\n")), "m.yaml"


@case("options", "nan/inf")
def map_image_resolution_nan(d):
    png = image(d / "m.png", drawn_plan())
    return ["map", "show", str(png), "--resolution", "nan", "--out", str(d / "o.png")], "--resolution"


@case("options", "wrong type")
def map_image_resolution_zero(d):
    png = image(d / "m.png", drawn_plan())
    return ["map", "show", str(png), "--resolution", "0", "--out", str(d / "o.png")], "--resolution"


@case("options", "wrong option")
def map_yaml_with_resolution(d):
    return [
        "map",
        "show",
        str(map_yaml(d, MAP_OK)),
        "--resolution",
        "0.1",
        "--out",
        str(d / "o.png"),
    ], "--resolution"


# ---------------------------------------------------------------- plan JSON
def convert(d: Path, p: Path, *extra: str) -> list[str]:
    return ["plan", "convert", str(p), str(d / "out.json"), *extra]


_PLAN_TEXT: list[str] = []


def _plan_text() -> str:
    if not _PLAN_TEXT:
        from frslam_graph.datasets.simulator import five_room_plan

        _PLAN_TEXT.append(json.dumps(five_room_plan().to_dict()))
    return _PLAN_TEXT[0]


def spoiled_plan(d: Path, name: str, fn) -> Path:
    data = json.loads(_plan_text())
    fn(data)
    return write(d / name, json.dumps(data))


@case("plan-json", "empty")
def plan_json_empty(d):
    return convert(d, write(d / "e.json", "")), "e.json"


@case("plan-json", "junk")
def plan_json_binary(d):
    return convert(d, write(d / "j.json", junk(8000))), "j.json"


@case("plan-json", "truncated")
def plan_json_cut(d):
    t = _plan_text()
    return convert(d, write(d / "cut.json", t[: len(t) // 2])), "cut.json"


@case("plan-json", "bomb")
def plan_json_nested(d):
    return convert(d, write(d / "deep.json", '{"rooms": ' + nested_json(100_000) + "}")), "deep.json"


@case("plan-json", "nan/inf")
def plan_json_nan_vertex(d):
    def f(p):
        p["rooms"][0]["polygon"][0][0] = "NaN_"

    t = json.dumps(json.loads(_plan_text()))
    data = json.loads(t)
    data["rooms"][0]["polygon"][0][0] = 0.0
    s = json.dumps(data).replace("[0.0,", "[NaN,", 1)
    return convert(d, write(d / "nan.json", s)), "nan.json"


@case("plan-json", "nan/inf")
def plan_json_huge_number(d):
    data = json.loads(_plan_text())
    data["rooms"][0]["polygon"][0][0] = 0.0
    s = json.dumps(data).replace("[0.0,", "[1e400,", 1)
    return convert(d, write(d / "inf.json", s)), "inf.json"


@case("plan-json", "nan/inf")
def plan_json_1e300(d):
    def f(p):
        for r in p["rooms"]:
            r["polygon"] = [[x * 1e300, y * 1e300] for x, y in r["polygon"]]

    return convert(d, spoiled_plan(d, "e300.json", f)), "e300.json"


@case("plan-json", "wrong type")
def plan_json_bool_vertex(d):
    def f(p):
        p["rooms"][0]["polygon"][0] = [True, False]

    return convert(d, spoiled_plan(d, "bool.json", f)), "bool.json"


@case("plan-json", "wrong type")
def plan_json_string_number(d):
    def f(p):
        p["rooms"][0]["polygon"][0][0] = "107.0"

    return convert(d, spoiled_plan(d, "str.json", f)), "str.json"


@case("plan-json", "wrong type")
def plan_json_rooms_dict(d):
    def f(p):
        p["rooms"] = {"a": 1}

    return convert(d, spoiled_plan(d, "rd.json", f)), "rd.json"


@case("plan-json", "wrong type")
def plan_json_top_list(d):
    return convert(d, write(d / "list.json", "[1, 2, 3]")), "list.json"


@case("plan-json", "duplicates")
def plan_json_duplicate_room_ids(d):
    def f(p):
        p["rooms"][1]["id"] = p["rooms"][0]["id"]

    return convert(d, spoiled_plan(d, "dupid.json", f)), "dupid.json"


@case("plan-json", "duplicates")
def plan_json_duplicate_key(d):
    t = _plan_text()
    s = '{"rooms": [], ' + t[1:]
    return convert(d, write(d / "dupkey.json", s)), "dupkey.json"


@case("plan-json", "wrong type")
def plan_json_two_vertex_room(d):
    def f(p):
        p["rooms"][0]["polygon"] = p["rooms"][0]["polygon"][:2]

    return convert(d, spoiled_plan(d, "two.json", f)), "two.json"


@case("plan-json", "wrong type")
def plan_json_self_intersecting(d):
    def f(p):
        p["rooms"][0]["polygon"] = [[0, 0], [10, 10], [10, 0], [0, 10]]

    return convert(d, spoiled_plan(d, "bow.json", f)), "bow.json"


@case("plan-json", "wrong type")
def plan_json_door_unknown_room(d):
    def f(p):
        if p.get("doors"):
            p["doors"][0]["rooms"] = ["nowhere", "nothere"]
        else:
            p["doors"] = [{"rooms": ["nowhere", "nothere"], "segment": [[0, 0], [1, 0]]}]

    return convert(d, spoiled_plan(d, "door.json", f)), "door.json"


@case("plan-json", "huge header")
def plan_json_many_rooms(d):
    """9 MB: 60,000 small rooms."""
    rooms = [
        {"id": f"r{i}", "polygon": [[i * 3, 0], [i * 3 + 2, 0], [i * 3 + 2, 2], [i * 3, 2]]}
        for i in range(60_000)
    ]
    return [
        "plan",
        "show",
        str(write(d / "many.json", json.dumps({"rooms": rooms}))),
        "--out",
        str(d / "o.png"),
    ], "many.json"


@case("plan-json", "wrong type")
def plan_json_directory(d):
    (d / "dir.json").mkdir()
    return convert(d, d / "dir.json"), "dir.json"


@case("plan-json", "wrong type")
def plan_unknown_suffix(d):
    return convert(d, write(d / "plan.xyz", _plan_text())), "plan.xyz"


# ---------------------------------------------------------------- R2V
def r2v_lines(rows) -> str:
    return "".join("\t".join(str(v) for v in r) + "\t\n" for r in rows)


R2V_OK = [
    (0, 0, 100, 0, "wall", 1, 1),
    (100, 0, 100, 80, "wall", 1, 1),
    (100, 80, 0, 80, "wall", 1, 1),
    (0, 80, 0, 0, "wall", 1, 1),
    (20, 20, 40, 40, "bedroom", 1, 1),
]


@case("r2v", "empty")
def r2v_empty(d):
    return convert(d, write(d / "e.txt", "")), "e.txt"


@case("r2v", "junk")
def r2v_binary(d):
    return convert(d, write(d / "j.txt", junk(8000))), "j.txt"


@case("r2v", "wrong type")
def r2v_wrong_columns(d):
    return convert(d, write(d / "c.txt", "0 0 100\n1 2 3\n")), "c.txt"


@case("r2v", "nan/inf")
def r2v_nan(d):
    rows = [*R2V_OK, ("nan", 0, 50, "inf", "wall", 1, 1)]
    return convert(d, write(d / "n.txt", r2v_lines(rows))), "n.txt"


@case("r2v", "nan/inf")
def r2v_1e300(d):
    rows = [*R2V_OK, (0, 0, 1e300, 0, "wall", 1, 1)]
    return convert(d, write(d / "big.txt", r2v_lines(rows))), "big.txt"


@case("r2v", "huge header")
def r2v_too_many_walls(d):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 1000, (250_000, 4))
    return convert(
        d, write(d / "many.txt", "".join(f"{r[0]} {r[1]} {r[2]} {r[3]} wall 1 1\n" for r in a))
    ), "many.txt"


@case("r2v", "huge header")
def r2v_many_random_walls_under_limit(d):
    rng = np.random.default_rng(1)
    a = rng.integers(0, 1000, (100_000, 4))
    return convert(
        d, write(d / "rnd.txt", "".join(f"{r[0]} {r[1]} {r[2]} {r[3]} wall 1 1\n" for r in a))
    ), "rnd.txt"


@case("r2v", "wrong type")
def r2v_no_walls(d):
    return convert(d, write(d / "nw.txt", r2v_lines([(20, 20, 40, 40, "bedroom", 1, 1)]))), "nw.txt"


@case("r2v", "truncated", expect="warn")
def r2v_cut_mid_line(d):
    return convert(d, write(d / "cut.txt", r2v_lines(R2V_OK)[:-9])), "cut.txt"


# ---------------------------------------------------------------- HouseExpo
HOUSE = {
    "id": "h",
    "room_num": 2,
    "bbox": {"min": [0, 0], "max": [10, 8]},
    "verts": [[0, 0], [10, 0], [10, 8], [0, 8]],
    "room_category": {"bedroom": [[1, 1, 4, 4]], "kitchen": [[6, 1, 9, 7]]},
}


def house(d: Path, name: str, **change) -> Path:
    h = json.loads(json.dumps(HOUSE))
    h.update(change)
    return write(d / name, json.dumps(h))


@case("houseexpo", "nan/inf")
def house_nan_vertex(d):
    return convert(d, write(d / "n.json", json.dumps(HOUSE).replace("[10, 0]", "[NaN, 0]"))), "n.json"


@case("houseexpo", "wrong type")
def house_self_intersecting(d):
    return convert(d, house(d, "bow.json", verts=[[0, 0], [10, 8], [10, 0], [0, 8]])), "bow.json"


@case("houseexpo", "wrong type")
def house_verts_not_list(d):
    return convert(d, house(d, "v.json", verts="square")), "v.json"


@case("houseexpo", "wrong type")
def house_room_outside(d):
    return convert(
        d, house(d, "outside.json", room_category={"bedroom": [[1, 1, 4, 4]], "kitchen": [[50, 50, 60, 60]]})
    ), "kitchen"


@case("houseexpo", "wrong type")
def house_bool_vertex(d):
    return convert(d, house(d, "b.json", verts=[[0, 0], [True, 0], [10, 8], [0, 8]])), "b.json"


@case("houseexpo", "wrong type")
def house_category_junk(d):
    return convert(d, house(d, "c.json", room_category=[1, 2, 3])), "c.json"


@case("houseexpo", "huge header")
def house_many_verts(d):
    t = np.linspace(0, 2 * np.pi, 400_000, endpoint=False)
    verts = np.column_stack((50 + 40 * np.cos(t), 50 + 40 * np.sin(t))).round(3).tolist()
    return convert(
        d, house(d, "mv.json", verts=verts, room_category={"bedroom": [[40, 40, 60, 60]]})
    ), "mv.json"


# ---------------------------------------------------------------- room segmentation
@case("roomseg", "empty")
def roomseg_no_rooms(d):
    png, y = roomseg(d, np.zeros((100, 100), np.uint8))
    return convert(d, png, "--yaml", str(y)), "segRoomSeg.png"


@case("roomseg", "junk", expect="warn")
def roomseg_noise_labels(d):
    """Every pixel its own room (16-bit labels): 1 million rooms of one pixel."""
    lab = (np.random.default_rng(0).integers(1, 65535, (1000, 1000))).astype(np.uint16)
    png, y = roomseg(d, lab)
    return convert(d, png, "--yaml", str(y)), "segRoomSeg.png"


@case("roomseg", "junk", expect="warn")
def roomseg_noise_8bit(d):
    lab = (np.random.default_rng(0).integers(1, 200, (800, 800))).astype(np.uint8)
    png, y = roomseg(d, lab)
    return convert(d, png, "--yaml", str(y)), "segRoomSeg.png"


@case("roomseg", "huge header")
def roomseg_header_bomb(d):
    write(d / "bigRoomSeg.png", png_header_only(30000, 30000))
    y = write(d / "big.yaml", MAP_OK.replace("m.pgm", "big.png"))
    return convert(d, d / "bigRoomSeg.png", "--yaml", str(y)), "bigRoomSeg.png"


@case("roomseg", "bomb")
def roomseg_yaml_alias_bomb(d):
    lab = np.zeros((100, 100), np.uint8)
    lab[10:50, 10:50] = 1
    png, y = roomseg(d, lab, "image: seg.png\nresolution: *a11\norigin: [0, 0, 0]\n" + alias_bomb() + "\n")
    return convert(d, png, "--yaml", str(y)), "seg.yaml"


@case("roomseg", "missing")
def roomseg_yaml_missing(d):
    lab = np.zeros((100, 100), np.uint8)
    lab[10:50, 10:50] = 1
    png, _ = roomseg(d, lab)
    return convert(d, png, "--yaml", str(d / "gone.yaml")), "gone.yaml"


@case("roomseg", "nan/inf")
def roomseg_yaml_nan_resolution(d):
    lab = np.zeros((100, 100), np.uint8)
    lab[10:50, 10:50] = 1
    png, y = roomseg(d, lab, "image: seg.png\nresolution: .nan\norigin: [0, 0, 0]\n")
    return convert(d, png, "--yaml", str(y)), "seg.yaml"


@case("roomseg", "truncated")
def roomseg_png_truncated(d):
    import cv2

    lab = np.zeros((300, 300), np.uint8)
    lab[10:150, 10:150] = 1
    lab[150:290, 150:290] = 2
    ok, buf = cv2.imencode(".png", lab)
    write(d / "tRoomSeg.png", buf.tobytes()[: len(buf) // 2])
    y = write(d / "t.yaml", MAP_OK)
    return convert(d, d / "tRoomSeg.png", "--yaml", str(y)), "tRoomSeg.png"


# ---------------------------------------------------------------- plan images
@case("plan-image", "empty")
def plan_image_white(d):
    return convert(d, plan_image(d, np.full((200, 200), 255, np.uint8))), "plan.png"


@case("plan-image", "empty")
def plan_image_black(d):
    return convert(d, plan_image(d, np.zeros((200, 200), np.uint8))), "plan.png"


@case("plan-image", "junk")
def plan_image_noise(d):
    return convert(
        d, plan_image(d, (np.random.default_rng(0).random((2000, 2000)) > 0.5).astype(np.uint8) * 255)
    ), "plan.png"


@case("plan-image", "huge header")
def plan_image_header_bomb(d):
    return convert(d, write(d / "big.png", png_header_only(25000, 25000))), "big.png"


@case("plan-image", "bomb")
def plan_image_png_bomb(d):
    return convert(d, write(d / "bomb.png", png_bomb(19000))), "bomb.png"


@case("plan-image", "truncated")
def plan_image_truncated(d):
    import cv2

    ok, buf = cv2.imencode(".png", drawn_plan())
    return convert(d, write(d / "t.png", buf.tobytes()[: len(buf) // 2])), "t.png"


@case("plan-image", "junk")
def plan_image_jpeg_junk(d):
    return convert(d, write(d / "j.jpg", b"\xff\xd8\xff\xe0" + junk(5000))), "j.jpg"


@case("plan-image", "empty")
def plan_image_1px(d):
    return convert(d, plan_image(d, np.zeros((1, 1), np.uint8), "one.png")), "one.png"


@case("options", "missing")
def plan_image_segmentation_missing(d):
    return convert(d, plan_image(d, drawn_plan()), "--segmentation", str(d / "gone.png")), "gone.png"


@case("plan-image", "wrong type")
def plan_image_segmentation_other_size(d):
    seg = image(d / "seg.png", np.zeros((50, 50, 3), np.uint8))
    return convert(d, plan_image(d, drawn_plan()), "--segmentation", str(seg)), "seg.png"


@case("options", "nan/inf")
def plan_image_door_width_nan(d):
    return convert(d, plan_image(d, drawn_plan()), "--door-width", "nan"), "--door-width"


@case("options", "wrong type")
def plan_image_door_width_negative(d):
    return convert(d, plan_image(d, drawn_plan()), "--door-width", "-5"), "--door-width"


@case("options", "huge header")
def plan_image_door_width_huge(d):
    return convert(d, plan_image(d, drawn_plan()), "--door-width", "1e9"), "--door-width"


# ---------------------------------------------------------------- configuration
def run_cfg(d: Path, cfg: Path) -> list[str]:
    return ["run", str(small_log(d)), "--config", str(cfg), "--out", str(d / "o"), "--sequential"]


@case(
    "config",
    "empty",
    expect="ok",
    check=lambda d: None if (d / "o" / "metrics.json").exists() else "no metrics.json",
)
def config_empty_yaml(d):
    return run_cfg(d, write(d / "c.yaml", "")), "c.yaml"


@case("config", "junk")
def config_binary(d):
    return run_cfg(d, write(d / "c.yaml", junk(3000))), "c.yaml"


@case("config", "bomb")
def config_alias_bomb(d):
    return run_cfg(d, write(d / "c.yaml", alias_bomb() + "\nodometry:\n  max_range: *a11\n")), "c.yaml"


@case("config", "duplicates")
def config_duplicate_key(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_range: 10\n  max_range: 20\n")), "c.yaml"


@case("config", "wrong type")
def config_unknown_key(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_rnage: 10\n")), "max_rnage"


@case("config", "wrong type")
def config_bool_number(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_range: true\n")), "max_range"


@case("config", "wrong type")
def config_string_number(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_range: '10'\n")), "max_range"


@case("config", "wrong type")
def config_list_for_section(d):
    return run_cfg(d, write(d / "c.yaml", "odometry: [1, 2]\n")), "odometry"


@case("config", "nan/inf")
def config_inf_max_range(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_range: .inf\n")), "max_range"


@case("config", "nan/inf")
def config_nan_voxel(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  voxel_size: .nan\n")), "voxel_size"


@case("config", "wrong type")
def config_negative_voxel(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  voxel_size: -0.1\n")), "voxel_size"


@case("config", "nan/inf")
def config_huge_int(d):
    return run_cfg(d, write(d / "c.yaml", "odometry:\n  max_range: " + "9" * 500 + "\n")), "max_range"


@case("config", "wrong type")
def config_top_list(d):
    return run_cfg(d, write(d / "c.yaml", "- 1\n- 2\n")), "c.yaml"


@case("config", "wrong type")
def config_python_tag(d):
    return run_cfg(d, write(d / "c.yaml", "odometry: !!python/object/apply:os.system ['true']\n")), "c.yaml"


@case("config", "bomb")
def config_json_nested(d):
    return run_cfg(d, write(d / "c.json", '{"odometry": ' + nested_json(100_000) + "}")), "c.json"


@case("config", "nan/inf")
def config_json_nan(d):
    return run_cfg(d, write(d / "c.json", '{"odometry": {"max_range": NaN}}')), "max_range"


@case("config", "duplicates")
def config_json_duplicate_key(d):
    return run_cfg(d, write(d / "c.json", '{"odometry": {"max_range": 10, "max_range": 20}}')), "c.json"


@case("config", "wrong type")
def config_directory(d):
    (d / "cfgdir.yaml").mkdir()
    return run_cfg(d, d / "cfgdir.yaml"), "cfgdir.yaml"


@case("config", "device")
def config_dev_zero(d):
    (d / "z.yaml").symlink_to("/dev/zero")
    return run_cfg(d, d / "z.yaml"), "z.yaml"


@case("plan-json", "device")
def plan_json_dev_zero(d):
    (d / "z.json").symlink_to("/dev/zero")
    return convert(d, d / "z.json"), "z.json"


@case("config", "missing")
def config_missing(d):
    return run_cfg(d, d / "gone.yaml"), "gone.yaml"


@case("config", "huge header")
def config_huge_budget(d):
    return run_cfg(d, write(d / "c.yaml", "loop_closure:\n  resolution: 1.0e-9\n")), "resolution"


@case("config", "wrong type")
def config_unknown_suffix(d):
    return run_cfg(d, write(d / "c.toml", "a = 1\n")), "c.toml"


# ---------------------------------------------------------------- relations
def rel_cmd(d: Path, rel: Path) -> list[str]:
    return ["relations", str(write(d / "t.tum", tum_text())), str(rel)]


REL_OK = "".join(f"{100 + 0.2 * i:.6f} {100 + 0.2 * (i + 5):.6f} 0.25 0 0 0 0 0.025\n" for i in range(30))


@case("relations", "empty")
def relations_empty(d):
    return rel_cmd(d, write(d / "r.relations", "")), "r.relations"


@case("relations", "junk")
def relations_binary(d):
    return rel_cmd(d, write(d / "r.relations", junk(5000))), "r.relations"


@case("relations", "wrong type")
def relations_wrong_columns(d):
    return rel_cmd(d, write(d / "r.relations", "1 2 3\n4 5 6\n")), "r.relations"


@case("relations", "nan/inf")
def relations_nan(d):
    return rel_cmd(d, write(d / "r.relations", REL_OK.replace(" 0.25 ", " nan ", 3))), "r.relations"


@case("relations", "nan/inf")
def relations_inf_stamps(d):
    return rel_cmd(d, write(d / "r.relations", "inf inf 0 0 0 0 0 0\n" * 5)), "r.relations"


@case("relations", "wrong type")
def relations_words(d):
    return rel_cmd(d, write(d / "r.relations", REL_OK.replace("0.25", "a quarter", 1))), "r.relations"


@case("relations", "duplicates", expect="warn")
def relations_duplicate_rows(d):
    return rel_cmd(d, write(d / "r.relations", REL_OK + REL_OK)), "r.relations"


@case("relations", "wrong type")
def relations_other_recording(d):
    rel = "".join(f"{5000 + i:.6f} {5001 + i:.6f} 0.25 0 0 0 0 0.025\n" for i in range(30))
    return rel_cmd(d, write(d / "r.relations", rel)), "r.relations"


@case("options", "nan/inf")
def relations_tolerance_nan(d):
    return [*rel_cmd(d, write(d / "r.relations", REL_OK)), "--tolerance", "nan"], "--tolerance"


@case("options", "wrong type")
def relations_tolerance_negative(d):
    return [*rel_cmd(d, write(d / "r.relations", REL_OK)), "--tolerance", "-1"], "--tolerance"


@case("options", "nan/inf")
def relations_interpolate_inf(d):
    return [*rel_cmd(d, write(d / "r.relations", REL_OK)), "--interpolate", "inf"], "--interpolate"


# ---------------------------------------------------------------- TUM ground truth
def gt_run(d: Path, gt: Path) -> list[str]:
    return ["run", str(small_log(d)), "--ground-truth", str(gt), "--out", str(d / "o"), "--sequential"]


@case("tum", "empty")
def tum_empty(d):
    return gt_run(d, write(d / "gt.tum", "")), "gt.tum"


@case("tum", "junk")
def tum_binary(d):
    return gt_run(d, write(d / "gt.tum", junk(5000))), "gt.tum"


@case("tum", "wrong type")
def tum_seven_columns(d):
    return gt_run(
        d, write(d / "gt.tum", "".join(" ".join(x.split()[:7]) + "\n" for x in tum_text().splitlines()))
    ), "gt.tum"


@case("tum", "nan/inf")
def tum_nan(d):
    return gt_run(d, write(d / "gt.tum", tum_text().replace(" 0 0 0 0 ", " nan 0 0 0 ", 5))), "gt.tum"


@case("tum", "nan/inf")
def tum_zero_quaternion(d):
    return gt_run(
        d,
        write(d / "gt.tum", "".join(" ".join(x.split()[:4]) + " 0 0 0 0\n" for x in tum_text().splitlines())),
    ), "gt.tum"


@case("tum", "duplicates")
def tum_duplicate_stamps(d):
    return gt_run(
        d, write(d / "gt.tum", "".join(f"100.0 {x.split(' ', 1)[1]}\n" for x in tum_text().splitlines()))
    ), "gt.tum"


@case("tum", "wrong type")
def tum_unsorted(d):
    lines = tum_text().splitlines()
    random.Random(3).shuffle(lines)
    return gt_run(d, write(d / "gt.tum", "\n".join(lines) + "\n")), "gt.tum"


@case("tum", "wrong type")
def tum_other_recording(d):
    return gt_run(d, write(d / "gt.tum", tum_text(stamp0=9000.0))), "gt.tum"


@case("tum", "junk")
def tum_as_trajectory_binary(d):
    return [
        "relations",
        str(write(d / "traj.tum", junk(4000))),
        str(write(d / "r.relations", REL_OK)),
    ], "traj.tum"


@case("tum", "truncated")
def tum_cut_mid_row(d):
    t = tum_text()
    return [
        "relations",
        str(write(d / "traj.tum", t[: len(t) // 2 + 5])),
        str(write(d / "r.relations", REL_OK)),
    ], "traj.tum"


# ---------------------------------------------------------------- CLI options
def sim(d: Path, *extra: str) -> list[str]:
    return ["simulate", str(good_plan(d)), "--out", str(d / "sim"), "--length", "5", "--beams", "90", *extra]


for _opt, _val, _klass in [
    ("--beams", "-5", "wrong type"),
    ("--beams", "100000000", "huge header"),
    ("--max-range", "nan", "nan/inf"),
    ("--max-range", "inf", "nan/inf"),
    ("--noise", "-1", "wrong type"),
    ("--noise", "inf", "nan/inf"),
    ("--dropout", "2", "wrong type"),
    ("--fov", "0", "wrong type"),
    ("--scan-rate", "0", "wrong type"),
    ("--scan-rate", "1e9", "huge header"),
    ("--odom-rate", "nan", "nan/inf"),
    ("--speed", "0", "wrong type"),
    ("--length", "1e12", "huge header"),
    ("--length", "nan", "nan/inf"),
    ("--closed-doors", "-1", "wrong type"),
    ("--clutter", "1000000000", "huge header"),
    ("--metres-per-unit", "1e300", "huge header"),
    ("--metres-per-unit", "0", "wrong type"),
    ("--aspect-max", "nan", "nan/inf"),
    ("--rotation", "sideways", "wrong option"),
    ("--caster", "laser", "wrong option"),
    ("--rooms", "attic,cellar", "wrong option"),
    ("--map-completeness", "0", "wrong type"),
    ("--odom-heading-drift", "-3", "wrong type"),
]:

    def _mk(d, _o=_opt, _v=_val):
        return sim(d, _o, _v), _o

    _mk.__name__ = f"simulate{_opt.replace('-', '_')}_{re.sub(r'[^0-9a-z]', '_', _val)}"
    CASES.append(Case(_mk.__name__, "options", _klass, _mk))


@case("options", "wrong type")
def cli_not_a_number(d):
    return sim(d, "--beams", "many"), "--beams"


@case("options", "wrong option")
def cli_unknown_option(d):
    return sim(d, "--bemas", "10"), "--bemas"


@case("options", "wrong option")
def cli_unknown_command(d):
    return ["simulte"], "simulte"


@case("options", "wrong option")
def register_seed_room_unknown(d):
    return [
        "register",
        str(good_plan(d)),
        str(map_yaml(d, MAP_OK)),
        "--seed-room",
        "nope",
        "--out",
        str(d / "r"),
    ], "--seed-room"


@case("options", "wrong option")
def register_method_unknown(d):
    return [
        "register",
        str(good_plan(d)),
        str(map_yaml(d, MAP_OK)),
        "--method",
        "magic",
        "--out",
        str(d / "r"),
    ], "--method"


@case("options", "missing")
def register_plan_yaml_missing(d):
    lab = np.zeros((100, 100), np.uint8)
    lab[10:50, 10:50] = 1
    png, _ = roomseg(d, lab)
    return [
        "register",
        str(png),
        str(map_yaml(d, MAP_OK)),
        "--plan-yaml",
        str(d / "gone.yaml"),
        "--out",
        str(d / "r"),
    ], "gone.yaml"


@case("options", "nan/inf")
def navigate_from_nan(d):
    return [
        "navigate",
        str(metric_plan(d)),
        "--from",
        "nan",
        "1",
        "--to",
        "1,1",
        "--out",
        str(d / "p.png"),
    ], "--from"


@case("options", "huge header")
def navigate_resolution_tiny(d):
    return [
        "navigate",
        str(metric_plan(d)),
        "--from",
        "1",
        "1",
        "--to",
        "2,2",
        "--resolution",
        "1e-7",
        "--out",
        str(d / "p.png"),
    ], "--resolution"


@case("options", "wrong type")
def navigate_to_junk(d):
    return [
        "navigate",
        str(metric_plan(d)),
        "--from",
        "1",
        "1",
        "--to",
        "1,2,3",
        "--out",
        str(d / "p.png"),
    ], "--to"


@case("options", "nan/inf")
def navigate_clearance_inf(d):
    return [
        "navigate",
        str(metric_plan(d)),
        "--from",
        "1",
        "1",
        "--to",
        "2,2",
        "--clearance",
        "inf",
        "--out",
        str(d / "p.png"),
    ], "--clearance"


@case("options", "wrong option")
def run_odom_unknown(d):
    return ["run", str(small_log(d)), "--odom", "gps", "--out", str(d / "o")], "--odom"


@case("options", "wrong option")
def run_laser_unknown(d):
    return ["run", str(small_log(d)), "--laser", "left", "--out", str(d / "o")], "--laser"


@case("options", "wrong option")
def run_plane_tol_on_log(d):
    return ["run", str(small_log(d)), "--plane-tol", "0.1", "--out", str(d / "o")], "--plane-tol"


@case("options", "nan/inf")
def inspect_plane_tol_nan(d):
    f = pcd_folder(d, "ok", PCD_HEAD.format(n=2, kind="ascii") + "1 2 0\n3 4 0\n")
    return ["inspect", str(f), "--plane-tol", "nan"], "--plane-tol"


@case("options", "wrong option")
def run_viz_wrong_suffix(d):
    return ["run", str(small_log(d)), "--viz", str(d / "v.txt"), "--out", str(d / "o")], "--viz"


@case("options", "wrong type")
def demo_length_negative(d):
    return ["demo", "--length", "-5", "--out", str(d / "demo")], "--length"


@case("options", "wrong option")
def compare_without_plan(d):
    return ["compare", str(small_log(d)), "--out", str(d / "o")], "--floor-plan"


@case("options", "wrong option")
def run_plan_and_no_priors_missing_plan(d):
    return [
        "run",
        str(small_log(d)),
        "--floor-plan",
        str(d / "gone.json"),
        "--out",
        str(d / "o"),
    ], "gone.json"


# ---------------------------------------------------------------- outputs
def existing_file(d: Path) -> Path:
    return write(d / "taken", "mine\n")


@case("outputs", "existing --out")
def out_run_existing_file(d):
    return ["run", str(small_log(d)), "--out", str(existing_file(d))], "taken"


@case("outputs", "existing --out")
def out_simulate_existing_file(d):
    return ["simulate", str(good_plan(d)), "--out", str(existing_file(d)), "--length", "5"], "taken"


@case("outputs", "existing --out")
def out_register_existing_file(d):
    return ["register", str(good_plan(d)), str(map_yaml(d, MAP_OK)), "--out", str(existing_file(d))], "taken"


@case("outputs", "existing --out")
def out_plan_show_existing_dir(d):
    (d / "adir").mkdir()
    return ["plan", "show", str(good_plan(d)), "--out", str(d / "adir")], "adir"


@case("outputs", "wrong type")
def out_plan_show_txt(d):
    return ["plan", "show", str(good_plan(d)), "--out", str(d / "x.txt")], "x.txt"


@case("outputs", "existing --out")
def out_compare_existing_file(d):
    return [
        "compare",
        str(small_log(d)),
        "--floor-plan",
        str(good_plan(d)),
        "--out",
        str(existing_file(d)),
    ], "taken"


@case("outputs", "read-only")
def out_run_read_only(d):
    ro = d / "ro"
    ro.mkdir()
    return ["run", str(small_log(d)), "--out", str(ro / "run")], "ro"


@case("outputs", "read-only")
def out_convert_read_only(d):
    ro = d / "ro"
    ro.mkdir()
    return ["plan", "convert", str(good_plan(d)), str(ro / "p.json")], "ro"


@case("outputs", "read-only")
def out_map_show_read_only(d):
    ro = d / "ro"
    ro.mkdir()
    return ["map", "show", str(map_yaml(d, MAP_OK)), "--out", str(ro / "m.png")], "ro"


@case("outputs", "read-only")
def out_simulate_read_only(d):
    ro = d / "ro"
    ro.mkdir()
    return ["simulate", str(good_plan(d)), "--out", str(ro / "sim"), "--length", "5"], "ro"


@case("outputs", "wrong type")
def out_under_a_file(d):
    f = existing_file(d)
    return ["plan", "convert", str(good_plan(d)), str(f / "p.json")], "taken"


@case("outputs", "disk full")
def out_config_dump_dev_full(d):
    return ["config", "dump", "--out", "/dev/full"], "/dev/full"


@case("outputs", "existing --out")
def out_navigate_existing_dir(d):
    (d / "adir").mkdir()
    return [
        "navigate",
        str(metric_plan(d)),
        "--from",
        "1",
        "1",
        "--to",
        "2,2",
        "--out",
        str(d / "adir"),
    ], "adir"


def _victim_untouched(d: Path) -> str | None:
    v = d / "victim.txt"
    if v.read_text() != "not yours\n":
        return "the symlink's target was overwritten"
    return None


@case("outputs", "symlink", expect="ok", check=_victim_untouched)
def out_symlink_at_convert_target(d):
    write(d / "victim.txt", "not yours\n")
    (d / "p.json").symlink_to(d / "victim.txt")
    return ["plan", "convert", str(good_plan(d)), str(d / "p.json")], "p.json"


@case("outputs", "symlink", expect="ok", check=_victim_untouched)
def out_symlink_in_run_folder(d):
    write(d / "victim.txt", "not yours\n")
    (d / "o").mkdir()
    (d / "o" / "trajectory.tum").symlink_to(d / "victim.txt")
    (d / "o" / "metrics.json").symlink_to(d / "victim.txt")
    return ["run", str(small_log(d)), "--out", str(d / "o"), "--sequential"], "o"


@case("outputs", "symlink", expect="ok", check=_victim_untouched)
def out_symlink_config_dump(d):
    write(d / "victim.txt", "not yours\n")
    (d / "c.yaml").symlink_to(d / "victim.txt")
    return ["config", "dump", "--out", str(d / "c.yaml")], "c.yaml"


# ---------------------------------------------------------------- streaming API
API_HEAD = """
import sys, numpy as np
from frslam_graph.errors import FrslamError
from frslam_graph.slam import FRSlam
try:
    s = FRSlam()
    R = np.full(90, 3.0)
{body}
except FrslamError as e:
    print(f"frslam: {{e}}", file=sys.stderr)
    sys.exit(2)
"""

API_CASES = [
    ("api_ranges_string", "wrong type", "s.add_scan(0.0, 'far', -1.5, 0.03)", "ranges"),
    ("api_ranges_strings", "wrong type", "s.add_scan(0.0, ['1.0', '2.0'], -1.5, 0.03)", "ranges"),
    ("api_ranges_bools", "wrong type", "s.add_scan(0.0, [True, False] * 45, -1.5, 0.03)", "ranges"),
    ("api_ranges_2d", "wrong type", "s.add_scan(0.0, np.ones((4, 90)), -1.5, 0.03)", "ranges"),
    ("api_ranges_ragged", "wrong type", "s.add_scan(0.0, [[1, 2], [3]], -1.5, 0.03)", "ranges"),
    ("api_ranges_huge_string", "wrong type", "s.add_scan(0.0, 'x' * 50_000_000, -1.5, 0.03)", "ranges"),
    ("api_stamp_nan", "nan/inf", "s.add_scan(float('nan'), R, -1.5, 0.03)", "stamp"),
    ("api_stamp_string", "wrong type", "s.add_scan('1.0', R, -1.5, 0.03)", "stamp"),
    ("api_stamp_huge_string", "wrong type", "s.add_scan('1' * 50_000_000, R, -1.5, 0.03)", "stamp"),
    ("api_stamp_bool", "wrong type", "s.add_scan(True, R, -1.5, 0.03)", "stamp"),
    ("api_increment_zero", "wrong type", "s.add_scan(0.0, R, -1.5, 0.0)", "angle_increment"),
    ("api_angle_min_inf", "nan/inf", "s.add_scan(0.0, R, float('inf'), 0.03)", "angle_min"),
    ("api_range_max_negative", "wrong type", "s.add_scan(0.0, R, -1.5, 0.03, range_max=-1.0)", "range_max"),
    ("api_range_max_nan", "nan/inf", "s.add_scan(0.0, R, -1.5, 0.03, range_max=float('nan'))", "range_max"),
    (
        "api_range_max_huge_list",
        "wrong type",
        "s.add_scan(0.0, R, -1.5, 0.03, range_max=[1.0] * 10_000_000)",
        "range_max",
    ),
    ("api_odom_short", "wrong type", "s.add_scan(0.0, R, -1.5, 0.03, odom=(1.0, 2.0))", "odom"),
    ("api_odom_string", "wrong type", "s.add_scan(0.0, R, -1.5, 0.03, odom='home')", "odom"),
    (
        "api_sensor_offset_nan",
        "nan/inf",
        "s.add_scan(0.0, R, -1.5, 0.03, sensor_offset=(float('nan'), 0, 0))",
        "sensor_offset",
    ),
    (
        "api_sensor_offset_short",
        "wrong type",
        "s.add_scan(0.0, R, -1.5, 0.03, sensor_offset=(1, 2))",
        "sensor_offset",
    ),
    ("api_points_3d", "wrong type", "s.add_points(0.0, np.ones((10, 3)))", "points"),
    ("api_points_nan", "nan/inf", "s.add_points(0.0, np.full((10, 2), np.nan))", "points"),
    ("api_points_strings", "wrong type", "s.add_points(0.0, [['1', '2']] * 10)", "points"),
    ("api_floor_plan_int", "wrong type", "FRSlam(floor_plan=123)", "floor_plan"),
    ("api_floor_plan_missing", "missing", "FRSlam(floor_plan='gone_plan.json')", "gone_plan.json"),
    ("api_config_inf", "nan/inf", "FRSlam({'odometry': {'max_range': float('inf')}})", "max_range"),
    ("api_config_missing", "missing", "FRSlam('gone_config.yaml')", "gone_config.yaml"),
    ("api_config_wrong_type", "wrong type", "FRSlam(42)", "config"),
    ("api_grid_tiny", "huge header", "s.add_scan(0.0, R, -1.5, 0.03); s.occupancy_grid(1e-4)", "resolution"),
    ("api_grid_zero", "wrong type", "s.add_scan(0.0, R, -1.5, 0.03); s.occupancy_grid(0.0)", "resolution"),
    (
        "api_grid_nan",
        "nan/inf",
        "s.add_scan(0.0, R, -1.5, 0.03); s.occupancy_grid(float('nan'))",
        "resolution",
    ),
    (
        "api_grid_string",
        "wrong type",
        "s.add_scan(0.0, R, -1.5, 0.03); s.occupancy_grid('fine')",
        "resolution",
    ),
]

for _name, _klass, _body, _token in API_CASES:

    def _mk(d, _b=_body, _t=_token):
        return [API_HEAD.format(body="    " + _b)], _t

    _mk.__name__ = _name
    CASES.append(Case(_name, "api", _klass, _mk, api=True))


# ---------------------------------------------------------------- running
def run_case(c: Case, root: Path) -> Outcome:
    d = root / c.name
    d.mkdir(parents=True, exist_ok=True)
    try:
        argv, token = c.make(d)
    except Exception as exc:  # a case that cannot be built is the harness's fault: report it
        return Outcome(
            c,
            None,
            f"[harness] {type(exc).__name__}: {exc}",
            False,
            False,
            False,
            0.0,
            0.0,
            problem=["case not built"],
        )
    ro = [p for p in d.iterdir() if p.name == "ro"]
    for p in ro:
        subprocess.run(["chattr", "+i", str(p)], check=False)
    cmd = [PY, "-c", argv[0]] if c.api else [*FRSLAM, *argv]
    full = ["/usr/bin/time", "-v", *cmd]
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200", "OMP_NUM_THREADS": "1"}
    t0 = time.monotonic()
    errf = open(d / ".stderr", "w+b")  # noqa: SIM115 (a file, not a pipe: a huge message cannot block)
    with open(d / ".stdout", "wb") as outf:
        proc = subprocess.Popen(full, cwd=d, stdout=outf, stderr=errf, env=env, start_new_session=True)
    killed = ""
    peak_poll = 0.0
    ps = psutil.Process(proc.pid)
    while proc.poll() is None:
        try:
            rss = sum(p.memory_info().rss for p in [ps, *ps.children(recursive=True)]) / 1e6
        except psutil.Error:
            rss = 0.0
        peak_poll = max(peak_poll, rss)
        if rss > RSS_GUARD_MB:
            killed = f"killed at {rss:.0f} MB"
        elif time.monotonic() - t0 > TIMEOUT_S:
            killed = f"killed after {TIMEOUT_S:.0f} s"
        if killed:
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.05)
    proc.wait()
    seconds = time.monotonic() - t0
    errf.seek(0)
    err = errf.read(4_000_000)
    errf.close()
    for p in ro:
        subprocess.run(["chattr", "-i", str(p)], check=False)
    err_text = err.decode(errors="replace")
    split = err_text.split("\tCommand being timed:")
    own = re.sub(r"Command (exited with non-zero status|terminated by signal) \d+\n?", "", split[0])
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", err_text)
    rss_mb = max(int(m.group(1)) / 1024 if m else 0.0, peak_poll)
    m = re.search(r"Exit status: (\d+)", err_text)
    sig = re.search(r"Command terminated by signal (\d+)", err_text)
    code = int(m.group(1)) if m else (-int(sig.group(1)) if sig else proc.returncode)
    lines = [x for x in own.splitlines() if x.strip()]
    line = lines[0] if len(lines) == 1 else (f"[{len(lines)} lines] " + (lines[-1] if lines else ""))
    tb = "Traceback (most recent call last)" in own or "Fatal Python error" in own or "core dumped" in own
    names = token.lower() in own.lower()
    o = Outcome(c, code, line[:200], len(lines) == 1, tb, names, rss_mb, seconds, killed)
    if killed:
        o.problem.append(killed)
    if tb:
        o.problem.append("traceback")
    if rss_mb > RSS_TARGET_MB:
        o.problem.append(f"RSS {rss_mb:.0f} MB")
    if seconds > TIMEOUT_S:
        o.problem.append(f"{seconds:.0f} s")
    if c.expect == "error":
        if code != 2:
            o.problem.append(f"exit {code}")
        if len(lines) != 1:
            o.problem.append(f"{len(lines)} lines")
        if not names:
            o.problem.append(f"does not name {token}")
        if len(line) > 300:
            o.problem.append("line over 300 chars")
    elif c.expect == "warn":  # read in part: exit 0, or 2 with the one line naming the file
        if code not in (0, 2):
            o.problem.append(f"exit {code}")
        if code == 2 and (len(lines) != 1 or not names):
            o.problem.append(f"exit 2 without one line naming {token}")
    else:
        if code != 0:
            o.problem.append(f"exit {code}")
        if c.check is not None and not killed:
            why = c.check(d)
            if why:
                o.problem.append(why)
    return o


def table(outcomes: list[Outcome]) -> str:
    rows = [
        "| case | kind | class | exit | one line | traceback | names it | RSS MB | s | result / stderr |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for o in outcomes:
        res = "ok" if o.passed else "FAIL: " + ", ".join(o.problem)
        line = o.line.replace("|", "\\|")
        rows.append(
            f"| {o.case.name} | {o.case.kind} | {o.case.klass} | {o.code} | {'y' if o.one_line else 'n'} | "
            f"{'Y' if o.traceback else '-'} | {'y' if o.names else 'n'} | {o.rss_mb:.0f} | {o.seconds:.1f} | {res} — {line} |"
        )
    return "\n".join(rows)


def summary(outcomes: list[Outcome]) -> str:
    by_kind: Counter = Counter()
    ok_kind: Counter = Counter()
    by_class: Counter = Counter()
    ok_class: Counter = Counter()
    for o in outcomes:
        by_kind[o.case.kind] += 1
        by_class[o.case.klass] += 1
        ok_kind[o.case.kind] += o.passed
        ok_class[o.case.klass] += o.passed
    n_ok = sum(o.passed for o in outcomes)
    out = [
        f"passed {n_ok} / {len(outcomes)}",
        "by kind: " + ", ".join(f"{k} {ok_kind[k]}/{v}" for k, v in sorted(by_kind.items())),
    ]
    out.append("by class: " + ", ".join(f"{k} {ok_class[k]}/{v}" for k, v in sorted(by_class.items())))
    worst_rss = max(outcomes, key=lambda o: o.rss_mb)
    worst_s = max(outcomes, key=lambda o: o.seconds)
    out.append(
        f"peak RSS {worst_rss.rss_mb:.0f} MB ({worst_rss.case.name}); slowest {worst_s.seconds:.1f} s ({worst_s.case.name})"
    )
    return "\n".join(out)


# ---------------------------------------------------------------- kill test
def _tum_complete(p: Path) -> str | None:
    text = p.read_text()
    if text and not text.endswith("\n"):
        return f"{p.name} cut mid-line"
    rows = [x.split() for x in text.splitlines() if x.strip() and not x.startswith("#")]
    if not rows or any(len(r) != 8 for r in rows):
        return f"{p.name} has a row that is not 8 numbers (or no rows)"
    return None


def check_folder(folder: Path, manifest_name: str) -> tuple[str, list[str]]:
    """(state, problems): every file in ``folder`` must be whole (a TUM file rows of 8 numbers
    ending in a newline, JSON parsing, JSON lines ending in a newline); with the manifest
    (``state`` "manifest") every file it lists must be there; without it (``state`` "no manifest":
    the folder says it is incomplete) the files present must still each be whole."""
    problems: list[str] = []
    if not folder.exists():
        return "absent", problems
    manifest = folder / manifest_name
    files = {p.name for p in folder.iterdir()}
    temps = sorted(n for n in files if n.startswith(".frslam-tmp"))
    state = "manifest" if manifest.exists() else "no manifest"
    if manifest.exists():
        try:
            listed = json.loads(manifest.read_text()).get("outputs", [])
        except ValueError:
            return state, [f"{manifest_name} does not parse"]
        problems += [f"{n} listed in {manifest_name} but absent" for n in listed if n not in files]
    for n in sorted(files - set(temps)):
        p = folder / n
        if not p.is_file():
            continue
        if n.endswith(".tum"):
            why = _tum_complete(p)
            if why:
                problems.append(why)
        elif n.endswith(".json"):
            try:
                json.loads(p.read_text())
            except ValueError:
                problems.append(f"{n} does not parse")
        elif n.endswith(".jsonl"):
            t = p.read_text()
            if t and not t.endswith("\n"):
                problems.append(f"{n} cut mid-line")
    if temps:
        problems.append(f"temporary files left: {temps}")
    return state, problems


def _wait_session(sid: int, seconds: float) -> int:
    """Wait up to ``seconds`` for every process of session ``sid`` (a killed run's odometry
    worker) to end; kill those left and return how many there were."""
    deadline = time.monotonic() + seconds
    while True:
        left = []
        for p in psutil.process_iter():
            try:
                if os.getsid(p.pid) == sid and p.status() != psutil.STATUS_ZOMBIE:
                    left.append(p)
            except (OSError, psutil.Error):
                continue
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    for p in left:
        try:
            p.kill()
        except psutil.Error:
            pass
    return len(left)


def kill_test(n: int, root: Path, seed: int) -> None:
    rng = random.Random(seed)
    root.mkdir(parents=True, exist_ok=True)
    plan = good_plan(root)
    # a recording of ~20 s run time: a simulated bag
    sim_src = root / "rec"
    if not (sim_src / "meta.json").exists():
        subprocess.run(
            [
                *FRSLAM,
                "simulate",
                str(plan),
                "--out",
                str(sim_src),
                "--length",
                "8",
                "--beams",
                "360",
                "--scan-rate",
                "5",
                "--overwrite",
            ],
            check=True,
            capture_output=True,
        )
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"}
    jobs = {
        "run": ([*FRSLAM, "run", str(sim_src), "--floor-plan", str(plan), "--out"], "metrics.json"),
        "simulate": (
            [
                *FRSLAM,
                "simulate",
                str(plan),
                "--length",
                "8",
                "--beams",
                "360",
                "--scan-rate",
                "5",
                "--overwrite",
                "--out",
            ],
            "meta.json",
        ),
    }
    # one unkilled run of each for its duration
    full = {}
    for name, (cmd, _) in jobs.items():
        t0 = time.monotonic()
        subprocess.run([*cmd, str(root / f"full_{name}")], check=True, capture_output=True, env=env)
        full[name] = time.monotonic() - t0
    print(f"unkilled: run {full['run']:.1f} s, simulate {full['simulate']:.1f} s")
    counts: Counter = Counter()
    states: Counter = Counter()
    fails = []
    for name, (cmd, manifest) in jobs.items():
        for sig in (signal.SIGKILL, signal.SIGTERM, signal.SIGINT):
            for k in range(n):
                out = root / f"k_{name}_{sig.name}_{k}"
                if k % 2 and (root / f"full_{name}").exists():  # half of them over a previous complete run
                    shutil.rmtree(out, ignore_errors=True)
                    shutil.copytree(root / f"full_{name}", out, symlinks=True)
                at = rng.uniform(0.3, full[name] * 1.05)
                with open(root / "stdout.txt", "wb") as fo, open(root / "stderr.txt", "w+b") as fe:
                    proc = subprocess.Popen(
                        [*cmd, str(out)], stdout=fo, stderr=fe, env=env, start_new_session=True
                    )
                    try:
                        proc.wait(timeout=at)
                    except subprocess.TimeoutExpired:
                        proc.send_signal(sig)
                    proc.wait()
                    fe.seek(0)
                    err = fe.read()
                orphans = _wait_session(proc.pid, 30.0)
                state, problems = check_folder(out, manifest)
                if sig == signal.SIGKILL:  # SIGKILL cannot clean up: a stale temporary file is allowed
                    problems = [p for p in problems if not p.startswith("temporary files left")]
                states[(name, sig.name, state)] += 1
                tb = "Traceback" in err.decode(errors="replace")
                if tb:
                    problems.append("traceback")
                if orphans:
                    problems.append(
                        f"{orphans} process(es) of the run still alive 30 s after it ended (killed)"
                    )
                expected_code = {signal.SIGKILL: -9, signal.SIGTERM: 143, signal.SIGINT: 130}[sig]
                finished = proc.returncode == 0
                if not finished and proc.returncode != expected_code:
                    problems.append(f"exit {proc.returncode} (expected {expected_code})")
                state = "finished" if finished else "killed"
                counts[(name, sig.name, state, "ok" if not problems else "bad")] += 1
                if problems:
                    fails.append(
                        f"{name} {sig.name} at {at:.1f} s: {problems}; stderr: {err.decode(errors='replace')[-300:]}"
                    )
    print("| command | signal | killed, outputs whole | killed, outputs bad | finished first |")
    print("|---|---|---|---|---|")
    for name in jobs:
        for sig in ("SIGKILL", "SIGTERM", "SIGINT"):
            ok = counts[(name, sig, "killed", "ok")]
            bad = counts[(name, sig, "killed", "bad")]
            fin = counts[(name, sig, "finished", "ok")] + counts[(name, sig, "finished", "bad")]
            print(f"| {name} | {sig} | {ok} | {bad} | {fin} |")
    print()
    print(
        "folder states after the kill: "
        + ", ".join(f"{k[0]} {k[1]} {k[2]}: {v}" for k, v in sorted(states.items()))
    )
    for f in fails:
        print("FAIL", f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="run cases whose name or kind contains this")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="folder for the cases (kept); default a temporary one, removed")
    ap.add_argument("--kill", type=int, metavar="N", help="run the kill test, N kills per command and signal")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--failures", action="store_true", help="print only the failing rows")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="frslam-bad-"))
    try:
        if args.kill:
            kill_test(args.kill, root / "kill", args.seed)
            return 0
        cases = [c for c in CASES if not args.only or args.only in c.name or args.only == c.kind]
        with ThreadPoolExecutor(args.jobs) as ex:
            outcomes = list(ex.map(lambda c: run_case(c, root), cases))
        shown = [o for o in outcomes if not o.passed] if args.failures else outcomes
        print(table(shown))
        print()
        print(summary(outcomes))
        return 0 if all(o.passed for o in outcomes) else 1
    finally:
        if args.keep is None:
            for p in root.rglob("ro"):
                subprocess.run(["chattr", "-i", str(p)], check=False)
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
