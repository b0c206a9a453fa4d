"""tools/bench_aces.py's reference check: quantised reference relations are told from continuous ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import load_tool
from frslam_graph.datasets.scan import Scan


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_aces")


def straight_run(n: int = 200):
    """Scans 0.1 s apart driving along a turning path; wheel odometry = truth."""
    rng = np.random.default_rng(3)
    th = np.cumsum(rng.normal(0.0, 0.05, n))
    x = np.cumsum(0.05 * np.cos(th))
    y = np.cumsum(0.05 * np.sin(th))
    stamps = 100.0 + 0.1 * np.arange(n)
    empty = np.zeros(0)
    scans = [
        Scan(float(t), empty, empty, odom=(float(a), float(b), float(c)))
        for t, a, b, c in zip(stamps, x, y, th, strict=True)
    ]
    return scans, np.column_stack((stamps, x, y, th))


def write_relations(path: Path, traj: np.ndarray, forward_offsets: np.ndarray) -> Path:
    lines = []
    for k, off in enumerate(forward_offsets):
        i, j = 2 * k, 2 * k + 3
        a, b = traj[i], traj[j]
        c, s = np.cos(a[3]), np.sin(a[3])
        dx, dy = b[1] - a[1], b[2] - a[2]
        rx, ry = c * dx + s * dy + off, -s * dx + c * dy
        lines.append(f"{a[0]:.6f} {b[0]:.6f} {rx:.6f} {ry:.6f} 0 0 0 {b[3] - a[3]:.6f}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_quantised_reference_is_reported(bench, tmp_path):
    scans, traj = straight_run()
    offsets = np.where(np.arange(90) % 2 == 0, 0.0, 0.05 * np.where(np.arange(90) % 4 == 1, 1, -2))
    rel = write_relations(tmp_path / "q.relations", traj, offsets)
    estimate = traj.copy()
    estimate[:, 1] += np.linspace(0.0, 0.3, len(traj))  # continuous drift: off the grid
    line = bench.reference_check(scans, rel, estimate)
    assert "50 % of the reference relations equal the logged wheel odometry" in line
    assert "and 50 % differ from it by a non-zero multiple of 5 cm" in line


def test_continuous_reference_is_not_on_the_grid(bench, tmp_path):
    scans, traj = straight_run()
    offsets = np.random.default_rng(0).uniform(0.011, 0.039, 90)  # never within 5 mm of the grid
    rel = write_relations(tmp_path / "c.relations", traj, offsets)
    line = bench.reference_check(scans, rel, traj)
    assert "0 % of the reference relations equal" in line and "and 0 % differ" in line


def test_wheel_trajectory_is_the_logged_odometry(bench):
    scans, traj = straight_run(10)
    np.testing.assert_allclose(bench.wheel_trajectory(scans), traj)
