"""Point clouds: a header claiming more points than the limit or than the file holds is refused
before open3d reads it."""

from __future__ import annotations

import resource

import numpy as np
import pytest
from frslam_graph.datasets import PointCloudFolder

from frslam_graph.cli import main
from frslam_graph.errors import RecordingError

GIB = 1 << 30


def _rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def pcd(points: int, data: str, body: bytes) -> bytes:
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    )
    return header.encode() + body


def ply(points: int, body: bytes) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {points}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    return header.encode() + body


def read_all(folder):
    return list(PointCloudFolder(folder))


GOOD = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=np.float32)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("0.pcd", pcd(1_000_000_000, "binary", GOOD.tobytes())),
        ("0.pcd", pcd(1_000_000_000, "ascii", b"1 0 0\n")),
        ("0.ply", ply(1_000_000_000, GOOD.tobytes())),
    ],
    ids=["pcd-binary", "pcd-ascii", "ply"],
)
def test_a_billion_points_header_is_refused(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    before = _rss_kib()
    with pytest.raises(RecordingError, match=rf"{name}: header claims 1,000,000,000 points, over the limit"):
        read_all(tmp_path)
    assert (_rss_kib() - before) * 1024 < GIB // 4


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("0.pcd", pcd(360, "ascii", b"1 0 0\n0 2 0\n")),
        ("0.pcd", pcd(360, "binary", GOOD.tobytes())),
        ("0.ply", ply(360, GOOD.tobytes())),
    ],
    ids=["pcd-ascii", "pcd-binary", "ply"],
)
def test_a_truncated_cloud_is_refused(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(
        RecordingError, match=rf"{name}: truncated cloud: header claims 360 points, the file holds 2"
    ):
        read_all(tmp_path)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("0.pcd", pcd(2, "ascii", b"1 0 0\n0 2 0")),
        ("0.pcd", pcd(2, "binary", GOOD.tobytes())),
        ("0.ply", ply(2, GOOD.tobytes())),
    ],
    ids=["pcd-ascii", "pcd-binary", "ply"],
)
def test_a_complete_cloud_is_read(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    scans = read_all(tmp_path)
    assert len(scans) == 1


def test_inspect_of_a_truncated_cloud_exits_2_with_one_line(tmp_path, capsys):
    (tmp_path / "7.pcd").write_bytes(pcd(360, "ascii", b"1 0 0\n0 2 0\n"))
    assert main(["inspect", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "7.pcd" in err and "truncated cloud" in err and len(err.splitlines()) == 1


def test_ascii_cloud_of_words_is_refused(tmp_path):
    """open3d read 'one two three' as a point: a run on junk gave a scan and exit 0."""
    from frslam_graph.datasets.pointcloud_folder import check_cloud_size

    path = tmp_path / "0001.pcd"
    path.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\none two three\nfour five six\n"
    )
    with pytest.raises(
        RecordingError, match=r"0001\.pcd: ASCII point data holds something other than numbers"
    ):
        check_cloud_size(path)
    path.write_text(path.read_text().replace("one two three\nfour five six", "1 2 nan\n-3.5e1 +4 inf"))
    check_cloud_size(path)  # numbers, nan and inf are fine
