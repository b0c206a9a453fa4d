"""Configuration of the SLAM backend (odometry, motion model, graph, floor-plan updates).

Units: metres, radians (angles in the config are given in **degrees** where the field name ends
in ``_deg``), seconds. ``FRSlamConfig()`` gives sane indoor defaults for a 2D LiDAR with 360–1080
beams; ``FRSlamConfig.load(path)`` reads YAML or JSON; ``FRSlamConfig.from_dict(d)`` validates a
mapping. Any invalid value raises :class:`frslam_graph.errors.ConfigError` naming the field
(e.g. ``odometry.voxel_size``) and what was expected.
"""

from __future__ import annotations

import difflib
import json
import re
import textwrap
from collections.abc import Collection
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from frslam_graph.errors import ConfigError
from frslam_graph.limits import short_repr
from frslam_graph.textfile import DuplicateKeyError, load_json, load_yaml, read_text, yaml_problem


class _Section(BaseModel):
    """A config section: unknown keys and non-finite numbers (inf, nan) are errors; errors become
    ConfigError naming the field."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise _config_error(exc, None, prefix=_SECTION_NAMES.get(type(self).__name__)) from None

    def __setattr__(self, name: str, value: Any) -> None:
        try:
            super().__setattr__(name, value)
        except ValidationError as exc:
            raise _config_error(exc, None, prefix=_SECTION_NAMES.get(type(self).__name__)) from None

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_as_number(cls, value: Any, info: ValidationInfo) -> Any:
        """``true`` / ``false`` or a string such as ``'10'`` for a number field is an error
        (pydantic would read 1 / 0, or parse the string)."""
        field = cls.model_fields.get(info.field_name or "")
        if isinstance(value, bool | str) and field is not None:
            kinds = get_args(field.annotation) or (field.annotation,)
            number = int in kinds or float in kinds
            if (
                number
                and not (isinstance(value, bool) and bool in kinds)
                and not (isinstance(value, str) and str in kinds)
            ):
                raise ValueError(f"expected a number, got {short_repr(value)}")
        return value


class OdometryConfig(_Section):
    """KISS-ICP scan odometry (planar scans as z = 0 points) and keyframe selection."""

    # KISS-ICP scan matching
    voxel_size: float = Field(
        0.1,
        gt=0.0,
        le=5.0,
        description="m; voxel of KISS-ICP's local map and of the scan downsampling; larger = fewer points, faster, coarser ICP",
    )
    max_range: float = Field(
        30.0,
        gt=0.0,
        description="m; beams longer than this are dropped; larger = more far points (noisier at range)",
    )
    min_range: float = Field(
        0.05,
        ge=0.0,
        description="m; beams shorter than this are dropped (robot body, sensor noise); must be < max_range",
    )
    initial_threshold: float = Field(
        2.0,
        gt=0.0,
        description="m; KISS-ICP correspondence distance before its adaptive threshold has seen motion; larger = tolerates larger first jumps",
    )
    fixed_threshold: float | None = Field(
        None,
        gt=0.0,
        description="m; fixed KISS-ICP correspondence distance instead of the adaptive one; null = adaptive",
    )
    local_map_scans: int = Field(
        20,
        ge=0,
        description="recent scans in a local map that refines each KISS-ICP result by point-to-line "
        "ICP (walls as lines, not KISS-ICP's sparse voxel points); larger = a longer memory, slower; "
        "20 sharpens the odometry on most logs (tools/README.md); 0 = KISS-ICP alone",
    )
    max_points_per_voxel: int = Field(
        5,
        ge=1,
        description="points kept per voxel of the local map; larger = denser map, slower ICP (KISS-ICP uses 20 in 3D)",
    )
    max_iterations: int = Field(
        500, ge=1, description="ICP iterations per scan at most; larger = more time on hard scans"
    )
    convergence_criterion: float = Field(
        1e-4,
        gt=0.0,
        description="ICP stops when its step is below this (KISS-ICP units); larger = fewer iterations, less exact",
    )
    num_threads: int = Field(
        1, ge=0, description="KISS-ICP threads; 0 = all cores; the first KissICP fixes it process-wide"
    )
    min_points: int = Field(
        20,
        ge=3,
        description="valid beams needed for ICP; fewer -> no ICP, the motion model carries the step; larger = ICP skipped more often",
    )
    scan_matching: bool = Field(
        True,
        description="false: wheel odometry alone drives the motion model (no KISS-ICP), scans still mapped and used by loop closure and plan priors; ignored without wheel odometry",
    )
    # keyframes
    keyframe_distance: float = Field(
        0.3,
        gt=0.0,
        description="m; keyframe every this much travel; larger = fewer keyframes, faster, coarser graph",
    )
    keyframe_angle_deg: float = Field(
        10.0,
        gt=0.0,
        le=180.0,
        description="deg; keyframe every this much turning; larger = fewer keyframes, coarser graph",
    )
    keyframe_max_interval_s: float | None = Field(
        None,
        gt=0.0,
        description="s; a keyframe at least this often even when standing still, so loop closure and plan updates still run when progress is obstructed; null = never",
    )
    # ICP noise model: covariance from the scan's Hessian
    icp_sigma: float = Field(
        0.03,
        gt=0.0,
        description="m; point-to-line residual sigma of the ICP covariance; larger = ICP steps trusted less",
    )
    degeneracy_threshold: float = Field(
        0.04,
        gt=0.0,
        lt=0.5,
        description="smallest / largest eigenvalue of the summed point normals' outer products below which a scan is degenerate (a corridor); larger = more scans degenerate",
    )
    normal_neighbours: int = Field(
        2,
        ge=1,
        le=10,
        description="beam offset k: a point's normal is perpendicular to p[i+k] - p[i-k] (degeneracy test); larger = smoother normals",
    )
    # wheel odometry noise: sigma_d = dist_frac * d, sigma_theta = rot_per_m * d + rot_frac * |dtheta|
    wheel_dist_frac: float = Field(
        0.08,
        gt=0.0,
        description="translation sigma per metre travelled (fraction), of a wheel increment as paired with its scan; larger = wheels trusted less, the scan carries more of each step (tools/README.md, tuning history)",
    )
    wheel_rot_per_m_deg: float = Field(
        1.0, ge=0.0, description="deg per m travelled of heading sigma; larger = wheel heading trusted less"
    )
    wheel_rot_frac: float = Field(
        0.02,
        ge=0.0,
        description="heading sigma per radian turned (fraction); larger = wheel turns trusted less",
    )
    wheel_sigma_floor_xy: float = Field(
        0.008,
        gt=0.0,
        description="m; smallest wheel translation sigma per step (pairing a wheel reading with a scan: stamps, delays); larger = ICP carries each step where it sees structure",
    )
    wheel_correlation_length: float = Field(
        5.0,
        ge=0.0,
        description="m; distance over which wheel errors (wheel radius, heading bias) stay correlated where the wheels alone carry the motion; larger = wheel chains trusted less",
    )
    wheel_sigma_floor_theta_deg: float = Field(
        0.5,
        gt=0.0,
        description="deg; smallest wheel heading sigma per step (wheel heading errors are systematic); larger = ICP keeps the heading",
    )
    # constant-velocity prediction (no wheel odometry)
    cv_sigma_xy_per_s: float = Field(
        0.5, gt=0.0, description="m per s; random-walk translation sigma of the constant-velocity prediction"
    )
    cv_sigma_theta_deg_per_s: float = Field(
        30.0, gt=0.0, description="deg per s; random-walk heading sigma of the constant-velocity prediction"
    )
    # fault gates
    icp_gate: Literal["fuse", "reject"] = Field(
        "fuse",
        description="an ICP result beyond the gate from the wheel increment: fuse (plain EKF update) or reject (the motion model carries the step, the scan is not mapped)",
    )
    max_speed: float = Field(
        3.0, gt=0.0, description="m/s; faster wheel increments are jumps; larger = fewer jumps detected"
    )
    max_turn_rate_deg: float = Field(
        360.0, gt=0.0, description="deg/s; faster wheel turns are jumps; larger = fewer jumps detected"
    )

    @model_validator(mode="after")
    def _ranges(self) -> OdometryConfig:
        if self.min_range >= self.max_range:
            raise ValueError("min_range must be smaller than max_range")
        return self


class GraphConfig(_Section):
    """GTSAM Pose2 graph: noise floors, robust prior kernel, iSAM2 settings."""

    prior_kernel: Literal["cauchy", "geman_mcclure", "huber", "none"] = Field(
        "cauchy", description="robust kernel of floor-plan priors (none = plain Gaussian)"
    )
    prior_kernel_param: float = Field(
        2.0,
        gt=0.0,
        description="sigmas (whitened units); width of the prior kernel; larger = outlying priors pull harder",
    )
    prior_sigma_floor_xy: float = Field(
        0.02,
        gt=0.0,
        description="m; smallest translation sigma of a floor-plan prior; larger = priors trusted less",
    )
    prior_sigma_floor_theta_deg: float = Field(
        0.5,
        gt=0.0,
        description="deg; smallest heading sigma of a floor-plan prior; larger = priors trusted less",
    )
    relinearize_threshold: float = Field(
        0.01,
        gt=0.0,
        description="iSAM2 relinearises variables whose update exceeds this; larger = faster, less exact streaming estimate",
    )
    relinearize_skip: int = Field(
        10,
        ge=1,
        description="iSAM2 relinearises every this many updates while streaming (settle() after priors forces it); larger = faster",
    )
    prior_settle_near_iterations: int = Field(
        1,
        ge=0,
        description="forced relinearising iSAM2 steps after a floor-plan prior within 5 cm and 1 deg of the estimate (others get 10; each a few ms on a large graph); larger = slower, settles more",
    )
    factorization: Literal["QR", "CHOLESKY"] = Field(
        "CHOLESKY",
        description="iSAM2 linear solver: CHOLESKY (a third of QR's memory and CPU on a graph of "
        "many passes; same relation errors on the real logs) or QR",
    )
    batch_relative_tolerance: float = Field(
        1e-6,
        gt=0.0,
        description="LM batch stops when the error drops by less than this fraction; larger = stops earlier",
    )


class UpdatesConfig(_Section):
    """Floor-plan update strategy (paper Alg. 3, :mod:`frslam_graph.plan_updates.updater`).

    Registration triggers: the mapped area reached ``first_register_area_m2`` (first attempt) or
    grew by ``register_min_growth_m2`` and a share of its area since the last attempt, or
    progress is obstructed. A registration is accepted when ok, ``score >= min_score``,
    ``ambiguity <= max_ambiguity``, the registered plan's walls explain ``min_map_fit`` of the
    map's occupied cells and the current scan relocalises consistently. Every
    ``relocation_distance_D`` metres the current scan is relocalised against the plan; a good,
    unambiguous match passing a chi² gate against the estimate becomes a robust prior.
    """

    enabled: bool = Field(
        True, description="register the floor plan and add its priors (false = plain SLAM even with a plan)"
    )
    register_min_growth_m2: float = Field(
        4.0,
        ge=0.0,
        description="m²; the map must grow by this (and by 20 % of its area) before another registration; larger = fewer attempts",
    )
    relocation_distance_D: float = Field(
        1.0,
        gt=0.0,
        description="m; relocalise the scan on the plan every this much travel; larger = fewer priors, less CPU",
    )
    relocation_angle_deg: float = Field(
        30.0, gt=0.0, description="deg; also relocalise after turning this much; larger = fewer priors"
    )
    max_ambiguity: float = Field(
        0.9,
        gt=0.0,
        le=1.0,
        description="registration ambiguity (runner-up / best) accepted at most; larger = more ambiguous registrations accepted",
    )
    min_score: float = Field(
        0.5, ge=0.0, le=1.0, description="registration score needed (0..1); larger = stricter acceptance"
    )
    map_resolution: float = Field(
        0.05,
        ge=0.01,
        description="m; cell of the occupancy map registered on the plan; larger = faster, coarser",
    )
    # registration triggers and acceptance
    first_register_area_m2: float = Field(
        12.0,
        ge=0.0,
        description="m²; mapped area at the first registration attempt; larger = later but better-informed first attempt",
    )
    register_retry_distance: float = Field(
        15.0,
        gt=0.0,
        description="m travelled; retry the registration this often while none is accepted; larger = fewer retries",
    )
    register_retry_backoff: float = Field(
        2.0,
        ge=1.0,
        description="factor on the retry distance after each retry on a map that has not grown by register_min_growth_m2 (any growth resets it); 1 = off",
    )
    register_retry_max_distance: float = Field(
        60.0, gt=0.0, description="m; the backed-off retry distance grows up to this"
    )
    register_recheck_distance: float = Field(
        3.0,
        ge=0.0,
        description="m; while none is accepted, a registration that matched but failed the checks is retried after this travel (a fresh map before drift grows); 0 = off",
    )
    register_recheck_max: int = Field(
        3,
        ge=0,
        description="quick rechecks in a row at most (an attempt another trigger made starts a new run); larger = more attempts",
    )
    register_refine_distance: float = Field(
        20.0,
        ge=0.0,
        description="m; with a registration accepted, register again after this travel without an attempt; 0 = off",
    )
    register_refine_max: int = Field(3, ge=0, description="such re-registrations at most; 0 = off")
    min_map_fit: float = Field(
        0.5,
        ge=0.0,
        le=1.0,
        description="share of occupied map cells near a plan wall needed to accept; larger = stricter acceptance",
    )
    min_scan_fit: float = Field(
        0.85,
        ge=0.0,
        le=1.0,
        description="mean soft score with which keyframe scans (refine_scan_samples, each relocalised) must fit a registration to accept it; 0 = off",
    )
    disambiguate_margin: float = Field(
        0.05,
        ge=0.0,
        description="before any is accepted, an ambiguous registration's placement is taken if it explains the keyframe scans better than the runner-ups by this margin; 0 = rejected",
    )
    max_walls_in_free_space: float = Field(
        0.1,
        ge=0.0,
        le=1.0,
        description="share of observed interior plan walls in mapped free space accepted at most; larger = laxer",
    )
    # "near a wall" / "in free space" tolerances grow with the travel since the last accepted prior
    map_fit_distance: float = Field(
        0.1,
        gt=0.0,
        description="m; an occupied cell within this of a plan wall is 'near' it; grows by 1 cm per m travelled since the last accepted prior; larger = laxer fit",
    )
    map_fit_distance_max: float = Field(0.25, gt=0.0, description="m; map_fit_distance grows up to this")
    free_space_margin: float = Field(
        0.2,
        ge=0.0,
        description="m; 'in free space' means farther than this from any occupied cell; grows like map_fit_distance; larger = laxer",
    )
    free_space_margin_max: float = Field(0.4, ge=0.0, description="m; free_space_margin grows up to this")
    retract_walls_in_free_space: float = Field(
        0.2,
        ge=0.0,
        le=1.0,
        description="the accepted registration is retracted when the grown map shows this share of its walls in free space; larger = retracted later",
    )
    agree_tol: float = Field(
        0.3, gt=0.0, description="m; RMS displacement of plan corners within which two registrations agree"
    )
    confirm_after_m: float = Field(
        20.0,
        ge=0.0,
        description="m; with none accepted, after this travel without a prior a registration needs a second, agreeing one before it is accepted",
    )
    refine_on_agreement: bool = Field(
        True,
        description="an agreeing registration (within agree_tol) that explains the grown map at least as well refines the accepted one",
    )
    refine_by: Literal["map", "scans"] = Field(
        "scans",
        description="'explains at least as well' on: map (its occupied cells, biased towards the accepted plan) or scans (refine_scan_samples keyframe scans relocalised on both plans)",
    )
    refine_scan_samples: int = Field(
        24,
        ge=1,
        description="keyframe scans spread over the run used by the scan-fit checks; larger = surer, slower",
    )
    # scale refinement of the accepted plan
    scale_refine_distance: float = Field(
        20.0,
        ge=0.0,
        description="m after an acceptance; fit the plan's scale along its two axes to keyframe scans (interval doubles after a fit changing nothing); 0 = off",
    )
    align_to_start: bool = Field(
        True,
        description="with each scale refinement, move the plan rigidly so that the first keyframe's scan fits it at the anchor (the first pose)",
    )
    align_min_xy: float = Field(
        0.02, ge=0.0, description="m; ... when it is off by at least this (or align_min_theta_deg)"
    )
    align_min_theta_deg: float = Field(0.2, ge=0.0, description="deg; ... or turned by at least this")
    align_min_gain: float = Field(
        0.002,
        ge=0.0,
        description="... and only when the first scan's soft fit at the anchor improves by this much",
    )
    final_refine: bool = Field(
        True,
        description="at the end of an offline run, one more registration on the complete map, whatever max_registrations left (with none accepted it is judged as a first one), and scale refinement (the final plan depends less on timing)",
    )
    max_registrations: int = Field(
        40,
        ge=1,
        description="registration attempts per run at most; larger = more CPU on plans that do not fit",
    )
    # relocalisation against the registered plan
    reloc_window_xy: float = Field(
        0.75,
        gt=0.0,
        description="m; translation half-width of the relocalisation search; larger = slower, finds larger drift",
    )
    reloc_window_theta_deg: float = Field(
        15.0, gt=0.0, le=180.0, description="deg; heading half-width of the relocalisation search"
    )
    reloc_min_score: float = Field(
        0.5, ge=0.0, le=1.0, description="relocalisation score needed (0..1); larger = fewer, surer priors"
    )
    reloc_resolution: float = Field(
        0.025,
        ge=0.01,
        description="m; cell of the plan's distance field for relocalisation; larger = faster, coarser",
    )
    wall_half_thickness: float = Field(
        0.06, ge=0.0, description="m; half the plan's wall thickness (rooms are eroded by it)"
    )
    reloc_sigma_floor_xy: float = Field(
        0.02, gt=0.0, description="m; smallest translation sigma of a relocalisation"
    )
    reloc_sigma_floor_theta_deg: float = Field(
        0.3, gt=0.0, description="deg; smallest heading sigma of a relocalisation"
    )
    backfill: bool = Field(
        True,
        description="after a registration is accepted, relocalise the keyframes before it on the plan too (one per relocation_distance_D, newest first)",
    )
    spread_over_scans: bool = Field(
        True,
        description="relocalisation, prior and its check run as separate steps on the scans after the keyframe (same decisions, lower per-scan latency)",
    )
    background_registration_s: float = Field(
        0.0,
        ge=0.0,
        le=60.0,
        description="s of recording a registration of the plan (its map, the recheck of the accepted one, the "
        "judge's checks: 0.3-3 s of CPU on the Intel lab) runs in a background thread before its verdict is "
        "applied, at the first keyframe that late (waiting for it if it is not done); 0 = in the step of the "
        "keyframe that triggered it, which stalls that scan. Set it (e.g. 2) when streaming on a robot that must "
        "not stall; results depend on the recording only, never on how fast the registration ran (the later "
        "verdicts cost the simulator's regime-A houses 0.004 -> 0.007 m ATE at 2 s)",
    )


class LoopClosureConfig(_Section):
    """Loop closure (:mod:`frslam_graph.loop_closure.closer`, its scan matcher
    :mod:`frslam_graph.loop_closure.submap_matching`): candidates, matching, acceptance."""

    enabled: bool = Field(
        True, description="search for loop closures (false = odometry and plan priors only; faster, drifts)"
    )
    # candidates and the search around them
    search_window_xy: float = Field(
        2.0,
        gt=0.0,
        description="m; translation half-width of the correlative search around the prediction (or the candidate); larger = slower, finds larger drift",
    )
    attempt_every: int = Field(
        2, ge=1, description="keyframes between attempts; larger = less CPU, closures found later"
    )
    max_candidates: int = Field(
        2, ge=1, description="candidates matched per attempt; larger = more CPU, more closures"
    )
    max_candidates_idle: int = Field(
        3, ge=1, description="... or this many when nothing is queued (the work keeps up with the budget)"
    )
    retry_keyframes: int = Field(
        30, ge=0, description="a region is not retried within this many keyframes; larger = fewer retries"
    )
    redundant_travel: float = Field(
        0.0,
        ge=0.0,
        description="m; no search while a keyframe in the search radius is tied to this one by a graph path of at most this travel (closures count zero); 0 = off",
    )
    redundant_travel_with_plan: float = Field(
        6.0,
        ge=0.0,
        description="m; redundant_travel while floor-plan priors are in the graph (they hold the map); 0 = always search",
    )
    redundant_turn_deg: float = Field(
        90.0, ge=0.0, description="deg; ... and at most this much turning on that path"
    )
    # submaps (points in the keyframe's frame)
    max_point_range: float = Field(
        15.0, gt=0.0, description="m; scan points farther from their keyframe are left out of submaps"
    )
    # matcher
    resolution: float = Field(
        0.05,
        ge=0.01,
        description="m; cell of the submap likelihood field (at least 0.01: finer asks for gigabytes); larger = faster, coarser",
    )
    likelihood_sigma: float = Field(
        0.1,
        gt=0.0,
        description="m; width of the likelihood field around submap points; larger = smoother, less exact",
    )
    # acceptance
    min_inlier_fraction: float = Field(
        0.6, ge=0.0, le=1.0, description="inlier fraction needed; larger = fewer, surer closures"
    )
    max_ambiguity: float = Field(
        0.85,
        gt=0.0,
        le=1.0,
        description="second peak / best accepted at most; larger = more aliased closures accepted",
    )
    max_free_violation: float = Field(
        0.1,
        ge=0.0,
        le=1.0,
        description="share of query points in space the reference saw free (another place that looks alike) accepted at most; larger = laxer",
    )
    free_space_margin: float = Field(
        0.3, gt=0.0, description="m; 'seen free' means farther than this from the reference's points"
    )
    # large corrections need a second, consistent closure before entering the graph
    pending_keyframes: int = Field(
        30, ge=1, description="a pending closure waits this many keyframes for confirmation"
    )
    confirm_min_inlier_fraction: float = Field(
        0.45,
        ge=0.0,
        le=1.0,
        description="inlier fraction with which a match agreeing with a pending closure confirms it (alone it is rejected) when that closure moves the robot at most search_window_xy; = min_inlier_fraction: off",
    )
    verify_back_travel: float = Field(
        2.0,
        ge=0.0,
        description="m; when a large correction goes pending, the keyframe this far back is matched where it predicts (an independent check); 0 = off",
    )
    hypothesis_window_xy: float = Field(
        2.0,
        gt=0.0,
        description="m; each attempt first checks where the latest pending closure predicts the robot, in this half-window",
    )
    hypothesis_window_theta_deg: float = Field(
        10.0, gt=0.0, description="deg; heading half-window of that check"
    )
    # closure factors: robust kernel (whitened units), pruning
    kernel: Literal["cauchy", "geman_mcclure", "huber", "none"] = Field(
        "cauchy",
        description="robust kernel of closure factors (a confirmed pair may enter as plain Gaussians; none = Gaussian)",
    )
    kernel_param: float = Field(
        4.0, gt=0.0, description="sigmas (whitened); kernel width; larger = outlying closures pull harder"
    )
    prune_chi2: float = Field(
        200.0,
        ge=0.0,
        description="an accepted closure whose residual chi² exceeds this (and is 0.3 m or 3 deg off) is removed, worst first; 0 = off",
    )
    prune_pair_contradictions: int = Field(
        10,
        ge=1,
        description="a confirmed pair that this many older closures disagree with at once is removed before them; larger = pairs kept more",
    )
    final_alignment_rounds: int = Field(
        1,
        ge=0,
        description="rounds of dense scan-to-submap constraints between passes when a run finishes "
        "(frslam_graph.loop_closure.final_alignment): each matches every keyframe against the keyframes of other "
        "passes near it and re-optimises; 0 = off (finish() only runs the LM batch, faster); 2 = match "
        "again at the re-optimised estimate (on the real logs within 0.0001 m, for 3-6 % more run time); "
        "also off when loop closure is off",
    )
    final_alignment_radius: float = Field(
        2.0,
        gt=0.0,
        description="m; keyframes of other passes within this distance of a keyframe are matched to it "
        "by the final alignment; larger ties more places (more time at finish)",
    )
    # Anytime scheduling (bounded latency per add_scan): a keyframe queues its candidates (every
    # attempt_every keyframes); every scan then runs *steps* of the queued work (a submap build,
    # a chunk of the correlative search of a bounded number of field look-ups, the ICP
    # data, one ICP refinement, one relinearising iSAM2 update after a closure; an LM batch after
    # a large correction is one step) while their estimated cost fits in budget_ms. The estimate
    # comes from the sizes involved (look-ups, grid cells, points, keyframes), not from a clock,
    # so results do not depend on the machine's speed. A step estimated above the budget runs
    # alone. FRSlam.finish() runs what is left.
    budget_ms: float = Field(
        8.0,
        gt=0.0,
        description="ms (estimated cost, not clock) of loop-closure work per scan (a scanner slower than 0.3 s per scan: per 0.3 s of its period); larger = closures sooner, higher latency",
    )
    keyframe_budget_ms: float = Field(
        4.0,
        gt=0.0,
        description="ms; the budget on keyframe scans (their graph update and plan updates run there too)",
    )
    settle_small: int = Field(
        0,
        ge=0,
        description="relinearising iSAM2 iterations (each a step) after a small closure at most; larger = more CPU",
    )
    wall_budget_ms: float | None = Field(
        None,
        gt=0.0,
        description="ms; optional wall-clock cap per add_scan (then results depend on the machine's load); null = the cost model alone (deterministic)",
    )


def _first_line(section: type[BaseModel]) -> str:
    """The first sentence of a section's docstring (its description in the dump)."""
    text = " ".join((section.__doc__ or "").split("\n\n")[0].split()).rstrip(".")
    return re.sub(r":\w+:`([^`]*)`", r"\1", text)  # :mod:`name` -> name


