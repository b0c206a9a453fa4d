"""Configuration of the SLAM backend (odometry, motion model, graph, floor-plan updates).

Units: metres, radians (angles in the config are given in **degrees** where the field name ends
in ``_deg``), seconds. ``FRSlamConfig()`` gives sane indoor defaults for a 2D LiDAR with 360–1080
beams; ``FRSlamConfig.load(path)`` reads YAML or JSON; ``FRSlamConfig.from_dict(d)`` validates a
mapping. Any invalid value raises :class:`frslam_graph.errors.ConfigError` naming the field
(e.g. ``odometry.voxel_size``) and what was expected.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from frslam_graph.errors import ConfigError


class _Section(BaseModel):
    """A config section: unknown keys are errors; errors become ConfigError naming the field."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

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


class OdometryConfig(_Section):
    """KISS-ICP scan odometry (planar scans as z = 0 points) and keyframe selection."""

    voxel_size: float = Field(0.1, gt=0.0, le=5.0)
    max_range: float = Field(30.0, gt=0.0)
    min_range: float = Field(0.05, ge=0.0)
    initial_threshold: float = Field(2.0, gt=0.0)
    fixed_threshold: float | None = Field(None, gt=0.0)
    min_motion: float = Field(0.1, ge=0.0)
    # KISS-ICP's 20 suits 3D voxels of 0.5-1 m; a 0.1 m voxel of a planar scan holds a short
    # wall segment, which 5 points describe: each ICP step then searches a quarter of the points
    # (worker CPU per scan 2.23 -> 1.58 ms on the synthetic room; odometry ATE there 0.041 ->
    # 0.028 m; regime B over 8 houses mean ATE 0.228 -> 0.215 m without the plan, 0.045 ->
    # 0.033 m with it; regime A 0.032 -> 0.025 / 0.020 -> 0.015 m; ACES 0.0456 -> 0.0471 m, the
    # spread of its loop closures under small perturbations, short relations 0.0415 -> 0.0411 m)
    max_points_per_voxel: int = Field(5, ge=1)
    max_iterations: int = Field(500, ge=1)
    convergence_criterion: float = Field(1e-4, gt=0.0)
    num_threads: int = Field(1, ge=0)  # 0 = all cores; the first KissICP fixes it process-wide
    min_points: int = Field(20, ge=3)  # fewer valid beams -> no ICP, motion-model fallback
    # False: wheel odometry alone drives the motion model (no KISS-ICP); scans are still mapped
    # and used by loop closure and floor-plan priors. Ignored for scans without wheel odometry.
    scan_matching: bool = True
    keyframe_distance: float = Field(0.3, gt=0.0)
    keyframe_angle_deg: float = Field(10.0, gt=0.0, le=180.0)
    # a keyframe at least this often (s) even when standing still, so the per-keyframe hooks (loop
    # closure, floor-plan update strategy) still run when progress is obstructed; None = never
    keyframe_max_interval_s: float | None = Field(None, gt=0.0)
    # ICP noise model: point-to-line residual sigma (m) -> covariance from the scan's Hessian,
    # inflated by ``icp_cov_inflation`` and floored by the sigma floors below.
    icp_sigma: float = Field(0.03, gt=0.0)
    icp_cov_inflation: float = Field(1.0, ge=1.0)
    icp_sigma_floor_xy: float = Field(0.001, gt=0.0)
    icp_sigma_floor_theta_deg: float = Field(0.01, gt=0.0)
    # Degeneracy: smallest / largest eigenvalue of the summed point normals' outer products.
    degeneracy_threshold: float = Field(0.04, gt=0.0, lt=0.5)
    degenerate_sigma: float = Field(10.0, gt=0.0)  # ICP sigma (m) along a degenerate axis
    normal_neighbours: int = Field(2, ge=1, le=10)
    # Wheel odometry noise: sigma_d = dist_frac * d, sigma_theta = rot_per_m * d + rot_frac * |dtheta|.
    wheel_dist_frac: float = Field(0.02, gt=0.0)
    wheel_rot_per_m_deg: float = Field(1.0, ge=0.0)
    wheel_rot_frac: float = Field(0.02, ge=0.0)
    wheel_sigma_floor_xy: float = Field(0.002, gt=0.0)
    # Distance (m) over which wheel errors (a wrong wheel radius, a heading bias) stay correlated;
    # used where the wheels alone carry the motion (scan_matching off, or no usable scan), so that
    # a chain of wheel increments allows wheel_dist_frac of every stretch up to this length (see
    # motion_model.wheel_noise). Fused with ICP, the per-increment noise applies.
    wheel_correlation_length: float = Field(5.0, ge=0.0)
    # Per-step heading floor: wheel heading errors are systematic (not white), so a generous floor
    # keeps ICP in charge of the heading wherever the scan observes it.
    wheel_sigma_floor_theta_deg: float = Field(0.5, gt=0.0)
    # Constant-velocity prediction (no wheel odometry): per-second random-walk sigmas.
    cv_sigma_xy_per_s: float = Field(0.5, gt=0.0)
    cv_sigma_theta_deg_per_s: float = Field(30.0, gt=0.0)
    # Fault gates.
    # Jump / ICP-failure gate: Mahalanobis sigmas on wheel-vs-constant-velocity (two-seed check)
    # and, with icp_gate="reject", on ICP-vs-wheel; the disagreement must also exceed the minima.
    odom_jump_gate: float = Field(5.0, gt=0.0)
    odom_jump_min_m: float = Field(0.15, ge=0.0)  # and the disagreement is at least this large
    odom_jump_min_deg: float = Field(5.0, ge=0.0)
    # What an ICP result beyond the gate from an accepted wheel increment means: "fuse" (plain EKF
    # update; on real logs with lagging odometry stamps ICP is usually the right one) or "reject"
    # (ICP fell into a wrong minimum: the motion model carries the step, the scan is not mapped).
    icp_gate: Literal["fuse", "reject"] = "fuse"
    max_speed: float = Field(3.0, gt=0.0)  # m/s; faster wheel increments are jumps
    max_turn_rate_deg: float = Field(360.0, gt=0.0)
    gap_factor: float = Field(2.5, gt=1.0)  # stamp gap > gap_factor * nominal period -> dropped scans

    @model_validator(mode="after")
    def _ranges(self) -> OdometryConfig:
        if self.min_range >= self.max_range:
            raise ValueError("min_range must be smaller than max_range")
        return self


