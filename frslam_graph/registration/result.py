"""The result of registering a floor plan to an occupancy grid, and its matrix convention.

A registration maps *plan coordinates* (plan units, right-handed, y up) to *map metres* (the
occupancy grid's world frame, REP-105 ``map``). The 3×3 homogeneous matrix acts on column
vectors and factors as::

    matrix = T(tx, ty) · R(rotation) · diag(1, -1 if flipped else 1) · diag(sx, sy)

so the plan is first scaled per axis (metres per plan unit, ``sx``, ``sy`` > 0), then mirrored
about its x axis if ``flipped``, then rotated counter-clockwise by ``rotation`` and translated.
Rotations are in radians in code and in degrees (``rotation_deg``) in the result for reading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph.se2 import wrap_deg

if TYPE_CHECKING:
    from frslam_graph.floorplan import FloorPlan


def matrix_from_params(
    flipped: bool, rotation_rad: float, sx: float, sy: float, tx: float = 0.0, ty: float = 0.0
) -> np.ndarray:
    """3×3 matrix ``T(tx, ty) · R(rotation_rad) · diag(1, ±1) · diag(sx, sy)`` (plan -> map)."""
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    f = -1.0 if flipped else 1.0
    return np.array(
        [
            [c * sx, -s * f * sy, tx],
            [s * sx, c * f * sy, ty],
            [0.0, 0.0, 1.0],
        ]
    )


def params_from_matrix(matrix: np.ndarray) -> tuple[bool, float, float, float, float, float]:
    """Inverse of :func:`matrix_from_params`: ``(flipped, rotation_rad, sx, sy, tx, ty)``.

    ``flipped`` is the sign of the determinant; the rotation is the direction of the image of the
    plan's x axis, in (-pi, pi]. A shear (not produced by this convention) is dropped.
    """
    m = np.asarray(matrix, dtype=float)
    a = m[:2, :2]
    det = float(np.linalg.det(a))
    flipped = det < 0.0
    col0, col1 = a[:, 0], a[:, 1]
    sx = float(np.hypot(col0[0], col0[1]))
    rotation = math.atan2(col0[1], col0[0])
    c, s = math.cos(rotation), math.sin(rotation)
    # R^T col1 = (shear, f * sy)
    sy = abs(-s * col1[0] + c * col1[1])
    return flipped, rotation, sx, float(sy), float(m[0, 2]), float(m[1, 2])


@dataclass
class Registration:
    """A floor plan registered to a map: the plan -> map-metres transform and its quality.

    ``ok`` is False for a failed or meaningless match (then ``reason`` says why and the matrix is
    the identity). ``score`` is the IoU of the match on the map's observed area, ``ambiguity`` the
    best score of a *different* hypothesis divided by ``score`` (in [0, 1]; near 1 = ambiguous),
    ``covariance`` the 3×3 covariance of the pose part (x, y in metres, theta in radians) or None:
    x, y are the matrix's translation (where the plan's origin lands in the map), theta its
    rotation; the scales are marginalised. ``doubt`` is the method's own reason to doubt an ``ok``
    match (empty: none; the paper-faithful method sets it from its score and ambiguity): a
    doubtful registration still carries its placement for a user to judge, but ``verdict`` is
    ``"doubtful"`` and the SLAM pipeline does not turn it into priors.
    """

    ok: bool
    reason: str = ""
    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    flipped: bool = False
    rotation_deg: float = 0.0
    scale: tuple[float, float] = (1.0, 1.0)
    translation: tuple[float, float] = (0.0, 0.0)
    score: float = 0.0
    ambiguity: float = 1.0
    rooms: tuple[str, ...] = ()
    covariance: np.ndarray | None = None
    method: str = ""
    time_s: float = 0.0
    candidates: list[tuple[float, bool, float]] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)
    doubt: str = ""

    @property
    def verdict(self) -> str:
        """``"registered"`` (ok, not doubted), ``"doubtful"`` (ok, with a ``doubt``) or ``"failed"``."""
        if not self.ok:
            return "failed"
        return "doubtful" if self.doubt else "registered"

    @property
    def placed(self) -> bool:
        """Whether the matrix places the plan: an ok registration, or a failed one that still
        carries its best placement (MFR's "no match": refused by its checks, with candidates), as
        opposed to one that never got a placement (too few rooms, no subset fits, degenerate)."""
        if not self.ok and not self.candidates:
            return False
        a = np.asarray(self.matrix, dtype=float)
        return bool(np.all(np.isfinite(a)) and abs(np.linalg.det(a[:2, :2])) > 0.0)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, **kwargs: Any) -> Registration:
        """A successful registration whose parameters are read from ``matrix``."""
        m = np.asarray(matrix, dtype=float).copy()
        flipped, rot, sx, sy, tx, ty = params_from_matrix(m)
        return cls(
            ok=kwargs.pop("ok", True),
            matrix=m,
            flipped=flipped,
            rotation_deg=wrap_deg(math.degrees(rot)),
            scale=(sx, sy),
            translation=(tx, ty),
            **kwargs,
        )

    @classmethod
    def failure(cls, reason: str, method: str = "", time_s: float = 0.0, **details: Any) -> Registration:
        """A failed registration: ``ok`` False, identity matrix, zero score, the reason given."""
        return cls(ok=False, reason=reason, method=method, time_s=time_s, details=dict(details))

    def apply(self, plan: FloorPlan) -> FloorPlan:
        """The plan transformed into map metres (rooms, doors and walls)."""
        return plan.transformed(self.matrix, units="m")

    def transform_points(self, xy: np.ndarray) -> np.ndarray:
        """Plan points (N, 2) -> map metres (N, 2)."""
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        return p @ self.matrix[:2, :2].T + self.matrix[:2, 2]

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dictionary (numpy arrays as nested lists)."""
        return {
            "ok": bool(self.ok),
            "verdict": self.verdict,
            "reason": self.reason,
            "doubt": self.doubt,
            "method": self.method,
            "matrix": np.asarray(self.matrix, dtype=float).tolist(),
            "flipped": bool(self.flipped),
            "rotation_deg": float(self.rotation_deg),
            "scale": [float(v) for v in self.scale],
            "translation": [float(v) for v in self.translation],
            "score": float(self.score),
            "ambiguity": float(self.ambiguity),
            "rooms": list(self.rooms),
            "covariance": None if self.covariance is None else np.asarray(self.covariance, float).tolist(),
            "time_s": float(self.time_s),
            "candidates": [[float(s), bool(f), float(r)] for s, f, r in self.candidates],
            "details": _jsonable(self.details),
        }


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
