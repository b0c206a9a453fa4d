"""A folder of ``.pcd`` / ``.ply`` point clouds (read by open3d) as a stream of planar scans.

Each cloud is sliced to the plane ``|z - plane_z| < plane_tol`` (sensor frame, metres) and
projected to (x, y): one :class:`Scan` per file, built with ``Scan.from_points``. Files are taken
in name order; when every file name (without suffix) is a number they are ordered by that number
and it is the stamp (seconds, or nanoseconds when larger than 1e15), otherwise the stamp is
``index / rate``. Clouds carry no odometry (``odom`` is None). An unreadable or empty file is
skipped and counted in the warning; a folder without clouds raises RecordingError, and so does
a ``.pcd`` / ``.ply`` whose header claims more points than ``MAX_CLOUD_POINTS``
(``frslam_graph.limits``) or than the file holds (a truncated cloud: open3d would fill the rest
with whatever memory held).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from frslam_graph.datasets.recording import Recording, RecordingStats
from frslam_graph.datasets.scan import Scan

from frslam_graph.errors import RecordingError
from frslam_graph.limits import MAX_CLOUD_POINTS

HEADER_BYTES = 1 << 16  # a PCD / PLY header longer than this is left to open3d to judge
PLY_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip

SUFFIXES = (".pcd", ".ply")


def _number(stem: str) -> float | None:
    try:
        value = float(stem)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def cloud_files(folder: Path) -> list[Path]:
    """The ``.pcd`` / ``.ply`` files directly in ``folder`` (any letter case)."""
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES]


def _header(path: Path, end: bytes) -> tuple[list[list[str]], int] | None:
    """The header lines (split) up to and including the one starting with ``end``, and the
    header's length in bytes; None when it is not found in the first ``HEADER_BYTES``."""
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
    lines, offset = [], 0
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        tok = raw.decode("latin-1").split()
        lines.append(tok)
        if tok and tok[0].encode() == end:
            return lines, offset
    return None


#: bytes of ASCII point data: numbers (with nan / inf) and white space
_ASCII_NUMBER_BYTES = b"0123456789+-.eEnaifNAIF \t\r\n"


def _count_lines(path: Path, start: int) -> int:
    """Lines from byte ``start`` on (an unterminated last line counts), read in 1 MiB pieces;
    RecordingError when they hold anything but numbers (open3d read words as points)."""
    count, last = 0, b"\n"
    with open(path, "rb") as f:
        f.seek(start)
        while piece := f.read(1 << 20):
            if piece.translate(None, _ASCII_NUMBER_BYTES):
                raise RecordingError("ASCII point data holds something other than numbers", source=path)
            count += piece.count(b"\n")
            last = piece[-1:]
    return count + (last != b"\n")


def _claimed_points(path: Path) -> tuple[int, str, int, int] | None:
    """``(points, data kind, bytes per point, header bytes)`` from a PCD / PLY header; None when
    the header cannot be read (open3d then reports the file)."""
    try:
        if path.suffix.lower() == ".pcd":
            found = _header(path, b"DATA")
            if found is None:
                return None
            lines, start = found
            fields = {tok[0].upper(): tok[1:] for tok in lines if tok}
            count = [int(c) for c in fields.get("COUNT", ["1"] * len(fields.get("SIZE", [])))]
            size = sum(int(s) * c for s, c in zip(fields.get("SIZE", []), count, strict=False))
            if "POINTS" in fields:
                points = int(fields["POINTS"][0])
            else:
                points = int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
            return points, fields["DATA"][0].lower(), size, start
        found = _header(path, b"end_header")
        if found is None:
            return None
        lines, start = found
        kind = next(tok[1] for tok in lines if tok and tok[0] == "format")
        points, size, in_vertex = 0, 0, False
        for tok in lines:
            if tok[:1] == ["element"]:
                in_vertex = tok[1] == "vertex"
                if in_vertex:
                    points = int(tok[2])
            elif in_vertex and tok[:1] == ["property"]:
                size += PLY_SIZES.get(tok[1], 0) if tok[1] != "list" else 0
        return points, "ascii" if kind == "ascii" else "binary", size, start
    except (OSError, ValueError, KeyError, IndexError, StopIteration):
        return None


