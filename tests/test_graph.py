"""GTSAM Pose2 graph: robust floor-plan priors, removal, residuals, map->odom, batch."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from frslam_graph.factors.between import between_factor, regularise_covariance
from frslam_graph.factors.floorplan_prior import floorplan_prior, m_estimator, prior_chi2, robust_noise

from frslam_graph.backend.graph import PoseGraph, key
from frslam_graph.config import FRSlamConfig, GraphConfig
from frslam_graph.errors import ConfigError, FrslamError
from frslam_graph.odometry.motion_model import compose, inverse

ODO_COV = np.diag([0.01**2, 0.01**2, np.deg2rad(0.5) ** 2])
PRIOR_COV = np.diag([0.05**2, 0.05**2, 0.02**2])


def chain(n=300, kernel="cauchy", drift=0.0, prior_every=0):
    """Straight chain along x, 0.3 m steps; odometry optionally biased by ``drift`` rad/step.

    With ``prior_every``, correct priors (true pose) arrive while driving, as in the pipeline.
    """
    g = PoseGraph(GraphConfig(prior_kernel=kernel))
    g.add_first()
    for i in range(1, n):
        g.add_keyframe([0.3, 0.0, drift], ODO_COV)
        if prior_every and i % prior_every == 0:
            g.add_prior(i, [0.3 * i, 0.0, 0.0], PRIOR_COV, source="plan")
    return g


def add_good_priors(g, n=300, every=30):
    return [g.add_prior(i, [0.3 * i, 0.0, 0.0], PRIOR_COV, source="plan") for i in range(every, n, every)]


@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure"])
def test_gross_outlier_prior_is_down_weighted(kernel):
    g = chain(kernel=kernel)
    add_good_priors(g)
    before = g.estimates()
    bad = g.add_prior(150, [45.0, 20.0, 1.0], PRIOR_COV, source="wrong room")
    after = g.estimates()
    assert np.abs(after - before)[:, :2].max() < 0.01
    res = g.prior_residual(bad)
    assert not res.consistent and res.weight < 0.01 and res.chi2 > 1e4


def test_huber_does_not_hold_against_the_same_outlier():
    g = chain(kernel="huber")
    add_good_priors(g)
    before = g.estimates()
    g.add_prior(150, [45.0, 20.0, 1.0], PRIOR_COV, source="wrong room")
    assert np.abs(g.estimates() - before)[:, :2].max() > 0.05


def test_priors_correct_drift_and_are_consistent():
    free = chain(drift=np.deg2rad(0.05)).estimates()  # odometry curves away (1.5 deg per 9 m)
    g = chain(drift=np.deg2rad(0.05), prior_every=30)
    est = g.estimates()
    assert np.abs(free[:, 1]).max() > 5.0
    assert np.abs(est[:270, 1]).max() < 0.15
    handles = g.priors()
    assert len(handles) == 9
    assert all(g.prior_residual(h).consistent for h in handles)
    assert all(g.prior_residual(h).weight > 0.5 for h in handles)


@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure", "none"])
def test_prior_residuals_batch_equals_one_by_one(kernel):
    g = chain(n=120, kernel=kernel, drift=np.deg2rad(0.05))
    handles = [
        g.add_prior(30, [9.0, 0.1, 0.02], PRIOR_COV),
        g.add_prior(60, [18.0, -0.4, 3.1], PRIOR_COV),  # near +pi: the logmap wraps
        g.add_prior(90, [27.2, 0.3, -0.5], PRIOR_COV, kind="translation"),
        g.add_prior(119, [35.0, 2.0, 0.0], PRIOR_COV, kind="rotation"),
        g.add_prior(100, [45.0, 20.0, 1.0], PRIOR_COV),  # gross outlier: tiny weight
    ]
    batch = g.prior_residuals(handles)
    est = g.estimates()
    for h, b in zip(handles, batch, strict=True):
        # the reference: gtsam's Pose2 logmap (prior_chi2) and robust noise model, one prior at a time
        cov3 = np.eye(3)
        sl = {"full": slice(0, 3), "translation": slice(0, 2), "rotation": slice(2, 3)}[h.kind]
        cov3[sl, sl] = h.covariance
        e, chi2 = prior_chi2(est[h.keyframe], h.pose, cov3, h.kind)
        noise = robust_noise(h.covariance, kernel, g.config.prior_kernel_param)
        weight = float(noise.robust().weight(np.sqrt(chi2))) if kernel != "none" else 1.0
        one = g.prior_residual(h)
        assert b.handle_id == one.handle_id == h.id and b.consistent == one.consistent
        np.testing.assert_allclose(b.error, e, atol=1e-9)
        np.testing.assert_allclose(one.error, e, atol=1e-9)
        assert b.chi2 == pytest.approx(chi2, rel=1e-9)
        assert b.weight == pytest.approx(weight, rel=1e-9, abs=1e-15)
    assert g.prior_residuals([]) == []


def test_remove_prior_restores_the_estimate():
    g = chain(kernel="none")  # plain Gaussian: an outlier really bends the graph
    add_good_priors(g)
    before = g.estimates()
    bad = g.add_prior(150, [45.0, 3.0, 0.0], PRIOR_COV)
    assert np.abs(g.estimates() - before)[:, 1].max() > 1.0
    n_factors = len(g._factors)
    g.remove_prior(bad)
    assert not bad.active and bad not in g.priors()
    assert g._factors[bad.factor_index] is None and len(g._factors) == n_factors
    assert np.abs(g.estimates() - before)[:, :2].max() < 0.02
    g.optimize_batch()
    assert np.abs(g.estimates() - before)[:, :2].max() < 1e-4
    g.remove_prior(bad)  # idempotent


def test_remove_priors_in_one_update_equals_one_by_one():
    g1, g2 = chain(kernel="none", drift=0.002), chain(kernel="none", drift=0.002)
    h1, h2 = add_good_priors(g1), add_good_priors(g2)
    removals = []
    real = g2._isam_update

    def counting(graph, values, remove, *args, **kw):
        if remove:
            removals.append(list(remove))
        return real(graph, values, remove, *args, **kw)

    g2._isam_update = counting
    for h in h1[::2]:
        g1.remove_prior(h)
    g2.remove_priors(h2[::2] + [h2[0]])  # a handle listed twice is removed once
    assert len(removals) == 1 and len(removals[0]) == len(h2[::2])  # one iSAM2 update for all
    assert all(not h.active for h in h2[::2]) and all(h.active for h in h2[1::2])
    assert {h.keyframe for h in g2.priors()} == {h.keyframe for h in g1.priors()}
    g1.optimize_batch()
    g2.optimize_batch()
    np.testing.assert_allclose(g2.estimates(), g1.estimates(), atol=1e-6)
    version = g2.version
    g2.remove_priors(h2[::2])  # all inactive now: nothing to do
    assert g2.version == version and len(removals) == 1


def test_remove_factors_in_one_update_and_bad_indices():
    """Two loop-closure factors removed in one iSAM2 update leave the chain as before them;
    a missing or repeated index is refused before anything is removed."""
    g = chain(40)
    before = g.estimates()
    bad = [between_factor(key(k), key(k + 20), [5.0, 0.0, 0.0], ODO_COV) for k in (5, 10)]
    idx = [g.add_factor(f) for f in bad]
    assert np.abs(g.estimates() - before).max() > 0.1
    with pytest.raises(FrslamError, match="repeat"):
        g.remove_factors([idx[0], idx[0]])
    with pytest.raises(FrslamError, match="no factor at index 9999"):
        g.remove_factors([idx[0], 9999])
    assert [g.factor_index(f) for f in bad] == idx  # nothing removed by the refused calls
    g.remove_factors(idx)
    assert [g.factor_index(f) for f in bad] == [-1, -1]
    np.testing.assert_allclose(g.estimates(), before, atol=1e-6)


def test_partial_priors():
    g = chain(n=60, drift=np.deg2rad(0.5), kernel="none")
    h_t = g.add_prior(59, [17.7, 0.0, 0.0], PRIOR_COV, kind="translation")
    est = g.estimates()[59]
    assert np.hypot(est[0] - 17.7, est[1]) < 0.1
    assert h_t.covariance.shape == (2, 2)
    g2 = chain(n=60, drift=np.deg2rad(0.5), kernel="none")
    g2.add_prior(59, [0.0, 0.0, 0.0], PRIOR_COV, kind="rotation")
    assert abs(g2.estimates()[59, 2]) < 0.05


def test_map_to_odom_follows_a_prior_shift():
    g = chain(n=50)
    odom = np.array([[0.3 * i, 0.0, 0.0] for i in range(50)])  # odometry poses of the keyframes
    np.testing.assert_allclose(g.map_to_odom(49, odom[49]), 0.0, atol=1e-6)
    # the floor plan says the robot is 1 m further in y and turned by 0.1 rad
    shift = np.array([0.5, 1.0, 0.1])
    for i in (10, 20, 30, 40):
        g.add_prior(i, compose(shift, odom[i]), np.diag([0.01**2, 0.01**2, 0.005**2]), kernel="none")
    g.optimize_batch()
    t = g.map_to_odom(49, odom[49])
    np.testing.assert_allclose(t, shift, atol=0.02)
    # REP-105: map->base == map->odom ⊕ odom->base for every keyframe
    for i in (0, 25, 49):
        np.testing.assert_allclose(compose(g.map_to_odom(i, odom[i]), odom[i]), g.estimate(i), atol=1e-9)
    np.testing.assert_allclose(compose(t, inverse(t)), 0.0, atol=1e-12)


def test_transform_map_reanchors_everything():
    g = chain(n=20)
    h = g.add_prior(10, [3.0, 0.0, 0.0], PRIOR_COV)
    T = np.array([5.0, -2.0, np.pi / 2])
    before = g.estimates()
    g.transform_map(T)
    after = g.estimates()
    for b, a in zip(before, after, strict=True):
        np.testing.assert_allclose(a[:2], compose(T, b)[:2], atol=0.01)  # the old prior pulls a little
    assert h.active and g._factors[h.factor_index] is not None
    g.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    assert len(g) == 21


def test_marginal_covariance_and_latency_shape():
    g = chain(n=100)
    c0, c1 = g.marginal_covariance(0), g.marginal_covariance()
    assert c0.shape == (3, 3) and c1[1, 1] > c0[1, 1]
    add_good_priors(g, 100, 20)
    assert g.marginal_covariance()[1, 1] < c1[1, 1]


def test_batch_matches_isam():
    g = chain(n=200, drift=np.deg2rad(0.05), prior_every=25)
    isam = g.estimates()
    batch = g.optimize_batch()
    assert np.abs(batch - isam)[:, :2].max() < 0.05
    assert np.isfinite(g.error())


def test_factor_helpers_and_bad_input():
    f = between_factor(key(0), key(1), [1.0, 0.0, 0.0], np.zeros((3, 3)), 0.01, 0.01)
    assert isinstance(f, gtsam.BetweenFactorPose2)
    c = regularise_covariance(np.zeros((3, 3)), 0.1, 0.2)
    np.testing.assert_allclose(np.diag(c), [0.01, 0.01, 0.04])
    with pytest.raises(FrslamError, match="covariance"):
        between_factor(key(0), key(1), [1.0, 0.0, 0.0], np.eye(2))
    with pytest.raises(FrslamError, match="relative"):
        between_factor(key(0), key(1), [1.0, np.nan, 0.0], np.eye(3))
    with pytest.raises(FrslamError, match="pose"):
        floorplan_prior(key(0), [1.0, 2.0], np.eye(3))
    with pytest.raises(ConfigError, match="kernel"):
        m_estimator("tukey-ish")
    with pytest.raises(ConfigError, match="graph.prior_kernel"):
        FRSlamConfig.from_dict({"graph": {"prior_kernel": "l1"}})
    g = PoseGraph()
    with pytest.raises(FrslamError):
        g.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    g.add_first()
    with pytest.raises(FrslamError, match="keyframe"):
        g.add_prior(5, [0.0, 0.0, 0.0], PRIOR_COV)
    with pytest.raises(FrslamError, match="keyframe"):
        g.estimate(3)
    with pytest.raises(FrslamError, match="keyframe"):
        g.marginal_covariance(3)


def test_estimates_refresh_incrementally_and_bit_identical():
    """Streaming keyframes refresh only the poses iSAM2 changed; every refresh equals the full
    calculateEstimate exactly, also across priors, loop closures, removals and a batch."""
    g = PoseGraph(GraphConfig())
    g.add_first()
    full_calls = []
    real_full = g.full_estimates

    def counting_full():
        full_calls.append(len(g))
        return real_full()

    g.full_estimates = counting_full
    rng = np.random.default_rng(5)
    for i in range(1, 200):
        g.add_keyframe([0.3, 0.0, 0.02 + 0.01 * rng.standard_normal()], ODO_COV)
        if i == 120:
            lc = between_factor(key(10), key(i), [0.0, 0.5, 0.1], ODO_COV, 0.002, np.deg2rad(0.05))
            g.add_factor(lc)
        if i == 150:
            h = g.add_prior(i, [10.0, 12.0, 1.0], PRIOR_COV, source="plan")
        if i == 170:
            g.remove_prior(h)
        assert np.array_equal(g.estimates(), real_full())
    # plain streaming keyframes (before the closure) never recompute every pose
    assert full_calls and not [n for n in full_calls if 20 <= n <= 120]
    g.optimize_batch()
    g.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    assert np.array_equal(g.estimates(), real_full())
    assert [g.estimate(i).tolist() for i in (0, 57, -1)] == [real_full()[i].tolist() for i in (0, 57, -1)]


def test_prior_that_agrees_with_the_estimate_gets_a_short_settle():
    """A prior within PRIOR_SETTLE_NEAR_XY / _THETA_DEG of the estimate is followed by only
    prior_settle_near_iterations forced relinearisations (the streaming updates converge the rest,
    and each forced step costs milliseconds on a large graph); one that moves the trajectory gets
    the full settle; an explicit extra_iterations wins."""
    g = chain(n=60, drift=0.002)
    calls = []
    settle = g.settle
    g.settle = lambda n=10, tol=1e-4: calls.append(n) or settle(n, tol)
    est = g.estimate(40)
    g.add_prior(40, est + [0.01, -0.01, 0.005], PRIOR_COV, source="plan")  # 1.4 cm, 0.3 deg
    g.add_prior(50, g.estimate(50) + [0.4, 0.0, 0.0], PRIOR_COV, source="plan")  # 40 cm off
    g.add_prior(30, g.estimate(30) + [0.0, 0.0, np.deg2rad(3.0)], PRIOR_COV, source="plan")
    g.add_prior(20, g.estimate(20), PRIOR_COV, source="plan", extra_iterations=4)
    assert calls == [GraphConfig().prior_settle_near_iterations, 10, 10, 4]
    assert GraphConfig().prior_settle_near_iterations < 10
    assert abs(g.estimate(50)[0] - (g.estimate(49)[0] + 0.3)) < 0.1  # the far prior still converged


def test_settle_steps_are_settle_one_iteration_at_a_time():
    """settle_steps yields before each relinearising iteration (nothing happens until the caller
    asks for the step) and, run to the end, gives exactly settle()'s estimates; keyframes added
    between steps are fine."""
    a, b = chain(n=60, drift=0.002), chain(n=60, drift=0.002)
    for g in (a, b):
        g.add_prior(50, g.estimate(50) + [0.4, 0.0, 0.0], PRIOR_COV, source="plan", extra_iterations=0)
    assert a.prior_settle_iterations(50, a.estimate(50) + [0.4, 0.0, 0.0]) == 10
    assert a.prior_settle_iterations(50, a.estimate(50)) == GraphConfig().prior_settle_near_iterations
    n = a.settle(10)
    steps = b.settle_steps(10)
    before, version = b.estimates(), b.version
    next(steps)  # up to the first yield: no iteration yet
    assert b.version == version
    np.testing.assert_array_equal(b.estimates(), before)
    done = 1 + sum(1 for _ in steps)
    assert done == n and b.version == version + n
    np.testing.assert_array_equal(b.estimates(), a.estimates())
    # a keyframe added between two steps: the iterations go on over the longer graph
    c = chain(n=60, drift=0.002)
    c.add_prior(50, c.estimate(50) + [0.4, 0.0, 0.0], PRIOR_COV, source="plan", extra_iterations=0)
    steps = c.settle_steps(10)
    next(steps)
    next(steps)
    c.add_keyframe(np.array([0.3, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-5]))
    for _ in steps:
        pass
    assert len(c) == 61
    assert abs(c.estimate(50)[0] - (c.estimate(49)[0] + 0.3)) < 0.1


def test_batch_without_incremental_frees_isam_and_streaming_rebuilds_it():
    """optimize_batch(incremental=False) (the end of a run) holds no iSAM2: the estimates are the
    batch's values; factor changes only change the graph until the next batch; a new keyframe,
    settle or a marginal rebuilds iSAM2 from those values."""
    kept = chain(n=120, drift=np.deg2rad(0.05), prior_every=25)
    freed = chain(n=120, drift=np.deg2rad(0.05), prior_every=25)
    want = kept.optimize_batch()
    got = freed.optimize_batch(incremental=False)
    assert kept.incremental and not freed.incremental
    # the rebuilt iSAM2 took one more Gauss-Newton step from the same LM values
    assert np.abs(got - want).max() < 1e-6
    np.testing.assert_array_equal(freed.estimates(), got)
    np.testing.assert_array_equal(freed.estimate(), got[-1])
    assert freed.error() == pytest.approx(kept.error(), rel=1e-6)
    # factors replaced while freed: new slots after the last, found again by identity
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    loop = [gtsam.BetweenFactorPose2(key(10), key(100), gtsam.Pose2(27.0, 0.0, 0.0), noise)]
    for g in (kept, freed):
        (idx,) = g.replace_factors([], loop)
        assert g.factor_indices(loop) == [idx]
    assert not freed.incremental
    np.testing.assert_array_equal(freed.estimates(), got)  # no step taken: the next batch takes it
    np.testing.assert_allclose(freed.optimize_batch(incremental=False), kept.optimize_batch(), atol=1e-6)
    g2 = freed.replace_factors(freed.factor_indices(loop), [])
    assert g2 == [] and freed.factor_indices(loop) == [-1]
    # streaming on: iSAM2 comes back
    freed.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    assert freed.incremental and len(freed) == 121
    assert freed.marginal_covariance().shape == (3, 3)


def test_batch_runs_after_isam_is_freed(monkeypatch):
    """A batch during streaming frees iSAM2 before LM (not after: both factorisations at once) and
    rebuilds it on the result, with the same estimates as LM's."""
    g = chain(n=80, drift=np.deg2rad(0.05), prior_every=20)
    held = []
    lm = gtsam.LevenbergMarquardtOptimizer

    def spy(graph, values, params):
        held.append(g.incremental)
        return lm(graph, values, params)

    monkeypatch.setattr(gtsam, "LevenbergMarquardtOptimizer", spy)
    out = g.optimize_batch()
    assert held == [False] and g.incremental
    np.testing.assert_array_equal(out, g.estimates())
    g.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    assert len(g.estimates()) == 81


