"""What a backend hook sees: :class:`BackendContext`, and the hook contract :class:`BackendHook`.

The floor-plan update strategy and the loop closer are hooks: :class:`~frslam_graph.slam.FRSlam`
calls ``on_keyframe(ctx, keyframe)`` after each keyframe is in the graph and ``on_finish(ctx)``
before the final batch. Through the context they read the keyframes (poses in ``map`` from the
graph, in ``odom`` from the odometry; scans in ``base_link``; metres, radians), read and change
the pose graph, add and remove floor-plan priors, defer work to the following scans and record
decisions; they cannot call back into the facade (no scans, no ``finish``).

One thread at a time (see :class:`ThreadGuard`): a mutating call made while another thread is
inside one raises :class:`~frslam_graph.errors.FrslamError` at once instead of blocking; the same
thread may re-enter (hooks run inside ``add_scan``).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any, Protocol, runtime_checkable

import gtsam
import numpy as np

from frslam_graph.backend.decisions import PRIOR_REMOVAL_CAUSES, DecisionLog, PriorRemoval
from frslam_graph.backend.deferred import DeferredSteps
from frslam_graph.backend.graph import PoseGraph, PriorHandle
from frslam_graph.backend.keyframes import KeyframeInfo, KeyframeStore, StoredKeyframe
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, FrslamError, RecordingError
from frslam_graph.se2 import compose, inverse


class ThreadGuard:
    """A non-blocking, re-entrant lock naming the call that holds it."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._holder: str | None = None

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if not self._lock.acquire(blocking=False):
            raise FrslamError(
                f"FRSlam is not thread-safe: {name} called from two threads at once (another "
                f"thread is in {self._holder or 'it'}); feed and query one FRSlam from one thread"
            )
        outer = self._holder is None
        if outer:
            self._holder = name
        try:
            yield
        finally:
            if outer:
                self._holder = None
            self._lock.release()


