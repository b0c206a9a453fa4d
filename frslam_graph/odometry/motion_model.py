"""The paper's motion model x_t = g(u_t, x_{t-1}) + e_t in SE(2), and an EKF that fuses it with ICP.

Poses are (x, y, theta) arrays: metres, radians, theta wrapped to [-pi, pi); their algebra
(``compose(a, b)`` = a ⊕ b, ``between(a, b)`` = a⁻¹ ⊕ b, ...) is :mod:`frslam_graph.se2`. A wheel-odometry increment u_t is
``between(odom_{t-1}, odom_t)`` (base_link motion in the previous base_link frame).

:class:`MotionEKF` (filterpy ``ExtendedKalmanFilter``) keeps the pose of the current ``base_link``
relative to the last keyframe: it predicts with g(u_t, ·) (wheel odometry or constant velocity)
and is updated with the KISS-ICP pose relative to the same keyframe. Its output is the fused
relative motion between keyframes and its 3×3 covariance, also given in GTSAM's Pose2 tangent
convention (right perturbation: x_true = x ⊕ Exp(ξ)) for a ``BetweenFactorPose2``.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

# The pose algebra lives in frslam_graph.se2. between_many, compose_many, from_matrix, inverse,
# to_matrix, to_matrix4 and vector_cov are only re-exported: the backend, odometry, loop-closure
# and plan-update modules and their tests import them from here until they import frslam_graph.se2.
from frslam_graph.se2 import (  # noqa: F401
    Pose,
    between,
    between_many,
    compose,
    compose_jacobians,
    compose_many,
    exp,
    from_matrix,
    inverse,
    log,
    tangent_cov,
    to_matrix,
    to_matrix4,
    vector_cov,
    wrap,
)


def wheel_increment(odom_prev: Pose, odom_curr: Pose) -> np.ndarray:
    """u_t: base_link motion between two wheel-odometry poses, in the previous base_link frame."""
    return between(np.asarray(odom_prev, float), np.asarray(odom_curr, float))


def wheel_noise(
    u: Pose,
    dist_frac: float = 0.02,
    rot_per_m: float = np.deg2rad(1.0),
    rot_frac: float = 0.02,
    floor_xy: float = 0.002,
    floor_theta: float = np.deg2rad(0.1),
    correlation_length: float = 0.0,
) -> np.ndarray:
    """3×3 covariance of a wheel increment u (in its own start frame).

    Translation: sigma = dist_frac · sqrt(d · max(d, L)) along and across the motion (isotropic, so
    slip sideways is covered); heading: sigma = rot_per_m · sqrt(d · max(d, L)) + rot_frac ·
    |dtheta|; both floored. ``L = correlation_length`` (m) is the distance over which wheel errors
    stay correlated (a wrong wheel radius, a slow heading bias): summed over the increments of a
    stretch s <= L the white-noise model still allows dist_frac · s, the error a systematic 2 %
    scale error makes there, where the plain per-increment dist_frac · d would allow only
    dist_frac · s / sqrt(n) after n increments (an odometry chain that overrules right floor-plan
    priors after a long stretch without them). L = 0 gives the per-increment model.
    """
    d = float(np.hypot(u[0], u[1]))
    dl = float(np.sqrt(d * max(d, correlation_length)))
    sxy = max(dist_frac * dl, floor_xy)
    sth = max(rot_per_m * dl + rot_frac * abs(float(u[2])), floor_theta)
    return np.diag([sxy * sxy, sxy * sxy, sth * sth])


def constant_velocity(last_increment: Pose, dt_last: float, dt: float) -> np.ndarray:
    """Predicted increment for a step of dt seconds when the previous one took dt_last seconds."""
    if dt_last <= 0.0 or not np.isfinite(dt_last):
        return np.zeros(3)
    k = dt / dt_last  # clipped to [0, 20] as np.clip (a NaN stays NaN), without its array round trip
    k = float(0.0 if k < 0.0 else 20.0 if k > 20.0 else k)
    # exact for constant twist: scale the twist, not the pose components
    v = log(last_increment) * k
    return exp(v)


def constant_velocity_span(
    last_increment: Pose,
    dt_last: float,
    step: Pose,
    dt: float,
    span: float,
    sigma_xy_per_s: float,
    sigma_theta_per_s: float,
) -> float:
    """Seconds t in [dt, span] over which the last velocity (``last_increment`` over ``dt_last``
    seconds) comes nearest to ``step`` (weighted least squares on the twists, weights the
    constant-velocity noise per second); ``dt`` when ``span <= dt`` or the robot stood.

    A clock that cannot tell the time between two scans (bursty stamps: a late stamp or a logger
    pause both make a long step) bounds it only: at least one period ``dt``, at most the stamp
    step ``span``. The wheel step then tells how long the robot kept moving.
    """
    if not span > dt or dt_last <= 0.0 or not np.isfinite(dt_last):
        return dt
    v = log(np.asarray(last_increment, dtype=np.float64)) / dt_last
    w = np.array([1.0 / sigma_xy_per_s**2, 1.0 / sigma_xy_per_s**2, 1.0 / sigma_theta_per_s**2])
    den = float(np.sum(w * v * v))
    if not den > 1e-12:
        return dt
    t = float(np.sum(w * v * log(np.asarray(step, dtype=np.float64)))) / den
    return float(np.clip(t, dt, span))


def constant_velocity_noise(dt: float, sigma_xy_per_s: float, sigma_theta_per_s: float) -> np.ndarray:
    dt = max(float(dt), 1e-3)
    return np.diag([(sigma_xy_per_s * dt) ** 2] * 2 + [(sigma_theta_per_s * dt) ** 2])


def g(u: Pose, x_prev: Pose) -> np.ndarray:
    """The motion model's mean: x_t = x_{t-1} ⊕ u_t."""
    return compose(x_prev, u)


