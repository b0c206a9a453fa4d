"""Reading throughput of the recording readers on the shared logs and bag (Markdown table).

For each recording: the median over ``--runs`` of opening it and iterating every scan (wall and
CPU time; CPU time is the steadier figure on a shared machine), as scans per CPU-second and as a
multiple of the recording's real time. Baselines timed in the same run:
for CARMEN logs, decompressing and splitting every line (the floor of any Python text reader);
for the demo bag, rosbags' own indexed reader deserialising the same messages from a copy whose
index records were repaired (rosbags cannot read the original); for intel.bag (odometry, tf and
scans), rosbags' reader deserialising every message of the bag once.

    .venv/bin/python tools/bench_readers.py [--runs 3] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import bz2
import shutil
import statistics
import struct
import tempfile
import time
import warnings
from pathlib import Path

from _paths import SHARED_DATA  # noqa: E402
from frslam_graph.datasets import RecordingWarning, open_recording


def read_all(path: Path) -> tuple[int, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        rec = open_recording(path)
        n = sum(1 for _ in rec)
    return n, rec.stats.duration


def split_lines(path: Path) -> int:
    n = 0
    with bz2.open(path, "rt", encoding="latin-1") as f:
        for line in f:
            n += len(line.split())
    return n


def repaired_copy(src: Path, dst: Path) -> Path:
    """Copy of a ROS 1 bag with each version-1 index record's data length set to count * 12."""
    shutil.copy(src, dst)
    b = bytearray(dst.read_bytes())
    pos = 13
    while pos < len(b):
        (hlen,) = struct.unpack_from("<I", b, pos)
        header = bytes(b[pos + 4 : pos + 4 + hlen])
        dpos = pos + 4 + hlen
        (dlen,) = struct.unpack_from("<I", b, dpos)
        if b"op=\x04" in header:
            dlen = 12 * struct.unpack_from("<I", header, header.index(b"count=") + 6)[0]
            struct.pack_into("<I", b, dpos, dlen)
        pos = dpos + 4 + dlen
    dst.write_bytes(bytes(b))
    return dst


def rosbags_read(path: Path) -> int:
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    n = 0
    with Reader(path) as reader:
        for c in reader.connections:  # types the store lacks (intel.bag's TFMessage) from the bag
            if c.msgtype not in ts.fielddefs and c.msgdef.data:
                ts.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        for c, _t, raw in reader.messages():
            ts.deserialize_ros1(raw, c.msgtype)
            n += 1
    return n


def median_time(fn, runs: int) -> tuple[float, float, object]:
    """Median wall time, median CPU time of this process (robust on a shared machine), result."""
    wall, cpu, out = [], [], None
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return statistics.median(wall), statistics.median(cpu), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument(
        "--data",
        type=Path,
        default=SHARED_DATA,
    )
    args = ap.parse_args()
    rows = []
    for name in ("intel", "fr079", "aces"):
        path = args.data / "carmen" / f"{name}.clf.bz2"
        t, c, (n, duration) = median_time(lambda p=path: read_all(p), args.runs)
        _, c_base, _ = median_time(lambda p=path: split_lines(p), args.runs)
        rows.append((path.name, n, t, c, duration, "decompress + split lines", c_base))
    bag = args.data / "bags" / "scan_tools_demo.bag"
    t, c, (n, duration) = median_time(lambda: read_all(bag), args.runs)
    with tempfile.TemporaryDirectory() as tmp:
        fixed = repaired_copy(bag, Path(tmp) / "fixed.bag")
        _, c_base, _ = median_time(lambda: rosbags_read(fixed), args.runs)
    rows.append((bag.name, n, t, c, duration, "rosbags Reader on a repaired copy", c_base))
    bag = args.data / "bags" / "intel.bag"  # with odometry: the prologue's pass, then the scans'
    t, c, (n, duration) = median_time(lambda: read_all(bag), args.runs)
    _, c_base, _ = median_time(lambda: rosbags_read(bag), args.runs)
    rows.append((bag.name, n, t, c, duration, "rosbags Reader, every message once", c_base))
    print(f"Reading throughput, median of {args.runs} runs (open + iterate every scan)\n")
    print(
        "| recording | scans | wall (s) | CPU (s) | scans per CPU-s | × real time (CPU) "
        "| baseline | baseline CPU (s) | CPU / baseline |"
    )
    print("|---|---:|---:|---:|---:|---:|---|---:|---:|")
    for name, n, t, c, duration, base, c_base in rows:
        print(
            f"| {name} | {n:,} | {t:.2f} | {c:.2f} | {n / c:,.0f} | {duration / c:,.0f} | {base} "
            f"| {c_base:.2f} | {c / c_base:.1f} |"
        )


if __name__ == "__main__":
    main()