class FRSlamConfig(_Section):
    """Whole-backend configuration; see the section classes for fields and units."""

    odometry: OdometryConfig = Field(OdometryConfig(), description=_first_line(OdometryConfig))
    graph: GraphConfig = Field(GraphConfig(), description=_first_line(GraphConfig))
    updates: UpdatesConfig = Field(UpdatesConfig(), description=_first_line(UpdatesConfig))
    loop_closure: LoopClosureConfig = Field(LoopClosureConfig(), description=_first_line(LoopClosureConfig))

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, source: str | Path | None = None) -> FRSlamConfig:
        """Validate a nested mapping; raise ConfigError naming the first bad field."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"expected a mapping of sections, got {type(data).__name__}", source=source)
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise _config_error(exc, source) from None

    @classmethod
    def load(cls, path: str | Path) -> FRSlamConfig:
        """Read a YAML (.yaml/.yml) or JSON (.json) config file."""
        path = Path(path)
        text = read_text(path, ConfigError, "a YAML or JSON configuration", allow_empty=True)
        kind = path.suffix.lstrip(".") or "YAML"
        try:
            data = (
                load_json(text) if path.suffix.lower() == ".json" else load_yaml(text)
            )  # no aliases, no duplicate keys
        except RecursionError:
            raise ConfigError(f"not valid {kind}: nested too deeply", source=path) from None
        except (json.JSONDecodeError, DuplicateKeyError, Exception) as exc:  # yaml.YAMLError: no import here
            mark = getattr(exc, "problem_mark", None)
            where = f"line {mark.line + 1}" if mark is not None else None
            if isinstance(exc, json.JSONDecodeError):
                where, what = f"line {exc.lineno} column {exc.colno}", exc.msg
            else:
                what = yaml_problem(exc) if mark is not None else short_repr(str(exc), 200)[1:-1]
            raise ConfigError(f"not valid {kind}: {what}", source=path, where=where) from None
        return cls.from_dict(data, source=path)

    def save(self, path: str | Path) -> None:
        """Write the config as YAML or JSON (by suffix)."""
        path = Path(path)
        data = self.model_dump()
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps(data, indent=2), encoding="utf-8")
        else:
            import yaml

            path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")

    def to_yaml(self, keys: Collection[str] | None = None) -> str:
        """YAML of this config, sections nested, each field's description as a ``#`` comment above
        it; ``keys`` (dotted, e.g. ``BASIC_KEYS``) limits it to those fields (default: every field).
        :meth:`load` reads it back to this config (the fields left out at their defaults)."""
        data = self.model_dump()
        scope = "every key" if keys is None else "the common keys; frslam config dump --all lists every key"
        lines = [
            "# frslam configuration (FRSlamConfig), " + scope,
            "# units: m, s, degrees where the key ends in _deg; use with: frslam run --config FILE",
        ]
        for section, field in type(self).model_fields.items():
            fields = field.annotation.model_fields
            names = [n for n in fields if keys is None or f"{section}.{n}" in keys]
            if names:
                lines += ["", *_comment(field.description, ""), f"{section}:"]
            for name in names:
                lines += [
                    *_comment(fields[name].description, "  "),
                    f"  {name}: {_yaml_scalar(data[section][name])}",
                ]
        return "\n".join(lines) + "\n"

    def with_updates(self, **sections: dict[str, Any]) -> FRSlamConfig:
        """A copy with some fields changed, e.g. ``cfg.with_updates(odometry={"voxel_size": 0.2})``."""
        data = self.model_dump()
        for name, values in sections.items():
            if name not in data:
                raise ConfigError(unknown_key_message([name]), where=name)
            data[name].update(values)
        return type(self).from_dict(data)


#: the fields a user commonly changes (``frslam config dump`` without ``--all``): the sensor's
#: range, map and keyframe density, wheel-only odometry, whether and when the floor plan is used,
#: loop closure on / off, its per-scan budget and the final alignment, the plan priors' kernel
BASIC_KEYS: tuple[str, ...] = (
    "odometry.max_range",
    "odometry.min_range",
    "odometry.voxel_size",
    "odometry.keyframe_distance",
    "odometry.keyframe_angle_deg",
    "odometry.scan_matching",
    "graph.prior_kernel",
    "updates.enabled",
    "updates.first_register_area_m2",
    "updates.register_min_growth_m2",
    "updates.relocation_distance_D",
    "loop_closure.enabled",
    "loop_closure.budget_ms",
    "loop_closure.final_alignment_rounds",
)


def _comment(text: str | None, indent: str) -> list[str]:
    """``text`` as YAML comment lines at ``indent``, wrapped at 100 characters."""
    return [f"{indent}# {line}" for line in textwrap.wrap(text or "", 98 - len(indent))]


def _yaml_scalar(value: Any) -> str:
    """One value in YAML's own spelling (PyYAML reads ``1e-06`` as a string, ``1.0e-06`` as a float)."""
    import yaml

    return yaml.safe_dump(value, default_flow_style=True).removesuffix("...\n").strip()


