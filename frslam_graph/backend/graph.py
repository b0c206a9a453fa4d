"""GTSAM Pose2 pose graph of keyframes: iSAM2 online, Levenberg-Marquardt batch offline.

Variables are keyframe poses of ``base_link`` in ``map`` (metres, radians), keyed
``gtsam.symbol('x', i)``. Keyframe 0 carries an *anchor* prior (map == odom at start, REP-105);
consecutive keyframes are linked by odometry between-factors; floor-plan measurements enter as
robust priors (:mod:`frslam_graph.factors.floorplan_prior`) and return a :class:`PriorHandle`
so a prior later proven wrong can be removed from iSAM2 by its factor index.

``map_to_odom(i, odom_pose)`` = T_map_base(i) · T_odom_base(i)⁻¹: the correction a floor-plan
prior applies; odometry itself is never changed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import gtsam
import numpy as np

from frslam_graph.config import GraphConfig
from frslam_graph.errors import FrslamError
from frslam_graph.factors.between import between_factor, pose2, regularise_covariance
from frslam_graph.factors.floorplan_prior import (
    KernelName,
    PriorKind,
    floorplan_prior,
    m_estimator,
    prior_covariance,
)
from frslam_graph.se2 import between_many, compose, inverse, wrap
from frslam_graph.steps import Steps, run_steps

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# m; smallest translation sigma of an odometry between-factor; larger = odometry trusted less
BETWEEN_SIGMA_FLOOR_XY = 0.002
# deg; smallest heading sigma of an odometry between-factor; larger = odometry trusted less
BETWEEN_SIGMA_FLOOR_THETA_DEG = 0.05
# m; sigma of the prior on the first keyframe (map == odom at start); larger = a looser anchor
ANCHOR_SIGMA_XY = 0.001
ANCHOR_SIGMA_THETA_DEG = 0.001  # deg; heading sigma of the prior on the first keyframe
BATCH_MAX_ITERATIONS = 100  # Levenberg-Marquardt batch iterations at most; larger = slower on hard graphs
# m; a floor-plan prior within this of the estimate (and PRIOR_SETTLE_NEAR_THETA_DEG) gets only
# prior_settle_near_iterations forced iSAM2 steps (others 10)
PRIOR_SETTLE_NEAR_XY = 0.05
PRIOR_SETTLE_NEAR_THETA_DEG = 1.0  # deg; heading part of the 'near' test of PRIOR_SETTLE_NEAR_XY

# Cost model of the batch's steps (ms per keyframe on one core of the development machine; only
# needs to be right within a factor of about two; measured on the Intel log's streaming batches,
# 1,300-2,600 keyframes): one LM iteration, and the iSAM2 rebuild on its result.
MS_PER_KEYFRAME_LM_ITERATION = 0.008
MS_PER_KEYFRAME_REBUILD = 0.022

_CHI2_99 = {1: 6.635, 2: 9.210, 3: 11.345}


def key(i: int) -> int:
    """GTSAM key of keyframe i."""
    return gtsam.symbol("x", int(i))


@dataclass(slots=True)
class PriorHandle:
    """A floor-plan prior in the graph. ``active`` turns False once removed."""

    id: int
    keyframe: int
    kind: str
    pose: np.ndarray
    covariance: np.ndarray  # the floored covariance block used (3×3, 2×2 or 1×1)
    kernel: str
    source: str = ""
    factor_index: int = -1  # index in iSAM2's factor graph
    active: bool = True
    info: dict = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class PriorResidual:
    """How well the current estimate agrees with a prior.

    ``error``: residual in tangent units; ``chi2``: its squared Mahalanobis norm under the prior's
    Gaussian covariance (ignoring the kernel); ``weight``: the robust kernel's weight at that
    error (1 = fully trusted, → 0 = rejected as an outlier); ``consistent``: chi2 below the 99 %
    quantile for the prior's dimension.
    """

    handle_id: int
    error: np.ndarray
    chi2: float
    weight: float
    consistent: bool


class PoseGraph:
    """Keyframe pose graph (iSAM2, Cholesky by default: ``GraphConfig.factorization``; LM batch on demand)."""

    def __init__(self, config: GraphConfig | None = None):
        self.config = config or GraphConfig()
        self._floor_xy = BETWEEN_SIGMA_FLOOR_XY
        self._floor_th = np.deg2rad(BETWEEN_SIGMA_FLOOR_THETA_DEG)
        self._isam: gtsam.ISAM2 | None = self._new_isam()
        # the last batch's result while iSAM2 is released (optimize_batch(incremental=False))
        self._batch_values: gtsam.Values | None = None
        # an LM batch run one iteration per step (optimize_batch_steps) not finished yet
        self._inflight: _InflightBatch | None = None
        self._factors: list[gtsam.NonlinearFactor | None] = []  # mirror of iSAM2's factor slots
        self._version = 0  # iSAM2 updates so far
        self._n = 0
        self._estimate_cache: np.ndarray | None = None  # all estimates, valid now
        # incremental refresh (see estimates()): the last computed estimates, iSAM2's delta then,
        # and the keyframes iSAM2 marked (new, relinearised, touched factors) since
        self._stale: tuple[np.ndarray, np.ndarray] | None = None
        self._marked: set[int] = set()
        self._marked_all = False
        self._latest = np.zeros(3)
        self._priors: dict[int, PriorHandle] = {}
        self._next_prior = 0
        self.anchor: PriorHandle | None = None

    # ------------------------------------------------------------------ build
    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setFactorization(self.config.factorization)
        params.relinearizeSkip = self.config.relinearize_skip
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        return gtsam.ISAM2(params)

    def __len__(self) -> int:
        return self._n

    def _update(
        self, factors: list, values: gtsam.Values | None = None, remove: list[int] | None = None
    ) -> list[int]:
        if self._isam is None:  # released: factors change, the estimate does not
            return self._update_released(factors, remove or [])
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f)
        result = self._isam_update(graph, values or gtsam.Values(), remove or [])
        idx = list(result.getNewFactorsIndices())
        for f, i in zip(factors, idx, strict=True):
            while len(self._factors) <= i:
                self._factors.append(None)
            self._factors[i] = f
        for i in remove or []:
            self._factors[i] = None
        if self._n:
            self._latest = _vec(self._isam.calculateEstimatePose2(key(self._n - 1)))
        return idx

    def _update_released(self, factors: list, remove: list[int]) -> list[int]:
        """:meth:`_update` while iSAM2 is released: the factor slots only (new factors take the
        next slots, as iSAM2 would give them); the estimate stays the last batch's until the next
        batch or iSAM2 update."""
        self._version += 1
        idx = list(range(len(self._factors), len(self._factors) + len(factors)))
        self._factors.extend(factors)
        for i in remove:
            self._factors[i] = None
        return idx

    def _restore_isam(self) -> None:
        """Rebuild iSAM2 on the last batch's values after :meth:`optimize_batch` released it (an
        LM batch still running in steps is finished first: its values are the ones to keep)."""
        if self._inflight is not None:
            self._finish_inflight()
        else:
            self._rebuild(self._batch_values)

    @property
    def incremental(self) -> bool:
        """Whether iSAM2 is held (False after ``optimize_batch(incremental=False)`` until the next
        update that needs it rebuilds it)."""
        return self._isam is not None

    def _isam_update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        remove: list[int],
        force_relinearize: bool = False,
    ) -> gtsam.ISAM2Result:
        """Every iSAM2 update goes through here: it invalidates the estimates and records the
        keyframes whose linearisation point may have moved (for the incremental refresh)."""
        if self._isam is None:
            self._restore_isam()
        self._version += 1
        if force_relinearize:
            result = self._isam.update(graph, values, remove, None, None, None, True)
        else:
            result = self._isam.update(graph, values, remove)
        self._estimate_cache = None
        marked = result.getMarkedKeys()
        if self._marked_all or len(self._marked) + len(marked) > self._n // 4:
            self._marked_all = True  # most of the graph: the next refresh is a full one anyway
        else:
            self._marked.update(gtsam.Symbol(k).index() for k in marked)
        return result

    @property
    def version(self) -> int:
        """Number of iSAM2 updates so far: changes whenever factors are added or removed or the
        graph is relinearised (a caller can tell whether a hook touched the graph)."""
        return self._version

    def add_first(self, pose: np.ndarray = (0.0, 0.0, 0.0)) -> int:
        """Keyframe 0 at ``pose`` in map, held by the anchor prior. Returns 0."""
        if self._n:
            raise FrslamError("the graph already has keyframes", where="add_first")
        cov = np.diag([ANCHOR_SIGMA_XY**2] * 2 + [np.deg2rad(ANCHOR_SIGMA_THETA_DEG) ** 2])
        p = np.asarray(pose, dtype=np.float64)
        factor = gtsam.PriorFactorPose2(key(0), pose2(p), gtsam.noiseModel.Gaussian.Covariance(cov))
        values = gtsam.Values()
        values.insert(key(0), pose2(p))
        self._n = 1
        (idx,) = self._update([factor], values)
        self.anchor = PriorHandle(-1, 0, "full", p.copy(), cov, "none", "anchor", idx)
        return 0

    def add_keyframe(
        self, relative: np.ndarray, covariance: np.ndarray, initial: np.ndarray | None = None
    ) -> int:
        """Append keyframe n linked to n-1 by the odometry ``relative`` (tangent ``covariance``)."""
        if not self._n:
            raise FrslamError("add_first() must come before add_keyframe()", where="add_keyframe")
        if self._isam is None and self._inflight is None:  # released by the last batch
            self._restore_isam()
        i = self._n
        factor = between_factor(key(i - 1), key(i), relative, covariance, self._floor_xy, self._floor_th)
        guess = (
            np.asarray(initial, float)
            if initial is not None
            else compose(self._latest, np.asarray(relative, float))
        )
        values = gtsam.Values()
        values.insert(key(i), pose2(guess))
        self._n = i + 1
        if self._inflight is not None:  # an LM batch runs in steps: the keyframe waits for it
            self._update_released([factor], [])
            self._batch_values.insert(key(i), pose2(guess))
            self._estimate_cache = None
            self._latest = guess.copy()
            return i
        self._update([factor], values)
        return i

    def add_prior(
        self,
        keyframe: int,
        pose: np.ndarray,
        covariance: np.ndarray,
        kind: PriorKind = "full",
        kernel: KernelName | None = None,
        kernel_param: float | None = None,
        source: str = "",
        info: dict | None = None,
        extra_iterations: int | None = None,
    ) -> PriorHandle:
        """Add a robust floor-plan prior on a keyframe; returns its handle (for removal/residuals).

        ``extra_iterations`` relinearising iSAM2 steps follow (:meth:`settle`). By default a
        prior that agrees with the current estimate (within ``PRIOR_SETTLE_NEAR_XY`` /
        ``PRIOR_SETTLE_NEAR_THETA_DEG``) gets ``prior_settle_near_iterations`` (the streaming
        updates converge the rest), one that moves the trajectory 10."""
        cfg = self.config
        if not 0 <= keyframe < self._n:
            raise FrslamError(f"no keyframe {keyframe} (graph has {self._n})", where="keyframe")
        if extra_iterations is None:
            extra_iterations = self.prior_settle_iterations(int(keyframe), pose, kind)
        kernel = kernel or cfg.prior_kernel
        param = kernel_param if kernel_param is not None else cfg.prior_kernel_param
        fxy, fth = cfg.prior_sigma_floor_xy, np.deg2rad(cfg.prior_sigma_floor_theta_deg)
        factor = floorplan_prior(key(keyframe), pose, covariance, kind, kernel, param, fxy, fth)
        (idx,) = self._update([factor])
        self.settle(extra_iterations)
        handle = PriorHandle(
            self._next_prior,
            int(keyframe),
            kind,
            np.asarray(pose, float).copy(),
            prior_covariance(covariance, kind, fxy, fth),
            kernel,
            source,
            idx,
            True,
            dict(info or {}),
        )
        self._priors[handle.id] = handle
        self._next_prior += 1
        return handle

    def prior_settle_iterations(self, keyframe: int, pose: np.ndarray, kind: PriorKind = "full") -> int:
        """Relinearising iterations a new prior gets (:meth:`add_prior`'s default): few when it
        agrees with the keyframe's current estimate (``prior_settle_near_*``), else 10."""
        cfg = self.config
        d = np.asarray(pose, float) - self.estimate(int(keyframe))
        near = float(np.hypot(d[0], d[1])) <= PRIOR_SETTLE_NEAR_XY and (
            kind == "translation" or abs(float(wrap(d[2]))) <= np.deg2rad(PRIOR_SETTLE_NEAR_THETA_DEG)
        )
        return cfg.prior_settle_near_iterations if near else 10

    def remove_prior(self, handle: PriorHandle, extra_iterations: int = 10) -> None:
        """Remove a prior (or the anchor) from iSAM2 by its factor index."""
        self.remove_priors([handle], extra_iterations)

    def remove_priors(self, handles: list[PriorHandle], extra_iterations: int = 10) -> list[PriorHandle]:
        """Remove several priors in one iSAM2 update (one settle for all of them); returns those
        removed (each active handle once; inactive ones are skipped)."""
        live = list({id(h): h for h in handles if h.active}.values())
        for h in live:
            if self._factors[h.factor_index] is None:
                raise FrslamError(f"prior {h.id} is not in the graph", where="handle")
        if not live:
            return []
        indices = [h.factor_index for h in live]
        # inactive before the update: its settle may finish an in-flight batch, whose rebuild
        # re-maps the indices of the active handles only (a removed one has none left)
        for h in live:
            h.active = False
        self.remove_factors(indices, extra_iterations)
        return live

    def settle(self, max_iterations: int = 10, tol: float = 1e-4) -> int:
        """Extra iSAM2 steps (relinearising) until no pose moves more than ``tol``; returns the count.

        One iSAM2 update is a single Gauss-Newton step; after a prior or a removal moves the
        trajectory far, a few more are needed to converge. These force relinearisation (the
        streaming updates relinearise only every ``relinearize_skip`` steps).
        """
        return sum(1 for _ in self.settle_steps(max_iterations, tol))

    def settle_steps(self, max_iterations: int = 10, tol: float = 1e-4) -> Iterator[None]:
        """:meth:`settle` as a generator: it yields before each iteration, so a caller can run
        them one at a time (one per scan). Keyframes added in between are fine: iSAM2 takes them
        in its own updates; convergence is judged on the keyframes that were there before."""
        if max_iterations <= 0:  # nothing to run: no estimates to refresh either
            return
        prev = self.estimates()
        for _ in range(max_iterations):
            yield
            self._isam_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], True)
            cur = self.estimates()
            n = min(len(cur), len(prev))
            moved = float(np.abs(cur[:n] - prev[:n]).max()) if n else 0.0
            prev = cur
            if len(cur):
                self._latest = cur[-1].copy()
            if moved < tol:
                break

    def add_factor(self, factor: gtsam.NonlinearFactor, extra_iterations: int = 10) -> int:
        """Add a factor between existing keyframes (e.g. a loop closure); returns its iSAM2 index.

        It is part of the LM batch. Indices change when the graph is rebuilt (``optimize_batch``,
        ``transform_map``): find the factor again with :meth:`factor_index`.
        """
        (idx,) = self._update([factor])
        self.settle(extra_iterations)
        return idx

    def replace_factors(self, remove: list[int], factors: list[gtsam.NonlinearFactor]) -> list[int]:
        """Remove factors by their iSAM2 indices and add ``factors`` (between existing keyframes)
        in one iSAM2 update, without relinearising steps (an LM batch is meant to follow)."""
        for index in remove:
            if not 0 <= index < len(self._factors) or self._factors[index] is None:
                raise FrslamError(f"no factor at index {index}", where="index")
        return self._update(list(factors), remove=list(remove))

    def factor_indices(self, factors: list[gtsam.NonlinearFactor]) -> list[int]:
        """Current iSAM2 indices of factor objects added earlier (-1 for those not in the graph)."""
        where = {id(f): i for i, f in enumerate(self._factors) if f is not None}
        return [where.get(id(f), -1) for f in factors]

    def remove_factor(self, index: int, extra_iterations: int = 10) -> None:
        """Remove a factor added with :meth:`add_factor` by its iSAM2 index."""
        self.remove_factors([index], extra_iterations)

    def remove_factors(self, indices: list[int], extra_iterations: int = 10) -> None:
        """Remove factors added with :meth:`add_factor` by their iSAM2 indices (one update)."""
        for index in indices:
            if not 0 <= index < len(self._factors) or self._factors[index] is None:
                raise FrslamError(f"no factor at index {index}", where="index")
        if len(set(indices)) != len(indices):
            raise FrslamError(f"factor indices repeat: {sorted(indices)}", where="indices")
        self._update([], remove=list(indices))
        self.settle(extra_iterations)

    def factor_index(self, factor: gtsam.NonlinearFactor) -> int:
        """Current iSAM2 index of a factor object added earlier (-1 when not in the graph)."""
        for i, f in enumerate(self._factors):
            if f is factor:
                return i
        return -1

    def priors(self, active_only: bool = True) -> list[PriorHandle]:
        return [h for h in self._priors.values() if h.active or not active_only]

    def has_priors(self) -> bool:
        """Whether any floor-plan prior is in the graph (the anchor does not count)."""
        return any(h.active for h in self._priors.values())

    # -------------------------------------------------------------- estimates
    def estimate(self, i: int | None = None) -> np.ndarray:
        """Pose (x, y, theta) of keyframe i (default: the latest) in map."""
        if not self._n:
            raise FrslamError("the graph is empty", where="estimate")
        if i is None or i == self._n - 1:
            return self._latest.copy()
        if not -self._n <= i < self._n:
            raise FrslamError(f"no keyframe {i} (graph has {self._n})", where="keyframe")
        i = i % self._n
        if self._estimate_cache is None and self._isam is None:
            self._estimate_cache = self._refresh_estimates()
        if self._estimate_cache is not None:
            return self._estimate_cache[i].copy()
        return _vec(self._isam.calculateEstimatePose2(key(i)))

    def estimates(self) -> np.ndarray:
        """(N, 3) poses of all keyframes in map.

        Incremental after an update: a pose is iSAM2's linearisation point retracted by its delta,
        so only the keyframes whose delta changed (compared exactly) or that iSAM2 marked (new,
        relinearised) are recomputed, with the same per-key call; bit-identical to a full
        ``calculateEstimate``, which runs when most of the graph changed.
        """
        if self._estimate_cache is None:
            self._estimate_cache = self._refresh_estimates()
        return self._estimate_cache.copy()

    def _refresh_estimates(self) -> np.ndarray:
        n = self._n
        if self._isam is None:
            return _values_array(self._batch_values, n)
        delta = self._isam.getDelta().vector()
        if len(delta) != 3 * n:  # pragma: no cover - only keyframe Pose2 variables live in the graph
            raise FrslamError(f"graph holds {len(delta) // 3} poses, expected {n}", where="values")
        delta = delta.reshape(n, 3)
        est = None
        if self._stale is not None and not self._marked_all:
            old, old_delta = self._stale
            m = len(old)
            todo = set(np.flatnonzero(np.any(delta[:m] != old_delta, axis=1)).tolist())
            todo |= {i for i in self._marked if i < m}
            if len(todo) <= n // 4:
                est = np.empty((n, 3))
                est[:m] = old
                for i in [*todo, *range(m, n)]:
                    est[i] = _vec(self._isam.calculateEstimatePose2(key(i)))
        if est is None:
            est = self.full_estimates()
        self._stale = (est, delta)
        self._marked.clear()
        self._marked_all = False
        return est

    def full_estimates(self) -> np.ndarray:
        """(N, 3) poses of all keyframes from iSAM2's full ``calculateEstimate`` (no cache; the
        last batch's values while iSAM2 is released)."""
        return _values_array(self._current_values(), self._n)

    def _current_values(self) -> gtsam.Values:
        """iSAM2's estimate as Values (the last batch's while iSAM2 is released)."""
        return self._batch_values if self._isam is None else self._isam.calculateEstimate()

    def marginal_covariance(self, i: int | None = None) -> np.ndarray:
        """3×3 marginal covariance (tangent, body frame) of keyframe i (default: latest)."""
        i = self._n - 1 if i is None else i
        if not 0 <= i < self._n:
            raise FrslamError(f"no keyframe {i} (graph has {self._n})", where="keyframe")
        if self._isam is None:
            self._restore_isam()
        return np.asarray(self._isam.marginalCovariance(key(i)))

    def prior_residual(self, handle: PriorHandle) -> PriorResidual:
        """Residual of a prior at the current estimate: chi2, robust weight, consistency."""
        return self.prior_residuals([handle])[0]

    def prior_residuals(self, handles: list[PriorHandle]) -> list[PriorResidual]:
        """:meth:`prior_residual` of many priors at once: the error (tangent at the measurement,
        as ``factors.floorplan_prior.prior_chi2``; vectorised SE(2) logmap), its Gaussian chi2
        and the robust kernel's weight (one M-estimator object per kernel)."""
        if not handles:
            return []
        est = self.estimates()
        kf = np.array([h.keyframe for h in handles], dtype=np.intp)
        if kf.min() < 0 or kf.max() >= len(est):
            raise FrslamError(f"a prior's keyframe is not in the graph (has {self._n})", where="handle")
        meas = np.array([h.pose for h in handles], dtype=np.float64).reshape(-1, 3)
        full = _logmap_between(meas, est[kf])  # (n, 3), tangent at the measurement
        kernels: dict[str, object] = {}
        out = []
        for h, e3, x in zip(handles, full, est[kf], strict=True):
            if h.kind == "translation":
                e = x[:2] - h.pose[:2]
            elif h.kind == "rotation":
                e = e3[2:]
            else:
                e = e3
            chi2 = float(e @ np.linalg.solve(h.covariance, e))
            if h.kernel not in kernels:
                kernels[h.kernel] = m_estimator(h.kernel, self.config.prior_kernel_param)
            est_k = kernels[h.kernel]
            weight = float(est_k.weight(np.sqrt(chi2))) if est_k is not None else 1.0
            out.append(PriorResidual(h.id, e, chi2, weight, chi2 <= _CHI2_99[len(e)]))
        return out

    def map_to_odom(self, keyframe: int, odom_pose: np.ndarray) -> np.ndarray:
        """T_map_odom = T_map_base(keyframe) · T_odom_base⁻¹, as (x, y, theta)."""
        return compose(self.estimate(keyframe), inverse(np.asarray(odom_pose, float)))

    def error(self) -> float:
        """Total (robust) factor-graph error at the current estimate."""
        return float(self._graph().error(self._current_values()))

    # ------------------------------------------------------------ batch / re-anchoring
    def _graph(self) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for f in self._factors:
            if f is not None:
                g.add(f)
        return g

    def optimize_batch(self, incremental: bool = True) -> np.ndarray:
        """Levenberg-Marquardt on the whole graph from the iSAM2 estimate; iSAM2 is rebuilt on the
        result so streaming can continue. Returns the (N, 3) optimised poses.

        iSAM2 is freed before the batch runs. ``incremental=False`` (the end of an offline run): it
        is not rebuilt; the estimates are the batch's values. iSAM2 holds a dense factorisation of
        the graph (~15-30 kB per keyframe where places are passed often), so a run's final
        batches and alignment need not hold it. Factors added or removed meanwhile only change
        the graph (the next batch takes them); anything needing iSAM2 (a new keyframe, settle,
        marginals) rebuilds it from the batch's values first."""
        return run_steps(self.optimize_batch_steps(incremental))

    def optimize_batch_steps(self, incremental: bool = True) -> Steps[np.ndarray]:
        """:meth:`optimize_batch` as a step generator (:mod:`frslam_graph.steps`) for streaming:
        one LM iteration per step, then the iSAM2 rebuild as a step of its own, each yield giving
        the step's estimated cost (``MS_PER_KEYFRAME_LM_ITERATION`` / ``_REBUILD``). Run to the end it gives the same values as
        ``optimize_batch``; a batch of thousands of keyframes then costs a scan one iteration
        (~8 µs per keyframe) or the rebuild, not the whole batch (several iterations and the
        rebuild, 0.27 s at 2,555 keyframes on the Intel bag).

        Between steps the graph stays usable: the estimates are the ones from before the batch;
        a keyframe added meanwhile waits outside iSAM2 (its odometry factor joins the graph at
        once) and, when the batch ends, keeps its pose relative to the batch's last keyframe.
        Anything that needs iSAM2 before the end (a factor with relinearising steps, marginals,
        another batch) finishes the batch first, as :meth:`optimize_batch` would have."""
        if not self._n:
            return np.zeros((0, 3))
        if self._inflight is not None:
            self._finish_inflight()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(BATCH_MAX_ITERATIONS)
        params.setRelativeErrorTol(self.config.batch_relative_tolerance)
        initial = self._current_values()
        # iSAM2 is freed before the batch, not after: its factorisation and LM's do not coexist
        # (a failed batch leaves the graph released at ``initial``)
        self._isam, self._batch_values = None, gtsam.Values(initial)
        self._estimate_cache = None
        batch = _InflightBatch(
            gtsam.LevenbergMarquardtOptimizer(self._graph(), initial, params), params, self._n, incremental
        )
        self._inflight = batch
        while not batch.converged():
            yield MS_PER_KEYFRAME_LM_ITERATION * batch.n
            if self._inflight is not batch:  # finished meanwhile by something that needed iSAM2
                return self.estimates()
            batch.iterate()
        if incremental:
            yield MS_PER_KEYFRAME_REBUILD * self._n
            if self._inflight is not batch:
                return self.estimates()
        self._finish_inflight()
        return self.estimates()

    def _finish_inflight(self) -> None:
        """Run the in-flight batch's remaining iterations, then take its values: keyframes added
        since it started keep their pose relative to its last keyframe; iSAM2 is rebuilt unless
        the batch was the end of a run (``incremental=False``)."""
        batch, self._inflight = self._inflight, None
        while not batch.converged():
            batch.iterate()
        values = gtsam.Values(batch.optimizer.values())
        if self._n > batch.n:
            last = key(batch.n - 1)
            # the rigid correction the batch gave its last keyframe, carried onto the new ones
            shift = batch.optimizer.values().atPose2(last).compose(self._batch_values.atPose2(last).inverse())
            for i in range(batch.n, self._n):
                values.insert(key(i), shift.compose(self._batch_values.atPose2(key(i))))
        if batch.incremental or self._n > batch.n:
            self._rebuild(values)
        else:
            self._version += 1
            self._batch_values = values
            self._estimate_cache = None
            self._stale = None
            self._marked.clear()
            self._marked_all = False
            self._latest = _vec(values.atPose2(key(self._n - 1)))

    def transform_map(self, transform: np.ndarray) -> None:
        """Re-express the whole graph in a new map frame: every pose p becomes transform ⊕ p.

        For the first floor-plan registration (which defines ``map``): apply it before adding the
        priors so the robust kernels start near their minimum. The anchor prior moves with it.
        """
        if self._inflight is not None:
            self._finish_inflight()
        t = np.asarray(transform, dtype=np.float64)
        est = self.estimates()
        values = gtsam.Values()
        for i, p in enumerate(est):
            values.insert(key(i), pose2(compose(t, p)))
        if self.anchor is not None and self.anchor.active:
            new_anchor = compose(t, self.anchor.pose)
            f = gtsam.PriorFactorPose2(
                key(0), pose2(new_anchor), gtsam.noiseModel.Gaussian.Covariance(self.anchor.covariance)
            )
            self._factors[self.anchor.factor_index] = f
            self.anchor.pose = new_anchor
        self._rebuild(values)

    def _rebuild(self, values: gtsam.Values) -> None:
        """Fresh iSAM2 over the live factors (indices are re-mapped in the handles)."""
        old = self._factors
        self._isam = self._new_isam()
        self._batch_values = None
        self._factors = []
        live = [(i, f) for i, f in enumerate(old) if f is not None]
        graph = gtsam.NonlinearFactorGraph()
        for _, f in live:
            graph.add(f)
        result = self._isam.update(graph, values)
        self._stale = None  # a fresh iSAM2: nothing to refresh incrementally
        self._marked.clear()
        self._marked_all = False
        new_idx = list(result.getNewFactorsIndices())
        remap = {}
        for (oi, f), ni in zip(live, new_idx, strict=True):
            while len(self._factors) <= ni:
                self._factors.append(None)
            self._factors[ni] = f
            remap[oi] = ni
        for h in [*self._priors.values(), *([self.anchor] if self.anchor else [])]:
            if h.active:
                h.factor_index = remap[h.factor_index]
        self._estimate_cache = None
        self._latest = _vec(self._isam.calculateEstimatePose2(key(self._n - 1)))


