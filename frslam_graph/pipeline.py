"""Streaming FR-SLAM backend: scans in, poses in ``map`` out (REP-105; metres, radians, seconds).

``FRSlam.add_scan(stamp, ranges, angle_min, angle_increment, odom=None)`` runs the scan odometry
(KISS-ICP fused with wheel odometry, :mod:`frslam_graph.odometry`); every keyframe becomes a
Pose2 variable of the :class:`~frslam_graph.graph.PoseGraph` (iSAM2). Non-keyframe scans hang off
their keyframe by their odometry pose relative to it, so the whole trajectory follows the graph.

Seams for the floor-plan update strategy (paper Alg. 3):

- ``update_strategy``: any object with ``on_keyframe(slam, keyframe: KeyframeInfo)`` (or a plain
  callable with that signature), called after each keyframe is in the graph. It may read
  ``slam.occupancy_grid()``, ``slam.keyframes()``, ``slam.graph``; add priors with
  ``slam.add_floorplan_prior(...)``, remove them with ``slam.remove_prior(...)``, re-express the
  map with ``slam.transform_map(...)`` and record decisions with ``slam.log_event(...)``.
- ``finish()`` runs the final LM batch, after the strategy's optional ``on_finish(slam)`` (the end
  of an offline run: e.g. a last refinement on the complete map); ``process(recording)`` is the
  offline loop.

The decision log (``slam.log``) is a list of :class:`DecisionEvent`; nothing is printed.

Contract of the streaming API:

- Arguments are checked (:mod:`frslam_graph.stream_input`): a wrong type, shape or a non-finite
  stamp, angle or sensor offset raises :class:`~frslam_graph.errors.RecordingError` whose
  ``where`` names the argument; nothing is recorded then. ``floor_plan`` may be a path: it is
  loaded with ``FloorPlan.load``.
- One thread at a time. ``FRSlam`` is not thread-safe and does not serialise callers: the scan
  order is the trajectory's order, so two producers interleaving scans would be a wrong answer
  even behind a lock. A mutating call (``add_scan``, ``add_points``, ``add``, ``process``,
  ``finish``, the floor-plan seam's calls, ...) made while another thread is inside one raises
  :class:`~frslam_graph.errors.FrslamError` at once instead of blocking (a non-blocking,
  re-entrant lock: hooks call back on the same thread freely). Read-only queries (``pose``,
  ``trajectory``, ...) are not guarded: call them from the feeding thread too.
"""

from __future__ import annotations

import contextlib
import functools
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, get_args

import gtsam
import numpy as np

from frslam_graph import stream_input
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, FrslamError, RecordingError
from frslam_graph.graph import PoseGraph, PriorHandle
from frslam_graph.motion_model import compose, compose_many, inverse
from frslam_graph.odometry import OdometryResult, OdometryStats, ScanOdometry


@dataclass(frozen=True, slots=True)
class DecisionEvent:
    """One entry of the decision log: what happened, when, and the numbers behind it."""

    stamp: float
    kind: str  # e.g. odom_jump, empty_scan, dropped_scans, degenerate_start, prior_added, ...
    message: str
    keyframe: int | None = None
    data: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class KeyframeInfo:
    """A keyframe: graph index, stamp, index of its scan, poses in map (current) and odom."""

    index: int
    stamp: float
    scan_index: int
    pose_map: np.ndarray
    pose_odom: np.ndarray


#: why a floor-plan prior left the graph (``prior_removed`` events, ``metrics.json`` ``priors``)
PriorRemoval = Literal["wrong", "re-anchored"]
PRIOR_REMOVAL_CAUSES: tuple[str, ...] = get_args(PriorRemoval)


class UpdateStrategy(Protocol):
    def on_keyframe(self, slam: FRSlam, keyframe: KeyframeInfo) -> None: ...


