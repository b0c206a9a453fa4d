"""The verdict on a registration of the floor plan (paper Alg. 3's acceptance checks).

:meth:`RegistrationJudge.judge` returns a :class:`Verdict` with its numbers and writes nothing
(no log, no graph, no state): the updater acts on it. Checks, in order: the registration
succeeded, is not doubted by its method (``doubt``: the paper-faithful MFR flags its doubtful
matches) and scores ``min_score``; an ambiguous one (``max_ambiguity``) before any is accepted
is disambiguated with MFR's runner-up placements on the keyframe scans; the plan's walls
explain ``min_map_fit`` of the map's occupied cells and cross at most
``max_walls_in_free_space`` of its free space (else partial trust: the wall pieces, or for an
accurately drawn plan the rooms, the map has seen through are dropped when they are a minority
and the rest passes); against an accepted registration it refines it
(agrees within ``agree_tol`` and explains the data as well or better, ``refine_by``), is kept
out, or replaces it (``SWITCH_MARGIN`` better); the current scan relocalises on it
(``reloc_min_score``), the keyframe scans fit it (``min_scan_fit``); a first registration passes
the chi² gate against the trajectory and, after ``confirm_after_m`` metres without a prior, needs a
second one that agrees. Distances in metres (map frame), fits as shares of cells or scans.

A registration that says its plan is drawn off the building (MFR's drawing tolerance,
:func:`drawing_tolerance`) is judged at that tolerance (map fit, free-space margin), by wall
piece, and on the scans relative to its runner-up placements (:data:`SCAN_FIT_FLOOR`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.errors import FrslamError
from frslam_graph.localisation.relocalisation import Relocalisation, Relocaliser, RelocaliserParams
from frslam_graph.plan_checks import (
    ignoring_pieces,
    matrix_disagreement,
    occupied_points,
    rooms_seen_through,
    wall_pieces_seen_through,
    walls_through_free_space,
)
from frslam_graph.plan_updates.accepted import AcceptedPlan, runner_ups
from frslam_graph.plan_updates.evidence import ScanEvidence
from frslam_graph.plan_updates.priors import INCONSISTENT_CHI2, gate_chi2
from frslam_graph.registration import Registration

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# m per m travelled since the last accepted prior (uncorrected drift) added to map_fit_distance and
# free_space_margin
CHECK_GROWTH_PER_M = 0.01
# map-fit gain needed for a new registration to replace the accepted one; larger = switches less
SWITCH_MARGIN = 0.05
REFINE_SCAN_MARGIN = 0.005  # scan fits closer than this (mean soft score) are a tie (the map decides)
# a registration drawn off the building (drawing_tol > 0) below min_scan_fit passes on the scans
# when its fit is at least SCAN_FIT_FLOOR (mean soft score: the scans nearer its walls than not)
# and beats every runner-up placement by disambiguate_margin (the disambiguation's rule)
SCAN_FIT_FLOOR = 0.5
# registrations awaiting confirmation (confirm_after_m) a new one may agree with: the last ones
# that passed every other check
CONFIRM_CANDIDATES = 3
# a registration drawn off the building below min_map_fit passes on the map when its walls explain
# at least MAP_FIT_FLOOR of the map (share of occupied cells it can explain) and each runner-up
# placement at most MAP_FIT_RUNNER_UP of that (MFR's own margin, DRAWN_MARGIN, on its gate)
MAP_FIT_FLOOR = 0.25
MAP_FIT_RUNNER_UP = 0.8

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext
    from frslam_graph.backend.keyframes import KeyframeInfo


@dataclass
class Verdict:
    """``accept`` (a new accepted registration; ``relocalisation`` of the current scan on it),
    ``refine`` (the same placement fitted to more data replaces the accepted one) or ``reject``
    (``why``). ``pending``: the registrations awaiting confirmation afterwards (at most
    :data:`CONFIRM_CANDIDATES`, oldest first; empty: none), or None: unchanged."""

    outcome: Literal["accept", "refine", "reject"]
    why: str
    numbers: dict[str, float] = field(default_factory=dict)
    registration: Any = None
    plan_map: Any = None
    relocaliser: Relocaliser | None = None
    relocalisation: Relocalisation | None = None
    map_fit: float = float("nan")
    pending: tuple[Registration, ...] | None = None


def tolerances(config: UpdatesConfig, drift: float, drawing_tol: float = 0.0) -> tuple[float, float]:
    """(map-fit distance, free-space margin) in metres, grown with ``drift``, the distance
    travelled since the last accepted prior: how far the map may have drifted from the plan;
    at least ``drawing_tol`` (m, :func:`drawing_tolerance`): how far the plan is drawn off."""
    grow = CHECK_GROWTH_PER_M * max(drift, 0.0)
    fit = min(config.map_fit_distance + grow, max(config.map_fit_distance_max, config.map_fit_distance))
    margin = min(config.free_space_margin + grow, max(config.free_space_margin_max, config.free_space_margin))
    return max(fit, drawing_tol), max(margin, drawing_tol)


def drawing_tolerance(reg: Any) -> float:
    """How far (m) the registration says its plan is drawn off the building: the structure
    tolerance at which MFR accepted it when its fixed gate refused it, or the one its fit's
    residual gives when the fixed gate accepted it (``drawn_tol_m``: twice the fit's RMS, at
    most 0.35 m; a plan drawn 0.5-1 m off in places), else 0."""
    details = getattr(reg, "details", None) or {}
    drawn = details.get("drawn_ok") or details.get("drawn_off")
    return float(details.get("drawn_tol_m", 0.0)) if drawn else 0.0


def _runner_up_matrices(registration: Any) -> list[np.ndarray]:
    """The registration's runner-up placements (:func:`runner_ups`) as 3x3 plan -> map matrices."""
    return [np.asarray(a["matrix"], float) for a in runner_ups(registration)]