class BackendContext:
    """The backend state a hook may read and change (see the module docstring)."""

    def __init__(self, config: FRSlamConfig, guard: ThreadGuard | None = None) -> None:
        self.guard = guard or ThreadGuard()
        self.graph = PoseGraph(config.graph)
        self.store = KeyframeStore()
        self.log = DecisionLog(now=self.store.scans.latest_stamp)
        self.deferred = DeferredSteps(config.loop_closure.budget_ms)
        self._mappers: dict[tuple[float, bool], Any] = {}  # (resolution, free_space) -> OccupancyMapper

    # ----------------------------------------------------------------- keyframes
    def keyframe(self, i: int) -> KeyframeInfo:
        kf = self.store[i]
        return KeyframeInfo(i, kf.stamp, kf.scan_index, self.graph.estimate(i), kf.pose_odom.copy())

    def keyframes(self) -> list[KeyframeInfo]:
        return self.store.infos(self.graph.estimates() if len(self.store) else np.zeros((0, 3)))

    def keyframe_scans(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Per keyframe: end points (M, 2) and sensor origin (2,), both in base_link."""
        return list(self.store.points), list(self.store.origins)

    def frozen(self, index: int) -> FrozenContext:
        """The keyframes as they are now, and keyframe ``index``'s marginal covariance, for work
        that reads them from another thread while the backend goes on (:class:`FrozenContext`)."""
        with self.guard("frozen"):
            try:
                cov = self.graph.marginal_covariance(index)
            except Exception:  # noqa: BLE001 - a marginal may be unavailable right after a removal
                cov = None
            n = len(self.store)
            estimates = self.graph.estimates() if n else np.zeros((0, 3))
            return FrozenContext([self.store[i] for i in range(n)], estimates, index, cov)

    def occupancy_grid(self, resolution: float = 0.05, free_space: bool = False):
        """LiDAR occupancy grid of the keyframe scans at the current estimates (see
        :meth:`FRSlam.occupancy_grid <frslam_graph.slam.FRSlam.occupancy_grid>`)."""
        from frslam_graph.backend.mapping import FREE_SPACE_WEIGHTS, OccupancyMapper

        with self.guard("occupancy_grid"):
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
            poses = self.graph.estimates() if len(self.store) else np.zeros((0, 3))
            mapper.update(poses, pts, origins)
            return mapper.grid()

    # ----------------------------------------------------------------- priors
    def add_prior(
        self,
        stamp_or_keyframe: int | float,
        pose: np.ndarray,
        covariance: np.ndarray,
        source: str = "floorplan",
        kind: str = "full",
        kernel: str | None = None,
        info: dict | None = None,
        extra_iterations: int | None = None,
        why: str | None = None,
        **numbers: Any,
    ) -> PriorHandle:
        """Add a robust prior: ``pose`` (x, y, theta) of base_link in map at a keyframe (int) or at
        the scan with that stamp (float; moved onto its keyframe through the odometry).
        ``extra_iterations``: relinearising iSAM2 iterations after it (default: see
        :meth:`PoseGraph.add_prior`). Logged once as ``prior_added`` (message ``why``; ``numbers``
        are the decision's, e.g. the relocalisation's score)."""
        with self.guard("add_prior"):
            kf, stamp, p, cov = self._prior_on_keyframe(stamp_or_keyframe, pose, covariance, kind)
            handle = self.graph.add_prior(
                kf,
                p,
                cov,
                kind=kind,
                kernel=kernel,
                source=source,
                info=info,
                extra_iterations=extra_iterations,
            )
            self.log.record(
                "prior_added",
                why or f"{kind} prior from {source} on keyframe {kf}",
                stamp=stamp,
                keyframe=kf,
                prior=handle.id,
                pose=p.tolist(),
                source=source,
                **numbers,
            )
            return handle

    def _prior_on_keyframe(
        self, stamp_or_keyframe: int | float, pose: Any, covariance: Any, kind: str
    ) -> tuple[int, float, np.ndarray, np.ndarray]:
        """(keyframe, stamp, pose, covariance) of a prior given at a keyframe or a scan's stamp."""
        if isinstance(stamp_or_keyframe, int | np.integer):
            kf, rel = int(stamp_or_keyframe), np.zeros(3)
            stamp = self.store[kf].stamp if 0 <= kf < len(self.store) else float("nan")
        else:
            stamp = float(stamp_or_keyframe)
            kf, rel = self.store.scans.keyframe_at(stamp)
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        cov = np.asarray(covariance, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise RecordingError(f"prior pose must be finite (x, y, theta), got {pose!r}", where="pose")
        if not 0 <= kf < len(self.store):
            raise RecordingError(f"no keyframe {kf} (have {len(self.store)})", where="keyframe")
        if np.any(rel != 0.0):
            # prior on the scan -> prior on its keyframe: kf = pose ⊕ rel⁻¹
            if kind == "translation":  # the prior has no heading: use the estimated one
                p = np.array([p[0], p[1], self.graph.estimate(kf)[2] + rel[2]])
            kf_pose = compose(p, inverse(rel))
            if kind == "full":  # tangent at the keyframe: ξ_kf = Ad(rel) ξ_scan
                ad = np.asarray(gtsam.Pose2(*rel).AdjointMap())
                cov = ad @ cov @ ad.T
            p = kf_pose
        return kf, stamp, p, cov

    def remove_priors(
        self, handles: list[PriorHandle], reason: str = "", cause: PriorRemoval = "wrong", **numbers: Any
    ) -> None:
        """Remove priors in one graph update (e.g. all of a retracted registration), each logged
        as ``prior_removed`` with its ``cause``: "wrong" (proven wrong, or its plan retracted) or
        "re-anchored" (the plan was refined or replaced: the keyframe is relocalised on it)."""
        with self.guard("remove_priors"):
            if cause not in PRIOR_REMOVAL_CAUSES:
                raise ConfigError(
                    f"cause must be one of {', '.join(map(repr, PRIOR_REMOVAL_CAUSES))}, got {cause!r}",
                    where="cause",
                )
            for h in self.graph.remove_priors(handles):
                self.log.record(
                    "prior_removed",
                    reason or f"prior {h.id} removed",
                    keyframe=h.keyframe,
                    prior=h.id,
                    cause=cause,
                    **numbers,
                )

    def transform_map(self, transform: np.ndarray, reason: str = "") -> None:
        """Re-express everything in a new map frame (pose p -> transform ⊕ p); map->odom changes."""
        with self.guard("transform_map"):
            self.graph.transform_map(transform)
            self.log.record(
                "map_transformed",
                reason or "map frame re-expressed",
                transform=np.asarray(transform, float).tolist(),
            )


class FrozenContext:
    """The keyframes of a :class:`BackendContext` frozen at one moment (:meth:`BackendContext.frozen`):
    their stored records (stamp, odom pose, scan in base_link: never changed once stored; the
    points are read-only views later keyframes never overwrite), their estimates in ``map`` and
    one keyframe's marginal covariance. It answers the reading calls a check of a registration
    makes (``keyframe``, ``keyframe_scans``, ``graph.estimates``, ``graph.marginal_covariance``),
    so that check can run in another thread while scans keep coming; it changes nothing."""

    def __init__(
        self, stored: list[StoredKeyframe], estimates: np.ndarray, index: int, covariance: np.ndarray | None
    ) -> None:
        self._stored = stored
        self.graph = _FrozenGraph(estimates, index, covariance)

    def keyframe(self, i: int) -> KeyframeInfo:
        kf = self._stored[i]
        return KeyframeInfo(i, kf.stamp, kf.scan_index, self.graph.estimate(i), kf.pose_odom.copy())

    def keyframe_scans(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return [kf.points for kf in self._stored], [kf.sensor_origin for kf in self._stored]


class _FrozenGraph:
    """The pose graph's estimates and one keyframe's marginal covariance, as frozen."""

    def __init__(self, estimates: np.ndarray, index: int, covariance: np.ndarray | None) -> None:
        self._estimates, self._index, self._covariance = estimates, index, covariance

    def estimate(self, i: int) -> np.ndarray:
        return self._estimates[i].copy()

    def estimates(self) -> np.ndarray:
        return self._estimates.copy()

    def marginal_covariance(self, i: int | None = None) -> np.ndarray:
        if i != self._index or self._covariance is None:
            raise FrslamError(f"no frozen marginal covariance of keyframe {i}", where="keyframe")
        return self._covariance.copy()


@runtime_checkable
class BackendHook(Protocol):
    """A keyframe hook (the floor-plan update strategy, the loop closer, a user's)."""

    def on_keyframe(self, ctx: BackendContext, keyframe: KeyframeInfo) -> None:
        """Called after each keyframe is in the graph."""

    def on_finish(self, ctx: BackendContext) -> None:
        """Called once by ``finish`` before the final batch (the end of an offline run)."""


class CallableHook:
    """A plain function ``f(ctx, keyframe)`` as a :class:`BackendHook` (nothing at the finish)."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    def on_keyframe(self, ctx: BackendContext, keyframe: KeyframeInfo) -> None:
        self.fn(ctx, keyframe)

    def on_finish(self, ctx: BackendContext) -> None:
        return None


__all__ = ["BackendContext", "BackendHook", "CallableHook", "ThreadGuard"]
