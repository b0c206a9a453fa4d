"""Sub-pixel refinement of a plan -> map registration on the map's free-space signed distance.

The map's free space F (full resolution) gives a signed distance field ``sdf`` in metres
(positive inside free space, zero on the free/non-free pixel edges, bilinear in between). A plan
room's boundary lies a constant ``delta`` *outside* the free space it encloses: the wall's
half-thickness for plans drawn on wall centre lines (R2V), about zero for room-segmentation plans.
Boundary points ``p`` of the plan rooms (plan units) are mapped by

    q = R(theta) · diag(1, ±1) · diag(exp(lsx), exp(lsy)) · p + t        (map metres)

and the residual ``r = sdf(q + delta · n)`` vanishes when the point, moved by ``delta`` along the
room's inward normal ``n`` (rotated into the map), lands on the free-space edge *of its own room*:
the crisp side of a wall, whatever the wall's thickness or whether its other side was seen.
Parameters
``(theta, tx, ty, lsx, lsy, delta)`` are estimated by iteratively reweighted Gauss-Newton with
Levenberg damping and Cauchy weights; a point counts only when the map is free two cells further
into its room, so the unexplored rooms of the plan (and the far side of walls) do not pull. The covariance of ``(tx, ty, theta)`` is ``sigma² (JᵀWJ)⁻¹``
(scales and delta marginalised), in metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from frslam_graph.registration.result import matrix_from_params


@dataclass(frozen=True)
class DistanceField:
    """Bilinear fields over a pixel grid (row 0 = lowest y): ``sdf`` (metres) and ``known`` (0..1),
    here the free-space indicator: a point counts when the room side of it is free space."""

    sdf: np.ndarray
    known: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @classmethod
    def from_masks(cls, free: np.ndarray, resolution: float, origin) -> DistanceField:
        """Signed distance to the edge of ``free`` (bool), and ``free`` as a float field."""
        f = free.astype(np.uint8)
        d_in = cv2.distanceTransform(f, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        d_out = cv2.distanceTransform(1 - f, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        sdf = np.where(free, d_in - 0.5, 0.5 - d_out).astype(np.float32) * np.float32(resolution)
        kn = free.astype(np.float32)
        return cls(sdf, kn, float(resolution), (float(origin[0]), float(origin[1])))

    def sample(
        self, q: np.ndarray, probe: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At (N, 2) points: sdf value, its gradient (gx, gy) and the free indicator at ``probe``
        (default ``q``; bilinear; 0 outside the grid)."""
        h, w = self.sdf.shape
        u = (q[:, 0] - self.origin[0]) / self.resolution - 0.5
        v = (q[:, 1] - self.origin[1]) / self.resolution - 0.5
        inside = (u >= 0) & (v >= 0) & (u < w - 1) & (v < h - 1)
        u = np.clip(u, 0, w - 1.0001)
        v = np.clip(v, 0, h - 1.0001)
        i0 = u.astype(np.intp)
        j0 = v.astype(np.intp)
        fx = u - i0
        fy = v - j0
        flat = self.sdf.ravel()
        k = j0 * w + i0
        v00, v10, v01, v11 = flat[k], flat[k + 1], flat[k + w], flat[k + w + 1]
        val = (1 - fx) * (1 - fy) * v00 + fx * (1 - fy) * v10 + (1 - fx) * fy * v01 + fx * fy * v11
        gx = ((1 - fy) * (v10 - v00) + fy * (v11 - v01)) / self.resolution
        gy = ((1 - fx) * (v01 - v00) + fx * (v11 - v10)) / self.resolution
        if probe is not None:
            u = (probe[:, 0] - self.origin[0]) / self.resolution - 0.5
            v = (probe[:, 1] - self.origin[1]) / self.resolution - 0.5
            inside &= (u >= 0) & (v >= 0) & (u < w - 1) & (v < h - 1)
            u = np.clip(u, 0, w - 1.0001)
            v = np.clip(v, 0, h - 1.0001)
            i0 = u.astype(np.intp)
            j0 = v.astype(np.intp)
            fx = u - i0
            fy = v - j0
            k = j0 * w + i0
        kf = self.known.ravel()
        kn = (
            (1 - fx) * (1 - fy) * kf[k]
            + fx * (1 - fy) * kf[k + 1]
            + (1 - fx) * fy * kf[k + w]
            + fx * fy * kf[k + w + 1]
        )
        return val, gx, gy, kn * inside


