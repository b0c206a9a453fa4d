"""Checks of the streaming API's arguments (:class:`~frslam_graph.slam.FRSlam` ``add_scan``,
``add_points``, ``add`` and the constructor's ``floor_plan``).

Each check returns the value in the form the pipeline uses (float, float64 array, FloorPlan) or
raises :class:`~frslam_graph.errors.RecordingError` (``FloorPlanError`` for the plan) whose
``where`` is the argument's name, so a caller never sees numpy's bare ``ValueError``. They are
vectorised: an array is converted once and checked with whole-array numpy calls, never a Python
loop over beams or points.
"""

from __future__ import annotations

from numbers import Real
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from frslam_graph.errors import FloorPlanError, RecordingError
from frslam_graph.limits import short_repr

if TYPE_CHECKING:
    from frslam_graph.floorplan.model import FloorPlan


def finite_number(value: Any, name: str) -> float:
    """``value`` as a float; a real number (not a bool, not a string) and finite."""
    if isinstance(value, bool) or not isinstance(value, Real) or not np.isfinite(value):
        raise RecordingError(f"{name} must be a finite number, got {_short(value)}", where=name)
    return float(value)


def _array(value: Any, name: str, expected: str) -> np.ndarray:
    """``value`` as float64; only real numbers (no strings such as "1.0", no booleans)."""
    try:
        raw = value if isinstance(value, np.ndarray) else np.asarray(value)
        ok = raw.dtype.kind in "iuf"
        arr = raw.astype(np.float64, copy=False) if ok else None
    except (TypeError, ValueError):
        ok, arr = False, None
    if not ok or arr is None:
        raise RecordingError(
            f"{name} must be {expected}, got {type(value).__name__} {_short(value)}", where=name
        ) from None
    return arr


def ranges(value: Any) -> np.ndarray:
    """(N,) float64 ranges; nan / inf stay (they are no returns)."""
    r = _array(value, "ranges", "a 1-D array of numbers")
    if r.ndim != 1:
        raise RecordingError(f"ranges must be a 1-D array, got shape {r.shape}", where="ranges")
    return r


def range_max(value: Any, default: float) -> float:
    """The scan's maximum range: ``default`` when None, else a positive number (inf: no limit)."""
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, Real) or not value > 0.0:
        raise RecordingError(
            f"range_max must be a positive number (inf: no limit) or None, got {_short(value)}",
            where="range_max",
        )
    return float(value)


def pose(value: Any, name: str, finite: bool = True) -> np.ndarray:
    """(3,) float64 (x, y, theta); with ``finite`` every one must be finite."""
    p = _array(value, name, "(x, y, theta)").reshape(-1)
    if p.shape != (3,) or (finite and not np.all(np.isfinite(p))):
        what = "3 finite numbers" if finite else "3 numbers"
        raise RecordingError(f"{name} must be {what} (x, y, theta), got {_short(value)}", where=name)
    return p


def odom(value: Any) -> np.ndarray | None:
    """The wheel pose (3,) or None. A pose with a nan / inf is kept: the odometry reads it as no
    wheel reading at that scan (a dropout), as before."""
    return None if value is None else pose(value, "odom", finite=False)


def points(value: Any) -> np.ndarray:
    """(M, 2) finite float64 end points (an empty array of any shape: no points)."""
    p = _array(value, "points", "an (M, 2) array of numbers")
    if p.size == 0:
        return p.reshape(0, 2)
    if p.ndim != 2 or p.shape[1] != 2:
        raise RecordingError(f"points must be an (M, 2) array, got shape {p.shape}", where="points")
    if not np.isfinite(p).all():
        raise RecordingError("points must be finite (drop the beams without a return)", where="points")
    return p


def floor_plan(value: Any) -> FloorPlan | None:
    """None, a :class:`~frslam_graph.floorplan.model.FloorPlan`, or a path (str / Path) to a plan
    file, loaded with :meth:`FloorPlan.load` (any format it reads; errors name the file)."""
    if value is None:
        return None
    from frslam_graph.floorplan.model import FloorPlan

    if isinstance(value, FloorPlan):
        return value
    if isinstance(value, str | Path):
        return FloorPlan.load(value)
    raise FloorPlanError(
        f"floor_plan must be a FloorPlan or the path of a plan file, got {type(value).__name__}",
        where="floor_plan",
    )


def _short(value: Any) -> str:
    """``value`` quoted for a message, at most 60 characters (a huge value costs no memory)."""
    if isinstance(value, np.ndarray) and value.size > 60:
        return f"<array of shape {value.shape}>"
    return short_repr(value, 60)