@dataclass
class _Case:
    """One registration under judgement: what the checks share."""

    ctx: BackendContext
    keyframe: KeyframeInfo
    grid: Any
    nums: dict[str, float]
    accepted: AcceptedPlan | None
    pending: tuple[Registration, ...]
    drift: float  # metres since the last accepted prior
    n_keyframes: int
    drawing_tol: float = 0.0  # m, the registration's (drawing_tolerance)
    alternatives: list = field(default_factory=list)  # its runner-up placements' matrices (plan -> map)
    alike: dict = field(default_factory=dict)  # matrix bytes -> its relocaliser judged alike (_alike)

    def tolerances(self, config: UpdatesConfig) -> tuple[float, float]:
        """(map-fit distance, free-space margin) in metres for this case (:func:`tolerances`)."""
        return tolerances(config, self.drift, self.drawing_tol)


class RegistrationJudge:
    """Accept, refine or reject a registration (see the module docstring)."""

    def __init__(self, plan: Any, config: UpdatesConfig, params: RelocaliserParams, evidence: ScanEvidence):
        self.plan = plan
        self.config = config
        self.params = params
        self.evidence = evidence

    def judge(
        self,
        ctx: BackendContext,
        keyframe: KeyframeInfo,
        reg: Any,
        grid: Any,
        numbers: dict[str, float],
        accepted: AcceptedPlan | None,
        pending: tuple[Registration, ...],
        drift: float,
        n_keyframes: int,
    ) -> Verdict:
        """The verdict on ``reg`` (registration plan -> map) made on ``grid`` (the map); ``numbers``
        start its numbers; ``pending``: the registrations awaiting confirmation (oldest first); ``drift``: metres
        since the last accepted prior; ``n_keyframes``: keyframes seen by the updater."""
        case = _Case(ctx, keyframe, grid, dict(numbers), accepted, pending, drift, n_keyframes)
        case.drawing_tol = drawing_tolerance(reg)
        case.alternatives = _runner_up_matrices(reg)
        if case.drawing_tol > 0.0:
            case.nums["drawing_tol"] = case.drawing_tol
        cfg = self.config
        if not reg.ok:
            return self._reject(case, f"registration failed: {reg.reason or 'no match'}")
        if reg.doubt:  # the method's own verdict (the paper-faithful MFR's): never a prior
            return self._reject(case, f"doubtful match: {reg.doubt}")
        if reg.score < cfg.min_score:
            return self._reject(case, f"score {reg.score:.2f} < {cfg.min_score:.2f}")
        relocaliser = None  # the disambiguation's, when it picked a placement: built once
        if reg.ambiguity > cfg.max_ambiguity:
            picked = self._disambiguate(case, reg)
            if picked is None:
                why = f"ambiguous: {reg.ambiguity:.2f} > {cfg.max_ambiguity:.2f}"
                if "placements_map_fit" in case.nums:
                    why += (
                        f"; no placement's walls explain the map ({case.nums['placements_map_fit']:.0%} < "
                        f"{cfg.min_map_fit:.0%})"
                    )
                return self._reject(case, why)
            reg, relocaliser = picked
        try:
            if relocaliser is None:
                relocaliser = Relocaliser(reg.apply(self.plan), self.params)
            plan_map = relocaliser.plan
        except (FrslamError, ValueError) as exc:
            return self._reject(case, f"registered plan unusable: {exc}")
        return self._on_the_map(case, reg, plan_map, relocaliser)

    # ------------------------------------------------------------------ the checks
    def _on_the_map(self, case: _Case, reg: Any, plan_map: Any, relocaliser: Relocaliser) -> Verdict:
        """The map checks, against the accepted registration when there is one."""
        cfg, nums, acc = self.config, case.nums, case.accepted
        occ = occupied_points(case.grid)
        fit_tol, margin = case.tolerances(cfg)
        fit = relocaliser.fit_points(occ, fit_tol)
        nums["map_fit"] = fit
        if acc is not None and cfg.refine_on_agreement and cfg.refine_by == "scans":
            disp = matrix_disagreement(self.plan, acc.registration.matrix, reg.matrix)
            nums["disagreement"] = disp
            if disp <= cfg.agree_tol:
                if len(acc.plan.rooms) < len(self.plan.rooms) or acc.relocaliser.ignored is not None:
                    try:  # the rooms and wall pieces it trusts, no others
                        relocaliser = acc.relocaliser_on(reg, self.plan, self.params)
                    except (FrslamError, ValueError) as exc:
                        return self._reject(case, f"registered plan unusable: {exc}")
                    plan_map, fit = relocaliser.plan, relocaliser.fit_points(occ, fit_tol)
                    nums["map_fit"] = fit
                return self._by_the_scans(case, reg, plan_map, relocaliser, occ, fit_tol, fit, disp)
        if case.drawing_tol > 0.0:
            drawn = self._drawn_on_the_map(case, reg, relocaliser, margin, occ, fit_tol)
            if isinstance(drawn, Verdict):
                return drawn
            plan_map, relocaliser, fit = drawn
        else:
            if fit < cfg.min_map_fit:
                return self._reject(
                    case, f"plan walls explain {fit:.0%} of the map's occupied cells < {cfg.min_map_fit:.0%}"
                )
            crossing = walls_through_free_space(relocaliser, case.grid, margin)
            nums["walls_in_free_space"] = crossing
            if crossing > cfg.max_walls_in_free_space:
                # a plan known to be drawn off the building loses its wall pieces seen through
                # (_drawn_on_the_map); an accurately drawn one its rooms seen through (a wall piece
                # masked there could be the one wall that tells a near-symmetric plan's mirror from
                # the right placement)
                trusted = self._trusted_rooms(case, reg, relocaliser, margin, occ, fit_tol)
                if isinstance(trusted, str):
                    return self._walls_cross(case, crossing, trusted)
                plan_map, relocaliser, fit = trusted
        if acc is not None:
            disp = matrix_disagreement(self.plan, acc.registration.matrix, reg.matrix)
            old_fit = acc.relocaliser.fit_points(occ, fit_tol)
            nums.update(disagreement=disp, accepted_map_fit=old_fit)
            if disp <= cfg.agree_tol and fit < old_fit + SWITCH_MARGIN:
                if cfg.refine_on_agreement and fit >= old_fit:
                    better = f"the map as well or better ({fit:.0%} vs {old_fit:.0%})"
                    return self._refine(case, reg, plan_map, relocaliser, fit, disp, better)
                return self._reject(case, f"agrees with registration {acc.id} (RMS {disp:.2f} m); kept")
            if fit < old_fit + SWITCH_MARGIN:
                return self._reject(
                    case,
                    f"disagrees with registration {acc.id} (RMS {disp:.2f} m) and explains "
                    f"the map no better ({fit:.0%} vs {old_fit:.0%})",
                )
        return self._on_the_scans(case, reg, plan_map, relocaliser, fit)

    def _walls_cross(self, case: _Case, crossing: float, why: str) -> Verdict:
        """The refusal of a plan whose observed walls cross the map's free space (``why``: what
        dropping the parts seen through could not save)."""
        return self._reject(
            case,
            f"{crossing:.0%} of the plan's observed walls cross free space in the map "
            f"> {self.config.max_walls_in_free_space:.0%}{why}",
        )

    def _drawn_on_the_map(
        self, case: _Case, reg: Any, relocaliser: Relocaliser, margin: float, occ: np.ndarray, fit_tol: float
    ) -> tuple[Any, Relocaliser, float] | Verdict:
        """The map checks of a registration drawn off the building (``drawing_tol`` > 0): the wall
        pieces the map has seen through are dropped first (:meth:`_trusted_part`; a majority
        refuses), then the rest's map fit, over the map it can explain (the cells around the
        dropped pieces count neither way), passes at ``min_map_fit`` or, as on the scans
        (:meth:`_clearly_best_on_the_scans`), when it is at least :data:`MAP_FIT_FLOOR` and each
        runner-up placement, judged alike, explains at most :data:`MAP_FIT_RUNNER_UP` of it: a
        plan drawn 0.25-1 m off in a furnished building explains 43-55 % of the map at its right
        placement (Intel, kf 1,300-2,600), its wrong placements 14-36 %, and a single map moves it
        across 50 %. Returns the plan in ``map``, its relocaliser and its map fit, or the
        rejection."""
        cfg, nums = self.config, case.nums
        crossing = walls_through_free_space(relocaliser, case.grid, margin)
        nums["walls_in_free_space"] = crossing
        plan_map, fit = relocaliser.plan, relocaliser.fit_points(occ, fit_tol)
        if crossing > cfg.max_walls_in_free_space:
            trusted = self._trusted_part(case, reg, relocaliser, margin, occ, fit_tol)
            if isinstance(trusted, str):
                return self._walls_cross(case, crossing, trusted)
            plan_map, relocaliser, fit = trusted
        nums["map_fit"] = fit
        if fit >= cfg.min_map_fit:
            return plan_map, relocaliser, fit
        runner = 0.0
        if fit >= MAP_FIT_FLOOR:
            runner = nums["runner_up_map_fit"] = self._runner_up_fit(case, occ, fit, fit_tol)
            if case.alternatives and runner <= MAP_FIT_RUNNER_UP * fit:
                return plan_map, relocaliser, fit
        why = f"plan walls explain {fit:.0%} of the map's occupied cells < {cfg.min_map_fit:.0%}"
        if fit >= MAP_FIT_FLOOR and case.alternatives:
            why += f", and a runner-up placement {runner:.0%} (> {MAP_FIT_RUNNER_UP:.0%} of it)"
        return self._reject(case, why)

    def _runner_up_fit(self, case: _Case, occ: np.ndarray, fit: float, fit_tol: float) -> float:
        """The best map fit of the case's runner-up placements, each judged alike (:meth:`_alike`),
        at ``fit_tol`` metres; the search stops once one explains more than
        :data:`MAP_FIT_RUNNER_UP` of ``fit``."""
        runner = 0.0
        for m in case.alternatives:
            rel = self._alike(case, m)
            if rel is None:
                continue
            runner = max(runner, rel.fit_points(occ, fit_tol))
            if runner > MAP_FIT_RUNNER_UP * fit:
                break
        return runner

    def still_clearly_best(
        self,
        ctx: BackendContext,
        keyframe: KeyframeInfo,
        grid: Any,
        accepted: AcceptedPlan,
        drift: float,
        fit: float,
    ) -> bool:
        """The recheck of an accepted registration drawn off the building whose walls, but for the
        pieces seen through, explain ``fit`` < ``min_map_fit`` of the grown map: it stays by the
        rule that accepted it (:meth:`_drawn_on_the_map`): ``fit`` at least :data:`MAP_FIT_FLOOR`
        and each of its registration's runner-up placements, judged alike on this map, at most
        :data:`MAP_FIT_RUNNER_UP` of it."""
        case = _Case(ctx, keyframe, grid, {}, accepted, None, drift, 0, accepted.drawing_tol)
        case.alternatives = _runner_up_matrices(accepted.registration)
        if fit < MAP_FIT_FLOOR or not case.alternatives:
            return False
        fit_tol = case.tolerances(self.config)[0]
        return self._runner_up_fit(case, occupied_points(grid), fit, fit_tol) <= MAP_FIT_RUNNER_UP * fit

    def _trusted_rooms(
        self, case: _Case, reg: Any, relocaliser: Relocaliser, margin: float, occ: np.ndarray, fit_tol: float
    ) -> tuple[Any, Relocaliser, float] | str:
        """A registration whose walls cross the map's free space: the plan without the rooms the
        map has seen through (more than ``max_walls_in_free_space`` of a room's observed interior
        walls; a plan drawn differently from the building as built, e.g. a block drawn closed
        where the building has a corridor). Returns that plan in ``map``, its relocaliser and its
        map fit when those rooms are fewer than half of the rooms the registration matched and the
        rest passes the map checks (no prior then comes from a dropped room); else why not (text
        appended to the rejection)."""
        cfg, nums = self.config, case.nums
        per = rooms_seen_through(relocaliser, case.grid, margin)
        drop = [rid for rid, (seen, through) in per.items() if through > cfg.max_walls_in_free_space * seen]
        # the rooms the registration placed on the map, or whose walls the map observed
        matched = set(reg.rooms) | {rid for rid, (seen, _) in per.items() if seen > 0}
        nums["rooms_seen_through"] = len(drop)
        if not drop:
            return ""
        if 2 * len(drop) >= len(matched):
            return f"; the rooms seen through ({', '.join(drop)}) are not a minority of the {len(matched)} matched"
        kept = [r.id for r in self.plan.rooms if r.id not in set(drop)]
        try:
            part = Relocaliser(reg.apply(self.plan.subset(kept)), self.params)
        except (FrslamError, ValueError) as exc:
            return f"; the plan without the rooms seen through is unusable: {exc}"
        crossing = walls_through_free_space(part, case.grid, margin)
        fit = part.fit_points(occ, fit_tol)
        nums.update(walls_in_free_space_kept=crossing, map_fit_kept=fit)
        if crossing > cfg.max_walls_in_free_space:
            return f"; still {crossing:.0%} without the rooms seen through ({', '.join(drop)})"
        if fit < cfg.min_map_fit:
            return (
                f"; without the rooms seen through ({', '.join(drop)}) its walls explain {fit:.0%} of the map"
            )
        return part.plan, part, fit

    def _trusted_part(
        self, case: _Case, reg: Any, relocaliser: Relocaliser, margin: float, occ: np.ndarray, fit_tol: float
    ) -> tuple[Any, Relocaliser, float] | str:
        """A registration whose walls cross the map's free space: the plan without the wall
        pieces the map has seen through (:func:`~frslam_graph.plan_checks.wall_pieces_seen_through`;
        a plan drawn differently from the building as built, e.g. a block drawn closed where the
        building has a corridor, or a wall drawn a metre off). Returns the plan in ``map``, its
        relocaliser ignoring those pieces (no prior is pulled by them) and its map fit (over the
        cells it can explain) when they are a minority of the plan's observed walls (the caller
        judges the fit, :meth:`_drawn_on_the_map`); else why not (text appended to the rejection). A wrong placement draws walls across
        rooms seen empty nearly everywhere: most of its pieces are seen through."""
        cfg, nums = self.config, case.nums
        pts, dropped, rest = wall_pieces_seen_through(
            relocaliser, case.grid, margin, cfg.max_walls_in_free_space
        )
        nums.update(wall_pieces_dropped=dropped, walls_in_free_space_kept=rest)
        if dropped >= 0.5:
            return f"; the wall pieces seen through hold {dropped:.0%} of its observed walls: not a minority"
        part = ignoring_pieces(relocaliser, pts, margin)
        fit = part.fit_points(occ, fit_tol)
        nums["map_fit_kept"] = fit
        return part.plan, part, fit

    def _by_the_scans(
        self,
        case: _Case,
        reg: Any,
        plan_map: Any,
        relocaliser: Relocaliser,
        occ,
        fit_tol: float,
        fit: float,
        disp: float,
    ) -> Verdict:
        """An agreeing registration with ``refine_by`` "scans": the map was drawn at estimates
        the accepted plan's priors pulled onto it (its fit is biased towards that plan): compare
        the two on the keyframe scans, each relocalised on its own."""
        nums, acc = case.nums, case.accepted
        q_new = self.evidence.fit(case.ctx, relocaliser, case.n_keyframes)
        q_old = self.evidence.fit(case.ctx, acc.relocaliser, case.n_keyframes)
        nums.update(scan_fit=q_new, accepted_scan_fit=q_old)
        if q_new > q_old + REFINE_SCAN_MARGIN:
            better = f"the keyframe scans better ({q_new:.1%} vs {q_old:.1%})"
        elif q_new >= q_old - REFINE_SCAN_MARGIN:
            # the scans cannot tell (each scan absorbs a rigid offset of the plan): the map decides
            old_fit = acc.relocaliser.fit_points(occ, fit_tol)
            nums["accepted_map_fit"] = old_fit
            if fit < old_fit:
                return self._reject(
                    case,
                    f"agrees with registration {acc.id} (RMS {disp:.2f} m), explains the keyframe "
                    f"scans as well ({q_new:.1%} vs {q_old:.1%}) and the map no better "
                    f"({fit:.0%} vs {old_fit:.0%}); kept",
                )
            better = f"the keyframe scans as well and the map as well or better ({fit:.0%} vs {old_fit:.0%})"
        else:
            return self._reject(
                case,
                f"agrees with registration {acc.id} (RMS {disp:.2f} m) and explains the "
                f"keyframe scans worse ({q_new:.1%} vs {q_old:.1%}); kept",
            )
        return self._refine(case, reg, plan_map, relocaliser, fit, disp, better)

    def _on_the_scans(
        self, case: _Case, reg: Any, plan_map: Any, relocaliser: Relocaliser, fit: float
    ) -> Verdict:
        """The current scan and the keyframe scans on the plan; a first one against the trajectory."""
        cfg, nums = self.config, case.nums
        points = case.ctx.keyframe_scans()[0][case.keyframe.index]
        reloc = relocaliser.relocalise(points, case.keyframe.pose_map)
        nums.update(reloc_score=reloc.score, reloc_ambiguity=reloc.ambiguity)
        scan_fits = reloc.ok and reloc.score >= cfg.reloc_min_score
        # one scan is little evidence about a plan drawn off the building (it may stand where the
        # plan is drawn differently): with a second agreeing registration required anyway (drift
        # beyond confirm_after_m), the keyframe scans below and the confirmation judge it; its
        # first prior and the chi2 gate need a scan that fits (the prior is then refused)
        waived = case.drawing_tol > 0.0 and case.accepted is None and case.drift > cfg.confirm_after_m
        if not scan_fits and not waived:
            return self._reject(
                case, f"current scan does not fit the registered plan (inliers {reloc.score:.0%})"
            )
        if cfg.min_scan_fit > 0.0:
            # the keyframe scans of the whole run, each relocalised on its own: the plan of another
            # building (or a wrong placement) that the map checks let through by a small margin
            # explains them poorly
            q = (
                nums["scan_fit"]
                if "scan_fit" in nums
                else self.evidence.fit(case.ctx, relocaliser, case.n_keyframes)
            )
            nums["scan_fit"] = q
            if q < cfg.min_scan_fit and not self._clearly_best_on_the_scans(case, q):
                return self._reject(
                    case,
                    f"the keyframe scans do not fit the registered plan ({q:.1%} < {cfg.min_scan_fit:.0%})",
                )
        if case.accepted is None:
            chi2 = gate_chi2(cfg, case.ctx, case.keyframe, reloc, case.drift) if scan_fits else 0.0
            nums["chi2" if scan_fits else "current_scan_waived"] = chi2 if scan_fits else 1.0
            if chi2 > INCONSISTENT_CHI2:
                return self._reject(
                    case, f"inconsistent with the trajectory: chi2 {chi2:.1f} > {INCONSISTENT_CHI2:.1f}"
                )
            if case.drift > cfg.confirm_after_m:
                # the drift allowance has made the chi2 gate weak: a second registration that
                # agrees must confirm this one (as for loop closures with large corrections)
                # the candidates: the last CONFIRM_CANDIDATES registrations that passed every
                # other check (one odd placement in between does not reset the evidence)
                waiting = case.pending
                if not waiting:
                    why = f"{case.drift:.0f} m travelled without a prior: waiting for a second registration that agrees"
                    return self._reject(case, why, pending=(reg,))
                disp = min(matrix_disagreement(self.plan, p.matrix, reg.matrix) for p in waiting)
                nums["disagreement"] = disp
                if disp > cfg.agree_tol:
                    return self._reject(
                        case,
                        f"{case.drift:.0f} m travelled without a prior: disagrees with the previous "
                        f"{len(waiting)} registration(s) (RMS {disp:.2f} m at best); waiting for one that agrees",
                        pending=(*waiting, reg)[-CONFIRM_CANDIDATES:],
                    )
        return Verdict("accept", "accepted", nums, reg, plan_map, relocaliser, reloc, fit, pending=())

    def _clearly_best_on_the_scans(self, case: _Case, q: float) -> bool:
        """A plan drawn off the building (``drawing_tol`` > 0) in a cluttered building cannot fit
        the keyframe scans to ``min_scan_fit``: each scan's furniture and the walls drawn up to
        ``drawing_tol`` away score little whatever the placement. Its scan fit ``q`` then passes
        as in the disambiguation, against the registration's runner-up placements
        (``alternatives``, each judged alike: :meth:`_alike`): at least :data:`SCAN_FIT_FLOOR`
        instead of ``min_scan_fit``, and ``disambiguate_margin`` over each of them (a plan of
        another building fits every placement alike). ``runner_up_scan_fit`` in the numbers."""
        margin = self.config.disambiguate_margin
        if case.drawing_tol <= 0.0 or margin <= 0.0 or q < SCAN_FIT_FLOOR or not case.alternatives:
            return False
        runner = 0.0
        for m in case.alternatives:
            rel = self._alike(case, m)
            if rel is None:
                continue
            runner = max(runner, self.evidence.fit(case.ctx, rel, case.n_keyframes))
            if q < runner + margin:
                break
        case.nums["runner_up_scan_fit"] = runner
        return q >= runner + margin

    def _alike(self, case: _Case, matrix: np.ndarray) -> Relocaliser | None:
        """The relocaliser of a runner-up placement (``matrix``: plan -> map) judged like the
        registration drawn off the building: without its wall pieces the map has seen through
        (:func:`~frslam_graph.plan_checks.wall_pieces_seen_through` at the case's free-space
        margin), so that both are measured on what each can explain; None when unusable.
        Built once per case."""
        key = np.asarray(matrix, float).tobytes()
        if key not in case.alike:
            margin = case.tolerances(self.config)[1]
            try:
                rel = Relocaliser(Registration.from_matrix(matrix).apply(self.plan), self.params)
            except (FrslamError, ValueError):
                case.alike[key] = None
                return None
            pts, _, _ = wall_pieces_seen_through(rel, case.grid, margin, self.config.max_walls_in_free_space)
            case.alike[key] = ignoring_pieces(rel, pts, margin)
        return case.alike[key]

    def _disambiguate(self, case: _Case, reg: Any) -> tuple[Any, Relocaliser] | None:
        """An ambiguous registration: its placement and the registration's runner-up placements
        (``reg.details["alternatives"]``, MFR's) judged on the keyframe scans, each relocalised on
        its own (which a drifted map cannot bias). Returns the registration of the placement that
        explains them clearly best (by ``disambiguate_margin``, and at least ``min_scan_fit``)
        with its relocaliser, else None; the case's numbers get the two best fits.

        The placement picked is judged next by its map fit (``min_map_fit``, the first check after
        this one; no registration is accepted here). When no placement passes it, the verdict is a
        rejection whichever one the scans would pick: the scan fits (most of the cost, ~1-2 s
        with the plan of another building) are skipped and ``placements_map_fit`` says why."""
        cfg, nums = self.config, case.nums
        if cfg.disambiguate_margin <= 0.0 or not case.alternatives or case.accepted is not None:
            return None
        matrices = [np.asarray(reg.matrix, float), *case.alternatives]
        relocalisers: list[Relocaliser | None] = []
        for m in matrices:
            try:
                relocalisers.append(Relocaliser(type(reg).from_matrix(m).apply(self.plan), self.params))
            except (FrslamError, ValueError):
                relocalisers.append(None)  # the picked one would be "unusable": rejected too
        occ = occupied_points(case.grid)
        fit_tol = case.tolerances(cfg)[0]
        best_map_fit = max(r.fit_points(occ, fit_tol) if r is not None else 0.0 for r in relocalisers)
        if best_map_fit < cfg.min_map_fit:
            nums["placements_map_fit"] = best_map_fit
            return None
        fits = [
            self.evidence.fit(case.ctx, r, case.n_keyframes) if r is not None else 0.0 for r in relocalisers
        ]
        order = np.argsort(fits)[::-1]
        best, second = float(fits[order[0]]), float(fits[order[1]])
        nums.update(ambiguous_scan_fit=best, runner_up_scan_fit=second, placement=int(order[0]))
        if best < max(cfg.min_scan_fit, second + cfg.disambiguate_margin):
            return None
        nums["scan_fit"] = best
        case.alternatives = [m for k, m in enumerate(matrices) if k != int(order[0])]
        picked = type(reg).from_matrix(
            matrices[order[0]],
            score=reg.score,
            ambiguity=second / max(best, 1e-9),
            method=f"{reg.method}+scans",
            rooms=reg.rooms,
        )
        return picked, relocalisers[order[0]]

    # ------------------------------------------------------------------ verdicts
    @staticmethod
    def _reject(case: _Case, why: str, pending: tuple[Registration, ...] | None = None) -> Verdict:
        return Verdict("reject", why, case.nums, pending=pending)

    @staticmethod
    def _refine(
        case: _Case, reg: Any, plan_map: Any, relocaliser: Relocaliser, fit: float, disp: float, better: str
    ) -> Verdict:
        """An agreeing registration explains the data as well or better: the same placement fitted
        to more data; later relocalisations use it (earlier priors stay: they agree within
        agree_tol)."""
        why = f"agrees with registration {case.accepted.id} (RMS {disp:.2f} m) and explains {better}; refined"
        return Verdict("refine", why, case.nums, reg, plan_map, relocaliser, None, fit)


__all__ = ["RegistrationJudge", "Verdict", "tolerances"]
