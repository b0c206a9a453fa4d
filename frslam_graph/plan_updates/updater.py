"""The real-time floor-plan update strategy (paper Alg. 3) as a hook plugged into FRSlam.

Frames (REP-105; metres, radians): before any registration ``map`` is the odom frame of the
first pose (the graph's anchor). The LiDAR occupancy map is built in ``map`` from the keyframes
at their current estimates, so a registration's matrix (plan -> map metres) puts the plan *in
the SLAM map frame*; the first accepted registration fixes that plan -> map transform and the
graph is never re-expressed. Relocalisation priors then pull the trajectory onto the plan's
geometry, which corrects the drift accumulated along the way.

:class:`FloorPlanUpdater` is called after every keyframe (``on_keyframe(ctx, keyframe)``) and
routes the verdicts of its collaborators (:mod:`frslam_graph.plan_updates`), each owning its
state:

1. :class:`~frslam_graph.plan_updates.travel.Travel` and ``Coverage``: distance, turn,
   obstruction (no progress for ``OBSTRUCTION_TIME_S``, or :meth:`notify_obstructed`), the
   mapped area;
2. :class:`~frslam_graph.plan_updates.schedule.RegistrationSchedule`: whether to **register**
   the plan now (``register_fn(plan, grid)``, MFR by default) and why;
3. :class:`~frslam_graph.plan_updates.judge.RegistrationJudge`: the verdict on a registration
   (accept, refine the accepted one, or reject; it writes nothing). An accepted registration
   replaces the previous one, whose priors are re-anchored on the new plan;
4. :class:`~frslam_graph.plan_updates.refiner.PlanRefiner`: ``scale_refine_distance`` metres
   after an acceptance, the plan's scale fitted to keyframe scans and, with ``align_to_start``,
   the plan moved so that the first scan fits it at the anchor;
5. :class:`~frslam_graph.plan_updates.priors.PriorManager`: after every
   ``relocation_distance_D`` metres (or ``relocation_angle_deg``, or an obstruction) the current
   scan **relocalised** on the accepted plan and, when it passes the chi² gate, added as a robust
   prior; backfill of the keyframes before a registration; priors later proven wrong removed.
   With ``spread_over_scans`` this work runs as deferred steps on the following scans.

Before the grown map is registered again, the accepted registration is retracted when its walls
cross space the robot has seen free (``retract_walls_in_free_space``). At the end of an offline
run (:meth:`on_finish`, ``final_refine``) one more registration and the scale refinement run on
the complete map. Every decision is one event of the run's decision log (``ctx.log``; the
updater's are ``updater.log``, :data:`UPDATE_KINDS`); nothing is printed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.errors import FrslamError
from frslam_graph.localisation.relocalisation import RelocaliserParams
from frslam_graph.plan_checks import (
    ignoring_pieces,
    occupied_points,
    plan_seen,
    wall_pieces_seen_through,
    walls_through_free_space,
)
from frslam_graph.plan_updates.accepted import AcceptedPlan
from frslam_graph.plan_updates.evidence import ScanEvidence
from frslam_graph.plan_updates.judge import RegistrationJudge, Verdict, tolerances
from frslam_graph.plan_updates.priors import HeldReanchor, PriorManager, record
from frslam_graph.plan_updates.refiner import PlanRefiner, Refinement
from frslam_graph.plan_updates.schedule import LOCAL_MAP_DISTANCE, RegistrationSchedule, Trigger
from frslam_graph.plan_updates.travel import Coverage, Travel

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# m/s; progress slower than this for OBSTRUCTION_TIME_S counts as obstructed (triggers a registration)
OBSTRUCTION_SPEED = 0.02
OBSTRUCTION_TIME_S = 5.0  # s; how long progress must be slow to count as obstructed

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext, FrozenContext
    from frslam_graph.backend.decisions import DecisionEvent
    from frslam_graph.backend.keyframes import KeyframeInfo
    from frslam_graph.registration import Registration

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
class _Recheck:
    """The accepted registration rechecked on the grown map: the event to record (``kind``:
    ``plan_refined`` when its wall pieces seen through are dropped, ``registration_retracted``)
    and the accepted registration afterwards (None: retracted)."""

    kind: str
    message: str
    numbers: dict[str, float]
    accepted: AcceptedPlan | None


@dataclass
class _Outcome:
    """What a registration attempt found (it changed nothing): the map it registered on, the
    recheck of the accepted registration, the registration (None: the method raised ``error``)
    and the judge's verdict; ``seconds`` of work."""

    grid: Any
    recheck: _Recheck | None
    registration: Any
    error: str | None
    verdict: Verdict | None = None
    seconds: float = 0.0