def _looped(n=200):
    """A drifting chain closed by a loop factor far from the estimate: LM needs several iterations."""
    g = chain(n=n, drift=np.deg2rad(0.2))
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    g.add_factor(gtsam.BetweenFactorPose2(key(0), key(n - 1), gtsam.Pose2(0.3 * (n - 1), 0.0, 0.0), noise), 0)
    return g


def test_batch_in_steps_gives_lm_values_one_iteration_per_step():
    """optimize_batch_steps: one LM iteration per step (then the rebuild), each step costed, the
    result that of GTSAM's own LM run to convergence on the same graph."""
    g = _looped()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(g.config.batch_relative_tolerance)
    lm = gtsam.LevenbergMarquardtOptimizer(g._graph(), g._current_values(), params)
    want = np.asarray(gtsam.utilities.extractPose2(lm.optimize()))
    steps = g.optimize_batch_steps()
    costs = []
    with pytest.raises(StopIteration) as stop:
        while True:
            costs.append(next(steps))
    assert len(costs) == lm.iterations() + 1 >= 3  # the iterations and the rebuild
    assert all(c > 0 for c in costs)
    assert g.incremental
    # the rebuilt iSAM2 took one more Gauss-Newton step from LM's values
    np.testing.assert_allclose(stop.value.value, want, atol=1e-6)


