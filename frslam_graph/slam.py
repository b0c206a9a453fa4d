"""Streaming FR-SLAM backend: scans in, poses in ``map`` out (REP-105; metres, radians, seconds).

:class:`FRSlam` is the composition root and a small facade. ``add_scan(stamp, ranges,
angle_min, angle_increment, odom=None)`` runs the scan odometry (KISS-ICP fused with wheel
odometry, :mod:`frslam_graph.odometry.scan_odometry`); every keyframe becomes a Pose2 variable of the
:class:`~frslam_graph.backend.graph.PoseGraph` (iSAM2). Non-keyframe scans hang off their keyframe by
their odometry pose relative to it, so the whole trajectory follows the graph. ``pose()`` and
``map_to_odom()`` are the outputs a robot stack reads; ``finish()`` ends a run (the final LM
batch). The offline loop over a recording is :func:`frslam_graph.offline.process`.

Per scan (the core step, :meth:`FRSlam._record`):

1. log the odometry's faults (dropped scans, ICP rejected, wheel jump, degenerate geometry);
2. a scan that is not a keyframe runs one deferred step, and queued loop-closure work in the rest
   of the scan's budget (:mod:`frslam_graph.backend.deferred`);
3. a keyframe enters the graph and the keyframe store, then the hooks run: the floor-plan update
   strategy (paper Alg. 3, :class:`~frslam_graph.plan_updates.updater.FloorPlanUpdater` when a plan is
   given) and the loop closer. Hooks see a :class:`~frslam_graph.backend.context.BackendContext`
   (``slam.context``), never the facade.

Every decision is an event of one :class:`~frslam_graph.backend.decisions.DecisionLog`
(``slam.log``); nothing is printed.

Contract of the streaming API:

- Arguments are checked (:mod:`frslam_graph.stream_input`): a wrong type, shape or a non-finite
  stamp, angle or sensor offset raises :class:`~frslam_graph.errors.RecordingError` whose
  ``where`` names the argument; nothing is recorded then. ``floor_plan`` may be a path: it is
  loaded with ``FloorPlan.load``.
- One thread at a time. ``FRSlam`` is not thread-safe and does not serialise callers: the scan
  order is the trajectory's order, so two producers interleaving scans would be a wrong answer
  even behind a lock. A mutating call (``add_scan``, ``add_points``, ``add``, ``finish``, the
  context's prior calls, ...) made while another thread is inside one raises
  :class:`~frslam_graph.errors.FrslamError` at once instead of blocking (a non-blocking,
  re-entrant lock: hooks call back on the same thread freely). Read-only queries (``pose``,
  ``trajectory``, ...) are not guarded: call them from the feeding thread too.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from frslam_graph import stream_input
from frslam_graph.backend.context import BackendContext, BackendHook, CallableHook, ThreadGuard
from frslam_graph.backend.decisions import DecisionEvent, DecisionLog
from frslam_graph.backend.graph import PoseGraph
from frslam_graph.backend.keyframes import KeyframeInfo, StoredKeyframe
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, RecordingError
from frslam_graph.loop_closure.closer import LoopCloser
from frslam_graph.loop_closure.final_alignment import align_passes
from frslam_graph.odometry.motion_model import compose, compose_many
from frslam_graph.odometry.scan_odometry import OdometryResult, OdometryStats, ScanOdometry
from frslam_graph.plan_updates.updater import FloorPlanUpdater


def _one_thread(method: Callable[..., Any]) -> Callable[..., Any]:
    """Refuse a call while another thread is inside a guarded method of the same FRSlam (see the
    module docstring); the same thread may re-enter (hooks)."""
    name = method.__name__

    @functools.wraps(method)
    def guarded(self: FRSlam, *args: Any, **kwargs: Any) -> Any:
        with self.guard(name):
            return method(self, *args, **kwargs)

    return guarded


class FRSlam:
    """Streaming 2D SLAM backend with floor-plan priors (see module docstring): single-threaded,
    arguments checked."""

    def __init__(
        self,
        config: FRSlamConfig | dict | str | Path | None = None,
        floor_plan: Any = None,
        update_strategy: BackendHook | Callable[[BackendContext, KeyframeInfo], None] | None = None,
    ):
        """``floor_plan``: a FloorPlan, or a path loaded with ``FloorPlan.load``, or None.
        ``update_strategy``: a :class:`~frslam_graph.backend.context.BackendHook` or a plain
        function ``f(ctx, keyframe)``; None with a floor plan = the paper's Alg. 3
        (:class:`~frslam_graph.plan_updates.updater.FloorPlanUpdater`)."""
        self.guard = ThreadGuard()
        self.config = _as_config(config)
        self.floor_plan = floor_plan = stream_input.floor_plan(floor_plan)
        self.context = BackendContext(self.config, self.guard)
        self.odometry = ScanOdometry(self.config.odometry)
        if update_strategy is None and floor_plan is not None:
            # the paper's Alg. 3: register the plan as the map grows, relocalise, add robust priors
            update_strategy = FloorPlanUpdater(floor_plan, self.config.updates)
        self.update_strategy: BackendHook | None = _as_hook(update_strategy)
        # loop closure, run on each keyframe after the update strategy
        lc = self.config.loop_closure
        self.loop_closer: LoopCloser | None = LoopCloser(lc) if lc.enabled else None
        self.odometry_in_worker = False  # offline.process ran the odometry in a worker process
        self._was_degenerate = False
        self._angles_cache: tuple[float, float, int, tuple[np.ndarray, np.ndarray]] | None = None

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
        self.check_own_odometry()
        stamp = stream_input.finite_number(stamp, "stamp")
        pts, off = body_points(points, sensor_offset)
        self._record(self.odometry.process(stamp, pts, stream_input.odom(odom)), pts, off)
        return self.pose()

    @_one_thread
    def add_odometry(self, result: OdometryResult, points: np.ndarray, sensor_offset: np.ndarray) -> None:
        """Take a scan whose odometry ran elsewhere (the offline run's worker process):
        ``points`` (M, 2) in base_link, ``sensor_offset`` (x, y, theta) as :func:`body_points`
        gives them."""
        self._record(result, points, sensor_offset)

    def check_own_odometry(self) -> None:
        """Refuse scans after an offline run whose odometry ran in a worker process."""
        if self.odometry_in_worker:
            raise ConfigError(
                "this FRSlam ran process() with its odometry in a worker process and cannot take "
                "more scans; use process(..., parallel=False) to keep streaming afterwards",
                where="parallel",
            )

    # ------------------------------------------------------------ the core step
    def _angles(self, angle_min: float, inc: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """cos and sin of the beam angles (cached: the layout rarely changes)."""
        c = self._angles_cache
        if c is None or c[0] != angle_min or c[1] != inc or c[2] != n:
            ang = angle_min + inc * np.arange(n)
            self._angles_cache = c = (angle_min, inc, n, (np.cos(ang), np.sin(ang)))
        return c[3]

    def _record(self, res: OdometryResult, pts: np.ndarray, off: np.ndarray) -> None:
        """Take one scan's odometry result into the backend (module docstring: steps 1-3)."""
        ctx = self.context
        # 1. the odometry's faults
        self._log_odometry(res)
        scan_index = len(ctx.store.scans)
        ctx.store.scans.append(res.stamp, res.keyframe, res.relative, res.pose)
        if self.loop_closer is not None:  # its budgets follow the scan period
            self.loop_closer.set_scan_period(res.period)
        if not res.is_keyframe:
            # 2. a hook's deferred work, one step; queued loop-closure work in the rest of the budget
            spent = ctx.deferred.step()
            if self.loop_closer is not None:
                budget = ctx.deferred.budget_ms * self.loop_closer.budget_scale
                if spent is None:
                    self.loop_closer.on_scan(ctx)
                elif spent < budget:
                    self.loop_closer.on_scan(ctx, budget - spent)
            return
        # 3. the keyframe into the graph and the store, then the hooks
        if res.keyframe == 0:
            ctx.graph.add_first(res.pose)  # map == odom at start
        else:
            ctx.graph.add_keyframe(res.between, res.covariance)
        ctx.store.append(StoredKeyframe(res.stamp, scan_index, res.pose.copy(), pts, off[:2].copy()))
        info = ctx.keyframe(res.keyframe)
        busy = False
        if self.update_strategy is not None:
            version, steps = ctx.graph.version, ctx.deferred.steps_run
            self.update_strategy.on_keyframe(ctx, info)
            # priors added / removed, or deferred steps run now (the hook needed them done): this
            # scan's budget is spent. Work merely deferred to the next scans costs nothing here
            # (counting it starved loop closure behind a floor plan: queue lag ~120 keyframes).
            busy = ctx.graph.version != version or ctx.deferred.steps_run != steps
        if self.loop_closer is not None:  # uses the keyframe's index and odometry pose only
            self.loop_closer.on_keyframe(ctx, info, work=not busy)

    def _log_odometry(self, res: OdometryResult) -> None:
        """The odometry's faults as decisions (``dropped_scans``, ``motion_model_fallback``,
        ``icp_rejected``, ``odom_jump``, ``degenerate_start`` / ``degenerate_end``)."""
        log, stamp = self.context.log, res.stamp
        if res.dropped:
            log.record(
                "dropped_scans",
                f"stamp gap: about {res.dropped} scan(s) missing",
                stamp=stamp,
                count=res.dropped,
            )
        if res.fallback and not res.icp_rejected:
            log.record(
                "motion_model_fallback",
                f"{res.n_points} valid points: motion model used instead of ICP",
                stamp=stamp,
                n_points=res.n_points,
            )
        if res.icp_rejected:
            log.record(
                "icp_rejected",
                "ICP far from the wheel increment; motion model used, scan not mapped",
                stamp=stamp,
            )
        if res.odom_jump:
            log.record("odom_jump", "wheel odometry inconsistent with ICP; ICP trusted", stamp=stamp)
        if res.degenerate != self._was_degenerate:
            kind = "degenerate_start" if res.degenerate else "degenerate_end"
            data = {"axis": res.degenerate_axis.tolist()} if res.degenerate_axis is not None else {}
            message = (
                "scan geometry degenerate (corridor)" if res.degenerate else "scan geometry constrained again"
            )
            log.record(kind, message, stamp=stamp, **data)
            self._was_degenerate = res.degenerate

    # ------------------------------------------------------------- outputs
    def pose(self) -> tuple[float, float, float]:
        """Latest base_link pose in map."""
        scans = self.context.store.scans
        if not len(scans):
            return (0.0, 0.0, 0.0)
        p = compose(self.graph.estimate(), scans.relative[-1])
        return (float(p[0]), float(p[1]), float(p[2]))

    def map_to_odom(self) -> tuple[float, float, float]:
        """T_map_odom = T_map_base · T_odom_base⁻¹ at the latest keyframe (x, y, theta)."""
        store = self.context.store
        if not len(store):
            return (0.0, 0.0, 0.0)
        i = len(store) - 1
        t = self.graph.map_to_odom(i, store[i].pose_odom)
        return (float(t[0]), float(t[1]), float(t[2]))

    def __len__(self) -> int:
        return len(self.context.store.scans)

    @property
    def graph(self) -> PoseGraph:
        return self.context.graph

    @property
    def log(self) -> DecisionLog:
        """The decision log (one :class:`DecisionEvent` per decision)."""
        return self.context.log

    @property
    def stats(self) -> OdometryStats:
        return self.odometry.stats

    def keyframe(self, i: int) -> KeyframeInfo:
        return self.context.keyframe(i)

    def keyframes(self) -> list[KeyframeInfo]:
        return self.context.keyframes()

    def keyframe_scans(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Per keyframe: end points (M, 2) and sensor origin (2,), both in base_link."""
        return self.context.keyframe_scans()

    def keyframe_array(self) -> np.ndarray:
        """(K, 4) stamp, x, y, theta of the keyframes in map."""
        store = self.context.store
        if not len(store):
            return np.zeros((0, 4))
        return np.column_stack((store.stamps(), self.graph.estimates()))

    def trajectory(self) -> np.ndarray:
        """(N, 4) stamp, x, y, theta in map of every accepted scan (between two keyframes the
        map <- odom correction blended from one to the next: :meth:`KeyframeStore.scan_poses`)."""
        store = self.context.store
        if not len(store.scans):
            return np.zeros((0, 4))
        return np.column_stack((store.scans.stamps, store.scan_poses(self.graph.estimates())))

    def odometry_trajectory(self) -> np.ndarray:
        """(N, 4) stamp, x, y, theta in odom (the fused odometry, never corrected)."""
        scans = self.context.store.scans
        if not len(scans):
            return np.zeros((0, 4))
        return np.column_stack((scans.stamps, scans.odometry))

    def registered_plan(self):
        """The floor plan registered into ``map`` (FloorPlan in metres), or None before any
        accepted registration / without the floor-plan updater."""
        if isinstance(self.update_strategy, FloorPlanUpdater):
            return self.update_strategy.registered_plan
        return None

    def refused_plan(self):
        """With no registration accepted: the placement of the registration on the complete map
        at the end of the run (FloorPlan in ``map`` metres) that its checks refused, for a figure
        to show where the plan would sit; else None."""
        if isinstance(self.update_strategy, FloorPlanUpdater) and self.update_strategy.accepted is None:
            return self.update_strategy.final_placement
        return None

    def occupancy_grid(self, resolution: float = 0.05, free_space: bool = False):
        """LiDAR occupancy grid (``OccupancyGrid``) of the keyframe scans at the current estimates.

        The default keeps walls (a hit outweighs many passing beams: the map a user loads);
        ``free_space=True`` weighs hits and misses as the floor-plan registration wants it (free
        space wins over stray hits, see ``mapping.FREE_SPACE_WEIGHTS``). Incremental: one
        :class:`~frslam_graph.backend.mapping.OccupancyMapper` per resolution and kind is kept; each call
        inserts the new keyframes and re-inserts those whose estimate moved.
        """
        return self.context.occupancy_grid(resolution, free_space)

    # ---------------------------------------------------------------- the end
    @_one_thread
    def finish(self) -> np.ndarray:
        """Final Levenberg-Marquardt batch over the whole graph; returns :meth:`trajectory`.

        Before it, the hooks' ``on_finish`` (the floor-plan updater's final refinement, the loop
        closer's queued work). The batches free iSAM2 (``PoseGraph.optimize_batch(incremental=
        False)``): the estimates are then the batch's values, and a scan added afterwards
        rebuilds iSAM2 from them."""
        ctx = self.context
        ctx.deferred.run_all()
        if self.update_strategy is not None:
            self.update_strategy.on_finish(ctx)
            ctx.deferred.run_all()
        if self.loop_closer is not None:  # loop-closure work still queued
            self.loop_closer.on_finish(ctx)
        if len(ctx.store):
            t0 = time.perf_counter()
            before = self.graph.error()
            # iSAM2 is not rebuilt at the end of a run: the estimates are the batch's values (its
            # factorisation of the whole graph would be the run's largest allocation)
            self.graph.optimize_batch(incremental=False)
            ctx.log.record(
                "batch_optimised",
                "final LM batch",
                error_before=before,
                error_after=self.graph.error(),
                seconds=time.perf_counter() - t0,
            )
            if self.loop_closer is not None:  # constraints between passes are loop closures
                # an offline run with the odometry in a worker: its core is free now
                align_passes(ctx, self.config.loop_closure, processes=2 if self.odometry_in_worker else 1)
        return self.trajectory()


def body_points(points: np.ndarray, sensor_offset: Any) -> tuple[np.ndarray, np.ndarray]:
    """Planar end points (M, 2) in the sensor frame -> base_link, and the offset (x, y, theta);
    both checked (RecordingError naming ``points`` / ``sensor_offset``)."""
    pts = stream_input.points(points)
    off = stream_input.pose(sensor_offset, "sensor_offset")
    if np.any(off != 0.0):
        pts = compose_many(off, np.column_stack((pts, np.zeros(len(pts)))))[:, :2]
    return pts, off


def _as_hook(strategy: Any) -> BackendHook | None:
    """The update strategy as a hook: a BackendHook as is, a plain function wrapped."""
    if strategy is None or isinstance(strategy, BackendHook):
        return strategy
    if callable(strategy):
        return CallableHook(strategy)
    raise ConfigError(
        f"update_strategy must have on_keyframe(ctx, keyframe) and on_finish(ctx), or be a function "
        f"f(ctx, keyframe); got {type(strategy).__name__}",
        where="update_strategy",
    )


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


__all__ = ["DecisionEvent", "FRSlam", "KeyframeInfo", "body_points"]
