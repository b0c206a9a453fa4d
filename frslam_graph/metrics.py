"""Trajectory metrics: the relation-based error of Kümmerle et al. (2009), ATE and RPE, TUM files.

A trajectory is an (N, 4) array ``stamp, x, y, theta`` (seconds, metres, radians; ``base_link``
in ``map``). A TUM file holds one pose per line, ``stamp x y z qx qy qz qw``; we write z = 0 and a
yaw-only quaternion and read the yaw back (roll / pitch are ignored).

**Relation metric** ("On measuring the accuracy of SLAM algorithms", Autonomous Robots 2009): a
relations file lists reference relative poses ``t1 t2 x y z roll pitch yaw`` between scan stamps
(the pose at ``t2`` in the frame of the pose at ``t1``). For each relation the estimated relative
pose is ``δ* = x(t1)⁻¹ ⊕ x(t2)``, with each stamp matched to the nearest trajectory pose within
``tolerance`` seconds; the error is ``δ ⊖ δ*``: translational ``|t - t*|`` (m) and rotational
``|wrap(θ - θ*)|`` (deg). We report mean ± std of both (the figures of Kümmerle et al. and of Hess
et al. 2016) and the mean squares, and count relations that found no pose.

**ATE / RPE** go through evo; evo's alignment is SE(3)/Sim(3) and raises on a straight path, so
the estimate is aligned to the reference with Umeyama on the x, y columns only (SE(2) or Sim(2)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from frslam_graph.datasets.recording import interpolate_poses
from frslam_graph.errors import TrajectoryError


# ---------------------------------------------------------------------------- files
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
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return np.column_stack((a[:, 0], a[:, 1], a[:, 2], yaw))


def save_tum(path: str | Path, trajectory: np.ndarray) -> None:
    """Write an (N, 4) ``stamp, x, y, theta`` trajectory as TUM (z = 0, yaw-only quaternion),
    atomically (:func:`~frslam_graph.atomic.atomic_write`)."""
    traj = as_trajectory(trajectory, "trajectory")
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


def as_trajectory(trajectory: np.ndarray, what: str = "trajectory") -> np.ndarray:
    """Check an (N, 4) ``stamp, x, y, theta`` array; TrajectoryError when it is not one."""
    traj = np.asarray(trajectory, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 4:
        raise TrajectoryError(
            f"expected an (N, 4) array stamp, x, y, theta; got shape {traj.shape}", where=what
        )
    if not np.isfinite(traj).all():
        raise TrajectoryError("non-finite values", where=what)
    return traj


# ---------------------------------------------------------------------------- relation metric
@dataclass(frozen=True)
class RelationResult:
    """Relation-based error (Kümmerle et al. 2009) of a trajectory."""

    trans_mean: float  # m, mean of |t - t*|
    trans_std: float  # m
    rot_mean: float  # deg, mean of |wrap(θ - θ*)|
    rot_std: float  # deg
    trans_sq_mean: float  # m², mean of |t - t*|²
    rot_sq_mean: float  # deg², mean of wrap(θ - θ*)²
    matched: int  # relations evaluated
    unmatched: int  # relations with a stamp that found no pose within the tolerance
    trans_errors: np.ndarray  # (matched,) m
    rot_errors: np.ndarray  # (matched,) deg

    def __str__(self) -> str:
        return (
            f"{self.trans_mean:.4f} ± {self.trans_std:.4f} m, {self.rot_mean:.3f} ± {self.rot_std:.3f} deg "
            f"over {self.matched} relations ({self.unmatched} unmatched)"
        )


def nearest_pose(stamps: np.ndarray, query: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest of the sorted ``stamps`` for each query, and whether it is within tolerance."""
    query = np.asarray(query, dtype=np.float64)
    if len(stamps) == 1:
        idx = np.zeros(len(query), dtype=np.intp)
    else:
        hi = np.clip(np.searchsorted(stamps, query), 1, len(stamps) - 1)
        lo = hi - 1
        idx = np.where(query - stamps[lo] <= stamps[hi] - query, lo, hi)
    ok = np.abs(stamps[idx] - query) <= tolerance
    return idx, ok


