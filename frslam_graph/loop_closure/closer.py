"""Loop closure for the keyframe pose graph (``map`` frame; metres, radians).

Every ``attempt_every`` keyframes q, :class:`LoopCloser` looks for earlier keyframes c (not
recent ones: at least ``MIN_KEYFRAME_GAP`` keyframes and ``MIN_TRAVEL_GAP`` metres of travel or
``MIN_ROTATION_GAP_DEG`` of turning back) near the current estimate. The search radius and the
heading window grow with the travel / turning between the two along the shortest path of the
graph (accepted closures count as zero length), so a long excursion is searched widely and a
freshly corrected one narrowly. One candidate per ``CANDIDATE_SPACING`` cell; per attempt the
nearest cell not tried recently plus round-robin over the others (a wide area is covered over a
few keyframes); ``max_candidates`` per attempt, ``max_candidates_idle`` when nothing is queued (the
matching keeps up with the budget). When the prediction is too uncertain the search is centred on the candidate
itself ("is the robot back there?") instead of on the prediction.

Where the radius is wide (over ``PLACE_RADIUS``), round robin leaves it to luck whether a search
lands near the true place (a 128 m corridor loop at 0.3-0.5 deg/m of heading drift was never
closed: the keyframes back at the start searched its cells 9-31 m off). There each cell's
candidate is its keyframe that looks most like the current one and those cells go first, the
best-looking first (after the nearest cell: the prediction's own place). The look is place
recognition independent of the estimate (:mod:`frslam_graph.loop_closure.place`: a
rotation-invariant polar occupancy descriptor of each keyframe's query submap, made when the
keyframe arrives, compared as Scan Context does); ``stats.ranked`` counts the plans ranked so.

Redundant work is skipped, as mature systems do (Karto's graph-distance exclusion, Cartographer's
constraint sampling): while the graph ties the current keyframe to an old keyframe within its
search radius by a short path (at most ``redundant_travel`` metres and ``redundant_turn_deg`` of
turning, accepted closures counting as zero length), a recent verified closure keeps their
relative uncertainty small and another closure would add little: the keyframe plans no search at
all. Not only the tied region: farther regions would take its place among the candidates, and
those are the places that merely look alike (an aliased pair confirmed there bent a simulated
house by 7 m). Once the travel or turning since the closure grows past these, the search resumes,
nearest region first. A queued candidate that a closure accepted after its plan ties already (e.g.
the keyframe's other candidate) is dropped unmatched, and so is a pending closure's check of a
place already tied. Counted in ``stats.redundant``. The graph distances are updated incrementally
while no closure is added. Without a floor plan this is off by default (``redundant_travel`` 0:
the fewer closures let aliased ones weigh more); once floor-plan priors are in the graph
``redundant_travel_with_plan`` applies: the priors hold the map to the plan, and most closures of
a robot re-traversing the plan's rooms would only repeat what the priors already say.

Each candidate is verified by :func:`~frslam_graph.loop_closure.submap_matching.match_scan`: the *query* submap (the points of the last
``QUERY_TRAVEL`` metres of keyframes, in q's frame) is matched against the *reference* submap (the
points of c's neighbouring keyframes, in c's frame). A correlative grid search over (x, y, theta)
scores every pose at once (vectorised over poses × points) on a likelihood field of the reference
(``cv2.distanceTransform``), max-filtered so the coarse grid cannot step over the peak; the best
distinct peaks are refined by point-to-line ICP on the reference points. A match is accepted when
its inlier fraction is high and it is unambiguous (the best *distinct* second peak scores clearly
lower) and the query does not put points where the reference saw free space (another place that
looks alike: same walls, different furniture); it becomes ``gtsam.BetweenFactorPose2(x_c, x_q,
z)`` with the ICP covariance (inflated, floored) under a Cauchy kernel, so a wrong closure that
slips through cannot bend the map.

A robust kernel also refuses a *true* closure that disagrees with the current estimate by many
sigmas (after a long excursion). So a closure that would move the graph by more than
``CONFIRM_XY`` / ``CONFIRM_THETA_DEG`` waits until a second closure from another keyframe agrees
with it geometrically (pairwise consistency, as in PCM); then both enter the graph as plain
Gaussians (the graph converges to them with iSAM2, or an LM batch when the correction is large).
The bounded pull of a robust kernel could not hold such a correction against the stiff odometry
chain; the pairwise check takes its place as the guard against wrong closures. While a closure is
pending, each attempt first searches where it predicts the robot to be (same window and
ambiguity test as any candidate), which is what confirms the large corrections on ACES. The
keyframe ``verify_back_travel`` metres before the query is checked at once too (its query submap
shares no points with the pending one's), so the robot need not come back for a second look. A
match that agrees with a pending closure confirms it with a lower inlier fraction
(``confirm_min_inlier_fraction``: the agreement of two matches is the evidence); alone it is
rejected. Only while the closure moves its query at most ``search_window_xy`` from the estimate:
beyond, the search did not cover the prediction (it looked around the candidate itself), and in a
corridor or a row of alike rooms neighbouring keyframes match the same wrong place alike, so their
agreement is no evidence; a confirmation must be acceptable alone. With the wheel model varied
(session 7), ACES at 850 s and FR079 at 2,040 s confirmed a 12 m and a 3 m wrong pair by a match
of inlier fraction 0.50 / 0.59 and lost their loops; in session 6's real-log runs every pair over
2 m that such a match confirmed was removed again or bent its run.

Two more rules keep the confirmation independent of look-alike places (session 19). A check of a
pending closure's prediction (the check at each attempt, the one from ``verify_back_travel``
back) confirms that closure only: several pending closures of one aliased region send their
checks to look-alike places, and a check that fails its own closure would agree with whichever
other fits. A closure found through the place ranking (or agreeing with one that was) enters
once *two* closures from other keyframes agree with it: the ranking finds the places that look
alike wherever the estimate is, and on an aliased stretch a ranked match and the check of its
own prediction agree on the wrong place. ``found_by`` in ``loop_pending`` / ``loop_rejected``
says who proposed the candidate (``estimate``, ``ranked``, ``check``).

Closures already in the graph are re-checked after every addition and at the end
(:meth:`LoopCloser.on_finish`): at the converged estimate (an LM batch first), a closure whose residual
is far outside its covariance (``prune_chi2``, and ``PRUNE_XY`` / ``PRUNE_THETA_DEG``) is removed,
worst first: the odometry and the other closures disagree with it (on ACES, an aliased corridor
match confirmed by an unrelated closure of similar correction). Counted in ``stats.pruned``,
logged as ``loop_removed``. The lower confirmation threshold relies on it: without pruning,
regime-A houses 00dd / 026f went from 0.155 / 0.546 to 0.42 / 0.66 m ATE (0.04 / 0.05 with it).
A confirmed pair enters as plain Gaussians, so under its pull the older, robust closures show
the large residuals rather than the pair; when ``prune_pair_contradictions`` of them disagree at
once, the pair is removed first ("worst first" alone removed 134 good closures of a regime-A
house before the aliased pair that had bent it).

Bounded latency (anytime): a keyframe only *plans* (candidates into a queue, about 1 ms); the
work (query and reference submaps, the correlative search in chunks of at most
``MAX_LOOKUPS_PER_STEP`` look-ups, the reference's ICP data, each ICP refinement, the iSAM2 update
and each relinearising iteration after a closure, an LM batch) is a chain of steps run by every
``add_scan`` (keyframe or not) while their estimated cost fits ``budget_ms``. Each step announces
its cost from the sizes involved (a fixed cost model: look-ups, grid cells, points, keyframes),
never from a clock, so the run is deterministic and the same on any machine; a step estimated
above the budget runs alone. The budgets are per scan of a scanner at least as fast as
``BUDGET_PERIOD``; a slower one gets them per ``BUDGET_PERIOD`` of its period (keyframes come
with travel and turning, not with scans: :meth:`LoopCloser.set_scan_period`).
``wall_budget_ms`` optionally caps each call by the clock as well (then the spread depends on the
load). ``FRSlam.finish()`` runs what is left (:meth:`on_finish`).
With an unbounded budget the result is exactly that of doing everything in the keyframe's call.
When the matching falls behind the budget, a keyframe plans no candidates while
``MAX_QUEUED_JOBS`` wait (a pending closure's check excepted): without this cap the queue grew
all along a long log (FR079: 430 candidates waiting at the end, matched by ``finish`` hundreds of
keyframes after their plan), and the closures they found came too late to help the matches
after them (with it, FR079 finds more closures with two thirds of the matches; figures in
tools/README.md).

Decisions go to ``ctx.log`` as ``loop_closure`` / ``loop_pending`` / ``loop_rejected`` (with the
reason: ``no_overlap``, ``low_score``, ``low_inliers``, ``ambiguous``, ``free_space``).
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, TypeVar

import gtsam
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from frslam_graph.backend.graph import MS_PER_KEYFRAME_UPDATE, key
from frslam_graph.config import LoopClosureConfig
from frslam_graph.factors.between import pose2, regularise_covariance
from frslam_graph.factors.floorplan_prior import m_estimator
from frslam_graph.loop_closure.place import SpectrumCache, polar_occupancy
from frslam_graph.loop_closure.submap_matching import (
    MIN_COARSE_SCORE,
    GridPool,
    ReferenceSubmap,
    ScanMatch,
    match_scan_steps,
    rigid_points,
)
from frslam_graph.se2 import between, between_many, compose, wrap
from frslam_graph.steps import Steps, run_steps

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
MIN_KEYFRAME_GAP = 20  # candidates are at least this many keyframes back; larger = fewer, older candidates
MIN_TRAVEL_GAP = 5.0  # m; ... and at least this much travel back (or MIN_ROTATION_GAP_DEG of turning)
MIN_ROTATION_GAP_DEG = 300.0  # deg; ... or at least this much turning back
# m; candidate search radius around the estimate right after a closure; larger = more candidates
RADIUS_BASE = 2.0
# m of radius per m travelled since the last closure (or the candidate); larger = wider search
RADIUS_PER_M = 0.25
RADIUS_MAX = 60.0  # m; the radius grows up to this
THETA_WINDOW_BASE_DEG = 10.0  # deg; heading half-window of the search right after a closure
THETA_WINDOW_PER_M_DEG = 0.3  # deg of heading window per m travelled; larger = wider search
THETA_WINDOW_PER_TURN = 0.05  # deg of heading window per deg turned; larger = wider search
CANDIDATE_SPACING = 1.5  # m; one candidate per cell of this size; larger = fewer candidates
SUBMAPS_KEPT = 24  # reference submaps kept (least recently used dropped; ~5 MB each at 30 m range)
# m; candidates searched within a radius above this are ranked by place recognition (the
# descriptor distance of the two keyframes' submaps) instead of round-robin; larger = fewer plans
# ranked
PLACE_RADIUS = 8.0
# keyframes whose place descriptor's spectrum is kept for the ranking at most (least recently
# compared dropped first; ~10 kB each: 40 MB): a ranked plan compares its query with every
# keyframe within its radius; larger = more memory, fewer spectra computed anew
PLACE_SPECTRA_KEPT = 4096
SUBMAP_TRAVEL = 3.0  # m; reference submap: keyframes within ± this travel of the candidate
QUERY_TRAVEL = 2.0  # m; query submap: this much travel back from the keyframe
SUBMAP_KEYFRAMES = 30  # keyframes per side of a submap at most
CONFIRM_XY = 0.15  # m; corrections larger than this (or CONFIRM_THETA_DEG) wait for a confirming closure
CONFIRM_THETA_DEG = 1.5  # deg; heading part of that test
CONSISTENCY_XY = 0.3  # m; two closures agree within this (plus 2 % of the odometry between them)
CONSISTENCY_THETA_DEG = 3.0  # deg; heading part of the agreement
CLOSURE_COVARIANCE_INFLATION = 10.0  # factor on the closure covariance; larger = closures trusted less
CLOSURE_SIGMA_FLOOR_XY = 0.02  # m; smallest translation sigma of a closure
CLOSURE_SIGMA_FLOOR_THETA_DEG = 0.5  # deg; smallest heading sigma of a closure
# m; an LM batch runs when a closure moves the graph more than this; larger = fewer batches
BATCH_ON_CORRECTION = 1.0
PRUNE_XY = 0.3  # m; ... and whose residual is at least this
PRUNE_THETA_DEG = 3.0  # deg; ... or at least this turn
# candidates waiting to be matched at most: a keyframe plans none while this many wait (the
# matching fell behind the per-scan budget; planning more would only grow the queue, and a
# candidate matched hundreds of keyframes after its plan closes late). A pending closure's check
# is queued all the same.
MAX_QUEUED_JOBS = 12
# s; the budgets are per scan of a scanner at least this fast; a slower one gets them per this
# much of its period (LoopCloser.budget_scale)
BUDGET_PERIOD = 0.3

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext
    from frslam_graph.backend.keyframes import KeyframeInfo

T = TypeVar("T")

# Cost model: milliseconds on one core of the development machine (2-core x86 VM, 2020s); only
# needs to be right within a factor of about two. Fitted to the measured medians per step on ACES
# (180 beams) and regime-A houses (720 beams, 30 m; tools/bench_backend.py) as the geometric mean
# of the two ratios (before: the ICP, field and free-space steps took 2-3.5x their estimate on
# the houses, so a scan's 8 ms budget ran 15-30 ms of closure work).
_MS_GATHER = 0.2  # submap points: fixed part ...
_MS_PER_POINT_GATHER = 4.2e-5  # ... and per end point of the keyframes gathered


# ----------------------------------------------------------------------------- loop closer
@dataclass(frozen=True, slots=True, eq=False)
class LoopClosure:
    """An accepted (or pending) closure: x_reference⁻¹ ⊕ x_query = relative."""

    reference: int
    query: int
    relative: np.ndarray
    covariance: np.ndarray
    match: ScanMatch
    correction: np.ndarray  # prediction⁻¹ ⊕ relative at the time of the match (x, y, theta)
    # found through the place ranking (its candidate chosen by look), or agreeing with a pending
    # closure that was: a large correction needs two agreeing closures, not one
    ranked: bool = False


@dataclass(frozen=True, slots=True)
class _Job:
    """A candidate queued for matching: keyframe ``query`` against old keyframe ``reference``
    within ± radius (m) and ± window_theta (rad), around ``predicted`` (pose of the query in the
    reference's frame) when a pending closure predicts it."""

    reference: int
    query: int
    radius: float
    window_theta: float
    predicted: np.ndarray | None = None
    closures: int = 0  # closures accepted when it was planned
    ranked: bool = False  # chosen by the place ranking (its look), not by the estimate
    # the pending closure whose prediction this job checks (its prediction check or the check
    # from the keyframe before its query): the match confirms that closure only
    proposer: LoopClosure | None = None


def _gather_cost(ctx: BackendContext, lo: int, hi: int) -> float:
    """Estimated cost (ms) of gathering the points of keyframes lo..hi into a submap."""
    pts, _ = ctx.keyframe_scans()
    n = sum(len(pts[k]) for k in range(max(lo, 0), min(hi, len(pts) - 1) + 1))
    return _MS_GATHER + _MS_PER_POINT_GATHER * n


def _correction_xy(lc: LoopClosure, est: np.ndarray) -> float:
    """How far (m) closure ``lc`` would move its query from the estimate ``est``."""
    r = between(between(est[lc.reference], est[lc.query]), lc.relative)
    return float(np.hypot(r[0], r[1]))


def _moved(after: np.ndarray, before: np.ndarray) -> float:
    """Largest xy displacement (m) of the keyframes in both arrays."""
    n = min(len(after), len(before))
    return float(np.max(np.hypot(*(after[:n, :2] - before[:n, :2]).T))) if n else 0.0


@dataclass(slots=True)
class LoopClosureStats:
    attempts: int = 0  # candidates matched
    accepted: int = 0  # closures in the graph
    rejected: int = 0
    pending: int = 0  # waited for confirmation at least once
    batches: int = 0
    seconds: float = 0.0  # wall clock spent in the loop closer
    cpu_seconds: float = 0.0  # process CPU time spent in the loop closer
    keyframes: int = 0
    redundant: int = 0  # searches skipped: the keyframe already tied to the region (see config)
    pruned: int = 0  # accepted closures removed again: the rest of the graph disagreed
    verifications: int = 0  # earlier keyframes matched to check a pending closure
    plans_skipped: int = 0  # keyframes that planned no candidate: MAX_QUEUED_JOBS were waiting
    ranked: int = 0  # plans whose wide-radius candidates were ranked by place recognition
    reasons: dict[str, int] = field(default_factory=dict)


class LoopCloser:
    """Keyframe hook adding verified loop-closure factors to ``ctx.graph`` (see module docs)."""

    def __init__(
        self, config: LoopClosureConfig | None = None, clock: Callable[[], float] = time.perf_counter
    ):
        """``clock`` (seconds) measures ``wall_budget_ms`` (``budget_ms`` is in estimated
        milliseconds of the cost model, no clock involved); injectable for tests."""
        self.config = config or LoopClosureConfig()
        self.clock = clock
        self.closures: list[LoopClosure] = []
        self.stats = LoopClosureStats()
        self._travel: list[float] = []
        self._turn: list[float] = []
        self._odom: list[np.ndarray] = []
        self._last_closure = -1
        self._tried: dict[tuple[int, int], int] = {}
        self._pending: list[LoopClosure] = []
        # id of a pending closure found through the ranking -> the pending closures it agrees with
        self._support: dict[int, list[LoopClosure]] = {}
        self._factor_of: dict[int, gtsam.BetweenFactorPose2] = {}  # id(closure) -> its factor
        # graph distances of the latest plan: (keyframe, closures, travel, turn)
        self._dist: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._submaps: OrderedDict[int, ReferenceSubmap] = OrderedDict()
        # submaps a closure made stale (_drop_submaps), freed one per later build
        self._stale_submaps: list[ReferenceSubmap] = []
        # the large arrays of dropped submaps, for the next ones (no fresh mappings to fault in)
        self._pool = GridPool()
        # per keyframe: its points in range (_in_range), the keyframe's own float32 array when all
        # are (no copy), else a float32 subset
        self._local: list[np.ndarray | None] = []
        self._query: tuple[int, np.ndarray] | None = None  # (keyframe, query submap points)
        # per keyframe: its place descriptor's occupancy (loop_closure.place), packed bits (150
        # bytes), made when the keyframe arrives
        self._place: list[np.ndarray | None] = []
        # the descriptors' spectra last compared (place.SpectrumCache): kept between plans
        self._spectra = SpectrumCache(PLACE_SPECTRA_KEPT)
        self._rng = np.random.default_rng(0)
        # anytime work: candidates planned at a keyframe, matched a few steps per scan
        self._jobs: deque[_Job] = deque()
        self._task: Steps[list[LoopClosure]] | None = None  # the job being worked on
        self._last_plan = -(10**9)
        # redundant_travel, or redundant_travel_with_plan once floor-plan priors are in the graph
        # (set by each plan)
        self._redundant_travel = self.config.redundant_travel
        self._next_cost = 0.0  # estimated cost (ms) of the current task's next step
        # steps run by the latest on_keyframe / on_scan / on_finish and their estimated cost (ms)
        self.steps_last_call, self.cost_last_call = 0, 0.0
        self.budget_scale = 1.0  # factor on the per-call budgets (see set_scan_period)

    def set_scan_period(self, period: float) -> None:
        """The nominal scan period (s): the per-call budgets are for a scanner of at most
        ``BUDGET_PERIOD``; a slower one gets them per ``BUDGET_PERIOD`` of its period. Keyframes
        come with travel and turning, not with scans: at a third of FR079's scan rate most scans
        are keyframes, and a budget per scan matched a third of the candidates (263 attempts
        against 928, 455 keyframes planned none: 2.64 m against 0.033 m). A keyframe scan's own
        work (graph and plan updates, ``budget_ms - keyframe_budget_ms``) is not scaled: at 0.64 s
        most scans are keyframes, and scaling their reduced budget alone left the closer behind
        (FR079 1.62 m; with this 0.123 m)."""
        p = float(period)
        self.budget_scale = max(p / BUDGET_PERIOD, 1.0) if np.isfinite(p) else 1.0

    def _scaled(self, ms: float | None) -> float | None:
        return None if ms is None else ms * self.budget_scale

    # ------------------------------------------------------------------ motion bookkeeping
    def _append_motion(self, pose_odom: np.ndarray) -> None:
        p = np.asarray(pose_odom, dtype=np.float64)
        if self._odom:
            prev = self._odom[-1]
            self._travel.append(self._travel[-1] + float(np.hypot(*(p[:2] - prev[:2]))))
            self._turn.append(self._turn[-1] + float(abs(wrap(p[2] - prev[2]))))
        else:
            self._travel.append(0.0)
            self._turn.append(0.0)
        self._odom.append(p)

    def _sync(self, ctx: BackendContext, index: int) -> None:
        if len(self._odom) == index:
            return
        self._travel, self._turn, self._odom = [], [], []
        self._dist = None
        self._local = []
        self._place = []
        self._spectra.clear()
        for kf in ctx.keyframes()[:index]:
            self._append_motion(kf.pose_odom)

    # ------------------------------------------------------------------ hooks
    def on_keyframe(
        self, ctx: BackendContext, keyframe: KeyframeInfo, work: bool = True
    ) -> list[LoopClosure]:
        """A new keyframe: every ``attempt_every`` keyframes queue its candidates (a pending
        closure's check ahead of the older ones), then work on the queue within the per-scan
        budget (not with ``work`` False: this scan's budget is spent elsewhere; the queue goes
        on at the next scan). Returns the closures that entered the graph during this call (of
        this or an earlier keyframe)."""
        i = keyframe.index
        self._sync(ctx, i)
        self._append_motion(keyframe.pose_odom)
        self.stats.keyframes += 1
        cfg = self.config
        if not cfg.enabled:
            return []
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            self._descriptor(ctx, i)
            if i >= MIN_KEYFRAME_GAP and i % cfg.attempt_every == 0:
                self._plan(ctx, i)
            if not work:
                self.steps_last_call, self.cost_last_call = 0, 0.0
                return []
            # the keyframe's own work (graph and plan updates: budget_ms - keyframe_budget_ms)
            # comes out of its scan's budget once, whatever the period
            full = self._scaled(cfg.budget_ms)
            budget = min(cfg.keyframe_budget_ms, cfg.budget_ms) + full - cfg.budget_ms
            return self._work(ctx, budget, self._scaled(cfg.wall_budget_ms))
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    def on_scan(self, ctx: BackendContext, budget_ms: float | None = None) -> list[LoopClosure]:
        """A scan that is not a keyframe: continue the queued work within the per-scan budget.
        ``budget_ms``: what is left of it after other work on this scan (a deferred step); then
        only steps that fit run (none may)."""
        if self.idle:
            self.steps_last_call, self.cost_last_call = 0, 0.0
            return []
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            full = self._scaled(self.config.budget_ms)
            if budget_ms is not None:
                wall = self._scaled(self.config.wall_budget_ms)
                if wall is not None:
                    wall *= min(budget_ms / full, 1.0)
                return self._work(ctx, min(budget_ms, full), wall, first_free=False)
            return self._work(ctx, full, self._scaled(self.config.wall_budget_ms))
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    def on_finish(self, ctx: BackendContext) -> list[LoopClosure]:
        """Finish all queued work now (offline, before the final batch)."""
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            added = self._work(ctx, None, None)
            run_steps(self._prune(ctx))
            return added
        finally:
            self.stats.seconds += time.perf_counter() - t0
            self.stats.cpu_seconds += time.process_time() - c0

    @property
    def idle(self) -> bool:
        """No candidate waiting or being matched."""
        return self._task is None and not self._jobs

    def _work(
        self,
        ctx: BackendContext,
        budget: float | None,
        wall_budget_ms: float | None,
        first_free: bool = True,
    ) -> list[LoopClosure]:
        """Run steps of the queued jobs while their estimated costs (cost model, ms) fit in
        ``budget`` (None: run everything) and, with ``wall_budget_ms``, while the time spent in
        this call (``clock``) is below it. With ``first_free`` the first step always runs, so
        the queue advances even when a single step is estimated above the budget (the scan's
        own budget); without it (the rest of a budget other work used) every step must fit."""
        added: list[LoopClosure] = []
        start = self.clock()
        spent, steps = 0.0, 0
        while not self.idle:
            cost = self._next_cost
            bounded = steps or not first_free
            if bounded and budget is not None and spent + cost > budget:
                break
            if bounded and wall_budget_ms is not None and 1e3 * (self.clock() - start) >= wall_budget_ms:
                break
            if self._task is None:
                self._task = self._job(ctx, self._jobs.popleft())
            try:
                self._next_cost = float(next(self._task))
            except StopIteration as stop:
                added.extend(stop.value)
                self._task = None
                self._next_cost = 0.0
            spent += cost
            steps += 1
        self.steps_last_call, self.cost_last_call = steps, spent
        return added

    def _graph_distances(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Travel (m) and turn (rad) from keyframe i to every keyframe along the shortest path of
        the graph, accepted closures counting as zero length: how far the relative drift can grow."""
        trav, turn = np.asarray(self._travel[: i + 1]), np.asarray(self._turn[: i + 1])
        n = i + 1
        d = self._dist
        if d is not None and d[0] <= i and d[1] == len(self.closures) and self._last_closure <= d[0]:
            # no closure since the previous keyframe i0 = d[0] and none after it: every path from
            # i runs down the chain to i0 (each edge of the chain counts + 1e-9, as below)
            i0 = d[0]
            k = np.arange(i0 + 1, n)
            out = [
                np.concatenate((prev + (x[i] - x[i0]) + 1e-9 * (i - i0), x[i] - x[k] + 1e-9 * (i - k)))
                for prev, x in ((d[2], trav), (d[3], turn))
            ]
            self._dist = (i, len(self.closures), out[0], out[1])
            return out[0], out[1]
        a = np.arange(n - 1)
        rows = [a, a + 1]
        cols = [a + 1, a]
        dt = np.diff(trav) + 1e-9
        dr = np.diff(turn) + 1e-9
        wt, wr = [dt, dt], [dr, dr]
        lc = [(c.reference, c.query) for c in self.closures if c.query <= i]
        if lc:
            r, q = np.asarray(lc).T
            rows += [r, q]
            cols += [q, r]
            wt += [np.full(len(r), 1e-9)] * 2
            wr += [np.full(len(r), 1e-9)] * 2
        rr, cc = np.concatenate(rows), np.concatenate(cols)
        # one sparsity structure for both weights (rows sorted; duplicate edges are kept, the
        # search takes the shorter)
        perm = np.argsort(rr, kind="stable")
        indptr = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(rr, minlength=n), out=indptr[1:])
        cols_sorted = cc[perm].astype(np.int32)
        out = []
        for w in (wt, wr):
            g = csr_matrix((np.concatenate(w)[perm], cols_sorted, indptr), shape=(n, n))
            out.append(dijkstra(g, indices=i, directed=True))
        self._dist = (i, len(self.closures), out[0], out[1])
        return out[0], out[1]

    def _tied(self, i: int) -> np.ndarray:
        """Mask over keyframes 0..i: tied to keyframe i by a short path of the graph (the relative
        uncertainty is small; see ``LoopClosureConfig.redundant_travel``)."""
        cfg = self.config
        d = self._dist
        d_rel, r_rel = (d[2], d[3]) if d and d[:2] == (i, len(self.closures)) else self._graph_distances(i)
        return (d_rel <= self._redundant_travel) & (r_rel <= np.deg2rad(cfg.redundant_turn_deg))

    def _eligible(self, i: int) -> np.ndarray:
        """Mask over keyframes 0..i-MIN_KEYFRAME_GAP far enough back (travel or turn)."""
        n = i - MIN_KEYFRAME_GAP + 1
        if n <= 0:
            return np.zeros(0, bool)
        trav, turn = np.asarray(self._travel), np.asarray(self._turn)
        gap_t, gap_r = trav[i] - trav[:n], turn[i] - turn[:n]
        return (gap_t >= MIN_TRAVEL_GAP) | (gap_r >= np.deg2rad(MIN_ROTATION_GAP_DEG))

    def _hypothesis(self, est: np.ndarray, i: int) -> tuple[int, float, float, np.ndarray] | None:
        """Where the latest pending closure says keyframe i is in the old map: (the old keyframe
        nearest to that place, window xy, window theta, predicted pose relative to it)."""
        cfg = self.config
        if not self._pending:
            return None
        p = self._pending[-1]
        if p.query == i or i - p.query > cfg.pending_keyframes:
            return None
        ok = self._eligible(i)
        if not ok.any():
            return None
        pred = compose(compose(est[p.reference], p.relative), between(est[p.query], est[i]))
        d = np.hypot(*(est[: len(ok), :2] - pred[:2]).T)
        d[~ok] = np.inf
        c = int(np.argmin(d))
        if d[c] > cfg.search_window_xy:
            return None
        return c, cfg.hypothesis_window_xy, np.deg2rad(cfg.hypothesis_window_theta_deg), between(est[c], pred)

    def _candidates(
        self, est: np.ndarray, i: int, limit: int | None = None
    ) -> list[tuple[int, float, float, bool]]:
        """(keyframe, search radius, heading window, chosen by the place ranking) of the
        candidates to try now (at most ``limit``, default ``max_candidates``)."""
        cfg = self.config
        limit = cfg.max_candidates if limit is None else limit
        trav, turn = np.asarray(self._travel), np.asarray(self._turn)
        n = i - MIN_KEYFRAME_GAP + 1
        if n <= 0:
            return []
        idx = np.arange(n)
        gap_t, gap_r = trav[i] - trav[:n], turn[i] - turn[:n]
        ok = (gap_t >= MIN_TRAVEL_GAP) | (gap_r >= np.deg2rad(MIN_ROTATION_GAP_DEG))
        d_rel, r_rel = self._graph_distances(i)
        d_rel, r_rel = d_rel[:n], r_rel[:n]
        radius = np.minimum(RADIUS_MAX, RADIUS_BASE + RADIUS_PER_M * d_rel)
        dist = np.hypot(*(est[:n, :2] - est[i, :2]).T)
        ok &= dist <= radius
        if not ok.any():
            return []
        idx = idx[ok]
        order = idx[np.argsort(dist[ok], kind="stable")]
        if self._tied(i)[order].any():
            # keyframe i is tied to a region around it (short path through a recent verified
            # closure): it is not searched, and neither are the others (farther regions would
            # take its place: places that look alike, where a wrong pair can be confirmed)
            self.stats.redundant += 1
            return []
        cells = list(map(tuple, np.floor(est[order, :2] / CANDIDATE_SPACING).astype(int).tolist()))
        looks = self._place_distances(i, order[radius[order] > PLACE_RADIUS])
        self.stats.ranked += bool(looks)
        order = order.tolist()
        # one candidate per cell (the nearest); the first pick is the nearest cell not tried
        # recently, the others go round-robin (never tried first, then the least recently tried)
        # so that a wide search area is covered over the keyframes. Where the radius is wide
        # (the estimate no longer says where the robot is), a cell's candidate is its keyframe
        # that looks most like keyframe i, and those cells go first, the best-looking first.
        best: dict[tuple[int, int], tuple[float, int]] = {}
        for c, cell in zip(order, cells, strict=True):
            if c in looks and looks[c] < best.get(cell, (np.inf, -1))[0]:
                best[cell] = (looks[c], c)
        picks, seen = [], set()
        for rank, (c, cell) in enumerate(zip(order, cells, strict=True)):
            if cell in seen:
                continue
            seen.add(cell)
            last = self._tried.get(cell)
            if last is not None and i - last < cfg.retry_keyframes:
                continue
            look, alike = best.get(cell, (np.inf, c))
            picks.append((look, -1 if last is None else last, rank, c, alike, cell))
        if picks:
            first = min(picks, key=lambda t: t[2])
            picks.remove(first)
            # the first pick is the estimate's (the nearest cell): not ranked
            first = (np.inf, *first[1:4], first[5])
            picks = [first, *((p[:3] + p[4:]) for p in sorted(picks))]
        out = []
        for look, _, _, c, cell in picks[:limit]:
            window = np.deg2rad(
                THETA_WINDOW_BASE_DEG
                + THETA_WINDOW_PER_M_DEG * d_rel[c]
                + THETA_WINDOW_PER_TURN * np.rad2deg(r_rel[c])
            )
            out.append((c, float(radius[c]), float(min(window, np.pi)), bool(np.isfinite(look))))
            self._tried[cell] = i
        return out

    def _place_distances(self, i: int, cands: np.ndarray) -> dict[int, float]:
        """Descriptor distance (0: alike, 1: nothing in common) of keyframe i to each of the
        keyframes ``cands`` (those with a descriptor)."""
        have = [len(self._place) > k and self._place[k] is not None for k in (i, *cands.tolist())]
        if not have[0] or not any(have[1:]):
            return {}
        ks = [int(k) for k, h in zip(cands.tolist(), have[1:], strict=True) if h]
        dist = self._spectra.distances([i, *ks], self._place.__getitem__)
        return dict(zip(ks, dist.tolist(), strict=True))

    def _submap(
        self, ctx: BackendContext, est: np.ndarray, centre: int, lo: int, hi: int, travel: float
    ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """Points of keyframes lo..hi (within ± travel of ``centre``) in ``centre``'s frame, and
        per keyframe (sensor origin, end points in beam order) in that frame."""
        pts_all, origins = ctx.keyframe_scans()
        trav = self._travel
        ks = [
            k
            for k in range(max(lo, 0), min(hi, len(pts_all) - 1) + 1)
            if abs(trav[k] - trav[centre]) <= travel and len(pts_all[k])
        ]
        if not ks:
            return np.zeros((0, 2)), []
        local = [self._in_range(pts_all, origins, k) for k in ks]
        rels = [between(est[centre], est[k]) for k in ks]
        sizes = [len(p) for p in local]
        # one transform for all keyframes' points and one for their sensor origins: per point
        # the same products as transform_points
        rig = np.array([(r[0], r[1], np.cos(r[2]), np.sin(r[2])) for r in rels])
        pts = rigid_points(*np.repeat(rig, sizes, axis=0).T, np.concatenate(local, dtype=np.float64))
        ends = np.split(pts, np.cumsum(sizes)[:-1])
        sensors = rigid_points(*rig.T, np.array([origins[k] for k in ks], dtype=np.float64))
        return pts, list(zip(sensors, ends, strict=True))

    def _in_range(self, pts_all: list[np.ndarray], origins: list[np.ndarray], k: int) -> np.ndarray:
        """Keyframe k's end points within ``max_point_range`` of its sensor (base_link, the dtype of
        the keyframe's points; cached: keyframe scans never change). When all are in range the
        keyframe's own array is returned: the cache holds no copy of the map's points."""
        cache = self._local
        while len(cache) <= k:
            cache.append(None)
        p = cache[k]
        if p is None:
            q = pts_all[k]
            ok = np.hypot(*(q - origins[k]).T) <= self.config.max_point_range
            p = cache[k] = q if ok.all() else q[ok]
        return p

    def _reference(self, ctx: BackendContext, c: int, i: int) -> Steps[ReferenceSubmap]:
        """Reference submap of keyframe c (cached), two steps when built: points, field."""
        sub = self._submaps.get(c)
        if sub is not None:
            self._submaps.move_to_end(c)
            return sub
        cfg = self.config
        lo, hi = c - SUBMAP_KEYFRAMES, min(c + SUBMAP_KEYFRAMES, i - MIN_KEYFRAME_GAP)
        yield _gather_cost(ctx, lo, hi)
        pts, scans = self._submap(ctx, ctx.graph.estimates(), c, lo, hi, SUBMAP_TRAVEL)
        margin = 2.0 * cfg.search_window_xy + 4.0 * cfg.likelihood_sigma + 1.5
        if len(pts):
            yield ReferenceSubmap.build_cost(pts, cfg.resolution, cfg.likelihood_sigma, margin)
        self._make_room()  # first: the new submap's arrays may come from the one dropped
        sub = ReferenceSubmap(
            pts, cfg.resolution, cfg.likelihood_sigma, margin, scans, cfg.free_space_margin, pool=self._pool
        )
        self._keep_submap(c, sub)
        return sub

    def _make_room(self) -> None:
        """Before a new submap is built: free one stale submap (:meth:`_drop_submaps`), else
        the least recently used while ``SUBMAPS_KEPT`` are held (stale ones count); their
        arrays go to the pool (:class:`GridPool`)."""
        if self._stale_submaps:
            self._stale_submaps.pop().release()
        while len(self._submaps) + len(self._stale_submaps) >= SUBMAPS_KEPT:
            self._submaps.popitem(last=False)[1].release()

    def _keep_submap(self, c: int, sub: ReferenceSubmap) -> None:
        """Keep keyframe c's new reference submap (built after :meth:`_make_room`, which left
        room for it)."""
        self._submaps[c] = sub

    def _drop_submaps(self) -> None:
        """Forget the reference submaps (a closure moved their keyframes relative to each other).
        Their memory goes one submap per later build (:meth:`_make_room`), never more than
        ``SUBMAPS_KEPT`` held: freeing all at once (arrays of ~5 MB each, unmapped page by page)
        took 15-20 ms of CPU inside a step whose announced cost was a settle iteration's."""
        self._stale_submaps.extend(self._submaps.values())
        self._submaps.clear()

    def _reject(self, ctx: BackendContext, i: int, c: int, reason: str, **data: Any) -> None:
        self.stats.rejected += 1
        self.stats.reasons[reason] = self.stats.reasons.get(reason, 0) + 1
        ctx.log.record("loop_rejected", f"keyframe {i} vs {c}: {reason}", keyframe=i, reference=c, **data)

    def _plan(self, ctx: BackendContext, i: int) -> None:
        """Queue the candidates of keyframe i: first where a pending closure predicts the robot
        to be, then up to ``max_candidates`` in all (``max_candidates_idle`` when nothing is
        queued: the work keeps up with the budget; none but that check while
        ``MAX_QUEUED_JOBS`` wait)."""
        cfg = self.config
        limit = max(cfg.max_candidates, cfg.max_candidates_idle) if self.idle else cfg.max_candidates
        # pending closures too old when the previous plan was done
        self._pending = [p for p in self._pending if self._last_plan - p.query <= cfg.pending_keyframes]
        self._support = {id(p): self._support[id(p)] for p in self._pending if id(p) in self._support}
        self._last_plan = i
        self._redundant_travel = (
            cfg.redundant_travel_with_plan if ctx.graph.has_priors() else cfg.redundant_travel
        )
        est = ctx.graph.estimates()
        cands: list[tuple[int, float, float, bool]] = []
        if len(self._jobs) < MAX_QUEUED_JOBS:
            cands = self._candidates(est, i, limit)
        else:
            self.stats.plans_skipped += 1
        hyp = self._hypothesis(est, i)
        if hyp is not None and self._tied(i)[hyp[0]]:
            # the graph already ties keyframe i to the predicted place by a recent verified
            # closure: the check is redundant (and the closure, if it agrees, adds little)
            self.stats.redundant += 1
            hyp = None
        if hyp is not None:
            cands = cands[: limit - 1]
        n = len(self.closures)
        self._jobs.extend(_Job(c, i, r, w, None, n, ranked) for c, r, w, ranked in cands)
        if hyp is not None:  # time-critical (the pending closure expires): ahead of older jobs
            self._jobs.appendleft(_Job(hyp[0], i, hyp[1], hyp[2], hyp[3], n, proposer=self._pending[-1]))

    def _descriptor(self, ctx: BackendContext, k: int) -> None:
        """Make the place descriptor of keyframe k (kept as packed bits of its polar occupancy):
        its query submap (``QUERY_TRAVEL`` of travel back, in its frame) at the estimate when the
        keyframe arrives, so the points are those the robot saw there, placed by the local
        estimate (whatever the drift since)."""
        cache = self._place
        while len(cache) <= k:
            cache.append(None)
        if cache[k] is None:
            pts, _ = self._submap(ctx, ctx.graph.estimates(), k, k - SUBMAP_KEYFRAMES, k, QUERY_TRAVEL)
            cache[k] = np.packbits(polar_occupancy(pts))
            self._spectra.keep([k], cache.__getitem__)  # compared with every later query

    def _query_points(self, ctx: BackendContext, i: int) -> np.ndarray:
        """Query submap of keyframe i (kept: shared by its candidates)."""
        if self._query is not None and self._query[0] == i:
            return self._query[1]
        est = ctx.graph.estimates()
        query, _ = self._submap(ctx, est, i, i - SUBMAP_KEYFRAMES, i, QUERY_TRAVEL)
        self._query = (i, query)
        return query

    def _job(self, ctx: BackendContext, job: _Job) -> Steps[list[LoopClosure]]:
        """Match one candidate and act on the result (a step generator): query submap, reference
        submap, correlative search + ICP (:func:`match_scan_steps`), verification, graph update
        (:meth:`_add`)."""
        cfg = self.config
        c, i = job.reference, job.query
        if len(self.closures) != job.closures and self._tied(i)[c]:
            # a closure accepted since the plan (e.g. the keyframe's other candidate) ties the
            # region already: matching it would add little
            self.stats.redundant += 1
            return []
        if self._query is None or self._query[0] != i:
            yield _gather_cost(ctx, i - SUBMAP_KEYFRAMES, i)
        query = self._query_points(ctx, i)
        ref = yield from self._reference(ctx, c, i)
        est = ctx.graph.estimates()
        self.stats.attempts += 1
        guess = between(est[c], est[i])
        centre, win = self._search_window(job, guess)
        m = yield from match_scan_steps(ref, query, centre, win, job.window_theta, cfg, self._rng)
        if m is None:
            self._reject(ctx, i, c, "no_overlap")
            return []
        data = {
            # who proposed the candidate: the estimate, the place ranking, a pending closure's check
            "found_by": "check" if job.proposer is not None else "ranked" if job.ranked else "estimate",
            "inliers": round(m.inlier_fraction, 3),
            "ambiguity": round(m.ambiguity, 3),
            "relative": m.pose.tolist(),
            "coarse": round(m.coarse_score, 3),
        }
        refused = self._refused(m)
        if refused is not None:
            self._reject(ctx, i, c, refused[0], **refused[1], **data)
            return []
        weak = m.inlier_fraction < cfg.min_inlier_fraction  # only confirms a pending closure
        cov = regularise_covariance(
            m.covariance * CLOSURE_COVARIANCE_INFLATION,
            CLOSURE_SIGMA_FLOOR_XY,
            np.deg2rad(CLOSURE_SIGMA_FLOOR_THETA_DEG),
        )
        corr = between(guess, m.pose)
        lc = LoopClosure(c, i, m.pose.copy(), cov, m, corr, job.ranked)
        small = np.hypot(corr[0], corr[1]) <= CONFIRM_XY and abs(corr[2]) <= np.deg2rad(CONFIRM_THETA_DEG)
        partner = None if small else self._consistent_pending(lc, ctx.graph.estimates(), weak, job.proposer)
        if weak and partner is None:
            self._reject(ctx, i, c, "low_inliers", **data)
            return []
        if small:
            yield from self._add(ctx, [lc], settle=False)
            return [lc]
        group = [] if partner is None else [*self._support.get(id(partner), []), partner]
        if partner is not None and (lc.ranked or partner.ranked) and len(group) < 2:
            # found through the look: a second agreeing closure is asked (see _consistent_pending)
            lc = replace(lc, ranked=True)
            self._support[id(lc)] = group
            partner = None
        if partner is None:
            self._pending.append(lc)
            self.stats.pending += 1
            ctx.log.record(
                "loop_pending",
                f"keyframe {i} vs {c}: large correction, waiting for a consistent second closure",
                keyframe=i,
                reference=c,
                correction=corr.tolist(),
                **data,
            )
            self._verify_back(ctx, lc)
            return []
        self._pending = [q for q in self._pending if not any(q is g for g in group)]
        yield from self._add(ctx, [*group, lc], settle=True)
        return [*group, lc]

    def _search_window(self, job: _Job, guess: np.ndarray) -> tuple[np.ndarray, float]:
        """Centre (the query's pose in the reference's frame) and ± xy window (m) of a search."""
        cfg = self.config
        radius = job.radius
        if job.predicted is not None:  # check a pending closure's prediction
            return job.predicted, radius
        if radius <= cfg.search_window_xy or np.hypot(guess[0], guess[1]) <= cfg.search_window_xy:
            return guess, min(cfg.search_window_xy, max(radius, 0.5))
        # the prediction is too uncertain: is the robot back at the candidate itself?
        return np.array([0.0, 0.0, guess[2]]), cfg.search_window_xy

    def _refused(self, m: ScanMatch) -> tuple[str, dict[str, Any]] | None:
        """Why a match is refused whatever a pending closure says (reason, extra data), or None."""
        cfg = self.config
        if m.coarse_score < MIN_COARSE_SCORE:
            return "low_score", {}
        if m.inlier_fraction < min(cfg.min_inlier_fraction, cfg.confirm_min_inlier_fraction):
            return "low_inliers", {}
        if m.ambiguity > cfg.max_ambiguity:
            return "ambiguous", {}
        if m.free_violation > cfg.max_free_violation:
            return "free_space", {"free": round(m.free_violation, 3)}
        return None

    def _verify_back(self, ctx: BackendContext, lc: LoopClosure) -> None:
        """Queue (first) a check of the pending ``lc`` from the keyframe ``verify_back_travel``
        metres before its query: matched against the old keyframe nearest to where ``lc`` puts it.
        Its query submap shares no points with ``lc``'s, so an agreeing match is a second piece of
        evidence even when the robot does not come back to the place."""
        cfg = self.config
        i = lc.query
        if cfg.verify_back_travel <= 0.0:
            return
        trav = np.asarray(self._travel[: i + 1])
        back = np.flatnonzero(trav[i] - trav >= cfg.verify_back_travel)
        if not len(back):
            return
        j = int(back[-1])
        ok = self._eligible(j)
        if not ok.any():
            return
        est = ctx.graph.estimates()
        pred = compose(compose(est[lc.reference], lc.relative), between(est[i], est[j]))
        d = np.hypot(*(est[: len(ok), :2] - pred[:2]).T)
        d[~ok] = np.inf
        c = int(np.argmin(d))
        if d[c] > cfg.search_window_xy:
            return
        window = np.deg2rad(cfg.hypothesis_window_theta_deg)
        self._jobs.appendleft(
            _Job(
                c, j, cfg.hypothesis_window_xy, window, between(est[c], pred), len(self.closures), proposer=lc
            )
        )
        self.stats.verifications += 1

    def _consistent_pending(
        self, lc: LoopClosure, est: np.ndarray, weak: bool = False, proposer: LoopClosure | None = None
    ) -> LoopClosure | None:
        """The latest pending closure ``lc`` agrees with (pairwise consistency) among those whose
        query keyframe lies ``QUERY_TRAVEL`` or more of travel from ``lc``'s, or None. A ``weak``
        match (inlier fraction below ``min_inlier_fraction``) only confirms a closure that moves
        its query at most ``search_window_xy`` from the current estimate (see the module docs).
        A check of a pending closure's prediction (``proposer``) confirms that closure only: it
        tests that closure, and agreeing with another is chance. Pending closures of one aliased
        region send their checks to look-alike places, where a check that fails its own closure
        agrees with whichever other fits (ACES with 3 cm range noise, the ranking on: 554 on 15,
        554 on 11 (ranked), 560 on 52 and 552 on 10 pending, 20 m and 80 deg off; the check of
        the latest, 568 on 74, disagreed with it but agreed with 554 on 15: the pair entered and
        the true loop was lost).

        A closure found through the place ranking (``ranked``) is confirmed by two agreeing
        closures, not one (the caller keeps the first agreeing one pending as its support): the
        ranking finds the places that look alike wherever the estimate is, and where a whole
        stretch is aliased a ranked match and its own check agree on it (ACES with 3 cm range
        noise: 664 on 160, 30 m and 78 deg off, confirmed by its check 670 on 164)."""
        pending = self._pending if proposer is None else [p for p in self._pending if p is proposer]
        for p in reversed(pending):
            if abs(self._travel[lc.query] - self._travel[p.query]) < QUERY_TRAVEL:
                # query submaps this close share their points: the same match again, not a second
                # piece of evidence (FR079 with beams cut at 8 m: two closures 0.65 m apart both
                # 3 m along a corridor whose far end the scans no longer see)
                continue
            if weak and _correction_xy(p, est) > self.config.search_window_xy:
                continue
            implied = between(compose(est[p.reference], p.relative), compose(est[lc.reference], lc.relative))
            odo = between(est[p.query], est[lc.query])
            d = between(implied, odo)
            tol_xy = CONSISTENCY_XY + 0.02 * float(np.hypot(odo[0], odo[1]))
            if np.hypot(d[0], d[1]) <= tol_xy and abs(d[2]) <= np.deg2rad(CONSISTENCY_THETA_DEG):
                return p
        return None

    def _factor(self, lc: LoopClosure, robust: bool) -> gtsam.BetweenFactorPose2:
        gauss = gtsam.noiseModel.Gaussian.Covariance(lc.covariance)
        est = m_estimator(self.config.kernel, self.config.kernel_param) if robust else None
        noise = gauss if est is None else gtsam.noiseModel.Robust.Create(est, gauss)
        return gtsam.BetweenFactorPose2(key(lc.reference), key(lc.query), pose2(lc.relative), noise)

    def _add(self, ctx: BackendContext, closures: list[LoopClosure], settle: bool) -> Steps[None]:
        """Add closures to the graph (a step generator). A single closure with a small correction
        enters under the robust kernel. A confirmed pair (``settle``: two closures from different
        keyframes that agree) enters as plain Gaussians: a bounded-influence kernel cannot pull
        the stiff odometry chain far, not even after the graph has converged to the closure (the
        chain's stress exceeds the kernel's maximal pull and the graph slides back); an LM batch
        runs when the correction moved the graph far. The relinearising iSAM2 iterations after
        the factor (:meth:`PoseGraph.settle`) run one per step."""
        graph = ctx.graph
        yield MS_PER_KEYFRAME_UPDATE * len(graph)
        before = graph.estimates()
        # with floor-plan priors in the graph, absolute corrections come from the plan: a
        # confirmed pair stays under the robust kernel too, so an aliased pair (two matches of
        # the same repeated structure) cannot overrule the priors
        anchored = graph.has_priors()
        for lc in closures:
            factor = self._factor(lc, robust=not settle or anchored)
            self._factor_of[id(lc)] = factor
            graph.add_factor(factor, extra_iterations=0)
        if settle:
            yield from self._settle(graph, 10)
            moved = _moved(graph.estimates(), before)
            if moved >= BATCH_ON_CORRECTION or self._residual_large(graph, closures):
                yield from graph.optimize_batch_steps()
                self.stats.batches += 1
        yield from self._settle(graph, 10 if settle else self.config.settle_small)
        moved = _moved(graph.estimates(), before)
        for lc in closures:
            self.closures.append(lc)
            self.stats.accepted += 1
            self._last_closure = max(self._last_closure, lc.query)
            ctx.log.record(
                "loop_closure",
                f"keyframe {lc.query} closes on {lc.reference}",
                keyframe=lc.query,
                reference=lc.reference,
                relative=lc.relative.tolist(),
                correction=lc.correction.tolist(),
                inliers=round(lc.match.inlier_fraction, 3),
                ambiguity=round(lc.match.ambiguity, 3),
                sigma_xy=float(np.sqrt(max(lc.covariance[0, 0], lc.covariance[1, 1]))),
                moved=moved,
                robust=not settle,
            )
        if settle:  # neighbouring keyframes may have moved relative to each other
            self._drop_submaps()
        yield from self._prune(ctx, closures if settle else None)

    def _residual_chi2(self, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (K, 3: x, y, theta of prediction⁻¹ ⊕ measurement) of the accepted closures at
        ``est`` and their squared Mahalanobis norms (K,) under the closures' covariances."""
        if not self.closures:
            return np.zeros((0, 3)), np.zeros(0)
        ref = est[[lc.reference for lc in self.closures]]
        qry = est[[lc.query for lc in self.closures]]
        meas = np.array([lc.relative for lc in self.closures])
        cov = np.array([lc.covariance for lc in self.closures])
        pred = between_many(ref, qry)
        r = between_many(pred, meas)
        chi2 = np.einsum("ki,ki->k", r, np.linalg.solve(cov, r[:, :, None])[:, :, 0])
        return r, chi2

    def _prune(self, ctx: BackendContext, suspects: list[LoopClosure] | None = None) -> Steps[None]:
        """Remove accepted closures the rest of the graph disagrees with (a step generator): while
        the worst residual exceeds ``prune_chi2`` and ``PRUNE_XY`` / ``PRUNE_THETA_DEG`` at the
        converged estimate (an LM batch first), remove that closure and settle again.

        ``suspects``: a confirmed pair that just entered as plain Gaussians. Under its pull the
        older, robust closures show the large residuals, so "worst first" would remove them one
        by one before the pair (a regime-A house: 134 good closures removed, then the aliased
        pair). When at least ``prune_pair_contradictions`` older closures disagree at once, the
        pair is removed first."""
        cfg = self.config
        if cfg.prune_chi2 <= 0.0:
            return
        graph = ctx.graph
        converged = False
        suspects = list(suspects or [])
        while self.closures:
            r, chi2_all = self._residual_chi2(graph.estimates())
            big = (np.hypot(r[:, 0], r[:, 1]) > PRUNE_XY) | (np.abs(r[:, 2]) > np.deg2rad(PRUNE_THETA_DEG))
            chi2 = np.where(big, chi2_all, 0.0)
            k = int(np.argmax(chi2))
            if chi2[k] <= cfg.prune_chi2:
                return
            if not converged:  # judge at the optimum, not after a few Gauss-Newton steps
                yield from graph.optimize_batch_steps()
                self.stats.batches += 1
                converged = True
                continue
            suspect = np.array([any(lc is s for s in suspects) for lc in self.closures])
            others = int(np.count_nonzero((chi2 > cfg.prune_chi2) & ~suspect))
            if suspect.any() and others >= cfg.prune_pair_contradictions:
                worst = np.flatnonzero(suspect)
                why = f"it contradicts {others} accepted closures"
            else:
                worst = np.array([k])
                why = f"the graph disagrees (chi2 {chi2[k]:.0f})"
            suspects = []
            yield from self._remove(ctx, worst.tolist(), r, chi2_all, why)

    def _remove(
        self, ctx: BackendContext, which: list[int], r: np.ndarray, chi2: np.ndarray, why: str
    ) -> Steps[None]:
        """Remove the accepted closures at positions ``which`` of ``self.closures`` (residuals
        ``r`` / ``chi2`` as judged) in one iSAM2 update, then settle (a step generator)."""
        graph = ctx.graph
        yield MS_PER_KEYFRAME_UPDATE * len(graph)
        before = graph.estimates()
        removed = [self.closures[k] for k in which]
        gone = set(which)
        self.closures = [lc for k, lc in enumerate(self.closures) if k not in gone]
        idx = [
            graph.factor_index(f)
            for f in (self._factor_of.pop(id(lc), None) for lc in removed)
            if f is not None
        ]
        idx = [i for i in idx if i >= 0]
        if idx:
            graph.remove_factors(idx, extra_iterations=0)
        yield from self._settle(graph, 10)
        if _moved(graph.estimates(), before) >= BATCH_ON_CORRECTION:
            yield from graph.optimize_batch_steps()
            self.stats.batches += 1
        self._dist = None
        self._drop_submaps()
        self._last_closure = max((c.query for c in self.closures), default=-1)
        for k, lc in zip(which, removed, strict=True):
            self.stats.pruned += 1
            ctx.log.record(
                "loop_removed",
                f"keyframe {lc.query} on {lc.reference}: {why}",
                keyframe=lc.query,
                reference=lc.reference,
                residual=r[k].tolist(),
                chi2=float(chi2[k]),
            )

    @staticmethod
    def _settle(graph, max_iterations: int, tol: float = 1e-4) -> Steps[None]:
        """:meth:`PoseGraph.settle_steps` with this module's cost estimate for each step."""
        for _ in graph.settle_steps(max_iterations, tol):
            yield MS_PER_KEYFRAME_UPDATE * len(graph)

    @staticmethod
    def _residual_large(graph, closures: list[LoopClosure]) -> bool:
        est = graph.estimates()
        for lc in closures:
            r = between(between(est[lc.reference], est[lc.query]), lc.relative)
            if np.hypot(r[0], r[1]) > 0.1 or abs(r[2]) > np.deg2rad(1.0):
                return True
        return False


__all__ = ["LoopCloser", "LoopClosure", "LoopClosureStats"]
