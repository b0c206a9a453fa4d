"""Recording readers (CARMEN, ROS 1/2 bags, PCD/PLY folders, simulator output) and the 2D LiDAR simulator.

``open_recording(path)`` picks the reader from the file: ``.clf`` / ``.log`` (optionally ``.gz`` /
``.bz2``) -> :class:`CarmenLog`; ``.bag``, ``.mcap``, ``.db3``, a rosbag2 folder (``metadata.yaml``)
or a simulator output folder (``bag/metadata.yaml``) -> :class:`RosBag`; a folder of ``.pcd`` /
``.ply`` files -> :class:`PointCloudFolder`. Every reader is a :class:`Recording`: ``len(rec)``,
``for scan in rec`` (:class:`Scan`), ``rec.stats``, ``rec.odometry()``.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

from frslam_graph.datasets.recording import Recording, RecordingStats, RecordingWarning
from frslam_graph.datasets.scan import Scan

from frslam_graph.errors import RecordingError

__all__ = [
    "CarmenLog",
    "PointCloudFolder",
    "Recording",
    "RecordingStats",
    "RecordingWarning",
    "RosBag",
    "Scan",
    "open_recording",
    "reader_for",
]


def reader_for(path: str | Path) -> type[Recording] | None:
    """The reader class ``open_recording`` uses for ``path`` (None: no reader knows it)."""
    from frslam_graph.datasets.carmen import CarmenLog, is_carmen
    from frslam_graph.datasets.pointcloud_folder import PointCloudFolder, cloud_files
    from frslam_graph.datasets.rosbag import RosBag, bag_path

    p = Path(path)
    if p.is_file() and is_carmen(p):
        return CarmenLog
    if bag_path(p) is not None:
        return RosBag
    if p.is_dir() and cloud_files(p):
        return PointCloudFolder
    return None


def open_recording(path: str | Path, **opts: Any) -> Recording:
    """Open a recording with the reader its name / content calls for; ``opts`` go to the reader.

    Raises :class:`~frslam_graph.errors.RecordingError` for a missing path or an unknown kind.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError("no such file or folder", source=p)
    reader = reader_for(p)
    if reader is not None:
        accepted = inspect.signature(reader.__init__).parameters
        unknown = sorted(k for k in opts if k not in accepted or k in ("self", "path"))
        if unknown:
            raise RecordingError(f"{reader.__name__} takes no option {', '.join(unknown)}", source=p)
        return reader(p, **opts)
    raise RecordingError(
        "unknown recording kind: expected a CARMEN log (.clf/.log[.gz|.bz2]), a ROS bag (.bag, .mcap, "
        ".db3, a folder with metadata.yaml or bag/metadata.yaml) or a folder of .pcd/.ply files",
        source=p,
    )


def __getattr__(name: str) -> Any:
    modules = {
        "CarmenLog": "carmen",
        "RosBag": "rosbag",
        "PointCloudFolder": "pointcloud_folder",
    }
    if name in modules:
        import importlib

        return getattr(importlib.import_module(f"frslam_graph.datasets.{modules[name]}"), name)
    raise AttributeError(f"module 'frslam_graph.datasets' has no attribute {name!r}")
