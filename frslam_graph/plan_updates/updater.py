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
from frslam_graph.plan_updates.judge import KEEP, RegistrationJudge, Verdict, tolerances
from frslam_graph.plan_updates.priors import HeldReanchor, PriorManager, record
from frslam_graph.plan_updates.refiner import PlanRefiner, Refinement
from frslam_graph.plan_updates.schedule import LOCAL_MAP_DISTANCE, RegistrationSchedule, Trigger
from frslam_graph.plan_updates.travel import Coverage, Travel

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# m/s; progress slower than this for OBSTRUCTION_TIME_S counts as obstructed (triggers a registration)
OBSTRUCTION_SPEED = 0.02
OBSTRUCTION_TIME_S = 5.0  # s; how long progress must be slow to count as obstructed

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext
    from frslam_graph.backend.decisions import DecisionEvent
    from frslam_graph.backend.keyframes import KeyframeInfo

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
        self._pending_reg = None  # registrations waiting for confirmation (a list; see confirm_after_m)
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
        """Called by FRSlam after each keyframe is in the graph: register, refine the plan, or
        relocalise (one of them), then backfill."""
        self._decisions = ctx.log
        if not self.config.enabled or self.plan is None:
            return
        t0 = time.perf_counter()
        self.travel.advance(keyframe.pose_odom)
        self.coverage.add_scan(keyframe.pose_map, ctx.keyframe_scans()[0][keyframe.index])
        self.timings["coverage"] += time.perf_counter() - t0
        obstructed = self._obstruction(ctx, keyframe)
        dist = self.travel.dist
        trigger = self.schedule.next_trigger(self.coverage.area, dist, obstructed, self.accepted is not None)
        if trigger is not None:
            ctx.deferred.run_all()
            self._register(ctx, keyframe, trigger)
        elif self.accepted is not None:
            if self.refiner.due(dist):
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
        """Whether progress is obstructed at this keyframe (a new obstruction is logged)."""
        obstructed, newly = self.travel.obstruction(float(keyframe.stamp))
        if newly:
            ctx.deferred.run_all()  # what it triggers drains them anyway: their events first
            record(
                ctx,
                float(keyframe.stamp),
                "obstructed",
                "no progress: register and relocalise",
                keyframe.index,
            )
        return obstructed

    def _register(self, ctx: BackendContext, keyframe: KeyframeInfo, trigger: Trigger):
        """Register the plan on the map and route the judge's verdict; the registration (None
        when the method raised)."""
        cfg = self.config
        t0 = time.perf_counter()
        area = self.coverage.area
        self.schedule.attempted(trigger, area, self.travel.dist)
        stamp, i = float(keyframe.stamp), keyframe.index
        reason = trigger.reason
        if trigger.local:
            grid = self._local_grid(ctx)
            reason += f"; on the map of the last {LOCAL_MAP_DISTANCE:.0f} m"
        else:
            grid = ctx.occupancy_grid(cfg.map_resolution, free_space=True)
        if self.accepted is not None:
            self._recheck_accepted(ctx, keyframe, grid)
        try:
            reg = self.register_fn(self.plan, grid)
        except FrslamError as exc:
            record(ctx, stamp, "register", f"{reason}; registration failed: {exc}", i, False, area=area)
            self.timings["register"] += time.perf_counter() - t0
            return None
        nums = {"area": area, "score": float(reg.score), "ambiguity": float(reg.ambiguity)}
        if reg.ok:  # the placement itself (plan -> map): a run's log says what was judged
            nums.update(
                flipped=int(bool(reg.flipped)),
                rotation_deg=float(reg.rotation_deg),
                scale_x=float(reg.scale[0]),
                scale_y=float(reg.scale[1]),
            )
        n_kf = len(self.travel.kf_dist)
        verdict = self.judge.judge(
            ctx, keyframe, reg, grid, nums, self.accepted, self._pending_reg, self.priors.drift, n_kf
        )
        self.timings["register"] += time.perf_counter() - t0
        if verdict.pending is not KEEP:
            self._pending_reg = verdict.pending
        if verdict.outcome == "accept":
            self._accept(ctx, keyframe, verdict, reason, grid)
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
        self, ctx: BackendContext, keyframe: KeyframeInfo, verdict: Verdict, reason: str, grid
    ) -> None:
        """A new accepted registration: it replaces the previous one (whose priors are re-anchored
        on it); the current scan's relocalisation becomes its first prior; backfill follows. Its
        event also says how far the robot had travelled (``distance_m``, metres) and how much of
        the registered plan's room area the map ``grid`` had seen (``plan_seen``, 0..1)."""
        stamp, i = float(keyframe.stamp), keyframe.index
        msg, kind = f"{reason}; accepted", "register"
        if self.accepted is not None:
            msg, kind = f"{reason}; replaces registration {self.accepted.id}", "registration_replaced"
        seen = plan_seen(verdict.plan_map, grid)
        record(ctx, stamp, kind, msg, i, True, **verdict.numbers, distance_m=self.travel.dist, plan_seen=seen)
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
        self.priors.queue_backfill(ctx, i)

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

    def _recheck_accepted(self, ctx: BackendContext, keyframe: KeyframeInfo, grid) -> None:
        """Retract the accepted registration when the grown map contradicts it (its walls cross
        space the robot has seen free): its priors are removed and the next registration is
        judged as a first one. A plan known to be drawn off the building (``drawing_tol`` > 0:
        its registration needed a tolerance from its residual) whose wall pieces seen through are
        a minority of its observed walls, the rest still explaining the map as its acceptance
        required (``min_map_fit``, or clearly more than its runner-up placements:
        :meth:`RegistrationJudge.still_clearly_best`), loses those pieces instead (later
        relocalisations ignore them). An accurately drawn plan
        is retracted: there a wall the map sees through is a wrong placement (e.g. the mirror of
        a near-symmetric plan, which differs by a wall the first scans had not seen)."""
        cfg = self.config
        acc = self.accepted
        margin = tolerances(cfg, self.priors.drift, acc.drawing_tol)[1]
        crossing = walls_through_free_space(acc.relocaliser, grid, margin)
        if crossing <= cfg.retract_walls_in_free_space:
            return
        rel = acc.relocaliser
        pts, dropped, fit = np.zeros((0, 2)), 1.0, float("nan")
        if acc.drawing_tol > 0.0:
            pts, dropped, _ = wall_pieces_seen_through(rel, grid, margin, cfg.max_walls_in_free_space)
        if dropped < 0.5:
            part = ignoring_pieces(rel, pts, margin)
            fit_tol = tolerances(cfg, self.priors.drift, acc.drawing_tol)[0]
            fit = part.fit_points(occupied_points(grid), fit_tol)
            if fit >= cfg.min_map_fit or self.judge.still_clearly_best(
                ctx, keyframe, grid, acc, self.priors.drift, fit
            ):
                record(
                    ctx,
                    keyframe.stamp,
                    "plan_refined",
                    f"registration {acc.id}: {crossing:.0%} of its observed walls cross free space; the wall "
                    f"pieces seen through ({dropped:.0%} of them) dropped, the rest explains {fit:.0%} of the map",
                    keyframe.index,
                    True,
                    walls_in_free_space=crossing,
                    wall_pieces_dropped=dropped,
                    map_fit_kept=fit,
                )
                self.accepted = AcceptedPlan(
                    acc.id, acc.registration, acc.plan, part, acc.map_fit, acc.drawing_tol
                )
                return
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
        record(
            ctx,
            keyframe.stamp,
            "registration_retracted",
            why,
            keyframe.index,
            False,
            walls_in_free_space=crossing,
        )
        self.accepted = None
        self.priors.retract(ctx, acc, why)

    def _local_grid(self, ctx: BackendContext):
        """Occupancy grid (map frame) of the keyframes of the last ``LOCAL_MAP_DISTANCE`` metres
        travelled: less drift accumulated inside it than in the whole map."""
        from frslam_graph.backend.mapping import FREE_SPACE_WEIGHTS, occupancy_grid  # noqa: PLC0415

        d = np.asarray(self.travel.kf_dist)
        keep = np.nonzero(d >= self.travel.dist - LOCAL_MAP_DISTANCE)[0]
        pts, origins = ctx.keyframe_scans()
        est = ctx.graph.estimates()
        return occupancy_grid(
            est[keep],
            [pts[k] for k in keep],
            [origins[k] for k in keep],
            self.config.map_resolution,
            **FREE_SPACE_WEIGHTS,
        )


__all__ = ["UPDATE_KINDS", "FloorPlanUpdater"]
