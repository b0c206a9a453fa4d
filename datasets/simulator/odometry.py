"""Wheel odometry with systematic and random drift, from a true trajectory.

Frames (REP-105): the odometry pose is ``base_link`` in ``odom``; the ``odom`` frame starts at the
first true pose (``odom(t0) == true(t0)``, i.e. ``map -> odom`` is the identity at the start) and
drifts from there. Units: metres, radians, seconds.

Between consecutive odometry samples the true motion in the robot's frame
``(dx, dy, dtheta)`` (distance ``d``) is measured as

- translation ``(dx, dy) * (1 + scale_error)`` plus a random error along the motion with variance
  ``dist_noise**2 * d`` (a random walk: after 1 m the distance error has std ``dist_noise`` m,
  i.e. "2 % of distance" for the default 0.02);
- rotation ``dtheta * (1 + turn_scale_error)`` plus a random error with variance
  ``heading_noise**2 * d + turn_noise**2 * |dtheta|`` (``heading_noise`` = 1° per sqrt(metre) by
  default: the heading error after 1 m has std 1°).

The noise is a random walk in distance, so the drift does not depend on the odometry rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from frslam_graph.errors import ConfigError
from frslam_graph.se2 import compose_increments, interpolate_poses, relative_motion


@dataclass(frozen=True)
class OdometryNoise:
    """Drift parameters; angles in radians (use :meth:`from_degrees` for degrees)."""

    scale_error: float = 0.02
    turn_scale_error: float = 0.01
    dist_noise: float = 0.02
    heading_noise: float = math.radians(1.0)
    turn_noise: float = math.radians(0.5)
    rate: float = 50.0  # Hz

    def __post_init__(self) -> None:
        checks = {
            "scale_error": -0.5 < self.scale_error < 0.5,
            "turn_scale_error": -0.5 < self.turn_scale_error < 0.5,
            "dist_noise": 0.0 <= self.dist_noise < 1.0,
            "heading_noise": 0.0 <= self.heading_noise < 1.0,
            "turn_noise": 0.0 <= self.turn_noise < 1.0,
            "rate": 0.1 <= self.rate <= 1000.0,
        }
        for name, ok in checks.items():
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and ok):
                raise ConfigError(f"value {v!r} out of range", where=f"odometry.{name}")

    @classmethod
    def none(cls, rate: float = 50.0) -> OdometryNoise:
        """Perfect odometry (odom == true pose)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, rate)

    def to_dict(self) -> dict[str, float]:
        return {
            "scale_error": self.scale_error,
            "turn_scale_error": self.turn_scale_error,
            "dist_noise": self.dist_noise,
            "heading_noise_deg": math.degrees(self.heading_noise),
            "turn_noise_deg": math.degrees(self.turn_noise),
            "rate": self.rate,
        }


@dataclass
class OdometryTrack:
    """Odometry poses ``poses`` (N, 3) of ``base_link`` in ``odom`` at ``stamps`` (N,)."""

    stamps: np.ndarray
    poses: np.ndarray

    def sample(self, stamps: np.ndarray) -> np.ndarray:
        """Poses linearly interpolated at ``stamps`` (theta unwrapped, then wrapped)."""
        t = np.asarray(stamps, dtype=np.float64)
        return interpolate_poses(self.stamps, self.poses, t)

    def velocities(self) -> np.ndarray:
        """(N, 3) body-frame velocities (vx, vy, wz) by backward differences (first row zero)."""
        out = np.zeros_like(self.poses)
        if len(self.poses) < 2:
            return out
        dt = np.diff(self.stamps)
        d = np.diff(self.poses[:, :2], axis=0)
        th = self.poses[:-1, 2]
        c, s = np.cos(th), np.sin(th)
        out[1:, 0] = (c * d[:, 0] + s * d[:, 1]) / dt
        out[1:, 1] = (-s * d[:, 0] + c * d[:, 1]) / dt
        out[1:, 2] = np.diff(np.unwrap(self.poses[:, 2])) / dt
        return out


def wheel_odometry(
    stamps: np.ndarray, true_poses: np.ndarray, noise: OdometryNoise, rng: np.random.Generator
) -> OdometryTrack:
    """Odometry at ``stamps`` from the true poses at the same stamps (see the module docstring)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    true_poses = np.asarray(true_poses, dtype=np.float64)
    if true_poses.ndim != 2 or true_poses.shape[1] != 3 or len(true_poses) != len(stamps):
        raise ConfigError("expected (N, 3) poses matching N stamps", where="odometry.poses")
    if len(stamps) == 0:
        return OdometryTrack(stamps, true_poses.copy())
    inc = relative_motion(true_poses)
    d = np.hypot(inc[:, 0], inc[:, 1])
    meas = inc.copy()
    meas[:, :2] *= 1.0 + noise.scale_error
    if noise.dist_noise > 0.0:
        err = rng.normal(0.0, 1.0, size=len(d)) * noise.dist_noise * np.sqrt(d)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(d > 0, inc[:, 0] / d, 0.0)
            uy = np.where(d > 0, inc[:, 1] / d, 0.0)
        meas[:, 0] += err * ux
        meas[:, 1] += err * uy
    meas[:, 2] *= 1.0 + noise.turn_scale_error
    var_th = noise.heading_noise**2 * d + noise.turn_noise**2 * np.abs(inc[:, 2])
    if np.any(var_th > 0):
        meas[:, 2] += rng.normal(0.0, 1.0, size=len(d)) * np.sqrt(var_th)
    return OdometryTrack(stamps, compose_increments(true_poses[0], meas))