@dataclass(slots=True)
class SlamResult:
    """Output of :meth:`FRSlam.process`."""

    trajectory: np.ndarray  # (N, 4) stamp, x, y, theta in map
    keyframes: np.ndarray  # (K, 4) stamp, x, y, theta in map
    odometry: np.ndarray  # (N, 4) stamp, x, y, theta in odom
    map_to_odom: np.ndarray  # (3,)
    stats: OdometryStats
    log: list[DecisionEvent]
    latencies: np.ndarray  # (N,) seconds per scan (add_scan; parallel: odometry + backend stage)
    wall_time: float  # seconds for the whole run (incl. the batch)
    duration: float  # recording time span, seconds
    parallel: bool = False  # odometry ran in a worker process (latencies: sum of both stages)

    @property
    def realtime_factor(self) -> float:
        return self.duration / self.wall_time if self.wall_time > 0 else float("inf")


class _Rows:
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


class _ScanTrack:
    """Per scan what the trajectory needs, nothing more: stamp, keyframe index, pose relative to
    that keyframe and the odometry pose (64 B per scan, amortised)."""

    def __init__(self) -> None:
        self._f = _Rows(7)  # stamp, relative (x, y, theta), odometry (x, y, theta)
        self._kf = _Rows(None, np.int64)

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


@dataclass(slots=True)
class _Keyframe:
    stamp: float
    scan_index: int
    pose_odom: np.ndarray
    points: np.ndarray  # (M, 2) float32 in base_link
    sensor_origin: np.ndarray  # (2,) in base_link


def _one_thread(method: Callable[..., Any]) -> Callable[..., Any]:
    """Refuse a call while another thread is inside a guarded method of the same FRSlam (see the
    module docstring); the same thread may re-enter (hooks)."""
    name = method.__name__

    @functools.wraps(method)
    def guarded(self: FRSlam, *args: Any, **kwargs: Any) -> Any:
        if not self._lock.acquire(blocking=False):
            raise FrslamError(
                f"FRSlam is not thread-safe: {name} called from two threads at once (another "
                f"thread is in {self._lock_holder or 'it'}); feed and query one FRSlam from one thread"
            )
        outer = self._lock_holder is None
        if outer:
            self._lock_holder = name
        try:
            return method(self, *args, **kwargs)
        finally:
            if outer:
                self._lock_holder = None
            self._lock.release()

    return guarded