_SECTION_NAMES = {
    "OdometryConfig": "odometry",
    "GraphConfig": "graph",
    "UpdatesConfig": "updates",
    "LoopClosureConfig": "loop_closure",
}


def _config_error(exc: ValidationError, source: str | Path | None, prefix: str | None = None) -> ConfigError:
    err = exc.errors()[0]
    inner = (err.get("ctx") or {}).get("error")
    if isinstance(inner, ConfigError):  # a nested section already named the field
        return ConfigError(inner.message, source=source, where=inner.where)
    loc = [str(p) for p in err.get("loc", ())]
    if prefix:
        loc.insert(0, prefix)
    where = ".".join(loc) or None
    msg = err.get("msg", "invalid value")
    if err.get("type") == "extra_forbidden" and loc:
        msg = unknown_key_message(loc)
    elif err.get("type") == "value_error":
        msg = msg.removeprefix("Value error, ")
    elif "input" in err and err.get("type") != "missing":
        msg = f"{msg} (got {short_repr(err['input'])})"
    more = len(exc.errors()) - 1
    if more:
        msg += f"; and {more} more error(s)"
    return ConfigError(msg, source=source, where=where)


_LIST_HINT = "frslam config dump --all lists every key"


def unknown_key_message(loc: list[str]) -> str:
    """What to say about the unknown key ``loc`` (``["section"]`` or ``["section", "key"]``):
    the closest valid keys of its section (or, with none there, of the other sections)."""
    *parents, key = loc
    model: type[BaseModel] = FRSlamConfig
    for name in parents:
        inner = model.model_fields.get(name)
        if (
            inner is None
            or not isinstance(inner.annotation, type)
            or not issubclass(inner.annotation, BaseModel)
        ):
            return f"unknown key ({_LIST_HINT})"
        model = inner.annotation
    what = "section" if model is FRSlamConfig else "key"
    prefix = "".join(f"{name}." for name in parents)
    close = [prefix + k for k in difflib.get_close_matches(key, list(model.model_fields), n=3)]
    if not close and parents:  # a key of another section?
        elsewhere = {
            f"{section}.{name}": name
            for section, field in FRSlamConfig.model_fields.items()
            for name in field.annotation.model_fields
        }
        hits = set(difflib.get_close_matches(key, set(elsewhere.values()), n=3))
        close = sorted(k for k, name in elsewhere.items() if name in hits)
    if close:
        return f"unknown {what}; did you mean {' or '.join(close)}? ({_LIST_HINT})"
    if what == "section":
        return f"unknown section (expected one of {', '.join(FRSlamConfig.model_fields)})"
    return f"unknown key ({_LIST_HINT})"