class _PoseEKF(ExtendedKalmanFilter):
    """filterpy EKF whose state prediction is the SE(2) composition x ⊕ u (not F x + B u)."""

    def predict_x(self, u: np.ndarray | int = 0) -> None:
        self.x = compose(self.x[:, 0], np.asarray(u, dtype=np.float64)).reshape(3, 1)


class MotionEKF:
    """EKF on the pose of base_link relative to the last keyframe (state (3,), covariance (3, 3)).

    ``predict(u, cov_u)`` applies g; ``update(z, R)`` fuses a measurement of the same relative
    pose (KISS-ICP), with an angle-wrapping residual; ``reset()`` starts a new keyframe.
    """

    def __init__(self) -> None:
        self._kf = _PoseEKF(dim_x=3, dim_z=3)
        self.reset()

    def reset(self) -> None:
        self._kf.x = np.zeros((3, 1))
        self._kf.P = np.zeros((3, 3))

    @property
    def x(self) -> np.ndarray:
        return self._kf.x[:, 0].copy()

    @property
    def P(self) -> np.ndarray:
        return self._kf.P.copy()

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        return self._kf.x.copy(), self._kf.P.copy()

    def restore(self, snap: tuple[np.ndarray, np.ndarray]) -> None:
        self._kf.x, self._kf.P = snap[0].copy(), snap[1].copy()

    def set_state(self, x: Pose, P: np.ndarray) -> None:
        self._kf.x = np.asarray(x, float).reshape(3, 1).copy()
        self._kf.P = np.asarray(P, float).reshape(3, 3).copy()

    def predict(self, u: Pose, cov_u: np.ndarray) -> None:
        """x ← g(u, x); P ← F P Fᵀ + G Σ_u Gᵀ."""
        x = self._kf.x[:, 0]
        fa, gb = compose_jacobians(x, u)
        self._kf.F = fa
        self._kf.Q = gb @ cov_u @ gb.T
        self._kf.predict(u=np.asarray(u, dtype=np.float64))

    def innovation(self, z: Pose, R: np.ndarray) -> tuple[np.ndarray, float]:
        """Residual z - x (angle wrapped) and its squared Mahalanobis distance under P + R."""
        y = _residual(np.asarray(z, float).reshape(3, 1), self._kf.x)[:, 0]
        S = self._kf.P + R
        return y, float(y @ np.linalg.solve(S, y))

    def update(self, z: Pose, R: np.ndarray) -> None:
        """Fuse a direct measurement z of the relative pose with covariance R (H = I)."""
        self._kf.update(
            np.asarray(z, float).reshape(3, 1),
            HJacobian=_identity_jacobian,
            Hx=_identity,
            R=np.asarray(R, float),
            residual=_residual,
        )
        self._kf.x[2, 0] = wrap(self._kf.x[2, 0])

    def relative(self) -> tuple[np.ndarray, np.ndarray]:
        """Fused relative pose since the keyframe and its covariance in GTSAM's tangent convention."""
        x = self.x
        cov = tangent_cov(x, 0.5 * (self._kf.P + self._kf.P.T))
        return x, cov


def _identity(x: np.ndarray) -> np.ndarray:
    return x


def _identity_jacobian(x: np.ndarray) -> np.ndarray:
    return _EYE3


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False  # shared by every update (filterpy only multiplies by it)


def _residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    y = a - b
    y[2, 0] = wrap(y[2, 0])
    return y