@dataclass
class RefineResult:
    """Refined parameters and fit statistics."""

    flipped: bool
    theta: float
    tx: float
    ty: float
    sx: float
    sy: float
    delta: float
    rms: float  # weighted RMS residual (m)
    inliers: float  # share of known-area points within 2 pixels of the walls
    n_points: int
    covariance: np.ndarray | None  # (x, y, theta)
    covariance_full: np.ndarray | None  # (theta, tx, ty, lsx, lsy, delta)

    @property
    def matrix(self) -> np.ndarray:
        return matrix_from_params(self.flipped, self.theta, self.sx, self.sy, self.tx, self.ty)


def refine(
    points: np.ndarray,
    normals: np.ndarray,
    field: DistanceField,
    flipped: bool,
    theta: float,
    tx: float,
    ty: float,
    sx: float,
    sy: float,
    *,
    delta: float = 0.0,
    delta_sigma: float = 0.1,
    delta_bounds: tuple[float, float] = (-0.15, 0.4),
    scales: tuple[float, ...] = (0.4, 0.15, 0.05),
    iterations: int = 8,
) -> RefineResult:
    """Gauss-Newton/LM on boundary ``points`` (N, 2, plan units) with unit inward ``normals``
    (N, 2, plan frame); see the module docstring.

    ``scales``: Cauchy scales (metres) of successive stages, coarse to fine (the last is floored
    at two pixels). ``delta`` starts at the given value with a Gaussian prior of ``delta_sigma``.
    """
    p = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    f = -1.0 if flipped else 1.0
    x = np.array([theta, tx, ty, np.log(sx), np.log(sy), delta], dtype=np.float64)
    delta0 = float(delta)
    res = field.resolution
    lam = 1e-3
    prior_w = (0.5 * field.resolution / delta_sigma) ** 2
    probe = 2.0 * field.resolution  # the room side of a point, this far inside its free edge
    jtj = None
    stage_scales = [max(s, 2.0 * res) for s in scales]
    w_all = np.zeros(len(p))
    r = np.zeros(len(p))
    for c in stage_scales:
        for _ in range(iterations):
            th, ex, ey = x[0], np.exp(x[3]), np.exp(x[4])
            cth, sth = np.cos(th), np.sin(th)
            # plan point scaled and flipped: (ex * px, f * ey * py), then rotated
            ax = ex * p[:, 0]
            ay = f * ey * p[:, 1]
            # inward normal in the map (rotation and flip only), scaled by delta
            nx = cth * nrm[:, 0] - sth * f * nrm[:, 1]
            ny = sth * nrm[:, 0] + cth * f * nrm[:, 1]
            qx = cth * ax - sth * ay + x[1] + x[5] * nx
            qy = sth * ax + cth * ay + x[2] + x[5] * ny
            probe_d = x[5] + probe
            r, gx, gy, kn = field.sample(
                np.column_stack([qx, qy]),
                np.column_stack([qx - x[5] * nx + probe_d * nx, qy - x[5] * ny + probe_d * ny]),
            )
            w_all = kn / (1.0 + (r / c) ** 2)
            # d q / d theta = J90 (q - t)
            dth = gx * -(qy - x[2]) + gy * (qx - x[1])
            dsx = gx * (cth * ax) + gy * (sth * ax)
            dsy = gx * (-sth * ay) + gy * (cth * ay)
            jac = np.column_stack([dth, gx, gy, dsx, dsy, gx * nx + gy * ny])
            jw = jac * w_all[:, None]
            jtj = jac.T @ jw
            jtr = jw.T @ r
            # Gaussian prior on delta, relative to a residual noise of half a pixel
            jtj[5, 5] += prior_w
            jtr[5] += prior_w * (x[5] - delta0)
            if not np.all(np.isfinite(jtj)) or w_all.sum() < 6:
                break
            a = jtj + lam * np.diag(np.diag(jtj) + 1e-9)
            try:
                step = -np.linalg.solve(a, jtr)
            except np.linalg.LinAlgError:
                break
            x = x + step
            x[5] = float(np.clip(x[5], *delta_bounds))
            if abs(step[0]) < 1e-6 and np.all(np.abs(step[1:3]) < 1e-5) and np.all(np.abs(step[3:5]) < 1e-6):
                break
    wsum = float(w_all.sum())
    n_known = int((w_all > 0).sum())
    rms = float(np.sqrt((w_all * r * r).sum() / wsum)) if wsum > 0 else float("inf")
    known_pts = w_all > 0
    inl = float((np.abs(r[known_pts]) < 2.0 * res).mean()) if known_pts.any() else 0.0
    cov3 = covf = None
    if jtj is not None and n_known > 6:
        try:
            sigma2 = float((w_all * r * r).sum() / max(wsum - 6.0, 1.0))
            # points are correlated along a wall (spacing ~1.5 px); inflate accordingly
            covf = np.linalg.inv(jtj) * sigma2 * 2.0
            idx = [1, 2, 0]
            cov3 = covf[np.ix_(idx, idx)]
        except np.linalg.LinAlgError:
            cov3 = covf = None
    return RefineResult(
        flipped=flipped,
        theta=float(x[0]),
        tx=float(x[1]),
        ty=float(x[2]),
        sx=float(np.exp(x[3])),
        sy=float(np.exp(x[4])),
        delta=float(x[5]),
        rms=rms,
        inliers=inl,
        n_points=n_known,
        covariance=cov3,
        covariance_full=covf,
    )