def interpolate_trajectory(
    traj: np.ndarray, stamps: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a sorted (N, 4) trajectory at ``stamps`` by linear interpolation (heading unwrapped).

    Returns ((K, 4) poses, (K,) ok); ok is False outside the trajectory or where the two poses
    around a stamp are more than ``max_gap`` seconds apart.
    """
    t = traj[:, 0]
    stamps = np.asarray(stamps, dtype=np.float64)
    hi = np.clip(np.searchsorted(t, stamps, side="left"), 1, max(len(t) - 1, 1))
    lo = hi - 1
    inside = (stamps >= t[0]) & (stamps <= t[-1])
    if len(t) > 1:
        ok = inside & ((t[hi] - t[lo] <= max_gap) | (stamps == t[lo]) | (stamps == t[hi]))
    else:
        ok = inside
    out = np.column_stack((stamps, interpolate_poses(t, traj[:, 1:4], stamps)))
    return out, ok


def relative_poses(
    trajectory: np.ndarray,
    t1: np.ndarray,
    t2: np.ndarray,
    tolerance: float = 0.01,
    interpolate: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Relative poses ``x(t1)⁻¹ ⊕ x(t2)`` of ``trajectory`` (N, 4), (K, 3): x, y (m, in the frame
    of the pose at t1) and θ(t2) - θ(t1) (rad, not wrapped); and which of the K pairs found poses.

    Each stamp takes the nearest pose within ``tolerance`` seconds, or with ``interpolate``
    (seconds) the pose interpolated between poses at most that far apart (as
    :func:`relation_error`). Rows of pairs without poses are NaN.
    """
    traj = as_trajectory(trajectory)
    if len(traj) == 0:
        raise TrajectoryError("empty trajectory", where="trajectory")
    traj = traj[np.argsort(traj[:, 0], kind="stable")]
    if interpolate is not None:
        xi, ok_i = interpolate_trajectory(traj, t1, interpolate)
        xj, ok_j = interpolate_trajectory(traj, t2, interpolate)
    else:
        i, ok_i = nearest_pose(traj[:, 0], t1, tolerance)
        j, ok_j = nearest_pose(traj[:, 0], t2, tolerance)
        xi, xj = traj[i], traj[j]
    ok = ok_i & ok_j
    c, s = np.cos(xi[:, 3]), np.sin(xi[:, 3])
    dx, dy = xj[:, 1] - xi[:, 1], xj[:, 2] - xi[:, 2]
    out = np.column_stack((c * dx + s * dy, -s * dx + c * dy, xj[:, 3] - xi[:, 3]))
    out[~ok] = np.nan
    return out, ok


def relation_error(
    trajectory: np.ndarray,
    relations: np.ndarray | str | Path,
    tolerance: float = 0.01,
    interpolate: float | None = None,
) -> RelationResult:
    """Relation-based error of ``trajectory`` (N, 4) against ``relations`` ((K, 5) or a relations file).

    Each relation stamp takes the nearest pose within ``tolerance`` seconds; with ``interpolate``
    (seconds) a keyframe trajectory is instead interpolated at the stamps, between poses at most
    that far apart. Relations left without a pose are counted in ``unmatched``.
    """
    traj = as_trajectory(trajectory)
    rel = (
        load_relations(relations)
        if isinstance(relations, (str, Path))
        else np.asarray(relations, dtype=np.float64)
    )
    if rel.ndim != 2 or rel.shape[1] != 5:
        raise TrajectoryError(
            f"expected (K, 5) relations t1, t2, x, y, yaw; got shape {rel.shape}", where="relations"
        )
    if len(traj) == 0:
        raise TrajectoryError("empty trajectory", where="trajectory")
    est, ok = relative_poses(traj, rel[:, 0], rel[:, 1], tolerance, interpolate)
    est, r = est[ok], rel[ok]
    t_err = np.hypot(r[:, 2] - est[:, 0], r[:, 3] - est[:, 1])
    d_th = r[:, 4] - est[:, 2]
    r_err = np.degrees(np.abs(np.arctan2(np.sin(d_th), np.cos(d_th))))
    n = int(ok.sum())

    def stat(f, a):
        return float(f(a)) if n else float("nan")

    return RelationResult(
        trans_mean=stat(np.mean, t_err),
        trans_std=stat(np.std, t_err),
        rot_mean=stat(np.mean, r_err),
        rot_std=stat(np.std, r_err),
        trans_sq_mean=stat(np.mean, t_err**2),
        rot_sq_mean=stat(np.mean, r_err**2),
        matched=n,
        unmatched=int(len(rel) - n),
        trans_errors=t_err,
        rot_errors=r_err,
    )


# ---------------------------------------------------------------------------- ATE / RPE via evo
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
    out[:, 3] = np.arctan2(np.sin(traj_est[:, 3] + yaw), np.cos(traj_est[:, 3] + yaw))
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
