"""SE(2) motion model and the EKF that fuses wheel odometry with ICP."""

from __future__ import annotations

import gtsam
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from frslam_graph.odometry.motion_model import (
    MotionEKF,
    between,
    between_many,
    compose,
    compose_jacobians,
    constant_velocity,
    constant_velocity_span,
    g,
    inverse,
    tangent_cov,
    wheel_increment,
    wheel_noise,
    wrap,
)

pose_st = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-np.pi, np.pi)).map(
    lambda t: np.array(t)
)


@settings(max_examples=60, deadline=None)
@given(pose_st, pose_st)
def test_compose_between_inverse_match_gtsam(a, b):
    ga, gb = gtsam.Pose2(*a), gtsam.Pose2(*b)
    ab = ga.compose(gb)
    np.testing.assert_allclose(compose(a, b)[:2], [ab.x(), ab.y()], atol=1e-9)
    assert abs(wrap(compose(a, b)[2] - ab.theta())) < 1e-9
    np.testing.assert_allclose(compose(a, between(a, b))[:2], b[:2], atol=1e-9)
    assert abs(wrap(compose(a, inverse(a))[2])) < 1e-12


def test_compose_jacobians_numeric():
    a, b = np.array([1.0, -2.0, 0.7]), np.array([0.4, 0.1, -0.3])
    ja, jb = compose_jacobians(a, b)
    eps = 1e-6
    num_a = np.column_stack([(compose(a + eps * e, b) - compose(a, b)) / eps for e in np.eye(3)])
    num_b = np.column_stack([(compose(a, b + eps * e) - compose(a, b)) / eps for e in np.eye(3)])
    np.testing.assert_allclose(ja, num_a, atol=1e-5)
    np.testing.assert_allclose(jb, num_b, atol=1e-5)


