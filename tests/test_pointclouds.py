"""Folders of PCD / PLY clouds: slicing to the plane, order and stamps, bad files."""

from __future__ import annotations

import warnings

import numpy as np
import open3d as o3d
import pytest
from frslam_graph.datasets import RecordingWarning, open_recording
from frslam_graph.datasets.pointcloud_folder import PointCloudFolder

from frslam_graph.errors import RecordingError

# three points in the plane z = 0 (within 5 cm) and two off it
CLOUD = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.03], [-3.0, 0.0, -0.04], [1.0, 1.0, 0.5], [2.0, 2.0, -1.0]])


def write_cloud(path, xyz):
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64))
    assert o3d.io.write_point_cloud(str(path), pc)


def read_all(rec):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        scans = list(rec)
    return scans, [str(w.message) for w in got if issubclass(w.category, RecordingWarning)]


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_clouds_sliced_to_plane_numeric_names_are_stamps(tmp_path, suffix):
    for stamp in (9.5, 10.0, 100.25):  # name order would put "100.25" before "9.5"
        write_cloud(tmp_path / f"{stamp}{suffix}", CLOUD)
    rec = open_recording(tmp_path)
    assert isinstance(rec, PointCloudFolder) and len(rec) == 3
    scans, warns = read_all(rec)
    assert warns == []
    assert [s.stamp for s in scans] == [9.5, 10.0, 100.25]
    assert scans[0].points == pytest.approx(CLOUD[:3, :2])
    assert scans[0].ranges == pytest.approx([1.0, 2.0, 3.0])
    assert scans[0].angles == pytest.approx([0.0, np.pi / 2, np.pi])
    assert scans[0].odom is None
    thick, _ = read_all(open_recording(tmp_path, plane_tol=0.6))
    assert len(thick[0].points) == 4
    high, _ = read_all(open_recording(tmp_path, plane_z=-1.0, plane_tol=0.1))
    assert high[0].points == pytest.approx(np.array([[2.0, 2.0]]))


def test_non_numeric_names_sorted_by_name_stamped_by_rate(tmp_path):
    for name in ("scan_b.pcd", "scan_a.pcd", "scan_c.ply"):
        write_cloud(tmp_path / name, CLOUD)
    (tmp_path / "scan_c.ply").rename(tmp_path / "scan_c.PLY")  # suffix case does not matter
    (tmp_path / "notes.txt").write_text("not a cloud")
    rec = open_recording(tmp_path, rate=4.0)
    assert [p.name for p in rec.files] == ["scan_a.pcd", "scan_b.pcd", "scan_c.PLY"]
    scans, warns = read_all(rec)
    assert [s.stamp for s in scans] == [0.0, 0.25, 0.5] and warns == []
    assert all(len(s.points) == 3 for s in scans)


def test_nanosecond_names(tmp_path):
    write_cloud(tmp_path / "1600000000500000000.pcd", CLOUD)
    write_cloud(tmp_path / "1600000000000000000.pcd", CLOUD)
    scans, _ = read_all(open_recording(tmp_path))
    assert [s.stamp for s in scans] == pytest.approx([1.6e9, 1.6e9 + 0.5])


def test_broken_and_empty_files_skipped_and_counted(tmp_path):
    write_cloud(tmp_path / "1.pcd", CLOUD)
    (tmp_path / "2.pcd").write_text("this is not a pcd file\n")
    write_cloud(tmp_path / "3.pcd", CLOUD)
    write_cloud(tmp_path / "4.pcd", CLOUD[3:])  # no point in the slice: yielded, flagged
    rec = open_recording(tmp_path)
    scans, warns = read_all(rec)
    assert [s.stamp for s in scans] == [1.0, 3.0, 4.0]
    assert len(scans[2].points) == 0
    assert len(warns) == 1 and "2.pcd" in warns[0] and "no point in the slice (first at 4.pcd)" in warns[0]
    assert rec.stats.skipped["empty or unreadable cloud files"] == 1


def test_folder_errors(tmp_path):
    with pytest.raises(RecordingError, match="nothing: no such file or folder"):
        open_recording(tmp_path / "nothing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RecordingError, match="empty: unknown recording kind"):
        open_recording(empty)
    with pytest.raises(RecordingError, match="no .pcd or .ply files"):
        PointCloudFolder(empty)
    write_cloud(tmp_path / "a.pcd", CLOUD)
    with pytest.raises(RecordingError, match="rate must be a positive number"):
        PointCloudFolder(tmp_path, rate=0.0)
