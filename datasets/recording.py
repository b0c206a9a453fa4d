"""The common shape of every recording reader: a sized iterable of :class:`Scan` with statistics.

A reader streams its file: ``len(rec)`` comes from a cheap first pass (or the bag's index), and
``for scan in rec`` parses one record at a time. Each full iteration fills ``rec.stats`` afresh
(records per type, scans yielded, beams, invalid beams, records skipped and why, with the first
place each problem occurred) and ends with one :class:`RecordingWarning` when anything was skipped
or repaired, so nothing valid or invalid disappears silently. Unreadable input raises
:class:`~frslam_graph.errors.RecordingError` naming the file and the line / message.

Units: seconds (stamps), metres, radians. ``odometry()`` returns the recording's wheel-odometry
records as an (M, 4) array ``stamp, x, y, theta`` of ``base_link`` in ``odom`` (REP-105).
"""

from __future__ import annotations

import math
import warnings
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from frslam_graph.datasets.scan import Scan

from frslam_graph.se2 import wrap_atan2


class RecordingWarning(UserWarning):
    """Part of a recording was skipped or repaired; the message names the file and where."""


@dataclass
class RecordingStats:
    """What one pass over a recording saw. ``skipped``/``problems`` map a reason to a count."""

    records: Counter = field(default_factory=Counter)  # record / message type -> count seen
    scans: int = 0  # scans yielded
    beams: int = 0  # beams in the yielded scans
    invalid_beams: int = 0  # of which nan (no return, out of range, non-finite)
    skipped: Counter = field(default_factory=Counter)  # reason -> records not yielded
    problems: Counter = field(default_factory=Counter)  # reason -> records yielded but flagged
    first: dict[str, str] = field(default_factory=dict)  # reason -> where it first happened
    first_stamp: float = float("nan")
    last_stamp: float = float("nan")

    def skip(self, reason: str, where: str) -> None:
        self.skipped[reason] += 1
        self.first.setdefault(reason, where)

    def flag(self, reason: str, where: str) -> None:
        self.problems[reason] += 1
        self.first.setdefault(reason, where)

    def add_scan(self, scan: Scan) -> None:
        self.scans += 1
        self.beams += scan.ranges.size
        self.invalid_beams += int(np.count_nonzero(np.isnan(scan.ranges)))
        if not np.isfinite(self.first_stamp):
            self.first_stamp = scan.stamp
        self.last_stamp = scan.stamp

    @property
    def duration(self) -> float:
        """Seconds between the first and the last yielded scan (0 when fewer than two)."""
        if self.scans < 2:
            return 0.0
        return float(self.last_stamp - self.first_stamp)

    def summary(self) -> str:
        """One line per problem: ``count reason (first at where)``; empty when all was clean."""
        parts = [f"{n} skipped: {r} (first at {self.first.get(r, '?')})" for r, n in self.skipped.items()]
        parts += [f"{n} {r} (first at {self.first.get(r, '?')})" for r, n in self.problems.items()]
        return "; ".join(parts)


class Recording(ABC):
    """A recorded 2D laser stream. Subclasses implement :meth:`_scans` and :meth:`__len__`."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.stats = RecordingStats()

    @property
    def name(self) -> str:
        """The recording's file or folder name."""
        return self.path.name

    @abstractmethod
    def __len__(self) -> int:
        """Number of scan records (from the first pass / the index)."""

    @abstractmethod
    def _scans(self, stats: RecordingStats) -> Iterator[Scan]:
        """Yield the scans, recording everything skipped or flagged in ``stats``."""

    def __iter__(self) -> Iterator[Scan]:
        stats = RecordingStats()
        self.stats = stats
        for scan in self._scans(stats):
            stats.add_scan(scan)
            yield scan
        text = stats.summary()
        if text:
            warnings.warn(f"{self.path}: {text}", RecordingWarning, stacklevel=2)

    def odometry(self) -> np.ndarray:
        """(M, 4) wheel-odometry records ``stamp, x, y, theta`` (empty when the recording has none)."""
        return np.zeros((0, 4))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, scans={len(self)})"


