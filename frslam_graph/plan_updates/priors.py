"""Floor-plan priors from relocalisations on the accepted plan (paper Alg. 3's priors).

:class:`PriorManager` relocalises a keyframe's scan on the accepted plan (every
``relocation_distance_D`` metres or ``relocation_angle_deg`` of turning, or when obstructed),
gates the result (:func:`gate_chi2`: its covariance plus the estimate's marginal plus the drift
since the last accepted prior) and adds it as a robust prior; it backfills the keyframes before
a registration, re-anchors the priors of a replaced or refined plan and removes the priors later
proven wrong (``REMOVE_CHI2``). With ``spread_over_scans`` a relocalisation, its prior, each
relinearising iteration after it and the check of the priors are deferred steps (one per scan),
each announcing its cost from a fixed cost model (ms on one core; sizes, never a clock).
Poses in ``map`` (metres, radians).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.localisation.relocalisation import Relocalisation, Relocaliser
from frslam_graph.plan_updates.accepted import AcceptedPlan
from frslam_graph.plan_updates.schedule import RegistrationSchedule
from frslam_graph.plan_updates.travel import Travel
from frslam_graph.se2 import tangent_cov, vector_cov

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# chi² gate (3 dof, default 99 %) of a relocalisation against the trajectory; larger = more priors pass
INCONSISTENT_CHI2 = 11.34
RELOC_WINDOW_MAX_XY = 2.0  # m; the window grows with the drift since the last accepted prior up to this
RELOC_WINDOW_MAX_THETA_DEG = 30.0  # deg; the heading window grows up to this
# relocalisation ambiguity (runner-up / best) accepted at most; larger = more ambiguous priors
RELOC_MAX_AMBIGUITY = 0.8
# m per m travelled since the last prior added to the gate's sigma (and window); larger = laxer gate
GATE_DRIFT_FRAC = 0.05
GATE_DRIFT_DEG_PER_M = 1.0  # deg per m travelled added to the gate's heading sigma; larger = laxer gate
GATE_SIGMA_XY = 0.05  # m; base translation sigma of the gate; larger = laxer gate
GATE_SIGMA_THETA_DEG = 1.0  # deg; base heading sigma of the gate; larger = laxer gate
# a prior whose residual chi² after optimisation exceeds this is removed as proven wrong; larger = kept more
REMOVE_CHI2 = 30.0
REMOVE_MIN_XY = 0.15  # m; ... and is at least this far off
REMOVE_MIN_THETA_DEG = 3.0  # deg; ... or turned at least this much
# share of priors contradicted at once above which all are kept (the graph, not the priors, is off)
REMOVE_MAX_SHARE = 0.3
PRIOR_KIND = "full"  # what a floor-plan prior constrains: full pose or translation only
# backfilled keyframes per new keyframe; larger = backfill done sooner, more CPU per keyframe
BACKFILL_PER_KEYFRAME = 2


class StepRunner(Protocol):
    """Runs a step generator (each ``yield`` ends one step, giving its estimated ms)."""

    def __call__(self, ctx: BackendContext, steps: Iterator[Any]) -> None: ...


def _run_on_later_scans(ctx: BackendContext, steps: Iterator[Any]) -> None:
    ctx.deferred.defer(steps)  # one step per following scan (same decisions, lower latency)


def _run_now(ctx: BackendContext, steps: Iterator[Any]) -> None:
    for _ in steps:
        pass


def get_step_runner(config: UpdatesConfig) -> StepRunner:
    """How relocalisations, priors and their checks run, chosen once: as deferred steps on the
    scans after the keyframe (``spread_over_scans``) or all at once on the keyframe."""
    return _run_on_later_scans if config.spread_over_scans else _run_now


if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext
    from frslam_graph.backend.decisions import PriorRemoval
    from frslam_graph.backend.keyframes import KeyframeInfo


def gate_chi2(
    config: UpdatesConfig,
    ctx: BackendContext,
    keyframe: KeyframeInfo,
    reloc: Relocalisation,
    travelled: float,
) -> float:
    """chi² of (relocalised - estimated) pose under reloc + marginal + drift covariances;
    ``travelled``: metres since the last accepted prior (the drift allowance)."""
    est = np.asarray(keyframe.pose_map, float)
    d = reloc.pose - est
    d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
    sxy = GATE_SIGMA_XY + GATE_DRIFT_FRAC * travelled
    sth = np.deg2rad(GATE_SIGMA_THETA_DEG + GATE_DRIFT_DEG_PER_M * travelled)
    s = reloc.covariance + np.diag([sxy**2, sxy**2, sth**2])
    try:
        s = s + vector_cov(est, ctx.graph.marginal_covariance(keyframe.index))
    except Exception:  # noqa: BLE001 - a marginal may be unavailable right after a removal
        pass
    return float(d @ np.linalg.solve(s, d))


@dataclass
class HeldReanchor:
    """Re-anchorings noted while the end-of-run refinement holds them: the registrations whose
    priors are in the graph and why (done once, at the end)."""

    previous: list[AcceptedPlan] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)

    def note(self, previous: list[AcceptedPlan], why: str | None = None) -> None:
        self.previous.extend(p for p in previous if all(p.id != q.id for q in self.previous))
        if why:
            self.reasons.append(why)


class PriorManager:
    """Relocalisations on the accepted plan as gated priors; their check (module docstring)."""

    # cost model of the deferred steps (ms on one core; right within about a factor of two):
    # measured on regime-A houses (tools/bench_backend.py), p90 in tools/README.md
    ms_relocalise: float = 7.0  # a relocalisation (median 5.8 ms)
    ms_prior: float = 2.5  # the gated prior (median 1.9 ms)
    ms_per_keyframe_settle: float = 0.004  # a relinearising iteration, per keyframe of the graph
    ms_check_priors: float = 2.0  # the check of the priors (median 1.0 ms)
    #: the relocalisation window covers this many sigmas of the gate's drift model
    window_sigmas: float = 3.0
    #: the check looks at the latest ``check_recent`` priors, at all of them every ``check_all_every``-th time
    check_recent: int = 30
    check_all_every: int = 10

    def __init__(
        self,
        config: UpdatesConfig,
        travel: Travel,
        schedule: RegistrationSchedule,
        accepted: Callable[[], AcceptedPlan | None],
        timings: dict[str, float],
    ) -> None:
        self.config = config
        self._run = get_step_runner(config)
        self.travel = travel
        self.schedule = schedule
        self.accepted = accepted  # the accepted plan when a step runs (it may change meanwhile)
        self.timings = timings
        self.dist_at_prior = 0.0  # distance at the last accepted prior (the gate's drift)
        self.dist_at_reloc = 0.0
        self.turn_at_reloc = 0.0
        self.held: HeldReanchor | None = None  # re-anchoring held by the end-of-run refinement
        self._checks = 0
        self._backfill: list[int] = []  # past keyframes to relocalise on the accepted plan
        self._backfill_anchor = 0.0  # distance at the nearest keyframe with a prior (backfill)

    @property
    def drift(self) -> float:
        """Metres travelled since the last accepted prior."""
        return self.travel.dist - self.dist_at_prior

    # ------------------------------------------------------------------ relocalisation
    def relocalisation_due(self, obstructed: bool) -> str | None:
        """Why to relocalise at this keyframe (obstructed, relocation distance or angle), or None."""
        cfg, t = self.config, self.travel
        if obstructed:
            return "obstructed"
        if t.dist - self.dist_at_reloc >= cfg.relocation_distance_D:
            return "relocation distance"
        if t.turn - self.turn_at_reloc >= np.deg2rad(cfg.relocation_angle_deg):
            return "relocation angle"
        return None

    def relocalised_now(self) -> None:
        """The relocalisation counters restart here (a registration was accepted)."""
        self.dist_at_reloc = self.travel.dist
        self.turn_at_reloc = self.travel.turn

    def relocalise(self, ctx: BackendContext, keyframe: KeyframeInfo, why: str) -> None:
        """Relocalise the keyframe's scan (its pose and points as they are now), then gate and
        add its prior, settle the graph and check the priors, as steps (:meth:`later`)."""
        points = ctx.keyframe_scans()[0][keyframe.index]
        cfg = self.config
        # the search window covers the drift since the last accepted prior, so a run of rejected
        # relocalisations does not lose the plan for good
        travelled = self.drift
        k = self.window_sigmas
        wxy = min(max(cfg.reloc_window_xy, k * GATE_DRIFT_FRAC * travelled), RELOC_WINDOW_MAX_XY)
        wth = min(
            max(cfg.reloc_window_theta_deg, k * GATE_DRIFT_DEG_PER_M * travelled),
            RELOC_WINDOW_MAX_THETA_DEG,
        )
        self.relocalised_now()
        ctx.deferred.run_all()  # the previous relocalisation's, if any: a bounded backlog
        steps = self._relocalise_steps(
            ctx, keyframe, points, wxy, np.deg2rad(wth), why, self.accepted().relocaliser
        )
        self.later(ctx, steps)

    def later(self, ctx: BackendContext, steps: Iterator[Any]) -> None:
        """Run a step generator with the runner chosen at construction (:func:`get_step_runner`)."""
        self._run(ctx, steps)

    def _relocalise_steps(
        self,
        ctx: BackendContext,
        keyframe,
        points,
        wxy: float,
        wth: float,
        why: str,
        relocaliser: Relocaliser,
    ) -> Iterator[float]:
        t0 = time.perf_counter()
        reloc = relocaliser.relocalise(points, keyframe.pose_map, wxy, wth)
        self.timings["relocalise"] += time.perf_counter() - t0
        yield self.ms_relocalise
        _, cost = yield from self._prior_steps(ctx, keyframe, reloc, why)
        yield cost
        self.check(ctx, keyframe.stamp)
        yield self.ms_check_priors

    def _prior_steps(
        self,
        ctx: BackendContext,
        keyframe,
        reloc,
        why: str,
        drift: float | None = None,
        backfill: bool = False,
    ) -> Generator[float, None, tuple[bool, float]]:
        """:meth:`offer`, then the graph's relinearising iterations one per step (each yield ends
        one, giving its estimated ms); returns whether the prior was added and the estimated cost
        of the step still open (the caller yields it)."""
        n = ctx.graph.prior_settle_iterations(keyframe.index, reloc.pose, PRIOR_KIND)
        added = self.offer(ctx, keyframe, reloc, why, drift, backfill, settle=False)
        cost = self.ms_prior
        if added:
            for _ in ctx.graph.settle_steps(n):
                yield cost
                cost = self.ms_per_keyframe_settle * len(ctx.graph)
        return added, cost

    # ------------------------------------------------------------------ the gate
    def offer(
        self,
        ctx: BackendContext,
        keyframe: KeyframeInfo,
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
        record(ctx, stamp, "relocalise", why, i, reloc.ok, **nums)
        rej = None
        if not reloc.ok:
            rej = f"relocalisation failed: {reloc.reason}"
        elif reloc.score < cfg.reloc_min_score:
            rej = f"poor fit: inliers {reloc.score:.0%} < {cfg.reloc_min_score:.0%}"
        elif reloc.ambiguity > RELOC_MAX_AMBIGUITY:
            rej = f"ambiguous: {reloc.ambiguity:.2f} > {RELOC_MAX_AMBIGUITY:.2f}"
        else:
            chi2 = gate_chi2(cfg, ctx, keyframe, reloc, self.drift if drift is None else drift)
            nums["chi2"] = chi2
            if chi2 > INCONSISTENT_CHI2:
                rej = f"inconsistent with the estimate: chi2 {chi2:.1f} > {INCONSISTENT_CHI2:.1f}"
                if not backfill:
                    self.schedule.relocalised(consistent=False)
        if rej is not None:
            record(ctx, stamp, "prior_rejected", rej, i, False, **nums)
            return False
        if not backfill:
            self.schedule.relocalised(consistent=True)
        ctx.add_prior(
            int(i),
            reloc.pose,
            tangent_cov(reloc.pose, reloc.covariance),
            source=f"reloc:reg{self.accepted().id}",
            kind=PRIOR_KIND,
            info={"score": reloc.score, "ambiguity": reloc.ambiguity},
            extra_iterations=None if settle else 0,
            why=why,
            **{k: _num(v) for k, v in nums.items()},
            accepted=True,
        )
        if not backfill:
            self.dist_at_prior = self.travel.dist
        return True

    def check(self, ctx: BackendContext, stamp: float) -> None:
        """Remove priors whose residual after optimisation is far beyond their covariance.

        A prior is proven wrong when the rest of the graph (odometry and the other priors)
        contradicts it. When a large share of the priors is contradicted at once, the culprit is
        something else (e.g. a wrong loop closure bending the trajectory): then nothing is
        removed and a "prior_conflict" event is logged instead.
        """
        handles = [h for h in ctx.graph.priors() if h.source.startswith("reloc:")]
        if not handles:
            return
        self._checks += 1
        if self._checks % self.check_all_every and len(handles) > self.check_recent:
            handles = handles[-self.check_recent :]  # every time the recent ones, now and then all
        bad = []
        for h, res in zip(handles, ctx.graph.prior_residuals(handles), strict=True):
            e = np.asarray(res.error, float)
            far = (len(e) >= 2 and float(np.hypot(e[0], e[1])) > REMOVE_MIN_XY) or (
                len(e) != 2 and abs(float(e[-1])) > np.deg2rad(REMOVE_MIN_THETA_DEG)
            )
            if res.chi2 > REMOVE_CHI2 and far:
                bad.append((h, res, e))
        if not bad:
            return
        if len(bad) > max(1, REMOVE_MAX_SHARE * len(handles)):
            record(
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
                f"proven wrong: residual chi2 {res.chi2:.1f} > {REMOVE_CHI2:.1f}, "
                f"error {np.round(e, 3).tolist()} (weight {res.weight:.2f})"
            )
            ctx.remove_priors([h], reason=why, cause="wrong", chi2=_num(res.chi2), weight=_num(res.weight))

    # ------------------------------------------------------------------ a plan's priors
    def remove_of(self, ctx: BackendContext, acc: AcceptedPlan, why: str, cause: PriorRemoval) -> list:
        """Remove the priors of a registration in one graph update; returns their handles."""
        tag = f"reloc:reg{acc.id}"
        handles = [h for h in ctx.graph.priors() if h.source == tag]
        ctx.remove_priors(handles, reason=why, cause=cause)
        return handles

    def retract(self, ctx: BackendContext, acc: AcceptedPlan, why: str) -> None:
        """A retracted registration: its priors removed as wrong; the trajectory is back on
        odometry (the gate's drift allowance restarts from 0 m)."""
        self.remove_of(ctx, acc, why, "wrong")
        self.dist_at_prior = 0.0

    def reanchor(
        self, ctx: BackendContext, previous: AcceptedPlan | list[AcceptedPlan], why: str | None = None
    ) -> None:
        """Remove the replaced registration's priors (or those of several); relocalise those
        keyframes on the accepted plan. While the end-of-run refinement holds re-anchoring, only
        note it."""
        prev = previous if isinstance(previous, list) else [previous]
        why = why or f"registration {prev[0].id} replaced"
        if self.held is not None:  # on_finish: once, at the end, for all involved
            self.held.note(prev, why)
            return
        handles = [h for p in prev for h in self.remove_of(ctx, p, why, "re-anchored")]
        scans = ctx.keyframe_scans()[0]
        added = False
        for h in handles:
            kf = ctx.keyframe(h.keyframe)
            reloc = self.accepted().relocaliser.relocalise(scans[h.keyframe], kf.pose_map)
            added |= self.offer(
                ctx, kf, reloc, "re-anchored on the new registration", drift=self.travel.dist, settle=False
            )
        if added:  # one settle for all of them, not one per prior
            ctx.graph.settle()

    # ------------------------------------------------------------------ backfill
    def queue_backfill(self, ctx: BackendContext, i: int) -> None:
        """Queue the keyframes before ``i`` (newest first, one per ``relocation_distance_D``
        metres) that have no prior of the accepted registration: relocalised on the plan a few
        per keyframe, each prior pulling its older neighbours closer before their turn, so the
        map drawn before the registration is corrected too."""
        cfg = self.config
        acc = self.accepted()
        if not cfg.backfill or acc is None:
            self._backfill = []
            return
        tag = f"reloc:reg{acc.id}"
        have = {h.keyframe for h in ctx.graph.priors() if h.source == tag}
        d = self.travel.kf_dist
        here = d[i] if i < len(d) else self.travel.dist
        queue, last = [], here
        for k in range(min(i, len(d)) - 1, -1, -1):
            if last - d[k] >= cfg.relocation_distance_D and k not in have:
                queue.append(k)
                last = d[k]
        self._backfill = queue
        self._backfill_anchor = here

    def backfill_pending(self) -> bool:
        """Whether keyframes are still queued for backfill on the accepted registration."""
        return self.accepted() is not None and bool(self._backfill)

    def run_backfill(self, ctx: BackendContext) -> None:
        """Relocalise the next ``BACKFILL_PER_KEYFRAME`` queued keyframes and add their priors
        (as steps), once the previous steps are done."""
        if self.accepted() is None or not self._backfill or ctx.deferred.pending:
            return
        for _ in range(min(BACKFILL_PER_KEYFRAME, len(self._backfill))):
            self.later(ctx, self._backfill_steps(ctx, self._backfill.pop(0)))

    def _backfill_steps(self, ctx: BackendContext, k: int) -> Iterator[float]:
        kf = ctx.keyframe(k)  # its estimate when the step runs
        t0 = time.perf_counter()
        reloc = self.accepted().relocaliser.relocalise(ctx.keyframe_scans()[0][k], kf.pose_map)
        self.timings["relocalise"] += time.perf_counter() - t0
        yield self.ms_relocalise
        drift = max(self._backfill_anchor - self.travel.kf_dist[k], 0.0)
        added, cost = yield from self._prior_steps(ctx, kf, reloc, "backfill", drift=drift, backfill=True)
        if added:
            self._backfill_anchor = self.travel.kf_dist[k]
        yield cost


def record(
    ctx: BackendContext,
    stamp: float,
    kind: str,
    reason: str,
    keyframe: int | None = None,
    accepted: bool | None = None,
    **numbers: Any,
) -> None:
    """One decision of the updater into the run's decision log (numbers as floats)."""
    data: dict[str, Any] = {k: _num(v) for k, v in numbers.items()}
    if accepted is not None:
        data["accepted"] = accepted
    ctx.log.record(kind, reason, stamp=stamp, keyframe=keyframe, **data)


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


__all__ = ["HeldReanchor", "PriorManager", "gate_chi2", "record"]
