"""Relation metric (Kümmerle et al. 2009) on cases with known answers; ATE / RPE; TUM and relations files."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from frslam_graph.errors import TrajectoryError
from frslam_graph.evaluation.metrics import ate, rpe
from frslam_graph.evaluation.relations import relation_error, relative_poses
from frslam_graph.evaluation.trajectory_io import load_relations, load_tum, save_tum


def compose(a, b):
    """a ⊕ b for (..., 3) arrays x, y, theta."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = np.arctan2(np.sin(a[..., 2] + b[..., 2]), np.cos(a[..., 2] + b[..., 2]))
    return np.stack([x, y, th], axis=-1)


def between(a, b):
    """a⁻¹ ⊕ b."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    th = np.arctan2(np.sin(b[..., 2] - a[..., 2]), np.cos(b[..., 2] - a[..., 2]))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, th], axis=-1)


def ground_truth(n=200):
    t = np.arange(n) * 0.1
    th = 0.8 * np.sin(t / 3.0) + 0.2 * t  # winding, wrapping past pi
    steps = np.column_stack([np.full(n, 0.1), np.zeros(n), np.r_[0.0, np.diff(th)]])
    poses = np.zeros((n, 3))
    for k in range(1, n):
        poses[k] = compose(poses[k - 1], steps[k])
    return np.column_stack([1000.0 + t, poses])


def relations_for(gt, pairs, errors):
    """Relations between gt poses ``pairs`` whose reference is the true relative pose ⊕ ``errors``."""
    i, j = pairs[:, 0], pairs[:, 1]
    rel = compose(between(gt[i, 1:], gt[j, 1:]), errors)
    return np.column_stack([gt[i, 0], gt[j, 0], rel])


def pairs(n, rng):
    i = rng.integers(0, n - 30, 100)
    return np.column_stack([i, i + rng.integers(1, 30, 100)])


def se2_transform(traj, yaw, tx, ty, scale=1.0):
    out = traj.copy()
    c, s = math.cos(yaw), math.sin(yaw)
    out[:, 1] = scale * (c * traj[:, 1] - s * traj[:, 2]) + tx
    out[:, 2] = scale * (s * traj[:, 1] + c * traj[:, 2]) + ty
    out[:, 3] = np.arctan2(np.sin(traj[:, 3] + yaw), np.cos(traj[:, 3] + yaw))
    return out


def test_relation_error_known_answer():
    gt = ground_truth()
    rng = np.random.default_rng(1)
    pr = pairs(len(gt), rng)
    # errors alternate between |t| = 0.05 m, 2 deg and |t| = 0.1 m, -4 deg (in any direction)
    a = rng.uniform(-np.pi, np.pi, len(pr))
    mag = np.where(np.arange(len(pr)) % 2 == 0, 0.05, 0.10)
    rot = np.where(np.arange(len(pr)) % 2 == 0, math.radians(2.0), math.radians(-4.0))
    rel = relations_for(gt, pr, np.column_stack([mag * np.cos(a), mag * np.sin(a), rot]))
    res = relation_error(gt, rel)
    assert (res.matched, res.unmatched) == (100, 0)
    assert res.trans_mean == pytest.approx(0.075, abs=1e-9)
    assert res.trans_std == pytest.approx(0.025, abs=1e-9)
    assert res.rot_mean == pytest.approx(3.0, abs=1e-9)
    assert res.rot_std == pytest.approx(1.0, abs=1e-9)
    assert res.trans_sq_mean == pytest.approx((0.05**2 + 0.1**2) / 2, abs=1e-12)
    assert res.rot_sq_mean == pytest.approx((4.0 + 16.0) / 2, abs=1e-9)
    # the metric is relative: a trajectory moved as a whole scores the same
    moved = se2_transform(gt, 2.5, -40.0, 7.0)
    res2 = relation_error(moved, rel)
    assert res2.trans_mean == pytest.approx(0.075, abs=1e-9) and res2.rot_mean == pytest.approx(3.0, abs=1e-9)
    # shuffled poses are sorted by stamp first
    res3 = relation_error(gt[rng.permutation(len(gt))], rel)
    assert res3.trans_mean == pytest.approx(0.075, abs=1e-9)


def test_relation_error_of_a_scaled_trajectory():
    gt = ground_truth()
    pr = pairs(len(gt), np.random.default_rng(2))
    rel = relations_for(gt, pr, np.zeros((len(pr), 3)))
    assert relation_error(gt, rel).trans_mean == pytest.approx(0.0, abs=1e-12)
    est = se2_transform(gt, 0.0, 0.0, 0.0, scale=1.1)  # 10 % too long everywhere
    res = relation_error(est, rel)
    expected = 0.1 * np.hypot(rel[:, 2], rel[:, 3])
    np.testing.assert_allclose(res.trans_errors, expected, atol=1e-9)
    assert res.trans_mean == pytest.approx(expected.mean()) and res.rot_mean == pytest.approx(0.0, abs=1e-9)


def test_unmatched_relations_and_tolerance():
    gt = ground_truth(50)
    pr = np.array([[0, 5], [10, 20], [30, 40]])
    rel = relations_for(gt, pr, np.zeros((3, 3)))
    rel[1, 1] += 0.004  # 4 ms off: matches at 5 ms tolerance, not at 1 ms
    rel[2, 0] = 5000.0  # no pose anywhere near
    loose = relation_error(gt, rel, tolerance=0.005)
    tight = relation_error(gt, rel, tolerance=0.001)
    assert (loose.matched, loose.unmatched) == (2, 1)
    assert (tight.matched, tight.unmatched) == (1, 2)
    none = relation_error(gt, rel[2:], tolerance=0.001)
    assert none.matched == 0 and math.isnan(none.trans_mean)


def test_keyframe_trajectory_interpolated_at_relation_stamps():
    # moving straight along x at 1 m/s while turning at 0.5 rad/s: linear in x, y and heading
    t = np.arange(101) * 0.1
    gt = np.column_stack([t, t, np.zeros_like(t), np.arctan2(np.sin(0.5 * t), np.cos(0.5 * t))])
    rel = relations_for(gt, np.array([[1, 7], [13, 55], [3, 99], [60, 61]]), np.zeros((4, 3)))
    keyframes = gt[::4]  # poses only at every 4th scan
    assert relation_error(keyframes, rel).matched == 0  # no pose within 10 ms of the odd stamps
    res = relation_error(keyframes, rel, interpolate=0.5)
    assert (res.matched, res.unmatched) == (4, 0)
    assert res.trans_mean == pytest.approx(0.0, abs=1e-9) and res.rot_mean == pytest.approx(0.0, abs=1e-6)
    sparse = np.delete(keyframes, [15], axis=0)  # a 0.8 s gap around t = 6.0 s
    res = relation_error(sparse, rel, interpolate=0.5)
    assert (res.matched, res.unmatched) == (3, 1)


def test_relations_file_and_aces_format(tmp_path):
    gt = ground_truth(60)
    pr = np.array([[0, 10], [5, 50]])
    rel = relations_for(gt, pr, np.array([[0.0, 0.03, 0.0], [0.04, 0.0, 0.0]]))
    p = tmp_path / "x.relations"
    lines = [
        f"{r[0]:.6f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} 0.000000 0.000000 0.000000 {r[4]:.6f}" for r in rel
    ]
    p.write_text("\n".join(lines) + "\n")
    loaded = load_relations(p)
    np.testing.assert_allclose(loaded, rel, atol=1e-6)
    res = relation_error(gt, loaded)
    assert res.trans_mean == pytest.approx(0.035, abs=1e-5) and res.trans_std == pytest.approx(
        0.005, abs=1e-5
    )
    bad = tmp_path / "bad.relations"
    bad.write_text(lines[0] + "\n1.0 2.0 0.1 0.2 0 0 0\n")
    with pytest.raises(
        TrajectoryError, match=r"bad.relations: line 2: expected 8 numbers 't1 t2 x y z roll pitch yaw'"
    ):
        load_relations(bad)
    # the metric takes arrays; a path is named as one, with the reader to use
    with pytest.raises(TrajectoryError, match="not a path .*load_relations"):
        relation_error(gt, p)


def test_tum_round_trip_and_errors(tmp_path):
    gt = ground_truth(30)
    p = tmp_path / "t.tum"
    save_tum(p, gt)
    back = load_tum(p)
    np.testing.assert_allclose(back[:, :3], gt[:, :3], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (back[:, 3] - gt[:, 3]))), 0.0, atol=1e-6)
    cases = {
        "1.0 0 0 0 0 0 0\n": r"line 1: expected 8 numbers 'stamp x y z qx qy qz qw', found 7",
        "# header\n1.0 0 0 0 0 0 0 1\n2.0 a 0 0 0 0 0 1\n": r"line 3: non-numeric field",
        "1.0 0 0 0 0 0 0 2\n": r"line 1: quaternion norm 2.000000",
        "1.0 nan 0 0 0 0 0 1\n": r"line 1: non-finite value",
        "# only a comment\n": r"no data lines",
    }
    for text, msg in cases.items():
        bad = tmp_path / "bad.tum"
        bad.write_text(text)
        with pytest.raises(TrajectoryError, match=f"bad.tum: {msg}"):
            load_tum(bad)
    with pytest.raises(TrajectoryError, match="missing.tum: no such file"):
        load_tum(tmp_path / "missing.tum")
    with pytest.raises(TrajectoryError, match=r"shape \(3, 3\)"):
        save_tum(p, np.zeros((3, 3)))


def test_ate_aligns_in_se2_even_on_a_straight_path():
    n = 50
    straight = np.column_stack([np.arange(n) * 0.1, np.arange(n) * 0.5, np.zeros(n), np.zeros(n)])
    est = se2_transform(straight, 0.7, 3.0, -2.0)
    stats, al = ate(est, straight)
    assert stats.rmse == pytest.approx(0.0, abs=1e-9) and stats.n == n
    assert al.yaw == pytest.approx(-0.7) and al.scale == pytest.approx(1.0)
    off = straight.copy()
    off[:, 2] += 0.3  # 0.3 m to the side, no alignment: ATE is exactly 0.3
    stats, al = ate(off, straight, align=False)
    assert al is None and stats.rmse == pytest.approx(0.3) and stats.max == pytest.approx(0.3)
    gt = ground_truth(100)
    scaled = se2_transform(gt, -1.0, 5.0, 5.0, scale=0.8)
    assert ate(scaled, gt)[0].rmse > 0.1
    stats, al = ate(scaled, gt, scale=True)
    assert stats.rmse == pytest.approx(0.0, abs=1e-9) and al.scale == pytest.approx(1.25)
    with pytest.raises(TrajectoryError, match="no poses match in time"):
        ate(est + [100.0, 0, 0, 0], straight)


def test_rpe_known_answer():
    n = 40
    gt = np.column_stack([np.arange(n) * 0.1, np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    est = gt.copy()
    est[:, 1] *= 1.1  # 1.1 m per frame instead of 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trans, rot = rpe(est, gt)
    assert (
        trans.mean == pytest.approx(0.1) and trans.std == pytest.approx(0.0, abs=1e-12) and trans.n == n - 1
    )
    assert rot.max == pytest.approx(0.0, abs=1e-9)
    trans, _ = rpe(est, gt, delta=5)
    assert trans.mean == pytest.approx(0.5)
    turn = gt.copy()
    turn[:, 3] = np.radians(np.arange(n) * 2.0)  # 2 deg per frame more than the reference
    _, rot = rpe(turn, gt)
    assert rot.mean == pytest.approx(2.0)
    with pytest.raises(TrajectoryError, match="RPE failed"):
        rpe(gt, gt, delta=100.0, unit="meters")  # the path is only 39 m long


def test_relations_command(tmp_path, capsys):
    from frslam_graph.cli import main

    gt = ground_truth(60)
    rel = relations_for(gt, np.array([[0, 10], [5, 50]]), np.array([[0.0, 0.03, 0.0], [0.04, 0.0, 0.0]]))
    p = tmp_path / "x.relations"
    p.write_text("".join(f"{r[0]:.6f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} 0 0 0 {r[4]:.6f}\n" for r in rel))
    save_tum(tmp_path / "t.tum", gt)
    assert main(["relations", str(tmp_path / "t.tum"), str(p)]) == 0
    out = capsys.readouterr().out
    assert "0.0350 ± 0.0050 m" in out and "2 matched, 0 unmatched" in out
    (tmp_path / "bad.tum").write_text("1 2 3\n")
    assert main(["relations", str(tmp_path / "bad.tum"), str(p)]) == 2


def test_aces_odometry_against_its_relations(shared_data):
    """Smoke test: CARMEN's own odometry of ACES, all 1,279 relations matched at the FLASER stamps."""
    from frslam_graph.datasets import open_recording

    carmen = shared_data / "carmen"
    traj = np.array([(s.stamp, *s.odom) for s in open_recording(carmen / "aces.clf.bz2")])
    res = relation_error(traj, load_relations(carmen / "aces.relations"), tolerance=1e-3)
    assert (res.matched, res.unmatched) == (1279, 0)
    assert 0.0 < res.trans_mean < 5.0 and 0.0 < res.rot_mean < 20.0
    # odometry drifts: long relations are worse than short ones
    span = np.abs(
        load_relations(carmen / "aces.relations")[:, 1] - load_relations(carmen / "aces.relations")[:, 0]
    )
    assert res.trans_errors[span > 60].mean() > res.trans_errors[span < 2].mean()


