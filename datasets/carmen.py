"""CARMEN log reader (``.clf`` / ``.log``, plain, ``.gz`` or ``.bz2``): FLASER, RLASER, ROBOTLASER1/2, ODOM.

One message per line, ``NAME fields... ipc_timestamp ipc_hostname logger_timestamp``::

    FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp
    ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
                n r1..rn m e1..em x y theta odom_x odom_y odom_theta tv rv fsd ssd turn_axis
                ipc_timestamp host logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp host logger_timestamp

A scan's stamp is its ``ipc_timestamp`` (the stamps of Kümmerle's relation files). ``x y theta``
is the laser's pose and ``odom_x odom_y odom_theta`` the robot's (``base_link``), both in ``odom``;
the scan's ``odom`` is the robot pose and ``sensor_offset`` the laser pose in ``base_link``.
FLASER / RLASER carry no angles: CARMEN's convention (``carmen_laser_guess_angle_increment``) is a
first beam at -90° and 1° steps for 180/181 beams, 0.5° for 360/361, 0.25° for 400/401, otherwise
180° over ``n - 1`` steps. Units: metres, radians, seconds.

Ranges that are non-finite, <= 0 or >= the maximum range become ``nan``. Without an explicit
``max_range`` it is CARMEN's 80 m (or the log's ``PARAM robot_front_laser_max``), lowered to the
log's saturation value when the first laser lines show one repeated often (ACES saturates at 50 m).

The log is streamed: the constructor makes one fast pass (record counts, ODOM table, sanity of
each laser line), iteration a second, parsing one line at a time.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from frslam_graph.datasets.recording import PoseInterpolator, Recording, RecordingStats, acquisition_times
from frslam_graph.datasets.scan import Scan

from frslam_graph.errors import OptionError, RecordingError
from frslam_graph.limits import bounded_lines, open_binary, short_repr
from frslam_graph.se2 import wrap_atan2

FRONT = ("FLASER", "ROBOTLASER1")
REAR = ("RLASER", "ROBOTLASER2")
LASERS = {"front": FRONT, "rear": REAR, "all": FRONT + REAR}
ODOM_MODES = ("auto", "laser", "odom", "none")
# Record types CARMEN logs contain that carry no scan: counted, not warned about.
OTHER_TYPES = frozenset(
    "PARAM SYNC ODOM TRUEPOS NMEAGGA NMEARMC NMEA-GGA NMEA-RMC GPSNMEA RAWLASER1 RAWLASER2 RAWLASER3"
    " RAWLASER4 LASER1 LASER2 LASER3 LASER4 ROBOTLASER0 SONAR BUMPER VELOCITY VECTORMOVE FOLLOWTRAJECTORY"
    " IMU ARMSTATE BASEVELOCITY SCANMARK POSITIONLASER ODOM_ACK FLASER_ACK".split()
)
KNOWN_TYPES = OTHER_TYPES | set(FRONT + REAR)
CARMEN_MAX_RANGE = 80.0  # carmen_string_to_robot_laser_message_orig's maximum_range
SATURATION_SAMPLE = 300  # laser lines inspected for a saturation value
BURSTY = "recording stamped on arrival in bursts (ODOM records paired at estimated acquisition times)"
SUFFIXES = (".clf", ".log", ".clf.gz", ".log.gz", ".clf.bz2", ".log.bz2")


def is_carmen(path: Path) -> bool:
    """True when the file name has a CARMEN suffix (.clf / .log, optionally .gz / .bz2)."""
    return path.name.lower().endswith(SUFFIXES)


def _found(counts: Counter) -> str:
    """The record types of a log without the laser wanted, for its error: the known types with
    their counts, the others (e.g. a binary file's "lines") only counted, never quoted."""
    known = [(k, n) for k, n in counts.most_common() if k in KNOWN_TYPES]
    other = sum(n for k, n in counts.items() if k not in KNOWN_TYPES)
    parts = [f"{k} {n}" for k, n in known]
    if other:
        parts.append(f"{other} line{'s' * (other != 1)} of no known CARMEN record type")
    return ", ".join(parts) or "no records"


def carmen_angle_increment(n: int) -> float:
    """CARMEN's guess of the beam spacing of an FLASER/RLASER line with ``n`` readings (radians)."""
    if n in (180, 181):
        return math.pi / 180.0
    if n in (360, 361):
        return math.pi / 360.0
    if n in (400, 401):
        return math.pi / 720.0
    return math.pi / max(n - 1, 1)


def _lines(path: Path, stats: RecordingStats) -> Iterator[tuple[int, str]]:
    """Numbered lines (1-based); a damaged compressed stream ends the file, noted in ``stats``.

    Read in bounded pieces (``frslam_graph.limits``): a line over ``MAX_LINE_BYTES``, more than
    ``MAX_LINES`` lines or a ``.gz`` / ``.bz2`` stream expanding over ``MAX_EXPANSION`` times its
    size raises RecordingError naming the file and line.
    """
    compressed = path.name.lower().endswith((".gz", ".bz2"))
    size = path.stat().st_size if compressed else None
    lineno = 0
    try:
        with open_binary(path) as f:
            for raw in bounded_lines(f, path, RecordingError, compressed_size=size):
                lineno += 1
                line = raw.decode("latin-1")
                if line.endswith("\r\n"):
                    line = line[:-2] + "\n"
                yield lineno, line
    except RecordingError:
        raise
    except (EOFError, OSError, ValueError) as exc:  # truncated .gz/.bz2, corrupt stream
        stats.skip(f"rest of file unreadable ({exc})", f"{path.name}:{lineno + 1}")


class _Parsed(NamedTuple):
    """One laser line, parsed."""

    stamp: float
    ranges: np.ndarray
    start: float  # angle of the first beam, rad
    increment: float  # rad
    max_range: float | None  # from the line (ROBOTLASER), else None
    laser: list[float]  # laser pose x, y, theta in odom
    robot: list[float]  # robot pose x, y, theta in odom


def _check_fields(kind: str, tok: list[str]) -> str | None:
    """None when a laser line has the right number of fields, else what is wrong."""
    try:
        if kind in ("FLASER", "RLASER"):
            n = int(tok[1])
            need = n + 11
        else:
            n = int(tok[8])
            m = int(tok[9 + n])
            need = n + m + 24
    except (ValueError, IndexError):
        return "malformed laser record (bad beam count)"
    if n <= 0:
        return "laser record with no beams"
    if len(tok) != need:
        return f"malformed laser record (expected {need} fields, found {len(tok)})"
    return None


def _parse_laser(kind: str, tok: list[str]) -> _Parsed:
    """Parse a laser line whose field count was checked; raises ValueError on a bad number."""
    if kind in ("FLASER", "RLASER"):
        n = int(tok[1])
        ranges = np.array(tok[2 : 2 + n], dtype=np.float64)
        v = [float(x) for x in tok[2 + n : 2 + n + 7]]
        inc = carmen_angle_increment(n)
        return _Parsed(v[6], ranges, -math.pi / 2.0, inc, None, v[0:3], v[3:6])
    start, _fov, res, max_range = (float(x) for x in tok[2:6])
    n = int(tok[8])
    ranges = np.array(tok[9 : 9 + n], dtype=np.float64)
    m = int(tok[9 + n])
    p = 10 + n + m
    v = [float(x) for x in tok[p : p + 6]]
    stamp = float(tok[p + 11])
    return _Parsed(stamp, ranges, start, res, max_range, v[0:3], v[3:6])


class CarmenLog(Recording):
    """A CARMEN log as a stream of :class:`Scan`.

    Args:
        path: ``.clf`` / ``.log`` file, optionally ``.gz`` / ``.bz2``.
        laser: ``"front"`` (FLASER, ROBOTLASER1; default), ``"rear"`` or ``"all"``.
        odom: ``"auto"`` (default) interpolates the ODOM records at the scan stamps when the log
            shows that the laser lines' poses are stale copies of the last ODOM record and the
            stamps can be trusted, else takes the laser lines' poses (see :attr:`odom_source`,
            :attr:`odom_reason`; of the shared logs only ACES is interpolated: 0.0395 -> 0.0350 m,
            0.453 -> 0.306 deg, see tools/README.md); ``"laser"`` takes the robot pose written in
            each laser line; ``"odom"`` interpolates the ODOM records at the scan stamps (both
            re-timed from their message counts when the log stamps them on arrival in bursts, as
            Intel does: :func:`~frslam_graph.datasets.recording.acquisition_times`); ``"none"``
            attaches none.
        max_range: readings at or beyond it become ``nan``; ``None`` = detect (see module doc).
        backwards: a scan stamped before an earlier line's scan is ``"keep"`` (kept in file
            order, counted in the warning: the Intel log has 1,612 such FLASER lines, and its
            odometry shows that the file order is the true one), ``"skip"`` (the rest is then
            monotonic) or ``"error"`` (RecordingError).
        odom_tolerance: with ``odom="odom"``, seconds a scan may lie outside the ODOM records.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        laser: Literal["front", "rear", "all"] = "front",
        odom: Literal["auto", "laser", "odom", "none"] = "auto",
        max_range: float | None = None,
        backwards: Literal["keep", "skip", "error"] = "keep",
        odom_tolerance: float = 0.5,
    ):
        super().__init__(path)
        if laser not in LASERS:
            raise OptionError(
                f"laser must be one of {sorted(LASERS)}, got {short_repr(laser)}",
                path,
                option="laser",
                value=laser,
                choices=list(LASERS),
                problem="no such laser",
            )
        if odom not in ODOM_MODES:
            raise OptionError(
                f"odom must be 'auto', 'laser', 'odom' or 'none', got {short_repr(odom)}",
                path,
                option="odom",
                value=odom,
                choices=ODOM_MODES,
                problem="no such odometry source",
            )
        if backwards not in ("keep", "skip", "error"):
            raise RecordingError(
                f"backwards must be 'keep', 'skip' or 'error', got {backwards!r}", source=path
            )
        if not self.path.is_file():
            raise RecordingError("no such file", source=self.path)
        self.laser_types = LASERS[laser]
        self.backwards = backwards
        self.odom_tolerance = float(odom_tolerance)
        self.counts: Counter = Counter()  # record type -> lines, from the first pass
        self._len = 0
        self._odom = np.zeros((0, 4))
        self._odom_in_file_order = np.zeros((0, 4))
        self._first_stamp = self._last_stamp = float("nan")
        sample_max, sample_hits, sample_beams, param_max = self._index()
        if self._len == 0:
            found = _found(self.counts)
            if self._first_pass.skipped:
                found += "; " + self._first_pass.summary()
            present = [name for name, kinds in LASERS.items() if any(self.counts[k] for k in kinds)]
            message = f"no {'/'.join(self.laser_types)} laser records ({found})"
            if not present:
                raise RecordingError(message, source=self.path)
            raise OptionError(
                message,
                self.path,
                option="laser",
                value=laser,
                choices=present,
                problem=f"no {'/'.join(self.laser_types)} records in the log",
            )
        if odom == "odom" and not len(self._odom):
            raise OptionError(
                "odom='odom' but the log has no usable ODOM records",
                self.path,
                option="odom",
                value=odom,
                choices=[m for m in ODOM_MODES if m != "odom"],
                problem="no usable ODOM records in the log",
            )
        self.odom_source, self.odom_reason = self._odom_source(odom)
        if max_range is not None:
            self.max_range, self.max_range_source = float(max_range), "given"
        else:
            self.max_range, self.max_range_source = (
                param_max or CARMEN_MAX_RANGE,
                ("PARAM robot_front_laser_max" if param_max else "CARMEN default"),
            )
            # A value repeated on >= 0.5 % of the sampled beams is the sensor's "no return".
            if 0 < sample_max < self.max_range and sample_hits >= max(5, 0.005 * sample_beams):
                self.max_range, self.max_range_source = sample_max, "saturation value of the log"

    def _odom_source(self, mode: str) -> tuple[str, str]:
        """Where each scan's wheel pose comes from (``"laser"``, ``"odom"`` or ``"none"``), and why.

        CARMEN writes into a laser line the robot pose of the last ODOM record it received (ACES,
        Intel) or one interpolated at the scan's time (FR079). A copied pose is up to one ODOM
        period old (ACES: 0.18 s, 5-12 deg while turning in place), which the scan matcher then
        inherits as a wrong seed; interpolating the ODOM records at the scan's stamp removes it,
        but only where the stamps are trustworthy: on Intel laser and ODOM stamps go backwards by
        up to 0.9 s, and the file order (the copied pose) is then the better clock.
        """
        if mode != "auto":
            said = {
                "laser": "robot pose of each laser line",
                "odom": "ODOM records interpolated at the scan stamps",
            }
            return mode, said.get(mode, "none attached")
        stale, checked, backwards = self._pose_check
        if checked == 0:
            return "laser", "robot pose of each laser line"
        if stale < checked:
            return "laser", "robot pose of each laser line (interpolated by the logger)"
        if backwards or len(self._odom) < 2:
            return "laser", (
                "robot pose of each laser line (a copy of the last ODOM record, kept: "
                f"{backwards} stamps earlier than an earlier one)"
            )
        return "odom", "ODOM records interpolated at the scan stamps (the laser lines copy the last one)"

    # ---------------------------------------------------------------- first pass
    def _index(self) -> tuple[float, int, int, float | None]:
        odom_rows: list[tuple[float, float, float, float]] = []
        # stamps of the laser lines counted in self._len, file order (nan: unreadable)
        laser_stamps: list[float] = []
        sample_max, sample_hits, sample_beams, sampled = 0.0, 0, 0, 0
        param_max: float | None = None
        stamps_first = stamps_last = float("nan")
        # laser lines whose robot pose is the last ODOM record's, lines checked, backward stamps
        stale = checked = backwards = 0
        last_odom: tuple[float, float, float] | None = None
        last_laser_stamp = last_odom_stamp = -math.inf
        first_pass = RecordingStats()
        self._first_pass = first_pass
        for _lineno, line in _lines(self.path, first_pass):
            head = line.split(None, 2)
            if not head or head[0].startswith("#"):
                continue
            kind = head[0]
            self.counts[kind] += 1
            if kind in self.laser_types:
                # fast path: a well-formed FLASER/RLASER line has n + 11 single-space separated fields
                fast = kind in ("FLASER", "RLASER") and len(head) > 1 and head[1].isdigit()
                if fast and line.count(" ") + 1 == int(head[1]) + 11:
                    tok = None
                else:
                    tok = line.split()
                    if _check_fields(kind, tok) is not None:
                        continue
                self._len += 1
                try:
                    stamp = float(line.rsplit(None, 3)[1])
                except (ValueError, IndexError):
                    laser_stamps.append(math.nan)
                    continue
                laser_stamps.append(stamp)
                if not math.isfinite(stamps_first):
                    stamps_first = stamp
                stamps_last = stamp
                backwards += stamp < last_laser_stamp
                last_laser_stamp = max(last_laser_stamp, stamp)
                if kind in ("FLASER", "RLASER"):
                    try:  # ... odom_x odom_y odom_theta ipc_timestamp host logger_timestamp
                        robot = tuple(float(v) for v in line.rsplit(None, 6)[1:4])
                    except ValueError:
                        robot = None
                    if robot is not None and last_odom is not None:
                        checked += 1
                        stale += last_odom is not None and all(
                            abs(a - b) <= 1e-9 for a, b in zip(robot, last_odom, strict=True)
                        )
                if sampled < SATURATION_SAMPLE and kind in ("FLASER", "RLASER"):
                    sampled += 1
                    tok = tok or line.split()
                    try:
                        r = np.array(tok[2 : 2 + int(tok[1])], dtype=np.float64)
                    except ValueError:
                        continue
                    r = r[np.isfinite(r)]
                    if r.size:
                        top = float(r.max())
                        if top > sample_max:
                            sample_max, sample_hits = top, 0
                        sample_hits += int(np.count_nonzero(r == sample_max))
                        sample_beams += r.size
                continue
            tok = line.split() if kind in ("ODOM", "PARAM") else head
            if kind == "ODOM":
                if len(tok) >= 8:
                    try:
                        row = (float(tok[-3]), float(tok[1]), float(tok[2]), float(tok[3]))
                    except ValueError:
                        row = None
                    if row is not None:
                        odom_rows.append(row)
                        last_odom = row[1:]
                        backwards += row[0] < last_odom_stamp
                        last_odom_stamp = max(last_odom_stamp, row[0])
            elif kind == "PARAM" and len(tok) >= 3 and tok[1] == "robot_front_laser_max":
                try:
                    param_max = float(tok[2])
                except ValueError:
                    pass
        self._first_stamp, self._last_stamp = stamps_first, stamps_last
        self._pose_check = (stale, checked, backwards)
        self._laser_stamps = np.array(laser_stamps, dtype=np.float64)
        if odom_rows:
            table = np.array(odom_rows, dtype=np.float64)
            keep = np.ones(len(table), dtype=bool)  # drop records stamped before their predecessor
            keep[1:] = table[1:, 0] > np.maximum.accumulate(table[:, 0])[:-1]
            self._odom = table[keep]
            self._odom_in_file_order = table
        return sample_max, sample_hits, sample_beams, param_max

    def __len__(self) -> int:
        """Laser records of the selected kind with the right number of fields (first pass).

        A record that passes that check but holds a non-numeric value is found only while
        iterating; it is then skipped and reported, and ``stats.scans`` is one less.
        """
        return self._len

    @property
    def duration(self) -> float:
        """Seconds between the first and the last laser line's stamp (file order)."""
        return float(self._last_stamp - self._first_stamp)

    def odometry(self) -> np.ndarray:
        """(M, 4) ODOM records ``stamp, x, y, theta`` with increasing stamps (others dropped)."""
        return self._odom.copy()

    def _odom_track(self) -> tuple[np.ndarray, np.ndarray | None]:
        """What ``odom="odom"`` interpolates, and at which times: the ODOM table, or all ODOM records
        in file order at their acquisition times when their stamps are arrival times of a bursty
        stream (:func:`acquisition_times`); the laser lines' acquisition times (in the first
        pass's order), or None when their stamps follow a steady clock."""
        track = self._odom
        acquired = acquisition_times(self._odom_in_file_order[:, 0])
        if acquired is not None:
            track = np.column_stack((acquired, self._odom_in_file_order[:, 1:]))
            ok = np.ones(len(track), dtype=bool)  # the bound may tie or step back: keep it increasing
            ok[1:] = track[1:, 0] > np.maximum.accumulate(track[:, 0])[:-1]
            track = track[ok]
        stamps = self._laser_stamps.copy()
        good = np.isfinite(stamps)
        scans = acquisition_times(stamps[good])
        if scans is None:
            return track, None
        stamps[good] = scans
        return track, stamps

    # ---------------------------------------------------------------- iteration
    def _scans(self, stats: RecordingStats) -> Iterator[Scan]:
        angles_cache: dict[tuple[int, float, float], np.ndarray] = {}
        last_stamp = -math.inf
        name = self.path.name
        use_odom_table = self.odom_source == "odom"
        track, acquired = self._odom_track() if use_odom_table else (self._odom, None)
        odom_at = PoseInterpolator(track, self.odom_tolerance)
        if acquired is not None or track is not self._odom:
            stats.flag(BURSTY, name)  # once: says how the poses were paired
        line_index = -1  # laser lines passing the field check, as counted by the first pass
        for lineno, line in _lines(self.path, stats):
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            kind = tok[0]
            stats.records[kind] += 1
            where = f"{name}:{lineno}"
            if kind not in self.laser_types:
                if kind in FRONT or kind in REAR:
                    stats.flag(
                        f"{kind} records not selected (laser={'rear' if kind in FRONT else 'front'!r})", where
                    )
                elif kind not in OTHER_TYPES:
                    stats.skip(f"unknown record type {kind!r}", where)
                continue
            problem = _check_fields(kind, tok)
            if problem is not None:
                if not line.endswith("\n"):
                    problem = "laser record cut short at end of file"
                stats.skip(problem, where)
                continue
            line_index += 1
            try:
                rec = _parse_laser(kind, tok)
            except ValueError:
                stats.skip("laser record with a non-numeric field", where)
                continue
            if not math.isfinite(rec.stamp):
                stats.skip("laser record with a non-finite stamp", where)
                continue
            if rec.stamp < last_stamp:
                if self.backwards == "error":
                    raise RecordingError(
                        f"stamp {rec.stamp:.6f} earlier than an earlier scan's {last_stamp:.6f}",
                        source=self.path,
                        where=f"line {lineno}",
                    )
                if self.backwards == "skip":
                    stats.skip("scans stamped before an earlier scan", where)
                    continue
                stats.flag("scans stamped before an earlier scan (kept in file order)", where)
            last_stamp = max(last_stamp, rec.stamp)
            if not all(math.isfinite(v) for v in (*rec.laser, *rec.robot)):
                stats.skip("laser record with a non-finite pose", where)
                continue
            ranges = rec.ranges
            own = rec.max_range is not None and rec.max_range > 0 and self.max_range_source != "given"
            max_range = rec.max_range if own else self.max_range
            bad = ~np.isfinite(ranges) | (ranges < 0.0)
            if bad.any():
                stats.flag("scans with NaN/inf/negative ranges (set to nan)", where)
            invalid = bad | ~(ranges > 0.0) | (ranges >= max_range)
            ranges[invalid] = np.nan
            key = (ranges.size, rec.start, rec.increment)
            angles = angles_cache.get(key)
            if angles is None:
                angles = rec.start + rec.increment * np.arange(ranges.size, dtype=np.float64)
                angles.flags.writeable = False
                angles_cache[key] = angles
            rx, ry, rth = rec.robot
            lx, ly, lth = rec.laser
            c, s = math.cos(rth), math.sin(rth)
            dx, dy = lx - rx, ly - ry
            offset = (c * dx + s * dy, -s * dx + c * dy, wrap_atan2(lth - rth))
            if self.odom_source == "laser":
                odom = (rx, ry, rth)
            elif use_odom_table:
                at = rec.stamp
                if (
                    acquired is not None
                    and line_index < acquired.size
                    and math.isfinite(acquired[line_index])
                ):
                    at = float(acquired[line_index])
                odom = odom_at(at)
                if odom is None:
                    stats.flag("scans outside the ODOM records (odom None)", where)
            else:
                odom = None
            yield Scan(rec.stamp, ranges, angles, odom, float(max_range), offset)
