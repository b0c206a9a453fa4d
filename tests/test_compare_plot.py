"""compare.png, evo-style: each run's trajectory coloured by its error (one colour scale) and the
errors over the distance travelled, beside the overview over the map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from matplotlib.collections import LineCollection

from frslam_graph.cli import main
from frslam_graph.evaluation.metrics import translation_errors
from frslam_graph.evaluation.trajectory_io import save_tum
from frslam_graph.viz import compare_figure


def square(n: int = 41) -> np.ndarray:
    """(n, 4) a 4 m square walked at 1 m per 10 poses, 10 Hz."""
    s = np.linspace(0.0, 16.0, n)
    x = np.clip(s, 0, 4) - np.clip(s - 8, 0, 4)
    y = np.clip(s - 4, 0, 4) - np.clip(s - 12, 0, 4)
    return np.column_stack([100.0 + 0.1 * np.arange(n), x, y, np.zeros(n)])


def moved(traj: np.ndarray, yaw: float, tx: float, ty: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    out = traj.copy()
    out[:, 1] = c * traj[:, 1] - s * traj[:, 2] + tx
    out[:, 2] = s * traj[:, 1] + c * traj[:, 2] + ty
    out[:, 3] = traj[:, 3] + yaw
    return out


def test_translation_errors_are_per_pose_along_the_distance_travelled():
    ref = square()
    dist, err, est, gt = translation_errors(moved(ref, 0.7, 3.0, -1.0), ref)
    assert err.max() < 1e-9  # a rigid motion: nothing left after the SE(2) alignment
    np.testing.assert_allclose(dist, np.linspace(0.0, 16.0, 41), atol=1e-9)
    np.testing.assert_allclose(gt, ref)
    _, err, _, _ = translation_errors(moved(ref, 0.0, 0.3, 0.4), ref, align=False)
    np.testing.assert_allclose(err, 0.5)


def test_compare_figure_colours_each_run_by_its_error_on_one_scale():
    ref = square()
    drifted = ref.copy()
    drifted[:, 1] += np.linspace(0.0, 0.8, len(ref))  # error growing along the way
    fig = compare_figure({"without priors": drifted, "with priors": ref}, ref)
    panels = [ax for ax in fig.axes if "ATE RMSE" in ax.get_title()]
    assert [ax.get_title().split(":")[0] for ax in panels] == ["without priors", "with priors"]
    collections = [c for ax in panels for c in ax.collections if isinstance(c, LineCollection)]
    assert len(collections) == 2
    assert (
        collections[0].norm.vmax
        == collections[1].norm.vmax
        == pytest.approx(translation_errors(drifted, ref)[1].max())
    )
    assert collections[1].get_array().max() < 1e-9
    labels = [ax.get_xlabel() for ax in fig.axes]
    assert "distance travelled [m]" in labels
    err_ax = fig.axes[labels.index("distance travelled [m]")]
    assert [line.get_label().split(" (")[0] for line in err_ax.get_lines()] == [
        "without priors",
        "with priors",
    ]
    assert any("translation error" in ax.get_ylabel() for ax in fig.axes if ax is not err_ax)  # colour bar


def test_compare_figure_without_ground_truth_is_the_overview_only():
    fig = compare_figure({"a": square(), "b": square()}, None)
    assert len(fig.axes) == 1 and fig.axes[0].get_title() == "trajectories (map frame)"


def test_compare_writes_the_error_panels_with_a_ground_truth(small_log, five_room_sim, replayed, tmp_path):
    _, sim, _ = five_room_sim
    gt = tmp_path / "gt.tum"
    save_tum(gt, sim.ground_truth)
    out = tmp_path / "cmp"
    argv = ["compare", str(small_log[0]), "--floor-plan", str(tmp_path / "plan.json"), "--out", str(out)]
    sim_plan = five_room_sim[0].save(tmp_path / "plan.json")
    assert sim_plan.exists()
    assert main([*argv, "--ground-truth", str(gt)]) == 0
    with_errors = cv2.imread(str(out / "compare.png")).shape
    assert main(argv) == 0
    overview = cv2.imread(str(out / "compare.png")).shape
    assert with_errors[1] == 3 * overview[1]  # the overview and one panel per run side by side
    assert with_errors[0] > overview[0]  # and the errors over distance below