def sample_boundaries(
    rings: list[np.ndarray], step: float, doors: np.ndarray | None = None, door_tol: float = 0.0
):
    """Points every ``step`` (plan units) along closed rings, minus those on door segments.

    Rings must have their room on the left (exterior counter-clockwise, holes clockwise).
    ``doors``: (D, 4) segments x1 y1 x2 y2; points within ``door_tol`` of a door are dropped.
    Returns (N, 2) points, (N, 2) unit inward normals and (N,) ring indices.
    """
    pts, nrms, owner = [], [], []
    for k, ring in enumerate(rings):
        a = np.asarray(ring, dtype=np.float64)
        b = np.roll(a, -1, axis=0)
        seg = b - a
        length = np.hypot(seg[:, 0], seg[:, 1])
        count = np.maximum(1, np.ceil(length / step).astype(int))
        total = int(count.sum())
        if total == 0:
            continue
        e = np.repeat(np.arange(len(a)), count)
        start = np.repeat(np.cumsum(count) - count, count)
        t = (np.arange(total) - start + 0.5) / count[e]
        pts.append(a[e] + seg[e] * t[:, None])
        unit = seg / np.maximum(length, 1e-300)[:, None]
        nrms.append(np.column_stack([-unit[e, 1], unit[e, 0]]))
        owner.append(np.full(total, k))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)
    p = np.concatenate(pts)
    nr = np.concatenate(nrms)
    o = np.concatenate(owner)
    if doors is not None and len(doors) and door_tol > 0:
        keep = np.ones(len(p), bool)
        for x1, y1, x2, y2 in np.asarray(doors, dtype=np.float64):
            d = np.array([x2 - x1, y2 - y1])
            L2 = float(d @ d)
            if L2 <= 0:
                continue
            rel = p - (x1, y1)
            t = np.clip(rel @ d / L2, 0.0, 1.0)
            dist = np.hypot(rel[:, 0] - t * d[0], rel[:, 1] - t * d[1])
            keep &= dist > door_tol
        p, nr, o = p[keep], nr[keep], o[keep]
    return p, nr, o