def test_keyframes_added_during_a_batch_in_steps_follow_it():
    """Streaming goes on between the batch's steps: a keyframe added meanwhile waits outside iSAM2
    and keeps its odometry relative to the batch's last keyframe when the batch ends; something
    that needs iSAM2 mid-way (a factor with relinearising steps) finishes the batch first."""
    g = _looped()
    n0 = len(g)
    steps = g.optimize_batch_steps()
    next(steps)
    next(steps)  # one iteration run
    before = g.estimates()
    g.add_keyframe([0.3, 0.0, 0.0], ODO_COV)
    g.add_keyframe([0.3, 0.0, 0.1], ODO_COV)
    assert not g.incremental and len(g.estimates()) == n0 + 2
    np.testing.assert_array_equal(g.estimates()[:n0], before)  # the pre-batch estimates meanwhile
    rel = [inverse(g.estimates()[n0 - 1]), g.estimates()[n0:]]
    rel = np.array([compose(rel[0], p) for p in rel[1]])
    out = None
    with pytest.raises(StopIteration) as stop:
        while True:
            next(steps)
    out = stop.value.value
    assert g.incremental and len(out) == n0 + 2
    kept = np.array([compose(inverse(out[n0 - 1]), p) for p in out[n0:]])
    np.testing.assert_allclose(kept, rel, atol=1e-3)  # one iSAM2 step after the rebuild
    # the batch moved the chain: the new keyframes moved with it
    assert np.abs(out[n0 - 1] - before[n0 - 1]).max() > 0.02

    # something needing iSAM2 mid-batch finishes it: same as the batch, then the factor
    a, b = _looped(), _looped()
    steps = a.optimize_batch_steps()
    next(steps)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.05)
    extra = [gtsam.BetweenFactorPose2(key(10), key(100), gtsam.Pose2(27.0, 0.0, 0.0), noise) for _ in "ab"]
    a.add_factor(extra[0], 2)
    b.optimize_batch()
    b.add_factor(extra[1], 2)
    np.testing.assert_allclose(a.estimates(), b.estimates(), atol=1e-9)
    assert next(steps, None) is None  # the generator sees its batch finished and ends


def test_priors_removed_during_a_batch_in_steps():
    """Removing priors while an LM batch runs in steps: the removal's settle finishes the batch,
    whose rebuild re-maps the factor indices of the active priors. The removed ones were still
    active then (marked inactive after the update): KeyError on their index (intel.bag with its
    plan, a prior removed as wrong mid-batch). Now the others stay in the graph, re-mapped."""
    g = _looped()
    handles = [g.add_prior(k, [0.3 * k, 0.0, 0.0], np.diag([0.01, 0.01, 0.001])) for k in (20, 60, 120)]
    steps = g.optimize_batch_steps()
    next(steps)
    next(steps)
    assert g.remove_priors(handles[:2]) == handles[:2]
    assert not handles[0].active and not handles[1].active and handles[2].active
    assert g._factors[handles[2].factor_index] is not None
    g.remove_prior(handles[2])
    assert g.priors() == []