def test_relative_poses_in_the_first_pose_frame_and_nan_without_poses():
    traj = np.array([[0.0, 1.0, 2.0, np.pi / 2], [1.0, 1.0, 3.0, np.pi]])  # 1 m ahead, turned 90°
    rel, ok = relative_poses(traj, np.array([0.0, 0.0]), np.array([1.0, 5.0]))
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(rel[0], [1.0, 0.0, np.pi / 2], atol=1e-12)
    assert np.all(np.isnan(rel[1]))


def test_a_tum_file_out_of_time_order_is_refused(tmp_path):
    """Rows out of order were matched to the wrong poses without a word; the stamps in the message
    are given to the nanosecond (a log's epoch stamps differ in their decimals)."""
    p = tmp_path / "gt.tum"
    p.write_text("1.0 0 0 0 0 0 0 1\n976052862.228 0 0 0 0 0 0 1\n976052862.222 0 0 0 0 0 0 1\n")
    with pytest.raises(
        TrajectoryError,
        match=r"gt\.tum: line 3: stamp 976052862\.222 is before the previous row's 976052862\.228 ",
    ):
        load_tum(p)


def test_a_trajectory_whose_stamps_go_backwards_is_written_in_time_order(tmp_path, capsys):
    """A run keeps every scan of a log whose stamps go backwards (Intel: 631 rows of its
    trajectory), in the log's order; its TUM file lists the same poses in time order, which evo
    requires and which `frslam relations` reads back (it refused frslam's own Intel trajectory)."""
    from frslam_graph.cli import main

    gt = ground_truth(60)
    order = np.arange(60)
    order[[20, 21]] = order[[21, 20]]  # scan 21 stamped before scan 20, kept in file order
    run = gt[order]
    save_tum(tmp_path / "t.tum", run)
    back = load_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back, gt, atol=1e-9)  # every row, sorted by stamp
    rel = relations_for(gt, np.array([[0, 21], [20, 50]]), np.array([[0.0, 0.03, 0.0], [0.04, 0.0, 0.0]]))
    p = tmp_path / "x.relations"
    p.write_text("".join(f"{r[0]:.6f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} 0 0 0 {r[4]:.6f}\n" for r in rel))
    assert main(["relations", str(tmp_path / "t.tum"), str(p)]) == 0
    assert "0.0350 ± 0.0050 m" in capsys.readouterr().out
    assert relation_error(run, load_relations(p)).trans_mean == pytest.approx(0.035, abs=1e-6)
