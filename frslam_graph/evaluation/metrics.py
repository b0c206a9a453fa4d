"""ATE and RPE of a trajectory against a reference, through evo.

Trajectories are (N, 4) ``stamp, x, y, theta`` arrays (seconds, metres, radians; ``base_link`` in
``map``). evo's alignment is SE(3)/Sim(3) and raises on a straight path, so the estimate is
aligned to the reference with Umeyama on the x, y columns only (SE(2) or Sim(2)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from frslam_graph.errors import TrajectoryError
from frslam_graph.evaluation.trajectory import as_trajectory
from frslam_graph.se2 import wrap_atan2


@dataclass(frozen=True)
class ErrorStats:
    """Summary of per-pose (ATE) or per-pair (RPE) errors."""

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    n: int


@dataclass(frozen=True)
class Alignment2D:
    """x_ref ≈ scale · R(yaw) · x_est + (tx, ty)."""

    yaw: float
    tx: float
    ty: float
    scale: float


def _evo_traj(traj: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    half = traj[:, 3] / 2.0
    zeros = np.zeros(len(traj))
    quat_wxyz = np.column_stack((np.cos(half), zeros, zeros, np.sin(half)))
    xyz = np.column_stack((traj[:, 1], traj[:, 2], zeros))
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=quat_wxyz, timestamps=traj[:, 0].copy())


def _stats(values: np.ndarray) -> ErrorStats:
    v = np.asarray(values, dtype=np.float64)
    return ErrorStats(
        float(np.sqrt(np.mean(v**2))),
        float(np.mean(v)),
        float(np.median(v)),
        float(np.std(v)),
        float(np.max(v)),
        len(v),
    )


def associate(
    traj_est: np.ndarray, traj_ref: np.ndarray, max_dt: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of poses with stamps within ``max_dt`` (evo's nearest-time association)."""
    from evo.core import sync
    from evo.core.sync import SyncException

    est, ref = as_trajectory(traj_est, "estimate"), as_trajectory(traj_ref, "reference")
    try:
        ref_s, est_s = sync.associate_trajectories(_evo_traj(ref), _evo_traj(est), max_diff=max_dt)
    except SyncException as exc:
        raise TrajectoryError(f"no poses match in time within {max_dt} s ({exc})", where="estimate") from None
    return _from_evo(est_s), _from_evo(ref_s)


def _from_evo(t) -> np.ndarray:
    q = t.orientations_quat_wxyz
    return np.column_stack((t.timestamps, t.positions_xyz[:, 0], t.positions_xyz[:, 1], _yaw_wxyz(q)))


def _yaw_wxyz(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def align_2d(
    traj_est: np.ndarray, traj_ref: np.ndarray, scale: bool = False
) -> tuple[np.ndarray, Alignment2D]:
    """Umeyama on x, y of associated (same-length) trajectories; returns the aligned estimate."""
    from evo.core.geometry import GeometryException, umeyama_alignment

    if len(traj_est) < 2:
        raise TrajectoryError("at least 2 associated poses are needed to align", where="estimate")
    try:
        r, t, c = umeyama_alignment(traj_est[:, 1:3].T, traj_ref[:, 1:3].T, with_scale=scale)
    except GeometryException as exc:
        raise TrajectoryError(f"alignment failed ({exc})", where="estimate") from None
    yaw = math.atan2(r[1, 0], r[0, 0])
    out = traj_est.copy()
    out[:, 1:3] = (c * (r @ traj_est[:, 1:3].T)).T + t
    out[:, 3] = wrap_atan2(traj_est[:, 3] + yaw)
    return out, Alignment2D(yaw, float(t[0]), float(t[1]), float(c))


def ate(
    traj_est: np.ndarray,
    traj_ref: np.ndarray,
    *,
    align: bool = True,
    scale: bool = False,
    max_dt: float = 0.01,
) -> tuple[ErrorStats, Alignment2D | None]:
    """Absolute trajectory error (translation, m) after SE(2) (or Sim(2)) Umeyama alignment on x, y."""
    from evo.core import metrics

    est, ref = associate(traj_est, traj_ref, max_dt)
    alignment = None
    if align:
        est, alignment = align_2d(est, ref, scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((_evo_traj(ref), _evo_traj(est)))
    return _stats(ape.error), alignment


def translation_errors(
    traj_est: np.ndarray, traj_ref: np.ndarray, *, align: bool = True, max_dt: float = 0.02
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pose translation error (m) of the estimate against the reference, the quantity
    :func:`ate` summarises, with where it occurs: (distance travelled along the reference up to
    each pose (K,), error (K,), the estimate's associated poses (K, 4) SE(2)-aligned when
    ``align``, the reference's (K, 4))."""
    est, ref = associate(traj_est, traj_ref, max_dt)
    if align:
        est, _ = align_2d(est, ref)
    error = np.hypot(est[:, 1] - ref[:, 1], est[:, 2] - ref[:, 2])
    distance = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, 1:3], axis=0).T))])
    return distance, error, est, ref


def rpe(
    traj_est: np.ndarray,
    traj_ref: np.ndarray,
    *,
    delta: float = 1.0,
    unit: str = "frames",
    max_dt: float = 0.01,
) -> tuple[ErrorStats, ErrorStats]:
    """Relative pose error over pose pairs ``delta`` apart (``unit`` "frames" or "meters").

    Returns (translation m, rotation deg). RPE needs no alignment (it compares relative motions).
    """
    from evo.core import metrics
    from evo.core.filters import FilterException
    from evo.core.units import Unit

    est, ref = associate(traj_est, traj_ref, max_dt)
    units = {"frames": Unit.frames, "meters": Unit.meters, "m": Unit.meters}
    if unit not in units:
        raise TrajectoryError(f"unit must be 'frames' or 'meters', got {unit!r}", where="rpe")
    out = []
    for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
        m = metrics.RPE(rel, delta=delta, delta_unit=units[unit], all_pairs=False)
        try:
            m.process_data((_evo_traj(ref), _evo_traj(est)))
        except (metrics.MetricsException, FilterException) as exc:  # e.g. no pose pairs delta apart
            raise TrajectoryError(f"RPE failed ({exc})", where="estimate") from None
        out.append(_stats(m.error))
    return out[0], out[1]