@dataclass(slots=True, eq=False)
class _InflightBatch:
    """An LM batch run one iteration at a time: its optimizer, the number of keyframes it holds,
    and whether iSAM2 is rebuilt on its result. Convergence as ``NonlinearOptimizer.optimize``
    judges it (the same iterations, so the same values)."""

    optimizer: gtsam.LevenbergMarquardtOptimizer
    params: gtsam.LevenbergMarquardtParams
    n: int
    incremental: bool
    _errors: tuple[float, float] | None = None  # error before and after the last iteration

    def converged(self) -> bool:
        p = self.params
        if self._errors is None:
            return self.optimizer.error() <= p.getErrorTol()
        before, after = self._errors
        return (
            self.optimizer.iterations() >= p.getMaxIterations()
            or not np.isfinite(after)
            or gtsam.checkConvergence(
                p.getRelativeErrorTol(), p.getAbsoluteErrorTol(), p.getErrorTol(), before, after
            )
        )

    def iterate(self) -> None:
        before = self.optimizer.error()
        self.optimizer.iterate()
        self._errors = (before, self.optimizer.error())


def _vec(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _values_array(values: gtsam.Values, n: int) -> np.ndarray:
    out = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64).reshape(-1, 3)
    if len(out) != n:  # pragma: no cover - only keyframe Pose2 variables live in the graph
        raise FrslamError(f"graph holds {len(out)} poses, expected {n}", where="values")
    return out


def _logmap_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) ``Logmap(a⁻¹ · b)`` for (n, 3) poses: (v_x, v_y, θ) as ``gtsam.Pose2.Logmap``."""
    tx, ty, th = between_many(a, b).T
    small = np.abs(th) < 1e-10
    t = np.where(small, 1.0, th)
    half = 0.5 * t
    # V⁻¹ = (θ/2) [[cot(θ/2), 1], [-1, cot(θ/2)]]
    cot = np.where(small, 0.0, half / np.tan(np.where(small, 1.0, half)))
    vx = np.where(small, tx, cot * tx + half * ty)
    vy = np.where(small, ty, -half * tx + cot * ty)
    return np.column_stack((vx, vy, th))


__all__ = ["PoseGraph", "PriorHandle", "PriorResidual", "key", "regularise_covariance"]
