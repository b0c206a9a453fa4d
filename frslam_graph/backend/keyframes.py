"""The keyframe store: per scan what the trajectory needs, per keyframe its scan (base_link).

Poses are (x, y, theta) in metres / radians: ``pose_odom`` in ``odom``, ``relative`` of a scan to
its keyframe; the ``map`` poses are the pose graph's (:class:`~frslam_graph.backend.graph.PoseGraph`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from frslam_graph.errors import RecordingError
from frslam_graph.se2 import between_many, compose_rows, inverse_rows


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


class PointArena:
    """Keyframe end points (float32, (M, 2)) packed into chunks of ``chunk_points`` rows, each
    allocated once (1 MB: above the pinned mmap threshold, so mapped on its own): a keyframe's
    points are a read-only view into its chunk. A separate 5.8 kB array per keyframe came from
    the heap between iSAM2's blocks, and dropping them did not give all their pages back (2-h
    recording at 32,000 scans: points + store 53.8 -> 49.8 MB, issue 19); the
    chunks waste at most one scan's rows at their ends. Scans larger than a chunk keep their own
    array."""

    def __init__(self, chunk_points: int = 131072) -> None:
        self._chunk_points = chunk_points
        self._chunk = np.empty((0, 2), np.float32)
        self._used = 0
        self.nbytes = 0  # bytes of every chunk and own array so far

    def add(self, points: np.ndarray) -> np.ndarray:
        """A read-only float32 copy of ``points`` (M, 2), stored in the current chunk."""
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 2)
        m = len(pts)
        if m > self._chunk_points:
            out = pts.copy()
            self.nbytes += out.nbytes
        else:
            if self._used + m > len(self._chunk):
                self._chunk = np.empty((self._chunk_points, 2), np.float32)
                self._used = 0
                self.nbytes += self._chunk.nbytes
            out = self._chunk[self._used : self._used + m]
            out[:] = pts
            self._used += m
        out.flags.writeable = False
        return out


class KeyframeStore:
    """The keyframes in graph order and every scan's track (:class:`ScanTrack`); the keyframes'
    points in a :class:`PointArena`."""

    def __init__(self) -> None:
        self.scans = ScanTrack()
        self._kfs: list[StoredKeyframe] = []
        self.points: list[np.ndarray] = []  # per keyframe (kept as lists: no rebuild per query)
        self.origins: list[np.ndarray] = []
        self.arena = PointArena()

    def __len__(self) -> int:
        return len(self._kfs)

    def __getitem__(self, i: int) -> StoredKeyframe:
        return self._kfs[i]

    def append(self, kf: StoredKeyframe) -> None:
        """Keep a keyframe; its points are copied into the arena (``kf.points`` becomes the view)."""
        kf.points = self.arena.add(kf.points)
        self._kfs.append(kf)
        self.points.append(kf.points)
        self.origins.append(kf.sensor_origin)

    def stamps(self) -> list[float]:
        return [k.stamp for k in self._kfs]

    def odometry(self) -> np.ndarray:
        """(K, 3) keyframe poses in odom."""
        return np.array([k.pose_odom for k in self._kfs])

    def scan_poses(self, estimates: np.ndarray) -> np.ndarray:
        """(N, 3) every scan's pose in ``map`` at these keyframe estimates (K, 3).

        A keyframe's estimate against its odometry pose is the ``map`` <- ``odom`` correction
        there. A scan takes its odometry pose moved by its keyframe's correction blended linearly
        into the next keyframe's, by its place among the scans between the two (scan order:
        stamps may go backwards), so the trajectory has no step where a keyframe's correction
        differs from the next one's (drift corrected along the way, as it accrued). Scans after
        the last keyframe take its correction: the latest pose is ``estimate ⊕ relative``.
        """
        scans = self.scans
        n = len(scans)
        if n == 0 or not len(self._kfs):
            return np.zeros((0, 3))
        est = np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
        kf_odom = self.odometry()
        # correction map <- odom at each keyframe: est ⊕ odom⁻¹ = (odom ⊖ est)⁻¹ in frame map
        corr = compose_rows(est, inverse_rows(kf_odom))
        first = np.array([k.scan_index for k in self._kfs], dtype=np.float64)
        k = scans.keyframe
        nxt = np.minimum(k + 1, len(self._kfs) - 1)
        span = first[nxt] - first[k]
        alpha = np.where(span > 0, (np.arange(n) - first[k]) / np.where(span > 0, span, 1.0), 0.0)
        step = between_many(corr[k], corr[nxt]) * np.clip(alpha, 0.0, 1.0)[:, None]
        return compose_rows(compose_rows(corr[k], step), scans.odometry)

    def infos(self, estimates: np.ndarray) -> list[KeyframeInfo]:
        """Every keyframe as a :class:`KeyframeInfo` at these map estimates (K, 3)."""
        return [
            KeyframeInfo(i, k.stamp, k.scan_index, estimates[i], k.pose_odom.copy())
            for i, k in enumerate(self._kfs)
        ]


__all__ = ["KeyframeInfo", "KeyframeStore", "PointArena", "Rows", "ScanTrack", "StoredKeyframe"]
