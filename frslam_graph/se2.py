"""SE(2) algebra on (x, y, theta) poses: metres, radians.

A pose is an (x, y, theta) array; (N, 3) arrays hold one pose per row. ``compose(a, b)`` is
a ⊕ b (b given in a's frame), ``between(a, b)`` = a⁻¹ ⊕ b, ``log`` / ``exp`` the group's
Log / Exp (GTSAM's Pose2 convention), ``tangent_cov`` / ``vector_cov`` move a covariance between
additive (x, y, theta) errors and the body-frame tangent (right perturbation x ⊕ Exp(ξ)).

Two angle wraps, which differ in the last bits and at the end of the range they include:
:func:`wrap` (modulo, to [-pi, pi)) for the backend's algebra, :func:`wrap_atan2`
(``atan2(sin, cos)``, to (-pi, pi]) for the readers, the simulator and the metrics; each caller
kept the one it had, so recordings and figures stay identical bit for bit. :func:`wrap_deg`
wraps degrees to (-180, 180].
"""

from __future__ import annotations

import math

import numpy as np

Pose = np.ndarray  # (3,) x, y, theta
_TWO_PI = 2.0 * math.pi


def wrap(theta: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    if isinstance(theta, float | int | np.floating):  # scalar fast path (hot in compose/between)
        return (float(theta) + math.pi) % _TWO_PI - math.pi
    out = (np.asarray(theta, dtype=np.float64) + np.pi) % _TWO_PI - np.pi
    return float(out) if out.ndim == 0 else out


def wrap_atan2(theta: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped to (-pi, pi] as ``atan2(sin, cos)``: a Python or numpy float scalar
    through :mod:`math`, an array (0-d included) through numpy."""
    if isinstance(theta, float | int):
        return math.atan2(math.sin(theta), math.cos(theta))
    return np.arctan2(np.sin(theta), np.cos(theta))


def wrap_deg(deg: float) -> float:
    """Angle in degrees wrapped to (-180, 180]."""
    w = math.fmod(deg, 360.0)
    if w <= -180.0:
        w += 360.0
    elif w > 180.0:
        w -= 360.0
    return w


def rot(theta: float) -> np.ndarray:
    """2×2 rotation matrix of ``theta``."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def compose(a: Pose, b: Pose) -> np.ndarray:
    """a ⊕ b: pose b given in frame a, returned in a's parent frame."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])])


def inverse(a: Pose) -> np.ndarray:
    """a⁻¹: the parent frame's pose given in frame a."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap(-a[2])])


def between(a: Pose, b: Pose) -> np.ndarray:
    """a⁻¹ ⊕ b: pose b expressed in frame a."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])])


def between_many(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a[i]⁻¹ ⊕ b[i] for (N, 3) arrays a and b (vectorised, row by row)."""
    a, b = np.asarray(a, dtype=np.float64).reshape(-1, 3), np.asarray(b, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy, wrap(b[:, 2] - a[:, 2])))


def compose_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a[i] ⊕ b[i] for (N, 3) arrays a and b (vectorised, row by row)."""
    a, b = np.asarray(a, dtype=np.float64).reshape(-1, 3), np.asarray(b, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack(
        (a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1], wrap(a[:, 2] + b[:, 2]))
    )


def inverse_rows(a: np.ndarray) -> np.ndarray:
    """a[i]⁻¹ for an (N, 3) array of poses (vectorised, row by row)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack((-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], wrap(-a[:, 2])))