class GraphConfig(_Section):
    """GTSAM Pose2 graph: noise floors, robust prior kernel, iSAM2 settings."""

    between_sigma_floor_xy: float = Field(0.002, gt=0.0)
    between_sigma_floor_theta_deg: float = Field(0.05, gt=0.0)
    anchor_sigma_xy: float = Field(1e-3, gt=0.0)  # prior on the first keyframe (map == odom at start)
    anchor_sigma_theta_deg: float = Field(1e-3, gt=0.0)
    prior_kernel: Literal["cauchy", "geman_mcclure", "huber", "none"] = "cauchy"
    prior_kernel_param: float = Field(2.0, gt=0.0)  # in whitened units (sigmas)
    prior_sigma_floor_xy: float = Field(0.02, gt=0.0)
    prior_sigma_floor_theta_deg: float = Field(0.5, gt=0.0)
    relinearize_threshold: float = Field(0.01, gt=0.0)
    relinearize_skip: int = Field(10, ge=1)  # streaming; settle() after priors forces it
    # a floor-plan prior that agrees with the estimate this well gets only this many forced
    # relinearising iSAM2 steps (each costs a few ms on a large graph); others get 10
    prior_settle_near_xy: float = Field(0.05, ge=0.0)
    prior_settle_near_theta_deg: float = Field(1.0, ge=0.0)
    prior_settle_near_iterations: int = Field(1, ge=0)
    factorization: Literal["QR", "CHOLESKY"] = "QR"
    batch_max_iterations: int = Field(100, ge=1)
    batch_relative_tolerance: float = Field(1e-6, gt=0.0)