class PoseInterpolator:
    """Pose of an (M, 4) ``stamp, x, y, theta`` table (increasing stamps) at one stamp, O(log M).

    Returns None for a stamp more than ``tolerance`` seconds outside the table.
    """

    def __init__(self, table: np.ndarray, tolerance: float):
        self.t = np.ascontiguousarray(table[:, 0])
        self.x = np.ascontiguousarray(table[:, 1])
        self.y = np.ascontiguousarray(table[:, 2])
        self.theta = np.unwrap(table[:, 3]) if len(table) else np.zeros(0)
        self.tolerance = float(tolerance)

    def __call__(self, stamp: float) -> tuple[float, float, float] | None:
        t = self.t
        if t.size == 0 or stamp < t[0] - self.tolerance or stamp > t[-1] + self.tolerance:
            return None
        heading = float(np.interp(stamp, t, self.theta))
        return (
            float(np.interp(stamp, t, self.x)),
            float(np.interp(stamp, t, self.y)),
            wrap_atan2(heading),
        )


#: Seconds of later messages that bound each message's acquisition time in
#: :func:`acquisition_times`: longer than a recording's delivery bursts (Intel: most within 2 s).
ACQUISITION_WINDOW = 3.0
#: Share of a stream's stamp gaps under a tenth of its period from which its stamps are read as
#: arrival times (bursts) in :func:`acquisition_times` (Intel: 65 % / 38 %; ACES, FR079: 0).
BURST_SHARE = 0.1


def stream_period(stamps: np.ndarray, span: float = 5.0) -> float:
    """Typical period (s) of a message stream from its stamps in publish order: the median over
    windows of about ``span`` seconds of (stamp difference / messages), so bursts (delivery
    delays) and drops barely move it. NaN for fewer than two stamps."""
    a = np.asarray(stamps, dtype=np.float64)
    if a.size < 2:
        return float("nan")
    mean = (a[-1] - a[0]) / (a.size - 1)
    k = int(np.clip(round(span / mean), 1, a.size - 1)) if mean > 0 else a.size - 1
    return float(np.median((a[k:] - a[:-k]) / k))


def acquisition_times(stamps: np.ndarray, window: float = ACQUISITION_WINDOW) -> np.ndarray | None:
    """Acquisition times (s) of a steady message stream stamped on arrival, or None when the
    stamps already follow a steady clock.

    ``stamps`` are in publish order (ROS ``header.seq``, a log's file order). A sensor publishing
    every ``T`` seconds whose messages reach the stamping process late and in bursts (stamps are
    arrival times) took message ``i`` at most ``stamps[j] - (j - i) T`` for every later ``j``:
    delays are never negative, and a dropped message between ``i`` and ``j`` only loosens the
    bound. The estimate is the tightest such bound over the next ``window`` seconds (Olson's
    passive synchronisation, "A passive solution to the sensor synchronization problem", IROS
    2010, with the message count as the sensor clock). ``T`` is :func:`stream_period`.

    None (keep the stamps) unless the stream shows bursts: at least ``BURST_SHARE`` of its
    consecutive stamps less than a tenth of a period apart, which a steady publisher cannot send
    and only a delivery burst stamps so. The Intel recording (``intel.clf``, ``intel.bag``) is the
    bursty case: ODOM at 10 Hz, 65 % of its gaps under 10 ms (median 0.9 ms), delays up to 3.4 s;
    laser at 5 Hz, 38 %. ACES's and FR079's stamps have none (ACES's gaps vary from 0.5 to 1.9
    periods: a varying rate, which re-timing by count would get wrong: relations under 2 s with
    ``odom="odom"`` 0.0334 m as stamped, 0.0355 m re-timed).
    """
    a = np.asarray(stamps, dtype=np.float64)
    period = stream_period(a)
    if a.size < 3 or not period > 0.0 or np.mean(np.diff(a) < 0.1 * period) < BURST_SHARE:
        return None
    k = max(1, math.ceil(window / period))
    idx = np.arange(a.size)
    bound = a - idx * period  # stamps[j] - j T
    padded = np.concatenate([bound, np.full(k, np.inf)])
    return np.lib.stride_tricks.sliding_window_view(padded, k + 1).min(axis=1) + idx * period
