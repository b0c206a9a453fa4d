"""The keyframe store: per scan what the trajectory needs, per keyframe its scan (base_link).

Poses are (x, y, theta) in metres / radians: ``pose_odom`` in ``odom``, ``relative`` of a scan to
its keyframe; the ``map`` poses are the pose graph's (:class:`~frslam_graph.backend.graph.PoseGraph`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from frslam_graph.errors import RecordingError


@dataclass(frozen=True, slots=True)
class KeyframeInfo:
    """A keyframe: graph index, stamp, index of its scan, poses in map (current) and odom."""

    index: int
    stamp: float
    scan_index: int
    pose_map: np.ndarray
    pose_odom: np.ndarray


class Rows:
    """Rows of a fixed width (None: scalars) appended one at a time, in one array that doubles
    when full: ``width`` × itemsize bytes per row (at most twice that while it is half-empty),
    where a Python list of small arrays costs ~130 B per 3-vector and 32 B per float."""

    def __init__(self, width: int | None = None, dtype: Any = np.float64, capacity: int = 256):
        self._a = np.empty((capacity,) if width is None else (capacity, width), dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row: Any) -> None:
        if self._n == len(self._a):
            grown = np.empty((2 * len(self._a), *self._a.shape[1:]), self._a.dtype)
            grown[: self._n] = self._a
            self._a = grown
        self._a[self._n] = row
        self._n += 1

    @property
    def array(self) -> np.ndarray:
        """The rows so far (a view: valid until the next append)."""
        return self._a[: self._n]

    @property
    def nbytes(self) -> int:
        return self._a.nbytes


class ScanTrack:
    """Per scan what the trajectory needs, nothing more: stamp, keyframe index, pose relative to
    that keyframe and the odometry pose (64 B per scan, amortised)."""

    def __init__(self) -> None:
        self._f = Rows(7)  # stamp, relative (x, y, theta), odometry (x, y, theta)
        self._kf = Rows(None, np.int64)

    def __len__(self) -> int:
        return len(self._kf)

    def append(self, stamp: float, keyframe: int, relative: np.ndarray, odometry: np.ndarray) -> None:
        row = np.empty(7)
        row[0], row[1:4], row[4:7] = stamp, relative, odometry
        self._f.append(row)
        self._kf.append(keyframe)

    @property
    def stamps(self) -> np.ndarray:
        return self._f.array[:, 0]

    @property
    def keyframe(self) -> np.ndarray:
        return self._kf.array

    @property
    def relative(self) -> np.ndarray:
        return self._f.array[:, 1:4]

    @property
    def odometry(self) -> np.ndarray:
        return self._f.array[:, 4:7]

    @property
    def nbytes(self) -> int:
        return self._f.nbytes + self._kf.nbytes

    def latest_stamp(self) -> float:
        """Stamp of the latest scan (nan before any)."""
        return self.stamps[-1] if len(self) else float("nan")

    def keyframe_at(self, stamp: float, tolerance: float = 1e-6) -> tuple[int, np.ndarray]:
        """(keyframe index, pose of the scan relative to it) of the scan with this stamp."""
        st = self.stamps
        if len(st) == 0:
            raise RecordingError("no scans yet", where="stamp")
        j = int(np.argmin(np.abs(st - stamp)))
        if abs(st[j] - stamp) > tolerance:
            raise RecordingError(f"no scan at stamp {stamp} (nearest {st[j]})", where="stamp")
        return int(self.keyframe[j]), self.relative[j].copy()


@dataclass(slots=True)
class StoredKeyframe:
    """What the backend keeps of a keyframe: its scan's end points in base_link (float32) and
    the sensor origin (2,) in base_link."""

    stamp: float
    scan_index: int
    pose_odom: np.ndarray
    points: np.ndarray
    sensor_origin: np.ndarray


class KeyframeStore:
    """The keyframes in graph order and every scan's track (:class:`ScanTrack`)."""

    def __init__(self) -> None:
        self.scans = ScanTrack()
        self._kfs: list[StoredKeyframe] = []
        self.points: list[np.ndarray] = []  # per keyframe (kept as lists: no rebuild per query)
        self.origins: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._kfs)

    def __getitem__(self, i: int) -> StoredKeyframe:
        return self._kfs[i]

    def append(self, kf: StoredKeyframe) -> None:
        self._kfs.append(kf)
        self.points.append(kf.points)
        self.origins.append(kf.sensor_origin)

    def stamps(self) -> list[float]:
        return [k.stamp for k in self._kfs]

    def odometry(self) -> np.ndarray:
        """(K, 3) keyframe poses in odom."""
        return np.array([k.pose_odom for k in self._kfs])

    def infos(self, estimates: np.ndarray) -> list[KeyframeInfo]:
        """Every keyframe as a :class:`KeyframeInfo` at these map estimates (K, 3)."""
        return [
            KeyframeInfo(i, k.stamp, k.scan_index, estimates[i], k.pose_odom.copy())
            for i, k in enumerate(self._kfs)
        ]


__all__ = ["KeyframeInfo", "KeyframeStore", "Rows", "ScanTrack", "StoredKeyframe"]