class UpdatesConfig(_Section):
    """Floor-plan update strategy (paper Alg. 3, :mod:`frslam_graph.update_strategy`).

    Registration triggers: the mapped area reached ``first_register_area_m2`` (first attempt) or
    grew by ``register_min_growth_m2`` and ``register_growth_frac`` since the last attempt, or
    progress is obstructed. A registration is accepted when ok, ``score >= min_score``,
    ``ambiguity <= max_ambiguity``, the registered plan's walls explain ``min_map_fit`` of the
    map's occupied cells and the current scan relocalises consistently. Every
    ``relocation_distance_D`` metres the current scan is relocalised against the plan; a good,
    unambiguous match passing the chi² gate (``inconsistent_chi2``) becomes a robust prior.
    """

    enabled: bool = True
    register_min_growth_m2: float = Field(4.0, ge=0.0)
    relocation_distance_D: float = Field(1.0, gt=0.0)
    relocation_angle_deg: float = Field(30.0, gt=0.0)  # also relocalise after turning this much
    obstruction_speed: float = Field(0.02, ge=0.0)
    obstruction_time_s: float = Field(5.0, gt=0.0)
    max_ambiguity: float = Field(0.9, gt=0.0, le=1.0)
    min_score: float = Field(0.5, ge=0.0, le=1.0)
    inconsistent_chi2: float = Field(11.34, gt=0.0)  # chi2(3 dof, 99 %)
    map_resolution: float = Field(0.05, gt=0.0)
    # registration triggers and acceptance
    first_register_area_m2: float = Field(12.0, ge=0.0)
    register_growth_frac: float = Field(0.2, ge=0.0)
    register_retry_distance: float = Field(15.0, gt=0.0)  # m travelled: retry while none accepted
    # ... times this factor after each retry on a map that has not grown by register_min_growth_m2
    # since the attempt before (the robot re-traversing a mapped building whose plan does not
    # fit: another building's plan was retried every 15 m to the end of the run), up to
    # register_retry_max_distance; any growth starts again at register_retry_distance. 1 = off.
    register_retry_backoff: float = Field(2.0, ge=1.0)
    register_retry_max_distance: float = Field(60.0, gt=0.0)
    # while none is accepted, a registration that matched but failed the checks is retried after
    # this many metres (a fresh map before drift grows; 0 = off), up to register_recheck_max
    # quick rechecks in a row (an attempt another trigger made starts a new run)
    register_recheck_distance: float = Field(3.0, ge=0.0)
    # (3: a house of tools/bench_backend.py regime C whose first two registrations were wrong got
    # its right one at the third, 0.36 -> 0.05 m ATE, before the drift grew)
    register_recheck_max: int = Field(3, ge=0)
    # with a registration accepted, register again after this many metres without an attempt (at
    # most register_refine_max times; 0 = off)
    register_refine_distance: float = Field(20.0, ge=0.0)
    register_refine_max: int = Field(3, ge=0)
    # every other retry registers on the map of the keyframes of the last this many metres (the
    # whole map may have drifted too far to match)
    local_map_distance: float = Field(40.0, gt=0.0)
    min_map_fit: float = Field(0.5, ge=0.0, le=1.0)  # occupied map cells near a plan wall
    # keyframe scans (refine_scan_samples, each relocalised on its own) must fit a registration
    # about to be accepted with this mean soft score (0 = off)
    min_scan_fit: float = Field(0.85, ge=0.0, le=1.0)
    # an ambiguous registration (before any is accepted): the placement that explains the keyframe
    # scans better than the registration's runner-up placements by this margin (mean soft score)
    # is taken; 0 = ambiguous registrations are rejected
    disambiguate_margin: float = Field(0.05, ge=0.0)
    max_walls_in_free_space: float = Field(0.1, ge=0.0, le=1.0)  # observed interior plan walls in free space
    # The map is built at drifting estimates: "near a wall" means within map_fit_distance and "in
    # free space" farther than free_space_margin from any occupied cell, both growing by
    # check_growth_per_m per metre travelled since the last accepted prior (odometry drift not
    # yet corrected) up to their maxima.
    map_fit_distance: float = Field(0.1, gt=0.0)
    map_fit_distance_max: float = Field(0.25, gt=0.0)
    free_space_margin: float = Field(0.2, ge=0.0)
    free_space_margin_max: float = Field(0.4, ge=0.0)
    check_growth_per_m: float = Field(0.01, ge=0.0)
    # the accepted registration is retracted when the grown map shows this share of its walls in
    # free space (above the acceptance threshold: the map keeps drifting where priors are sparse)
    retract_walls_in_free_space: float = Field(0.2, ge=0.0, le=1.0)
    agree_tol: float = Field(0.3, gt=0.0)  # m, RMS displacement of plan corners between registrations
    # with no registration accepted, after this many metres without a prior a registration needs
    # a second one that agrees (within agree_tol) before it is accepted
    confirm_after_m: float = Field(20.0, ge=0.0)
    switch_margin: float = Field(0.05, ge=0.0)  # map-fit gain needed to replace a registration
    # an agreeing registration (within agree_tol) that explains the grown map at least as well
    # refines the accepted one for the relocalisations that follow (a first registration on a
    # small map can be 0.2-0.3 m off: a regime-C house of tools/bench_backend.py 0.175 -> 0.025 m
    # ATE; no house of regimes A / B / C worse by more than 0.01 m)
    refine_on_agreement: bool = True
    # "explains as well or better" on: "map" the occupied cells of the map (drawn at estimates the
    # accepted plan's priors shaped, so biased towards it); "scans" up to refine_scan_samples
    # keyframe scans spread over the run, each relocalised on its own on both plans (mean soft
    # score)
    refine_by: Literal["map", "scans"] = "scans"
    refine_scan_samples: int = Field(24, ge=1)
    # scan fits closer than this are a tie (the map decides)
    refine_scan_margin: float = Field(0.005, ge=0.0)
    # this many metres after a registration is accepted, its scale along the plan's two axes is
    # fitted to keyframe scans (refine_scan_samples, their poses free); the result replaces it
    # when it explains the scans better by scale_refine_margin (0 = off); the interval doubles
    # after each fit that changes nothing. Prior sigma of the log scale factors, and the largest
    # factor change accepted (fraction).
    scale_refine_distance: float = Field(20.0, ge=0.0)
    scale_refine_sigma: float = Field(0.05, gt=0.0)
    scale_refine_max: float = Field(0.1, gt=0.0)
    scale_refine_min: float = Field(0.002, ge=0.0)  # smaller factor changes are not tried
    scale_refine_margin: float = Field(0.002, ge=0.0)  # scan-fit gain needed (mean soft score)
    # with each scale refinement, move the plan rigidly so that the first keyframe's scan fits it
    # at the anchor (the first pose), when it is off by at least these
    # (regime C of tools/bench_backend.py, 20 houses, with the registration / scale refinements
    # and refine_by="scans": mean ATE with the plan 0.023 -> 0.014 m, with 25 % wrong registrations
    # 0.080 -> 0.046 m, within 10 % of the clean run 14 -> 16 houses; another building unchanged)
    align_to_start: bool = True
    align_min_xy: float = Field(0.02, ge=0.0)
    align_min_theta_deg: float = Field(0.2, ge=0.0)
    # ... and only when the first scan's soft fit at the anchor improves by this much
    align_min_gain: float = Field(0.002, ge=0.0)
    # a refined scale moving a prior's keyframe more than this (m) relocalises the keyframes
    # with priors on the refined plan
    scale_reanchor_xy: float = Field(0.05, ge=0.0)
    # at the end of an offline run (FRSlam.finish), one more registration on the complete map and
    # the scale refinement, so the final plan depends less on when the run's refinements happened
    final_refine: bool = True
    max_registrations: int = Field(40, ge=1)
    # relocalisation against the registered plan
    reloc_window_xy: float = Field(0.75, gt=0.0)
    reloc_window_theta_deg: float = Field(15.0, gt=0.0, le=180.0)
    # the window grows with the drift since the last accepted prior, up to these
    reloc_window_max_xy: float = Field(2.0, gt=0.0)
    reloc_window_max_theta_deg: float = Field(30.0, gt=0.0, le=180.0)
    reloc_min_score: float = Field(0.5, ge=0.0, le=1.0)
    reloc_max_ambiguity: float = Field(0.8, ge=0.0, le=1.0)
    reloc_resolution: float = Field(0.025, gt=0.0)
    reloc_inlier_distance: float = Field(0.1, gt=0.0)
    wall_half_thickness: float = Field(0.06, ge=0.0)
    reloc_cov_inflation: float = Field(4.0, ge=1.0)
    reloc_sigma_floor_xy: float = Field(0.02, gt=0.0)
    reloc_sigma_floor_theta_deg: float = Field(0.3, gt=0.0)
    # chi2 gate: the estimate's marginal covariance plus drift since the last accepted prior
    gate_drift_frac: float = Field(0.05, ge=0.0)
    gate_drift_deg_per_m: float = Field(1.0, ge=0.0)
    gate_sigma_xy: float = Field(0.05, gt=0.0)
    gate_sigma_theta_deg: float = Field(1.0, gt=0.0)
    # a prior whose residual after optimisation exceeds this chi2 is removed as proven wrong
    remove_chi2: float = Field(30.0, gt=0.0)
    remove_min_xy: float = Field(0.15, ge=0.0)  # ... and is at least this far off (m)
    remove_min_theta_deg: float = Field(3.0, ge=0.0)  # ... or turned (deg)
    remove_max_share: float = Field(0.3, gt=0.0, le=1.0)  # more contradicted at once: keep all
    prior_kind: Literal["full", "translation"] = "full"
    # after a registration is accepted, the keyframes before it (one per relocation_distance_D,
    # newest first) are relocalised on the plan too, this many per keyframe
    backfill: bool = True
    backfill_per_keyframe: int = Field(2, ge=1)
    # relocalisation, prior and prior check (and each backfill) run as separate steps on the
    # scans after the keyframe (FRSlam.defer): same decisions, no scan pays for all of them
    spread_over_scans: bool = True