def compose_jacobians(a: Pose, b: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of compose(a, b) w.r.t. the vectors a and b (additive perturbations)."""
    c, s = np.cos(a[2]), np.sin(a[2])
    ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]])
    jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja, jb


def compose_many(a: Pose, b: np.ndarray) -> np.ndarray:
    """a ⊕ b[i] for an (N, 3) array b (vectorised)."""
    b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(a[2]), np.sin(a[2])
    out = np.empty_like(b)
    out[:, 0] = a[0] + c * b[:, 0] - s * b[:, 1]
    out[:, 1] = a[1] + s * b[:, 0] + c * b[:, 1]
    out[:, 2] = wrap(a[2] + b[:, 2])
    return out


def to_matrix(p: Pose) -> np.ndarray:
    """3×3 homogeneous matrix of an SE(2) pose."""
    c, s = np.cos(p[2]), np.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


def from_matrix(m: np.ndarray) -> np.ndarray:
    """(x, y, theta) of a 3×3 SE(2) or 4×4 SE(3) matrix (the latter projected to the plane)."""
    m = np.asarray(m)
    if m.shape == (4, 4):
        return np.array([m[0, 3], m[1, 3], np.arctan2(m[1, 0], m[0, 0])])
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])


def to_matrix4(p: Pose) -> np.ndarray:
    """4×4 SE(3) matrix of a planar pose (z = 0, rotation about z)."""
    c, s = np.cos(p[2]), np.sin(p[2])
    return np.array([[c, -s, 0.0, p[0]], [s, c, 0.0, p[1]], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def tangent_cov(pose: Pose, cov_vec: np.ndarray) -> np.ndarray:
    """Covariance of additive (x, y, theta) errors -> GTSAM Pose2 tangent (body-frame) covariance."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    a = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # rot(theta)ᵀ in an identity
    return a @ cov_vec @ a.T


def vector_cov(pose: Pose, cov_tangent: np.ndarray) -> np.ndarray:
    """Inverse of :func:`tangent_cov`: body-frame covariance -> additive (x, y, theta) covariance."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    a = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # rot(theta) in an identity
    return a @ cov_tangent @ a.T


def log(p: Pose) -> np.ndarray:
    """SE(2) Log: the twist (v_x, v_y, theta) of a pose, ``exp(log(p)) == p``."""
    th = float(p[2])
    half = 0.5 * th
    # a = (θ/2) sin θ / (1 - cos θ); its series avoids 0/0 for tiny θ
    t2 = th * th
    a = 1.0 - t2 / 12.0 - t2 * t2 / 720.0 if abs(th) < 1e-3 else half * np.sin(th) / (1.0 - np.cos(th))
    vinv = np.array([[a, half], [-half, a]])
    return np.array([*(vinv @ np.asarray(p[:2])), th])


def exp(v: np.ndarray) -> np.ndarray:
    """SE(2) Exp: the pose reached by the twist ``v`` = (v_x, v_y, theta) in unit time, theta wrapped."""
    th = float(v[2])
    if abs(th) < 1e-3:  # series of sin θ / θ and (1 - cos θ) / θ
        t2 = th * th
        sa, ca = 1.0 - t2 / 6.0 + t2 * t2 / 120.0, th * (0.5 - t2 / 24.0)
    else:
        sa, ca = np.sin(th) / th, (1.0 - np.cos(th)) / th
    vm = np.array([[sa, -ca], [ca, sa]])
    return np.array([*(vm @ np.asarray(v[:2])), wrap(th)])


def relative_motion(poses: np.ndarray) -> np.ndarray:
    """(N-1, 3) increments ``pose[k-1]^-1 ⊕ pose[k]`` in the frame of ``pose[k-1]``."""
    d = np.diff(poses[:, :2], axis=0)
    th = poses[:-1, 2]
    c, s = np.cos(th), np.sin(th)
    dth = np.diff(poses[:, 2])
    dth = wrap_atan2(dth)
    return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], dth))


def compose_increments(start: np.ndarray, inc: np.ndarray) -> np.ndarray:
    """(N+1, 3) poses from ``start`` composed with the body-frame increments ``inc`` (N, 3)."""
    th = start[2] + np.concatenate(([0.0], np.cumsum(inc[:, 2])))
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dx = c * inc[:, 0] - s * inc[:, 1]
    dy = s * inc[:, 0] + c * inc[:, 1]
    x = start[0] + np.concatenate(([0.0], np.cumsum(dx)))
    y = start[1] + np.concatenate(([0.0], np.cumsum(dy)))
    return np.column_stack((x, y, wrap_atan2(th)))


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(M, 3) SE(2) poses linearly interpolated at ``query`` from ``poses`` (N, 3) at increasing
    ``stamps`` (N,): x, y linearly, the heading unwrapped then wrapped to (-pi, pi]. Queries
    outside the stamps take the end poses (``np.interp``)."""
    q = np.asarray(query, dtype=np.float64)
    heading = np.interp(q, stamps, np.unwrap(poses[:, 2]))
    return np.column_stack(
        (
            np.interp(q, stamps, poses[:, 0]),
            np.interp(q, stamps, poses[:, 1]),
            wrap_atan2(np.asarray(heading)),
        )
    )
