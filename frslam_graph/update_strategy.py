"""The real-time floor-plan update strategy (paper Alg. 3) as a policy plugged into FRSlam.

Frames (REP-105; metres, radians): before any registration ``map`` is the odom frame of the
first pose (the graph's anchor). The LiDAR occupancy map is built in ``map`` from the keyframes
at their current estimates, so a registration's matrix (plan -> map metres) puts the plan *in
the SLAM map frame*; the first accepted registration fixes that plan -> map transform and the
graph is never re-expressed. Relocalisation priors then pull the trajectory onto the plan's
geometry, which corrects the drift accumulated along the way.

:class:`FloorPlanUpdater` is called after every keyframe (``on_keyframe(ctx, keyframe)``):

- it keeps a coarse coverage of the mapped area (cells seen by the keyframe beams);
- it **registers** the plan (``register_fn(plan, grid)``, MFR by default) when the mapped area
  first reaches ``first_register_area_m2``, when it has grown by ``register_min_growth_m2`` and
  ``register_growth_frac`` since the last attempt, every ``register_retry_distance`` metres while
  no registration is accepted (the map changes as it is re-estimated; the interval doubles,
  ``register_retry_backoff``, after each retry on a map that has not grown, up to
  ``register_retry_max_distance``),
  ``register_recheck_distance`` metres after a match that the checks rejected while none is
  accepted (before the drift grows further; up to ``register_recheck_max`` quick rechecks in a
  row), every
  ``register_refine_distance`` metres after one is accepted (at most ``register_refine_max``
  times: the priors have corrected the map since), and when progress is obstructed (no
  progress for ``obstruction_time_s``, or :meth:`FloorPlanUpdater.notify_obstructed`);
- a registration is **accepted** when ok and not doubted by its method (``doubt``: the
  paper-faithful MFR flags its doubtful matches), its score and ambiguity pass, the registered plan's
  walls explain ``min_map_fit`` of the map's occupied cells, and the current scan relocalises
  against it consistently with the current estimate. A later registration that agrees with the
  accepted one refines it when it explains the data as well or better (``refine_by``: the map,
  or keyframe scans each relocalised on its own on both plans, which unlike the map are not
  shaped by the accepted plan's priors) and is otherwise only noted; one that disagrees
  replaces it only when it explains the current map clearly better (then the old plan's priors
  are removed and the keyframes that had them are relocalised against the new plan);
- after every ``relocation_distance_D`` metres travelled it **relocalises** the current scan
  (:mod:`frslam_graph.relocalisation`) and, when the match is good, unambiguous and passes a
  chi² gate against the current estimate (its marginal covariance plus the drift since the
  last accepted prior), adds it as a robust floor-plan prior;
- ``scale_refine_distance`` metres after a registration is accepted it fits the plan's scale
  along its two axes to keyframe scans (their poses free) and keeps the result when it explains
  them better; the interval doubles after each fit that changes nothing; with ``align_to_start``
  it then moves the plan rigidly so that the first keyframe's scan fits it at the graph's anchor
  (a registration made on a drifted map is placed to fit the drift, not the start);
- it removes priors later proven wrong (chi² of their residual after optimisation above
  ``remove_chi2``);
- with ``spread_over_scans`` a relocalisation, its prior, each relinearising iteration after it
  and the check of the priors (and each backfill) are steps run on the following scans
  (:meth:`FRSlam.defer`), so no scan pays for all of them; what is pending is finished before a
  registration, a scale fit or the next relocalisation;
- an ambiguous registration before any is accepted is judged with MFR's runner-up placements on
  the keyframe scans (``disambiguate_margin``).

Every decision is one event of the run's decision log (``ctx.log``; the updater's are
``updater.log``, :data:`UPDATE_KINDS`); nothing is printed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.errors import FrslamError
from frslam_graph.motion_model import compose, inverse, tangent_cov, to_matrix, vector_cov
from frslam_graph.plan_checks import (
    fit_plan_scale,
    matrix_disagreement,
    occupied_points,
    walls_through_free_space,
)
from frslam_graph.relocalisation import (
    Relocalisation,
    Relocaliser,
    RelocaliserParams,
    subsample,
)

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext
    from frslam_graph.backend.decisions import DecisionEvent, PriorRemoval

_COVER_CELL = 0.25  # m, coverage cells for the mapped-area estimate
# Cost model of the deferred steps (ms on one core; sizes, never a clock, so the schedule stays
# deterministic; right within about a factor of two): each step yields its estimate and the loop
# closer gets the rest of the scan's budget (FRSlam.defer). Measured on regime-A houses
# (tools/bench_backend.py): relocalisation median 5.8 / p90 8 ms, the gated prior 1.9 / 2.7,
# a relinearising iteration 1.4 / 4.9 (~600 keyframes), the prior check 1.0 / 2.4.
_MS_RELOCALISE = 7.0
_MS_PRIOR = 2.5
_MS_PER_KEYFRAME_SETTLE = 0.004
_MS_CHECK_PRIORS = 2.0


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


#: the kinds of decision the updater records (``register``: a registration was attempted, its
#: message says accepted / why not; ``prior_conflict``: many priors contradicted at once, none
#: removed; ``registration_retracted``: the grown map contradicts the accepted registration;
#: ``plan_refined``: the plan's scale fitted or the plan moved to the start, ``accepted`` says
#: whether it replaced the accepted matrix)
UPDATE_KINDS = frozenset(
    {
        "register",
        "registration_replaced",
        "registration_retracted",
        "relocalise",
        "prior_added",
        "prior_rejected",
        "prior_removed",
        "prior_conflict",
        "obstructed",
        "plan_refined",
    }
)


@dataclass
class _Accepted:
    """An accepted registration and what was built from it."""

    id: int
    registration: Any
    plan: Any  # FloorPlan in map metres
    relocaliser: Relocaliser
    map_fit: float


@dataclass
class _HeldReanchor:
    """Re-anchorings noted while on_finish holds them: the registrations whose priors are in the
    graph and why (done once, at the end)."""

    previous: list[_Accepted] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)

    def note(self, previous: list[_Accepted], why: str | None = None) -> None:
        self.previous.extend(p for p in previous if all(p.id != q.id for q in self.previous))
        if why:
            self.reasons.append(why)


class FloorPlanUpdater:
    """Paper Alg. 3 as an ``FRSlam.update_strategy`` (see the module docstring)."""

    def __init__(
        self,
        plan,
        config: UpdatesConfig | None = None,
        register_fn: Callable[[Any, Any], Any] | None = None,
    ) -> None:
        self.plan = plan
        self.config = cfg = config or UpdatesConfig()
        if register_fn is None:
            from frslam_graph.registration import register as register_fn  # noqa: PLC0415
        self.register_fn = register_fn
        self._decisions: Sequence[DecisionEvent] = ()  # the run's decision log (the context's)
        self.accepted: _Accepted | None = None
        self.params = RelocaliserParams(
            resolution=cfg.reloc_resolution,
            wall_offset=cfg.wall_half_thickness,
            window_xy=cfg.reloc_window_xy,
            window_theta=np.deg2rad(cfg.reloc_window_theta_deg),
            inlier_distance=cfg.reloc_inlier_distance,
            cov_inflation=cfg.reloc_cov_inflation,
            sigma_floor_xy=cfg.reloc_sigma_floor_xy,
            sigma_floor_theta=np.deg2rad(cfg.reloc_sigma_floor_theta_deg),
        )
        self._cover = _CoverageCells()
        self._dist = 0.0  # metres travelled (odometry)
        self._last_odom: np.ndarray | None = None
        self._area_at_attempt = 0.0
        self._dist_at_attempt = 0.0
        self._kf_dist: list[float] = []  # odometry distance travelled at each keyframe
        self._retries = 0
        self._stale_retries = 0  # retries in a row on a map that had not grown (backoff)
        self._recheck = False  # the last attempt matched but was rejected: retry soon
        self._recheck_run = 0  # quick retries in a row (register_recheck_max)
        self._refines = 0  # registrations triggered by register_refine_distance
        self._dist_at_scale = 0.0  # distance at the last scale refinement (or acceptance)
        self._scale_interval = 0.0  # metres to the next scale refinement (0: scale_refine_distance)
        self._pending_reg = None  # a registration waiting for confirmation (see confirm_after_m)
        # while on_finish holds re-anchoring, it is noted here and done once for all the changes
        self._held_reanchor: _HeldReanchor | None = None
        self._backfill: list[int] = []  # past keyframes to relocalise on the accepted plan
        self._backfill_anchor = 0.0  # distance at the nearest keyframe with a prior (backfill)
        self._attempts = 0
        self._dist_at_reloc = 0.0
        self._turn = 0.0  # radians turned (odometry)
        self._turn_at_reloc = 0.0
        self._dist_at_prior = 0.0
        self._obstructed = False
        self._obstruction_reported = False
        self._history: list[tuple[float, float]] = []  # (stamp, distance) per keyframe
        self._inconsistent_run = 0
        self._checks = 0
        self._next_id = 0
        self.timings: dict[str, float] = {"register": 0.0, "relocalise": 0.0, "coverage": 0.0}

    # ------------------------------------------------------------------ public
    @property
    def registered_plan(self):
        """The accepted registered plan (FloorPlan in map metres) or None."""
        return None if self.accepted is None else self.accepted.plan

    @property
    def registration(self):
        """The accepted :class:`~frslam_graph.registration.Registration` or None."""
        return None if self.accepted is None else self.accepted.registration

    @property
    def mapped_area(self) -> float:
        """Area (m²) of the coverage cells seen so far."""
        return float(self._cover.count) * _COVER_CELL**2

    def notify_obstructed(self) -> None:
        """The caller's motion is obstructed (paper Alg. 3: d <= 0): register and relocalise at
        the next keyframe."""
        self._obstructed = True

    @property
    def log(self) -> list[DecisionEvent]:
        """The updater's decisions (:data:`UPDATE_KINDS`) in the run's decision log."""
        return [e for e in self._decisions if e.kind in UPDATE_KINDS]

    def events(self, kind: str | None = None) -> list[DecisionEvent]:
        return [e for e in self.log if kind is None or e.kind == kind]

    def on_finish(self, ctx: BackendContext) -> None:
        """The end of an offline run (:meth:`FRSlam.finish`, before the final batch): with a
        registration accepted and ``final_refine`` on, one more registration on the complete map
        (it refines the accepted one when it agrees and explains the data as well or better, as
        any later one) and the scale refinement, whenever the schedule last ran them. The plan the
        run ends with then depends less on when its refinements happened (a rejected wrong draw
        or an attempt on a small map no longer leaves an unrefined plan behind)."""
        self._decisions = ctx.log
        cfg = self.config
        if not cfg.enabled or self.plan is None or self.accepted is None or not cfg.final_refine:
            return  # (a registration accepted: the graph has keyframes)
        self._finish_steps(ctx)
        last = ctx.keyframe(len(ctx.graph) - 1)
        # the registration, the scale and the move to the start may each change the plan: its
        # priors are relocalised once, on the plan the run ends with (each re-anchoring
        # relocalises every prior: ~7 s on a 200 m run)
        self._held_reanchor = _HeldReanchor()
        try:
            self._register(ctx, last, "end of the run: final refinement")
            self._finish_steps(ctx)
            if self.accepted is not None and cfg.scale_refine_distance > 0.0:
                # the run's last word on the scale: any gain on the keyframe scans of the whole
                # run (the margin keeps a run's plan from changing back and forth; no later)
                self._refine_scale(ctx, last, final=True)
                if cfg.align_to_start:
                    self._align_to_start(ctx, last)
        finally:
            held, self._held_reanchor = self._held_reanchor, None
        if held.reasons and self.accepted is not None:
            # the accepted registration's own priors too: those placed while holding (the
            # registration's first prior, the pending relocalisations) are on an earlier plan
            held.note([self.accepted])
            self._reanchor(ctx, held.previous, "; ".join(held.reasons))
        self._finish_steps(ctx)

    def on_keyframe(self, ctx: BackendContext, keyframe) -> None:
        """Called by FRSlam after each keyframe is in the graph."""
        self._decisions = ctx.log
        cfg = self.config
        if not cfg.enabled or self.plan is None:
            return
        t0 = time.perf_counter()
        i = keyframe.index
        if self._last_odom is not None:
            self._dist += float(np.hypot(*(keyframe.pose_odom[:2] - self._last_odom[:2])))
            dth = keyframe.pose_odom[2] - self._last_odom[2]
            self._turn += abs(float((dth + np.pi) % (2 * np.pi) - np.pi))
        self._last_odom = np.asarray(keyframe.pose_odom, float).copy()
        self._kf_dist.append(self._dist)
        points = ctx.keyframe_scans()[0][i]
        self._update_coverage(keyframe.pose_map, points)
        self.timings["coverage"] += time.perf_counter() - t0
        obstructed = self._check_obstruction(ctx, keyframe)

        area = self.mapped_area
        reason, local, quick = None, False, False
        if self._attempts < cfg.max_registrations:
            if self._attempts == 0:
                if area >= cfg.first_register_area_m2:
                    reason = f"mapped area {area:.1f} m² reached the first-registration threshold"
            else:
                grown = area - self._area_at_attempt
                if grown >= cfg.register_min_growth_m2 and grown >= cfg.register_growth_frac * max(
                    self._area_at_attempt, 1e-9
                ):
                    reason = f"mapped area grew by {grown:.1f} m² to {area:.1f} m²"
                    self._stale_retries = 0
                elif obstructed and grown >= 1.0:
                    reason = "progress obstructed"
                elif (
                    self._recheck  # set only while no registration is accepted (_register)
                    and cfg.register_recheck_distance > 0.0
                    and self._dist - self._dist_at_attempt >= cfg.register_recheck_distance
                ):
                    reason = (
                        f"the last registration matched but was rejected; retry after "
                        f"{self._dist - self._dist_at_attempt:.0f} m"
                    )
                    quick = True
                elif self.accepted is None and self._dist - self._dist_at_attempt >= self._retry_distance():
                    reason = f"no registration accepted yet; retry after {self._dist - self._dist_at_attempt:.0f} m"
                    # the map has not grown since the last attempt: the next retry waits longer
                    self._stale_retries = self._stale_retries + 1 if grown < cfg.register_min_growth_m2 else 0
                    # the whole map may have drifted too far to match: alternate with the map of
                    # the last local_map_distance metres
                    local = self._retries % 2 == 1 and self._dist > cfg.local_map_distance
                    self._retries += 1
                elif (
                    self.accepted is not None
                    and cfg.register_refine_distance > 0.0
                    and self._refines < cfg.register_refine_max
                    and self._dist - self._dist_at_attempt >= cfg.register_refine_distance
                ):
                    # the priors have corrected the map since: a registration on it may refine
                    # the accepted one (refine_on_agreement) or show it wrong (retraction)
                    reason = f"registration accepted; register again after {self._dist - self._dist_at_attempt:.0f} m"
                    self._refines += 1
                elif self._inconsistent_run >= 5:
                    reason = (
                        f"{self._inconsistent_run} relocalisations in a row inconsistent with the estimate"
                    )
                    self._inconsistent_run = 0
        if reason is not None:
            self._finish_steps(ctx)
            self._register(ctx, keyframe, reason, local, quick)
        elif self.accepted is not None:
            if cfg.scale_refine_distance > 0.0 and self._dist - self._dist_at_scale >= max(
                self._scale_interval, cfg.scale_refine_distance
            ):
                self._finish_steps(ctx)
                self._dist_at_scale = self._dist
                changed = self._refine_scale(ctx, keyframe)
                if cfg.align_to_start:
                    changed = self._align_to_start(ctx, keyframe) or changed
                # nothing to change: look again later (the map grows, rooms are added)
                self._scale_interval = (
                    cfg.scale_refine_distance
                    if changed
                    else 2.0 * max(self._scale_interval, cfg.scale_refine_distance)
                )
            elif obstructed:
                self._relocalise_current(ctx, keyframe, "obstructed")
            elif self._dist - self._dist_at_reloc >= cfg.relocation_distance_D:
                self._relocalise_current(ctx, keyframe, "relocation distance")
            elif self._turn - self._turn_at_reloc >= np.deg2rad(cfg.relocation_angle_deg):
                self._relocalise_current(ctx, keyframe, "relocation angle")
        if self.accepted is not None and self._backfill and not ctx.deferred.pending:
            self._run_backfill(ctx, cfg.backfill_per_keyframe)  # as fast as the steps get done

    def _retry_distance(self) -> float:
        """Metres after an attempt before a retry while none is accepted (see
        ``register_retry_backoff``)."""
        cfg = self.config
        d = cfg.register_retry_distance * cfg.register_retry_backoff**self._stale_retries
        return min(d, max(cfg.register_retry_max_distance, cfg.register_retry_distance))

    # ------------------------------------------------------------------ events
    def _event(
        self,
        ctx: BackendContext,
        stamp: float,
        kind: str,
        reason: str,
        keyframe: int | None = None,
        accepted: bool | None = None,
        **numbers: float,
    ) -> DecisionEvent:
        data: dict[str, Any] = {k: _num(v) for k, v in numbers.items()}
        if accepted is not None:
            data["accepted"] = accepted
        return ctx.log.record(kind, reason, stamp=stamp, keyframe=keyframe, **data)

    # ------------------------------------------------------------------ coverage / triggers
    def _update_coverage(self, pose: np.ndarray, points: np.ndarray) -> None:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not len(pts):
            return
        if len(pts) > 180:
            pts = pts[np.linspace(0, len(pts) - 1, 180).round().astype(np.intp)]
        t = np.linspace(0.0, 1.0, 41)
        samples = (pts[:, None, :] * t[None, :, None]).reshape(-1, 2)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        wx = c * samples[:, 0] - s * samples[:, 1] + pose[0]
        wy = s * samples[:, 0] + c * samples[:, 1] + pose[1]
        kx = np.floor(wx / _COVER_CELL).astype(np.int64)
        ky = np.floor(wy / _COVER_CELL).astype(np.int64)
        self._cover.add(kx, ky)

    def _check_obstruction(self, ctx, keyframe) -> bool:
        cfg = self.config
        stamp = float(keyframe.stamp)
        self._history.append((stamp, self._dist))
        obstructed = self._obstructed
        if len(self._history) >= 2:
            t_prev, d_prev = self._history[-2]
            if stamp - t_prev >= cfg.obstruction_time_s:
                obstructed = True  # stood still long enough to make no keyframe
        # progress over the last obstruction_time_s
        old = [(t, d) for t, d in self._history if stamp - t >= cfg.obstruction_time_s]
        if old:
            t_o, d_o = old[-1]
            if (self._dist - d_o) < cfg.obstruction_speed * (stamp - t_o):
                obstructed = True
            self._history = self._history[len(old) - 1 :]
        if obstructed and not self._obstruction_reported:
            self._finish_steps(ctx)  # what it triggers drains them anyway: their events first
            self._event(ctx, stamp, "obstructed", "no progress: register and relocalise", keyframe.index)
        self._obstruction_reported = obstructed
        self._obstructed = False
        return obstructed

    # ------------------------------------------------------------------ registration
    def _register(self, ctx, keyframe, reason: str, local: bool = False, quick: bool = False) -> None:
        """Register the plan on the map and act on the verdict. ``quick``: this attempt is a
        quick recheck (``register_recheck_distance``): it counts towards ``register_recheck_max``
        in a row; any other trigger (the map grew, a retry, a refinement) starts a new run."""
        cfg = self.config
        t0 = time.perf_counter()
        self._attempts += 1
        self._recheck = False
        self._recheck_run = self._recheck_run + 1 if quick else 0
        area = self.mapped_area
        self._area_at_attempt = area
        self._dist_at_attempt = self._dist
        stamp, i = float(keyframe.stamp), keyframe.index
        if local:
            grid = self._local_grid(ctx)
            reason += f"; on the map of the last {cfg.local_map_distance:.0f} m"
        else:
            grid = ctx.occupancy_grid(cfg.map_resolution, free_space=True)
        if self.accepted is not None:
            self._recheck_accepted(ctx, keyframe, grid)
        try:
            reg = self.register_fn(self.plan, grid)
        except FrslamError as exc:
            self._event(ctx, stamp, "register", f"{reason}; registration failed: {exc}", i, False, area=area)
            self.timings["register"] += time.perf_counter() - t0
            return
        nums = {"area": area, "score": float(reg.score), "ambiguity": float(reg.ambiguity)}
        verdict = self._judge(ctx, keyframe, reg, grid, nums, reason)
        self.timings["register"] += time.perf_counter() - t0
        if verdict is None:
            # a match the checks rejected (wrong, or right on a map that drifted) gets a quick
            # retry on a map a few metres larger, before the drift grows any further (up to
            # register_recheck_max in a row: each retry is a new draw on a larger map). Not with
            # one accepted: quick retries of the refinements drew more wrong matches and changed
            # the runs' paths more than the refinements gained (regime C, 20 houses x 3 corruption
            # seeds: runs within 10 % of the clean run 55 -> 48 of 60; regime A house 4 worse)
            self._recheck = reg.ok and self.accepted is None and self._recheck_run < cfg.register_recheck_max
            return
        accepted, relocaliser, reloc = verdict
        msg, kind = f"{reason}; accepted", "register"
        if self.accepted is not None:
            msg, kind = f"{reason}; replaces registration {self.accepted.id}", "registration_replaced"
        self._event(ctx, stamp, kind, msg, i, True, **nums)
        previous = self.accepted
        self.accepted = accepted
        self._dist_at_scale = self._dist
        self._scale_interval = 0.0
        if previous is not None:
            self._reanchor(ctx, previous)
        self._try_prior(ctx, keyframe, reloc, "registration accepted")
        self._dist_at_reloc = self._dist
        self._turn_at_reloc = self._turn
        self._queue_backfill(ctx, i)

    def _recheck_accepted(self, ctx, keyframe, grid) -> None:
        """Retract the accepted registration when the grown map contradicts it (its walls cross
        space the robot has seen free): its priors are removed and the next registration is
        judged as a first one."""
        cfg = self.config
        acc = self.accepted
        crossing = walls_through_free_space(acc.relocaliser, grid, self._tolerances()[1])
        if crossing <= cfg.retract_walls_in_free_space:
            return
        why = (
            f"registration {acc.id} contradicted by the map: {crossing:.0%} of its observed walls "
            f"cross free space > {cfg.retract_walls_in_free_space:.0%}"
        )
        self._event(
            ctx,
            keyframe.stamp,
            "registration_retracted",
            why,
            keyframe.index,
            False,
            walls_in_free_space=crossing,
        )
        self.accepted = None
        self._remove_priors_of(ctx, acc, why, "wrong")
        self._dist_at_prior = 0.0  # the trajectory is back on odometry: gate loosely

    # ------------------------------------------------------------------ backfill
    def _queue_backfill(self, ctx, i: int) -> None:
        """Queue the keyframes before ``i`` (newest first, one per ``relocation_distance_D``
        metres) that have no prior of the accepted registration: relocalised on the plan a few
        per keyframe, each prior pulling its older neighbours closer before their turn, so the
        map drawn before the registration is corrected too."""
        cfg = self.config
        if not cfg.backfill or self.accepted is None:
            self._backfill = []
            return
        tag = f"reloc:reg{self.accepted.id}"
        have = {h.keyframe for h in ctx.graph.priors() if h.source == tag}
        d = self._kf_dist
        here = d[i] if i < len(d) else self._dist
        queue, last = [], here
        for k in range(min(i, len(d)) - 1, -1, -1):
            if last - d[k] >= cfg.relocation_distance_D and k not in have:
                queue.append(k)
                last = d[k]
        self._backfill = queue
        self._backfill_anchor = here

    def _run_backfill(self, ctx, n: int) -> None:
        """Relocalise the next ``n`` queued keyframes and add their priors (as steps)."""
        for _ in range(min(n, len(self._backfill))):
            self._later(ctx, self._backfill_steps(ctx, self._backfill.pop(0)))

    def _backfill_steps(self, ctx, k: int) -> Iterator[None]:
        kf = ctx.keyframe(k)  # its estimate when the step runs
        t0 = time.perf_counter()
        reloc = self.accepted.relocaliser.relocalise(ctx.keyframe_scans()[0][k], kf.pose_map)
        self.timings["relocalise"] += time.perf_counter() - t0
        yield _MS_RELOCALISE
        drift = max(self._backfill_anchor - self._kf_dist[k], 0.0)
        added, cost = yield from self._prior_steps(ctx, kf, reloc, "backfill", drift=drift, backfill=True)
        if added:
            self._backfill_anchor = self._kf_dist[k]
        yield cost

    def _local_grid(self, ctx):
        """Occupancy grid (map frame) of the keyframes of the last ``local_map_distance`` metres
        travelled: less drift accumulated inside it than in the whole map."""
        from frslam_graph.mapping import FREE_SPACE_WEIGHTS, occupancy_grid  # noqa: PLC0415

        d = np.asarray(self._kf_dist)
        keep = np.nonzero(d >= self._dist - self.config.local_map_distance)[0]
        pts, origins = ctx.keyframe_scans()
        est = ctx.graph.estimates()
        return occupancy_grid(
            est[keep],
            [pts[k] for k in keep],
            [origins[k] for k in keep],
            self.config.map_resolution,
            **FREE_SPACE_WEIGHTS,
        )

    def _tolerances(self) -> tuple[float, float]:
        """(map-fit distance, free-space margin) in metres, grown with the distance travelled
        since the last accepted prior: how far the map may have drifted from the plan."""
        cfg = self.config
        grow = cfg.check_growth_per_m * max(self._dist - self._dist_at_prior, 0.0)
        fit = min(cfg.map_fit_distance + grow, max(cfg.map_fit_distance_max, cfg.map_fit_distance))
        margin = min(cfg.free_space_margin + grow, max(cfg.free_space_margin_max, cfg.free_space_margin))
        return fit, margin

    def _remove_priors_of(self, ctx, acc: _Accepted, why: str, cause: PriorRemoval) -> list:
        tag = f"reloc:reg{acc.id}"
        handles = [h for h in ctx.graph.priors() if h.source == tag]
        ctx.remove_priors(handles, reason=why, cause=cause)  # one graph update for all of them
        return handles

    def _judge(self, ctx, keyframe, reg, grid, nums: dict[str, float], trigger: str = ""):
        """Accept / reject a registration; returns (accepted, relocaliser, relocalisation) or None."""
        cfg = self.config
        stamp, i = float(keyframe.stamp), keyframe.index

        def reject(why: str) -> None:
            self._event(ctx, stamp, "register", f"{trigger}; {why}" if trigger else why, i, False, **nums)

        if not reg.ok:
            return reject(f"registration failed: {reg.reason or 'no match'}")
        if reg.doubt:  # the method's own verdict (the paper-faithful MFR's): never a prior
            return reject(f"doubtful match: {reg.doubt}")
        if reg.score < cfg.min_score:
            return reject(f"score {reg.score:.2f} < {cfg.min_score:.2f}")
        relocaliser = None  # the disambiguation's, when it picked a placement: built once
        if reg.ambiguity > cfg.max_ambiguity:
            picked = self._disambiguate(ctx, reg, grid, nums)
            if picked is None:
                why = f"ambiguous: {reg.ambiguity:.2f} > {cfg.max_ambiguity:.2f}"
                if "placements_map_fit" in nums:
                    why += (
                        f"; no placement's walls explain the map ({nums['placements_map_fit']:.0%} < "
                        f"{cfg.min_map_fit:.0%})"
                    )
                return reject(why)
            reg, relocaliser = picked
        try:
            if relocaliser is None:
                relocaliser = Relocaliser(reg.apply(self.plan), self.params)
            plan_map = relocaliser.plan
        except (FrslamError, ValueError) as exc:
            return reject(f"registered plan unusable: {exc}")
        occ = occupied_points(grid)
        fit_tol, margin = self._tolerances()
        fit = relocaliser.fit_points(occ, fit_tol)
        nums["map_fit"] = fit
        acc = self.accepted
        if acc is not None and cfg.refine_on_agreement and cfg.refine_by == "scans":
            disp = matrix_disagreement(self.plan, acc.registration.matrix, reg.matrix)
            nums["disagreement"] = disp
            if disp <= cfg.agree_tol:
                # the map was drawn at estimates the accepted plan's priors pulled onto it (its
                # fit is biased towards that plan): compare the two on the keyframe scans, each
                # relocalised on its own
                q_new = self._scan_fit(ctx, relocaliser)
                q_old = self._scan_fit(ctx, acc.relocaliser)
                nums.update(scan_fit=q_new, accepted_scan_fit=q_old)
                if q_new > q_old + cfg.refine_scan_margin:
                    better = f"the keyframe scans better ({q_new:.1%} vs {q_old:.1%})"
                elif q_new >= q_old - cfg.refine_scan_margin:
                    # the scans cannot tell (each scan absorbs a rigid offset of the plan): the
                    # map decides, as with refine_by="map"
                    old_fit = acc.relocaliser.fit_points(occ, fit_tol)
                    nums["accepted_map_fit"] = old_fit
                    if fit < old_fit:
                        return reject(
                            f"agrees with registration {acc.id} (RMS {disp:.2f} m), explains the keyframe "
                            f"scans as well ({q_new:.1%} vs {q_old:.1%}) and the map no better "
                            f"({fit:.0%} vs {old_fit:.0%}); kept"
                        )
                    better = f"the keyframe scans as well and the map as well or better ({fit:.0%} vs {old_fit:.0%})"
                else:
                    return reject(
                        f"agrees with registration {acc.id} (RMS {disp:.2f} m) and explains the "
                        f"keyframe scans worse ({q_new:.1%} vs {q_old:.1%}); kept"
                    )
                return self._refine(
                    ctx, stamp, i, reg, plan_map, relocaliser, fit, nums, trigger, disp, better
                )
        if fit < cfg.min_map_fit:
            return reject(f"plan walls explain {fit:.0%} of the map's occupied cells < {cfg.min_map_fit:.0%}")
        crossing = walls_through_free_space(relocaliser, grid, margin)
        nums["walls_in_free_space"] = crossing
        if crossing > cfg.max_walls_in_free_space:
            return reject(
                f"{crossing:.0%} of the plan's observed walls cross free space in the map "
                f"> {cfg.max_walls_in_free_space:.0%}"
            )
        if acc is not None:
            disp = matrix_disagreement(self.plan, acc.registration.matrix, reg.matrix)
            old_fit = acc.relocaliser.fit_points(occ, fit_tol)
            nums.update(disagreement=disp, accepted_map_fit=old_fit)
            if disp <= cfg.agree_tol and fit < old_fit + cfg.switch_margin:
                if cfg.refine_on_agreement and fit >= old_fit:
                    return self._refine(
                        ctx,
                        stamp,
                        i,
                        reg,
                        plan_map,
                        relocaliser,
                        fit,
                        nums,
                        trigger,
                        disp,
                        f"the map as well or better ({fit:.0%} vs {old_fit:.0%})",
                    )
                return reject(f"agrees with registration {acc.id} (RMS {disp:.2f} m); kept")
            if fit < old_fit + cfg.switch_margin:
                return reject(
                    f"disagrees with registration {acc.id} (RMS {disp:.2f} m) and explains "
                    f"the map no better ({fit:.0%} vs {old_fit:.0%})"
                )
        points = ctx.keyframe_scans()[0][i]
        reloc = relocaliser.relocalise(points, keyframe.pose_map)
        nums.update(reloc_score=reloc.score, reloc_ambiguity=reloc.ambiguity)
        if not reloc.ok or reloc.score < cfg.reloc_min_score:
            return reject(f"current scan does not fit the registered plan (inliers {reloc.score:.0%})")
        if cfg.min_scan_fit > 0.0:
            # the keyframe scans of the whole run, each relocalised on its own: the plan of another
            # building (or a wrong placement) that the map checks let through by a small margin
            # explains them poorly
            q = nums["scan_fit"] if "scan_fit" in nums else self._scan_fit(ctx, relocaliser)
            nums["scan_fit"] = q
            if q < cfg.min_scan_fit:
                return reject(
                    f"the keyframe scans do not fit the registered plan ({q:.1%} < {cfg.min_scan_fit:.0%})"
                )
        if self.accepted is None:
            chi2 = self._gate_chi2(ctx, keyframe, reloc)
            nums["chi2"] = chi2
            if chi2 > cfg.inconsistent_chi2:
                return reject(
                    f"inconsistent with the trajectory: chi2 {chi2:.1f} > {cfg.inconsistent_chi2:.1f}"
                )
            travelled = self._dist - self._dist_at_prior
            if travelled > cfg.confirm_after_m:
                # the drift allowance has made the chi2 gate weak: a second registration that
                # agrees must confirm this one (as for loop closures with large corrections)
                pending, self._pending_reg = self._pending_reg, reg
                if pending is None:
                    return reject(
                        f"{travelled:.0f} m travelled without a prior: waiting for a second "
                        "registration that agrees"
                    )
                disp = matrix_disagreement(self.plan, pending.matrix, reg.matrix)
                nums["disagreement"] = disp
                if disp > cfg.agree_tol:
                    return reject(
                        f"{travelled:.0f} m travelled without a prior: disagrees with the previous "
                        f"registration (RMS {disp:.2f} m); waiting for one that agrees"
                    )
        self._pending_reg = None
        acc = _Accepted(self._next_id, reg, plan_map, relocaliser, fit)
        self._next_id += 1
        return acc, relocaliser, reloc

    def _disambiguate(self, ctx, reg, grid, nums: dict[str, float]):
        """An ambiguous registration: its placement and the registration's runner-up placements
        (``reg.details["alternatives"]``, MFR's) judged on the keyframe scans, each relocalised on
        its own (which a drifted map cannot bias). Returns the registration of the placement that
        explains them clearly best (by ``disambiguate_margin``, and at least ``min_scan_fit``)
        with its relocaliser, else None; ``nums`` get the two best fits.

        The placement picked is judged next by its map fit (``min_map_fit``, the first check after
        this one; no registration is accepted here). When no placement passes it, the verdict is a
        rejection whichever one the scans would pick: the scan fits (most of the cost, ~1-2 s
        with the plan of another building) are skipped and ``nums["placements_map_fit"]`` says why."""
        cfg = self.config
        alts = [np.asarray(a["matrix"], float) for a in (reg.details or {}).get("alternatives", [])]
        if cfg.disambiguate_margin <= 0.0 or not alts or self.accepted is not None:
            return None
        matrices = [np.asarray(reg.matrix, float), *alts]
        relocalisers: list[Relocaliser | None] = []
        for m in matrices:
            try:
                relocalisers.append(Relocaliser(type(reg).from_matrix(m).apply(self.plan), self.params))
            except (FrslamError, ValueError):
                relocalisers.append(None)  # the picked one would be "unusable": rejected too
        occ = occupied_points(grid)
        fit_tol = self._tolerances()[0]
        best_map_fit = max(r.fit_points(occ, fit_tol) if r is not None else 0.0 for r in relocalisers)
        if best_map_fit < cfg.min_map_fit:
            nums["placements_map_fit"] = best_map_fit
            return None
        fits = [self._scan_fit(ctx, r) if r is not None else 0.0 for r in relocalisers]
        order = np.argsort(fits)[::-1]
        best, second = float(fits[order[0]]), float(fits[order[1]])
        nums.update(ambiguous_scan_fit=best, runner_up_scan_fit=second, placement=int(order[0]))
        if best < max(cfg.min_scan_fit, second + cfg.disambiguate_margin):
            return None
        nums["scan_fit"] = best
        picked = type(reg).from_matrix(
            matrices[order[0]],
            score=reg.score,
            ambiguity=second / max(best, 1e-9),
            method=f"{reg.method}+scans",
            rooms=reg.rooms,
        )
        return picked, relocalisers[order[0]]

    def _refine(self, ctx, stamp, i, reg, plan_map, relocaliser, fit, nums, trigger, disp, better) -> None:
        """An agreeing registration explains the data as well or better: the same placement fitted
        to more data; later relocalisations use it (earlier priors stay: they agree within
        agree_tol)."""
        acc = self.accepted
        self._event(
            ctx,
            stamp,
            "register",
            f"{trigger}; agrees with registration {acc.id} (RMS {disp:.2f} m) and explains {better}; refined",
            i,
            False,
            **nums,
        )
        self.accepted = _Accepted(acc.id, reg, plan_map, relocaliser, fit)

    def _scan_sample(self) -> np.ndarray:
        """Indices of up to ``refine_scan_samples`` keyframes spread evenly over the run."""
        n = len(self._kf_dist)
        return np.unique(
            np.linspace(0, n - 1, min(n, self.config.refine_scan_samples)).round().astype(np.intp)
        )

    def _refine_scale(self, ctx, keyframe, final: bool = False) -> bool:
        """Refine the accepted plan's scale along its two axes on keyframe scans.

        The keyframe scans (spread over the run) are relocalised on the accepted plan; then their
        poses and the plan's two scale factors (about the scans' centroid, in plan axes) are
        fitted jointly to the plan's distance field (Levenberg-Marquardt, Tukey kernel): a
        scale error shows inside single scans (two walls of a room cannot both fit), which their
        poses cannot absorb, unlike a rigid offset. A registration made on a small or drifted map
        can be a few per cent off in scale; the priors then bend the map onto it, so a
        registration on the map would repeat the error. The refined plan replaces the accepted
        one (same id; its priors are relocalised on it when it moves them by more than
        ``scale_reanchor_xy``) when it explains the scans better (``scale_refine_margin``). With
        ``final`` (the end of the run: no later check) any gain on the scans is enough and all
        its priors are relocalised on the refined plan. Returns
        whether it did.
        """
        cfg = self.config
        acc = self.accepted
        t0 = time.perf_counter()
        rel = acc.relocaliser
        p = rel.params
        scans = ctx.keyframe_scans()[0]
        pts, poses, soft = [], [], []
        for k in self._scan_sample():
            r = rel.relocalise(scans[k], ctx.keyframe(int(k)).pose_map)
            soft.append(r.soft_score)
            if r.ok and r.score >= cfg.reloc_min_score:
                pts.append(subsample(np.asarray(scans[k], float).reshape(-1, 2), p.voxel, p.max_points))
                poses.append(r.pose)
        stamp, i = float(keyframe.stamp), keyframe.index

        def kept(why: str, **data) -> bool:
            self.timings["relocalise"] += time.perf_counter() - t0
            self._event(ctx, stamp, "plan_refined", why, i, False, **data)
            return False

        if len(poses) < 3:
            return kept(f"scale: {len(poses)} scans fit the plan; too few")
        m = np.asarray(acc.registration.matrix, float)
        lin, t = m[:2, :2], m[:2, 2]
        lin_inv = np.linalg.inv(lin)
        poses = np.asarray(poses)
        centre = np.mean((poses[:, :2] - t) @ lin_inv.T, axis=0)  # plan units
        log_s = fit_plan_scale(rel.field, pts, poses, lin, t, centre, p.truncation, cfg.scale_refine_sigma)
        f = np.exp(log_s)
        nums = {"scale_x": f[0], "scale_y": f[1], "scans": len(pts)}
        if np.max(np.abs(log_s)) > np.log1p(cfg.scale_refine_max):
            return kept(f"scale: factors {np.round(f, 4).tolist()} out of range", **nums)
        if np.max(np.abs(log_s)) < cfg.scale_refine_min:
            return kept(f"scale x{f[0]:.4f} / x{f[1]:.4f}: below {cfg.scale_refine_min:.1%}; kept", **nums)
        fix = np.eye(3)
        fix[:2, :2] = np.diag(f)
        fix[:2, 2] = centre - f * centre
        reg = acc.registration
        new = type(reg).from_matrix(
            m @ fix, score=reg.score, ambiguity=reg.ambiguity, method=f"{reg.method}+scale", rooms=reg.rooms
        )
        try:
            plan_map = new.apply(self.plan)
            relocaliser = Relocaliser(plan_map, self.params)
        except (FrslamError, ValueError) as exc:
            return kept(f"scale: refined plan unusable: {exc}", **nums)
        t_fit = time.perf_counter()
        q_new, q_old = self._scan_fit(ctx, relocaliser), float(np.mean(soft))
        nums.update(scan_fit=q_new, accepted_scan_fit=q_old, time_s=time.perf_counter() - t0)
        t0 += time.perf_counter() - t_fit  # _scan_fit counted its own time
        if q_new <= q_old + (0.0 if final else cfg.scale_refine_margin):
            return kept(
                f"scale x{f[0]:.4f} / x{f[1]:.4f} explains the keyframe scans no better "
                f"({q_new:.1%} vs {q_old:.1%}); kept",
                **nums,
            )
        self.timings["relocalise"] += time.perf_counter() - t0
        self._event(
            ctx,
            stamp,
            "plan_refined",
            f"scale x{f[0]:.4f} / x{f[1]:.4f} explains the keyframe scans better ({q_new:.1%} vs {q_old:.1%}); refined",
            i,
            True,
            **nums,
        )
        self.accepted = _Accepted(acc.id, new, plan_map, relocaliser, acc.map_fit)
        # the priors placed on the old scale are as far off as the change moves their keyframes:
        # relocalise those keyframes on the refined plan
        tag = f"reloc:reg{acc.id}"
        xy = np.asarray([h.pose[:2] for h in ctx.graph.priors() if h.source == tag]).reshape(-1, 2)
        moved = (xy - t) @ lin_inv.T @ (m @ fix)[:2, :2].T + (m @ fix)[:2, 2] - xy
        if len(xy) and (final or float(np.max(np.hypot(moved[:, 0], moved[:, 1]))) > cfg.scale_reanchor_xy):
            self._reanchor(ctx, acc, f"registration {acc.id} rescaled")
        return True

    def _align_to_start(self, ctx, keyframe) -> bool:
        """Move the accepted plan rigidly so that the first keyframe's scan fits it at the first
        keyframe's pose (the graph's anchor: ``map`` is the odom frame of the first pose). A
        registration made on a drifted map is placed consistently with the drifted map, not with
        the start; its priors then bend the early trajectory against the anchor. Returns whether
        the plan moved (its priors are then relocalised on it)."""
        cfg = self.config
        acc = self.accepted
        stamp, i = float(keyframe.stamp), keyframe.index
        # the anchor prior's pose, not keyframe 0's estimate: the plan's priors pull that
        # estimate, so fitting the plan to it would chase its own pull (the plan moving back
        # and forth at every check, each time re-anchoring all its priors)
        anchor = ctx.graph.anchor
        start = anchor.pose if anchor is not None and anchor.active else ctx.keyframe(0).pose_map
        r = acc.relocaliser.relocalise(
            ctx.keyframe_scans()[0][0],
            start,
            cfg.reloc_window_max_xy,
            np.deg2rad(cfg.reloc_window_max_theta_deg),
        )
        d = compose(start, inverse(r.pose))  # plan-consistent pose -> anchored pose
        nums = {"dx": d[0], "dy": d[1], "dtheta": d[2], "score": r.score, "ambiguity": r.ambiguity}
        moved = float(np.hypot(*(compose(d, r.pose)[:2] - r.pose[:2])))

        def kept(why: str) -> bool:
            self._event(ctx, stamp, "plan_refined", f"start: {why}", i, False, **nums)
            return False

        if not r.ok or r.score < cfg.reloc_min_score or r.ambiguity > cfg.reloc_max_ambiguity:
            return kept("the first scan does not fit the plan unambiguously; kept")
        # d's translation includes the lever arm of its rotation about the map origin: judge the
        # move by its rotation and by how far the scan's pose moves; and move only when the fit
        # at the anchor gets clearly better (a centimetre of matching noise must not flip the
        # plan back and forth at every check)
        gain = r.soft_score - acc.relocaliser.evaluate(ctx.keyframe_scans()[0][0], start)[1]
        nums["gain"] = gain
        small = abs(d[2]) < np.deg2rad(cfg.align_min_theta_deg) and moved < cfg.align_min_xy
        if small or gain < cfg.align_min_gain:
            return kept("the first scan fits the plan at the anchor; kept")
        reg = acc.registration
        new = type(reg).from_matrix(
            to_matrix(d) @ np.asarray(reg.matrix, float),
            score=reg.score,
            ambiguity=reg.ambiguity,
            method=f"{reg.method}+start",
            rooms=reg.rooms,
        )
        try:
            plan_map = new.apply(self.plan)
            relocaliser = Relocaliser(plan_map, self.params)
        except (FrslamError, ValueError) as exc:
            return kept(f"moved plan unusable: {exc}")
        self._event(
            ctx,
            stamp,
            "plan_refined",
            f"start: plan moved by {np.hypot(d[0], d[1]):.2f} m / {np.rad2deg(d[2]):.2f} deg so that the first "
            "scan fits it at the anchor",
            i,
            True,
            **nums,
        )
        self.accepted = _Accepted(acc.id, new, plan_map, relocaliser, acc.map_fit)
        self._reanchor(ctx, acc, f"registration {acc.id} moved to the start")
        return True

    def _scan_fit(self, ctx, relocaliser: Relocaliser) -> float:
        """Mean soft score of keyframe scans, each relocalised on its own against the plan (in a
        window around its estimate): how well the plan explains the scans, unlike the map fit not
        biased towards the plan whose priors shaped the map."""
        if not self._kf_dist:
            return 0.0
        ks = self._scan_sample()
        scans = ctx.keyframe_scans()[0]
        t0 = time.perf_counter()
        soft = [relocaliser.relocalise(scans[k], ctx.keyframe(int(k)).pose_map).soft_score for k in ks]
        self.timings["relocalise"] += time.perf_counter() - t0
        return float(np.mean(soft))

    def _reanchor(self, ctx, previous: _Accepted | list[_Accepted], why: str | None = None) -> None:
        """Remove the replaced registration's priors (or those of several); relocalise those
        keyframes on the accepted plan. While on_finish holds re-anchoring, only note it."""
        prev = previous if isinstance(previous, list) else [previous]
        why = why or f"registration {prev[0].id} replaced"
        if self._held_reanchor is not None:  # on_finish: once, at the end, for all involved
            self._held_reanchor.note(prev, why)
            return
        handles = [h for p in prev for h in self._remove_priors_of(ctx, p, why, "re-anchored")]
        scans = ctx.keyframe_scans()[0]
        added = False
        for h in handles:
            kf = ctx.keyframe(h.keyframe)
            reloc = self.accepted.relocaliser.relocalise(scans[h.keyframe], kf.pose_map)
            added |= self._try_prior(
                ctx, kf, reloc, "re-anchored on the new registration", drift=self._dist, settle=False
            )
        if added:  # one settle for all of them, not one per prior
            ctx.graph.settle()

    # ------------------------------------------------------------------ relocalisation
    @staticmethod
    def _finish_steps(ctx: BackendContext) -> None:
        """Run the steps still pending (before work that changes the plan or needs them done)."""
        ctx.deferred.run_all()

    def _later(self, ctx, steps: Iterator[Any]) -> None:
        """Run a step generator: one step per following scan (``ctx.defer``) with
        ``spread_over_scans``, else all of it now."""
        if self.config.spread_over_scans:
            ctx.deferred.defer(steps)
        else:
            for _ in steps:
                pass

    def _relocalise_current(self, ctx, keyframe, why: str) -> None:
        """Relocalise the keyframe's scan (its pose and points as they are now), then gate and
        add its prior, settle the graph and check the priors, as steps (:meth:`_later`)."""
        points = ctx.keyframe_scans()[0][keyframe.index]
        cfg = self.config
        # the search window covers the drift since the last accepted prior (3 sigma of the gate's
        # drift model), so a run of rejected relocalisations does not lose the plan for good
        travelled = self._dist - self._dist_at_prior
        wxy = min(max(cfg.reloc_window_xy, 3.0 * cfg.gate_drift_frac * travelled), cfg.reloc_window_max_xy)
        wth = min(
            max(cfg.reloc_window_theta_deg, 3.0 * cfg.gate_drift_deg_per_m * travelled),
            cfg.reloc_window_max_theta_deg,
        )
        self._dist_at_reloc = self._dist
        self._turn_at_reloc = self._turn
        self._finish_steps(ctx)  # the previous relocalisation's, if any: a bounded backlog
        steps = self._relocalise_steps(
            ctx, keyframe, points, wxy, np.deg2rad(wth), why, self.accepted.relocaliser
        )
        self._later(ctx, steps)

    def _relocalise_steps(
        self, ctx, keyframe, points, wxy: float, wth: float, why: str, relocaliser: Relocaliser
    ) -> Iterator[None]:
        t0 = time.perf_counter()
        reloc = relocaliser.relocalise(points, keyframe.pose_map, wxy, wth)
        self.timings["relocalise"] += time.perf_counter() - t0
        yield _MS_RELOCALISE
        _, cost = yield from self._prior_steps(ctx, keyframe, reloc, why)
        yield cost
        self._check_priors(ctx, keyframe.stamp)
        yield _MS_CHECK_PRIORS

    def _prior_steps(
        self, ctx, keyframe, reloc, why: str, drift: float | None = None, backfill: bool = False
    ) -> Generator[float, None, tuple[bool, float]]:
        """:meth:`_try_prior`, then the graph's relinearising iterations one per step (each
        yield ends one, giving its estimated ms); returns whether the prior was added and the
        estimated cost of the step still open (the caller yields it)."""
        n = ctx.graph.prior_settle_iterations(keyframe.index, reloc.pose, self.config.prior_kind)
        added = self._try_prior(ctx, keyframe, reloc, why, drift, backfill, settle=False)
        cost = _MS_PRIOR
        if added:
            for _ in ctx.graph.settle_steps(n):
                yield cost
                cost = _MS_PER_KEYFRAME_SETTLE * len(ctx.graph)
        return added, cost

    def _gate_chi2(self, ctx, keyframe, reloc: Relocalisation, drift: float | None = None) -> float:
        """chi² of (relocalised - estimated) pose under reloc + marginal + drift covariances."""
        cfg = self.config
        est = np.asarray(keyframe.pose_map, float)
        d = reloc.pose - est
        d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
        travelled = self._dist - self._dist_at_prior if drift is None else drift
        sxy = cfg.gate_sigma_xy + cfg.gate_drift_frac * travelled
        sth = np.deg2rad(cfg.gate_sigma_theta_deg + cfg.gate_drift_deg_per_m * travelled)
        s = reloc.covariance + np.diag([sxy**2, sxy**2, sth**2])
        try:
            s = s + vector_cov(est, ctx.graph.marginal_covariance(keyframe.index))
        except Exception:  # noqa: BLE001 - a marginal may be unavailable right after a removal
            pass
        return float(d @ np.linalg.solve(s, d))

    def _try_prior(
        self,
        ctx,
        keyframe,
        reloc: Relocalisation,
        why: str,
        drift: float | None = None,
        backfill: bool = False,
        settle: bool = True,
    ) -> bool:
        """Gate a relocalisation and add it as a prior (logged either way); True when added.
        Without ``settle`` the graph's relinearising iterations are the caller's."""
        cfg = self.config
        stamp, i = float(keyframe.stamp), keyframe.index
        est = np.asarray(keyframe.pose_map, float)
        d = reloc.pose - est
        d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
        nums = {
            "score": reloc.score,
            "ambiguity": reloc.ambiguity,
            "dx": d[0],
            "dy": d[1],
            "dtheta": d[2],
            "sigma_x": reloc.std[0],
            "sigma_y": reloc.std[1],
            "sigma_theta": reloc.std[2],
            "time_s": reloc.time_s,
        }
        self._event(ctx, stamp, "relocalise", why, i, reloc.ok, **nums)
        rej = None
        if not reloc.ok:
            rej = f"relocalisation failed: {reloc.reason}"
        elif reloc.score < cfg.reloc_min_score:
            rej = f"poor fit: inliers {reloc.score:.0%} < {cfg.reloc_min_score:.0%}"
        elif reloc.ambiguity > cfg.reloc_max_ambiguity:
            rej = f"ambiguous: {reloc.ambiguity:.2f} > {cfg.reloc_max_ambiguity:.2f}"
        else:
            chi2 = self._gate_chi2(ctx, keyframe, reloc, drift)
            nums["chi2"] = chi2
            if chi2 > cfg.inconsistent_chi2:
                rej = f"inconsistent with the estimate: chi2 {chi2:.1f} > {cfg.inconsistent_chi2:.1f}"
                if not backfill:
                    self._inconsistent_run += 1
        if rej is not None:
            self._event(ctx, stamp, "prior_rejected", rej, i, False, **nums)
            return False
        if not backfill:
            self._inconsistent_run = 0
        cov = tangent_cov(reloc.pose, reloc.covariance)
        ctx.add_prior(
            int(i),
            reloc.pose,
            cov,
            source=f"reloc:reg{self.accepted.id}",
            kind=cfg.prior_kind,
            info={"score": reloc.score, "ambiguity": reloc.ambiguity},
            extra_iterations=None if settle else 0,
            why=why,
            **{k: _num(v) for k, v in nums.items()},
            accepted=True,
        )
        if not backfill:
            self._dist_at_prior = self._dist
        return True

    def _check_priors(self, ctx, stamp: float) -> None:
        """Remove priors whose residual after optimisation is far beyond their covariance.

        A prior is proven wrong when the rest of the graph (odometry and the other priors)
        contradicts it. When a large share of the priors is contradicted at once, the culprit is
        something else (e.g. a wrong loop closure bending the trajectory): then nothing is
        removed and a "prior_conflict" event is logged instead.
        """
        cfg = self.config
        handles = [h for h in ctx.graph.priors() if h.source.startswith("reloc:")]
        if not handles:
            return
        self._checks += 1
        if self._checks % 10 and len(handles) > 30:  # every time the recent ones, now and then all
            handles = handles[-30:]
        bad = []
        for h, res in zip(handles, ctx.graph.prior_residuals(handles), strict=True):
            e = np.asarray(res.error, float)
            far = (len(e) >= 2 and float(np.hypot(e[0], e[1])) > cfg.remove_min_xy) or (
                len(e) != 2 and abs(float(e[-1])) > np.deg2rad(cfg.remove_min_theta_deg)
            )
            if res.chi2 > cfg.remove_chi2 and far:
                bad.append((h, res, e))
        if not bad:
            return
        if len(bad) > max(1, cfg.remove_max_share * len(handles)):
            self._event(
                ctx,
                stamp,
                "prior_conflict",
                f"{len(bad)} of {len(handles)} priors contradicted at once: the trajectory, not the "
                "priors, is suspect; none removed",
                None,
                False,
                contradicted=len(bad),
                priors=len(handles),
            )
            return
        for h, res, e in bad:
            why = (
                f"proven wrong: residual chi2 {res.chi2:.1f} > {cfg.remove_chi2:.1f}, "
                f"error {np.round(e, 3).tolist()} (weight {res.weight:.2f})"
            )
            ctx.remove_priors([h], reason=why, cause="wrong", chi2=_num(res.chi2), weight=_num(res.weight))


# --------------------------------------------------------------------------- helpers
def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


__all__ = ["UPDATE_KINDS", "FloorPlanUpdater"]
