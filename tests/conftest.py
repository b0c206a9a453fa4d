"""Shared pytest fixtures.

``shared_data``: the project's shared real data (``../shared/data`` next to the repository, as in
CI). Tests that need it skip with a clear reason when it is absent; small excerpts live in
``tests/data`` and are always available (``test_data``).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FRSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
TEST_DATA = REPO / "tests" / "data"


def load_tool(name: str) -> ModuleType:
    """Import ``tools/<name>.py`` (the tools are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(
            f"shared data not found at {SHARED_DATA} (set FRSLAM_SHARED_DATA or clone next to ../shared)"
        )
    return SHARED_DATA


@pytest.fixture(scope="session")
def test_data() -> Path:
    return TEST_DATA


@pytest.fixture(scope="session")
def five_room_sim():
    """(plan, run, true plan -> map matrix): the five-room plan and a short simulated run in it
    (12 m, 360 beams, 4 Hz). The SLAM map is the odom frame of the first pose; the simulator's
    odom frame starts at the true pose."""
    import numpy as np
    from frslam_graph.datasets.simulator import SimulationOptions, five_room_plan, simulate_run

    from frslam_graph.odometry.motion_model import to_matrix

    plan = five_room_plan()
    opts = SimulationOptions(length=12.0, beams=360, fov_deg=360.0, max_range=12.0, scan_rate=4.0)
    run = simulate_run(plan, seed=3, options=opts)
    true_matrix = (
        to_matrix(run.odom_poses[0])
        @ np.linalg.inv(to_matrix(run.true_poses[0]))
        @ run.house.distortion.matrix
    )
    return plan, run, true_matrix


@pytest.fixture(scope="session")
def accepted_run(five_room_sim):
    """A run of the five-room simulation with its plan (the plan is accepted within seconds)."""
    from frslam_graph.offline import run_recording

    plan, sim, _ = five_room_sim
    return run_recording(sim.scans, floor_plan=plan, parallel=False)


@pytest.fixture
def replayed(accepted_run, monkeypatch):
    """``run`` / ``compare`` return ``accepted_run`` instead of processing the recording given."""
    import frslam_graph.offline as offline

    monkeypatch.setattr(offline, "run_recording", lambda recording, floor_plan=None, **kw: accepted_run)
    return accepted_run


def _write_carmen(path: Path, truth, odom, ranges) -> None:
    """A CARMEN log of FLASER lines (180 beams of the 360 given, odometry = the pose fields)."""
    import numpy as np

    lines = []
    for row, o, r in zip(truth, odom, ranges, strict=True):
        beams = np.nan_to_num(r[90:270], nan=81.9)  # CARMEN: 180 beams, -90..+89 deg; 81.9 = no return
        vals = " ".join(f"{v:.3f}" for v in beams)
        lines.append(
            f"FLASER 180 {vals} {o[0]:.4f} {o[1]:.4f} {o[2]:.5f} {o[0]:.4f} {o[1]:.4f} {o[2]:.5f} "
            f"{row[0] + 1000:.6f} host {row[0] + 1000:.6f}"
        )
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="session")
def small_log(tmp_path_factory):
    """(CARMEN log, TUM ground truth): a drifting robot looping a synthetic room (5 Hz, 360 beams)."""
    from tests import synthetic_world as sw

    d = tmp_path_factory.mktemp("log")
    world = sw.room_world()
    truth = sw.route(sw.ROOM_LOOP, speed=0.6, rate=5.0)
    odom = sw.drifting_odometry(truth, scale=0.02)
    ranges, _, _ = zip(*(sw.cast(world, p[1:], n_beams=360, max_range=20.0) for p in truth), strict=True)
    log = d / "room.clf"
    _write_carmen(log, truth, odom, ranges)
    gt = truth.copy()
    gt[:, 0] += 1000
    from frslam_graph.evaluation.trajectory_io import save_tum

    save_tum(d / "gt.tum", gt)
    return log, d / "gt.tum"
