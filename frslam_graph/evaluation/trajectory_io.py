"""Trajectory files: TUM trajectories and relations files (text, one record per line).

A TUM file holds one pose per line, ``stamp x y z qx qy qz qw``, in time order (evo refuses
stamps that are not ascending); we write z = 0 and a yaw-only quaternion, rows sorted by stamp
(a log whose stamps go backwards, such as Intel's, keeps every pose: only the rows' order is
time's, not the log's), and read the yaw back (roll / pitch are ignored), as an (N, 4) ``stamp,
x, y, theta`` array (seconds, metres, radians). A relations file (Kümmerle et al. 2009) lists reference
relative poses ``t1 t2 x y z roll pitch yaw`` between scan stamps. '#' starts a comment; commas
count as spaces.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from frslam_graph.errors import TrajectoryError
from frslam_graph.evaluation.trajectory import as_trajectory


def _rows(path: Path, width: int, layout: str) -> tuple[np.ndarray, list[int]]:
    """Numeric rows of a whitespace-separated text file; '#' comments and blank lines skipped."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError("no such file", source=path)
    rows: list[list[float]] = []
    lines: list[int] = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            text = line.split("#", 1)[0].replace(",", " ").strip()
            if not text:
                continue
            tok = text.split()
            if len(tok) != width:
                raise TrajectoryError(
                    f"expected {width} numbers '{layout}', found {len(tok)} fields",
                    source=path,
                    where=f"line {lineno}",
                )
            try:
                values = [float(x) for x in tok]
            except ValueError:
                raise TrajectoryError(
                    f"non-numeric field in '{line.strip()[:60]}' (expected '{layout}')",
                    source=path,
                    where=f"line {lineno}",
                ) from None
            if not all(math.isfinite(v) for v in values):
                raise TrajectoryError(
                    f"non-finite value (expected '{layout}')", source=path, where=f"line {lineno}"
                )
            rows.append(values)
            lines.append(lineno)
    if not rows:
        raise TrajectoryError(f"no data lines (expected '{layout}')", source=path)
    return np.array(rows, dtype=np.float64), lines


def load_tum(path: str | Path) -> np.ndarray:
    """Read a TUM trajectory ``stamp x y z qx qy qz qw`` as (N, 4) ``stamp, x, y, yaw``."""
    path = Path(path)
    a, lines = _rows(path, 8, "stamp x y z qx qy qz qw")
    qx, qy, qz, qw = a[:, 4], a[:, 5], a[:, 6], a[:, 7]
    norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        raise TrajectoryError(
            f"quaternion norm {norm[bad[0]]:.6f} (expected 1)", source=path, where=f"line {lines[bad[0]]}"
        )
    back = np.flatnonzero(np.diff(a[:, 0]) < 0.0)
    if back.size:  # unsorted rows were matched to the wrong poses without a word
        k = back[0] + 1
        raise TrajectoryError(
            f"stamp {float(a[k, 0])!r} is before the previous row's {float(a[k - 1, 0])!r} (expected stamps in time order)",
            source=path,
            where=f"line {lines[k]}",
        )
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return np.column_stack((a[:, 0], a[:, 1], a[:, 2], yaw))


def save_tum(path: str | Path, trajectory: np.ndarray) -> None:
    """Write an (N, 4) ``stamp, x, y, theta`` trajectory as TUM (z = 0, yaw-only quaternion), rows
    in time order (a stable sort by stamp: every row is kept), atomically
    (:func:`~frslam_graph.atomic.atomic_write`)."""
    traj = as_trajectory(trajectory, "trajectory")
    traj = traj[np.argsort(traj[:, 0], kind="stable")]
    half = traj[:, 3] / 2.0
    zeros = np.zeros(len(traj))
    out = np.column_stack(
        (traj[:, 0], traj[:, 1], traj[:, 2], zeros, zeros, zeros, np.sin(half), np.cos(half))
    )
    from frslam_graph.atomic import atomic_write

    with atomic_write(path) as f:
        f.write("# stamp x y z qx qy qz qw\n")
        np.savetxt(f, out, fmt=["%.9f"] + ["%.9g"] * 7)


def load_relations(path: str | Path) -> np.ndarray:
    """Read a relations file ``t1 t2 x y z roll pitch yaw`` as (K, 5) ``t1, t2, x, y, yaw``."""
    a, _lines = _rows(Path(path), 8, "t1 t2 x y z roll pitch yaw")
    return a[:, [0, 1, 2, 3, 7]]