class FRSlam:
    """Streaming 2D SLAM backend with floor-plan priors (see module docstring): single-threaded,
    arguments checked."""

    def __init__(
        self,
        config: FRSlamConfig | dict | str | Path | None = None,
        floor_plan: Any = None,
        update_strategy: UpdateStrategy | Callable[[FRSlam, KeyframeInfo], None] | None = None,
    ):
        """``floor_plan``: a FloorPlan, or a path loaded with ``FloorPlan.load``, or None."""
        self._lock = threading.RLock()  # see _one_thread
        self._lock_holder: str | None = None
        self.config = _as_config(config)
        self.floor_plan = floor_plan = stream_input.floor_plan(floor_plan)
        if update_strategy is None and floor_plan is not None:
            # the paper's Alg. 3: register the plan as the map grows, relocalise, add robust priors
            from frslam_graph.update_strategy import FloorPlanUpdater

            update_strategy = FloorPlanUpdater(floor_plan, self.config.updates)
        self.update_strategy = update_strategy
        self.odometry = ScanOdometry(self.config.odometry)
        self.graph = PoseGraph(self.config.graph)
        self.log: list[DecisionEvent] = []
        self._kfs: list[_Keyframe] = []
        self._kf_points: list[np.ndarray] = []  # per keyframe, for keyframe_scans() (no rebuild)
        self._kf_origins: list[np.ndarray] = []
        self._scans = _ScanTrack()
        self._was_degenerate = False
        self._angles_cache: tuple[float, float, int, tuple[np.ndarray, np.ndarray]] | None = None
        self._odometry_elsewhere = False  # process() ran the odometry in a worker process
        self._mappers: dict[tuple[float, bool], Any] = {}  # (resolution, free_space) -> OccupancyMapper
        self._deferred: deque[Iterator[Any]] = deque()  # see defer()
        self._head_costed = False  # the first deferred job's last yield gave a cost
        self._steps_run = 0  # deferred steps run so far (a hook that ran some made its scan busy)
        # loop closure (frslam_graph.loop_closure), run on each keyframe after the update strategy
        from frslam_graph.loop_closure import LoopCloser

        lc = self.config.loop_closure
        self.loop_closer: LoopCloser | None = LoopCloser(lc) if lc.enabled else None

    # ----------------------------------------------------------------- input
    @_one_thread
    def add_scan(
        self,
        stamp: float,
        ranges: np.ndarray,
        angle_min: float,
        angle_increment: float,
        odom: tuple[float, float, float] | None = None,
        range_max: float | None = None,
        sensor_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[float, float, float]:
        """Add a laser scan (sensor frame, sensor_msgs/LaserScan layout); return base_link in map.

        ``ranges`` (N,): nan / inf / <= 0 / >= range_max are no returns. ``odom``: wheel pose
        (x, y, theta) in the wheel-odometry frame at ``stamp``, or None (a nan in it: no wheel
        reading). ``range_max``: None = ``odometry.max_range``; inf = no limit. A bad argument
        raises RecordingError naming it (module docstring).
        """
        stamp = stream_input.finite_number(stamp, "stamp")
        r = stream_input.ranges(ranges)
        amin = stream_input.finite_number(angle_min, "angle_min")
        inc = stream_input.finite_number(angle_increment, "angle_increment")
        if inc == 0.0:
            raise RecordingError("angle_increment must be non-zero", where="angle_increment")
        rmax = stream_input.range_max(range_max, self.config.odometry.max_range)
        odom = stream_input.odom(odom)
        cos_a, sin_a = self._angles(amin, inc, len(r))
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > 0.0) & (r < rmax)
        rv = r[ok]
        pts = np.column_stack((rv * cos_a[ok], rv * sin_a[ok]))
        return self.add_points(stamp, pts, odom, sensor_offset)

    @_one_thread
    def add(self, scan: Any) -> tuple[float, float, float]:
        """Add a :class:`frslam_graph.datasets.Scan`."""
        return self.add_points(scan.stamp, scan.points, scan.odom, scan.sensor_offset)

    @_one_thread
    def add_points(
        self,
        stamp: float,
        points: np.ndarray,
        odom: tuple[float, float, float] | None = None,
        sensor_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[float, float, float]:
        """Add planar end points (M, 2) in the sensor frame; return base_link in map."""
        self._check_own_odometry()
        stamp = stream_input.finite_number(stamp, "stamp")
        pts, off = _body_points(points, sensor_offset)
        self._record(self.odometry.process(stamp, pts, stream_input.odom(odom)), pts, off)
        return self.pose()

    # ------------------------------------------------------------ internals
    def _check_own_odometry(self) -> None:
        if self._odometry_elsewhere:
            raise ConfigError(
                "this FRSlam ran process() with its odometry in a worker process and cannot take "
                "more scans; use process(..., parallel=False) to keep streaming afterwards",
                where="parallel",
            )

    @_one_thread
    def defer(self, steps: Iterator[Any]) -> None:
        """Run a hook's work as ``steps`` (a generator: the work between two yields is one step)
        on the following scans instead of this one.

        One step runs per scan that is not a keyframe (keyframe scans have the graph update and
        the hooks), jobs in the order they were deferred; :meth:`run_deferred` runs all that are
        pending (a hook calls it before work that needs them done; :meth:`finish` and
        :meth:`process` call it). The schedule depends only on the sequence of scans, so results
        are deterministic whatever the timing. A floor-plan relocalisation, its prior, each
        relinearising iteration after it and the prior check are such steps: no single scan pays
        for all of them.

        Sharing the scan with loop closure: each ``yield`` may give the estimated cost (ms, a
        cost model from the sizes involved, never a clock) of the step that ends there; the loop
        closer then gets the rest of ``loop_closure.budget_ms`` on that scan (only steps that
        fit). A step that yields None, or a job's last part when its last yield was None, takes
        the scan's whole budget. A job whose last yield was a number ends with light glue: the
        next job's step runs on the same scan.
        """
        if not isinstance(steps, Iterator):
            raise TypeError(
                f"defer() takes the steps as a generator (call the generator function), got "
                f"{type(steps).__name__}"
            )
        self._deferred.append(steps)

    @property
    def deferred_jobs(self) -> int:
        """Number of deferred jobs not finished yet (see :meth:`defer`)."""
        return len(self._deferred)

    @_one_thread
    def run_deferred(self) -> None:
        """Run every pending deferred step now."""
        while self._deferred:
            self._step_deferred()

    def _step_deferred(self) -> float | None:
        """Run the next deferred step; its estimated cost (ms; inf when unknown), None when no
        job was pending (see :meth:`defer`)."""
        while self._deferred:
            self._steps_run += 1
            try:
                cost = next(self._deferred[0])
            except StopIteration:
                self._deferred.popleft()
                costed, self._head_costed = self._head_costed, False
                if costed:
                    continue  # only glue after its last costed step: the next job's step runs
                return float("inf")
            self._head_costed = isinstance(cost, int | float) and not isinstance(cost, bool)
            return max(float(cost), 0.0) if self._head_costed else float("inf")
        return None

    def _angles(self, angle_min: float, inc: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """cos and sin of the beam angles (cached: the layout rarely changes)."""
        c = self._angles_cache
        if c is None or c[0] != angle_min or c[1] != inc or c[2] != n:
            ang = angle_min + inc * np.arange(n)
            self._angles_cache = c = (angle_min, inc, n, (np.cos(ang), np.sin(ang)))
        return c[3]

    def _record(self, res: OdometryResult, pts: np.ndarray, off: np.ndarray) -> None:
        """Take one scan's odometry result into the backend (log, trajectory, keyframe hooks)."""
        stamp = res.stamp
        if res.dropped:
            self.log_event(
                "dropped_scans",
                f"stamp gap: about {res.dropped} scan(s) missing",
                stamp=stamp,
                count=res.dropped,
            )
        if res.fallback and not res.icp_rejected:
            self.log_event(
                "motion_model_fallback",
                f"{res.n_points} valid points: motion model used instead of ICP",
                stamp=stamp,
                n_points=res.n_points,
            )
        if res.icp_rejected:
            self.log_event(
                "icp_rejected",
                "ICP far from the wheel increment; motion model used, scan not mapped",
                stamp=stamp,
            )
        if res.odom_jump:
            self.log_event("odom_jump", "wheel odometry inconsistent with ICP; ICP trusted", stamp=stamp)
        if res.degenerate != self._was_degenerate:
            kind = "degenerate_start" if res.degenerate else "degenerate_end"
            data = {"axis": res.degenerate_axis.tolist()} if res.degenerate_axis is not None else {}
            self.log_event(
                kind,
                "scan geometry degenerate (corridor)"
                if res.degenerate
                else "scan geometry constrained again",
                stamp=stamp,
                **data,
            )
            self._was_degenerate = res.degenerate
        scan_index = len(self._scans)
        self._scans.append(stamp, res.keyframe, res.relative, res.pose)
        if not res.is_keyframe:
            # a hook's deferred work, one step per scan; queued loop-closure work in the rest of
            # the scan's budget
            spent = self._step_deferred()
            if self.loop_closer is not None:
                if spent is None:
                    self.loop_closer.on_scan(self)
                elif spent < self.config.loop_closure.budget_ms:
                    self.loop_closer.on_scan(self, self.config.loop_closure.budget_ms - spent)
            return
        if res.keyframe == 0:
            self.graph.add_first(res.pose)  # map == odom at start
        else:
            self.graph.add_keyframe(res.between, res.covariance)
        kf = _Keyframe(stamp, scan_index, res.pose.copy(), pts.astype(np.float32), off[:2].copy())
        self._kfs.append(kf)
        self._kf_points.append(kf.points)
        self._kf_origins.append(kf.sensor_origin)
        info = self.keyframe(res.keyframe)
        busy = False
        if self.update_strategy is not None:
            hook = getattr(self.update_strategy, "on_keyframe", self.update_strategy)
            version, steps = self.graph.version, self._steps_run
            hook(self, info)
            # priors added / removed, or deferred steps run now (the hook needed them done): this
            # scan's budget is spent. Work merely deferred to the next scans costs nothing here
            # (counting it starved loop closure behind a floor plan: queue lag ~120 keyframes).
            busy = self.graph.version != version or self._steps_run != steps
        if self.loop_closer is not None:  # uses the keyframe's index and odometry pose only
            self.loop_closer.on_keyframe(self, info, work=not busy)

    # ------------------------------------------------------------- outputs
    def pose(self) -> tuple[float, float, float]:
        """Latest base_link pose in map."""
        if not len(self._scans):
            return (0.0, 0.0, 0.0)
        p = compose(self.graph.estimate(), self._scans.relative[-1])
        return (float(p[0]), float(p[1]), float(p[2]))

    def __len__(self) -> int:
        return len(self._scans)

    @property
    def _scan_kf(self) -> np.ndarray:
        """Keyframe index of every scan (a view)."""
        return self._scans.keyframe

    @property
    def _scan_rel(self) -> np.ndarray:
        """Pose of every scan relative to its keyframe (N, 3; a view)."""
        return self._scans.relative

    def keyframe(self, i: int) -> KeyframeInfo:
        kf = self._kfs[i]
        return KeyframeInfo(i, kf.stamp, kf.scan_index, self.graph.estimate(i), kf.pose_odom.copy())

    def keyframes(self) -> list[KeyframeInfo]:
        est = self.graph.estimates() if self._kfs else np.zeros((0, 3))
        return [
            KeyframeInfo(i, k.stamp, k.scan_index, est[i], k.pose_odom.copy())
            for i, k in enumerate(self._kfs)
        ]

    def keyframe_array(self) -> np.ndarray:
        """(K, 4) stamp, x, y, theta of the keyframes in map."""
        if not self._kfs:
            return np.zeros((0, 4))
        return np.column_stack(([k.stamp for k in self._kfs], self.graph.estimates()))

    def trajectory(self) -> np.ndarray:
        """(N, 4) stamp, x, y, theta in map of every accepted scan."""
        if not len(self._scans):
            return np.zeros((0, 4))
        est = self.graph.estimates()
        kf = self._scans.keyframe
        rel = self._scans.relative
        base = est[kf]
        c, s = np.cos(base[:, 2]), np.sin(base[:, 2])
        x = base[:, 0] + c * rel[:, 0] - s * rel[:, 1]
        y = base[:, 1] + s * rel[:, 0] + c * rel[:, 1]
        th = (base[:, 2] + rel[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return np.column_stack((self._scans.stamps, x, y, th))

    def odometry_trajectory(self) -> np.ndarray:
        """(N, 4) stamp, x, y, theta in odom (the fused odometry, never corrected)."""
        if not len(self._scans):
            return np.zeros((0, 4))
        return np.column_stack((self._scans.stamps, self._scans.odometry))

    def map_to_odom(self) -> tuple[float, float, float]:
        """T_map_odom = T_map_base · T_odom_base⁻¹ at the latest keyframe (x, y, theta)."""
        if not self._kfs:
            return (0.0, 0.0, 0.0)
        i = len(self._kfs) - 1
        t = self.graph.map_to_odom(i, self._kfs[i].pose_odom)
        return (float(t[0]), float(t[1]), float(t[2]))

    def registered_plan(self):
        """The floor plan registered into ``map`` (FloorPlan in metres), or None before any
        accepted registration / without a floor plan."""
        return getattr(self.update_strategy, "registered_plan", None)

    def keyframe_scans(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Per keyframe: end points (M, 2) and sensor origin (2,), both in base_link."""
        return list(self._kf_points), list(self._kf_origins)

    @_one_thread
    def occupancy_grid(self, resolution: float = 0.05, free_space: bool = False):
        """LiDAR occupancy grid (``OccupancyGrid``) of the keyframe scans at the current estimates.

        The default keeps walls (a hit outweighs many passing beams: the map a user loads);
        ``free_space=True`` weighs hits and misses as the floor-plan registration wants it (free
        space wins over stray hits, see ``mapping.FREE_SPACE_WEIGHTS``). Incremental: one
        :class:`~frslam_graph.mapping.OccupancyMapper` per resolution and kind is kept; each call
        inserts the new keyframes and re-inserts those whose estimate moved.
        """
        from frslam_graph.mapping import FREE_SPACE_WEIGHTS, OccupancyMapper

        if not isinstance(resolution, int | float) or not np.isfinite(resolution) or resolution <= 0:
            raise ConfigError(
                f"resolution must be a positive number of metres, got {resolution!r}", where="resolution"
            )
        key = (float(resolution), bool(free_space))
        mapper = self._mappers.get(key)
        if mapper is None:
            weights = FREE_SPACE_WEIGHTS if free_space else {}
            mapper = self._mappers[key] = OccupancyMapper(float(resolution), **weights)
        pts, origins = self.keyframe_scans()
        poses = self.graph.estimates() if self._kfs else np.zeros((0, 3))
        mapper.update(poses, pts, origins)
        return mapper.grid()

    @property
    def stats(self) -> OdometryStats:
        return self.odometry.stats

    # ------------------------------------------------------- floor-plan seam
    def log_event(
        self, kind: str, message: str, stamp: float | None = None, keyframe: int | None = None, **data: Any
    ) -> DecisionEvent:
        """Append a decision to the log (for the pipeline and the update strategy)."""
        if stamp is None:
            stamp = self._scans.stamps[-1] if len(self._scans) else float("nan")
        ev = DecisionEvent(float(stamp), kind, message, keyframe, dict(data))
        self.log.append(ev)
        return ev

    def keyframe_at(self, stamp: float, tolerance: float = 1e-6) -> tuple[int, np.ndarray]:
        """(keyframe index, pose of the scan relative to it) of the scan with this stamp."""
        st = self._scans.stamps
        if len(st) == 0:
            raise RecordingError("no scans yet", where="stamp")
        j = int(np.argmin(np.abs(st - stamp)))
        if abs(st[j] - stamp) > tolerance:
            raise RecordingError(f"no scan at stamp {stamp} (nearest {st[j]})", where="stamp")
        return int(self._scans.keyframe[j]), self._scans.relative[j].copy()

    @_one_thread
    def add_floorplan_prior(
        self,
        stamp_or_keyframe: int | float,
        pose: np.ndarray,
        covariance: np.ndarray,
        source: str = "floorplan",
        kind: str = "full",
        kernel: str | None = None,
        info: dict | None = None,
        extra_iterations: int | None = None,
    ) -> PriorHandle:
        """Add a robust prior: ``pose`` (x, y, theta) of base_link in map at a keyframe (int) or at
        the scan with that stamp (float; moved onto its keyframe through the odometry).
        ``extra_iterations``: relinearising iSAM2 iterations after it (default: see
        :meth:`PoseGraph.add_prior`)."""
        if isinstance(stamp_or_keyframe, int | np.integer):
            kf, rel = int(stamp_or_keyframe), np.zeros(3)
            stamp = self._kfs[kf].stamp if 0 <= kf < len(self._kfs) else float("nan")
        else:
            stamp = float(stamp_or_keyframe)
            kf, rel = self.keyframe_at(stamp)
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        cov = np.asarray(covariance, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise RecordingError(f"prior pose must be finite (x, y, theta), got {pose!r}", where="pose")
        if not 0 <= kf < len(self._kfs):
            raise RecordingError(f"no keyframe {kf} (have {len(self._kfs)})", where="keyframe")
        if np.any(rel != 0.0):
            # prior on the scan -> prior on its keyframe: kf = pose ⊕ rel⁻¹
            if kind == "translation":  # the prior has no heading: use the estimated one
                p = np.array([p[0], p[1], self.graph.estimate(kf)[2] + rel[2]])
            kf_pose = compose(p, inverse(rel))
            if kind == "full":  # tangent at the keyframe: ξ_kf = Ad(rel) ξ_scan
                ad = np.asarray(gtsam.Pose2(*rel).AdjointMap())
                cov = ad @ cov @ ad.T
            p = kf_pose
        handle = self.graph.add_prior(
            kf, p, cov, kind=kind, kernel=kernel, source=source, info=info, extra_iterations=extra_iterations
        )
        self.log_event(
            "prior_added",
            f"{kind} prior from {source} on keyframe {kf}",
            stamp=stamp,
            keyframe=kf,
            prior=handle.id,
            pose=p.tolist(),
        )
        return handle

    @_one_thread
    def remove_prior(self, handle: PriorHandle, reason: str = "", cause: PriorRemoval = "wrong") -> None:
        """Remove a prior (logged with the reason); see :meth:`remove_priors`."""
        self.remove_priors([handle], reason, cause)

    @_one_thread
    def remove_priors(
        self, handles: list[PriorHandle], reason: str = "", cause: PriorRemoval = "wrong"
    ) -> None:
        """Remove priors in one graph update (e.g. all of a retracted registration), each logged
        as ``prior_removed`` with its ``cause``: "wrong" (proven wrong, or its plan retracted) or
        "re-anchored" (the plan was refined or replaced: the keyframe is relocalised on it)."""
        if cause not in PRIOR_REMOVAL_CAUSES:
            raise ConfigError(
                f"cause must be one of {', '.join(map(repr, PRIOR_REMOVAL_CAUSES))}, got {cause!r}",
                where="cause",
            )
        for h in self.graph.remove_priors(handles):
            self.log_event(
                "prior_removed",
                reason or f"prior {h.id} removed",
                keyframe=h.keyframe,
                prior=h.id,
                cause=cause,
            )

    @_one_thread
    def transform_map(self, transform: np.ndarray, reason: str = "") -> None:
        """Re-express everything in a new map frame (pose p -> transform ⊕ p); map->odom changes."""
        self.graph.transform_map(transform)
        self.log_event(
            "map_transformed",
            reason or "map frame re-expressed",
            transform=np.asarray(transform, float).tolist(),
        )

    # ---------------------------------------------------------------- offline
    @_one_thread
    def finish(self) -> np.ndarray:
        """Final Levenberg-Marquardt batch over the whole graph; returns :meth:`trajectory`.

        Before it, the update strategy's ``on_finish(slam)`` when it has one (the floor-plan
        updater's final refinement) and the loop closer's queued work. The batches free iSAM2
        (``PoseGraph.optimize_batch(incremental=False)``): the estimates are then the batch's
        values, and a scan added afterwards rebuilds iSAM2 from them."""
        self.run_deferred()
        on_finish = getattr(self.update_strategy, "on_finish", None)
        if on_finish is not None:
            on_finish(self)
            self.run_deferred()
        if self.loop_closer is not None:  # loop-closure work still queued
            self.loop_closer.flush(self)
        if self._kfs:
            t0 = time.perf_counter()
            before = self.graph.error()
            # iSAM2 is not rebuilt at the end of a run: the estimates are the batch's values (its
            # factorisation of the whole graph would be the run's largest allocation)
            self.graph.optimize_batch(incremental=False)
            self.log_event(
                "batch_optimised",
                "final LM batch",
                error_before=before,
                error_after=self.graph.error(),
                seconds=time.perf_counter() - t0,
            )
            if self.loop_closer is not None:  # constraints between passes are loop closures
                self._final_alignment()
        return self.trajectory()

    def _final_alignment(self) -> None:
        """Dense constraints between passes at the converged estimate, re-optimised
        (:mod:`frslam_graph.final_alignment`); the previous round's constraints are replaced."""
        from frslam_graph.final_alignment import constraint_factor, dense_constraints

        lc = self.config.loop_closure
        odom = np.array([k.pose_odom for k in self._kfs])
        factors: list = []
        for round_ in range(lc.final_alignment_rounds):
            t0 = time.perf_counter()
            cons = dense_constraints(
                self.graph.estimates(),
                odom,
                self._kf_points,
                lc.final_alignment_radius,
                lc.max_point_range,
                # an offline run with the odometry in a worker: its core is free now
                processes=2 if self._odometry_elsewhere else 1,
            )
            new = [constraint_factor(c) for c in cons]
            self.graph.replace_factors([i for i in self.graph.factor_indices(factors) if i >= 0], new)
            factors = new
            before = self.graph.error()
            self.graph.optimize_batch(incremental=False)
            self.log_event(
                "final_alignment",
                f"round {round_ + 1}: {len(cons)} constraints between passes",
                constraints=len(cons),
                error_before=before,
                error_after=self.graph.error(),
                seconds=time.perf_counter() - t0,
            )

    @_one_thread
    def process(
        self, recording: Iterable[Any], batch: bool = True, parallel: bool | None = None
    ) -> SlamResult:
        """Run over every Scan of a recording (offline); LM batch at the end when ``batch``.

        ``parallel``: run the scan odometry in a worker process, one stage ahead of the backend
        (:mod:`frslam_graph.odometry_worker`; same results, about 1.5x the throughput on two
        cores). None = whenever possible: a fresh instance (no scans yet) where
        :func:`~frslam_graph.odometry_worker.available` holds. Afterwards this instance takes no
        more scans (its own odometry did not run). ``SlamResult.latencies`` are then the sum of
        both stages' seconds per scan (what ``add_scan`` would take).
        """
        from frslam_graph import odometry_worker

        can = (
            not len(self._scans)
            and not self._odometry_elsewhere
            and odometry_worker.available(self.config.odometry)
        )
        if parallel and not can:
            raise ConfigError(
                "process(parallel=True) needs a fresh FRSlam, Linux fork, two cores, a non-daemonic "
                "process and odometry.num_threads 1",
                where="parallel",
            )
        parallel = can if parallel is None else parallel
        lat = _Rows()
        t_start = time.perf_counter()
        first = last = None
        with contextlib.ExitStack() as stack:
            if parallel:
                worker = stack.enter_context(odometry_worker.OdometryWorker(self.config.odometry))
                self._odometry_elsewhere = True
                staged = self._odometry_in_worker(recording, worker)
            else:
                staged = self._odometry_here(recording)
            for stamp, res, pts, off, odometry_s in staged:
                t0 = time.perf_counter()
                self._record(res, pts, off)
                lat.append(odometry_s + time.perf_counter() - t0)
                first = stamp if first is None else first
                last = stamp
            if parallel:
                self.odometry.stats = worker.stats
        self.run_deferred()  # the last keyframes' steps (also without the batch)
        if batch:
            self.finish()
        wall = time.perf_counter() - t_start
        return SlamResult(
            self.trajectory(),
            self.keyframe_array(),
            self.odometry_trajectory(),
            np.asarray(self.map_to_odom()),
            self.stats,
            self.log,
            lat.array.copy(),
            wall,
            float(last - first) if first is not None else 0.0,
            bool(parallel),
        )

    def _odometry_here(self, recording: Iterable[Any]) -> Iterator[tuple]:
        """(stamp, odometry result, base_link points, sensor offset, seconds) per scan, in-process."""
        for scan in recording:
            self._check_own_odometry()
            t0 = time.perf_counter()
            stamp = stream_input.finite_number(scan.stamp, "stamp")
            pts, off = _body_points(scan.points, scan.sensor_offset)
            res = self.odometry.process(stamp, pts, scan.odom)
            yield scan.stamp, res, pts, off, time.perf_counter() - t0

    def _odometry_in_worker(self, recording: Iterable[Any], worker) -> Iterator[tuple]:
        """The same from an :class:`~frslam_graph.odometry_worker.OdometryWorker`; the stateless
        part of the odometry (prepare) runs in whichever stage is the lighter one."""

        def inputs():
            for scan in recording:  # the stamp is checked in the worker (raised in order)
                pts, off = _body_points(scan.points, scan.sensor_offset)
                yield scan.stamp, pts, scan.odom, off

        for (stamp, pts, _, off), res, seconds in worker.run(inputs(), self.odometry.prepare):
            yield stamp, res, pts, off, seconds


def _body_points(points: np.ndarray, sensor_offset: Any) -> tuple[np.ndarray, np.ndarray]:
    """Planar end points (M, 2) in the sensor frame -> base_link, and the offset (x, y, theta);
    both checked (RecordingError naming ``points`` / ``sensor_offset``)."""
    pts = stream_input.points(points)
    off = stream_input.pose(sensor_offset, "sensor_offset")
    if np.any(off != 0.0):
        pts = compose_many(off, np.column_stack((pts, np.zeros(len(pts)))))[:, :2]
    return pts, off


def _as_config(config: FRSlamConfig | dict | str | Path | None) -> FRSlamConfig:
    if config is None:
        return FRSlamConfig()
    if isinstance(config, FRSlamConfig):
        return config
    if isinstance(config, dict):
        return FRSlamConfig.from_dict(config)
    if isinstance(config, str | Path):
        return FRSlamConfig.load(config)
    raise ConfigError(
        f"config must be FRSlamConfig, a mapping or a file path, got {type(config).__name__}", where="config"
    )


__all__ = ["DecisionEvent", "FRSlam", "KeyframeInfo", "SlamResult", "UpdateStrategy"]
