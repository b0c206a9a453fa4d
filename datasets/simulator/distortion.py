"""The distortion between a floor plan and the true house: what registration must recover.

A floor plan is drawn in plan units (pixels, say) with an unknown scale, a wrong aspect ratio,
an unknown rotation, possibly mirrored. The true house (in metres, the ``map`` frame of the
simulated robot) is ``house = D · plan`` with the 3×3 homogeneous matrix

    D = T(tx, ty) · R(rotation) · diag(1, -1 if flip else 1) · diag(sx, sy)

where ``sx = metres_per_unit * aspect[0]`` and ``sy = metres_per_unit * aspect[1]``. This is the
parametrisation a :class:`~frslam_graph.registration.Registration` reports
(``R(rotation) · diag(1, ±1) · diag(sx, sy)`` plus a translation). Units: metres, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from frslam_graph.errors import ConfigError
from frslam_graph.se2 import rot

RotationMode = Literal["step90", "any", "none"]


def _finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"expected a number, got {value!r}", where=f"distortion.{name}") from None
    if not math.isfinite(v):
        raise ConfigError(f"expected a finite number, got {value!r}", where=f"distortion.{name}")
    return v


@dataclass(frozen=True)
class Distortion:
    """Plan units -> house metres. See the module docstring for the exact matrix form."""

    metres_per_unit: float
    aspect: tuple[float, float] = (1.0, 1.0)
    flip: bool = False
    rotation: float = 0.0  # radians, counter-clockwise
    translation: tuple[float, float] = (0.0, 0.0)  # metres

    def __post_init__(self) -> None:
        mpu = _finite("metres_per_unit", self.metres_per_unit)
        if mpu <= 0.0:
            raise ConfigError(f"must be > 0, got {mpu!r}", where="distortion.metres_per_unit")
        try:
            ax, ay = (float(v) for v in self.aspect)
        except (TypeError, ValueError):
            raise ConfigError(
                f"expected two numbers, got {self.aspect!r}", where="distortion.aspect"
            ) from None
        for name, v in (("aspect[0]", ax), ("aspect[1]", ay)):
            if not math.isfinite(v) or v <= 0.0:
                raise ConfigError(f"must be a finite number > 0, got {v!r}", where=f"distortion.{name}")
        try:
            tx, ty = (float(v) for v in self.translation)
        except (TypeError, ValueError):
            raise ConfigError(
                f"expected two numbers, got {self.translation!r}", where="distortion.translation"
            ) from None
        _finite("translation[0]", tx)
        _finite("translation[1]", ty)
        object.__setattr__(self, "metres_per_unit", mpu)
        object.__setattr__(self, "aspect", (ax, ay))
        object.__setattr__(self, "flip", bool(self.flip))
        object.__setattr__(self, "rotation", _finite("rotation", self.rotation))
        object.__setattr__(self, "translation", (tx, ty))

    @property
    def sx(self) -> float:
        """Metres per plan unit along the plan's x axis."""
        return self.metres_per_unit * self.aspect[0]

    @property
    def sy(self) -> float:
        """Metres per plan unit along the plan's y axis."""
        return self.metres_per_unit * self.aspect[1]

    @property
    def linear(self) -> np.ndarray:
        """The 2×2 part ``R(rotation) · diag(1, ±1) · diag(sx, sy)``."""
        return rot(self.rotation) @ np.diag([1.0, -1.0 if self.flip else 1.0]) @ np.diag([self.sx, self.sy])

    @property
    def matrix(self) -> np.ndarray:
        """3×3 homogeneous matrix mapping plan coordinates (column vectors) to house metres."""
        m = np.eye(3)
        m[:2, :2] = self.linear
        m[:2, 2] = self.translation
        return m

    @property
    def inverse(self) -> np.ndarray:
        """3×3 matrix mapping house metres back to plan coordinates."""
        return np.linalg.inv(self.matrix)

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Map (N, 2) plan points to house metres."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return pts @ self.linear.T + np.asarray(self.translation)

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        rotation: RotationMode = "step90",
        aspect_max: float = 0.3,
        flip_prob: float = 0.5,
        metres_per_unit: float | None = None,
        plan_bounds: tuple[float, float, float, float] | None = None,
        diagonal_range: tuple[float, float] = (10.0, 25.0),
        translation_max: float = 10.0,
    ) -> Distortion:
        """A random distortion as in the registration benchmark's protocol (tools/README.md).

        ``aspect`` has ``aspect[1] / aspect[0] = 1 + e`` with ``e ~ U(-aspect_max, aspect_max)``
        (area kept); ``rotation`` is a multiple of 90° (``"step90"``), any angle (``"any"``) or 0
        (``"none"``); ``flip`` with probability ``flip_prob``. Without ``metres_per_unit`` the scale
        makes the plan's bounding-box diagonal (``plan_bounds``, required then) a length drawn
        from ``diagonal_range`` metres. With ``plan_bounds`` the house's bounding-box centre lands
        at a random point within ``±translation_max`` of the origin; without, the translation is
        drawn from that square directly.
        """
        if rotation not in ("step90", "any", "none"):
            raise ConfigError(
                f"expected 'step90', 'any' or 'none', got {rotation!r}", where="distortion.rotation"
            )
        if not (0.0 <= aspect_max < 1.0):
            raise ConfigError(f"must be in [0, 1), got {aspect_max!r}", where="distortion.aspect_max")
        if not (0.0 <= flip_prob <= 1.0):
            raise ConfigError(f"must be in [0, 1], got {flip_prob!r}", where="distortion.flip_prob")
        if metres_per_unit is None:
            if plan_bounds is None:
                raise ConfigError(
                    "give metres_per_unit or plan_bounds to choose a realistic scale",
                    where="distortion.metres_per_unit",
                )
            minx, miny, maxx, maxy = plan_bounds
            diag = math.hypot(maxx - minx, maxy - miny)
            if not (math.isfinite(diag) and diag > 0.0):
                raise ConfigError(f"degenerate plan bounds {plan_bounds!r}", where="distortion.plan_bounds")
            lo, hi = diagonal_range
            metres_per_unit = float(rng.uniform(lo, hi)) / diag
        e = float(rng.uniform(-aspect_max, aspect_max)) if aspect_max > 0 else 0.0
        aspect = (1.0 / math.sqrt(1.0 + e), math.sqrt(1.0 + e))
        flip = bool(rng.random() < flip_prob)
        if rotation == "step90":
            angle = float(rng.integers(0, 4)) * (math.pi / 2.0)
        elif rotation == "any":
            angle = float(rng.uniform(-math.pi, math.pi))
        else:
            angle = 0.0
        offset = rng.uniform(-translation_max, translation_max, size=2)
        d = cls(metres_per_unit, aspect, flip, angle, (0.0, 0.0))
        if plan_bounds is not None:
            minx, miny, maxx, maxy = plan_bounds
            centre = d.apply(np.array([[(minx + maxx) / 2.0, (miny + maxy) / 2.0]]))[0]
            offset = offset - centre
        return cls(metres_per_unit, aspect, flip, angle, (float(offset[0]), float(offset[1])))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping, including the matrix for readers that only want that."""
        return {
            "metres_per_unit": self.metres_per_unit,
            "aspect": list(self.aspect),
            "flip": self.flip,
            "rotation": self.rotation,
            "rotation_deg": math.degrees(self.rotation),
            "translation": list(self.translation),
            "sx": self.sx,
            "sy": self.sy,
            "matrix": self.matrix.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Distortion:
        """Inverse of :meth:`to_dict` (derived keys ``sx``, ``sy``, ``matrix`` are ignored)."""
        if not isinstance(data, dict):
            raise ConfigError(f"expected a mapping, got {type(data).__name__}", where="distortion")
        for key in ("metres_per_unit", "aspect", "flip", "rotation", "translation"):
            if key not in data:
                raise ConfigError("missing field", where=f"distortion.{key}")
        return cls(
            metres_per_unit=data["metres_per_unit"],
            aspect=data["aspect"],
            flip=data["flip"],
            rotation=data["rotation"],
            translation=data["translation"],
        )
