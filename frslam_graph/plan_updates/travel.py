"""Travel, obstruction and the mapped area, from the keyframes (``odom`` / ``map``; metres, radians).

:class:`Travel` accumulates the distance and the turn of the odometry from keyframe to keyframe
and detects an obstruction (no keyframe for ``time_s``, progress below ``speed`` m/s over
``time_s``, or the caller's report). :class:`Coverage` keeps the cells the keyframe beams swept
(the mapped area, m²) that schedules the registrations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class Travel:
    """Distance (m) and turn (rad) of the odometry so far, per keyframe, and obstruction."""

    def __init__(self, obstruction_time_s: float, obstruction_speed: float) -> None:
        self.time_s = obstruction_time_s  # s without progress that count as obstructed
        self.speed = obstruction_speed  # m/s: less progress than this over time_s is obstructed
        self.dist = 0.0  # metres travelled (odometry)
        self.turn = 0.0  # radians turned (odometry)
        self.kf_dist: list[float] = []  # distance travelled at each keyframe
        self._last_odom: np.ndarray | None = None
        self._history: list[tuple[float, float]] = []  # (stamp, distance) per keyframe
        self._obstructed = False  # reported by the caller since the last keyframe
        self._reported = False  # the current obstruction is already known

    def advance(self, pose_odom: np.ndarray) -> None:
        """A new keyframe at this odometry pose (x, y, theta)."""
        if self._last_odom is not None:
            self.dist += float(np.hypot(*(pose_odom[:2] - self._last_odom[:2])))
            dth = pose_odom[2] - self._last_odom[2]
            self.turn += abs(float((dth + np.pi) % (2 * np.pi) - np.pi))
        self._last_odom = np.asarray(pose_odom, float).copy()
        self.kf_dist.append(self.dist)

    def notify_obstructed(self) -> None:
        """The caller's motion is obstructed (paper Alg. 3: d <= 0)."""
        self._obstructed = True

    def obstruction(self, stamp: float) -> tuple[bool, bool]:
        """(obstructed at this keyframe, newly: an obstruction not reported before)."""
        self._history.append((stamp, self.dist))
        obstructed = self._obstructed
        if len(self._history) >= 2:
            t_prev, _ = self._history[-2]
            if stamp - t_prev >= self.time_s:
                obstructed = True  # stood still long enough to make no keyframe
        # progress over the last time_s
        old = [(t, d) for t, d in self._history if stamp - t >= self.time_s]
        if old:
            t_o, d_o = old[-1]
            if (self.dist - d_o) < self.speed * (stamp - t_o):
                obstructed = True
            self._history = self._history[len(old) - 1 :]
        newly = obstructed and not self._reported
        self._reported = obstructed
        self._obstructed = False
        return obstructed, newly


class _CoverageCells:
    """Set of integer cells (kx, ky): sparse 64 × 64 boolean tiles (any extent), with a count."""

    _TILE = 64

    def __init__(self) -> None:
        self._tiles: dict[tuple[int, int], np.ndarray] = {}
        self.count = 0

    def add(self, kx: np.ndarray, ky: np.ndarray) -> None:
        if not len(kx):
            return
        t = self._TILE
        tx, ty = kx // t, ky // t
        x0, y0 = int(tx.min()), int(ty.min())
        ny = int(ty.max()) - y0 + 1
        local = (tx - x0) * ny + (ty - y0)  # tile index in the batch's bounding box of tiles
        order = np.argsort(local, kind="stable")
        ids, starts = np.unique(local[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        for lid, a, b in zip(ids.tolist(), starts.tolist(), ends.tolist(), strict=True):
            kxt, kyt = x0 + lid // ny, y0 + lid % ny  # a handful of tiles per scan
            tile = self._tiles.get((kxt, kyt))
            if tile is None:
                tile = self._tiles[(kxt, kyt)] = np.zeros((t, t), dtype=bool)
            sel = order[a:b]
            before = int(np.count_nonzero(tile))
            tile[ky[sel] - kyt * t, kx[sel] - kxt * t] = True
            self.count += int(np.count_nonzero(tile)) - before


@dataclass
class Coverage:
    """The mapped area: cells of ``cell`` metres swept by the beams of the keyframe scans."""

    cell: float = 0.25  # m, coverage cell side
    max_beams: int = 180  # beams of a scan swept (evenly subsampled)
    samples_per_beam: int = 41  # points along each beam, sensor to end point
    _cells: _CoverageCells = field(default_factory=_CoverageCells, repr=False)

    @property
    def area(self) -> float:
        """Area (m²) of the cells seen so far."""
        return float(self._cells.count) * self.cell**2

    def add_scan(self, pose: np.ndarray, points: np.ndarray) -> None:
        """Sweep a keyframe scan: ``points`` (M, 2) in base_link at ``pose`` in map."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not len(pts):
            return
        if len(pts) > self.max_beams:
            pts = pts[np.linspace(0, len(pts) - 1, self.max_beams).round().astype(np.intp)]
        t = np.linspace(0.0, 1.0, self.samples_per_beam)
        samples = (pts[:, None, :] * t[None, :, None]).reshape(-1, 2)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        wx = c * samples[:, 0] - s * samples[:, 1] + pose[0]
        wy = s * samples[:, 0] + c * samples[:, 1] + pose[1]
        kx = np.floor(wx / self.cell).astype(np.int64)
        ky = np.floor(wy / self.cell).astype(np.int64)
        self._cells.add(kx, ky)


__all__ = ["Coverage", "Travel"]