class LoopClosureConfig(_Section):
    """Loop closure (:mod:`frslam_graph.loop_closure`, its scan matcher
    :mod:`frslam_graph.submap_matching`): candidates, matching, acceptance."""

    enabled: bool = True
    # Candidates: earlier keyframes at least this far back (keyframes AND travel or turned angle).
    min_keyframe_gap: int = Field(20, ge=1)
    min_travel_gap: float = Field(5.0, ge=0.0)
    min_rotation_gap_deg: float = Field(300.0, ge=0.0)
    # Search radius around the current estimate and heading window grow with the motion since
    # the last accepted closure (or since the candidate, whichever is shorter).
    radius_base: float = Field(2.0, gt=0.0)
    radius_per_m: float = Field(0.25, ge=0.0)
    radius_max: float = Field(60.0, gt=0.0)
    theta_window_base_deg: float = Field(10.0, gt=0.0, le=180.0)
    theta_window_per_m_deg: float = Field(0.3, ge=0.0)
    theta_window_per_turn: float = Field(0.05, ge=0.0)  # degrees of window per degree turned
    # Translation half-width of the correlative search around the prediction (or the candidate).
    search_window_xy: float = Field(2.0, gt=0.0)
    candidate_spacing: float = Field(1.5, gt=0.0)  # one candidate per cell of this size
    attempt_every: int = Field(2, ge=1)  # keyframes between attempts
    max_candidates: int = Field(2, ge=1)  # candidates matched per attempt
    # ... or this many when nothing is queued (the work keeps up with the budget): after a long
    # excursion a region the drift put metres from the estimate is reached in time (ACES with
    # convergence_criterion 2e-4: a 6 m loop was missed with 2, relation error 0.10 m). 3 at every
    # attempt fell minutes behind on FR079 (queue lag median 11 -> 138 s) and cost +85 % CPU.
    max_candidates_idle: int = Field(3, ge=1)
    retry_keyframes: int = Field(30, ge=0)  # a region is not retried within this many keyframes
    # No search while the keyframe is tied to a keyframe within its search radius by a short path
    # of the graph (at most redundant_travel metres and redundant_turn_deg of turning; accepted
    # closures count as zero length): a recent verified closure keeps their relative uncertainty
    # small. Once the travel or turning since that closure grows past these, the search resumes.
    # Off by default (0): with 6 m the synthetic room needs ~70 % less loop-closure CPU, but the
    # fewer closures let aliased ones weigh more in repetitive houses (regime-A ATE without plan
    # 0.155 -> 0.35, 0.546 -> 0.64 m) and the ACES relation error varies (0.046 .. 0.075 m).
    redundant_travel: float = Field(0.0, ge=0.0)
    # ... and this instead while floor-plan priors are in the graph: the priors hold the map to
    # the plan, so an aliased closure cannot weigh much and each further closure adds little.
    # Regime A, 8 simulated houses with the plan: loop-closure CPU -65 %, run CPU about -40 %,
    # mean ATE +5 % (0.0142 -> 0.0149 m); 0 keeps searching at every attempt as without a plan.
    redundant_travel_with_plan: float = Field(6.0, ge=0.0)
    redundant_turn_deg: float = Field(90.0, ge=0.0)
    # Submaps (points in the keyframe's frame).
    submap_travel: float = Field(3.0, ge=0.0)  # reference: keyframes within ± this travel
    query_travel: float = Field(2.0, ge=0.0)  # query: this much travel back from the keyframe
    submap_keyframes: int = Field(30, ge=1)  # at most this many keyframes per side
    max_point_range: float = Field(15.0, gt=0.0)
    # Matcher.
    resolution: float = Field(0.05, gt=0.0)
    coarse_step_xy: float = Field(0.3, gt=0.0)
    coarse_step_theta_deg: float = Field(1.5, gt=0.0)
    likelihood_sigma: float = Field(0.1, gt=0.0)
    max_query_points: int = Field(150, ge=20)
    icp_iterations: int = Field(10, ge=1)
    icp_max_distance: float = Field(0.5, gt=0.0)
    inlier_distance: float = Field(0.1, gt=0.0)
    min_coarse_score: float = Field(0.62, ge=0.0, le=1.0)  # below it: rejected without ICP
    refine_ratio: float = Field(0.7, gt=0.0, le=1.0)  # other peaks refined above ratio × best
    # Acceptance.
    min_inlier_fraction: float = Field(0.6, ge=0.0, le=1.0)
    max_ambiguity: float = Field(0.85, gt=0.0, le=1.0)  # second peak / best
    # query points in space the reference saw free (farther than free_space_margin from its
    # points) contradict the match: another place that looks alike
    max_free_violation: float = Field(0.1, ge=0.0, le=1.0)
    free_space_margin: float = Field(0.3, gt=0.0)
    peak_separation_xy: float = Field(1.0, gt=0.0)
    peak_separation_theta_deg: float = Field(10.0, gt=0.0)
    # Large corrections need a second, consistent closure before entering the graph.
    confirm_xy: float = Field(0.15, ge=0.0)
    confirm_theta_deg: float = Field(1.5, ge=0.0)
    consistency_xy: float = Field(0.3, gt=0.0)
    consistency_theta_deg: float = Field(3.0, gt=0.0)
    pending_keyframes: int = Field(30, ge=1)
    # A match that agrees with a pending closure (the check above) confirms it with at least this
    # inlier fraction (the other tests unchanged): two independent matches that agree are the
    # evidence; alone such a match is rejected (low_inliers). = min_inlier_fraction: off.
    confirm_min_inlier_fraction: float = Field(0.45, ge=0.0, le=1.0)
    # When a large correction goes pending, the keyframe this far back (its own query submap, no
    # shared points) is matched where the closure predicts it: a second, independent check while
    # the robot may already be leaving the place. 0: off.
    verify_back_travel: float = Field(2.0, ge=0.0)
    # each attempt first checks where the latest pending closure predicts the robot to be
    hypothesis_window_xy: float = Field(2.0, gt=0.0)  # as wide as a search: ambiguity still tested
    hypothesis_window_theta_deg: float = Field(10.0, gt=0.0)
    # Factor noise: point-to-line sigma, inflation, floors; robust kernel (whitened units).
    icp_sigma: float = Field(0.05, gt=0.0)
    covariance_inflation: float = Field(10.0, ge=1.0)
    sigma_floor_xy: float = Field(0.02, gt=0.0)
    sigma_floor_theta_deg: float = Field(0.5, gt=0.0)
    kernel: Literal["cauchy", "geman_mcclure", "huber", "none"] = "cauchy"
    kernel_param: float = Field(4.0, gt=0.0)
    batch_on_correction: float = Field(1.0, ge=0.0)  # LM batch when a closure moves the graph more (m)
    # After closures enter (and at the end), an accepted closure whose residual at the estimate
    # exceeds prune_chi2 (squared Mahalanobis norm under its covariance) and prune_xy (m) or
    # prune_theta_deg is removed, worst first, and the graph re-settled: the odometry and the other
    # closures disagree with it (an aliased pair that slipped through). prune_chi2 0: off.
    prune_chi2: float = Field(200.0, ge=0.0)
    prune_xy: float = Field(0.3, ge=0.0)
    prune_theta_deg: float = Field(3.0, ge=0.0)
    # a confirmed pair (plain Gaussians) that this many older closures disagree with at once is
    # removed before them: under its pull they show the large residuals, not the pair (regime A
    # without plan, houses 0-2: ATE 0.0368 / 0.0276 / 0.0311 -> 0.0346 / 0.0251 / 0.0298 m,
    # 74 / 144 / 177 -> 12 / 2 / 59 closures pruned). With 3, ACES lost a true 7 m correction
    # that seven recent closures disagreed with (relation error 0.0474 -> 0.0485 m); 10 keeps it.
    prune_pair_contradictions: int = Field(10, ge=1)
    final_alignment_rounds: int = Field(
        2,
        ge=0,
        description="rounds of dense scan-to-submap constraints between passes when a run finishes "
        "(frslam_graph.final_alignment): each matches every keyframe against the keyframes of other "
        "passes near it and re-optimises; 0 = off (finish() only runs the LM batch, faster); off "
        "with loop closure",
    )
    final_alignment_radius: float = Field(
        2.0,
        gt=0.0,
        description="m; keyframes of other passes within this distance of a keyframe are matched to it "
        "by the final alignment; larger ties more places (more time at finish)",
    )
    # Anytime scheduling (bounded latency per add_scan): a keyframe queues its candidates (every
    # attempt_every keyframes); every scan then runs *steps* of the queued work (a submap build,
    # a chunk of the correlative search of at most max_lookups_per_step field look-ups, the ICP
    # data, one ICP refinement, one relinearising iSAM2 update after a closure; an LM batch after
    # a large correction is one step) while their estimated cost fits in budget_ms. The estimate
    # comes from the sizes involved (look-ups, grid cells, points, keyframes), not from a clock,
    # so results do not depend on the machine's speed. A step estimated above the budget runs
    # alone. FRSlam.finish() runs what is left.
    budget_ms: float = Field(8.0, gt=0.0)
    # on keyframe scans (their odometry-graph update and update strategy run there too)
    keyframe_budget_ms: float = Field(4.0, gt=0.0)
    max_lookups_per_step: int = Field(300_000, ge=10_000)
    # at most this many relinearising iSAM2 iterations (each a step) after a small closure; the
    # factor's own iSAM2 update already takes one Gauss-Newton step from a nearby estimate, and
    # the keyframe updates relinearise (relinearize_skip). 1 -> 0: regime A without plan, 8
    # houses, same ATE (mean 0.0247 -> 0.0246 m), run CPU about -20 %; with the plan mean
    # 0.0149 -> 0.0150 m; ACES 0.0474 -> 0.0470 m
    settle_small: int = Field(0, ge=0)
    # Optional wall-clock cap per add_scan (ms): after the first step, another starts only while
    # less than this was spent. None: the cost model alone (deterministic). With a cap, how the
    # work is spread (hence which closures are found when) depends on the machine's load.
    wall_budget_ms: float | None = Field(None, gt=0.0)


