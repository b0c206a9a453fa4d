"""Refinements of the accepted plan: its scale along its two axes, its placement at the start.

:class:`PlanRefiner` says when a scale refinement is due (``scale_refine_distance`` metres after
the acceptance, the interval doubling after each that changes nothing) and computes
:class:`Refinement` verdicts; the updater records them, replaces the accepted plan and
re-anchors its priors. Poses in ``map`` (metres, radians); a plan matrix maps plan units to map
metres.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.errors import FrslamError
from frslam_graph.localisation.relocalisation import Relocaliser, RelocaliserParams, subsample
from frslam_graph.plan_checks import fit_plan_scale
from frslam_graph.plan_updates.accepted import AcceptedPlan, runner_ups
from frslam_graph.plan_updates.evidence import ScanEvidence
from frslam_graph.plan_updates.priors import (
    RELOC_MAX_AMBIGUITY,
    RELOC_WINDOW_MAX_THETA_DEG,
    RELOC_WINDOW_MAX_XY,
)
from frslam_graph.se2 import compose, inverse, to_matrix

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
SCALE_REFINE_SIGMA = 0.05  # prior sigma of the log scale factors; larger = scale moves more freely
SCALE_REFINE_MAX = 0.1  # largest scale change accepted (fraction); larger = bigger rescalings allowed
SCALE_REFINE_MIN = 0.002  # smaller scale changes (fraction) are not tried
# scan-fit gain (mean soft score) a refined scale needs to replace the plan; larger = changes less
SCALE_REFINE_MARGIN = 0.002
# m; a refined scale moving a prior's keyframe more than this relocalises the keyframes with priors on the
# new plan
SCALE_REANCHOR_XY = 0.05

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext


@dataclass
class Refinement:
    """A ``plan_refined`` verdict: ``plan`` replaces the accepted one (None: kept, ``message``
    says why); ``reanchor``: why its priors are to be relocalised on it (None: they stay)."""

    message: str
    numbers: dict[str, Any] = field(default_factory=dict)
    plan: AcceptedPlan | None = None
    reanchor: str | None = None


class PlanRefiner:
    """The accepted plan's scale and placement at the start (see the module docstring)."""

    def __init__(
        self, plan: Any, config: UpdatesConfig, params: RelocaliserParams, evidence: ScanEvidence
    ) -> None:
        self.plan = plan
        self.config = config
        self.params = params
        self.evidence = evidence
        self._dist_at_scale = 0.0  # distance at the last scale refinement (or acceptance)
        self._interval = 0.0  # metres to the next scale refinement (0: scale_refine_distance)

    # ------------------------------------------------------------------ schedule
    def restart(self, dist: float) -> None:
        """A registration was accepted at ``dist`` metres: the next refinement is one
        ``scale_refine_distance`` away."""
        self._dist_at_scale = dist
        self._interval = 0.0

    def due(self, dist: float) -> bool:
        """A scale refinement is due at ``dist`` metres."""
        step = self.config.scale_refine_distance
        return step > 0.0 and dist - self._dist_at_scale >= max(self._interval, step)

    def ran(self, dist: float, changed: bool) -> None:
        """A refinement ran at ``dist``; when it changed nothing, look again twice as far (the
        map grows, rooms are added)."""
        step = self.config.scale_refine_distance
        self._dist_at_scale = dist
        self._interval = step if changed else 2.0 * max(self._interval, step)

    # ------------------------------------------------------------------ scale
    def scale(
        self, ctx: BackendContext, acc: AcceptedPlan, n_keyframes: int, final: bool = False
    ) -> Refinement:
        """Refine the accepted plan's scale along its two axes on keyframe scans.

        The keyframe scans (spread over the run) are relocalised on the accepted plan; then their
        poses and the plan's two scale factors (about the scans' centroid, in plan axes) are
        fitted jointly to the plan's distance field (Levenberg-Marquardt, Tukey kernel): a
        scale error shows inside single scans (two walls of a room cannot both fit), which their
        poses cannot absorb, unlike a rigid offset. A registration made on a small or drifted map
        can be a few per cent off in scale; the priors then bend the map onto it, so a
        registration on the map would repeat the error. The refined plan replaces the accepted
        one (same id; its priors are relocalised on it when it moves them by more than
        ``SCALE_REANCHOR_XY``) when it explains the scans better (``SCALE_REFINE_MARGIN``). With
        ``final`` (the end of the run: no later check) any gain on the scans is enough and all
        its priors are relocalised on the refined plan.
        """
        t0 = time.perf_counter()
        rel = acc.relocaliser
        p = rel.params
        pts, poses, soft = self._on_the_plan(ctx, rel, n_keyframes)

        def kept(why: str, **data) -> Refinement:
            self.evidence.timings["relocalise"] += time.perf_counter() - t0
            return Refinement(why, data)

        if len(poses) < 3:
            return kept(f"scale: {len(poses)} scans fit the plan; too few")
        m = np.asarray(acc.registration.matrix, float)
        lin, t = m[:2, :2], m[:2, 2]
        lin_inv = np.linalg.inv(lin)
        poses = np.asarray(poses)
        centre = np.mean((poses[:, :2] - t) @ lin_inv.T, axis=0)  # plan units
        log_s = fit_plan_scale(rel.field, pts, poses, lin, t, centre, p.truncation, SCALE_REFINE_SIGMA)
        f = np.exp(log_s)
        nums = {"scale_x": f[0], "scale_y": f[1], "scans": len(pts)}
        if np.max(np.abs(log_s)) > np.log1p(SCALE_REFINE_MAX):
            return kept(f"scale: factors {np.round(f, 4).tolist()} out of range", **nums)
        if np.max(np.abs(log_s)) < SCALE_REFINE_MIN:
            return kept(f"scale x{f[0]:.4f} / x{f[1]:.4f}: below {SCALE_REFINE_MIN:.1%}; kept", **nums)
        fix = np.eye(3)
        fix[:2, :2] = np.diag(f)
        fix[:2, 2] = centre - f * centre
        reg = acc.registration
        new = type(reg).from_matrix(
            m @ fix,
            score=reg.score,
            ambiguity=reg.ambiguity,
            method=f"{reg.method}+scale",
            rooms=reg.rooms,
            details=_runner_ups(reg, np.eye(3)),
        )
        try:
            relocaliser = acc.relocaliser_on(new, self.plan, self.params)
            plan_map = relocaliser.plan
        except (FrslamError, ValueError) as exc:
            return kept(f"scale: refined plan unusable: {exc}", **nums)
        t_fit = time.perf_counter()
        q_new, q_old = self.evidence.fit(ctx, relocaliser, n_keyframes), float(np.mean(soft))
        nums.update(scan_fit=q_new, accepted_scan_fit=q_old, time_s=time.perf_counter() - t0)
        t0 += time.perf_counter() - t_fit  # the evidence counted its own time
        if q_new <= q_old + (0.0 if final else SCALE_REFINE_MARGIN):
            return kept(
                f"scale x{f[0]:.4f} / x{f[1]:.4f} explains the keyframe scans no better "
                f"({q_new:.1%} vs {q_old:.1%}); kept",
                **nums,
            )
        self.evidence.timings["relocalise"] += time.perf_counter() - t0
        # the priors placed on the old scale are as far off as the change moves their keyframes:
        # relocalise those keyframes on the refined plan
        tag = f"reloc:reg{acc.id}"
        xy = np.asarray([h.pose[:2] for h in ctx.graph.priors() if h.source == tag]).reshape(-1, 2)
        moved = (xy - t) @ lin_inv.T @ (m @ fix)[:2, :2].T + (m @ fix)[:2, 2] - xy
        far = len(xy) and (final or float(np.max(np.hypot(moved[:, 0], moved[:, 1]))) > SCALE_REANCHOR_XY)
        return Refinement(
            f"scale x{f[0]:.4f} / x{f[1]:.4f} explains the keyframe scans better ({q_new:.1%} vs {q_old:.1%}); refined",
            nums,
            AcceptedPlan(acc.id, new, plan_map, relocaliser, acc.map_fit, acc.drawing_tol),
            f"registration {acc.id} rescaled" if far else None,
        )

    def _on_the_plan(
        self, ctx: BackendContext, rel: Relocaliser, n_keyframes: int
    ) -> tuple[list[np.ndarray], list[np.ndarray], list[float]]:
        """The sampled keyframe scans relocalised on the plan: the points (subsampled) and poses
        of those that fit it, and every scan's soft score."""
        p = rel.params
        scans = ctx.keyframe_scans()[0]
        pts, poses, soft = [], [], []
        for k in self.evidence.sample(n_keyframes):
            r = rel.relocalise(scans[k], ctx.keyframe(int(k)).pose_map)
            soft.append(r.soft_score)
            if r.ok and r.score >= self.config.reloc_min_score:
                pts.append(subsample(np.asarray(scans[k], float).reshape(-1, 2), p.voxel, p.max_points))
                poses.append(r.pose)
        return pts, poses, soft

    # ------------------------------------------------------------------ start
    def start(self, ctx: BackendContext, acc: AcceptedPlan) -> Refinement:
        """Move the accepted plan rigidly so that the first keyframe's scan fits it at the first
        keyframe's pose (the graph's anchor: ``map`` is the odom frame of the first pose). A
        registration made on a drifted map is placed consistently with the drifted map, not with
        the start; its priors then bend the early trajectory against the anchor. When the plan
        moves its priors are to be relocalised on it."""
        cfg = self.config
        # the anchor prior's pose, not keyframe 0's estimate: the plan's priors pull that
        # estimate, so fitting the plan to it would chase its own pull (the plan moving back
        # and forth at every check, each time re-anchoring all its priors)
        anchor = ctx.graph.anchor
        start = anchor.pose if anchor is not None and anchor.active else ctx.keyframe(0).pose_map
        first = ctx.keyframe_scans()[0][0]
        r = acc.relocaliser.relocalise(
            first, start, RELOC_WINDOW_MAX_XY, np.deg2rad(RELOC_WINDOW_MAX_THETA_DEG)
        )
        d = compose(start, inverse(r.pose))  # plan-consistent pose -> anchored pose
        nums = {"dx": d[0], "dy": d[1], "dtheta": d[2], "score": r.score, "ambiguity": r.ambiguity}
        moved = float(np.hypot(*(compose(d, r.pose)[:2] - r.pose[:2])))
        if not r.ok or r.score < cfg.reloc_min_score or r.ambiguity > RELOC_MAX_AMBIGUITY:
            return Refinement("start: the first scan does not fit the plan unambiguously; kept", nums)
        # d's translation includes the lever arm of its rotation about the map origin: judge the
        # move by its rotation and by how far the scan's pose moves; and move only when the fit
        # at the anchor gets clearly better (a centimetre of matching noise must not flip the
        # plan back and forth at every check)
        gain = r.soft_score - acc.relocaliser.evaluate(first, start)[1]
        nums["gain"] = gain
        small = abs(d[2]) < np.deg2rad(cfg.align_min_theta_deg) and moved < cfg.align_min_xy
        if small or gain < cfg.align_min_gain:
            return Refinement("start: the first scan fits the plan at the anchor; kept", nums)
        reg = acc.registration
        new = type(reg).from_matrix(
            to_matrix(d) @ np.asarray(reg.matrix, float),
            details=_runner_ups(reg, to_matrix(d)),
            score=reg.score,
            ambiguity=reg.ambiguity,
            method=f"{reg.method}+start",
            rooms=reg.rooms,
        )
        try:
            relocaliser = acc.relocaliser_on(new, self.plan, self.params)
            plan_map = relocaliser.plan
        except (FrslamError, ValueError) as exc:
            return Refinement(f"start: moved plan unusable: {exc}", nums)
        return Refinement(
            f"start: plan moved by {np.hypot(d[0], d[1]):.2f} m / {np.rad2deg(d[2]):.2f} deg so that the first "
            "scan fits it at the anchor",
            nums,
            AcceptedPlan(acc.id, new, plan_map, relocaliser, acc.map_fit, acc.drawing_tol),
            f"registration {acc.id} moved to the start",
        )


def _runner_ups(reg: Any, move: np.ndarray) -> dict:
    """``reg``'s runner-up placements (``details["alternatives"]``) for its refinement, moved in
    ``map`` by ``move`` (3x3) as the refinement moves the plan: the recheck of a plan drawn off
    the building judges it against them (:meth:`RegistrationJudge.still_clearly_best`)."""
    return {
        "alternatives": [
            {**a, "matrix": (move @ np.asarray(a["matrix"], float)).tolist()} for a in runner_ups(reg)
        ]
    }


__all__ = ["PlanRefiner", "Refinement"]