@dataclass
class _Attempt:
    """A registration attempt made at ``keyframe`` (the map up to it) and not yet concluded: its
    verdict is applied at the first keyframe stamped ``due`` or later (s, recording time).
    ``outcome``: the background thread's Future, or the outcome when it ran in the step."""

    keyframe: KeyframeInfo
    reason: str
    area: float  # m², mapped when it was made
    dist: float  # m travelled when it was made
    due: float
    outcome: Future | _Outcome


class FloorPlanUpdater:
    """Paper Alg. 3 as an FRSlam hook (see the module docstring)."""

    def __init__(
        self, plan, config: UpdatesConfig | None = None, register_fn: Callable[[Any, Any], Any] | None = None
    ) -> None:
        self.plan = plan
        self.config = cfg = config or UpdatesConfig()
        if register_fn is None:
            from frslam_graph.registration import register as register_fn  # noqa: PLC0415
        self.register_fn = register_fn
        self.accepted: AcceptedPlan | None = None
        self.params = RelocaliserParams(
            resolution=cfg.reloc_resolution,
            wall_offset=cfg.wall_half_thickness,
            window_xy=cfg.reloc_window_xy,
            window_theta=np.deg2rad(cfg.reloc_window_theta_deg),
            sigma_floor_xy=cfg.reloc_sigma_floor_xy,
            sigma_floor_theta=np.deg2rad(cfg.reloc_sigma_floor_theta_deg),
        )
        self.timings: dict[str, float] = {"register": 0.0, "relocalise": 0.0, "coverage": 0.0}
        self.coverage = Coverage()
        self.travel = Travel(OBSTRUCTION_TIME_S, OBSTRUCTION_SPEED)
        self.schedule = RegistrationSchedule(cfg)
        evidence = ScanEvidence(cfg.refine_scan_samples, self.timings)
        self.judge = RegistrationJudge(plan, cfg, self.params, evidence)
        self.refiner = PlanRefiner(plan, cfg, self.params, evidence)
        self.priors = PriorManager(cfg, self.travel, self.schedule, lambda: self.accepted, self.timings)
        # registrations waiting for confirmation, oldest first (see confirm_after_m)
        self._pending_reg: tuple[Registration, ...] = ()
        self._attempt: _Attempt | None = None  # a registration not yet concluded
        self._executor: ThreadPoolExecutor | None = None  # its background thread, made on first use
        self._mapper = None  # the registrations' occupancy mapper (only the attempt in progress uses it)
        self._next_id = 0
        #: a refused final registration's placement (FloorPlan in map metres), for the figures
        self.final_placement = None
        self._decisions: Sequence[DecisionEvent] = ()  # the run's decision log (the context's)

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
        return self.coverage.area

    def notify_obstructed(self) -> None:
        """The caller's motion is obstructed (paper Alg. 3: d <= 0): register and relocalise at
        the next keyframe."""
        self.travel.notify_obstructed()

    @property
    def log(self) -> list[DecisionEvent]:
        """The updater's decisions (:data:`UPDATE_KINDS`) in the run's decision log."""
        return [e for e in self._decisions if e.kind in UPDATE_KINDS]

    def events(self, kind: str | None = None) -> list[DecisionEvent]:
        return [e for e in self.log if kind is None or e.kind == kind]

    # ------------------------------------------------------------------ hooks
    def on_keyframe(self, ctx: BackendContext, keyframe: KeyframeInfo) -> None:
        """Called by FRSlam after each keyframe is in the graph: conclude the registration in
        progress when due; register, refine the plan, or relocalise (one of them); then backfill.
        While a registration is in progress the plan is neither registered again nor refined;
        relocalisation on the accepted one goes on."""
        self._decisions = ctx.log
        if not self.config.enabled or self.plan is None:
            return
        t0 = time.perf_counter()
        self.travel.advance(keyframe.pose_odom)
        self.coverage.add_scan(keyframe.pose_map, ctx.keyframe_scans()[0][keyframe.index])
        self.timings["coverage"] += time.perf_counter() - t0
        obstructed = self._obstruction(ctx, keyframe)
        if self._attempt is not None and float(keyframe.stamp) >= self._attempt.due:
            ctx.deferred.run_all()
            self._conclude(ctx, keyframe)
        dist = self.travel.dist
        trigger = None
        if self._attempt is None:
            trigger = self.schedule.next_trigger(
                self.coverage.area, dist, obstructed, self.accepted is not None
            )
        if trigger is not None:
            ctx.deferred.run_all()
            lag = self.config.background_registration_s
            if lag > 0.0:
                self._start(ctx, keyframe, trigger, lag)
            else:
                self._register(ctx, keyframe, trigger)
        elif self.accepted is not None:
            if self._attempt is None and self.refiner.due(dist):
                ctx.deferred.run_all()
                self.refiner.ran(dist, self._refine(ctx, keyframe))
            else:
                why = self.priors.relocalisation_due(obstructed)
                if why is not None:
                    self.priors.relocalise(ctx, keyframe, why)
        self.priors.run_backfill(ctx)  # as fast as the steps get done

    def on_finish(self, ctx: BackendContext) -> None:
        """The end of an offline run (:meth:`FRSlam.finish`, before the final batch), with
        ``final_refine`` on: one more registration on the complete map whatever the attempt budget
        left. With a registration accepted it refines the accepted one when it agrees and explains
        the data as well or better (as any later one), then the scale refinement runs, whenever
        the schedule last ran them: the plan the run ends with depends less on when its
        refinements happened. With none accepted it is judged as any first registration (accepted:
        its priors and their backfill are added before the final batch); refused, its placement
        is kept as :attr:`final_placement` for the run's figures."""
        self._decisions = ctx.log
        cfg = self.config
        if self._attempt is not None:  # the registration in progress first, as if it were due
            ctx.deferred.run_all()
            self._conclude(ctx, ctx.keyframe(len(ctx.graph) - 1))
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None
        if not cfg.enabled or self.plan is None or not cfg.final_refine or len(ctx.graph) == 0:
            return
        if self.accepted is None:
            self._final_first(ctx)
            return
        ctx.deferred.run_all()
        last = ctx.keyframe(len(ctx.graph) - 1)
        # the registration, the scale and the move to the start may each change the plan: its
        # priors are relocalised once, on the plan the run ends with (each re-anchoring
        # relocalises every prior: ~7 s on a 200 m run)
        self.priors.held = HeldReanchor()
        try:
            self._register(ctx, last, Trigger("end of the run: final refinement"))
            ctx.deferred.run_all()
            if self.accepted is not None and cfg.scale_refine_distance > 0.0:
                # the run's last word on the scale: any gain on the keyframe scans of the whole
                # run (the margin keeps a run's plan from changing back and forth; no later)
                self._refine(ctx, last, final=True)
        finally:
            held, self.priors.held = self.priors.held, None
        if held.reasons and self.accepted is not None:
            # the accepted registration's own priors too: those placed while holding (the
            # registration's first prior, the pending relocalisations) are on an earlier plan
            held.note([self.accepted])
            self.priors.reanchor(ctx, held.previous, "; ".join(held.reasons))
        ctx.deferred.run_all()

    def _final_first(self, ctx: BackendContext) -> None:
        """With none accepted: the registration on the complete map (see :meth:`on_finish`)."""
        ctx.deferred.run_all()
        last = ctx.keyframe(len(ctx.graph) - 1)
        reg = self._register(ctx, last, Trigger("end of the run: registration on the complete map"))
        if self.accepted is not None:  # its backfill, all of it, before the final batch
            while self.priors.backfill_pending():
                self.priors.run_backfill(ctx)
                ctx.deferred.run_all()
        elif reg is not None and reg.placed:
            try:
                self.final_placement = reg.apply(self.plan)
            except (FrslamError, ValueError):
                self.final_placement = None

    # ------------------------------------------------------------------ routing
    def _obstruction(self, ctx: BackendContext, keyframe: KeyframeInfo) -> bool:
        """Whether progress is obstructed at this keyframe (a new obstruction is logged; it
        concludes the registration in progress, so that it may trigger the next one)."""
        obstructed, newly = self.travel.obstruction(float(keyframe.stamp))
        if newly:
            ctx.deferred.run_all()  # what it triggers drains them anyway: their events first
            if self._attempt is not None:
                self._conclude(ctx, keyframe)
            record(
                ctx,
                float(keyframe.stamp),
                "obstructed",
                "no progress: register and relocalise",
                keyframe.index,
            )
        return obstructed

    def _register(self, ctx: BackendContext, keyframe: KeyframeInfo, trigger: Trigger):
        """Register the plan on the map now and route the judge's verdict; the registration (None
        when the method raised)."""
        self._start(ctx, keyframe, trigger, 0.0)
        return self._conclude(ctx, keyframe)

    def _start(self, ctx: BackendContext, keyframe: KeyframeInfo, trigger: Trigger, lag: float) -> None:
        """Start a registration attempt on the map up to ``keyframe``, concluded at the first
        keyframe ``lag`` seconds of recording later (0: now, in this step). It reads the backend
        through a frozen view (:meth:`BackendContext.frozen`) and changes nothing, so it runs in a
        background thread; when it is concluded depends only on the stamps, so the run's results
        do not depend on how fast it ran."""
        area, dist = self.coverage.area, self.travel.dist
        self.schedule.attempted(trigger, area, dist)
        reason, keep = trigger.reason, None
        if trigger.local:
            d = np.asarray(self.travel.kf_dist)
            keep = np.nonzero(d >= dist - LOCAL_MAP_DISTANCE)[0]
            reason += f"; on the map of the last {LOCAL_MAP_DISTANCE:.0f} m"
        args = (
            ctx.frozen(keyframe.index),
            keyframe,
            keep,
            self.accepted,
            self._pending_reg,
            self.priors.drift,
            dist,
            len(self.travel.kf_dist),
            area,
        )
        if lag > 0.0:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="frslam-registration")
            outcome: Future | _Outcome = self._executor.submit(self._attempt_on, *args)
        else:
            outcome = self._attempt_on(*args)
        self._attempt = _Attempt(keyframe, reason, area, dist, float(keyframe.stamp) + lag, outcome)

    def _attempt_on(
        self,
        view: FrozenContext,
        keyframe: KeyframeInfo,
        keep: np.ndarray | None,
        accepted: AcceptedPlan | None,
        pending: tuple[Registration, ...],
        drift: float,
        dist: float,
        n_kf: int,
        area: float,
    ) -> _Outcome:
        """The work of a registration attempt (any thread; it changes nothing the backend or the
        other collaborators read): the map of the keyframes (``keep``: only those; None: all),
        the recheck of ``accepted``, the registration and the judge's verdict."""
        from frslam_graph.backend.mapping import FREE_SPACE_WEIGHTS, OccupancyMapper, occupancy_grid  # noqa: PLC0415

        t0 = time.perf_counter()
        cfg = self.config
        pts, origins = view.keyframe_scans()
        est = view.graph.estimates()
        if keep is not None:
            grid = occupancy_grid(
                est[keep],
                [pts[k] for k in keep],
                [origins[k] for k in keep],
                cfg.map_resolution,
                **FREE_SPACE_WEIGHTS,
            )
        else:
            if self._mapper is None:
                self._mapper = OccupancyMapper(cfg.map_resolution, **FREE_SPACE_WEIGHTS)
            self._mapper.update(est, pts, origins)
            grid = self._mapper.grid()
        recheck = None
        if accepted is not None:
            recheck = self._recheck(view, keyframe, grid, accepted, drift)
            if recheck is not None:
                accepted = recheck.accepted
                if accepted is None:  # retracted: the gate's drift allowance restarts from 0 m
                    drift = dist
        try:
            reg = self.register_fn(self.plan, grid)
        except FrslamError as exc:
            return _Outcome(grid, recheck, None, str(exc), seconds=time.perf_counter() - t0)
        nums = {"area": area, "score": float(reg.score), "ambiguity": float(reg.ambiguity)}
        if reg.ok or reg.placed:
            # the placement itself (plan -> map), also one the method refused (MFR's "no match"
            # carries its best placement): a run's log says what was judged or refused
            nums.update(
                flipped=int(bool(reg.flipped)),
                rotation_deg=float(reg.rotation_deg),
                scale_x=float(reg.scale[0]),
                scale_y=float(reg.scale[1]),
            )
        verdict = self.judge.judge(view, keyframe, reg, grid, nums, accepted, pending, drift, n_kf)
        return _Outcome(grid, recheck, reg, None, verdict, time.perf_counter() - t0)

    def _conclude(self, ctx: BackendContext, now: KeyframeInfo):
        """Apply the registration attempt in progress (waiting for it if it is not done) at
        keyframe ``now``: the recheck's retraction, then the judge's verdict; the registration
        (None when the method raised)."""
        att, self._attempt = self._attempt, None
        out = att.outcome if isinstance(att.outcome, _Outcome) else att.outcome.result()
        self.timings["register"] += out.seconds
        keyframe, reason, area = att.keyframe, att.reason, att.area
        stamp, i = float(keyframe.stamp), keyframe.index
        if out.recheck is not None:
            self._apply_recheck(ctx, keyframe, out.recheck)
        if out.registration is None:
            record(ctx, stamp, "register", f"{reason}; registration failed: {out.error}", i, False, area=area)
            return None
        reg, verdict = out.registration, out.verdict
        if verdict.pending is not None:
            self._pending_reg = verdict.pending
        if verdict.outcome == "accept":
            self._accept(ctx, keyframe, verdict, reason, out.grid, att.dist, now.index)
            return reg
        record(ctx, stamp, "register", f"{reason}; {verdict.why}", i, False, **verdict.numbers)
        if verdict.outcome == "refine":  # the same placement fitted to more data
            acc = self.accepted
            self.accepted = AcceptedPlan(
                acc.id,
                verdict.registration,
                verdict.plan_map,
                verdict.relocaliser,
                verdict.map_fit,
                max(acc.drawing_tol, verdict.numbers.get("drawing_tol", 0.0)),
            )
        self.schedule.rejected(matched=reg.ok, accepted=self.accepted is not None)
        return reg

    def _accept(
        self,
        ctx: BackendContext,
        keyframe: KeyframeInfo,
        verdict: Verdict,
        reason: str,
        grid,
        dist: float,
        now: int,
    ) -> None:
        """A new accepted registration made on the map up to ``keyframe``: it replaces the
        previous one (whose priors are re-anchored on it); that keyframe's relocalisation becomes
        its first prior; backfill of the keyframes before keyframe ``now`` follows. Its event also
        says how far the robot had travelled when it was made (``distance_m``, metres: ``dist``)
        and how much of the registered plan's room area the map ``grid`` had seen
        (``plan_seen``, 0..1)."""
        stamp, i = float(keyframe.stamp), keyframe.index
        msg, kind = f"{reason}; accepted", "register"
        if self.accepted is not None:
            msg, kind = f"{reason}; replaces registration {self.accepted.id}", "registration_replaced"
        seen = plan_seen(verdict.plan_map, grid)
        record(ctx, stamp, kind, msg, i, True, **verdict.numbers, distance_m=dist, plan_seen=seen)
        previous = self.accepted
        self.accepted = AcceptedPlan(
            self._next_id,
            verdict.registration,
            verdict.plan_map,
            verdict.relocaliser,
            verdict.map_fit,
            verdict.numbers.get("drawing_tol", 0.0),
        )
        self._next_id += 1
        self.refiner.restart(self.travel.dist)
        if previous is not None:
            self.priors.reanchor(ctx, previous)
        self.priors.offer(ctx, keyframe, verdict.relocalisation, "registration accepted")
        self.priors.relocalised_now()
        self.priors.queue_backfill(ctx, now)

    def _refine(self, ctx: BackendContext, keyframe: KeyframeInfo, final: bool = False) -> bool:
        """The scale refinement, then (``align_to_start``) the move to the start; whether the
        plan changed."""
        n_kf = len(self.travel.kf_dist)
        changed = self._apply(ctx, keyframe, self.refiner.scale(ctx, self.accepted, n_kf, final))
        if self.config.align_to_start:
            changed = self._apply(ctx, keyframe, self.refiner.start(ctx, self.accepted)) or changed
        return changed

    def _apply(self, ctx: BackendContext, keyframe: KeyframeInfo, r: Refinement) -> bool:
        """Record a refinement; when it changed the plan, take it and re-anchor as it says."""
        record(
            ctx,
            float(keyframe.stamp),
            "plan_refined",
            r.message,
            keyframe.index,
            r.plan is not None,
            **r.numbers,
        )
        if r.plan is None:
            return False
        previous, self.accepted = self.accepted, r.plan
        if r.reanchor is not None:
            self.priors.reanchor(ctx, previous, r.reanchor)
        return True

    def _recheck(
        self, view: FrozenContext, keyframe: KeyframeInfo, grid, acc: AcceptedPlan, drift: float
    ) -> _Recheck | None:
        """The accepted registration ``acc`` rechecked on the grown map (any thread; changes
        nothing): None when it stands, else what :meth:`_apply_recheck` does. It is retracted
        when the map contradicts it (its walls cross space the robot has seen free): its priors
        are removed and the next registration is judged as a first one. A plan known to be drawn
        off the building (``drawing_tol`` > 0: its registration needed a tolerance from its
        residual) whose wall pieces seen through are a minority of its observed walls, the rest
        still explaining the map as its acceptance required (``min_map_fit``, or clearly more
        than its runner-up placements: :meth:`RegistrationJudge.still_clearly_best`), loses those
        pieces instead (later relocalisations ignore them). An accurately drawn plan is
        retracted: there a wall the map sees through is a wrong placement (e.g. the mirror of a
        near-symmetric plan, which differs by a wall the first scans had not seen)."""
        cfg = self.config
        fit_tol, margin = tolerances(cfg, drift, acc.drawing_tol)
        crossing = walls_through_free_space(acc.relocaliser, grid, margin)
        if crossing <= cfg.retract_walls_in_free_space:
            return None
        rel = acc.relocaliser
        pts, dropped, fit = np.zeros((0, 2)), 1.0, float("nan")
        if acc.drawing_tol > 0.0:
            pts, dropped, _ = wall_pieces_seen_through(rel, grid, margin, cfg.max_walls_in_free_space)
        if dropped < 0.5:
            part = ignoring_pieces(rel, pts, margin)
            fit = part.fit_points(occupied_points(grid), fit_tol)
            if fit >= cfg.min_map_fit or self.judge.still_clearly_best(view, keyframe, grid, acc, drift, fit):
                return _Recheck(
                    "plan_refined",
                    f"registration {acc.id}: {crossing:.0%} of its observed walls cross free space; the wall "
                    f"pieces seen through ({dropped:.0%} of them) dropped, the rest explains {fit:.0%} of the map",
                    {"walls_in_free_space": crossing, "wall_pieces_dropped": dropped, "map_fit_kept": fit},
                    AcceptedPlan(acc.id, acc.registration, acc.plan, part, acc.map_fit, acc.drawing_tol),
                )
        why = (
            f"registration {acc.id} contradicted by the map: {crossing:.0%} of its observed walls "
            f"cross free space > {cfg.retract_walls_in_free_space:.0%}"
        )
        if acc.drawing_tol > 0.0:
            why += (
                f"; the pieces seen through are {dropped:.0%} of them (a majority)"
                if dropped >= 0.5
                else f"; without the pieces seen through its walls explain {fit:.0%} of the map < "
                f"{cfg.min_map_fit:.0%}, and not clearly more than its runner-up placements"
            )
        return _Recheck("registration_retracted", why, {"walls_in_free_space": crossing}, None)

    def _apply_recheck(self, ctx: BackendContext, keyframe: KeyframeInfo, r: _Recheck) -> None:
        """Record the recheck of the accepted registration and act on it: its pieces dropped, or
        retracted (its priors removed as wrong)."""
        acc = self.accepted
        record(ctx, keyframe.stamp, r.kind, r.message, keyframe.index, r.accepted is not None, **r.numbers)
        self.accepted = r.accepted
        if r.accepted is None:
            self.priors.retract(ctx, acc, r.message)


__all__ = ["UPDATE_KINDS", "FloorPlanUpdater"]