class FRSlamConfig(_Section):
    """Whole-backend configuration; see the section classes for fields and units."""

    odometry: OdometryConfig = OdometryConfig()
    graph: GraphConfig = GraphConfig()
    updates: UpdatesConfig = UpdatesConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()

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
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot read config file ({exc.strerror})", source=path) from None
        try:
            if path.suffix.lower() == ".json":
                data = json.loads(text)
            else:
                import yaml

                data = yaml.safe_load(text)
        except (json.JSONDecodeError, Exception) as exc:  # yaml.YAMLError has no common import here
            raise ConfigError(f"not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}", source=path) from None
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

    def with_updates(self, **sections: dict[str, Any]) -> FRSlamConfig:
        """A copy with some fields changed, e.g. ``cfg.with_updates(odometry={"voxel_size": 0.2})``."""
        data = self.model_dump()
        for name, values in sections.items():
            if name not in data:
                raise ConfigError(f"unknown section (expected one of {sorted(data)})", where=name)
            data[name].update(values)
        return type(self).from_dict(data)


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
    if err.get("type") == "value_error":
        msg = msg.removeprefix("Value error, ")
    elif "input" in err and err.get("type") != "missing":
        msg = f"{msg} (got {err['input']!r})"
    more = len(exc.errors()) - 1
    if more:
        msg += f"; and {more} more error(s)"
    return ConfigError(msg, source=source, where=where)
