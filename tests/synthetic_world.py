"""A tiny vectorised 2D ray caster for backend tests (no simulator needed).

Worlds are (S, 4) arrays of wall segments (x0, y0, x1, y1) in metres. ``route`` makes a
trajectory at a constant speed through waypoints (turning in place at corners), ``cast`` a
720-beam scan, ``drifting_odometry`` wheel odometry with a scale error and a heading drift.
"""

from __future__ import annotations

import numpy as np


def box(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]], float)


def corridor_loop(width: float, height: float, boxes: int, seed: int, corridor: float = 2.5) -> np.ndarray:
    """Wall segments of a width x height rectangle of ``corridor``-wide corridors (m) with ``boxes``
    small boxes on the walls (irregular, seeded): the corners and corridors look alike, the boxes
    tell them apart."""
    w = corridor / 2.0
    rng = np.random.default_rng(seed)
    parts = [box(-w, -w, width + w, height + w), box(w, w, width - w, height - w)]
    for k in range(boxes):
        side = k % 4
        t = rng.uniform(2.0, (width if side % 2 == 0 else height) - 2.0)
        s, d = rng.uniform(0.3, 0.8), rng.uniform(0.2, 0.5)
        parts.append(
            [
                box(t, -w, t + s, -w + d),
                box(width + w - d, t, width + w, t + s),
                box(t, height + w - d, t + s, height + w),
                box(-w, t, -w + d, t + s),
            ][side]
        )
    return np.vstack(parts)


def room_world() -> np.ndarray:
    """A 12 × 8 m room with pillars, a cabinet and wall stubs: well constrained everywhere."""
    return np.vstack(
        [
            box(0, 0, 12, 8),
            box(3.0, 3.0, 3.4, 3.4),
            box(8.0, 4.5, 8.5, 5.0),
            box(5.5, 6.8, 7.5, 8.0),
            np.array([[6.0, 0.0, 6.0, 1.0], [0.0, 5.0, 1.0, 5.0], [12.0, 3.0, 11.0, 3.0]]),
            box(9.0, 2.6, 9.4, 3.2),
        ]
    )


def corridor_world(length: float = 200.0, width: float = 2.0) -> np.ndarray:
    """Two long parallel walls (y = ±width/2): translation along x is unobservable."""
    h = width / 2.0
    return np.array([[-length / 2, -h, length / 2, -h], [-length / 2, h, length / 2, h]], float)


def cast(
    world: np.ndarray,
    pose: np.ndarray,
    n_beams: int = 720,
    max_range: float = 10.0,
    noise: float = 0.01,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, float, float]:
    """Ranges (nan = no return), angle_min, angle_increment of a 360° scan from ``pose``."""
    angle_min, inc = -np.pi, 2.0 * np.pi / n_beams
    ang = pose[2] + angle_min + inc * np.arange(n_beams)
    d = np.column_stack((np.cos(ang), np.sin(ang)))  # (N, 2)
    a, e = world[:, :2], world[:, 2:] - world[:, :2]  # (S, 2)
    ao = a - pose[:2]
    denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[None, :, 0] * e[None, :, 1] - ao[None, :, 1] * e[None, :, 0]) / denom
        s = (ao[None, :, 0] * d[:, None, 1] - ao[None, :, 1] * d[:, None, 0]) / denom
    ok = (np.abs(denom) > 1e-12) & (t > 1e-6) & (s >= 0.0) & (s <= 1.0)
    r = np.where(ok, t, np.inf).min(axis=1)
    if noise > 0.0:
        rng = rng or np.random.default_rng(0)
        r = r + rng.normal(0.0, noise, r.shape)
    r[(r > max_range) | ~np.isfinite(r)] = np.nan
    return r, angle_min, inc


def route(
    waypoints: list[tuple[float, float]],
    speed: float = 0.5,
    rate: float = 10.0,
    turn_rate: float = np.deg2rad(60.0),
) -> np.ndarray:
    """(N, 4) stamp, x, y, theta: straight legs at ``speed``, turns in place at ``turn_rate``."""
    wp = np.asarray(waypoints, float)
    dt = 1.0 / rate
    poses = []
    heading = float(np.arctan2(*(wp[1] - wp[0])[::-1]))
    pos = wp[0].copy()
    for nxt in wp[1:]:
        leg = nxt - pos
        target = float(np.arctan2(leg[1], leg[0]))
        dth = (target - heading + np.pi) % (2 * np.pi) - np.pi
        n_turn = int(np.ceil(abs(dth) / (turn_rate * dt)))
        for k in range(1, n_turn + 1):
            poses.append((*pos, heading + dth * k / n_turn))
        heading = target
        n = max(int(np.ceil(np.hypot(*leg) / (speed * dt))), 1)
        for k in range(1, n + 1):
            poses.append((*(pos + leg * k / n), heading))
        pos = nxt.copy()
    poses = np.array([(*wp[0], float(np.arctan2(*(wp[1] - wp[0])[::-1])))] + poses)
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    stamps = np.arange(len(poses)) * dt
    return np.column_stack((stamps, poses))


def drifting_odometry(
    truth: np.ndarray, scale: float = 0.02, heading_per_m: float = np.deg2rad(1.0), seed: int = 0
) -> np.ndarray:
    """(N, 3) wheel-odometry poses: increments scaled by (1 + scale) and a heading drift per metre."""
    rng = np.random.default_rng(seed)
    out = np.zeros((len(truth), 3))
    out[0] = truth[0, 1:]
    for i in range(1, len(truth)):
        a, b = truth[i - 1, 1:], truth[i, 1:]
        c, s = np.cos(a[2]), np.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        u = np.array([c * dx + s * dy, -s * dx + c * dy, (b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi])
        dist = np.hypot(u[0], u[1])
        u[:2] *= 1.0 + scale
        u[2] += heading_per_m * dist + rng.normal(0.0, 1e-4)
        p = out[i - 1]
        c, s = np.cos(p[2]), np.sin(p[2])
        out[i] = (p[0] + c * u[0] - s * u[1], p[1] + s * u[0] + c * u[1], p[2] + u[2])
    out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return out


ROOM_LOOP = [(1.5, 1.5), (10.5, 1.5), (10.5, 6.2), (1.5, 6.2), (1.5, 1.5)]


def scans_along(
    world: np.ndarray, truth: np.ndarray, max_range: float = 10.0, noise: float = 0.01, seed: int = 1
) -> tuple[list[np.ndarray], float, float]:
    """Ranges of a 720-beam scan at every pose of ``truth`` (N, 4); plus angle_min, increment."""
    rng = np.random.default_rng(seed)
    out = []
    amin = inc = 0.0
    for row in truth:
        r, amin, inc = cast(world, row[1:], max_range=max_range, noise=noise, rng=rng)
        out.append(r)
    return out, amin, inc


def to_points(ranges: np.ndarray, angle_min: float, inc: float) -> np.ndarray:
    ang = angle_min + inc * np.arange(len(ranges))
    ok = np.isfinite(ranges)
    return np.column_stack((ranges[ok] * np.cos(ang[ok]), ranges[ok] * np.sin(ang[ok])))
