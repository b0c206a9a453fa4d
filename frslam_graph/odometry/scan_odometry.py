"""Scan odometry: KISS-ICP on planar scans, fused with wheel odometry through the motion model.

Frames (REP-105): every pose here is ``base_link`` in ``odom`` (metres, radians). ``odom`` starts
at the first scan's wheel-odometry pose (or at the origin without wheel odometry) and is
continuous: it never jumps. Input points are planar, in ``base_link`` (the caller applies the
laser's mounting offset).

Per scan: the wheel increment u_t (or a constant-velocity guess) seeds KISS-ICP through
``last_delta``; KISS-ICP's pose is refined by point-to-line ICP on a local map of the last
``local_map_scans`` scans, thinned to one mean point per ``voxel_size`` cell (walls as lines,
exact nearest neighbours: :meth:`ScanOdometry._refine`); the ICP pose relative
to the last keyframe is fused with u_t in
:class:`~frslam_graph.odometry.motion_model.MotionEKF`. The ICP covariance comes from the point-to-line
Hessian of the scan (normals from neighbouring beams, voxel-thinned), scaled by a residual sigma;
when the normals span only one direction (a featureless corridor) the scan is *degenerate*: the
covariance is inflated along the corridor axis so the motion model carries that direction.
Scans without enough valid points (all-NaN) fall back to the motion model. With
``scan_matching=False`` the wheel odometry alone drives the motion model (the scans are still
mapped and used by loop closure and the floor-plan priors); scans without wheel odometry are
then still matched. Wheel increments that are physically impossible, that the scan rejects in
favour of constant velocity (when the two disagree both seeds are aligned and the better map fit
wins) or of the wheel step reversed (tried when a step is longer than ``ODOM_JUMP_MIN_M``: a lost
sign would put the seed beyond ICP's reach, as on FR079 at a third of its scan rate), or that
move along the robot's x axis against the scan's motion beyond the gate (wheel
odometry that lost the sign: a reversal logged as forward motion) are *odometry jumps*: ICP is
trusted. Wheels that miss part of a fast turn while agreeing with constant velocity (FR079's,
spinning at 35-40 deg/s) are caught by the fit: where KISS-ICP's pose fits the recent scans' walls
worse than they fitted, the seed turned by 5-10 deg is aligned too and wins if it fits as they did
(:meth:`ScanOdometry._turned`); that step is an odometry jump too. An ICP result beyond a
Mahalanobis gate from an accepted wheel increment is an ICP failure (wrong minimum): the motion
model carries that step and the scan is not mapped. Stamps
are taken in arrival order through a scan clock robust to bursty and backwards stamps
(:meth:`ScanOdometry._clock`); on a steady clock, stamp gaps larger than ``GAP_FACTOR`` nominal
periods count as dropped scans; on a bursty one a step lasts from one period up to its stamp
step, and the wheel step says how long (a logger pause: the robot drove on). The wheel poses are re-timed to the scans by the wheel-to-scan
time offset estimated from the heading steps, where it is significant and negative
(:mod:`frslam_graph.odometry.time_offset`: FR079, -0.14 s).
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass

import numpy as np

from frslam_graph.config import OdometryConfig
from frslam_graph.errors import RecordingError
from frslam_graph.loop_closure.submap_matching import (
    LineMap,
    cell_means,
    first_of_each,
    fractions_within,
    icp_point_to_line,
    transform_points,
)
from frslam_graph.odometry.motion_model import (
    MotionEKF,
    between,
    compose,
    constant_velocity,
    constant_velocity_noise,
    constant_velocity_span,
    from_matrix,
    to_matrix4,
    vector_cov,
    wheel_increment,
    wheel_noise,
    wrap,
)
from frslam_graph.odometry.time_offset import WheelTimeOffset

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# m; KISS-ICP adaptive threshold learns only from steps moving at least this; larger = slower to adapt
MIN_MOTION = 0.1
ICP_COV_INFLATION = 1.0  # factor on the ICP covariance; larger = ICP steps trusted less
ICP_SIGMA_FLOOR_XY = 0.001  # m; smallest ICP translation sigma; larger = ICP never trusted beyond this
# deg; smallest ICP heading sigma; larger = ICP heading never trusted beyond this
ICP_SIGMA_FLOOR_THETA_DEG = 0.01
# m; ICP sigma along a degenerate axis; larger = the motion model carries that axis more
DEGENERATE_SIGMA = 10.0
# sigmas (Mahalanobis) of the jump / ICP-failure gate: wheel vs constant velocity and, with icp_gate reject,
# ICP vs wheel; larger = fewer jumps detected
ODOM_JUMP_GATE = 5.0
ODOM_JUMP_MIN_M = 0.15  # m; a jump must also disagree by at least this much; larger = fewer jumps detected
ODOM_JUMP_MIN_DEG = 5.0  # deg; ... or turn at least this much; larger = fewer jumps detected
# a stamp gap above this times the nominal scan period counts as dropped scans; larger = fewer gaps reported
GAP_FACTOR = 2.5


@dataclass(frozen=True, slots=True)
class OdometryResult:
    """Odometry of one scan.

    ``pose``: base_link in odom. ``keyframe``: index of the keyframe this scan hangs from (its own
    index when ``is_keyframe``). ``relative``: pose relative to that keyframe (zero for a keyframe).
    For a keyframe after the first, ``between`` / ``covariance`` are the fused motion from the
    previous keyframe and its 3×3 covariance in GTSAM's Pose2 tangent convention; otherwise
    ``between`` is None and ``covariance`` the covariance of ``relative``.
    """

    stamp: float
    pose: np.ndarray
    keyframe: int
    is_keyframe: bool
    relative: np.ndarray
    between: np.ndarray | None
    covariance: np.ndarray
    degenerate: bool = False
    degenerate_axis: np.ndarray | None = None  # unit vector in base_link
    fallback: bool = False
    odom_jump: bool = False
    dropped: int = 0
    n_points: int = 0
    icp_rejected: bool = False
    period: float = 0.0  # s, the nominal scan period at this scan (0 before it is known)


@dataclass(slots=True)
class OdometryStats:
    """Counters of everything unusual the odometry handled."""

    scans: int = 0
    keyframes: int = 0
    empty_scans: int = 0
    fallbacks: int = 0
    degenerate_scans: int = 0
    odom_jumps: int = 0
    icp_rejections: int = 0
    dropped_scans: int = 0
    gaps: int = 0
    out_of_order: int = 0
    # wheel-to-scan time offset (s; odometry/time_offset.py): estimate, its standard error, applied
    time_offset: float = 0.0
    time_offset_sigma: float = 0.0
    time_offset_applied: float = 0.0


@dataclass(frozen=True, slots=True)
class ScanGeometry:
    """Point-to-line information of a scan: 3×3 Hessian (per sigma²), normal eigen-analysis."""

    hessian: np.ndarray
    n_normals: int
    eig_ratio: float  # smallest / largest eigenvalue of sum(n nᵀ)
    weak_axis: np.ndarray  # unit vector of the smallest eigenvalue


@dataclass(frozen=True, slots=True)
class PreparedScan:
    """The per-scan work of the odometry that needs no state (:meth:`ScanOdometry.prepare`).

    ``points``: valid end points (M, 2) in base_link; ``source`` / ``frame_ds``: KISS-ICP's
    voxelised registration source and the thinned frame for its local map, (K, 3) with z = 0;
    ``geometry``: the point-to-line information; ``icp_covariance``: what it gives the ICP step
    (body-frame covariance, degenerate, fallback, weak axis). The last four are None when the scan has too
    few points or scan matching is off (computed on demand then). Preparing scans apart from the
    sequential registration lets it run in another process (:mod:`frslam_graph.odometry.worker`).
    """

    points: np.ndarray
    source: np.ndarray | None = None
    frame_ds: np.ndarray | None = None
    geometry: ScanGeometry | None = None
    icp_covariance: tuple[np.ndarray, bool, bool, np.ndarray | None] | None = None


def scan_geometry(points: np.ndarray, voxel_size: float, neighbours: int = 2) -> ScanGeometry:
    """Normals from beam-ordered points and the point-to-line Hessian of a planar registration.

    Normals are perpendicular to p[i+k] - p[i-k] where both neighbours are close (continuous
    surface); points are thinned to one per voxel so the information does not grow with the beam
    count. Row i of the Jacobian is [n_x, n_y, n_y p_x - n_x p_y].
    """
    pts = np.asarray(points, dtype=np.float64)
    k = int(neighbours)
    if len(pts) < 2 * k + 3:
        return ScanGeometry(np.zeros((3, 3)), 0, 0.0, np.array([1.0, 0.0]))
    x, y = pts[:, 0], pts[:, 1]
    mx, my = x[k:-k], y[k:-k]
    ax, ay = mx - x[: -2 * k], my - y[: -2 * k]  # mid - prev
    bx, by = x[2 * k :] - mx, y[2 * k :] - my  # next - mid
    tx, ty = ax + bx, ay + by  # next - prev
    tl2 = tx * tx + ty * ty
    # continuity: both neighbours close to the point (scaled with range for grazing walls)
    rng = np.sqrt(mx * mx + my * my)
    gap = np.maximum(4.0 * voxel_size, 0.05 * rng) * k
    gap2 = gap * gap
    ok = (tl2 > 1e-12) & (ax * ax + ay * ay < gap2) & (bx * bx + by * by < gap2)
    # collinearity: the middle point lies near the chord (|a × t| / |t|)
    tl = np.sqrt(np.maximum(tl2, 1e-24))
    ok &= np.abs(ax * ty - ay * tx) < np.maximum(0.5 * voxel_size, 0.01 * rng) * tl
    if not np.any(ok):
        return ScanGeometry(np.zeros((3, 3)), 0, 0.0, np.array([1.0, 0.0]))
    px, py, nx, ny = mx[ok], my[ok], -ty[ok] / tl[ok], tx[ok] / tl[ok]
    # one point per voxel
    cx = np.floor(px / voxel_size).astype(np.int64)
    cy = np.floor(py / voxel_size).astype(np.int64)
    first = first_of_each(cx * 2_000_003 + cy)
    px, py, nx, ny = px[first], py[first], nx[first], ny[first]
    J = np.column_stack((nx, ny, ny * px - nx * py))
    H = J.T @ J
    w, v = np.linalg.eigh(H[:2, :2])
    ratio = float(w[0] / w[1]) if w[1] > 1e-12 else 0.0
    return ScanGeometry(H, len(px), max(ratio, 0.0), v[:, 0])


class ScanOdometry:
    """KISS-ICP odometry of planar scans fused with wheel odometry; keyframe selection.

    ``process(stamp, points, odom=None)`` takes (M, 2) points in base_link and the wheel pose
    (x, y, theta) in the wheel-odometry frame (or None); returns an :class:`OdometryResult`. Scans
    are taken in arrival order; a stamp not after the previous one is counted in
    ``stats.out_of_order`` and the scan kept (see :meth:`_clock`).
    """

    def __init__(self, config: OdometryConfig | None = None):
        from kiss_icp.config import KISSConfig
        from kiss_icp.config.config import (
            AdaptiveThresholdConfig,
            DataConfig,
            MappingConfig,
            RegistrationConfig,
        )
        from kiss_icp.kiss_icp import KissICP

        self.config = cfg = config or OdometryConfig()
        # every field explicit so that KISS_ICP_* environment variables cannot change behaviour
        kcfg = KISSConfig(
            out_dir=os.devnull,
            data=DataConfig(max_range=cfg.max_range, min_range=cfg.min_range, deskew=False),
            mapping=MappingConfig(voxel_size=cfg.voxel_size, max_points_per_voxel=cfg.max_points_per_voxel),
            registration=RegistrationConfig(
                max_num_iterations=cfg.max_iterations,
                convergence_criterion=cfg.convergence_criterion,
                max_num_threads=cfg.num_threads,
            ),
            adaptive_threshold=AdaptiveThresholdConfig(
                fixed_threshold=cfg.fixed_threshold,
                initial_threshold=cfg.initial_threshold,
                min_motion_th=MIN_MOTION,
            ),
        )
        self._icp = KissICP(kcfg)
        self._ekf = MotionEKF()
        self.stats = OdometryStats()
        self._empty_ts = np.zeros(0)
        self._kf_dist = cfg.keyframe_distance
        self._kf_angle = np.deg2rad(cfg.keyframe_angle_deg)
        self._wheel_args = dict(
            dist_frac=cfg.wheel_dist_frac,
            rot_per_m=np.deg2rad(cfg.wheel_rot_per_m_deg),
            rot_frac=cfg.wheel_rot_frac,
            floor_xy=cfg.wheel_sigma_floor_xy,
            floor_theta=np.deg2rad(cfg.wheel_sigma_floor_theta_deg),
        )
        self._floor = np.diag([ICP_SIGMA_FLOOR_XY**2] * 2 + [np.deg2rad(ICP_SIGMA_FLOOR_THETA_DEG) ** 2])
        # state
        # recent stamps, never decreasing (a stamp before its predecessor does not rewind the
        # clock); empty before the first scan
        self._t_hist: deque[float] = deque(maxlen=_PERIOD_WINDOW)
        self._period = 0.0  # nominal scan period (s), see _clock
        self._steady = True  # recent stamps keep to the period (see _clock)
        self._last_dt = 0.0
        self._last_increment = np.zeros(3)
        self._prev_wheel: np.ndarray | None = None  # previous wheel pose, re-timed (see _toff)
        self._prev_raw: np.ndarray | None = None  # previous wheel pose as given
        # the wheels stalled: they report no motion at all where the scan saw the robot move (a
        # log with a constant odometry field); until they move again they carry no step
        self._stalled = False
        self._toff = WheelTimeOffset()
        self._prev_rel = np.zeros(3)  # fused pose relative to keyframe at the previous scan
        self._kf_index = -1
        self._kf_stamp = float("-inf")
        self._kf_pose = np.zeros(3)  # keyframe pose in odom (fused chain)
        self._kf_icp = np.zeros(3)  # keyframe pose in KISS-ICP's frame
        # local map of the point-to-line refinement: the points of the recent committed scans in
        # KISS-ICP's frame (each transformed once, at its commit; not one near the last added:
        # _near_added), rebuilt every _LOCAL_MAP_REBUILD commits
        self._recent: deque[np.ndarray] = deque(maxlen=max(cfg.local_map_scans, 1))
        self._local_ref: LineMap | None = None
        self._local_stale = False  # _recent changed since _local_ref was built (see _local_map)
        self._since_rebuild = 0
        # KISS-ICP-frame pose (x, y, theta) of the last scan added to _recent (see _commit)
        self._added_pose: np.ndarray | None = None
        self._aligned_points = np.zeros((0, 2))
        # share of each recent refined scan within a voxel of the local map (see _turned)
        self._fits: deque[float] = deque(maxlen=max(cfg.local_map_scans, 1))

    # ------------------------------------------------------------------ public
    @property
    def pose(self) -> np.ndarray:
        """Current base_link pose in odom."""
        return compose(self._kf_pose, self._ekf.x)

    @property
    def keyframe_index(self) -> int:
        return self._kf_index

    def nominal_period(self) -> float:
        """Nominal scan period (s) from the recent stamps, robust to bursts and gaps; 0 before two scans."""
        return self._period

    def prepare(self, points: np.ndarray, icp_inputs: bool | None = None) -> PreparedScan:
        """Valid points, KISS-ICP source / map frame and scan geometry of (M, 2) base_link points.

        Depends on the configuration only, never on the odometry's state. ``icp_inputs`` (None =
        when scan matching is on) computes what the registration needs.
        """
        cfg = self.config
        pts = _valid_points(points, cfg.min_range, cfg.max_range)
        if icp_inputs is None:
            icp_inputs = cfg.scan_matching
        if not icp_inputs or len(pts) < cfg.min_points:
            return PreparedScan(pts)
        icp = self._icp
        frame = icp.preprocessor.preprocess(np.column_stack((pts, np.zeros(len(pts)))), self._empty_ts, _EYE4)
        source, frame_ds = icp.voxelize(frame)
        geo = scan_geometry(pts, cfg.voxel_size, cfg.normal_neighbours)
        return PreparedScan(pts, source, frame_ds, geo, self._icp_covariance(geo))

    def process(
        self,
        stamp: float,
        points: np.ndarray | PreparedScan,
        odom: tuple[float, float, float] | None = None,
    ) -> OdometryResult:
        """One scan: (M, 2) points in base_link (or their :meth:`prepare`), wheel pose or None."""
        cfg = self.config
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise RecordingError(f"scan stamp must be a finite number, got {stamp!r}", where="stamp")
        scan = points if isinstance(points, PreparedScan) else self.prepare(points)
        pts = scan.points
        wheel = None
        if odom is not None:
            wheel = np.asarray(odom, dtype=np.float64).reshape(-1)
            if wheel.shape != (3,):
                raise RecordingError(f"odom must be (x, y, theta), got shape {wheel.shape}", where="odom")
            if not np.isfinite(wheel).all():
                wheel = None
        self.stats.scans += 1
        if not self._t_hist:
            return self._first(stamp, pts, wheel)
        dt, span, dt_speed, dropped = self._clock(stamp)
        clock_dt = dt  # the wheel re-timing keeps it (tools/README.md, degraded real logs)
        cv_sigmas = (cfg.cv_sigma_xy_per_s, np.deg2rad(cfg.cv_sigma_theta_deg_per_s))

        raw_wheel, uw_raw, wheel_ok = wheel, None, False
        if wheel is not None and self._prev_wheel is not None:
            uw_raw = wheel_increment(self._prev_raw, wheel)
            wheel_ok = not (
                np.hypot(uw_raw[0], uw_raw[1]) > cfg.max_speed * dt_speed + 0.05
                or abs(uw_raw[2]) > np.deg2rad(cfg.max_turn_rate_deg) * dt_speed + np.deg2rad(2.0)
            )
            if wheel_ok:  # the stamps leave the step's duration open (dt < span): the wheels tell it
                dt = constant_velocity_span(self._last_increment, self._last_dt, uw_raw, dt, span, *cv_sigmas)

        # --- prediction u_t, Σ_u (wheel odometry, or constant velocity)
        cv_u = constant_velocity(self._last_increment, self._last_dt, dt)
        cv_cov = constant_velocity_noise(dt, *cv_sigmas)
        u, cov_u, used_wheel, jump = cv_u, cv_cov, False, False
        if uw_raw is not None:
            if not wheel_ok:
                jump = True
            else:
                # the wheel pose at the scan's own time (time_offset.py: 0 unless significant)
                wheel = self._toff.retime(wheel, uw_raw, clock_dt)
                uw = wheel_increment(self._prev_wheel, wheel)
                # where the wheels alone carry the motion, increment after increment, their
                # errors are correlated over wheel_correlation_length (motion_model.wheel_noise)
                alone = not cfg.scan_matching or len(pts) < cfg.min_points
                corr = cfg.wheel_correlation_length if alone else 0.0
                u, cov_u, used_wheel = uw, wheel_noise(uw, **self._wheel_args, correlation_length=corr), True
        # wheels that report no motion at all (a fault when the scan moves the robot: below)
        wheels_still = uw_raw is not None and not uw_raw.any()
        if uw_raw is not None:
            self._stalled = self._stalled and wheels_still
            if self._stalled:  # still stalled: the step is the scan's, as without wheel odometry
                u, cov_u, used_wheel = cv_u, cv_cov, False
        seeds = [u]
        if used_wheel and self._last_dt > 0.0 and self._disagree(u, cv_u, cov_u + cv_cov):
            seeds.append(cv_u)  # wheels and constant velocity disagree: let the scan decide
        if used_wheel and abs(u[0]) > ODOM_JUMP_MIN_M and cv_u[0] * u[0] <= 0.5 * u[0] * u[0]:
            # a step this long whose sign the wheels lost (FR079 logs reversing as forward
            # motion) puts the seed 2|u_x| off, beyond ICP's reach: let the scan decide. Only
            # where a reversal is possible: a robot reverses through standstill, so not while the
            # last step moved on in the wheels' direction by more than half this one
            seeds.append(np.array([-u[0], -u[1], u[2]]))
        if not used_wheel:
            # constant velocity alone (no wheels, stalled or rejected ones) is no better than its
            # random walk: a robot that starts or stops turning within a scan period leaves it
            # beyond ICP's reach (ACES without odometry: lost for 80 scans after an in-place turn)
            seeds += _cv_alternatives(cv_u, cv_cov)
        # a scan without wheel odometry breaks the chain: the next increment must not span it
        self._prev_wheel, self._prev_raw = wheel, raw_wheel

        prev_rel = self._ekf.x
        degenerate, fallback, axis, icp_rejected = False, False, None, False
        wheel_only = not cfg.scan_matching and used_wheel and len(pts) >= cfg.min_points
        if len(pts) < cfg.min_points or wheel_only:
            if not wheel_only:
                self.stats.empty_scans += 1
            fallback = not wheel_only
            self._ekf.predict(u, cov_u)
            self._resync_icp(u)
            R_body = None
        else:
            if scan.source is None:  # prepared without the registration's inputs
                scan = self.prepare(pts, icp_inputs=True)
            chosen, new_pose, guess, frame_ds = self._align(scan, seeds)
            icp_pose = from_matrix(new_pose)
            z = between(self._kf_icp, icp_pose)
            if not self._possible(between(prev_rel, z), dt_speed):
                # a step no robot makes (faster than max_speed / max_turn_rate_deg, as wheel steps
                # are tested): a wrong minimum, whatever the seed. A scan that sees little (a short-
                # range laser in a hall: 20-30 points) slides onto a stale local map and would
                # otherwise overrule the wheels as a wheel fault (ACES at 4 m range: 1.4 m steps)
                icp_rejected, chosen = True, None
            if chosen is not None and used_wheel:
                # the scan sides with constant velocity, the reversed wheel step or a turned seed: a jump
                jump, used_wheel, u, cov_u = True, False, chosen, cv_cov
            elif chosen is not None:  # the scan sides with another constant-velocity seed: the prediction
                u = chosen
            R_body, degenerate, fallback, axis = scan.icp_covariance
            if degenerate and not fallback and not used_wheel:
                # along a corridor only the wheels know the axis; constant velocity does not (a
                # random walk that nothing bounds): what the scan still sees along it (doors,
                # wall ends, the corridor's end) is kept, at its own point-to-line information
                R_body = self._scan_covariance(scan.geometry)
            if not np.isfinite(new_pose).all():  # numerical failure: treat like a wrong minimum
                icp_rejected = True
            if icp_rejected:
                z = np.zeros(3)
            R = vector_cov(z, R_body)
            before = self._ekf.snapshot()
            self._ekf.predict(u, cov_u)
            if not icp_rejected and used_wheel and not fallback and not degenerate:
                y, m2 = self._ekf.innovation(z, R)
                outside = m2 > ODOM_JUMP_GATE**2
                beyond = outside and (
                    np.hypot(y[0], y[1]) > ODOM_JUMP_MIN_M or abs(y[2]) > np.deg2rad(ODOM_JUMP_MIN_DEG)
                )
                fault = outside and (
                    wheels_still or _reversed(between(prev_rel, z), u, ODOM_JUMP_MIN_M / 4.0)
                )
                if fault and wheels_still and not self._fits_better(scan.source, new_pose, guess):
                    # stalled wheels only where the scan fits the recent map better at ICP's pose
                    # than at the wheels': a scan that sees little (a short-range laser in a hall:
                    # 20-40 points, people passing) slides a few centimetres from a standing
                    # robot's true pose, and a stall declared on it hands the robot to constant
                    # velocity. Such a scan is a wrong minimum: the wheels carry the step, it is
                    # not mapped. (A lost sign is not asked: FR079's slow reversals, 4-10 cm a
                    # step, move too few points for the sign test, and the wheels are wrong there)
                    fault, icp_rejected = False, True
                if fault:
                    # the scan moved the robot backwards where the wheels say forwards (or the
                    # reverse): wheel odometry that lost the sign of the motion (FR079 logs
                    # reversing at 0.5 m/s as forward motion); or it moved the robot where the
                    # wheels report no motion at all (stalled). A wheel fault: ICP is trusted,
                    # under the constant-velocity prior
                    self._stalled = wheels_still
                    jump, used_wheel, u, cov_u = True, False, cv_u, cv_cov
                    self._ekf.restore(before)
                    self._ekf.predict(u, cov_u)
                elif beyond and cfg.icp_gate == "reject":
                    # ICP far from a plausible wheel increment (which agreed with constant
                    # velocity, or the two-seed test would have flagged a jump): a wrong minimum
                    icp_rejected = True
            if icp_rejected:
                self.stats.icp_rejections += 1
                fallback = True
                R_body = None
                self._resync_icp(u)  # the scan is not added to the local map
            else:
                self._ekf.update(z, R)
                self._commit(frame_ds, new_pose, guess, not (degenerate or fallback))
                if degenerate or fallback:
                    # keep KISS-ICP on the fused estimate along the unobservable axis
                    self._icp.last_pose = to_matrix4(compose(self._kf_icp, self._ekf.x))
        if jump:
            self.stats.odom_jumps += 1
        if degenerate:
            self.stats.degenerate_scans += 1
        if fallback:
            self.stats.fallbacks += 1

        rel = self._ekf.x
        self._last_increment = between(prev_rel, rel)
        self._last_dt = dt
        self._learn_offset(uw_raw, dt, used_wheel and not (jump or fallback or degenerate or icp_rejected))
        is_kf = np.hypot(rel[0], rel[1]) >= self._kf_dist or abs(rel[2]) >= self._kf_angle
        if cfg.keyframe_max_interval_s is not None and stamp - self._kf_stamp >= cfg.keyframe_max_interval_s:
            is_kf = True
        if is_kf:
            return self._new_keyframe(
                stamp, rel, R_body, degenerate, axis, fallback, jump, dropped, len(pts), icp_rejected
            )
        _, cov_t = self._ekf.relative()
        return OdometryResult(
            stamp,
            compose(self._kf_pose, rel),
            self._kf_index,
            False,
            rel,
            None,
            cov_t,
            degenerate,
            axis,
            fallback,
            jump,
            dropped,
            len(pts),
            icp_rejected,
            self._period,
        )

    # ----------------------------------------------------------------- helpers
    def _first(self, stamp: float, pts: np.ndarray, wheel: np.ndarray | None) -> OdometryResult:
        self._t_hist.append(stamp)
        self._prev_wheel = self._prev_raw = wheel
        start = wheel.copy() if wheel is not None else np.zeros(3)
        self._kf_pose = start
        fallback = len(pts) < self.config.min_points
        if fallback:
            self.stats.empty_scans += 1
            self.stats.fallbacks += 1
        else:
            self._icp.register_frame(np.column_stack((pts, np.zeros(len(pts)))), self._empty_ts)
            if self.config.local_map_scans:
                self._added_pose = from_matrix(self._icp.last_pose)
                self._recent.append(transform_points(self._added_pose, _local_points(pts)))
        self._kf_icp = from_matrix(self._icp.last_pose)
        self._kf_index = 0
        self._kf_stamp = stamp
        self.stats.keyframes += 1
        self._ekf.reset()
        return OdometryResult(
            stamp,
            start.copy(),
            0,
            True,
            np.zeros(3),
            None,
            np.zeros((3, 3)),
            fallback=fallback,
            n_points=len(pts),
        )

    def _learn_offset(self, uw_raw: np.ndarray | None, dt: float, held: bool) -> None:
        """One step of the wheel-to-scan time offset's estimate (time_offset.py): the logged wheel
        step ``uw_raw`` against the fused one, where the scan held the step (``held``) and the
        stamps keep time (a steady clock, :meth:`_clock`: an offset cannot be measured against
        bursty stamps)."""
        if uw_raw is None or not held or not self._steady or dt <= 0.0:
            self._toff.add(None)
        else:
            self._toff.add(float(uw_raw[2]) / dt, float(wrap(self._last_increment[2] - uw_raw[2])))
        st, toff = self.stats, self._toff
        st.time_offset, st.time_offset_sigma, st.time_offset_applied = toff.estimate, toff.sigma, toff.applied

    def _clock(self, stamp: float) -> tuple[float, float, float, int]:
        """Seconds of motion since the previous scan: ``dt`` for the motion model, ``span`` the
        longest it can have been (the wheel step then tells: motion_model.constant_velocity_span),
        ``dt_speed`` for the speed test of the wheel increment; and the scans a stamp gap says
        were dropped.

        Scans are taken in arrival order, each keeps its own stamp. Host stamps can jitter: a
        logger that writes scans in bursts stamps several of them within a millisecond, then none
        for half a second, and some are stamped before their predecessor (the Intel log: a
        quarter of its steps are under 2 ms, 631 are negative, at a 0.2 s scan period). On such
        an unsteady clock (recent steps off the nominal period by more than a quarter of it, in
        the median) a step cannot tell a gap from a late stamp: each scan is at least one
        nominal period of motion, at most the stamp step (``span``: a logger pause), and no scan
        counts as dropped. On a steady clock the step is the stamp
        difference, and one over ``GAP_FACTOR`` periods counts dropped scans. The speed test
        never gets less than one period, so a burst of stamps is never a wheel-odometry jump.
        """
        t = self._t_hist
        raw = stamp - t[-1]
        if raw <= 0.0:
            self.stats.out_of_order += 1
        t.append(max(stamp, t[-1]))
        period, steady = self._period, self._steady
        if len(t) > _PERIOD_SPAN:
            # median over the window of the mean step across _PERIOD_SPAN scans: bursts average
            # out within a span, a stamp gap spoils only the spans across it
            a = np.fromiter(t, dtype=np.float64)
            self._period = _median(a[_PERIOD_SPAN:] - a[:-_PERIOD_SPAN]) / _PERIOD_SPAN
            steps = a[1:] - a[:-1]  # np.diff
            self._steady = _median(np.abs(steps - self._period)) < 0.25 * self._period
        elif len(t) > 1:
            self._period = (t[-1] - t[0]) / (len(t) - 1)
        if len(t) <= _PERIOD_SPAN + 1:  # the first steps: no reliable period yet
            return max(raw, 1e-6), max(raw, 1e-6), max(raw, _FIRST_SPEED_STEP), 0
        if not steady:
            return period, max(raw, period), max(raw, period), 0
        dropped = 0
        if raw > GAP_FACTOR * period:
            dropped = max(int(round(raw / period)) - 1, 1)
            self.stats.dropped_scans += dropped
            self.stats.gaps += 1
        dt = raw if raw >= 0.5 * period else period
        return dt, dt, max(raw, period), dropped

    def _scan_covariance(self, geo: ScanGeometry) -> np.ndarray:
        """Body-frame ICP covariance from the scan's point-to-line Hessian alone (m, rad; no
        inflation along a degenerate axis), floored and capped as :meth:`_icp_covariance`'s."""
        return np.minimum(self._hessian_covariance(geo), _COV_CAP)

    def _hessian_covariance(self, geo: ScanGeometry) -> np.ndarray:
        """The scan's point-to-line Hessian inverted and scaled by the ICP sigma, symmetric and
        floored (m, rad; body frame), before any inflation or cap."""
        H = geo.hessian + 1e-9 * np.eye(3)
        cov = np.linalg.inv(H) * (self.config.icp_sigma**2 * ICP_COV_INFLATION)
        return 0.5 * (cov + cov.T) + self._floor

    def _icp_covariance(self, geo: ScanGeometry) -> tuple[np.ndarray, bool, bool, np.ndarray | None]:
        """Body-frame ICP covariance, degenerate flag, fallback flag, degenerate axis."""
        cfg = self.config
        if geo.n_normals < 10:
            big = np.diag([DEGENERATE_SIGMA**2] * 2 + [np.pi**2])
            return big, True, True, None
        cov = self._hessian_covariance(geo)
        degenerate = geo.eig_ratio < cfg.degeneracy_threshold
        axis = None
        if degenerate:
            axis = geo.weak_axis / np.linalg.norm(geo.weak_axis)
            a3 = np.array([axis[0], axis[1], 0.0])
            cov = cov + DEGENERATE_SIGMA**2 * np.outer(a3, a3)
        # an ill-conditioned Hessian also gives a huge inverse along the axis; cap it
        cov = np.minimum(cov, _COV_CAP)
        return cov, degenerate, False, axis

    def _possible(self, step: np.ndarray, dt: float) -> bool:
        """Whether a step (x, y, theta; m, rad) over ``dt`` seconds is within the robot's speed and
        turn rate (``max_speed``, ``max_turn_rate_deg``), with the wheel test's margins; a non-finite
        step is not."""
        cfg = self.config
        if not np.isfinite(step).all():
            return False
        return bool(
            np.hypot(step[0], step[1]) <= cfg.max_speed * dt + 0.05
            and abs(step[2]) <= np.deg2rad(cfg.max_turn_rate_deg) * dt + np.deg2rad(2.0)
        )

    def _fits_better(self, source: np.ndarray, pose: np.ndarray, guess: np.ndarray) -> bool:
        """Whether the scan's KISS-ICP source points fit KISS-ICP's local map at ``pose`` (4×4, the
        ICP result) by ``_SEED_MARGIN`` more than at ``guess`` (4×4, the prediction), within two
        voxels (the two-seed test's measure); True on an empty map."""
        icp = self._icp
        if icp.local_map.empty():
            return True
        at_pose, at_guess = _inliers(
            icp.local_map.point_cloud(), source, [pose, guess], 2.0 * self.config.voxel_size
        )
        gained = int(np.count_nonzero(at_pose & ~at_guess))
        lost = int(np.count_nonzero(at_guess & ~at_pose))
        # and by more than chance: the points gained outnumber those lost by _FAULT_SIGMAS sigmas
        # of a sign test (McNemar's), which a scan of 20-40 points rarely reaches
        more = gained - lost > _SEED_MARGIN * len(source)
        return bool(more and gained - lost > _FAULT_SIGMAS * np.sqrt(gained + lost))

    def _disagree(self, a: np.ndarray, b: np.ndarray, cov: np.ndarray) -> bool:
        d = between(b, a)
        big = np.hypot(d[0], d[1]) > ODOM_JUMP_MIN_M or abs(d[2]) > np.deg2rad(ODOM_JUMP_MIN_DEG)
        return bool(big and d @ np.linalg.solve(cov, d) > ODOM_JUMP_GATE**2)

    def _align(
        self, scan: PreparedScan, seeds: list[np.ndarray]
    ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """KISS-ICP's register_frame up to the alignment, with one or more seed increments.

        Same steps as ``KissICP.register_frame`` (preprocess and voxelise: :meth:`prepare`; align);
        nothing is changed until :meth:`_commit`. With more seeds, each is aligned and the one whose
        result has the most source points near the local map wins if that beats seed 0's by 0.05
        (else seed 0). Where the refinement runs, the winner may still lose to itself turned
        (:meth:`_turned`). Returns (the winning seed increment, None for seed 0; pose 4×4, initial
        guess 4×4, thinned frame for the map).
        """
        icp = self._icp
        source, frame_ds = scan.source, scan.frame_ds
        guesses = [icp.last_pose @ to_matrix4(s) for s in seeds]
        poses = self._kiss_align(source, guesses)
        best = 0
        if len(poses) > 1 and not icp.local_map.empty():
            first = from_matrix(poses[0])
            apart = []
            for j in range(1, len(poses)):
                d = between(first, from_matrix(poses[j]))
                if np.hypot(d[0], d[1]) > 0.02 or abs(d[2]) > np.deg2rad(0.5):
                    apart.append(j)
            if apart:
                scores = _inlier_fractions(
                    icp.local_map.point_cloud(), source, poses, 2.0 * self.config.voxel_size
                )
                j = max(apart, key=lambda j: scores[j])
                best = j if scores[j] > scores[0] + _SEED_MARGIN else 0
        chosen, pose, guess = (seeds[best] if best else None), poses[best], guesses[best]
        if self.config.local_map_scans:  # the refinement (off: nothing more on this hot path)
            self._aligned_points = _local_points(scan.points)
            if not scan.icp_covariance[1] and self._local_map() is not None:  # not along a corridor
                turned, at_pose = self._turned(source, seeds[best], pose)
                if turned is not None:
                    chosen, pose, guess = turned
                    at_pose = None  # the look-up was at KISS-ICP's pose from the seed that lost
                pose = self._refine(self._aligned_points, pose, at_pose)
        return chosen, pose, guess, frame_ds

    def _kiss_align(self, source: np.ndarray, guesses: list[np.ndarray]) -> list[np.ndarray]:
        """KISS-ICP's alignment of ``source`` to its local map from each initial guess (4×4)."""
        icp = self._icp
        sigma = icp.adaptive_threshold.get_threshold()
        return [
            icp.registration.align_points_to_map(
                points=source,
                voxel_map=icp.local_map,
                initial_guess=g,
                max_correspondance_distance=3 * sigma,
                kernel=sigma,
            )
            for g in guesses
        ]

    def _turned(
        self, source: np.ndarray, seed: np.ndarray, pose: np.ndarray
    ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, np.ndarray | None]:
        """The seed increment turned by one of ``_TURN_SEEDS_DEG`` when KISS-ICP's pose (4×4) from
        it fits the recent scans' walls worse than the recent scans fitted (their median share of
        points within a voxel, less ``_TURN_MARGIN``) and a turned seed's pose does not, putting
        ``_TURN_MARGIN`` more of the scan on them: (turned seed, its pose, its guess); else None.
        Returned with the look-up distances of the scan's points at ``pose`` (``LineMap.lookup_distances``;
        None without points), which :meth:`_refine`'s fit test of that pose reuses.
        (Where the scan sees little of what the recent scans saw, a pose turned the wrong way can
        fit a little better than the right one: FR079 at 1,471 s, 0.65 against 0.55, where the
        recent scans fitted at 0.93.)

        Wheels that miss part of a fast turn (FR079's, spinning at 40 deg/s: 8-23 deg missing
        over a second) put the seed beyond KISS-ICP's reach in heading, and the wheels and
        constant velocity agree, so the two-seed test does not fire. The fits are taken on the
        refinement's line map of the recent scans, within one voxel: KISS-ICP's voxel map at
        twice the voxel, the two-seed test's measure, scores a pose 5 deg off as well as the
        right one where the scan sees new ground (FR079 at 2,050 s).
        """
        ref, points, within = self._local_ref, self._aligned_points, self.config.voxel_size
        at_pose = (
            ref.lookup_distances(points, [from_matrix(pose)]) if len(points) and len(ref.points) else None
        )
        fit = float(fractions_within(at_pose, within)[0]) if at_pose is not None else 0.0
        bar = (_median(np.array(self._fits)) if self._fits else 1.0) - _TURN_MARGIN
        out = None
        if fit < bar:
            seeds = [seed + np.array([0.0, 0.0, np.deg2rad(d)]) for d in _TURN_SEEDS_DEG]
            guesses = [self._icp.last_pose @ to_matrix4(s) for s in seeds]
            poses = self._kiss_align(source, guesses)
            fits = ref.inlier_fractions(points, [from_matrix(p) for p in poses], within)
            j = int(np.argmax(fits))
            if fits[j] >= bar and fits[j] > fit + _TURN_MARGIN:
                out, fit = (seeds[j], poses[j], guesses[j]), float(fits[j])
        self._fits.append(fit)
        return out, at_pose

    def _refine(self, points: np.ndarray, pose: np.ndarray, at_pose: np.ndarray | None = None) -> np.ndarray:
        """KISS-ICP's pose (4×4, its frame) refined by point-to-line ICP on the recent scans.

        KISS-ICP matches points to the sparse points of its voxel map, so a scan can slide a few
        centimetres along a wall (ACES / FR079 relations under 2 s: 0.041 / 0.040 m, 0.54 / 1.16
        deg; with the refinement 0.038 / 0.026 m, 0.36 / 0.42 deg). A refinement that moves the
        pose by more than _REFINE_MAX_STEP / _REFINE_MAX_TURN, or that fits fewer points, is not
        trusted: KISS-ICP's pose stays. ``at_pose``: the points' look-up distances at ``pose``
        (:meth:`_turned`), if known.
        """
        start = from_matrix(pose)
        res = icp_point_to_line(
            self._local_ref, points, start, _REFINE_ITERATIONS, _REFINE_MAX_DISTANCE, 0.05, 0.05
        )
        if res is None or not np.isfinite(res[0]).all() or not np.isfinite(res[1]).all():
            return pose
        d = between(start, res[0])
        if np.hypot(d[0], d[1]) > _REFINE_MAX_STEP or abs(d[2]) > _REFINE_MAX_TURN:
            return pose
        # fused with KISS-ICP's pose as a prior: where the lines leave a direction unobserved
        # (along a corridor) the refinement must not slide, KISS-ICP's pose (seeded by the
        # wheels) stays; elsewhere the refinement's information dominates
        try:
            info = np.linalg.inv(res[1])
            d = np.linalg.solve(info + _REFINE_PRIOR_INFO, info @ d)
        except np.linalg.LinAlgError:
            return pose
        refined = compose(start, d)
        # a refinement that fits fewer points to the map than KISS-ICP's pose converged wrongly
        # (seen while rotating in place at 10-20 deg per scan: a few degrees off)
        if at_pose is None:
            fit_refined, fit_start = self._local_ref.inlier_fractions(
                points, [refined, start], _REFINE_INLIER
            )
        else:  # the start's look-up is _turned's (the same pose, the same points)
            fit_refined = self._local_ref.inlier_fractions(points, [refined], _REFINE_INLIER)[0]
            fit_start = fractions_within(at_pose, _REFINE_INLIER)[0]
        if fit_refined < fit_start:
            return pose
        return to_matrix4(refined)

    def _commit(
        self, frame_ds: np.ndarray, new_pose: np.ndarray, guess: np.ndarray, held: bool = True
    ) -> None:
        """The rest of ``register_frame``: threshold model, local map, delta and pose. ``held``: the
        scan's own match fixes its pose (neither degenerate nor a fallback), so it may be left out of
        the refinement's window when it stands (:meth:`_near_added`)."""
        icp = self._icp
        icp.adaptive_threshold.update_model_deviation(np.linalg.inv(guess) @ new_pose)
        icp.local_map.update(frame_ds, new_pose)
        icp.last_delta = np.linalg.inv(icp.last_pose) @ new_pose
        icp.last_pose = new_pose
        n = self.config.local_map_scans
        if n:
            pose = from_matrix(new_pose)
            if held and self._near_added(pose):
                return  # a standing robot: the window keeps its scans, the local map its normals
            self._added_pose = pose
            self._recent.append(transform_points(pose, self._aligned_points))
            self._since_rebuild += 1
            if self._since_rebuild >= _LOCAL_MAP_REBUILD and len(self._recent) >= min(n, 3):
                self._local_stale = True
                self._since_rebuild = 0

    def _near_added(self, pose: np.ndarray) -> bool:
        """Whether ``pose`` (KISS-ICP's frame; m, rad) is within _STILL_STEP and _STILL_TURN of the
        last scan added to the refinement's window: its scan would add near-duplicates of the same
        walls and push older (more informative) scans out. Taken against the last scan added, not the
        previous scan, so that a slow creep still adds a scan once it has moved that far."""
        last = self._added_pose
        if last is None:
            return False
        d = between(last, pose)
        return math.hypot(d[0], d[1]) < _STILL_STEP and abs(d[2]) < _STILL_TURN

    def _local_map(self) -> LineMap | None:
        """The refinement's local map of the recent scans (KISS-ICP's frame), None before there
        are enough. Rebuilt on first use after the commits that call for it (:meth:`_commit`):
        the same map as one built at the commit, never built for scans that do not refine
        (along a corridor, too few points)."""
        if self._local_stale:
            pts = cell_means(np.concatenate(self._recent), self.config.voxel_size)
            self._local_ref = LineMap(pts, _LOCAL_MAP_RESOLUTION, _REFINE_MAX_DISTANCE)
            self._local_stale = False
        return self._local_ref

    def _resync_icp(self, u: np.ndarray) -> None:
        self._icp.last_pose = to_matrix4(compose(self._kf_icp, self._ekf.x))
        self._icp.last_delta = to_matrix4(u)

    def _new_keyframe(
        self, stamp, rel, R_body, degenerate, axis, fallback, jump, dropped, n_points, icp_rejected=False
    ):
        between_pose, cov = self._ekf.relative()
        self._kf_pose = compose(self._kf_pose, rel)
        self._kf_icp = (
            compose(self._kf_icp, rel) if (fallback or degenerate) else from_matrix(self._icp.last_pose)
        )
        self._kf_index += 1
        self._kf_stamp = stamp
        self.stats.keyframes += 1
        self._ekf.reset()
        return OdometryResult(
            stamp,
            self._kf_pose.copy(),
            self._kf_index,
            True,
            np.zeros(3),
            between_pose,
            cov,
            degenerate,
            axis,
            fallback,
            jump,
            dropped,
            n_points,
            icp_rejected,
            self._period,
        )


def _cv_alternatives(cv_u: np.ndarray, cv_cov: np.ndarray) -> list[np.ndarray]:
    """Seeds beside the constant-velocity increment ``cv_u`` (x, y m, theta rad; previous
    base_link frame) that its own random walk ``cv_cov`` allows: turned one heading sigma either
    way (a turn that starts, ends or speeds up within the step) and no motion (a robot that
    stops; none when ``cv_u`` is no motion already). :meth:`ScanOdometry._align` keeps the
    constant-velocity one unless another fits the local map clearly better."""
    turn = np.array([0.0, 0.0, float(np.sqrt(cv_cov[2, 2]))])
    out = [compose(cv_u, turn), compose(cv_u, -turn)]
    if cv_u.any():
        out.append(np.zeros(3))
    return out


def _reversed(icp_increment: np.ndarray, wheel_increment: np.ndarray, least: float) -> bool:
    """True when the two increments move along base_link x in opposite directions, each by more
    than ``least`` metres."""
    a, b = float(icp_increment[0]), float(wheel_increment[0])
    return a * b < 0.0 and min(abs(a), abs(b)) > least


def _inlier_fractions(
    map_points: np.ndarray, source: np.ndarray, poses: list[np.ndarray], radius: float
) -> list[float]:
    """Fraction of the source points within ``radius`` of the map, for each candidate pose (4×4)."""
    return [
        float(np.count_nonzero(m) / max(len(source), 1)) for m in _inliers(map_points, source, poses, radius)
    ]


def _inliers(
    map_points: np.ndarray, source: np.ndarray, poses: list[np.ndarray], radius: float
) -> list[np.ndarray]:
    """Per candidate pose (4×4), which source points (a bool mask over them) lie within ``radius``
    of the map; a non-finite transformed point never does.

    Bounded work: only the map points in cells (of side ``radius``) next to a transformed source
    point can be within ``radius`` of it, so the k-d tree is built on those alone (exactly the same
    result as a tree over the whole local map, whose size grows with the explored area).
    """
    from scipy.spatial import cKDTree

    mp = np.asarray(map_points)[:, :2]
    moved = [source[:, :2] @ T[:2, :2].T + T[:2, 3] for T in poses]
    finite = [np.all(np.isfinite(p), axis=1) for p in moved]  # a failed pose: no inliers
    near = _near_cells(mp, np.vstack([p[f] for p, f in zip(moved, finite, strict=True)]), radius)
    tree = cKDTree(mp[near])
    out = []
    for p, f in zip(moved, finite, strict=True):
        mask = np.zeros(len(p), dtype=bool)
        if tree.n and np.any(f):
            dist, _ = tree.query(p[f], distance_upper_bound=radius)
            mask[f] = np.isfinite(dist)
        out.append(mask)
    return out


def _near_cells(points: np.ndarray, queries: np.ndarray, radius: float) -> np.ndarray:
    """Mask of ``points`` (N, 2) that may lie within ``radius`` of a query (a superset).

    On a raster of cells a hair larger than ``radius`` (both sets indexed by the same monotone
    formula), a point within ``radius`` of a query is in the query's cell or a neighbouring one:
    the queries' cells dilated by one, with a false border onto which outside points are clipped.
    """
    if len(queries) == 0 or len(points) == 0:
        return np.zeros(len(points), dtype=bool)
    # queries away from every point (a diverged seed pose) would only stretch the raster
    x, y = points[:, 0], points[:, 1]
    m = 2.0 * radius
    qx, qy = queries[:, 0], queries[:, 1]
    queries = queries[(qx >= x.min() - m) & (qx <= x.max() + m) & (qy >= y.min() - m) & (qy <= y.max() + m)]
    if len(queries) == 0:
        return np.zeros(len(points), dtype=bool)
    inv = 1.0 / (radius * (1.0 + 1e-6))
    o = queries.min(axis=0) - 3.0 / inv  # query cells >= 2: dilation and border fit below
    qi = ((queries - o) * inv).astype(np.intp)
    shape = (qi.max(axis=0) + 3).tolist()
    occ = np.zeros(shape, dtype=bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            occ[qi[:, 0] + dx, qi[:, 1] + dy] = True
    ix = np.clip((x - o[0]) * inv, 0, shape[0] - 1).astype(np.intp)
    iy = np.clip((y - o[1]) * inv, 0, shape[1] - 1).astype(np.intp)
    return occ[ix, iy]


_PERIOD_SPAN = 10  # scans per span of the nominal period's estimate (ScanOdometry._clock)
_PERIOD_WINDOW = 60  # recent stamps it looks at
_FIRST_SPEED_STEP = 0.1  # s: least step of the speed test before the period is known (5-40 Hz lasers)
# point-to-line refinement of KISS-ICP (ScanOdometry._refine)
_LOCAL_MAP_REBUILD = 1  # commits between rebuilds of its local map (3 let ACES's heading drift more)
_LOCAL_MAP_RANGE = 15.0  # m; farther points stay out of it and of the refinement (grid size)
_LOCAL_MAP_RESOLUTION = 0.05  # m
# a committed scan within both of the last scan added to the local map's window is not added (a
# standing robot, ScanOdometry._near_added): m, a fifth of the map's cell; rad, the turn that moves
# a point 10 m away by as much
_STILL_STEP = 0.2 * _LOCAL_MAP_RESOLUTION
_STILL_TURN = _STILL_STEP / 10.0
_REFINE_ITERATIONS = 6
_REFINE_MAX_DISTANCE = 0.3  # m, association distance (the second half of the iterations: half)
_REFINE_MAX_STEP = 0.3  # m (the association distance), a larger move from KISS-ICP's pose is not trusted
_REFINE_MAX_TURN = np.deg2rad(5.0)
_REFINE_INLIER = 0.05  # m, inlier distance of the refinement's fit test
_REFINE_PRIOR_INFO = np.diag([1.0 / 0.02**2, 1.0 / 0.02**2, 1.0 / np.deg2rad(0.5) ** 2])  # KISS-ICP's pose
_COV_CAP = DEGENERATE_SIGMA**2  # m², rad²: a cap on every entry of the ICP covariance
# deg; turns of the winning seed tried when its pose leaves over _TURN_MARGIN of the scan off the map
_SEED_MARGIN = 0.05  # share of points: another pose must fit the local map by this much more to win
_FAULT_SIGMAS = 3.0  # sign-test sigmas by which a wheel fault's scan must fit better (_fits_better)
_TURN_SEEDS_DEG = (-10.0, -5.0, 5.0, 10.0)
# share of the scan within a voxel of the recent scans' walls that a turned seed must add to win:
# twice the two-seed test's, as a turned seed departs from both predictions
_TURN_MARGIN = 0.1
_EYE4 = np.eye(4)  # deskewing is off: the preprocessor's relative motion is unused


def _median(a: np.ndarray) -> float:
    """np.median of a short finite 1-D array, the same value (the middle one, or the mean of the
    two middle ones), without np.median's overhead (~40 us, twice per scan)."""
    s = np.sort(a)
    h = len(s) // 2
    return float(s[h]) if len(s) % 2 else float((s[h - 1] + s[h]) / 2.0)


def _local_points(points: np.ndarray) -> np.ndarray:
    """Points (M, 2) within _LOCAL_MAP_RANGE of base_link: those the refinement's local map keeps."""
    return points.compress(np.einsum("ij,ij->i", points, points) <= _LOCAL_MAP_RANGE**2, axis=0)


def _valid_points(points: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 2:
        raise RecordingError(f"scan points must be an (M, 2) array, got shape {pts.shape}", where="points")
    pts = pts[:, :2]
    r = np.hypot(pts[:, 0], pts[:, 1])
    ok = np.isfinite(r) & (r >= max(min_range, 1e-6)) & (r <= max_range)
    return pts.compress(ok, axis=0)  # the rows of pts[ok], ~2x faster


__all__ = ["OdometryResult", "OdometryStats", "PreparedScan", "ScanGeometry", "ScanOdometry", "scan_geometry"]