def test_wheel_increment_is_motion_in_previous_base_frame():
    prev = np.array([2.0, 1.0, np.pi / 2])
    curr = np.array([2.0, 1.5, np.pi / 2 + 0.1])  # 0.5 m forward (along +y in odom), turned 0.1
    u = wheel_increment(prev, curr)
    np.testing.assert_allclose(u, [0.5, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(g(u, prev), curr, atol=1e-12)
    cov = wheel_noise(
        u, dist_frac=0.02, rot_per_m=np.deg2rad(1.0), rot_frac=0.0, floor_xy=0.0, floor_theta=0.0
    )
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [0.01, 0.01, np.deg2rad(0.5)])


def test_constant_velocity_is_exact_for_constant_twist():
    step = np.array([0.1, 0.02, 0.05])
    two = compose(step, step)
    np.testing.assert_allclose(constant_velocity(step, 0.1, 0.2), two, atol=1e-12)
    np.testing.assert_allclose(constant_velocity(step, 0.1, 0.1), step, atol=1e-12)


def test_constant_velocity_span_is_the_time_the_wheel_step_took_within_the_stamps():
    """At 0.3 m/s, a 2.1 m wheel step after a stamp step of 7.1 s took 7 s, not one period
    (0.6 s: all an unsteady clock would give); never outside [dt, span]; dt on a steady clock
    (span = dt), for a robot that stood, and for a wheel step shorter than one period's."""
    last = np.array([0.18, 0.0, 0.0])  # 0.6 s at 0.3 m/s
    sig = (0.5, np.deg2rad(30.0))
    assert constant_velocity_span(last, 0.6, np.array([2.1, 0.0, 0.0]), 0.6, 7.1, *sig) == 7.0
    assert constant_velocity_span(last, 0.6, np.array([4.0, 0.0, 0.0]), 0.6, 7.1, *sig) == 7.1
    assert constant_velocity_span(last, 0.6, np.array([0.1, 0.0, 0.0]), 0.6, 7.1, *sig) == 0.6
    assert constant_velocity_span(last, 0.6, np.array([2.1, 0.0, 0.0]), 0.6, 0.6, *sig) == 0.6
    assert constant_velocity_span(np.zeros(3), 0.6, np.array([2.1, 0.0, 0.0]), 0.6, 7.1, *sig) == 0.6


def test_ekf_prediction_grows_and_measurement_fuses():
    ekf = MotionEKF()
    u = np.array([0.1, 0.0, 0.0])
    cov_u = np.diag([1e-4, 1e-4, 1e-4])
    for _ in range(5):
        ekf.predict(u, cov_u)
    np.testing.assert_allclose(ekf.x, [0.5, 0.0, 0.0], atol=1e-12)
    p_pred = ekf.P
    assert p_pred[1, 1] > 5e-4  # heading uncertainty leaks into y
    z = np.array([0.52, 0.01, 0.0])
    ekf.update(z, np.diag([1e-6, 1e-6, 1e-6]))
    np.testing.assert_allclose(ekf.x, z, atol=2e-3)  # precise ICP dominates
    assert np.all(np.diag(ekf.P) < np.diag(p_pred))


def test_ekf_keeps_prediction_along_an_uninformative_axis():
    ekf = MotionEKF()
    ekf.predict(np.array([1.0, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-6]))
    # ICP slid along x (corridor): huge variance along x, precise across
    ekf.update(np.array([0.2, 0.05, 0.0]), np.diag([100.0, 1e-6, 1e-6]))
    assert abs(ekf.x[0] - 1.0) < 1e-3
    assert abs(ekf.x[1] - 0.05) < 1e-3


def test_ekf_angle_residual_wraps():
    ekf = MotionEKF()
    ekf.set_state([0.0, 0.0, np.pi - 0.01], np.diag([1e-2, 1e-2, 1e-2]))
    ekf.update(np.array([0.0, 0.0, -np.pi + 0.01]), np.diag([1e-2, 1e-2, 1e-2]))
    assert abs(abs(ekf.x[2]) - np.pi) < 0.011  # stays near ±pi, not dragged through 0


def test_tangent_covariance_matches_gtsam_convention():
    """Monte Carlo: additive (x, y, theta) noise -> covariance of Logmap(mean⁻¹ · sample)."""
    rng = np.random.default_rng(0)
    mean = np.array([1.0, 2.0, 1.1])
    cov = np.diag([0.02**2, 0.005**2, 0.01**2])
    samples = rng.multivariate_normal(mean, cov, 20000)
    xi = np.array([gtsam.Pose2.Logmap(gtsam.Pose2(*mean).between(gtsam.Pose2(*s))) for s in samples])
    np.testing.assert_allclose(np.cov(xi.T), tangent_cov(mean, cov), rtol=0.08, atol=2e-6)


def test_log_exp_match_gtsam_near_zero_rotation():
    from frslam_graph.se2 import exp, log

    for th in (0.0, 1e-12, 1e-8, 1e-5, 2e-4, 0.3, 3.0):
        p = np.array([0.3, -0.1, th])
        np.testing.assert_allclose(log(p), gtsam.Pose2.Logmap(gtsam.Pose2(*p)), atol=1e-12)
        np.testing.assert_allclose(exp(log(p)), p, atol=1e-12)


def _summed_std(noise_kw, step, metres):
    """Position std (m) of ``metres`` of straight driving in increments of ``step`` metres, each
    with its own wheel_noise (increments are independent in the pose graph)."""
    n = round(metres / step)
    u = np.array([step, 0.0, 0.0])
    var = n * wheel_noise(u, **noise_kw)[0, 0]
    return float(np.sqrt(var))


def test_wheel_noise_correlation_length_covers_a_systematic_scale_error():
    """A 2 % wheel-radius error makes 2 % of every stretch. Per-increment noise (L = 0) summed over
    n independent increments allows only 2 % / sqrt(n), and less the faster the odometry runs; with
    a correlation length L the summed std is at least 2 % of every stretch up to L, whatever the
    rate."""
    kw = dict(dist_frac=0.02, rot_per_m=np.deg2rad(1.0), rot_frac=0.0, floor_xy=1e-9, floor_theta=1e-9)
    plain_10hz = _summed_std(kw, 0.1, 5.0)
    plain_50hz = _summed_std(kw, 0.02, 5.0)
    assert plain_10hz < 0.2 * 0.02 * 5.0 and plain_50hz < plain_10hz  # overconfident, rate-dependent
    corr = dict(kw, correlation_length=5.0)
    for step in (0.02, 0.1, 0.3):
        for metres in (1.2, 3.0, 4.8):
            assert _summed_std(corr, step, metres) >= 0.02 * metres * 0.999
        np.testing.assert_allclose(_summed_std(corr, step, 4.8), _summed_std(corr, 0.1, 4.8), rtol=1e-6)
    # an increment longer than L keeps the per-increment model; L = 0 is the old model
    u = np.array([8.0, 0.0, 0.0])
    np.testing.assert_allclose(wheel_noise(u, **corr), wheel_noise(u, **kw))
    np.testing.assert_allclose(
        wheel_noise(np.array([0.5, 0.0, 0.1]), **dict(kw, correlation_length=0.0)),
        wheel_noise(np.array([0.5, 0.0, 0.1]), **kw),
    )


def test_between_many_is_between_row_by_row():
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (20, 3))
    b = rng.uniform(-5, 5, (20, 3))
    expected = np.array([between(p, q) for p, q in zip(a, b, strict=True)])
    np.testing.assert_allclose(between_many(a, b), expected, atol=1e-12)