def check_cloud_size(path: Path) -> None:
    """RecordingError naming the file when its header claims more points than ``MAX_CLOUD_POINTS``
    or than the file holds; compressed PCD data is checked against the limit only."""
    claimed = _claimed_points(path)
    if claimed is None:
        return
    points, kind, size, start = claimed
    if points > MAX_CLOUD_POINTS:
        raise RecordingError(
            f"header claims {points:,} points, over the limit of {MAX_CLOUD_POINTS:,} "
            "(MAX_CLOUD_POINTS, frslam_graph.limits)",
            source=path,
        )
    if kind == "ascii":
        held = _count_lines(path, start)
    elif kind == "binary" and size > 0:
        held = (path.stat().st_size - start) // size
    else:
        return
    if held < points:
        raise RecordingError(
            f"truncated cloud: header claims {points:,} points, the file holds {held:,}", source=path
        )


class PointCloudFolder(Recording):
    """Point-cloud files of one folder, sliced to a plane.

    Args:
        path: the folder.
        plane_z, plane_tol: the slice kept, metres.
        rate: clouds per second, for stamps when the file names are not numbers.
    """

    def __init__(
        self, path: str | Path, *, plane_z: float = 0.0, plane_tol: float = 0.05, rate: float = 10.0
    ):
        super().__init__(path)
        if not self.path.is_dir():
            raise RecordingError("no such folder", source=self.path)
        if not (rate > 0 and math.isfinite(rate)):
            raise RecordingError(f"rate must be a positive number of clouds per second, got {rate!r}")
        self.plane_z, self.plane_tol = float(plane_z), float(plane_tol)
        files = cloud_files(self.path)
        if not files:
            raise RecordingError("no .pcd or .ply files in the folder", source=self.path)
        numbers = [_number(p.stem) for p in files]
        if all(n is not None for n in numbers):
            order = sorted(range(len(files)), key=lambda i: (numbers[i], files[i].name))
            scale = 1e-9 if max(numbers) > 1e15 else 1.0  # type: ignore[type-var]
            self.files = [files[i] for i in order]
            self.stamps = np.array([numbers[i] * scale for i in order], dtype=np.float64)  # type: ignore[operator]
            self.stamp_source = "file names"
        else:
            self.files = sorted(files, key=lambda p: p.name)
            self.stamps = np.arange(len(files), dtype=np.float64) / float(rate)
            self.stamp_source = f"index / {rate:g} Hz"

    def __len__(self) -> int:
        return len(self.files)

    @property
    def duration(self) -> float:
        return float(self.stamps[-1] - self.stamps[0])

    def _scans(self, stats: RecordingStats) -> Iterator[Scan]:
        import open3d as o3d

        quiet = o3d.utility.VerbosityLevel.Error  # open3d reports a bad file on stdout otherwise
        last = -math.inf
        for path, stamp in zip(self.files, self.stamps, strict=True):
            stats.records[path.suffix.lower()] += 1
            check_cloud_size(path)
            try:
                with o3d.utility.VerbosityContextManager(quiet):
                    cloud = o3d.io.read_point_cloud(str(path), format=path.suffix.lower()[1:])
                xyz = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
            except Exception as exc:  # open3d raises RuntimeError on some broken files
                stats.skip(f"unreadable cloud files ({type(exc).__name__})", path.name)
                continue
            if xyz.shape[0] == 0:
                stats.skip("empty or unreadable cloud files", path.name)
                continue
            if stamp == last:
                stats.flag("clouds with the same stamp as the previous one", path.name)
            last = stamp
            finite = np.isfinite(xyz).all(axis=1)
            if not finite.all():
                stats.flag("clouds with non-finite points (dropped)", path.name)
            keep = finite & (np.abs(xyz[:, 2] - self.plane_z) < self.plane_tol)
            if not keep.any():
                stats.flag("clouds with no point in the slice", path.name)
            yield Scan.from_points(float(stamp), xyz[keep, :2])
